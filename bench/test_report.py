"""The report's reading of records (`lgnn.bench.report`): the rest baseline and the
per-node RMS error beside the paper's metric, the ratio to the chaos floor, no floor
where the perturbed run diverged, and "not computed" (never a number) for a record
written before a metric existed, as the committed full-profile records were."""

from pathlib import Path

import numpy as np

from lgnn.bench import grid, report
from lgnn.bench.stages import evaluate

ROOT = Path(__file__).resolve().parents[1]
T = np.array([0.01, 0.02])
JOB = grid.TrainingJob("lgnn", grid.TRAINING_SCENE, 0)


def _metric(prefix: str, per_ic: list[float]) -> dict:
    """A metric's arrays with per-IC geometric means `per_ic` (flat over frames)."""
    logs = np.log(per_ic)
    gmean = np.full(len(T), np.exp(logs.mean()))
    return {f"{prefix}/per_ic_log": logs, f"{prefix}/gmean": gmean, f"{prefix}/low": gmean, f"{prefix}/high": gmean}


def _truth(new_arrays: bool, floor_diverged: bool) -> tuple[dict, dict]:
    arrays = {"t": T, **_metric("chaos_floor", [1e-5, 1e-5]), **_metric("truth_vs_mujoco", [1e-12, 1e-12]),
              "chaos_floor/diverged_at": np.array([np.nan, 0.5 if floor_diverged else np.nan])}
    if new_arrays:
        arrays.update(_metric("chaos_floor/node_rms_error", [2e-4, 2e-4]))
        for metric in evaluate.METRICS:
            arrays.update(_metric(f"{evaluate.REST}/{metric}", [3e-2, 3e-2]))
        arrays[f"{evaluate.REST}/diverged_at"] = np.full(2, np.nan)
    return arrays, {}


def _pair(scene: str, new_arrays: bool):
    metrics = evaluate.METRICS if new_arrays else tuple(m for m in evaluate.METRICS if m != "node_rms_error")
    arrays = {"t": T, "diverged_at": np.full(2, np.nan)}
    for metric in metrics:
        arrays.update(_metric(metric, [1e-3, 1e-3]))
    return grid.Pair(JOB, scene), (arrays, {})


def _row(table: str, scene: str) -> dict:
    lines = [line for line in table.splitlines() if line.startswith("| ")]
    head = [c.strip() for c in lines[0].strip("|").split("|")]
    for line in lines[1:]:
        cells = [c.strip() for c in line.strip("|").split("|")]
        if cells[0] == scene:
            return dict(zip(head, cells))
    raise AssertionError(f"no row {scene}")


def test_rest_rms_error_and_its_ratio_to_the_chaos_floor():
    truths = {"chain4": _truth(True, False), "chain8": _truth(True, True)}
    summary, curves = report.tables(truths, [_pair("chain4", True), _pair("chain8", True)])
    rms = report.summary_markdown(summary, "node_rms_error")
    chain4 = _row(rms, "chain4")
    # The model's 1e-3 against the floor's 2e-4; the rest baseline's 3e-2.
    assert chain4["lgnn"] == "1.00e-03 [1.00e-03, 1.00e-03], 5x floor" and chain4["chaos floor"] == "2.00e-04"
    assert chain4["rest"] == "3.00e-02 [3.00e-02, 3.00e-02], 150x floor"
    ratio = summary[(summary.statistic == "chaos_floor_ratio") & (summary.scene == "chain4") & (summary.model == "lgnn")]
    assert np.isclose(ratio.value.item(), 5.0)
    for metric in ("rollout_error", "energy_error", "rollout_error_vs_mujoco"):
        assert _row(report.summary_markdown(summary, metric), "chain4")["rest"] == "3.00e-02 [3.00e-02, 3.00e-02]"


