"""What a researcher adds reaches the benchmark without other edits: a metric registered
with `lgnn.metrics.register_metric` is scored, recorded and given a table; an engine
registered in `lgnn.engines.ENGINES` and named in `evaluate.references` is run as a
reference and given its column and table. A tiny benchmark (chain4, the cheating
model: true accelerations, so no training; two initial conditions, 0.02 s)."""

import dataclasses

import numpy as np
import pytest

from lgnn import metrics, physics
from lgnn.bench import grid, profiles, store
from lgnn.bench.report import figures as report_figures, readme as report_readme, summary as report_summary
from lgnn.bench.stages import evaluate
from lgnn.engines import ENGINES
from lgnn.learn import models, protocol, train

# LagrangeBench's cheating model under a name of its own (one spec per name and process),
# with a parameter it does not use (the evaluate stage stacks a model's seeds' parameters).
CHEAT = models.ModelSpec("cheat-registries", lambda key, config: {"unused": np.zeros(1)}, acceleration=lambda config, params, scene: physics.true_acceleration_fn(scene))
# A metric of the test's own: the largest node distance, in lengths.
MAX_NODE_ERROR = metrics.Metric(
    "max_node_error", lambda scene, predicted, reference: np.max(np.linalg.norm(predicted.q - reference.q, axis=-1), axis=-1), "m",
    "Largest node error against the Lagrangian ground truth", "Largest node error", "largest node error (geometric mean)",
    maximum_fn=metrics.diverged_node_error, floor=True)


def _momentum(scene, trajectory) -> np.ndarray:
    """The structure's linear momentum (C, F, D): each uniform link's mass times the
    mean velocity of its two nodes."""
    ends = np.asarray(trajectory.qd)[..., np.asarray(scene.edge_index), :]  # (C, F, E, 2, D)
    return np.einsum("e,cfed->cfd", np.asarray(scene.masses), ends.mean(axis=-2))


# A metric that needs what positions and energies do not hold: velocities and masses.
MOMENTUM_ERROR = metrics.Metric(
    "momentum_error", lambda scene, predicted, reference: metrics.relative_error(_momentum(scene, predicted), _momentum(scene, reference), 1),
    "1", "Momentum error against the Lagrangian ground truth", "Momentum error", "momentum error (geometric mean)", against_references=True)
# A reference engine of the test's own: the Lagrangian engine under another name.
TWIN = "lagrangian-twin"


@pytest.fixture
def registered(monkeypatch):
    monkeypatch.setitem(metrics.METRICS, MAX_NODE_ERROR.name, MAX_NODE_ERROR)
    monkeypatch.setitem(metrics.METRICS, MOMENTUM_ERROR.name, MOMENTUM_ERROR)
    # Its own entry, so the report titles it by its own name, not the Lagrangian engine's.
    monkeypatch.setitem(ENGINES, TWIN, dataclasses.replace(ENGINES["lagrangian"], name=TWIN, title=TWIN))


def _tiny_benchmark(tmp_path):
    """A profile of one pair (the cheating model on chain4) against the twin engine,
    its checkpoint saved; `(profile, pair)`."""
    models.register(CHEAT)
    evaluate_settings = dataclasses.replace(profiles.PROFILES["quick"].evaluate, initial_conditions=2, duration=0.02, mujoco_dt=1e-3,
                                            references=(TWIN,))
    profile = dataclasses.replace(profiles.PROFILES["quick"], name="registries", evaluate=evaluate_settings, seeds=(0,), scenes=None,
                                  train_scenes=None, models=None, grid=(grid.GridEntry(CHEAT.name, "chain4", ("chain4",)),))
    (pair,) = profiles.evaluation_pairs(profile)
    config = models.ModelConfig(CHEAT.name)
    checkpoint = store.Layout(tmp_path).checkpoint(pair.job)
    checkpoint.parent.mkdir(parents=True)
    train.save_checkpoint(checkpoint, train.initial_state(config, protocol.TrainConfig()), config, protocol.TrainConfig())
    return profile, pair


