"""Record keys: every setting a stage reads enters its key, except those declared
`NOT_IN_KEY` (so a changed setting never reuses a stale record, and splitting work
differently never recomputes one); and the committed full-profile records match the
current settings (`lgnn benchmark --full --stage report` recomputes nothing)."""

import dataclasses
import threading
from pathlib import Path

import jax
import numpy as np
import pytest

from lgnn import metrics
from lgnn.bench import grid, profiles, store
from lgnn.bench.stages import evaluate, mass, scaling, speed
from lgnn.bench.stages import truth as truth_stage
from lgnn.engines.rollouts import Rollouts
from lgnn.learn import models, protocol, train
from lgnn.scene import get_scene
from lgnn.trajectory import Trajectory

ROOT = Path(__file__).resolve().parents[1]
QUICK = profiles.PROFILES["quick"]
SCENE = "chain4"
# Values for fields a generic change would not reach (a step for another scene).
CHANGED = {"scene_dts": ((SCENE, 5e-4),), "references": ("mujoco", "lagrangian")}


def _checkpoint(path: Path, seed: int = 0, **train_settings) -> Path:
    """An untrained true-physics checkpoint at `path` (parameters drawn from `seed`)."""
    model, config = models.ModelConfig("lgnn"), protocol.TrainConfig(seed=seed, **train_settings)
    train.save_checkpoint(path, train.initial_state(model, config), model, config)
    return path


def _changed(name, value):
    if name in CHANGED:
        return CHANGED[name]
    if isinstance(value, bool):
        return not value
    if name.endswith("dt"):  # a step still dividing the frame time, a frame time the duration
        return value / 2 if name != "frame_dt" else value * 2
    if name == "duration":
        return value * 2
    if isinstance(value, (int, float)):
        return value * 2 + 1
    if value is None:
        return ("lgnn",)
    if isinstance(value, tuple):
        return value + value[-1:] if value else ("x",)
    raise AssertionError(f"no change for {name}={value!r}")


def _keys(profile, out: Path, checkpoint: Path) -> dict:
    """Every stage's key on SCENE."""
    pair = grid.Pair(grid.TrainingJob("lgnn", grid.TRAINING_SCENE, 0), SCENE)
    return {
        "truth": truth_stage.truth_key(profile, SCENE),
        "pair": evaluate.pair_key(profile, pair, checkpoint),
        "speed": speed.speed_key(profile, SCENE, out),
        "scaling": scaling.scaling_key(profile, out),
        "mass": mass.mass_key(profile, SCENE, checkpoint),
    }


# The settings groups each stage reads.
READS = {
    "evaluate": {"truth", "pair", "speed", "scaling", "mass"},
    "speed": {"speed"},
    "scaling": {"scaling"},
    "mass": {"mass"},
}


@pytest.mark.parametrize("group", sorted(READS))
def test_every_setting_a_stage_reads_is_in_its_key(tmp_path, group):
    checkpoint = _checkpoint(tmp_path / "checkpoint.npz")
    before = _keys(QUICK, tmp_path, checkpoint)
    settings = getattr(QUICK, group)
    for field in dataclasses.fields(settings):
        value = getattr(settings, field.name)
        profile = dataclasses.replace(QUICK, **{group: dataclasses.replace(settings, **{field.name: _changed(field.name, value)})})
        after = _keys(profile, tmp_path, checkpoint)
        changed = {stage for stage in before if before[stage] != after[stage]}
        expected = READS[group] if field.metadata.get("in_key", True) else set()
        assert changed == expected, f"{group}.{field.name}: keys changed {sorted(changed)}, expected {sorted(expected)}"


def test_a_stage_key_follows_the_checkpoint_content_not_its_file(tmp_path):
    checkpoint = _checkpoint(tmp_path / "checkpoint.npz", seed=0)
    before = _keys(QUICK, tmp_path, checkpoint)
    # Other parameters: the records made from the checkpoint are stale.
    _checkpoint(checkpoint, seed=1)
    after = _keys(QUICK, tmp_path, checkpoint)
    assert {stage for stage in before if before[stage] != after[stage]} == {"pair", "mass"}
    # The same parameters in another file (other optimiser settings, so other bytes,
    # and converted): every record still holds.
    _checkpoint(checkpoint, seed=1, learning_rate=1e-4)
    converted = tmp_path / "converted" / "checkpoint.npz"
    converted.parent.mkdir()
    train.convert_checkpoint(checkpoint, converted)
    assert converted.read_bytes() != checkpoint.read_bytes()
    assert _keys(QUICK, tmp_path, checkpoint) == _keys(QUICK, tmp_path, converted) == after


