"""The command line: outputs, and one clear line for every bad input."""

import argparse
import dataclasses
import json
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from lgnn.cli import main
from lgnn.errors import ConfigError
from lgnn.scene import CATALOGUE
from lgnn.engines.base import Trajectory


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_scenes_lists_every_builtin(capsys):
    code, out, _ = run(capsys, "scenes")
    assert code == 0
    for name in CATALOGUE:
        assert name in out


def test_closed_output_pipe_is_quiet():
    """`lgnn scenes | head -0`: the reader is gone before lgnn writes; no traceback."""
    import os
    import subprocess
    import sys

    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        result = subprocess.run([sys.executable, "-m", "lgnn", "scenes"], stdout=write_end, stderr=subprocess.PIPE, timeout=120)
    finally:
        os.close(write_end)
    stderr = result.stderr.decode()
    assert result.returncode == 141 and "Traceback" not in stderr, stderr


def test_scene_export_round_trips_through_simulate(capsys, tmp_path):
    path = tmp_path / "chain4.json"
    code, _, _ = run(capsys, "scene", "export", "chain4", "--out", str(path))
    assert code == 0
    assert json.loads(path.read_text())["name"] == "chain4"
    out = tmp_path / "traj.npz"
    code, stdout, _ = run(capsys, "simulate", str(path), "--duration", "0.05", "--dt", "1e-3", "--frame-dt", "1e-2", "--out", str(out), "--quiet")
    assert code == 0 and "wrote" in stdout
    trajectory = Trajectory.load(out)
    assert trajectory.t.shape == (6,) and trajectory.q.shape == (6, 5, 2) and trajectory.qd.shape == (6, 5, 2)
    assert trajectory.energy.shape == (6,)
    np.testing.assert_allclose(trajectory.t, np.arange(6) * 1e-2)
    with np.load(out) as data:
        assert {"t", "q", "qd", "energy"} <= set(data.files)


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["simulate", "chain5", "--out", "{tmp}/x.npz"], "unknown scene 'chain5'"),
        (["simulate", "chain4", "--dt", "3e-4", "--out", "{tmp}/x.npz"], "not a whole multiple of dt"),
        (["simulate", "chain4", "--duration", "0.0015", "--out", "{tmp}/x.npz"], "duration"),
        (["simulate", "chain4", "--out", "{tmp}/missing/x.npz"], "output directory does not exist"),
        (["simulate", "chain4", "--out", "{tmp}"], "is a directory"),
        (["simulate", "{tmp}/nope.json", "--out", "{tmp}/x.npz"], "no such scene file"),
        (["scene", "export", "nope"], "unknown built-in scene"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(capsys, tmp_path, argv, words):
    code, _, err = run(capsys, *[a.format(tmp=tmp_path) for a in argv])
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("lgnn: error:") and words in lines[0], err
    assert not (tmp_path / "x.npz").exists()


@pytest.mark.parametrize("value", ["-1", "0", "nan", "abc"])
def test_invalid_numbers_are_rejected_by_the_parser(capsys, value):
    with pytest.raises(SystemExit) as info:
        main(["simulate", "chain4", "--dt", value, "--out", "x.npz"])
    assert info.value.code == 2
    assert "--dt" in capsys.readouterr().err


def test_diverged_simulation_keeps_its_frames_flagged_and_exits_3(capsys, tmp_path):
    """A diverging run (chain16, RK4 at 0.1 s, no projection) reports when it diverged,
    keeps the frames before it (flagged in the metadata) and exits 3, not 2 (bad input)."""
    out = tmp_path / "x.npz"
    code, _, err = run(capsys, "simulate", "chain16", "--dt", "0.1", "--frame-dt", "0.1", "--duration", "20", "--no-project", "--out", str(out), "--quiet")
    assert code == 3 and "exploded" in err and "t = 0.4 s" in err and "kept the 4 frames" in err, err
    kept = Trajectory.load(out)
    assert kept.q.shape == (4, 17, 2) and np.isfinite(kept.q).all()
    np.testing.assert_allclose(kept.t, [0.0, 0.1, 0.2, 0.3])
    assert kept.metadata["diverged"]["time"] == pytest.approx(0.4)


@pytest.mark.parametrize("mass", [1e12, 1e30])
def test_a_mujoco_run_flagged_unstable_keeps_the_frames_before_it(capsys, tmp_path, mass):
    """MuJoCo C resets a state it finds unstable (here a 3D net with one link of mass
    1e12, or 1e30, the largest a scene may hold, whose energies pass 1e30): the run exits
    3 in one line and keeps MuJoCo's own frames before the instability, flagged, in a
    file that loads, as the Lagrangian engine keeps its frames before a divergence."""
    import json

    from lgnn.engines import mujoco as lm
    from lgnn.engines.base import SimulationConfig
    from lgnn.scene import get_scene, scene_from_dict, scene_to_dict

    described = scene_to_dict(get_scene("net4x4-3d"))
    described["links"][0]["mass"] = mass
    (tmp_path / "heavy.json").write_text(json.dumps(described))
    out = tmp_path / "heavy.npz"
    code, _, err = run(capsys, "simulate", str(tmp_path / "heavy.json"), "--engine", "mujoco", "--duration", "0.2", "--out", str(out), "--quiet")
    assert code == 3 and len(err.strip().splitlines()) == 1 and "MuJoCo found a non-finite or huge qacc" in err and "kept the" in err, err
    kept = Trajectory.load(out)
    assert 1 < len(kept.t) and kept.t[-1] < kept.metadata["diverged"]["time"] and np.isfinite(kept.q).all()
    settings = kept.metadata["config"]
    config = SimulationConfig(dt=settings["dt"], frame_dt=settings["frame_dt"], duration=kept.t[-1])
    # Exact: MuJoCo C's own steps (no compiled program of ours) rerun in this process.
    np.testing.assert_array_equal(kept.q, lm.rollout(scene_from_dict(described), config, form=kept.metadata["engine"]["form"]).q[0])


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["simulate", "chain4", "--dt", "-1e-4", "--out", "x.npz"], "--dt: must be a positive number, got -1e-4"),
        (["simulate", "chain4", "--dt", "1e-2", "--out", "x.npz"], "pass --frame-dt too"),
        (["simulate", "chain4", "--out", "x.csv"], "trajectories are written as .npz"),
        (["simulate", "chain4", "--engine", "bullet", "--out", "x.npz"], "choose from 'lagrangian', 'mujoco', 'mjx'"),
        (["train", "--model", "lgnn", "--epochs", "0", "--out", "x.npz"], "--epochs: must be a positive whole number"),
        (["stability", "--case", "nope"], "invalid choice: 'nope'"),
    ],
)
def test_rough_edges_are_one_clear_line(capsys, tmp_path, monkeypatch, argv, words):
    monkeypatch.chdir(tmp_path)
    try:
        code = main(argv)
    except SystemExit as exit:
        code = exit.code
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and words in err, err
    assert not list(tmp_path.iterdir())


