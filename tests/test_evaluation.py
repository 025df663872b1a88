"""Evaluate and compare (`lgnn.bench.evaluation`, `lgnn evaluate`, `lgnn compare`) and
the constrained initial-condition sampler (`lgnn.physics.sampling`)."""

import csv
import dataclasses

import jax
import numpy as np
import pytest

from lgnn import physics
from lgnn.bench import evaluation
from lgnn.cli import main
from lgnn.engines.base import SimulationConfig, Trajectory
from lgnn.engines.lagrangian import simulate
from lgnn.learn import models, protocol, train
from lgnn.scene import get_scene, sample_initial_states
from lgnn.scene.catalogue import double_pinned_chain

SHORT = SimulationConfig(duration=0.02)
# LagrangeBench's cheating model: the true accelerations (as in tests/test_models.py,
# under a name of its own: a name keeps one spec per process, and xdist may run both files in one).
CHEAT = models.ModelSpec("cheat-evaluate", lambda key, config: {}, acceleration=lambda config, params, scene: physics.true_acceleration_fn(scene))


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def read_csv(path):
    with open(path) as handle:
        return list(csv.DictReader(line for line in handle if not line.startswith("#")))


def test_sampled_states_of_a_closed_loop_satisfy_its_constraints_and_differ():
    """A scene the chain sampler does not apply to (a chain between two pins: a closed
    loop, nonlinear constraints) gets distinct perturbed states on its constraint
    manifold: link lengths and pins to round-off, length rates zero, pins at rest."""
    scene = double_pinned_chain(4)
    states = physics.sample_states(scene, 3, 0)
    assert states.q.shape == (3, scene.n_nodes, 2)
    for q, qd in zip(states.q, states.qd):
        assert float(physics.constraint_violation(scene, q)) < 1e-12
        assert float(physics.velocity_constraint_violation(scene, q, qd)) < 1e-12
        np.testing.assert_array_equal(qd[list(scene.pinned)], 0.0)
    moved = np.max(np.abs(states.q - scene.nodes), axis=(1, 2))
    assert np.all(moved > 1e-3) and np.max(np.abs(states.q[0] - states.q[1])) > 1e-3
    assert np.max(np.abs(states.qd)) > 1e-3


def test_pinned_chains_keep_the_papers_sampler():
    scene = get_scene("chain4")
    # Exact: `sample_states` calls this very sampler with this key.
    np.testing.assert_array_equal(physics.sample_states(scene, 2, 3).q, np.asarray(sample_initial_states(scene, jax.random.PRNGKey(3), 2).q))


@pytest.fixture(scope="module")
def truth_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("compare") / "truth.npz"
    simulate(get_scene("chain4"), SHORT).save(path)
    return path


def test_compare_gives_zero_against_itself_and_the_shift_of_a_shifted_copy(capsys, tmp_path, truth_file):
    """A file against itself: every error at its floor. Against a copy with every node
    moved by d: the per-node RMS error is |d| at every frame, the rollout error
    `||d|| sqrt(N) / (||q|| + ||q + d||)`."""
    truth = Trajectory.load(truth_file)
    shift = np.array([3e-3, -4e-3])  # |shift| = 5e-3
    shifted = tmp_path / "shifted.npz"
    dataclasses.replace(truth, q=truth.q + shift).save(shifted)
    scored, notes = evaluation.compare_trajectories([truth_file, shifted])
    assert notes == [] and scored.diverged.tolist() == [-1]
    np.testing.assert_allclose(scored.errors["node_rms_error"][0], 5e-3, rtol=1e-12)
    norms = np.linalg.norm(truth.q[1:], axis=(1, 2)) + np.linalg.norm(truth.q[1:] + shift, axis=(1, 2))
    np.testing.assert_allclose(scored.errors["rollout_error"][0], 5e-3 * np.sqrt(truth.q.shape[1]) / norms, rtol=1e-12)
    code, out, err = run(capsys, "compare", str(truth_file), str(shifted), "--out-dir", str(tmp_path))
    assert code == 0, err
    frames = read_csv(tmp_path / "compare_frames.csv")
    assert len(frames) == 3 * (len(truth.t) - 1)  # metrics x frames after the initial one
    assert "node_rms_error (m)" in out and (tmp_path / "compare_summary.md").exists()

    code, out, err = run(capsys, "compare", str(truth_file), str(truth_file), "--out-dir", str(tmp_path))
    assert code == 0, err
    summary = read_csv(tmp_path / "compare_summary.csv")
    assert {r["metric"]: float(r["gmean"]) for r in summary}["rollout_error"] == pytest.approx(1e-16)
    assert {r["metric"]: float(r["gmean"]) for r in summary}["energy_error"] == pytest.approx(1e-16)