def test_committed_full_records_match_the_current_settings():
    """Every committed record is found under its current key: the report reproduces
    the committed tables without recomputing (tools/rekey_records.py made them so)."""
    profile, out = profiles.PROFILES["full"], ROOT / "results"
    truths = set(evaluate.load_truths(profile, out))
    committed = [pair for pair in profiles.evaluation_pairs(profile) if store.Layout(out).checkpoint(pair.job).exists()]
    assert {pair.scene for pair in committed} <= truths <= set(profiles.evaluation_scenes(profile))
    loaded = [pair for pair, _ in evaluate.load_pairs(profile, out)]
    # Every pair of the grid has its record: no cell of the report says "not evaluated".
    assert set(loaded) == set(committed) == set(profiles.evaluation_pairs(profile))
    assert all(speed.load_speed(profile, scene, out) is not None for scene in profile.speed.scenes)
    # The committed scaling record predates the 3D rows: it loads under the planar-only
    # settings it was made with (no 3D lengths leave the key as it was), never as the
    # current settings' record, until the scaling stage is rerun.
    planar = dataclasses.replace(profile.scaling, spatial_lengths=(),
                                 throughput_scenes=tuple(s for s in profile.scaling.throughput_scenes if not s.endswith("-3d")))
    assert scaling.load_scaling(profile, out) is not None or scaling.load_scaling(dataclasses.replace(profile, scaling=planar), out) is not None
    # chain16-3d's LGNN (trained on chain4-3d) comes with the spatial grid's GPU run.
    analysed = [scene for scene in profile.mass.scenes if store.Layout(out).checkpoint(profiles.lgnn_job(profile, scene)).exists()]
    assert "chain16" in analysed and len(mass.load_mass(profile, out)) == len(analysed)


def test_ground_truth_trajectories_are_kept_and_reused_only_under_their_key(tmp_path, monkeypatch, capsys):
    # Every process evaluating one of a scene's pairs reads the trajectories the first
    # one computed (chain100-3d's MuJoCo C reference takes 15 minutes on 16 cores).
    truth_stage.ground_truth.cache_clear()
    computed = truth_stage.ground_truth(QUICK, SCENE, False, tmp_path)
    # The one that computes them says in its log what they cost, the reference included.
    cost = [line for line in capsys.readouterr().err.splitlines() if line.startswith(f"[benchmark] ground truth {SCENE} cost: ")]
    assert len(cost) == 1 and f"mujoco {computed.reference_s['mujoco']:.1f} s" in cost[0], cost
    assert truth_stage.truth_file(QUICK, SCENE).exists()
    assert not (tmp_path / "datasets").exists()  # in the dataset cache, not the output folder
    truth_stage.ground_truth.cache_clear()

    def recompute(*args):
        raise AssertionError("recomputed")

    monkeypatch.setattr(truth_stage, "_computed_ground_truth", recompute)
    # Read back by a process of any output folder.
    read = truth_stage.ground_truth(QUICK, SCENE, False, tmp_path / "another-output-folder")
    kept, written = read.arrays(), computed.arrays()
    assert set(kept) == set(written) >= set(truth_stage.truth_trajectories(QUICK.evaluate.references))
    for name in written:
        assert kept[name].dtype == written[name].dtype and (kept[name] == written[name]).all(), name
    assert read.timings() == computed.timings() and read.platform == computed.platform
    other = dataclasses.replace(QUICK, evaluate=dataclasses.replace(QUICK.evaluate, ic_seed=QUICK.evaluate.ic_seed + 1))
    with pytest.raises(AssertionError, match="recomputed"):
        truth_stage.ground_truth(other, SCENE, False, tmp_path)
    truth_stage.ground_truth.cache_clear()