def test_stability_help_lists_the_cases(capsys):
    from lgnn.bench.stability import cases

    with pytest.raises(SystemExit):
        main(["stability", "--help"])
    help_text = "".join(capsys.readouterr().out.split())  # argparse wraps at hyphens
    for case in cases():
        assert case.name in help_text


def test_train_refuses_to_overwrite_a_checkpoint(capsys, tmp_path):
    (tmp_path / "other.npz").write_bytes(b"another model")
    code, _, err = run(capsys, "train", "--model", "gns", "--out", str(tmp_path / "other.npz"))
    assert code == 2 and "--resume to continue" in err and "--overwrite" in err
    assert (tmp_path / "other.npz").read_bytes() == b"another model"


def test_crosscheck_of_a_scene_file_writes_beside_the_user_and_summarises(capsys, tmp_path, monkeypatch):
    """Not told where to write, a report goes to ./lgnn-out (never the repository's
    results/), the console shows each engine's lines for a scene file too (they are
    filtered on the scene's name, not the path) and says where it wrote; a `|` inside a
    markdown cell is escaped, so every table row keeps its columns."""
    import re

    from lgnn.scene import get_scene, scene_to_json

    monkeypatch.chdir(tmp_path)
    scene_file = tmp_path / "mine.json"
    scene_file.write_text(scene_to_json(get_scene("chain4")).replace('"chain4"', '"mine"'))
    code, out, err = run(capsys, "crosscheck", str(scene_file), "--engines", "lagrangian,mujoco", "--dt", "1e-3", "--frame-dt", "1e-2", "--duration", "0.02")
    assert code == 0, err
    assert "mine     lagrangian" in out and "lagrangian~mujoco" in out
    assert "wrote lgnn-out/crosscheck.csv" in out
    markdown = (tmp_path / "lgnn-out" / "crosscheck.md").read_text()
    assert all(f"- {field}: " in markdown for field in ("command", "commit", "machine", "versions"))
    table = [line for line in markdown.splitlines() if line.startswith("| ")]
    assert len(table) > 2 and any("\\|E-E0\\|" in line for line in table)
    assert {len(re.findall(r"(?<!\\)\|", line)) for line in table} == {7}  # 6 columns (scene, engine, form, metric, value, note)


