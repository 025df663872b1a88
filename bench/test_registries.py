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
    "max_node_error", lambda q, energy, ref_q, ref_energy: np.max(np.linalg.norm(np.asarray(q) - ref_q, axis=-1), axis=-1), "m",
    "Largest node error against the Lagrangian ground truth", "Largest node error", "largest node error (geometric mean)",
    maximum_fn=metrics.diverged_node_error, floor=True)
# A reference engine of the test's own: the Lagrangian engine under another name.
TWIN = "lagrangian-twin"


@pytest.fixture
def registered(monkeypatch):
    monkeypatch.setitem(metrics.METRICS, MAX_NODE_ERROR.name, MAX_NODE_ERROR)
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
                                                                     f"rollout_error_vs_{TWIN}"}


def test_an_unknown_reference_engine_is_refused_in_one_line_when_the_profile_loads():
    from lgnn.errors import ConfigError

    with pytest.raises(ConfigError, match=r"^evaluate.references: unknown engine 'nope' \(choose from lagrangian, mujoco") as error:
        profiles.load_profile("quick", ['evaluate.references=["mujoco", "nope"]'])
    assert "\n" not in str(error.value)
    assert profiles.load_profile("quick", ['evaluate.references=["mjx"]']).evaluate.references == ("mjx",)
