"""Stability on hard cases, robustness to bad input, and to interruption.

Short horizons throughout (CI); `lgnn stability` runs the same cases for 10 s and
writes results/stability.md.
"""

import csv
import dataclasses
import json
import math
import os
import random
import signal
import struct
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from lgnn.learn import data, models, protocol, train
from lgnn.learn.checkpoints import load_model
from lgnn import physics, records
from lgnn.bench import stability
from lgnn.engines.base import Trajectory
from lgnn.cli import main
from lgnn.errors import SceneError, SimulationError
from lgnn.scene import scene_from_dict, scene_to_dict
from lgnn.scene import get_scene, taut_chain
from lgnn.engines.base import Integration, SimulationConfig
from lgnn.engines.lagrangian import rollout_fn, simulate
from lgnn.metrics import EXPLOSION_FACTOR, ExplosionBounds

ROOT = Path(__file__).resolve().parents[1]


def case(name, scene, engine="lagrangian", kind="rollout", **changes):
    """The declared case (stability.cases) with shorter settings."""
    found = [c for c in stability.cases() if (c.name, c.scene, c.engine, c.kind) == (name, scene, engine, kind)]
    assert found, (name, scene, engine, kind)
    return dataclasses.replace(found[0], **changes)


def run_cli(capsys, *argv):
    try:
        code = main([str(a) for a in argv])
    except SystemExit as exit_:
        code = exit_.code
    out, err = capsys.readouterr()
    return code, out, err