def test_crosscheck_of_a_damped_scene_says_its_energy_falls_by_its_damping(capsys, tmp_path):
    code, out, err = run(capsys, "crosscheck", "pendulum-bob", "--engines", "lagrangian,mujoco", "--dt", "1e-3", "--frame-dt", "1e-2", "--duration", "0.05",
                         "--out-dir", str(tmp_path))
    assert code == 0, err
    rows = [line for line in (tmp_path / "crosscheck.md").read_text().splitlines() if "energy_drift" in line]
    assert len(rows) == 2 and all("with what the scene's damping takes out" in line for line in rows)


def test_benchmark_workers_evaluate_each_models_seeds_together_scenes_interleaved(tmp_path, monkeypatch):
    """`--workers` evaluation parts (the child processes, spied on, not run): one per
    scene and (model, training scene), naming that scene and all the model's seeds;
    together exactly the grid's pairs; the first parts all on different scenes (each
    computes its scene's ground truth while the others run)."""
    from lgnn.bench import profiles, run as bench_run

    calls = []
    monkeypatch.setattr(bench_run, "run_split", lambda *args: calls.append(args))
    profile = profiles.get_profile("full")
    bench_run.run(profile, tmp_path, stages=["evaluate"], workers=4, profile_argv=["--full"])
    (stage, parts, argv, _, workers, after), = calls
    assert (stage, argv, workers, after) == ("evaluate", ["--full"], 4, ())
    covered = set()
    for name, args in parts.items():
        scene = args[args.index("--scene") + 1]
        jobs = [args[i + 1] for i, a in enumerate(args) if a == "--job"]
        assert len(jobs) == len(profile.seeds) and len({j.rsplit("-s", 1)[0] for j in jobs}) == 1, name
        assert name == f"{scene}-{jobs[0].rsplit('-s', 1)[0]}"
        covered |= {(job, scene) for job in jobs}
    assert covered == {(p.job.name, p.scene) for p in profiles.evaluation_pairs(profile)}
    scenes = profiles.evaluation_scenes(profile)
    first = [args[args.index("--scene") + 1] for args in list(parts.values())[: len(scenes)]]
    assert sorted(first) == sorted(scenes)


def test_benchmark_workers_start_the_costliest_evaluation_parts_first(tmp_path, monkeypatch):
    """Evaluation parts whose checkpoints say how long an epoch took start first, the
    dearest first (seconds per epoch times the scene's nodes); the others follow in the
    interleaved order; an unreadable checkpoint is only a part of unknown cost."""
    from lgnn.bench import grid, profiles, run as bench_run, store
    from lgnn.learn import checkpoints
    from lgnn.scene import get_scene

    calls = []
    monkeypatch.setattr(bench_run, "run_split", lambda *args: calls.append(args))
    profile = profiles.get_profile("full")
    layout = store.Layout(tmp_path)
    layout.checkpoint(profiles.training_jobs(profile)[0]).parent.mkdir(parents=True)
    for seed, seconds in enumerate((40.0, 50.0, 30.0)):  # LGN's: 5 s an epoch for its slowest seed
        checkpoints.write(layout.checkpoint(grid.TrainingJob("lgn", "chain4", seed)), {}, {}, [(1, 1.0, 1.0, 1.0), (10, 1.0, 1.0, seconds)])
    checkpoints.write(layout.checkpoint(grid.TrainingJob("gns", "chain4", 0)), {}, {}, [(10, 1.0, 1.0, 0.5)])
    layout.checkpoint(grid.TrainingJob("lgnn", "chain4", 0)).write_bytes(b"not an archive")
    assert checkpoints.seconds_per_epoch(layout.checkpoint(grid.TrainingJob("lgn", "chain4", 1))) == 5.0
    bench_run.run(profile, tmp_path, stages=["evaluate"], workers=4, profile_argv=["--full"])
    names = list(calls[0][1])
    lgn_scenes = [p.scene for p in profiles.evaluation_pairs(profile) if p.job.name == "lgn-chain4-s0"]
    gns_scenes = list(dict.fromkeys(p.scene for p in profiles.evaluation_pairs(profile) if p.job.name == "gns-chain4-s0"))
    by_size = lambda scenes: sorted(scenes, key=lambda scene: -get_scene(scene).n_nodes)  # noqa: E731 (stable: ties keep their order)
    known = [f"{scene}-lgn-chain4" for scene in by_size(lgn_scenes)] + [f"{scene}-gns-chain4" for scene in by_size(gns_scenes)]
    assert names[: len(known)] == known
    calls.clear()
    monkeypatch.setattr(bench_run, "_rollout_cost", lambda *args: 0.0)
    bench_run.run(profile, tmp_path, stages=["evaluate"], workers=4, profile_argv=["--full"])
    assert names[len(known):] == [name for name in calls[0][1] if name not in known]