def test_compare_refuses_files_of_different_frame_times(capsys, tmp_path, truth_file):
    truth = Trajectory.load(truth_file)
    other = tmp_path / "other.npz"
    dataclasses.replace(truth, t=2 * truth.t).save(other)
    code, _, err = run(capsys, "compare", str(truth_file), str(other))
    assert code == 2 and "frame times differ" in err and len(err.strip().splitlines()) == 1


def _cheat_checkpoint(tmp_path):
    """A checkpoint of the cheating model (`CHEAT`) in `tmp_path`."""
    models.register(CHEAT)
    config = models.ModelConfig("cheat-evaluate")
    checkpoint = tmp_path / "cheat.npz"
    train.save_checkpoint(checkpoint, train.initial_state(config, protocol.TrainConfig()), config, protocol.TrainConfig())
    return checkpoint


def test_evaluate_with_the_cheating_model_has_no_error(capsys, tmp_path):
    """The true-physics model scored by `lgnn evaluate` is exact against the Lagrangian
    engine and within MuJoCo's agreement with it; every output is written."""
    checkpoint = _cheat_checkpoint(tmp_path)
    code, out, err = run(capsys, "evaluate", "chain4", "--model", str(checkpoint), "--duration", "0.01", "--initial-conditions", "2",
                         "--out-dir", str(tmp_path), "--quiet")
    assert code == 0, err
    summary = {(r["reference"], r["metric"]): r for r in read_csv(tmp_path / "evaluate_summary.csv")}
    assert len(summary) == 6
    assert float(summary["lagrangian", "rollout_error"]["gmean"]) < 1e-15
    assert float(summary["lagrangian", "energy_error"]["gmean"]) < 1e-15
    assert float(summary["mujoco", "rollout_error"]["gmean"]) < 1e-12
    assert all(r["diverged"] == "0" and r["initial_conditions"] == "2" for r in summary.values())
    frames = read_csv(tmp_path / "evaluate_frames.csv")
    assert len(frames) == 2 * 3 * 2 * 10  # references x metrics x initial conditions x frames
    for engine in ("model", "lagrangian", "mujoco"):
        assert Trajectory.load(tmp_path / f"chain4_{engine}.npz").q.shape == (11, 5, 2)


def test_a_registered_metric_appears_in_the_evaluate_summary(capsys, tmp_path, monkeypatch):
    """A metric registered with `lgnn.metrics.register_metric` (here the absolute
    energy error, in joules) is scored by `lgnn evaluate` against each reference, in the
    terminal summary with its unit and in the CSV files, with no other edit."""
    from lgnn import metrics

    absolute = metrics.Metric("absolute_energy_error", lambda scene, predicted, reference: np.abs(predicted.energy - reference.energy), "J",
                              "Absolute energy error", "Absolute energy error", maximum_fn=lambda scene, q0: 1e6)
    monkeypatch.setitem(metrics.METRICS, absolute.name, absolute)
    checkpoint = _cheat_checkpoint(tmp_path)
    code, out, err = run(capsys, "evaluate", "chain4", "--model", str(checkpoint), "--duration", "0.01", "--initial-conditions", "1",
                         "--out-dir", str(tmp_path), "--quiet")
    assert code == 0, err
    assert "absolute_energy_error (J)" in out
    summary = {(r["reference"], r["metric"]): r for r in read_csv(tmp_path / "evaluate_summary.csv")}
    assert summary["lagrangian", "absolute_energy_error"]["unit"] == "J"
    assert float(summary["lagrangian", "absolute_energy_error"]["gmean"]) < 1e-9
    assert ("mujoco", "absolute_energy_error") in summary
    assert {r["metric"] for r in read_csv(tmp_path / "evaluate_frames.csv")} == set(metrics.METRICS)


