"""The report's reading of records (`lgnn.bench.report`): the rest baseline and the
per-node RMS error beside the paper's metric, the ratio to the chaos floor, no floor
where the perturbed run diverged, and "not computed" (never a number) for a record
written before a metric existed, as the committed full-profile records were; each
model's colour and column, figure groups from the grid, one line per seed, and a
registered stage's section."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from lgnn.bench import grid, profiles

from lgnn.bench.report import figures as report_figures, performance as report_performance, readme as report_readme, summary as report_summary
from lgnn.bench.stages import evaluate
from lgnn.bench.stages import truth as truth_stage
from lgnn.bench.stages import train as train_stage
from lgnn.errors import ConfigError

# What records of the default settings hold: rollout_error, node_rms_error, energy_error,
# rollout_error_vs_mujoco.
RECORDED = tuple(m.name for m in evaluate.recorded_metrics(report_summary.DEFAULT_REFERENCES))

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
        for metric in RECORDED:
            arrays.update(_metric(f"{evaluate.REST}/{metric}", [3e-2, 3e-2]))
        arrays[f"{evaluate.REST}/diverged_at"] = np.full(2, np.nan)
    return arrays, {}


def _pair(scene: str, new_arrays: bool, job: grid.TrainingJob = JOB, projected: bool = True):
    metrics = RECORDED if new_arrays else tuple(m for m in RECORDED if m != "node_rms_error")
    arrays = {"t": T, "diverged_at": np.full(2, np.nan)}
    for metric in metrics:
        arrays.update(_metric(metric, [1e-3, 1e-3]))
    return grid.Pair(job, scene, projected), (arrays, {})


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
    summary, curves = report_summary.tables(truths, [_pair("chain4", True), _pair("chain8", True)])
    rms = report_summary.summary_markdown(summary, "node_rms_error")
    chain4 = _row(rms, "chain4")
    # The model's 1e-3 against the floor's 2e-4; the rest baseline's 3e-2.
    assert chain4["lgnn"] == "1.00e-03 [1.00e-03, 1.00e-03] (1 seed), 5x floor" and chain4["chaos floor"] == "2.00e-04"
    assert chain4["rest"] == "3.00e-02 [3.00e-02, 3.00e-02], 150x floor"
    ratio = summary[(summary.statistic == "chaos_floor_ratio") & (summary.scene == "chain4") & (summary.model == "lgnn")]
    assert np.isclose(ratio.value.item(), 5.0)
    for metric in ("rollout_error", "energy_error", "rollout_error_vs_mujoco"):
        assert _row(report_summary.summary_markdown(summary, metric), "chain4")["rest"] == "3.00e-02 [3.00e-02, 3.00e-02]"


def test_no_chaos_floor_number_where_a_perturbed_run_diverged():
    truths = {"chain8": _truth(True, True)}
    summary, curves = report_summary.tables(truths, [_pair("chain8", True)])
    floor = summary[(summary.scene == "chain8") & summary.metric.isin(["chaos_floor", "chaos_floor_node_rms_error"])]
    assert set(floor.statistic) == {"initial_conditions", "diverged", "first_divergence_s"}, "no value, no interval"
    assert (curves.metric == "rollout_error").any() and not curves.metric.isin(["chaos_floor", "chaos_floor_node_rms_error"]).any()
    assert not (summary.statistic == "chaos_floor_ratio").any()
    for metric, column in (("rollout_error", "chaos floor"), ("node_rms_error", "chaos floor"), ("rollout_error_vs_mujoco", "chaos floor")):
        row = _row(report_summary.summary_markdown(summary, metric), "chain8")
        assert row[column] == "diverged (1 of 2 perturbed runs, first at 0.5 s)"
    assert _row(report_summary.summary_markdown(summary, "node_rms_error"), "chain8")["lgnn"] == "1.00e-03 [1.00e-03, 1.00e-03] (1 seed)"


def test_records_without_the_new_metrics_read_not_computed():
    summary, _ = report_summary.tables({"chain4": _truth(False, False)}, [_pair("chain4", False)])
    row = _row(report_summary.summary_markdown(summary, "node_rms_error"), "chain4")
    assert row["lgnn"] == row["rest"] == row["chaos floor"] == "not computed"
    row = _row(report_summary.summary_markdown(summary, "rollout_error"), "chain4")
    assert row["lgnn"].startswith("1.00e-03 [") and row["rest"] == "not computed" and row["chaos floor"] == "1.00e-05"


def test_the_committed_full_records_render_with_the_new_columns_not_computed():
    # Three scenes of the committed run (all of it takes minutes of CI to summarise):
    # the training scene, a stand-in for T2, and the spatial grid's training scene.
    profile = dataclasses.replace(profiles.PROFILES["full"], scenes=("chain4", "T2-slack", grid.SPATIAL_TRAINING_SCENE))
    out = ROOT / "results"
    truths = evaluate.load_truths(profile, out)
    summary, _ = report_summary.tables(truths, evaluate.load_pairs(profile, out))
    for metric in RECORDED:
        table = report_summary.summary_markdown(summary, metric)
        assert "nan" not in table.lower()
        for scene in truths:
            row = _row(table, scene)
            assert row["rest"] in ("not computed", "") or "e-" in row["rest"]
    # Committed numbers are read as results/README.md shows them: LGNN on chain4 and
    # T2-slack, over its three seeds.
    table = report_summary.summary_markdown(summary, "rollout_error")
    row = _row(table, "chain4")
    assert row["lgnn"].startswith("2.05e-05 [1.66e-05, 2.58e-05] (3 seeds)") and row["chaos floor"] == "1.10e-05"
    assert _row(table, "T2-slack")["lgnn"].startswith("4.21e-04")


def test_figures_drawn_in_processes_of_their_own_are_the_files_drawn_in_turn(tmp_path):
    """The full report draws its figures in spawned processes (`figures._drawn`): the
    same bytes as drawn in this process, each figure's name and whether it drew in
    order, a plot with nothing to draw saying so from its process too."""
    import pandas as pd

    curves = pd.DataFrame([dict(scene=scene, model=model, seed=0, metric=metric, statistic=stat, t=t, value=value * t)
                           for scene, model, value in (("chain4", "lgnn", 1e-3), ("chain4", "gns", 1e-2), ("chain8", "lgnn", 3e-3))
                           for metric in ("rollout_error", "energy_error", "node_rms_error") for stat in ("gmean", "low", "high")
                           for t in (0.1, 0.2, 0.3)])
    plots = [(f"error_{k}.png", report_figures._plot_error_vs_time, dict(curves=curves, scenes=scenes, trained_on="chain4"))
             for k, scenes in enumerate((["chain4"], ["chain4", "chain8"]))]
    plots.append(("speed_error.png", report_figures._plot_speed_error, dict(rows=[])))
    in_turn, in_processes = tmp_path / "in-turn", tmp_path / "in-processes"
    assert report_figures._drawn(plots, in_turn, parallel=False) == [True, True, False]
    assert report_figures._drawn(plots, in_processes, parallel=True) == [True, True, False]
    assert sorted(p.name for p in in_processes.iterdir()) == ["error_0.png", "error_1.png"]
    for name in ("error_0.png", "error_1.png"):
        assert (in_processes / name).read_bytes() == (in_turn / name).read_bytes(), name


def test_an_engine_the_figures_do_not_know_gets_a_marker_of_its_own():
    markers, offsets = report_figures.engine_markers(["mujoco", "my-engine", "lagrangian", "other"])
    assert {e: markers[e] for e in report_figures.ENGINE_MARKERS} == {e: m for e, (m, _) in report_figures.ENGINE_MARKERS.items()}
    assert markers["my-engine"] != markers["other"] and {markers["my-engine"], markers["other"]}.isdisjoint({"o", "s", "^"})
    assert set(offsets) == set(markers)


def test_error_figures_label_their_axes_legend_every_model_and_title_what_they_show(monkeypatch, tmp_path):
    """Each row has a y-axis label, one legend beside the panels names every model any
    panel draws (panels may hold different models), once each, an unprojected rollout
    dashed in its model's colour; the title names the scenes drawn (not those asked
    for) and says what an error of 1 means."""
    import matplotlib

    matplotlib.use("Agg")
    import pandas as pd

    rows = [dict(scene=scene, model=model, seed=0, metric=metric, statistic=stat, t=t, value=1e-3)
            for scene, model in (("chain4", "lgnn"), ("chain4", "gns"), ("chain4", "gns (unprojected)"), ("chain4-drag", "lgnn drag"))
            for metric in ("rollout_error", "energy_error") for stat in ("gmean", "low", "high") for t in (0.1, 0.2)]
    figures = []
    monkeypatch.setattr(report_figures, "_savefig", lambda fig, path: figures.append(fig))
    assert report_figures._plot_error_vs_time(pd.DataFrame(rows), ["chain4", "chain8", "chain4-drag"], tmp_path / "x.png", "each")
    (fig,) = figures
    axes = fig.get_axes()
    assert len(axes) == 4 and all(ax.get_legend() is None for ax in axes)
    (legend,) = fig.legends
    assert [text.get_text() for text in legend.get_texts()] == ["LGNN", "GNS", "gns (unprojected)", "lgnn drag"]
    lines = {line.get_label(): line for line in axes[0].get_lines()}
    assert lines["gns (unprojected)"].get_color() == lines["GNS"].get_color() and lines["gns (unprojected)"].get_linestyle() == "--"
    assert [ax.get_ylabel() for ax in axes if ax.get_ylabel()] == list(report_figures.error_axis_labels().values())
    title = fig._suptitle.get_text()
    assert "chain4, chain4-drag" in title and "chain8" not in title and "1 means diverged" in title


def test_several_seeds_give_one_cell_over_seeds_and_initial_conditions():
    """Two seeds (errors 1e-3 and 1e-4 on every IC): the cell is their geometric mean
    over seeds and ICs, 3.16e-4, with an interval spanning the seeds; one seed alone
    would be a zero-width interval. Each seed keeps its own rows in the CSV."""
    pairs = []
    for seed, value in ((0, 1e-3), (1, 1e-4)):
        arrays = {"t": T, "diverged_at": np.array([np.nan, 0.5 if seed else np.nan])}
        for metric in RECORDED:
            arrays.update(_metric(metric, [value, value]))
        pairs.append((grid.Pair(grid.TrainingJob("lgnn", grid.TRAINING_SCENE, seed), "chain4"), (arrays, {})))
    summary, _ = report_summary.tables({"chain4": _truth(True, False)}, pairs)
    cell = _row(report_summary.summary_markdown(summary, "rollout_error"), "chain4")["lgnn"]
    assert cell.startswith("3.16e-04 [1.00e-04, 1.00e-03] (1 diverged, first at 0.5 s) (2 seeds)"), cell
    assert set(summary[summary.model == "lgnn"].seed) == {0, 1, report_summary.ALL_SEEDS}


def test_missing_pairs_say_not_evaluated_and_unconverged_references_not_rankable():
    """A grid pair with no record is "not evaluated" (an empty cell is a pair the grid
    does not hold); a scene whose reference does not converge in dt (the convergence
    table's verdict) is named "(not rankable)" and shows no model number, one that
    converges is not."""
    from lgnn.bench import convergence

    arrays = {"t": T, "diverged_at": np.array([np.nan, np.nan])}
    for metric in RECORDED:
        arrays.update(_metric(metric, [1e-3, 1e-3]))
    pairs = [(grid.Pair(grid.TrainingJob("lgnn", grid.TRAINING_SCENE, 0), "chain4"), (arrays, {}))]
    pairs.append((grid.Pair(grid.TrainingJob("lgnn", grid.TRAINING_SCENE, 0), "T3"), (arrays, {})))
    summary, _ = report_summary.tables({"chain4": _truth(True, False), "T3": _truth(True, False)}, pairs)
    rows = [dict(scene="T3", note="singular at rest", verdict="not-converged", displacement="0.05"),
            dict(scene="T3", note="", verdict="", displacement="0.05"),
            dict(scene="T3-slack", note="", verdict="asymptotic", displacement="0.047")]
    unrankable = convergence.unrankable(rows)
    assert list(unrankable) == ["T3"] and "unknown" in unrankable["T3"]
    table = report_summary.summary_markdown(summary, "rollout_error", {("T3", "lgnn"), ("chain4", "lgnn")}, unrankable)
    assert _row(table, "T3 (not rankable)")["lgnn"] == "not rankable"
    assert _row(table, "T3 (not rankable)")["rest"] == "not rankable"
    assert _row(table, "chain4")["lgnn"].startswith("1.00e-03")
    assert _row(report_summary.summary_markdown(summary, "rollout_error"), "T3")["lgnn"].startswith("1.00e-03")
    without = summary[(summary.scene != "T3") | (summary.model != "lgnn")]
    assert _row(report_summary.summary_markdown(without, "rollout_error", {("T3", "lgnn")}), "T3")["lgnn"] == "not evaluated"
    # A scene of the grid with no record at all is a row of its own, not left out.
    table = report_summary.summary_markdown(summary, "rollout_error", {("chain8", "lgnn")}, None, ["chain4", "chain8"])
    assert _row(table, "chain8")["lgnn"] == "not evaluated"


def test_training_table_says_why_each_run_stopped():
    """Epoch budget, plateau (no 1 % gain in `patience` epochs), or cut off and resumable."""
    from lgnn.learn import protocol

    config = protocol.TrainConfig(learning_rate=1e-3, warmup_steps=1, epochs=100, patience=10, min_improvement=0.01)

    def state(losses):
        history = [(k + 1, 0.0, v, 0.0) for k, v in enumerate(losses)]
        best = int(np.argmin(losses))
        return protocol.TrainState({}, (), {}, float(losses[best]), best + 1, len(losses), history)

    assert report_readme._stopped_by(state(list(np.geomspace(1, 1e-3, 100))), config) == "epoch budget"
    assert report_readme._stopped_by(state([1.0, 0.5] + [0.499] * 20), config) == "plateau (best improved by under 1% in epochs 12-22)"
    assert report_readme._stopped_by(state([1.0, 0.5, 0.4]), config) == "not finished: cut off, resumable"


def test_runs_the_protocols_rules_did_not_end_are_named_at_the_top(tmp_path):
    """A checkpoint whose run stopped short of the epoch budget and the plateau rule (a
    wall-clock cap it was trained under, an interrupted job) is named in the report's
    opening warning, by model and training scene; one that ended is not."""
    import dataclasses

    from lgnn.bench import store
    from lgnn.learn import models, train
    from lgnn.scene import get_scene

    profile = dataclasses.replace(profiles.PROFILES["full"], seeds=(0,), models=("lgnn", "gns"), tracks=("paper",))
    for model_name, epochs in (("lgnn", 3), ("gns", profile.training.train.epochs)):
        job = grid.TrainingJob(model_name, grid.TRAINING_SCENE, 0)
        model, config = models.ModelConfig.for_scene(model_name, get_scene(job.scene)), profile.training.train
        path = store.Layout(tmp_path).checkpoint(job)
        path.parent.mkdir(parents=True, exist_ok=True)
        history = [(k + 1, 1.0, 1.0 / (k + 1), 0.0) for k in range(3)]
        state = train.initial_state(model, config)._replace(best_val=1 / 3, epoch=epochs, best_epoch=3, history=history)
        train.save_checkpoint(path, state, model, config)
    (line, _) = report_readme._cut_off_lines(profile, train_stage.load_checkpoints(profile, tmp_path))
    assert line.startswith("**Training cut off.**") and "lgnn (chain4; 1 run)" in line and "gns (" not in line
    assert report_readme._cut_off_lines(dataclasses.replace(profile, models=("gns",)), train_stage.load_checkpoints(dataclasses.replace(profile, models=("gns",)), tmp_path)) == []


def test_default_lgnn_is_read_from_the_training_records(tmp_path):
    """Per training scene, the variant with the lowest geometric mean over seeds of the
    best validation MSE. Planar: mp1 (1e-3 and 1e-5, mean 1e-4) against lgnn's 2e-4; a
    variant missing a seed (mp2, best on its one seed) is not a candidate. 3D (chain4-3d):
    lgnn (1e-2) against the notebook variant, whose one stalled seed (1e3) outweighs its
    best one (1e-3: mean 1); the 3D records do not enter the planar choice."""
    import dataclasses

    from lgnn.bench import store
    from lgnn.learn import models, train
    from lgnn.scene import get_scene

    profile = dataclasses.replace(profiles.PROFILES["full"], seeds=(0, 1), models=grid.LGNN_VARIANTS)
    spatial = grid.TRAINING_SCENES[3]
    best = {("lgnn", grid.TRAINING_SCENE, 0): 2e-4, ("lgnn", grid.TRAINING_SCENE, 1): 2e-4, ("lgnn-mp1", grid.TRAINING_SCENE, 0): 1e-3,
            ("lgnn-mp1", grid.TRAINING_SCENE, 1): 1e-5, ("lgnn-mp2", grid.TRAINING_SCENE, 0): 1e-6,
            ("lgnn", spatial, 0): 1e-2, ("lgnn", spatial, 1): 1e-2, ("lgnn-notebook", spatial, 0): 1e3, ("lgnn-notebook", spatial, 1): 1e-3}
    for (variant, scene, seed), value in best.items():
        job = grid.TrainingJob(variant, scene, seed)
        model, config = models.ModelConfig.for_scene(variant, get_scene(job.scene)), profile.training.train
        path = store.Layout(tmp_path).checkpoint(job)
        path.parent.mkdir(parents=True, exist_ok=True)
        train.save_checkpoint(path, train.initial_state(model, config)._replace(best_val=value, epoch=1, best_epoch=1), model, config)
    chosen, scores = train_stage.default_lgnn(profile, tmp_path)
    assert chosen == "lgnn-mp1" and set(scores) == {"lgnn", "lgnn-mp1"}
    assert np.isclose(scores["lgnn-mp1"], 1e-4) and np.isclose(scores["lgnn"], 2e-4)
    chosen, scores = train_stage.default_lgnn(profile, tmp_path, spatial)
    assert chosen == "lgnn" and set(scores) == {"lgnn", "lgnn-notebook"}
    assert np.isclose(scores["lgnn"], 1e-2) and np.isclose(scores["lgnn-notebook"], 1.0)
    lines = report_readme._training_lines(profile, tmp_path, train_stage.load_checkpoints(profile, tmp_path))
    assert any("Default LGNN (trained on chain4" in line and "**lgnn-mp1**" in line for line in lines)
    assert any("Default LGNN in 3D (trained on chain4-3d" in line and "**lgnn**" in line for line in lines)


def test_a_drag_scene_record_scores_the_exact_physics_without_drag(tmp_path):
    """chain4-drag's ground-truth record holds the drag-free exact physics from the
    same initial conditions, scored as a model: recomputed here from `simulate` and the
    metric's formula; drag makes it differ from the truth; the report shows the row."""
    import dataclasses

    from lgnn.bench import store
    from lgnn.engines.lagrangian import simulate
    from lgnn.scene import State, get_scene

    quick = profiles.PROFILES["quick"]
    profile = dataclasses.replace(quick, evaluate=dataclasses.replace(quick.evaluate, initial_conditions=2, duration=0.02, chunk=2))
    arrays, meta = store.load(evaluate.evaluate_scene(profile, "chain4-drag", tmp_path, progress=False))
    scene, truth = get_scene("chain4-drag"), truth_stage.ground_truth(profile, "chain4-drag", False)
    config = profile.evaluate.simulation("chain4-drag")
    for c in range(2):
        q = simulate(scene.replace(drag=0.0), config, State(truth.states.q[c], truth.states.qd[c])).q[1:]
        reference = truth.truth.q[c, 1:]
        flat = lambda a: a.reshape(len(a), -1)  # noqa: E731
        errors = np.linalg.norm(flat(q - reference), axis=1) / (np.linalg.norm(flat(q), axis=1) + np.linalg.norm(flat(reference), axis=1))
        # (errors of 1e-12-1e-8 over 0.02 s: a vmapped and a single run agree to ~1e-6 of them)
        np.testing.assert_allclose(arrays[f"{evaluate.NO_DRAG}/rollout_error/per_ic_log"][c], np.mean(np.log(errors)), rtol=1e-7)
        assert errors.min() > 1e-12
    summary, _ = report_summary.tables({"chain4-drag": (arrays, meta)}, [])
    assert _row(report_summary.summary_markdown(summary, "rollout_error"), "chain4-drag")[report_summary.EXACT_NO_DRAG].startswith(
        f"{np.exp(arrays[f'{evaluate.NO_DRAG}/rollout_error/per_ic_log'].mean()):.2e}")


SPATIAL_JOB = grid.TrainingJob("gns", grid.SPATIAL_TRAINING_SCENE, 0)


def _section(text: str, heading: str) -> str:
    """The markdown under `## heading` up to the next heading."""
    start = text.index(f"## {heading}\n") + len(heading) + 4
    end = text.find("\n## ", start)
    return text[start:] if end < 0 else text[start:end]


def test_the_planar_and_spatial_grids_get_tables_of_their_own():
    """A planar model (LGNN on chain4) and a spatial one (GNS on chain4-3d, also
    unprojected): each grid's tables hold its scenes and its models only, headed by the
    grid and its training scene (the 3D columns drop the `(chain4-3d)` the heading
    names); a 3D pair of the grid without a record is "not evaluated" there."""
    import dataclasses

    profile = dataclasses.replace(profiles.PROFILES["quick"], train_scenes=None, scenes=None, models=None, grid=(
        grid.GridEntry("lgnn", grid.TRAINING_SCENE, ("chain4", "chain8")),
        grid.GridEntry("gns", grid.SPATIAL_TRAINING_SCENE, ("tensegrity-3d", "chain4-3d"), unprojected=True)))
    truths = {scene: _truth(True, False) for scene in ("chain4", "chain8", "chain4-3d", "tensegrity-3d")}
    pairs = [_pair("chain4", True), _pair("chain8", True), _pair("chain4-3d", True, SPATIAL_JOB),
             _pair("chain4-3d", True, SPATIAL_JOB, projected=False), _pair("tensegrity-3d", True, SPATIAL_JOB, projected=False)]
    summary, _ = report_summary.tables(truths, pairs)
    text = "\n".join(report_readme._summary_sections(profile, summary, {}))
    for metric, heading in report_summary.summary_tables():
        planar = _section(text, f"{heading} (planar: trained on chain4)")
        spatial = _section(text, f"{heading} (3D: trained on chain4-3d)")
        head = lambda table: table.strip().splitlines()[0].strip("|").split(" | ")  # noqa: E731
        truth_columns = [title for _, title in report_summary.truth_columns(metric)]
        assert [c.strip() for c in head(planar)] == ["scene", "lgnn", "rest", *truth_columns]
        assert [c.strip() for c in head(spatial)] == ["scene", "gns", "gns (unprojected)", "rest", *truth_columns]
        assert [_row(planar, s)["scene"] for s in ("chain4", "chain8")] and "3d" not in planar
        # Table order: the built-in grid's (chain4-3d before tensegrity-3d), not the entry's.
        assert [line.split(" | ")[0] for line in spatial.strip().splitlines()[2:]] == ["| chain4-3d", "| tensegrity-3d"]
        assert _row(spatial, "tensegrity-3d")["gns"] == "not evaluated"
        assert _row(spatial, "tensegrity-3d")["gns (unprojected)"].startswith("1.00e-03")


def test_a_3d_snapshot_figure_shows_each_model_and_mujoco_from_the_front_and_from_above(monkeypatch, tmp_path):
    """chain4-3d swinging out of the x-y plane: a row per model trained on chain4-3d,
    first seed (neither a planar model's record nor another seed is drawn), at every time a front
    (x-y) and a top (x-z) view that draw those coordinates, MuJoCo and the model in
    each panel's lines; the file is a PNG."""
    import dataclasses

    from lgnn.scene import get_scene

    scene = get_scene("chain4-3d")
    frames = np.arange(6)[:, None, None] * np.array([0.0, 0.0, 0.1])  # each frame 0.1 further along z
    truth_q = (np.asarray(scene.nodes) + frames).astype(np.float32)
    truths = {"chain4-3d": ({"snapshot/mujoco": truth_q, "snapshot/truth": truth_q}, {})}
    pairs = [(grid.Pair(SPATIAL_JOB, "chain4-3d"), ({"snapshot/model": truth_q + 0.05}, {})),
             (grid.Pair(grid.TrainingJob("lgn", grid.SPATIAL_TRAINING_SCENE, 0), "chain4-3d"), ({"snapshot/model": truth_q - 0.05}, {})),
             (grid.Pair(JOB, "chain4"), ({"snapshot/model": np.zeros((6, 5, 2))}, {})),
             (grid.Pair(dataclasses.replace(SPATIAL_JOB, seed=1), "chain4-3d"), ({"snapshot/model": truth_q}, {}))]
    figures = []
    save = report_figures._savefig
    monkeypatch.setattr(report_figures, "_savefig", lambda fig, path: (figures.append(fig), save(fig, path)))
    assert report_figures._plot_snapshots("chain4-3d", truths, pairs, tmp_path / "snapshots.png")
    assert (tmp_path / "snapshots.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    (fig,) = figures
    axes = np.array(fig.get_axes()).reshape(2, 10)
    assert [ax.get_title().split(", ")[1] for ax in axes[0, :2]] == ["front (x-y)", "top (x-z)"]
    last = axes[0, 8:]  # the last time (frame 5) of the GNS row, front and top
    assert [line.get_label() for line in last[0].get_lines() if not line.get_label().startswith("_")] == ["MuJoCo", "GNS"]
    front, top = (np.concatenate([line.get_ydata() for line in ax.get_lines()[:4]]) for ax in last)
    np.testing.assert_allclose(np.sort(front), np.sort(truth_q[5][np.asarray(scene.edges)][..., 1].ravel()))
    np.testing.assert_allclose(np.sort(top), np.sort(truth_q[5][np.asarray(scene.edges)][..., 2].ravel()))
    assert axes[1, 0].get_legend().get_texts()[1].get_text() == "LGN"
    assert "trained on chain4-3d, seed 0" in fig._suptitle.get_text()


def _speed_row(scene: str, solver: str, wall: float, dt: float = 1e-3, form: str = "", kind: str = "engine") -> dict:
    return dict(scene=scene, solver=solver, kind=kind, dt=dt, wall_s_per_sim_s=wall, rollout_error=1e-9, compile_s=1.0,
                horizon_s=0.1, note="", form=form)


def _size_row(solver: str, n: int, s_per_step: float, dim: int | None = None) -> dict:
    row = dict(kind="size", scene=f"chain{n}" + ("-3d" if dim == 3 else ""), n_links=n, solver=solver, batch=1,
               s_per_step=s_per_step, compile_s=1.0, note="")
    return row if dim is None else {**row, "dim": dim}


def test_performance_puts_each_3d_chain_beside_the_planar_one_and_their_ratio():
    profile = profiles.PROFILES["full"]
    rows = [_speed_row("chain4", "lagrangian", 0.05), _speed_row("chain4", "mujoco", 0.04, form="nested"),
            _speed_row("chain4-3d", "lagrangian", 0.2), _speed_row("chain4-3d", "mujoco", 0.1, form="nested"),
            # learned rows: the median over seeds, each dimension's own model (3D labels name their training scene)
            *(_speed_row("chain4", "lgnn", wall, kind="learned") for wall in (1.0, 2.0, 9.0)),
            *(_speed_row("chain4-3d", "lgnn (chain4-3d)", wall, kind="learned") for wall in (3.0, 4.0, 5.0)),
            # another step than the evaluation's is not compared
            _speed_row("chain4-3d", "lagrangian", 7.0, dt=1e-5)]
    scaling = {"rows": [_size_row("lagrangian", 4, 1e-5, 2), _size_row("lagrangian", 16, 4e-5, 2),
                        _size_row("lagrangian", 4, 3e-5, 3), _size_row("lagrangian", 16, 2.4e-4, 3)]}
    text = report_performance.performance_markdown(profile, rows, scaling)
    third = text[text.index("## The third dimension's cost"):]
    assert "| chain4, chain4-3d | lagrangian | 0.05 | 0.2 | 4 | — |" in third
    assert "| chain4, chain4-3d | mujoco | 0.04 | 0.1 | 2.5 | nested, nested |" in third
    assert "| chain4, chain4-3d | lgnn | 2 | 4 | 2 | — |" in third
    # The ground-truth table names MuJoCo C's form; the size table a row per dimension,
    # each with its own exponent (planar n^1, 3D n^1.5), and their ratio.
    assert _row(text, "chain4-3d")["MuJoCo C MJCF form"] == "nested"
    size = text[text.index("## Cost per step against chain length"):]
    assert "| lagrangian | planar | 1e-05 | 4e-05 | 1.00 (n = 4..16) | 1.0 |" in size
    assert "| lagrangian | 3D | 3e-05 | 0.00024 | 1.50 (n = 4..16) | 1.0 |" in size
    assert "| lagrangian | 3D / planar | 3 | 6 | — | — |" in size


def test_a_scaling_record_made_before_3d_rows_reads_as_planar_and_old_speed_rows_say_form_not_recorded():
    profile = profiles.PROFILES["full"]
    rows = [_speed_row("chain4", "lagrangian", 0.05), {**_speed_row("chain4", "mujoco", 0.04), "form": None}]
    del rows[1]["form"]
    text = report_performance.performance_markdown(profile, rows, {"rows": [_size_row("mujoco", 4, 1e-5), _size_row("mujoco", 16, 2e-5)]})
    assert _row(text, "chain4")["MuJoCo C MJCF form"] == "not recorded"
    # A 3D record timed elsewhere: its ratios say so, and the old record's form is not guessed.
    spatial = [{**_speed_row("chain4-3d", solver, wall, form="nested"), "device": "a GPU host"} for solver, wall in (("lagrangian", 0.1), ("mujoco", 0.08))]
    third = report_performance.performance_markdown(profile, rows + spatial)
    assert "| chain4, chain4-3d | mujoco | 0.04 | 0.08 | 2 (different machines) | not recorded, nested |" in third
    assert "| mujoco | planar | 1e-05 | 2e-05 |" in text
    assert "| mujoco | 3D |" not in text and "3D / planar" not in text and "## The third dimension" not in text


def test_a_registered_stage_is_run_and_reported(tmp_path, monkeypatch):
    """A stage added to the registry (`lgnn.bench.run.register_stage`) runs in registry
    order before the report, and its section and keyed settings are in README.md."""
    from lgnn.bench import run as bench_run

    @dataclasses.dataclass(frozen=True)
    class CountSettings:
        count: int = 3

    def count_scenes(request):
        (request.out / "count.txt").write_text(str(len(request.scenes)))

    monkeypatch.setattr(bench_run, "STAGES", dict(bench_run.STAGES))
    bench_run.register_stage(bench_run.Stage(
        "count", count_scenes, settings=lambda profile: CountSettings(),
        load=lambda profile, out: (out / "count.txt").read_text(),
        section=lambda profile, out, records: ["## Scenes counted", "", f"{records} evaluation scenes."]))
    assert list(bench_run.STAGES)[-2:] == ["count", "report"]
    with pytest.raises(ConfigError, match="benchmark stage 'count' is already registered"):
        bench_run.register_stage(bench_run.Stage("count", count_scenes))
    profile = profiles.get_profile("quick")
    bench_run.run(profile, tmp_path, stages=("count", "report"), progress=False)
    readme = (tmp_path / "README.md").read_text()
    assert f"## Scenes counted\n\n{len(profiles.evaluation_scenes(profile))} evaluation scenes." in readme
    assert "Settings of the count stage: `count` = 3." in readme
    assert readme.index("## Scenes counted") < readme.index("## Where each record was made")


def test_a_model_added_to_a_profiles_grid_gets_a_colour_and_place_of_its_own():
    """The built-ins keep their colours and order; each model a profile's grid adds gets
    the next colour no built-in has and a column after them, the same every time."""
    mine = (grid.GridEntry("mine", grid.TRAINING_SCENE, ("chain4",)), grid.GridEntry("yours", grid.TRAINING_SCENE, ("chain4",)))
    profile = dataclasses.replace(profiles.get_profile("quick"), grid=(*grid.GRID, *mine), models=None)
    order = profiles.model_order(profile)
    assert order[: len(report_summary.MODEL_ORDER)] == report_summary.MODEL_ORDER == ("lgnn", "lgnn-mp1", "lgnn-mp2", "lgnn-notebook", "gns", "lgn", "clnn",
                                                                       "gns-10-128", "cgnode", "chgn", "chnn")
    assert order[len(report_summary.MODEL_ORDER):] == ("mine", "yours")
    colors = report_figures.model_colors(order)
    assert {model: colors[model] for model in report_figures.COLORS} == report_figures.COLORS
    assert colors["mine"] not in report_figures.COLORS.values() and colors["yours"] not in report_figures.COLORS.values()
    assert colors["mine"] != colors["yours"] and report_figures.model_colors(order) == colors


def test_a_scene_no_declared_figure_draws_gets_one_from_the_grid():
    """A scene added to a profile's grid is drawn in an error figure named after it, its
    title naming the scene its models were trained on; the built-in groups are kept."""
    entry = grid.GridEntry("lgnn", grid.TRAINING_SCENE, ("chain4", "double-pinned"))
    figures = profiles.error_figures(dataclasses.replace(profiles.get_profile("quick"), grid=(entry,), scenes=None, models=None))
    assert figures[: len(grid.ERROR_FIGURES)] == list(grid.ERROR_FIGURES)
    assert figures[len(grid.ERROR_FIGURES):] == [grid.FigureGroup("error_vs_time_doublepinned.png", ("double-pinned",), grid.TRAINING_SCENE)]


def test_several_seeds_are_drawn_one_line_each(monkeypatch, tmp_path):
    """Each seed's curve is its own line running forward in time (never from t = 1 of
    one seed back to t = 0 of the next), labelled once, in the model's colour."""
    import matplotlib

    matplotlib.use("Agg")
    import pandas as pd

    rows = [dict(scene="chain4", model="lgnn", seed=seed, metric=metric, statistic=stat, t=t, value=1e-3 * (seed + 1))
            for seed in (0, 1, 2) for metric in ("rollout_error", "energy_error") for stat in ("gmean", "low", "high") for t in (0.1, 0.2, 0.3)]
    figures = []
    monkeypatch.setattr(report_figures, "_savefig", lambda fig, path: figures.append(fig))
    assert report_figures._plot_error_vs_time(pd.DataFrame(rows), ["chain4"], tmp_path / "x.png", "chain4")
    (fig,) = figures
    for ax in fig.get_axes():
        lines = ax.get_lines()
        assert len(lines) == 3 and all(np.all(np.diff(line.get_xdata()) > 0) for line in lines)
        assert {line.get_color() for line in lines} == {"C0"}
        assert ax.get_legend_handles_labels()[1] == ["LGNN"]


def test_the_settings_say_how_each_evaluated_scene_starts():
    """From each scene's initial-state policy: the rope (a pinned chain) is sampled, the
    net and the trusses keep their own state (the prose once said the rope did too)."""
    text = report_readme._initial_states_text(profiles.get_profile("full"))
    sampled, own = text.split("; their own state, one initial condition: ")
    assert "rope-3d" in sampled and "chain4-3d" in sampled
    assert own.split(", ") == ["T1", "T2-slack", "T3-slack", "net4x4-3d", "tensegrity-3d"]


def test_a_figure_the_report_no_longer_draws_is_removed_and_other_files_are_kept(tmp_path):
    """Figures of an earlier report that this one does not draw (here: no records at
    all) go; a file of another name under figures/ stays."""
    from lgnn.bench import run as bench_run

    figures = tmp_path / "figures"
    figures.mkdir()
    for name in ("error_vs_time_gone.png", "snapshots_gone.png", "mass_matrix.png", "my_own_plot.png", "notes.txt"):
        (figures / name).write_bytes(b"x")
    bench_run.run(profiles.get_profile("quick"), tmp_path, stages=("report",), progress=False)
    assert sorted(p.name for p in figures.iterdir()) == ["my_own_plot.png", "notes.txt"]