def test_benchmark_workers_queue_the_ground_truths_behind_the_training_groups(tmp_path, monkeypatch):
    """With the truth stage to come, split training queues one part per evaluation scene
    behind its groups in the same pool, the costliest reference first; the truth stage
    then runs those still missing (here all: the children are spied on, not run). In one
    process the truth stage leaves the ground truths to a following evaluate stage
    (which computes each beside its models' rollouts) and computes them when alone."""
    from lgnn.bench import profiles, run as bench_run

    calls, scenes_computed = [], []
    monkeypatch.setattr(bench_run, "run_split", lambda *args: calls.append(args))
    monkeypatch.setattr(bench_run, "prepare_datasets", lambda *args: None)
    profile = profiles.get_profile("full")
    bench_run.run(profile, tmp_path, stages=["train", "truth"], workers=4, profile_argv=["--full"])
    (stage, groups, _, _, _, after), (truth_stage, truth_parts, _, _, _, truth_after) = calls
    assert stage == "train" and {job.group for job in profiles.training_jobs(profile)} == set(groups)
    ((queued_stage, queued),) = after
    scenes = profiles.evaluation_scenes(profile)
    assert queued_stage == "truth" and sorted(queued) == sorted(scenes)
    assert all(args == ["--scene", scene] for scene, args in queued.items())
    assert list(queued)[0] == "chain100-3d" and list(queued).index("chain100") < list(queued).index("chain4")
    assert (truth_stage, truth_parts, truth_after) == ("truth", queued, ())
    # Training alone queues no ground truth; the truth stage of some jobs computes their scenes'.
    calls.clear()
    bench_run.run(profile, tmp_path, stages=["train"], workers=4, profile_argv=["--full"])
    assert calls[0][-1] == ()
    calls.clear()
    bench_run.run(profile, tmp_path, stages=["truth"], jobs=["clnn-chain4-s0", "clnn-chain4-3d-s0"], workers=4, profile_argv=["--full"])
    assert calls[0][:2] == ("truth", {"chain4-3d": ["--scene", "chain4-3d"], "chain4": ["--scene", "chain4"]})
    # One process.
    monkeypatch.setattr(bench_run, "evaluate_scene", lambda profile, scene, out, progress: scenes_computed.append(scene))
    monkeypatch.setitem(bench_run.STAGES, "evaluate", dataclasses.replace(bench_run.STAGES["evaluate"], run=lambda request: None))
    quick = profiles.get_profile("quick")
    bench_run.run(quick, tmp_path, stages=["truth", "evaluate"], progress=False)
    assert scenes_computed == []
    bench_run.run(quick, tmp_path, stages=["truth"], progress=False)
    assert scenes_computed == profiles.evaluation_scenes(quick)


def test_benchmark_workers_train_groups_in_child_processes_and_name_a_failing_ones_log(capsys, tmp_path, monkeypatch):
    """`lgnn benchmark --workers 2`: the training data are generated once, before the
    children start; each (model, training scene) group trains in its own child process,
    checkpoints and logs under the output directory; a part that fails fails the stage
    with one line naming its log, the others' records kept."""
    from lgnn.bench import run as bench_run
    from lgnn.bench.parallel import run_split
    from lgnn.errors import LgnnError
    from lgnn.learn import data

    data_before_children = []

    def spy(*args, **kwargs):
        data_before_children.append(sorted(p.name.split("-")[1] for p in data.default_cache_dir().glob("data-*.npz")))
        return run_split(*args, **kwargs)

    monkeypatch.setattr(bench_run, "run_split", spy)

    # Two models, one epoch of 20 states integrated at dt 1e-3: the child processes are
    # the point here (each child's imports, data and compiles: ~35 s on 2 loaded cores).
    profile_argv = ["--set", 'models=["gns","clnn"]', "--set", "training.train.epochs=1", "--set", "training.data.n_trajectories=4",
                    "--set", "training.data.duration=0.1", "--set", "training.data.sample_dt=0.02", "--set", "training.data.dt=1e-3"]
    code, out, err = run(capsys, "benchmark", *profile_argv, "--stage", "train", "--workers", "2", "--out-dir", tmp_path, "--quiet")
    assert code == 0, err
    bench = tmp_path / "benchmark"
    assert {p.name for p in (bench / "checkpoints").iterdir()} >= {"gns-chain4-s0.npz", "clnn-chain4-s0.npz"}
    assert {p.name for p in (bench / "logs").iterdir()} == {"train-gns-chain4.log", "train-clnn-chain4.log"}
    assert data_before_children == [["chain4"]]
    # A part that fails (a child that stops at once: an unknown job).
    with pytest.raises(LgnnError) as failed:
        run_split("train", {"nonsense": ["--job", "no-such-job"]}, profile_argv, tmp_path, 2)
    message = str(failed.value)
    assert "\n" not in message and "1 of 1 parts failed" in message and str(bench / "logs" / "train-nonsense.log") in message
    assert "unknown training job 'no-such-job'" in (bench / "logs" / "train-nonsense.log").read_text()