def test_evaluate_and_compare_create_their_output_folder_only_once_they_succeed(tmp_path, capsys):
    """A folder that does not exist yet is made, with its parents, once the scores are
    in; a command that fails leaves none; a folder under a file is refused in one line."""
    checkpoint, out = _cheat_checkpoint(tmp_path), tmp_path / "new" / "eval"
    code, _, err = run(capsys, "evaluate", "chain4", "--model", str(checkpoint), "--duration", "0.01", "--out-dir", str(out), "--quiet")
    assert code == 0, err
    assert (out / "evaluate_summary.md").is_file() and (out / "chain4_model.npz").is_file()
    failed = tmp_path / "never"
    code, _, err = run(capsys, "evaluate", "chain4", str(tmp_path / "missing.json"), "--model", str(checkpoint), "--duration", "0.01",
                       "--out-dir", str(failed), "--quiet")
    assert code != 0 and not failed.exists() and err.count("\n") == 1, err
    (tmp_path / "file").write_text("")
    code, _, err = run(capsys, "compare", str(out / "chain4_lagrangian.npz"), str(out / "chain4_model.npz"), "--out-dir", str(tmp_path / "file" / "x"))
    assert code == 2 and "is not a directory" in err, err
    code, _, err = run(capsys, "compare", str(out / "chain4_lagrangian.npz"), str(out / "chain4_model.npz"), "--out-dir", str(tmp_path / "cmp" / "x"))
    assert code == 0 and (tmp_path / "cmp" / "x" / "compare_summary.md").is_file(), err


def test_the_frame_table_is_one_row_per_frame_metric_and_initial_condition_from_divergence_on_flagged(tmp_path):
    """`frame_csv` (written by hand, for speed) as pandas reads it: every column, the
    values at 6 significant digits, the divergence flag from the diverged frame on, and
    a scene name with a comma quoted."""
    import pandas as pd

    from lgnn.metrics import METRICS, Scored

    rng = np.random.default_rng(0)
    t = np.arange(1, 6) * 0.1
    errors = {metric: rng.random((3, 5)) * 1e-3 for metric in METRICS}
    scored = [Scored("rope, long", "my-model", "lagrangian", t, errors, np.array([-1, 2, 5]))]
    (tmp_path / "frames.csv").write_text(evaluation.frame_csv(scored))
    table = pd.read_csv(tmp_path / "frames.csv")
    assert tuple(table.columns) == evaluation.FRAME_COLUMNS and len(table) == len(METRICS) * 3 * 5
    assert set(table["scene"]) == {"rope, long"} and set(table["metric"]) == set(METRICS)
    first = table[table["metric"] == "rollout_error"]
    np.testing.assert_allclose(first["value"], errors["rollout_error"].ravel(), rtol=1e-5)
    np.testing.assert_allclose(first["t"], np.tile(t, 3))
    # Initial condition 1 diverged at frame 2 (t = 0.2), 2 at its last frame, 0 never.
    assert first["diverged"].tolist() == [False] * 5 + [False, True, True, True, True] + [False] * 4 + [True]
    assert set(table["unit"][table["metric"] == "node_rms_error"]) == {METRICS["node_rms_error"].unit}