def one_error_line(err: str, *words: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("lgnn: error: "), err
    for word in words:
        assert word in lines[0], lines[0]
    return lines[0]


# ---------------------------------------------------------------------------------
# Failure detection: non-finite and exploding states stop a run and say when
# ---------------------------------------------------------------------------------


def test_explosion_bounds_flag_exploding_but_finite_frames_only():
    scene = get_scene("chain4")
    q0, qd0 = scene.nodes, scene.velocities
    energy0 = float(physics.energy_fn(scene)(jnp.asarray(q0), jnp.asarray(qd0)))
    bounds = ExplosionBounds.of(scene, scene.initial_state, energy0)
    t = np.array([0.1, 0.2, 0.3, 0.4])
    q, qd = np.stack([q0] * 4), np.stack([qd0] * 4)
    energy = np.full(4, energy0)
    assert bounds.first_violation(t, q, qd, energy) is None
    energy[2] = energy0 + 2 * EXPLOSION_FACTOR * bounds.energy_scale  # finite, but impossible
    assert bounds.first_violation(t, q, qd, energy)[0] == 2
    energy[2] = energy0
    q = q.copy()
    q[1, 3] += 3 * EXPLOSION_FACTOR * bounds.size
    k, reason = bounds.first_violation(t, q, qd, energy)
    assert k == 1 and "moved" in reason
    qd = qd.copy()
    qd[0, 2, 0] = np.nan
    assert bounds.first_violation(t, q, qd, energy) == (0, "became non-finite")


def test_free_fall_is_not_an_explosion():
    """An unpinned body falls without bound: its energy is conserved and its drop is
    within the free-fall allowance, so 3 s of falling is a correct run."""
    scene = scene_from_dict({"name": "stick", "nodes": [[0, 0], [1, 0]], "pinned": [], "links": [{"nodes": [0, 1], "mass": 1, "inertia": 0.1}]})
    trajectory = simulate(scene, SimulationConfig(dt=1e-2, frame_dt=1e-1, duration=3.0))
    np.testing.assert_allclose(trajectory.q[-1, :, 1], -0.5 * 10 * 3.0**2, rtol=1e-9)


def test_diverging_large_step_stops_at_the_first_bad_frame():
    """Verlet at dt 1e-2 without projection diverges on chain4 (measured: 7.5 s); the
    run stops there with the time, the frames before it, and no NaN among them."""
    row = stability.run_case(case("large-step-noproj", "chain4", integrator="verlet", dt=1e-2))
    assert row["status"] == "detected", row
    assert 0 < row["time_to_failure"] < 10 and f"t = {row['time_to_failure']:g} s" in row["message"]
    with pytest.raises(SimulationError) as info:
        simulate(get_scene("chain4"), SimulationConfig(1e-2, 1e-2, 10.0), integration=Integration("verlet", project=False))
    err = info.value
    assert err.time == row["time_to_failure"]  # exact: a frame's time, its index times frame_dt
    partial = err.trajectory
    assert len(partial.t) == round(err.time / 1e-2) and np.isfinite(partial.q).all() and np.isfinite(partial.energy).all()


def test_large_steps_with_projection_stay_on_the_constraints():
    row = stability.run_case(case("large-step", "chain16", integrator="verlet", dt=1e-2, duration=2.0))
    assert row["status"] == "ok" and row["max_constraint_violation"] < 1e-9 and row["energy_drift"] < 5e-2, row


def test_mujoco_instability_is_detected_not_reset(tmp_path, monkeypatch):
    """MuJoCo C resets an unstable state to the rest pose and carries on; T3 at dt 1e-2
    then looked perfectly at rest. It must be an error naming the time instead, without
    MuJoCo's own printout and MUJOCO_LOG.TXT in the working directory."""
    monkeypatch.chdir(tmp_path)
    row = stability.run_case(stability.Case("large-step", "T3", "mujoco", dt=1e-2, frame_dt=1e-2, duration=0.3))
    assert row["status"] == "detected" and "MuJoCo" in row["message"] and 0 < row["time_to_failure"] <= 0.3, row
    assert not list(tmp_path.iterdir())


def test_bad_learned_model_stops_through_lgnn_rollout(tmp_path, capsys):
    ckpt = stability.bad_model_checkpoint(tmp_path / "bad.npz", get_scene("chain4"), stability.BAD_MODEL_SCALE)
    out = tmp_path / "roll.npz"
    code, _, err = run_cli(capsys, "rollout", "chain4", "--model", ckpt, "--dt", "1e-3", "--frame-dt", "1e-2", "--duration", "2", "--out", out, "--quiet")
    assert code == 3  # diverged (not bad input): the frames before it are kept, flagged
    line = one_error_line(err, "exploded", "gns")
    time_of_failure = float(line.split("t = ")[1].split(" s")[0])
    assert 0 < time_of_failure < 2
    kept = Trajectory.load(out)
    assert kept.metadata["diverged"]["time"] == pytest.approx(time_of_failure) and kept.t[-1] < time_of_failure
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.npz", "roll.npz"]


# ---------------------------------------------------------------------------------
# Near-singular geometry and redundant constraints: accelerations unique and correct
# ---------------------------------------------------------------------------------


@pytest.mark.parametrize("scene", ["taut4-0.999", "taut4-exact", "folded4", "pinned-triangle", "T3"])
def test_hard_accelerations_are_unique_and_keep_every_constraint(scene):
    name = "redundant" if scene in ("pinned-triangle", "T3") else "near-singular"
    row = stability.run_case(case(name, scene, kind="acceleration"))
    assert row["status"] == "ok", row
    assert row["accel_error"] <= 1e-8 and row["max_constraint_violation"] <= 1e-6
    if scene == "pinned-triangle":
        # At rest to the round-off of g = 10 (the Schur solve of the ground truth gives
        # ~4e-16; the generic KKT solve happens to give exactly zero, checked below).
        assert row["accel_error"] <= 1e-14
        triangle = get_scene(scene)
        generic = physics.true_acceleration_fn(triangle, "generic")(jnp.asarray(triangle.nodes), jnp.asarray(triangle.velocities))
        assert np.abs(np.asarray(generic)).max() < 1e-30


def test_exactly_taut_rope_is_a_rank_deficient_jacobian():
    scene = taut_chain(4, 1.0)
    constraints = physics.Constraints(scene)
    assert constraints.self_stresses == 1
    assert physics.Constraints(taut_chain(4, 0.999)).self_stresses == 0


def test_folded_chain_unfolds_conserving_energy():
    row = stability.run_case(case("near-singular", "folded4", dt=1e-3, duration=0.2))
    assert row["status"] == "ok" and row["energy_drift"] < 1e-8 and row["max_constraint_violation"] < 1e-12, row


# ---------------------------------------------------------------------------------
# The report command
# ---------------------------------------------------------------------------------


def test_stability_report_command(tmp_path, capsys):
    out = tmp_path / "stability.md"
    code, stdout, _ = run_cli(capsys, "stability", "--case", "redundant", "--singular-horizon", "0.05", "--cost-sizes", "4", "16", "--out", out, "--quiet")
    assert code == 0 and "wrote" in stdout
    text = out.read_text()
    for word in ("command: lgnn", "--case redundant", "commit:", "machine:", "versions:", "jax", "seed: 0", "n^"):
        assert word in text, word
    lines = out.with_suffix(".csv").read_text().splitlines()
    rows = list(csv.DictReader(line for line in lines if not line.startswith("#")))
    assert [r["case"] for r in rows] == ["redundant"] * 3 + ["cost-per-step"] * 2
    assert all(r["status"] == "ok" for r in rows)
    assert float(rows[-1]["step_s"]) > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["stability.csv", "stability.md"]


# ---------------------------------------------------------------------------------
# Bad input: one line `lgnn: error: ...`, exit 2, no file
# ---------------------------------------------------------------------------------

BAD_SCENE_FILES = {
    "malformed.json": ('{"name": "x", ', "not valid JSON"),
    "notjson.json": ("hello", "not valid JSON"),
    "empty.json": ("", "not valid JSON"),
    "nan.json": ('{"name": "x", "nodes": [[0, 0], [0, NaN]], "pinned": [0], "links": [{"nodes": [0, 1], "mass": 1, "inertia": 0.1}]}', "NaN is not a JSON number"),
    "inf.json": ('{"name": "x", "nodes": [[0, 0], [0, -1e999]], "pinned": [0], "links": [{"nodes": [0, 1], "mass": 1, "inertia": 0.1}]}', "must be finite"),
    "huge.json": ('{"name": "x", "nodes": [[0, 0], [0, -1e300]], "pinned": [0], "links": [{"nodes": [0, 1], "mass": 1, "inertia": 0.1}]}', "overflow"),
    "list.json": ("[1, 2]", "JSON object"),
}


@pytest.mark.parametrize("name", list(BAD_SCENE_FILES))
def test_bad_scene_files_through_the_cli(tmp_path, capsys, name):
    content, words = BAD_SCENE_FILES[name]
    (tmp_path / name).write_text(content)
    code, _, err = run_cli(capsys, "simulate", tmp_path / name, "--out", tmp_path / "x.npz", "--quiet")
    assert code == 2
    one_error_line(err, words, name)
    assert not (tmp_path / "x.npz").exists()


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["simulate", "{tmp}/absent.json"], "no such scene file"),
        (["simulate", "chain4", "--dt=-1e-3"], "--dt: must be a positive number"),
        (["simulate", "chain4", "--duration", "0"], "--duration: must be a positive number"),
        (["simulate", "chain4", "--dt", "1e-3", "--frame-dt", "1.5e-3"], "not a whole multiple of dt"),
        (["simulate", "chain4", "--integrator", "euler"], "invalid choice: 'euler'"),
        (["simulate", "chain4", "--engine", "bullet"], "invalid choice: 'bullet'"),
        (["train", "--model", "foo", "--scene", "chain4"], "invalid choice: 'foo'"),
        (["train", "--model", "lgnn", "--scene", "chain5"], "unknown scene 'chain5'"),
        (["rollout", "chain5", "--model", "{tmp}/ok.npz"], "unknown scene 'chain5'"),
        (["frobnicate"], "invalid choice: 'frobnicate'"),
        (["stability", "--case", "nope"], "invalid choice: 'nope'"),
    ],
)
def test_bad_names_and_numbers_are_one_line(tmp_path, capsys, argv, words):
    ckpt = tmp_path / "ok.npz"
    model = models.ModelConfig("lgnn")
    train.save_checkpoint(ckpt, train.initial_state(model, protocol.TrainConfig()), model, protocol.TrainConfig())
    argv = [a.format(tmp=tmp_path) for a in argv]
    if argv[0] != "frobnicate":
        argv += ["--out", str(tmp_path / ("x.md" if argv[0] == "stability" else "x.npz"))]
    code, _, err = run_cli(capsys, *argv)
    assert code == 2
    one_error_line(err, words)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ok.npz"]