def test_benchmark_on_ray_without_ray_installed_is_one_line(capsys, tmp_path, monkeypatch):
    """`--executor ray` without Ray fails at once, one line saying how to install it;
    `--address` without `--executor ray` is refused likewise."""
    import sys

    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    code, _, err = run(capsys, "benchmark", "--executor", "ray", "--stage", "train", "--out-dir", tmp_path, "--quiet")
    assert code == 2 and err.count("\n") == 1 and "pip install 'lgnn[ray]'" in err, err
    code, _, err = run(capsys, "benchmark", "--address", "auto", "--stage", "train", "--out-dir", tmp_path, "--quiet")
    assert code == 2 and err.count("\n") == 1 and "--executor ray" in err, err


def test_workers_share_a_gpu_through_a_private_mps_daemon_stopped_afterwards(tmp_path, monkeypatch, capsys):
    """`gpu_sharing` (a stand-in `nvidia-cuda-mps-control` on the PATH records its
    calls): a daemon is started with a private pipe directory that the children's
    environment names, and told to quit with the same one on exit; nothing is started
    for one child, with `LGNN_MPS=0`, or when the caller names its own daemon; a daemon
    that fails to start leaves the environment as it was, with a warning."""
    from lgnn.bench.parallel import MPS_CONTROL, gpu_sharing

    calls = tmp_path / "calls.txt"
    control = tmp_path / "bin" / MPS_CONTROL
    control.parent.mkdir()
    # Reads its standard input (the "quit" command) unless started as the daemon ("-d").
    control.write_text(f'#!/bin/sh\nin=""; [ "$1" = "-d" ] || in=$(cat)\necho "$* stdin=$in pipe=$CUDA_MPS_PIPE_DIRECTORY" >> {calls}\nexit ${{FAKE_MPS_EXIT:-0}}\n')
    control.chmod(0o755)
    monkeypatch.setenv("PATH", f"{control.parent}:{os.environ['PATH']}")
    env = {"PATH": os.environ["PATH"], "XLA_PYTHON_CLIENT_PREALLOCATE": "false"}

    with gpu_sharing(env) as shared:
        pipe = shared["CUDA_MPS_PIPE_DIRECTORY"]
        assert Path(pipe).is_dir() and shared["XLA_PYTHON_CLIENT_PREALLOCATE"] == "false"
        assert calls.read_text().splitlines() == [f"-d stdin= pipe={pipe}"]
    assert calls.read_text().splitlines()[1] == f" stdin=quit pipe={pipe}"
    assert not Path(pipe).exists()

    calls.unlink()
    for kept in (dict(env=env, enabled=False), dict(env={**env, "LGNN_MPS": "0"}), dict(env={**env, "CUDA_MPS_PIPE_DIRECTORY": "/theirs"})):
        with gpu_sharing(**kept) as shared:
            assert shared == kept["env"]
    assert not calls.exists()

    # A SIGTERM inside the block unwinds it: the daemon is still told to quit.
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(SystemExit):
        with gpu_sharing(env) as shared:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)  # (the handler raises as soon as the signal arrives)
    assert calls.read_text().splitlines()[-1] == f" stdin=quit pipe={shared['CUDA_MPS_PIPE_DIRECTORY']}"
    assert signal.getsignal(signal.SIGTERM) is before

    with gpu_sharing({**env, "FAKE_MPS_EXIT": "1"}) as shared:
        assert "CUDA_MPS_PIPE_DIRECTORY" not in shared
    assert "warning: no MPS daemon" in capsys.readouterr().err


def test_workers_spread_over_the_visible_gpus(tmp_path, monkeypatch):
    """On a host of several GPUs each child gets the GPU running the fewest children
    (ties: the first), from `CUDA_VISIBLE_DEVICES` where set, else `nvidia-smi`'s list
    (a stand-in on the PATH); a CPU host (no `nvidia-smi`) has none."""
    from lgnn.bench.parallel import least_loaded, visible_gpus

    assert least_loaded(["0", "1", "2"], []) == "0"
    assert least_loaded(["0", "1", "2"], ["0", "1", "0"]) == "2"
    assert least_loaded(["0", "1"], ["0", "1", "1"]) == "0"
    assert visible_gpus({"CUDA_VISIBLE_DEVICES": "2, 3"}) == ["2", "3"]
    smi = tmp_path / "bin" / "nvidia-smi"
    smi.parent.mkdir()
    smi.write_text("#!/bin/sh\nprintf '0\\n1\\n'\n")
    smi.chmod(0o755)
    monkeypatch.setenv("PATH", str(smi.parent))
    assert visible_gpus({}) == ["0", "1"]
    monkeypatch.setenv("PATH", str(tmp_path))
    assert visible_gpus({}) == []