def test_a_registered_metric_and_reference_engine_reach_records_and_report(registered, tmp_path):
    profile, pair = _tiny_benchmark(tmp_path)
    assert not evaluate.truth_recorded(profile, "chain4", tmp_path)
    evaluate.evaluate_scene(profile, "chain4", tmp_path, progress=False)
    assert evaluate.truth_recorded(profile, "chain4", tmp_path)  # what the truth stage skips
    evaluate.evaluate_pair(profile, pair, tmp_path, progress=False)
    truth, _ = evaluate.load_truth(profile, "chain4", tmp_path)
    arrays, _ = evaluate.load_pair(profile, pair, tmp_path)
    # Records: the new metric for the model, the rest baseline and the chaos floor; the
    # twin's scores where MuJoCo's were (no MuJoCo: only the references named run).
    assert arrays["max_node_error/per_ic_log"].shape == (2,) and truth["rest/max_node_error/per_ic_log"].shape == (2,)
    assert "chaos_floor/max_node_error/per_ic_log" in truth
    assert arrays[f"rollout_error_vs_{TWIN}/per_ic_log"].shape == (2,) and f"truth_vs_{TWIN}/per_ic_log" in truth
    assert not any("mujoco" in name for name in [*arrays, *truth])
    # The twin at dt 1e-3 (RK4, projected) is the ground truth's own integrator: it agrees.
    assert metrics.summarise(truth[f"truth_vs_{TWIN}/per_ic_log"])[0] < 1e-6
    # The report: a table of each, the twin a column beside the rollout error.
    summary, curves = report_summary.tables(*((evaluate.load_truths(profile, tmp_path), evaluate.load_pairs(profile, tmp_path))), profile.evaluate.references)
    text = "\n".join(report_readme._summary_sections(profile, summary, {}))
    assert "## Largest node error against the Lagrangian ground truth (planar" in text
    assert f"## Rollout error against {TWIN} (planar" in text
    rollout = report_summary.summary_markdown(summary, "rollout_error", references=profile.evaluate.references)
    assert rollout.splitlines()[0].split(" | ")[-1] == f"Lagrangian vs {TWIN} |"
    row = rollout.splitlines()[2].split(" | ")
    assert row[0] == "| chain4" and row[-1].endswith(" |") and "e-" in row[-1]
    largest = report_summary.summary_markdown(summary, "max_node_error", references=profile.evaluate.references)
    assert largest.splitlines()[0].split(" | ")[1:] == ["cheat-registries", "rest", "chaos floor |"]
    assert "largest node error (geometric mean)" in report_figures.error_axis_labels().values()
    assert set(curves[curves.model == "cheat-registries"].metric) == {"rollout_error", "node_rms_error", "energy_error", "max_node_error",
                                                                     "momentum_error", f"rollout_error_vs_{TWIN}", f"momentum_error_vs_{TWIN}"}


def test_a_momentum_error_registered_in_one_place_reaches_records_report_figure_and_cli(registered, tmp_path, capsys):
    """The metric contract gives a metric whole trajectories and the scene: a momentum
    error (velocities and masses) is scored against the ground truth and the twin
    engine's trajectories, recorded, tabled, drawn and printed by `lgnn evaluate`."""
    from lgnn.cli import main

    profile, pair = _tiny_benchmark(tmp_path)
    evaluate.evaluate_scene(profile, "chain4", tmp_path, progress=False)
    evaluate.evaluate_pair(profile, pair, tmp_path, progress=False)
    truth, _ = evaluate.load_truth(profile, "chain4", tmp_path)
    arrays, _ = evaluate.load_pair(profile, pair, tmp_path)
    # The cheating model is the ground truth's dynamics: the momentum agrees to round-off
    # against the truth and the twin (the same integrator); the rest baseline, released
    # with the chain's initial velocities held, does not.
    assert metrics.summarise(arrays["momentum_error/per_ic_log"])[0] < 1e-9
    assert metrics.summarise(arrays[f"momentum_error_vs_{TWIN}/per_ic_log"])[0] < 1e-6
    assert metrics.summarise(truth["rest/momentum_error/per_ic_log"])[0] > 1e-3
    assert f"truth_vs_{TWIN}/momentum_error/per_ic_log" in truth
    summary, _ = report_summary.tables(evaluate.load_truths(profile, tmp_path), evaluate.load_pairs(profile, tmp_path), profile.evaluate.references)
    text = "\n".join(report_readme._summary_sections(profile, summary, {}))
    assert "## Momentum error against the Lagrangian ground truth (planar" in text
    assert "momentum error (geometric mean)" in report_figures.error_axis_labels().values()
    checkpoint = store.Layout(tmp_path).checkpoint(pair.job)
    capsys.readouterr()
    code = main(["evaluate", "chain4", "--model", str(checkpoint), "--duration", "0.01", "--initial-conditions", "2",
                 "--out-dir", str(tmp_path / "cli"), "--quiet"])
    out = capsys.readouterr().out
    assert code == 0
    assert [line.split()[2] for line in out.splitlines() if "momentum_error (1)" in line] == ["lagrangian", "mujoco"]


def test_an_unknown_reference_engine_is_refused_in_one_line_when_the_profile_loads():
    from lgnn.errors import ConfigError

    with pytest.raises(ConfigError, match=r"^evaluate.references: unknown engine 'nope' \(choose from lagrangian, mujoco") as error:
        profiles.load_profile("quick", ['evaluate.references=["mujoco", "nope"]'])
    assert "\n" not in str(error.value)
    assert profiles.load_profile("quick", ['evaluate.references=["mjx"]']).evaluate.references == ("mjx",)