@pytest.mark.parametrize(("out", "words"), [("{tmp}/missing/x.npz", "does not exist"), ("/proc/x.npz", "cannot write"), ("{tmp}", "is a directory")])
def test_unwritable_outputs(tmp_path, capsys, out, words):
    code, _, err = run_cli(capsys, "simulate", "chain4", "--dt", "1e-3", "--duration", "0.01", "--out", out.format(tmp=tmp_path), "--quiet")
    assert code == 2
    one_error_line(err, words)


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    """A valid LGNN checkpoint and broken variants of it."""
    tmp = tmp_path_factory.mktemp("ckpt")
    model, config = models.ModelConfig("lgnn"), protocol.TrainConfig()
    good = tmp / "good.npz"
    train.save_checkpoint(good, train.initial_state(model, config), model, config)
    raw = good.read_bytes()
    (tmp / "truncated.npz").write_bytes(raw[: len(raw) // 2])
    # A byte flipped in the middle of the (deflated) parameters (the middle of the file
    # may be a redundant zip size field that readers ignore, where a flip changes nothing).
    with zipfile.ZipFile(good) as archive:
        weights = max((info for info in archive.infolist() if info.filename.startswith("params/")), key=lambda info: info.compress_size)
    name_length, extra_length = struct.unpack("<HH", raw[weights.header_offset + 26 : weights.header_offset + 30])
    flipped = bytearray(raw)
    flipped[weights.header_offset + 30 + name_length + extra_length + weights.compress_size // 2] ^= 0xFF
    (tmp / "corrupted.npz").write_bytes(bytes(flipped))
    (tmp / "text.npz").write_text("not a checkpoint\n")
    with np.load(good) as stored:
        arrays = dict(stored)
    meta = json.loads(str(arrays["meta"]))
    meta["format"] = train.CHECKPOINT_FORMAT + 1
    arrays["meta"] = json.dumps(meta, sort_keys=True)
    arrays["checksum"] = records.checksum({k: v for k, v in arrays.items() if k not in ("meta", "checksum")}, arrays["meta"])
    np.savez(tmp / "future.npz", **arrays)
    trajectory = simulate(get_scene("chain4"), SimulationConfig(dt=1e-3, frame_dt=1e-2, duration=0.02))
    trajectory.save(tmp / "trajectory.npz")  # a valid .npz, but no checkpoint
    gns = models.ModelConfig.for_scene("gns", get_scene("chain4"))
    train.save_checkpoint(tmp / "gns.npz", train.initial_state(gns, config), gns, config)
    clnn = models.ModelConfig.for_scene("clnn", get_scene("chain4"))
    train.save_checkpoint(tmp / "clnn.npz", train.initial_state(clnn, config), clnn, config)
    return tmp


@pytest.mark.parametrize(
    ("name", "scene", "words"),
    [
        ("absent.npz", "chain4", "no such checkpoint"),
        ("truncated.npz", "chain4", "not a readable lgnn checkpoint"),
        ("corrupted.npz", "chain4", "checkpoint"),
        ("text.npz", "chain4", "not a readable lgnn checkpoint"),
        ("future.npz", "chain4", "checkpoint format 3, expected 2"),
        ("trajectory.npz", "chain4", "not a readable lgnn checkpoint"),
        ("clnn.npz", "chain8", "tied to its training system size"),
    ],
)
def test_bad_checkpoints_for_rollout(checkpoints, tmp_path, capsys, name, scene, words):
    code, _, err = run_cli(capsys, "rollout", scene, "--model", checkpoints / name, "--dt", "1e-3", "--duration", "0.01", "--out", tmp_path / "x.npz", "--quiet")
    assert code == 2
    one_error_line(err, words)
    assert not list(tmp_path.iterdir())


def test_resume_from_another_models_checkpoint_fails_before_any_work(checkpoints, tmp_path, capsys):
    ckpt = tmp_path / "ckpt.npz"
    ckpt.write_bytes((checkpoints / "gns.npz").read_bytes())
    start = time.perf_counter()
    code, _, err = run_cli(capsys, "train", "--model", "lgnn", "--resume", "--trajectories", "2", "--cache-dir", tmp_path / "cache", "--out", ckpt, "--quiet")
    assert code == 2
    one_error_line(err, "cannot resume", "model.name: checkpoint 'gns', now 'lgnn'")
    assert not (tmp_path / "cache").exists() and time.perf_counter() - start < 10  # no data generated
    assert ckpt.read_bytes() == (checkpoints / "gns.npz").read_bytes()


def test_truncated_dataset_cache_is_regenerated(tmp_path, capsys):
    config = data.DataConfig(n_trajectories=2, duration=0.04, sample_dt=0.01, dt=1e-3)
    first = data.load_or_generate(config, tmp_path)
    path = data.cache_path(config, tmp_path)
    path.write_bytes(path.read_bytes()[:500])
    again = data.load_or_generate(config, tmp_path)
    assert "not a readable lgnn data cache" in capsys.readouterr().err
    np.testing.assert_array_equal(again.q, first.q)
    data.load(config, path)


# ---------------------------------------------------------------------------------
# Property-based: the scene loader
# ---------------------------------------------------------------------------------

finite = st.floats(-10, 10, allow_nan=False, allow_infinity=False)
positive = st.floats(0.1, 10, allow_nan=False, allow_infinity=False)


@st.composite
def scene_dicts(draw, min_links=1, max_links=6):
    """A valid scene: a chain of random links from a random start, random pins, random
    optional fields (velocities at rest; lengths given or defaulted)."""
    n = draw(st.integers(min_links, max_links))
    start = [draw(finite), draw(finite)]
    angles = draw(st.lists(st.floats(-math.pi, math.pi, allow_nan=False), min_size=n, max_size=n))
    lengths = draw(st.lists(st.floats(0.2, 3.0, allow_nan=False), min_size=n, max_size=n))
    nodes = [start]
    for angle, length in zip(angles, lengths):
        x, y = nodes[-1]
        nodes.append([x + length * math.cos(angle), y + length * math.sin(angle)])
    pinned = sorted(draw(st.sets(st.integers(0, n), max_size=n)))
    links = []
    for k in range(n):
        link = {"nodes": [k, k + 1], "mass": draw(positive), "inertia": draw(st.floats(0, 1, allow_nan=False))}
        if draw(st.booleans()):
            link["length"] = math.dist(nodes[k], nodes[k + 1])
        if draw(st.booleans()):
            link["type"] = draw(st.sampled_from(["link", "rod", "rope"]))
        links.append(link)
    # A valid name is printable text (an unprintable one is refused: tests/test_inputs.py).
    name = draw(st.text(min_size=1, max_size=8).filter(lambda text: text.strip() and text.isprintable()))
    scene = {"name": name, "nodes": nodes, "pinned": pinned, "links": links}
    if draw(st.booleans()):
        scene["gravity"] = draw(finite)
    if draw(st.booleans()):
        scene["drag"] = draw(st.floats(0, 1, allow_nan=False))
    if draw(st.booleans()):
        scene["velocities"] = [[0.0, 0.0] for _ in nodes]
    return scene


@settings(max_examples=40, deadline=None)
@given(scene_dicts())
def test_random_valid_scenes_load_and_round_trip_exactly(data_):
    scene = scene_from_dict(data_)
    again = scene_from_dict(json.loads(json.dumps(scene_to_dict(scene))))
    assert scene_to_dict(again) == scene_to_dict(scene)
    for field in ("nodes", "velocities", "lengths", "masses", "inertias", "gravity"):
        np.testing.assert_array_equal(getattr(again, field), getattr(scene, field))


INVALID = [
    ("mass zero", lambda d, k: d["links"][k].__setitem__("mass", 0.0)),
    ("mass NaN", lambda d, k: d["links"][k].__setitem__("mass", float("nan"))),
    ("inertia negative", lambda d, k: d["links"][k].__setitem__("inertia", -0.5)),
    ("length wrong", lambda d, k: d["links"][k].__setitem__("length", math.dist(*(d["nodes"][i] for i in d["links"][k]["nodes"])) * 1.1)),
    ("node index out of range", lambda d, k: d["links"][k].__setitem__("nodes", [k, len(d["nodes"])])),
    ("self link", lambda d, k: d["links"][k].__setitem__("nodes", [k, k])),
    ("duplicate link", lambda d, k: d["links"].append(dict(d["links"][k]))),
    ("unknown key", lambda d, k: d.__setitem__("colour", "red")),
    ("unknown link key", lambda d, k: d["links"][k].__setitem__("colour", "red")),
    ("node as string", lambda d, k: d["nodes"].__setitem__(k, "here")),
    ("coordinate inf", lambda d, k: d["nodes"][k].__setitem__(0, float("inf"))),
    ("coordinate huge", lambda d, k: d["nodes"][k].__setitem__(0, 1e300)),
    ("pin twice", lambda d, k: d.__setitem__("pinned", [k, k])),
    ("no links", lambda d, k: d.__setitem__("links", [])),
    ("missing name", lambda d, k: d.pop("name")),
    ("bool mass", lambda d, k: d["links"][k].__setitem__("mass", True)),
    ("negative drag", lambda d, k: d.__setitem__("drag", -1.0)),
]


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scene_dicts(), st.sampled_from(INVALID), st.integers(0, 100))
def test_random_invalid_scenes_raise_scene_error(data_, mutation, index):
    _, mutate = mutation
    mutate(data_, index % len(data_["links"]))
    with pytest.raises(SceneError) as info:
        scene_from_dict(data_)
    assert "\n" not in str(info.value)


# ---------------------------------------------------------------------------------
# Property-based: physics on random small scenes
# ---------------------------------------------------------------------------------

PHYSICS_CONFIG = SimulationConfig(dt=1e-3, frame_dt=1e-2, duration=0.05)


@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scene_dicts(min_links=2, max_links=5))
def test_random_scenes_accelerate_finitely_keep_constraints_and_conserve_energy(data_):
    data_.update(drag=0.0, gravity=10.0, nodes=[[x, y] for x, y in data_["nodes"]])
    data_.pop("velocities", None)
    data_["pinned"] = sorted(set(data_["pinned"]) | {0})  # something holds it: no free fall for 0.05 s
    scene = scene_from_dict(data_)
    # A link run pulled straight between two pins is self-stressed: its constraint
    # Jacobian loses rank and holds only to the regularisation's 1e-6 (the hard cases
    # above test those scenes with their own tolerances).
    assume(physics.prepare(scene).constraints.self_stresses == 0)

    @jax.jit
    def run(q, qd):
        qdd = physics.true_acceleration_fn(scene)(q, qd)
        frames = rollout_fn(scene, PHYSICS_CONFIG)(q, qd)
        return qdd, frames, jax.vmap(physics.energy_fn(scene))(frames.q, frames.qd), jax.vmap(lambda x: physics.constraint_violation(scene, x))(frames.q)

    qdd, frames, energy, violation = run(jnp.asarray(scene.nodes), jnp.asarray(scene.velocities))
    assert np.isfinite(qdd).all() and np.isfinite(frames.q).all()
    assert float(jnp.max(violation)) < 1e-10
    scale = ExplosionBounds.of(scene, scene.initial_state, float(energy[0])).energy_scale
    assert float(jnp.max(jnp.abs(energy - energy[0]))) < 1e-6 * scale


# ---------------------------------------------------------------------------------
# Interruption: kill `lgnn train` mid-run, resume, end with a valid checkpoint
# ---------------------------------------------------------------------------------


def test_killed_training_resumes_from_its_last_checkpoint(tmp_path):
    cache, ckpt = tmp_path / "cache", tmp_path / "ckpt.npz"
    # The CLI's data settings for `--trajectories 2`, filled with a short dataset (its
    # default 1 s trajectories take a minute to make).
    tiny = data.load_or_generate(data.DataConfig(n_trajectories=2, duration=0.2, sample_dt=0.01, dt=1e-3), None)
    cli_data = data.DataConfig("chain4", n_trajectories=2)
    cache.mkdir()
    data.save(tiny, cli_data, data.cache_path(cli_data, cache))
    epochs = 3000
    # GNS: the kill and the resume are the point, not the model, and its training
    # compiles quickest; the resumed process reads the first one's compiled programs
    # from JAX's persistent cache instead of compiling them again.
    argv = [sys.executable, "-m", "lgnn", "train", "--model", "gns", "--trajectories", "2", "--epochs", str(epochs),
            "--patience", str(epochs), "--lr", "1e-2", "--batch-size", "10", "--cache-dir", str(cache), "--out", str(ckpt), "--quiet"]
    env = {**os.environ, "PYTHONPATH": str(ROOT), "JAX_COMPILATION_CACHE_DIR": str(tmp_path / "jax-cache")}
    process = subprocess.Popen(argv, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 90
        while not ckpt.exists():
            assert process.poll() is None, process.communicate()
            assert time.monotonic() < deadline, "no checkpoint after 90 s"
            time.sleep(0.05)
        delay = random.Random(os.getpid()).uniform(0.0, 1.5)
        time.sleep(delay)
        assert process.poll() is None, f"finished before the kill ({delay:.2f} s after the first checkpoint)"
        process.send_signal(signal.SIGKILL)
    finally:
        process.kill()
        process.communicate()
    killed, meta = train.load_checkpoint(ckpt)  # the last checkpoint is whole, never half-written
    assert 1 <= killed.epoch < epochs
    # Mark the checkpoint so the resumed run provably starts from it (a fresh start
    # would recompute the same losses): its first history entry carries a sentinel.
    marked = killed._replace(history=[(1, -1.0, killed.history[0][2])] + killed.history[1:])
    model = models.ModelConfig.from_dict(meta["model"])
    train.save_checkpoint(ckpt, marked, model, protocol.TrainConfig(**meta["train_config"]), data.DataConfig(**meta["data"]))
    short = [a if a != str(epochs) else str(killed.epoch + 5) for a in argv] + ["--resume"]
    finished = subprocess.run(short, cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert finished.returncode == 0, finished.stderr
    resumed, _ = train.load_checkpoint(ckpt)
    assert resumed.epoch == killed.epoch + 5 and len(resumed.history) == resumed.epoch
    assert resumed.history[0][1] == -1.0 and resumed.history[1 : killed.epoch] == killed.history[1:]
    load_model(ckpt)


def test_killed_benchmark_keeps_its_finished_records_and_resumes(tmp_path):
    """`lgnn benchmark` killed at a random moment after its first record: the restarted
    run reuses every record that was finished (not rewritten) and completes the rest."""
    from lgnn.bench import grid, profiles
    from lgnn.bench.stages import evaluate
    from lgnn.bench.store import Layout

    out = tmp_path / "out"
    profile, pair = profiles.PROFILES["quick"], grid.Pair(grid.TrainingJob("gns", grid.TRAINING_SCENE, 0), grid.TRAINING_SCENE)
    layout = Layout(out)
    layout.checkpoint(pair.job).parent.mkdir(parents=True)
    # Evaluation needs only a checkpoint file: the committed full-profile one will do.
    layout.checkpoint(pair.job).write_bytes((ROOT / "results/benchmark/checkpoints/gns-chain4-s0.npz").read_bytes())
    argv = [sys.executable, "-m", "lgnn", "benchmark", "--stage", "evaluate", "--scene", "chain4", "--job", pair.job.name,
            "--out-dir", str(out), "--quiet"]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    truth = layout.truth_record("chain4")
    process = subprocess.Popen(argv, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 300
        while not truth.exists() and process.poll() is None:
            assert time.monotonic() < deadline, "no ground-truth record after 300 s"
            time.sleep(0.02)
        time.sleep(random.Random(os.getpid()).uniform(0.0, 1.0))
        process.send_signal(signal.SIGKILL)
    finally:
        process.kill()
        process.communicate()
    finished_before = {path: path.stat().st_mtime_ns for path in (truth, layout.pair_record(pair)) if path.exists()}
    assert truth in finished_before, "the first record was written before the kill"
    restarted = subprocess.run(argv, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert restarted.returncode == 0, restarted.stderr
    for path, mtime in finished_before.items():
        assert path.stat().st_mtime_ns == mtime, f"{path.name} was recomputed instead of reused"
    assert evaluate.load_truth(profile, "chain4", out) is not None
    assert evaluate.load_pair(profile, pair, out) is not None