def test_crosscheck_runs_a_mujoco_engine_in_both_forms(capsys, tmp_path):
    """`--engines lagrangian,mujoco:nested,mujoco:maximal` on a 3D net with one loop:
    each form gets its rows, the pair of forms its error, and a bad form or a form
    on the Lagrangian engine is a one-line error before any run."""
    import pandas as pd

    from lgnn.scene import scene_to_json, spatial_net

    scene_file = tmp_path / "net.json"
    scene_file.write_text(scene_to_json(spatial_net(2, 2)))
    (tmp_path / "out").mkdir()
    (tmp_path / "bad").mkdir()
    code, out, err = run(capsys, "crosscheck", str(scene_file), "--engines", "lagrangian,mujoco:nested,mujoco:maximal",
                         "--dt", "1e-3", "--frame-dt", "1e-2", "--duration", "0.05", "--out-dir", str(tmp_path / "out"))
    assert code == 0, err
    table = pd.read_csv(tmp_path / "out" / "crosscheck.csv", comment="#", keep_default_na=False)
    errors = table[table.metric == "max_node_error"].set_index(["engine", "form"]).value
    assert set(errors.index) == {("lagrangian~mujoco", "-~nested"), ("lagrangian~mujoco", "-~maximal"), ("mujoco~mujoco", "nested~maximal")}
    assert errors.max() < 1e-6
    assert set(table[table.metric == "wall_s"].form) == {"", "nested", "maximal"}
    for engines, message in (("mujoco:sideways", "unknown MJCF form"), ("lagrangian:nested", "has no MJCF form")):
        code, _, err = run(capsys, "crosscheck", str(scene_file), "--engines", engines, "--out-dir", str(tmp_path / "bad"))
        assert code == 2 and message in err and not (tmp_path / "bad" / "crosscheck.csv").exists()


CHILD_WAITING_FOR_SIGINT = """
import sys, time
from lgnn.runtime import accept_interrupts_if_child
accept_interrupts_if_child()
try:  # "ready" inside: the SIGINT may arrive while print() still returns
    print("ready", flush=True)
    time.sleep(30)
except KeyboardInterrupt:
    print("interrupted", flush=True)
"""


@pytest.mark.parametrize("marked", [True, False])
def test_a_benchmark_child_accepts_interrupts_its_parent_ignored(marked):
    # A parent in the background of a non-interactive shell ignores SIGINT, and its
    # children inherit that; a benchmark child (marked by `run_split`) takes it back, so
    # the SIGINT its parent stops it with lets it save its work. Unmarked, it would not
    # react (the case the flag exists for: shown here so that the test can fail).
    import shlex
    import subprocess
    import sys

    from lgnn.runtime import BENCHMARK_CHILD

    env = {k: v for k, v in os.environ.items() if k != BENCHMARK_CHILD} | ({BENCHMARK_CHILD: "1"} if marked else {})
    # The shell's `trap '' INT` ignores SIGINT, and `exec` hands that on to Python, as a
    # backgrounded parent would (no preexec_fn: a fork of this multithreaded process).
    command = f"trap '' INT; exec {shlex.quote(sys.executable)} -c {shlex.quote(CHILD_WAITING_FOR_SIGINT)}"
    child = subprocess.Popen(["sh", "-c", command], stdout=subprocess.PIPE, text=True, env=env)
    try:
        assert child.stdout.readline().strip() == "ready"
        child.send_signal(signal.SIGINT)
        try:
            output, _ = child.communicate(timeout=10)
            reacted = "interrupted" in output
        except subprocess.TimeoutExpired:
            reacted = False
    finally:
        child.kill()
        child.wait()
    assert reacted is marked