def test_the_3d_lgnn_enters_the_scaling_key_only_with_3d_lengths(tmp_path):
    checkpoint = store.Layout(tmp_path).checkpoint(profiles.lgnn_job(QUICK, grid.SPATIAL_TRAINING_SCENE))
    checkpoint.parent.mkdir(parents=True, exist_ok=True)
    planar = dataclasses.replace(QUICK, scaling=dataclasses.replace(QUICK.scaling, spatial_lengths=()))
    assert QUICK.scaling.spatial_lengths
    before = scaling.scaling_key(QUICK, tmp_path), scaling.scaling_key(planar, tmp_path)
    _checkpoint(checkpoint)
    after = scaling.scaling_key(QUICK, tmp_path), scaling.scaling_key(planar, tmp_path)
    assert before[0] != after[0] and before[1] == after[1]


def test_a_models_rollouts_do_not_wait_for_its_scenes_ground_truth(tmp_path, monkeypatch):
    # The truth (here a stand-in) waits until the model's rollouts have started: run one
    # after the other, this would time out; run beside each other, the record is scored.
    from lgnn.learn import models

    profile = dataclasses.replace(QUICK, evaluate=dataclasses.replace(QUICK.evaluate, initial_conditions=2))
    scene = get_scene(SCENE)
    states = truth_stage.evaluation_initial_states(profile, scene)
    config = profile.evaluate.simulation(SCENE)
    rollouts_started = threading.Event()

    def held_states(count):
        q = np.repeat(np.asarray(states.q)[:, None], config.n_frames + 1, axis=1)
        return np.stack([q] * count), np.zeros((count,) + q.shape)

    def truth_after_rollouts(*args):
        assert rollouts_started.wait(timeout=30), "the ground truth was computed before the rollouts started"
        (q,), (qd,) = held_states(1)
        energy = metrics.true_energies(scene, q, qd)
        t = np.arange(q.shape[1]) * profile.evaluate.frame_dt
        held = Trajectory(t, q, qd, energy)
        return truth_stage.GroundTruth(states, held, states, {"mujoco": held}, 0.0, 0.0, {"mujoco": 0.0}, "cpu")

    def rollouts(engine, scene, config, initial, label=""):
        rollouts_started.set()
        np.testing.assert_array_equal(initial.q, states.q)
        q, qd = held_states(len(jax.tree.leaves(engine.params)[0]))
        return Rollouts(q, qd, metrics.true_energies(scene, q, qd), 1.0, 1.0, "cpu")

    monkeypatch.setattr(evaluate, "ground_truth", truth_after_rollouts)
    monkeypatch.setattr(models.ModelEngine, "rollouts", rollouts)
    model = models.ModelConfig("lgnn", latent=4, hidden=8)
    pair = grid.Pair(grid.TrainingJob("lgnn", grid.TRAINING_SCENE, 0), SCENE)
    path = tmp_path / "pair.npz"
    evaluate._evaluate_stacked(profile, [(pair, path, "key", model, models.init(jax.random.PRNGKey(0), model))], False, tmp_path)
    arrays, meta = store.load(path, "key")
    assert meta["initial_conditions"] == 2 and arrays["rollout_error/per_ic_log"].shape == (2,)


def test_an_interrupted_ground_truth_does_not_wait_for_mujocos_reference(monkeypatch):
    # MuJoCo C's reference runs beside the Lagrangian ground truth (chain100-3d: 8-14
    # minutes); Ctrl-C during the latter stops at once instead of waiting it out.
    release = threading.Event()
    monkeypatch.setattr(truth_stage, "_reference_rollouts", lambda *args: release.wait(60))

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(truth_stage, "batched_rollouts", interrupted)
    outcome = {}

    def compute():
        try:
            truth_stage._computed_ground_truth(QUICK, SCENE, False)
        except KeyboardInterrupt:
            outcome["interrupted"] = True

    worker = threading.Thread(target=compute, daemon=True)
    worker.start()
    worker.join(timeout=30)
    release.set()
    assert outcome.get("interrupted"), "the interrupt waited for MuJoCo's reference"
