"""The benchmark's summary statistics: the tidy tables of every record's metrics and
their markdown tables, from the records the stages wrote (`lgnn.bench.stages`), read
through their public `load_*` functions only (nothing is computed here but statistics
of them). The report (`lgnn.bench.report`) writes them with the figures and README.md.

Files under `<out>` (`results/` for the full profile, `lgnn-out/quick/` for the quick):

- `benchmark/summary.csv.gz`: `scene, model, seed, metric, statistic, value` plus
  `commit, versions, device` of the run that made each number. Models: the learned
  ones and `rest` (the rest baseline, from the ground-truth records); metrics: every
  metric of the registry `lgnn.metrics.METRICS` (`rollout_error`, `node_rms_error`,
  `energy_error`) and `<metric>_vs_<engine>` against each reference engine of
  `evaluate.references` (`rollout_error_vs_mujoco`: `evaluate.recorded_metrics`), and
  per scene the ground truth's `chaos_floor`, `chaos_floor_node_rms_error` and
  `truth_vs_<engine>`; each gets a table and its columns from the registry; statistics: `gmean` (over frames t > 0 and initial conditions),
  `ci_low`/`ci_high` (bootstrap 95% over initial conditions), `initial_conditions`,
  `diverged` (count), `first_divergence_s`, and for `node_rms_error`
  `chaos_floor_ratio`. A chaos floor whose perturbed run diverged has no `gmean` or
  interval; a record without a metric (written before it existed) has no row for it.
  A model trained with several seeds also has rows with `seed` -1 (`ALL_SEEDS`): the
  geometric mean over seeds and initial conditions with a two-level bootstrap interval
  (`lgnn.metrics.summarise_seeds`), `seeds`, and the summed divergences; the markdown
  tables show these. Gzipped, as the curves: its provenance columns repeat on every
  row (7.6 MB plain for the full profile, 0.2 MB gzipped); pandas reads it as is.
- `benchmark/curves.csv.gz`: the same metrics per frame (every `evaluate.CURVE_DT`, 0.01 s): geometric mean
  over initial conditions with a normal-approximation 95% band (`t` column); columns
  `scene, model, seed, metric, statistic, t, value`. Each curve's commit, versions and
  device are those of its `summary.csv.gz` rows (same scene, model, seed): repeated on
  each of 200 000 frames they made the file 56 MB. Gzipped (pandas reads it as is).
- `benchmark/speed_error.csv`, `.md`: wall time per simulated second against rollout
  error (`lgnn.bench.stages.speed`).
- `benchmark/mass_matrix.csv`: percentage errors of the learned mass matrix.
- `figures/*.png` (`lgnn.bench.report.figures`); `README.md` (`lgnn.bench.report.readme`): the summary
  tables and how each file was made.

pandas is imported by the report's modules only (the library's numerics do not need it).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from lgnn import metrics
from lgnn.bench import convergence
from lgnn.bench.grid import EXTERNAL, GRID, PAPER_TRACK, TRACKS, Pair
from lgnn.bench.profiles import EvaluateSettings
from lgnn.bench.stages.evaluate import FLOOR, NO_DRAG, TRUTH, curve_frames, recorded_metrics, scene_level_prefix, scene_level_scores, truth_against
from lgnn.bench.stages.evaluate import REST as REST_PREFIX
from lgnn.engines import ENGINES
from lgnn.scene import get_scene

# Column order of the built-in grid's models (a profile's own models follow: `profiles.model_order`).
MODEL_ORDER = tuple(dict.fromkeys(entry.model for entry in GRID))
# The rest baseline's model name in the tables (the initial state held).
REST = "rest"
# How tables mark predictions made outside lgnn (`grid.external_pair`): `my-sim (external)`.
EXTERNAL_MARK = f" ({EXTERNAL})"
# The drag scenes' exact physics without drag, as the tables name it.
EXACT_NO_DRAG = "exact, no drag"
# The reference engines the benchmark scores against unless its settings say otherwise.
DEFAULT_REFERENCES = EvaluateSettings.references
# The summary's and the per-frame curves' files under `benchmark/` (gzipped: module
# docstring).
SUMMARY = "summary.csv.gz"
CURVES = "curves.csv.gz"
# The `seed` of summary rows over every training seed of a model.
ALL_SEEDS = -1
MASS_COLUMNS = ("scene", "job", "percent_error", "tangent_percent_error", "scale", "scaled_percent_error", "scaled_tangent_percent_error")
# Table order of scenes: the built-in grid's evaluation scenes as it declares them
# (planar, then 3D); a user's grid's other scenes follow as recorded. A track's tables
# follow its own entries' order (the transfer track's starts from its training chain).
SCENE_ORDER = tuple(dict.fromkeys(scene for entry in GRID for scene in entry.eval_scenes))
TRACK_SCENE_ORDERS = {track: tuple(dict.fromkeys(scene for entry in GRID if entry.track == track for scene in entry.eval_scenes))
                      for track in TRACKS}
# How headings name each dimension's grid.
DIMENSION_NAMES = {2: "planar", 3: "3D"}


def provenance_columns(meta: dict) -> dict:
    env = meta.get("environment", {})
    return {k: env.get(k, "unknown") for k in ("commit", "versions", "device")}


def _summary_rows(scene, model, seed, metric, arrays, meta, prefix, diverged=None, value=True):
    """Tidy rows of one record's metric: its statistics, the divergence count and time
    if `diverged` (seconds per initial condition, NaN for none) is given, and no value
    or interval when `value` is false (a chaos floor whose perturbed run diverged)."""
    gmean, low, high = metrics.summarise(arrays[f"{prefix}/per_ic_log"])
    base = dict(scene=scene, model=model, seed=seed, metric=metric, **provenance_columns(meta))
    stats = {"gmean": gmean, "ci_low": low, "ci_high": high} if value else {}
    stats["initial_conditions"] = len(arrays[f"{prefix}/per_ic_log"])
    if diverged is not None:
        stats["diverged"] = int(np.sum(np.isfinite(diverged)))
        stats["first_divergence_s"] = float(np.nanmin(diverged)) if np.isfinite(diverged).any() else float("nan")
    return [{**base, "statistic": k, "value": v} for k, v in stats.items()]


def _curve_rows(scene, model, seed, metric, arrays, prefix):
    t = arrays["t"]
    # Records kept every frame before they kept their curves every CURVE_DT s: the same
    # frames are read from either.
    frames = range(len(t))[curve_frames(float(t[1] - t[0]))] if len(t) > 1 else range(len(t))
    rows = []
    for statistic in ("gmean", "low", "high"):
        values = arrays[f"{prefix}/{statistic}"]
        for k in frames:
            rows.append(dict(scene=scene, model=model, seed=seed, metric=metric, statistic=statistic, t=round(float(t[k]), 9), value=float(values[k])))
    return rows


def scene_level_metric(group: str, metric: str) -> str:
    """The summary's metric name of a scene-level score (`evaluate.scene_level_scores`):
    `chaos_floor`, `chaos_floor_node_rms_error`, `truth_vs_mujoco`, ..."""
    return scene_level_prefix(group, metric).replace("/", "_")


def _floor_diverged(arrays: dict) -> bool:
    return bool(np.isfinite(arrays.get("chaos_floor/diverged_at", np.nan)).any())


def tables(truths: dict, pairs: list, references: tuple[str, ...] = DEFAULT_REFERENCES):
    """`(summary, curves)` DataFrames from the ground-truth and pair records (module
    docstring), every metric of `evaluate.recorded_metrics(references)`. A metric a
    record lacks (written before it existed) has no rows; a chaos floor whose perturbed
    run diverged has no value, interval or curve."""
    import pandas as pd

    summary, curves = [], []
    floor_rms = {}
    recorded = [m.name for m in recorded_metrics(references)]
    for scene, (arrays, meta) in truths.items():
        diverged_at, floor_ok = arrays.get(f"{FLOOR}/diverged_at"), not _floor_diverged(arrays)
        for group, name in scene_level_scores(references):
            prefix, metric, is_floor = scene_level_prefix(group, name), scene_level_metric(group, name), group == FLOOR
            if f"{prefix}/per_ic_log" not in arrays:
                continue
            diverged = diverged_at if is_floor else arrays.get(f"{group}/diverged_at")
            summary += _summary_rows(scene, "ground truth", 0, metric, arrays, meta, prefix, diverged, value=floor_ok or not is_floor)
            if floor_ok or not is_floor:
                curves += _curve_rows(scene, "ground truth", 0, metric, arrays, prefix)
        if floor_ok and f"{FLOOR}/node_rms_error/per_ic_log" in arrays:
            floor_rms[scene] = metrics.summarise(arrays[f"{FLOOR}/node_rms_error/per_ic_log"])[0]
    rows = [(scene, REST, 0, arrays, meta, f"{REST_PREFIX}/", arrays.get(f"{REST_PREFIX}/diverged_at")) for scene, (arrays, meta) in truths.items()]
    rows += [(scene, EXACT_NO_DRAG, 0, arrays, meta, f"{NO_DRAG}/", arrays[f"{NO_DRAG}/diverged_at"])
             for scene, (arrays, meta) in truths.items() if f"{NO_DRAG}/diverged_at" in arrays]
    rows += [(pair.scene, pair.label, pair.job.seed, arrays, meta, "", arrays["diverged_at"]) for pair, (arrays, meta) in pairs]
    for scene, model, seed, arrays, meta, prefix, diverged in rows:
        for metric in recorded:
            if f"{prefix}{metric}/per_ic_log" not in arrays:
                continue
            summary += _summary_rows(scene, model, seed, metric, arrays, meta, prefix + metric, diverged)
            curves += _curve_rows(scene, model, seed, metric, arrays, prefix + metric)
            if metric == "node_rms_error" and scene in floor_rms:
                ratio = metrics.summarise(arrays[f"{prefix}{metric}/per_ic_log"])[0] / floor_rms[scene]
                summary.append(dict(scene=scene, model=model, seed=seed, metric=metric, **provenance_columns(meta), statistic="chaos_floor_ratio", value=ratio))
    summary += _seed_rows(pairs, recorded)
    return pd.DataFrame(summary), pd.DataFrame(curves)


def _seed_rows(pairs: list, recorded: list[str]) -> list[dict]:
    """`ALL_SEEDS` rows of every (scene, model, metric of `recorded`) evaluated for several seeds."""
    groups: dict[tuple[str, str, str], list] = {}
    for pair, (arrays, meta) in pairs:
        for metric in recorded:
            if f"{metric}/per_ic_log" in arrays:
                groups.setdefault((pair.scene, pair.label, metric), []).append((arrays, meta))
    rows = []
    for (scene, model, metric), records in groups.items():
        if len(records) < 2:
            continue
        gmean, low, high = metrics.summarise_seeds([arrays[f"{metric}/per_ic_log"] for arrays, _ in records])
        diverged = np.concatenate([arrays["diverged_at"] for arrays, _ in records])
        stats = {"gmean": gmean, "ci_low": low, "ci_high": high, "seeds": len(records),
                 "initial_conditions": len(records[0][0][f"{metric}/per_ic_log"]), "diverged": int(np.sum(np.isfinite(diverged))),
                 "first_divergence_s": float(np.nanmin(diverged)) if np.isfinite(diverged).any() else float("nan")}
        base = dict(scene=scene, model=model, seed=ALL_SEEDS, metric=metric, **provenance_columns(records[0][1]))
        rows += [{**base, "statistic": k, "value": v} for k, v in stats.items()]
    return rows


def number_cell(value: float) -> str:
    return "—" if value is None or not math.isfinite(value) else f"{value:.2e}"


def interval_cell(row: dict) -> str:
    text = number_cell(row.get("gmean"))
    if math.isfinite(row.get("ci_low", float("nan"))):
        text += f" [{number_cell(row['ci_low'])}, {number_cell(row['ci_high'])}]"
    if math.isfinite(row.get("diverged", float("nan"))) and row["diverged"] > 0:
        text += f" ({int(row['diverged'])} diverged, first at {row['first_divergence_s']:.3g} s)"
    if math.isfinite(row.get("seeds", float("nan"))):
        text += f" ({int(row['seeds'])} seed{'s' if row['seeds'] != 1 else ''})"
    if math.isfinite(row.get("chaos_floor_ratio", float("nan"))):
        text += f", {row['chaos_floor_ratio']:.3g}x floor"
    return text


def _truth_cell(row: dict, truth_metric: str) -> str:
    """A scene-level reference: its value and any divergence, without an interval; a
    chaos floor whose perturbed run diverged is no floor, and says so instead."""
    if truth_metric.startswith(FLOOR) and row.get("diverged", 0) > 0:
        return f"diverged ({int(row['diverged'])} of {int(row['initial_conditions'])} perturbed runs, first at {row['first_divergence_s']:.3g} s)"
    return interval_cell({k: v for k, v in row.items() if k != "ci_low"})


def engine_title(engine: str) -> str:
    """A reference engine as headings and columns name it: its registry entry's `title`
    (`lgnn.engines.EngineEntry`), or its name where none is registered under it."""
    entry = ENGINES.get(engine)
    return entry.title if entry is not None else engine


def truth_columns(metric: str, references: tuple[str, ...] = DEFAULT_REFERENCES) -> list[tuple[str, str]]:
    """`(summary metric, column title)` of the scene-level columns beside the table of a
    recorded metric (`evaluate.recorded_metrics`): the chaos floor of a position error
    (`Metric.floor`; it has no place beside energy errors) and, against the Lagrangian
    ground truth, how far it is from each reference engine (`against_references`)."""
    (recorded,) = [m for m in recorded_metrics(references) if m.name == metric]
    name = recorded.metric.name
    columns = [(scene_level_metric(FLOOR, name), "chaos floor")] if recorded.metric.floor else []
    if recorded.reference == TRUTH and recorded.metric.against_references:
        columns += [(scene_level_metric(truth_against(engine), name), f"Lagrangian vs {engine_title(engine)}") for engine in references]
    return columns


def scene_groups(scenes, track: str = PAPER_TRACK) -> dict[int, list[str]]:
    """`{dim: scenes}`, dimensions ascending, each group in table order (the `track`'s
    `TRACK_SCENE_ORDERS`, then `SCENE_ORDER`, then as given): each dimension's grid
    gets its own tables, whose columns are the models evaluated on its scenes (a model
    trained in 2D is never evaluated in 3D)."""
    scenes = list(dict.fromkeys(scenes))
    order = tuple(dict.fromkeys((*TRACK_SCENE_ORDERS.get(track, ()), *SCENE_ORDER)))
    groups: dict[int, list[str]] = {}
    for scene in [s for s in order if s in scenes] + [s for s in scenes if s not in order]:
        groups.setdefault(get_scene(scene).dim, []).append(scene)
    return dict(sorted(groups.items()))


def without_training_scene(label: str, training_scene: str | None) -> str:
    """A model's label without its ` (training scene)`, where a heading or title names
    that scene once (`lgnn (chain4-3d)` under "trained on chain4-3d" is `lgnn`)."""
    return label if training_scene is None else label.replace(f" ({training_scene})", "", 1)


def summary_markdown(summary, metric: str, expected: set[tuple[str, str]] = frozenset(), unrankable: dict[str, str] | None = None,
                     scenes: list[str] | None = None, trained_on: str | None = None, order: tuple[str, ...] = MODEL_ORDER,
                     references: tuple[str, ...] = DEFAULT_REFERENCES) -> str:
    """A markdown table: rows the summary's `scenes` (default: all, in table order),
    columns the models evaluated on them (the rest baseline last; `trained_on`, the one
    training scene the heading names, dropped from their names), `gmean
    [95% interval]` cells, and the scene's chaos floor (and, for the rollout error,
    the ground truth against each reference engine of `references`) beside (`truth_columns`). A record that exists but lacks the metric (written
    before it was computed) shows "not computed", never a number; a `(scene, model)`
    of `expected` (the profile's pairs) with no record "not evaluated". A scene of
    `unrankable` is named "(not rankable)" and shows no model number, only "not
    rankable": its reference does not converge in dt, so its reference error may exceed
    the spread between models (the reason is in the report's settings)."""
    if summary.empty:
        return "(no results)\n"
    wide = summary.pivot_table(index=["scene", "model", "seed", "metric"], columns="statistic", values="value", aggfunc="first").reset_index()
    recorded = list(wide["scene"].unique())
    # A scene of the grid with no record at all is still a row ("not evaluated").
    expected_scenes = {scene for scene, _ in expected}
    scenes = ([s for group in scene_groups(recorded).values() for s in group] if scenes is None else
              [s for s in scenes if s in recorded or s in expected_scenes])
    wide = wide[wide.scene.isin(scenes)]
    models = [m for m in wide["model"].unique() if m not in ("ground truth", REST)]
    # Models in `order` (a profile's: `profiles.model_order`), any other after them by name.
    models.sort(key=lambda m: (order.index(m.split()[0]) if m.split()[0] in order else len(order), m))
    models.append(REST)
    # Which records exist: a model with any metric on a scene; the rest baseline and
    # the scene-level columns wherever the scene's ground-truth record does.
    present = {(scene, "ground truth" if model == REST else model) for scene, model in zip(wide["scene"], wide["model"])}
    truth_metrics = [column for column, _ in truth_columns(metric, references)]
    extra = [title for _, title in truth_columns(metric, references)]
    columns = [without_training_scene(m, trained_on) for m in models]
    lines = ["| scene | " + " | ".join(columns + extra) + " |", "|---" * (len(models) + len(extra) + 1) + "|"]
    for scene in scenes:
        cells = []
        for model in models:
            match = wide[(wide.scene == scene) & (wide.model == model) & (wide.metric == metric)]
            if (match.seed == ALL_SEEDS).any():  # several seeds: the interval over seeds and ICs
                match = match[match.seed == ALL_SEEDS]
            record = (scene, "ground truth" if model == REST else model) in present
            if scene in (unrankable or {}) and (len(match) or (scene, model) in expected):
                cells.append("not rankable")
                continue
            # A trained model's cell says how many seeds it holds, one included (the baselines
            # and predictions made outside lgnn are not trained here).
            trained = model not in (REST, EXACT_NO_DRAG) and not model.endswith(EXTERNAL_MARK)
            row = {**match.iloc[0].to_dict(), **({"seeds": 1} if trained and match.iloc[0]["seed"] != ALL_SEEDS else {})} if len(match) else None
            cells.append(interval_cell(row) if row is not None else "not computed" if record
                         else "not evaluated" if (scene, model) in expected else "")
        for truth_metric in truth_metrics:
            match = wide[(wide.scene == scene) & (wide.model == "ground truth") & (wide.metric == truth_metric)]
            cells.append(_truth_cell(match.iloc[0].to_dict(), truth_metric) if len(match) else
                         "not computed" if (scene, "ground truth") in present else "")
        lines.append(f"| {scene}{' (not rankable)' if scene in (unrankable or {}) else ''} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def unrankable_scenes(out: Path) -> dict[str, str]:
    """`{scene: why}` from the reference convergence table beside the report
    (`lgnn.bench.convergence.load_unrankable`: `lgnn convergence`'s), if there is one."""
    return convergence.load_unrankable(out)


def summary_tables(references: tuple[str, ...] = DEFAULT_REFERENCES) -> list[tuple[str, str]]:
    """The summary tables of each grid, in README order: `(recorded metric, heading)` of
    every metric of `evaluate.recorded_metrics(references)`."""
    return [(m.name, m.metric.heading if m.reference == TRUTH else f"{m.metric.title} against {engine_title(m.reference)}")
            for m in recorded_metrics(references)]


def track_rows(table, pairs: list[Pair], track: str):
    """The rows of `table` (a DataFrame with a `model` column of row labels) shown with
    `track` (`grid.TRACKS`): those of another track's `pairs` left out. Rows of no pair
    (the baselines, predictions made outside lgnn) stay in every track's."""
    others = {pair.label for pair in pairs if pair.job.track != track}
    return table[~table["model"].isin(others)] if not table.empty else table