def test_run_split_marks_its_children_and_gives_them_one_minute_together(tmp_path, monkeypatch):
    # Stopping (the parent interrupted), every child gets SIGINT, then the children
    # share one grace period: one that ignores it is killed at the end of it, not after a
    # grace period of its own for each child before it.
    from lgnn.bench import parallel
    from lgnn.runtime import BENCHMARK_CHILD

    started, timeouts = [], []

    class Child:
        def __init__(self, command, stdout, stderr, env):
            started.append(env)
            self.signals, self.killed = [], False

        def poll(self):
            return None

        def send_signal(self, signum):
            self.signals.append(signum)

        def wait(self, timeout=None):
            if timeout is None:
                return 0
            timeouts.append(timeout)
            time.sleep(min(timeout, 0.2))
            raise parallel.subprocess.TimeoutExpired("child", timeout)

        def kill(self):
            self.killed = True

    def interrupted(*args):
        raise KeyboardInterrupt

    monkeypatch.setattr(parallel.subprocess, "Popen", Child)
    monkeypatch.setattr(parallel.time, "sleep", lambda s, real=time.sleep: real(min(s, 0.2)) if s < 1 else interrupted())
    monkeypatch.setattr(parallel, "STOP_GRACE_S", 0.3)
    with pytest.raises(KeyboardInterrupt):
        parallel.run_split("train", {f"part{k}": [] for k in range(3)}, [], tmp_path, 3)
    assert len(started) == 3 and all(env[BENCHMARK_CHILD] == "1" for env in started)
    assert timeouts[0] <= 0.3 and sum(timeouts) < 0.3 + 0.1, timeouts


def test_run_split_starts_another_stages_parts_behind_its_own(tmp_path, monkeypatch):
    """`after`'s parts (the truth stage's behind training's) start once the stage's own
    have, in the same pool of workers, each with its own `--stage` and log."""
    from lgnn.bench import parallel

    started = []

    class Child:
        returncode = 0

        def __init__(self, command, stdout, stderr, env):
            started.append((command[command.index("--stage") + 1], command[-1], Path(stdout.name).name))

        def poll(self):
            return 0

    monkeypatch.setattr(parallel.subprocess, "Popen", Child)
    monkeypatch.setattr(parallel.time, "sleep", lambda s: None)
    parallel.run_split("train", {"a": ["--job", "a-s0"], "b": ["--job", "b-s0"]}, [], tmp_path, 1,
                       after=(("truth", {"chain8": ["--scene", "chain8"]}),))
    assert started == [("train", "a-s0", "train-a.log"), ("train", "b-s0", "train-b.log"), ("truth", "chain8", "truth-chain8.log")]


def test_scene_export_takes_every_builtin(capsys):
    """T2-slack, which the grid evaluates, is a built-in like any other."""
    from lgnn.scene import get_scene, scene_from_dict

    code, out, _ = run(capsys, "scene", "export", "T2-slack")
    assert code == 0 and scene_from_dict(json.loads(out)) == get_scene("T2-slack")


def test_scenes_says_which_the_benchmark_evaluates(capsys):
    """The grid's 3D scenes and T2-slack are marked evaluated; T2 (left out of the grid)
    and the hard cases are not; each line gives the scene's tags and initial states."""
    from lgnn.bench.profiles import PROFILES, evaluation_scenes

    code, out, _ = run(capsys, "scenes")
    assert code == 0
    lines = {line.split()[0]: line for line in out.splitlines() if not line.startswith("#")}
    for name in evaluation_scenes(PROFILES["full"]):
        assert "evaluated (" in lines[name] and "full" in lines[name], lines[name]
    assert "chain4-3d" in evaluation_scenes(PROFILES["full"]) and " 3d " in lines["chain4-3d"]
    for name in ("T2", "folded4", "pendulum"):
        assert "evaluated" not in lines[name], lines[name]
    assert "own state" in lines["T1"] and "chain sampler" in lines["chain4"]


def test_lgnn_train_defaults_are_the_full_profiles_recipe():
    """`lgnn train` trains as the full profile trains every model (batch, rate and its
    schedule, plateau rule, data), read from the profile: its checkpoint is comparable
    with the committed ones, and the report's banner names no other training."""
    from lgnn.bench import profiles
    from lgnn.cli import build_parser, train_settings
    from lgnn.learn import protocol

    full = profiles.PROFILES["full"].training
    data_config, config = train_settings(build_parser().parse_args(["train", "--model", "lgnn", "--out", "x.npz"]))
    assert data_config == full.data_for("chain4")
    assert protocol.training_key(config) == protocol.training_key(full.train)
    assert (config.epochs, config.patience, config.min_improvement, config.minutes) == (
        full.train.epochs, full.train.patience, full.train.min_improvement, full.train.minutes)
    data_config, config = train_settings(build_parser().parse_args(["train", "--model", "gns", "--scene", "chain8", "--seed", "2",
                                                                     "--epochs", "20", "--out", "x.npz"]))
    assert data_config == full.data_for("chain8") and config.seed == 2 and config.epochs == 20
    assert protocol.training_key(config) | {"seed": 0} == protocol.training_key(full.train)