def test_no_chaos_floor_number_where_a_perturbed_run_diverged():
    truths = {"chain8": _truth(True, True)}
    summary, curves = report.tables(truths, [_pair("chain8", True)])
    floor = summary[(summary.scene == "chain8") & summary.metric.isin([report.FLOOR, report.FLOOR_RMS])]
    assert set(floor.statistic) == {"initial_conditions", "diverged", "first_divergence_s"}, "no value, no interval"
    assert (curves.metric == "rollout_error").any() and not curves.metric.isin([report.FLOOR, report.FLOOR_RMS]).any()
    assert not (summary.statistic == "chaos_floor_ratio").any()
    for metric, column in (("rollout_error", "chaos floor"), ("node_rms_error", "chaos floor"), ("rollout_error_vs_mujoco", "chaos floor")):
        row = _row(report.summary_markdown(summary, metric), "chain8")
        assert row[column] == "diverged (1 of 2 perturbed runs, first at 0.5 s)"
    assert _row(report.summary_markdown(summary, "node_rms_error"), "chain8")["lgnn"] == "1.00e-03 [1.00e-03, 1.00e-03]"


def test_records_without_the_new_metrics_read_not_computed():
    summary, _ = report.tables({"chain4": _truth(False, False)}, [_pair("chain4", False)])
    row = _row(report.summary_markdown(summary, "node_rms_error"), "chain4")
    assert row["lgnn"] == row["rest"] == row["chaos floor"] == "not computed"
    row = _row(report.summary_markdown(summary, "rollout_error"), "chain4")
    assert row["lgnn"].startswith("1.00e-03 [") and row["rest"] == "not computed" and row["chaos floor"] == "1.00e-05"


def test_the_committed_full_records_render_with_the_new_columns_not_computed():
    profile, out = grid.PROFILES["full"], ROOT / "results"
    summary, _ = report.tables(evaluate.load_truths(profile, out), evaluate.load_pairs(profile, out))
    for metric in report.TRUTH_COLUMNS:
        table = report.summary_markdown(summary, metric)
        assert "nan" not in table.lower()
        for scene in grid.evaluation_scenes(profile):
            row = _row(table, scene)
            assert row["rest"] in ("not computed", "") or "e-" in row["rest"]
    # Committed numbers are read as before: LGNN on chain4, and T2's diverged floor.
    row = _row(report.summary_markdown(summary, "rollout_error"), "chain4")
    assert row["lgnn"].startswith("5.09e-05") and row["chaos floor"] == "1.10e-05"
    assert _row(report.summary_markdown(summary, "rollout_error"), "T2")["chaos floor"].startswith("diverged (1 of 1")


def test_error_figures_label_their_axes_legend_every_panel_and_title_what_they_show(monkeypatch, tmp_path):
    """Each row has a y-axis label, every panel with lines its own legend (panels may
    hold different models), the title names the scenes drawn (not those asked for)
    and says what an error of 1 means."""
    import matplotlib

    matplotlib.use("Agg")
    import pandas as pd

    rows = [dict(scene=scene, model=model, seed=0, metric=metric, statistic=stat, t=t, value=1e-3)
            for scene, model in (("chain4", "lgnn"), ("chain4-drag", "lgnn drag"))
            for metric in ("rollout_error", "energy_error") for stat in ("gmean", "low", "high") for t in (0.1, 0.2)]
    figures = []
    monkeypatch.setattr(report, "_savefig", lambda fig, path: figures.append(fig))
    assert report._plot_error_vs_time(pd.DataFrame(rows), ["chain4", "chain8", "chain4-drag"], tmp_path / "x.png", "each")
    (fig,) = figures
    axes = fig.get_axes()
    assert len(axes) == 4 and all(ax.get_legend() is not None for ax in axes)
    assert [ax.get_ylabel() for ax in axes if ax.get_ylabel()] == list(report.ERROR_AXIS_LABELS.values())
    title = fig._suptitle.get_text()
    assert "chain4, chain4-drag" in title and "chain8" not in title and "1 means diverged" in title