def test_lgnn_train_and_the_full_benchmark_read_one_copy_of_the_training_data(tmp_path):
    """One dataset cache: `lgnn train`'s default data (the full profile's recipe, in the
    user's cache) are the file the full benchmark's train stage reads, whatever its
    output folder, never a second copy under it."""
    from lgnn.bench import profiles, store
    from lgnn.cli import build_parser, train_settings
    from lgnn.learn import data

    data_config, _ = train_settings(build_parser().parse_args(["train", "--model", "gns", "--out", str(tmp_path / "model.npz")]))
    benchmark_data = profiles.PROFILES["full"].training.data_for("chain4")
    assert store.Layout(tmp_path / "out").datasets == data.default_cache_dir()
    assert data.cache_path(data_config, data.default_cache_dir()) == data.cache_path(benchmark_data, store.Layout(tmp_path / "out").datasets)


def test_version_names_lgnn_its_commit_and_the_versions_results_record(capsys):
    from lgnn import provenance

    try:
        code = main(["--version"])
    except SystemExit as exit_:
        code = exit_.code
    out = capsys.readouterr().out
    assert code == 0 and out.strip() == f"{provenance.versions()}; commit {provenance.commit()}"
    for package in ("lgnn", "jax", "jaxlib", "mujoco", "numpy"):
        assert f"{package} " in out


# The one rule for missing output folders (docs/cli.md): a named output file's folder must
# exist; a named output folder is created with its parents.
_OUTPUT_FILES = [
    ["simulate", "chain4", "--duration", "0.01", "--out", "{out}/x.npz"],
    ["scene", "export", "chain4", "--out", "{out}/x.json"],
    ["scene", "import", "lgnn/assets/mjcf/acrobot.xml", "--out", "{out}/x.json"],
    ["mjcf", "chain4", "--out", "{out}/x.xml"],
    ["rollout", "chain4", "--model", "results/benchmark/checkpoints/lgnn-chain4-s0.npz", "--duration", "0.01", "--out", "{out}/x.npz"],
    ["train", "--scene", "chain4", "--model", "lgnn", "--epochs", "1", "--out", "{out}/x.npz"],
    ["plot", "{tmp}/a.npz", "--out", "{out}/x.png"],
    ["animate", "{tmp}/a.npz", "--out", "{out}/x.gif"],
    ["dataset", "export", "--scene", "chain4", "--out", "{out}/x.npz"],
    ["stability", "--out", "{out}/x.md"],
]


@pytest.mark.parametrize("argv", _OUTPUT_FILES, ids=lambda argv: " ".join(argv[:2]))
def test_an_output_file_in_a_missing_folder_is_refused_before_any_work(capsys, tmp_path, monkeypatch, argv):
    monkeypatch.chdir(Path(__file__).resolve().parents[1])
    missing = tmp_path / "missing" / "deeper"
    code, _, err = run(capsys, *[a.format(out=missing, tmp=tmp_path) for a in argv])
    assert code == 2 and f"output directory does not exist: {missing}" in err, err
    assert not (tmp_path / "missing").exists()


def test_an_output_folder_is_created_with_its_parents(capsys, tmp_path):
    from lgnn.files import out_dir

    assert run(capsys, "simulate", "chain4", "--duration", "0.01", "--out", str(tmp_path / "a.npz"))[0] == 0
    folder = tmp_path / "new" / "deeper"
    assert run(capsys, "compare", str(tmp_path / "a.npz"), str(tmp_path / "a.npz"), "--out-dir", str(folder))[0] == 0
    assert (folder / "compare_summary.md").is_file()
    # crosscheck's, convergence's and gpu-truth's folders go through the same function.
    assert out_dir(tmp_path / "other" / "deeper").is_dir()
    (tmp_path / "file").write_text("")
    with pytest.raises(ConfigError, match="is not a directory"):
        out_dir(tmp_path / "file" / "x")


def test_every_output_option_follows_the_rule():
    """Each command's --out and --out-dir is one this file tests, so a new command's
    output is classified (a file whose folder must exist, or a folder created)."""
    from lgnn.cli import build_parser

    tested_files = {tuple(argv[:2]) if argv[0] in ("scene", "dataset") else (argv[0],) for argv in _OUTPUT_FILES}
    folders = {("benchmark",), ("leaderboard",), ("evaluate",), ("compare",), ("crosscheck",), ("convergence",), ("gpu-truth",),
               ("mjcf",), ("papers",), ("handoff", "pack"), ("handoff", "unpack")}
    found = set()

    def walk(parser, path):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    walk(sub, (*path, name))
            elif {"--out", "--out-dir", "--to"} & set(action.option_strings):
                found.add(path)

    walk(build_parser(), ())
    assert found <= tested_files | folders, found - tested_files - folders
