"""The benchmark's report: tidy CSVs, markdown tables, figures and `README.md`, from
the records the stages wrote (`lgnn.bench.stages`), read through their public `load_*`
functions only (nothing is computed here but statistics of them).

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
- `figures/*.png`; `README.md`: the summary tables and how each file was made.

pandas and matplotlib are imported here only (the library's numerics do not need them).
"""

from __future__ import annotations

import fnmatch
import math
from pathlib import Path

import numpy as np

from lgnn import metrics
from lgnn.bench import convergence, gpu_truth
from lgnn.bench.grid import (EXTERNAL, GRID, PAPER_TRACK, PROFILES, SNAPSHOT_SCENES, TRACKS, TRAINING_SCENES, TRANSFER_TRACK, EvaluateSettings,
                             Profile, error_figures, evaluation_pairs, Pair, TrainingJob, evaluation_scenes, model_order, settings_key, train_config,
                             training_jobs)
from lgnn.bench.stability import fit_exponent
from lgnn.bench.stages.evaluate import CURVE_DT, FLOOR, NO_DRAG, SNAPSHOT_DT, TRUTH, curve_frames, load_pairs, load_truths, recorded_metrics
from lgnn.bench.stages.evaluate import REST as REST_PREFIX
from lgnn.bench.stages.evaluate import scene_level_prefix, scene_level_scores, truth_against, unmatched_base_pairs
from lgnn.bench.stages.external import load_externals
from lgnn.bench.stages.mass import load_mass
from lgnn.bench.stages.scaling import load_scaling
from lgnn.bench.stages.speed import speed_rows as load_speed_rows
from lgnn.bench.stages.train import default_lgnn, load_checkpoints
from lgnn.bench import store
from lgnn.bench.tables import escape_markdown_cell, read_table, write_csv
from lgnn.files import atomic_path, write_text_atomic
from lgnn.learn.models import get_spec
from lgnn.learn.train import stop_reason, training_key
from lgnn.scene import CHAIN_SAMPLER, OWN_STATE, PROJECTED, get_scene, initial_state_policy, is_pinned_chain

# Column order of the built-in grid's models (a profile's own models follow: `grid.model_order`).
MODEL_ORDER = tuple(dict.fromkeys(entry.model for entry in GRID))
# The built-in models' colours and the rest baseline's (the committed figures use them).
COLORS = {"lgnn": "C0", "gns": "C1", "lgn": "C2", "clnn": "C3", "rest": "0.5", "lgnn-mp1": "C4", "lgnn-mp2": "C5", "lgnn-notebook": "C6",
          "gns-10-128": "C8", "cgnode": "C9", "chgn": "#7b4173", "chnn": "#393b79"}
# Colours no built-in has (tab20b's darker shades; not C7, a grey beside the rest
# baseline's), given in turn to every other model (`model_colors`).
SPARE_COLORS = ("#637939", "#843c39", "#8c6d31", "#5254a3", "#8ca252", "#bd9e39", "#ad494a", "#a55194")
# How error figures draw a model rolled out without projection (`Pair.projected`): its
# projected row's colour, dashed.
UNPROJECTED_STYLE = "--"
# The rest baseline's model name in the tables (the initial state held).
REST = "rest"
# How tables mark predictions made outside lgnn (`grid.external_pair`): `my-sim (external)`.
EXTERNAL_MARK = f" ({EXTERNAL})"
# The drag scenes' exact physics without drag, as the tables name it.
EXACT_NO_DRAG = "exact, no drag"
# The reference engines the benchmark scores against unless its settings say otherwise.
DEFAULT_REFERENCES = EvaluateSettings.references
# How headings and columns name a reference engine (others by their registry name).
ENGINE_TITLES = {"lagrangian": "the Lagrangian engine", "mujoco": "MuJoCo", "mjx": "MJX", "mjwarp": "MuJoCo Warp"}
# The names of the figures the report draws under `figures/` (and removes when it no
# longer draws them).
REPORT_FIGURES = ("error_vs_time_*.png", "snapshots_*.png", "mass_matrix.png", "speed_error.png")
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


def model_colors(models) -> dict[str, str]:
    """`{model: colour}`: a built-in's own (`COLORS`); every other of `models`, in the
    order given, the next of `SPARE_COLORS` (repeating only past the last of them)."""
    others = [model for model in dict.fromkeys(models) if model not in COLORS]
    return {**COLORS, **{model: SPARE_COLORS[k % len(SPARE_COLORS)] for k, model in enumerate(others)}}


def _env_columns(meta: dict) -> dict:
    env = meta.get("environment", {})
    return {k: env.get(k, "unknown") for k in ("commit", "versions", "device")}


def _summary_rows(scene, model, seed, metric, arrays, meta, prefix, diverged=None, value=True):
    """Tidy rows of one record's metric: its statistics, the divergence count and time
    if `diverged` (seconds per initial condition, NaN for none) is given, and no value
    or interval when `value` is false (a chaos floor whose perturbed run diverged)."""
    gmean, low, high = metrics.summarise(arrays[f"{prefix}/per_ic_log"])
    base = dict(scene=scene, model=model, seed=seed, metric=metric, **_env_columns(meta))
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
                summary.append(dict(scene=scene, model=model, seed=seed, metric=metric, **_env_columns(meta), statistic="chaos_floor_ratio", value=ratio))
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
        base = dict(scene=scene, model=model, seed=ALL_SEEDS, metric=metric, **_env_columns(records[0][1]))
        rows += [{**base, "statistic": k, "value": v} for k, v in stats.items()]
    return rows


def _fmt(value: float) -> str:
    return "—" if value is None or not math.isfinite(value) else f"{value:.2e}"


def _interval(row: dict) -> str:
    text = _fmt(row.get("gmean"))
    if math.isfinite(row.get("ci_low", float("nan"))):
        text += f" [{_fmt(row['ci_low'])}, {_fmt(row['ci_high'])}]"
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
    return _interval({k: v for k, v in row.items() if k != "ci_low"})


def engine_title(engine: str) -> str:
    """A reference engine as headings and columns name it (`ENGINE_TITLES`)."""
    return ENGINE_TITLES.get(engine, engine)


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


def _without_training_scene(label: str, training_scene: str | None) -> str:
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
    # Models in `order` (a profile's: `grid.model_order`), any other after them by name.
    models.sort(key=lambda m: (order.index(m.split()[0]) if m.split()[0] in order else len(order), m))
    models.append(REST)
    # Which records exist: a model with any metric on a scene; the rest baseline and
    # the scene-level columns wherever the scene's ground-truth record does.
    present = {(scene, "ground truth" if model == REST else model) for scene, model in zip(wide["scene"], wide["model"])}
    truth_metrics = [column for column, _ in truth_columns(metric, references)]
    extra = [title for _, title in truth_columns(metric, references)]
    columns = [_without_training_scene(m, trained_on) for m in models]
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
            cells.append(_interval(row) if row is not None else "not computed" if record
                         else "not evaluated" if (scene, model) in expected else "")
        for truth_metric in truth_metrics:
            match = wide[(wide.scene == scene) & (wide.model == "ground truth") & (wide.metric == truth_metric)]
            cells.append(_truth_cell(match.iloc[0].to_dict(), truth_metric) if len(match) else
                         "not computed" if (scene, "ground truth") in present else "")
        lines.append(f"| {scene}{' (not rankable)' if scene in (unrankable or {}) else ''} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _spread(r: dict) -> str:
    """`min..max (n runs)` of a speed row's timed runs; `1 run` for one (records made
    before the spread was kept hold one run)."""
    runs = r.get("runs", 1 if math.isfinite(r["wall_s_per_sim_s"]) else 0)
    if not runs:
        return "—"
    if runs == 1:
        return "1 run"
    return f"{_fmt(r['wall_s_min_per_sim_s'])}..{_fmt(r['wall_s_max_per_sim_s'])} ({runs} runs)"


def speed_markdown(rows: list[dict]) -> str:
    lines = ["| scene | solver | dt | wall s per simulated s (median) | spread | evaluations per simulated s | compile s | rollout error | note |",
             "|---" * 9 + "|"]
    for r in rows:
        compile_s = "—" if not math.isfinite(r["compile_s"]) else f"{r['compile_s']:.1f}"
        note = "; ".join(filter(None, (f"{r['form']} MJCF" if r.get("form") else "", r["note"])))
        lines.append(f"| {r['scene']} | {r['solver']} | {r['dt']:g} | {_fmt(r['wall_s_per_sim_s'])} | {_spread(r)} | {r['evaluations_per_sim_s']:.0f} | "
                     f"{compile_s} | {_fmt(r['rollout_error'])} | {note} |")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------
# Figures
# ---------------------------------------------------------------------------------


def _savefig(fig, path: Path) -> None:
    """`fig` as a PNG of 256 colours at most: the figures are line art on white, which
    loses nothing visible in a palette, and the committed ones take a third of the
    space (the 3D snapshots 2.2 MB in full colour, 0.7 MB so)."""
    import io

    import matplotlib.pyplot as plt
    from PIL import Image  # matplotlib's own dependency

    path.parent.mkdir(parents=True, exist_ok=True)
    rendered = io.BytesIO()
    fig.savefig(rendered, dpi=110, format="png")
    plt.close(fig)
    image = Image.open(rendered).convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    with atomic_path(path) as tmp:
        image.save(tmp, format="PNG", optimize=True)


def error_axis_labels() -> dict[str, str]:
    """`{metric: y-axis label}` of the rows of an error-against-time figure: the
    registered metrics with a `label`, in registry order."""
    return {m.name: m.label for m in metrics.METRICS.values() if m.label}


def _plot_error_vs_time(curves, scenes: list[str], path: Path, trained_on: str, colors: dict[str, str] | None = None) -> bool:
    """Error against time of every model on `scenes` (those with curves; the title
    names them, so a profile without some scenes is not mislabelled), a line per
    training seed in the model's colour (`colors`, default `model_colors` of the curves'
    models)."""
    import matplotlib.pyplot as plt

    scenes = [s for s in scenes if s in set(curves["scene"])]
    if not scenes:
        return False
    title = (f"Error against time: {', '.join(scenes)} (trained on {trained_on})\n"
             f"errors are clipped to [{metrics.ERROR_FLOOR:g}, 1]: 1 means diverged (or no better than that); band: interval over initial conditions")
    colors = colors or model_colors(model.split()[0] for model in curves["model"].unique())
    labels = error_axis_labels()
    fig, axes = plt.subplots(len(labels), len(scenes), figsize=(4.2 * len(scenes), 3.2 * len(labels)), squeeze=False, sharex=True)
    for col, scene in enumerate(scenes):
        for row, metric in enumerate(labels):
            ax = axes[row, col]
            sub = curves[(curves.scene == scene) & (curves.metric == metric)]
            for model in sub["model"].unique():
                if model == "ground truth":
                    continue
                kind, name = model.split()[0], _without_training_scene(model, trained_on)
                # One line per seed (the model's label on the first only), never one
                # line running from the last frame of a seed back to t = 0 of the next.
                for k, (_, m) in enumerate(sub[sub.model == model].groupby("seed", sort=True)):
                    g = m[m.statistic == "gmean"]
                    ax.plot(g.t, g.value, UNPROJECTED_STYLE if "(unprojected)" in model else "-", color=colors.get(kind),
                            label=(name.upper() if kind == name else name) if k == 0 else None)
                    lo, hi = m[m.statistic == "low"], m[m.statistic == "high"]
                    if np.isfinite(lo.value.to_numpy()).any():
                        ax.fill_between(lo.t, lo.value, hi.value, color=colors.get(kind), alpha=0.2, linewidth=0)
            floor = curves[(curves.scene == scene) & (curves.metric == "chaos_floor") & (curves.statistic == "gmean")]
            if len(floor) and metric == "rollout_error":
                ax.plot(floor.t, floor.value, "k--", linewidth=1, label="chaos floor (1e-4)")
            ax.set_yscale("log")
            ax.set_title(f"{scene}: {metric.replace('_', ' ')}", fontsize=9)
            if col == 0:
                ax.set_ylabel(labels[metric])
            if row == len(labels) - 1:
                ax.set_xlabel("t (s)")
    # One legend beside the panels, of every model any panel draws (panels of one figure
    # may hold different models), so no panel's curves hide under it.
    shown = {}
    for ax in axes.flat:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            shown.setdefault(label, handle)
    if shown:
        fig.legend(shown.values(), shown.keys(), loc="center right", fontsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout(rect=(0, 0, 1 - 1.6 / fig.get_figwidth(), 1))
    _savefig(fig, path)
    return True


def _plot_mass_matrices(records, path: Path) -> bool:
    import matplotlib.pyplot as plt

    if not records:
        return False
    fig, axes = plt.subplots(len(records), 3, figsize=(12, 3.8 * len(records)), squeeze=False)
    for row, (arrays, meta) in enumerate(records):
        # The learned matrix times the fitted overall factor (a Lagrangian's scale is not identifiable).
        true_m, learned_m = arrays["true"], meta["scale"] * arrays["learned"]
        scale = np.max(np.abs(true_m))
        for col, (matrix, name) in enumerate(((true_m, "true M"), (learned_m, f"learned M ({meta['job']}) x {meta['scale']:.3g}"))):
            image = axes[row, col].imshow(matrix, cmap="RdBu_r", vmin=-scale, vmax=scale)
            axes[row, col].set_title(f"{meta['scene']}: {name}", fontsize=9)
            fig.colorbar(image, ax=axes[row, col], shrink=0.8)
        diff = 100 * np.abs(learned_m - true_m) / scale
        image = axes[row, 2].imshow(diff, cmap="viridis")
        axes[row, 2].set_title(f"|difference| (% of max |M|); Frobenius {meta['scaled_percent_error']:.2g}%, tangent {meta['scaled_tangent_percent_error']:.2g}%", fontsize=8)
        fig.colorbar(image, ax=axes[row, 2], shrink=0.8)
    fig.tight_layout()
    _savefig(fig, path)
    return True


# The views a snapshot panel draws, per scene dimension: (horizontal, vertical)
# coordinate and name. Gravity is along -y, so a front view shows the hang and, in 3D, a
# top view the motion out of the x-y plane.
SNAPSHOT_VIEWS = {2: ((0, 1, ""),), 3: ((0, 1, "front (x-y)"), (0, 2, "top (x-z)"))}


def _square_limits(points: np.ndarray, margin: float = 0.08) -> tuple[tuple[float, float], tuple[float, float]]:
    """`(xlim, ylim)`: the square around `points` (..., 2) with `margin` of its side
    spare, so every panel of a view draws the same box at one scale and the motion
    shows (a model that leaves the truth's box runs off the panel)."""
    low, high = points.reshape(-1, 2).min(0), points.reshape(-1, 2).max(0)
    half = (1 + 2 * margin) * max(high - low) / 2 or 1.0
    centre = (low + high) / 2
    return (centre[0] - half, centre[0] + half), (centre[1] - half, centre[1] + half)


def _plot_snapshots(scene: str, truths: dict, pairs: list, path: Path, colors: dict[str, str] | None = None) -> bool:
    """Initial condition 0 at 5 times: a row per model trained on the main training
    scene of the scene's dimension (`TRAINING_SCENES`), its first seed (more rows of a
    model would not say which seed each is), dashed in its colour, over
    MuJoCo's trajectory in black; in 3D each time drawn from the front and from above.
    Each view's panels share the box of MuJoCo's whole trajectory (`_square_limits`)."""
    import matplotlib.pyplot as plt

    if scene not in truths:
        return False
    structure = get_scene(scene)
    trained_on = TRAINING_SCENES[structure.dim]
    learned = [(p, r) for p, r in pairs if p.scene == scene and p.job.scene == trained_on]
    if not learned:
        return False
    colors = colors or model_colors(p.job.model for p, _ in learned)
    seed = min(p.job.seed for p, _ in learned)
    learned = [(p, r) for p, r in learned if p.job.seed == seed]
    # MuJoCo's trajectory, or the Lagrangian ground truth's where the record's MuJoCo
    # reference was stale (`evaluate.MUJOCO_REFERENCE`): the figure says which.
    truth = truths[scene][0]
    reference = "MuJoCo" if "snapshot/mujoco" in truth else "the Lagrangian ground truth"
    mujoco_q = truth["snapshot/mujoco"] if "snapshot/mujoco" in truth else truth["snapshot/truth"]
    views = SNAPSHOT_VIEWS[structure.dim]
    limits = [_square_limits(mujoco_q[..., [x, y]]) for x, y, _ in views]
    frames = np.linspace(0, len(mujoco_q) - 1, 5).round().astype(int)
    n_cols = len(frames) * len(views)
    fig, axes = plt.subplots(len(learned), n_cols, figsize=(2.6 * n_cols, 2.6 * len(learned)), squeeze=False, layout="constrained")
    edges = np.asarray(structure.edges)
    for row, (pair, (arrays, _)) in enumerate(learned):
        model_q = arrays["snapshot/model"]
        label = _without_training_scene(pair.label, trained_on).upper()
        for k, f in enumerate(frames):
            for v, (x, y, view) in enumerate(views):
                ax = axes[row, k * len(views) + v]
                for q, style, color, name in ((mujoco_q[f], "-", "k", "MuJoCo" if reference == "MuJoCo" else "ground truth"), (model_q[f], "--", colors.get(pair.job.model), label)):
                    if np.isfinite(q).all():
                        for e, seg in enumerate(q[edges]):
                            ax.plot(seg[:, x], seg[:, y], style, color=color, linewidth=1.2, label=name if e == 0 else None)
                ax.set_xlim(limits[v][0])
                ax.set_ylim(limits[v][1])
                ax.set_aspect("equal")
                ax.set_xticks([])
                ax.set_yticks([])
                if row == 0:
                    ax.set_title(f"t = {f * SNAPSHOT_DT:.2f} s" + (f", {view}" if view else ""), fontsize=9)
                if k == v == 0:
                    ax.legend(fontsize=6, loc="lower left")
    views_text = "; ".join(view for _, _, view in views if view)
    fig.suptitle(f"{scene}: learned (dashed, trained on {trained_on}, seed {seed}) against {reference} (black), initial condition 0"
                 + (f"\nviews: {views_text}, gravity along -y" if views_text else ""), fontsize=10)
    _savefig(fig, path)
    return True


def _plot_speed_error(rows: list[dict], path: Path, colors: dict[str, str] | None = None) -> bool:
    import matplotlib.pyplot as plt

    colors = colors or model_colors(r["solver"].split()[0] for r in rows if r["kind"] != "engine")
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    if not scenes:
        return False
    cols = min(2, len(scenes))
    n_rows = -(-len(scenes) // cols)
    fig, axes = plt.subplots(n_rows, cols, figsize=(6 * cols, 4.5 * n_rows), squeeze=False)
    for ax in axes.flat[len(scenes):]:
        ax.set_visible(False)
    from matplotlib.lines import Line2D

    markers = {"lagrangian": "o", "mujoco": "s", "mjx": "^"}
    # dt labels beside their marker, on a side per engine, so the engines' labels at one
    # dt do not overprint each other.
    offsets = {"lagrangian": (4, 3), "mujoco": (4, -9), "mjx": (-26, 3)}
    for ax, scene in zip(axes.flat, scenes):
        for r in rows:
            if r["scene"] != scene or not (math.isfinite(r["wall_s_per_sim_s"]) and math.isfinite(r["rollout_error"])):
                continue
            if r["kind"] == "engine":
                ax.loglog(r["wall_s_per_sim_s"], r["rollout_error"], markers[r["solver"]], color="k", fillstyle="none")
                ax.annotate(f"{r['dt']:g}", (r["wall_s_per_sim_s"], r["rollout_error"]), xytext=offsets[r["solver"]],
                            textcoords="offset points", fontsize=6)
            else:
                kind = r["solver"].split()[0]
                ax.loglog(r["wall_s_per_sim_s"], r["rollout_error"], "*", color=colors.get(kind), markersize=10, label=r["solver"].upper())
        ax.set_title(scene, fontsize=9)
        ax.set_xlabel("wall s per simulated s")
        ax.set_ylabel("rollout error vs MuJoCo reference")
        engines = sorted({r["solver"] for r in rows if r["scene"] == scene and r["kind"] == "engine"
                          and math.isfinite(r["wall_s_per_sim_s"]) and math.isfinite(r["rollout_error"])})
        handles = [Line2D([], [], marker=markers[e], color="k", fillstyle="none", linestyle="none", label=f"{e} (label: dt)") for e in engines]
        handles += ax.get_legend_handles_labels()[0]
        if handles:
            ax.legend(handles=handles, fontsize=7)
    fig.tight_layout()
    _savefig(fig, path)
    return True


# ---------------------------------------------------------------------------------
# README
# ---------------------------------------------------------------------------------


def _command(profile: Profile, command: str | None) -> str:
    """What wrote the report: the command given (`lgnn benchmark ...`), else a call of
    `lgnn.bench.run.run` or `report.write` on the profile (the tests' and notebooks' way)."""
    return command or f"lgnn.bench.run.run(load_profile(...)), profile {profile.name!r}"


def _stopped_by(state, config) -> str:
    """Why a run's training ended (`lgnn.learn.train.stop_reason`), or that it has not."""
    return stop_reason(state, config) or "not finished: cut off, resumable"


def _training_lines(profile: Profile, out: Path) -> list[str]:
    lines = ["| model | training scene | seed | epochs | minutes | best validation MSE (epoch) | stopped by |", "|---|---|---|---|---|---|---|"]
    checkpoints = load_checkpoints(profile, out)
    for job, state in checkpoints:
        lines.append(f"| {job.model} | {job.scene} | {job.seed} | {state.epoch} | {state.elapsed_s / 60:.1f} | {state.best_val:.3g} ({state.best_epoch}) "
                     f"| {_stopped_by(state, train_config(profile, job))} |")
    for dim, training_scene in TRAINING_SCENES.items():
        chosen, scores = default_lgnn(profile, out, training_scene, checkpoints)
        if scores:
            # The planar grid's is "the" default LGNN; another dimension's is named.
            lines += ["", f"Default LGNN{'' if dim == 2 else ' in ' + DIMENSION_NAMES.get(dim, f'{dim}D')} (trained on {training_scene}; lowest geometric mean over seeds of the best "
                      f"validation MSE among the variants with every seed trained): **{chosen}** ({', '.join(f'{v} {s:.3g}' for v, s in scores.items())})."]
    return lines


def _provenance_lines(truths: dict, pairs: list, speed_rows: list[dict], mass_records: list, out: Path) -> list[str]:
    """Which folder (this report's `out`, or the base read in place: `store.Layout.load`),
    machine and commit made each record, grouped (the stages may run apart)."""
    groups: dict[tuple[str, str, str], list[str]] = {}

    def add(meta: dict, label: str) -> None:
        env = meta.get("environment", meta)
        folder = meta.get("folder", str(out))
        groups.setdefault((folder, env.get("device", "unknown"), env.get("commit", "unknown")), []).append(label)

    for scene, (_, meta) in truths.items():
        add(meta, f"ground truth {scene}")
    for pair, (_, meta) in pairs:
        add(meta, f"{pair.label}{'' if pair.job.external else f' s{pair.job.seed}'} on {pair.scene}")
    for scene, device, commit, folder in dict.fromkeys((r["scene"], r["device"], r["commit"], r.get("folder", str(out))) for r in speed_rows):
        add({"device": device, "commit": commit, "folder": folder}, f"speed {scene}")
    for _, meta in mass_records:
        add(meta, f"mass matrix {meta['scene']}")
    lines = ["| folder | machine | commit | records |", "|---|---|---|---|"]
    lines += [f"| `{folder}` | {device} | {commit} | {', '.join(labels)} |" for (folder, device, commit), labels in groups.items()]
    return lines


# Heads a non-full profile's report (and the console, which prints the report).
QUICK_WARNING = ("**Not results.** This profile checks that the pipeline runs: its training budgets are tiny and it has few initial "
                 "conditions, so the ranking of the models means nothing, and so do its timings: a few runs of a short horizon on a "
                 "shared machine, which vary several-fold between benchmark runs (single runs gave a Lagrangian/MuJoCo ratio of 3.05 "
                 "in one, 0.41 in the next; the speed table's spread column shows the runs of this one). "
                 "Numbers: `lgnn benchmark --full`, or the committed `results/`.")


def _cut_off_lines(profile: Profile, out: Path) -> list[str]:
    """A warning naming the checkpoints whose training the protocol's rules (epoch
    budget, plateau) did not end: cut off by a wall-clock cap they were trained under,
    or by an interrupted run. Their rows rank what that training learned, not the
    protocol's; a full run resumes or retrains them. Nothing where every run ended."""
    cut: dict[str, list[TrainingJob]] = {}
    for job, state in load_checkpoints(profile, out):
        if stop_reason(state, train_config(profile, job)) is None:
            cut.setdefault(job.model, []).append(job)
    if not cut:
        return []
    named = [f"{model} ({'; '.join(dict.fromkeys(j.trained_on for j in jobs))}; {len(jobs)} run{'s' if len(jobs) > 1 else ''})"
             for model, jobs in cut.items()]
    return [f"**Training cut off.** These runs stopped before the training protocol's rules ended them (the epoch budget or "
            f"the plateau rule; the training table says where each stopped): {', '.join(named)}. Their rows rank what that "
            "training learned, not what the protocol's would: `lgnn benchmark --full --stage train` resumes or retrains them.", ""]


def banner(profile: Profile) -> list[str]:
    """The report's opening warning, from what was run, not the profile's name:
    `QUICK_WARNING` unless the evaluation settings and training data are the full
    profile's; with those, the training jobs whose settings differ from the full
    profile's (a smaller budget, or another optimisation), each named: their rows rank
    what that training learned, not the full recipe's. No warning otherwise."""
    full = PROFILES["full"]
    if settings_key(profile.evaluate) != settings_key(full.evaluate) or profile.training.data != full.training.data:
        return [QUICK_WARNING, ""]
    recipe = full.training.train
    short_jobs: dict[tuple[str, str], list[TrainingJob]] = {}
    other = []
    for job in training_jobs(profile):
        config = train_config(profile, job)
        if training_key(config) | {"seed": 0} != training_key(recipe) | {"seed": 0}:
            other.append(job.name)
        elif config.epochs < recipe.epochs or (config.minutes is not None and (recipe.minutes is None or config.minutes < recipe.minutes)):
            budget = f"{config.epochs} epochs" + (f" or {config.minutes:g} minutes" if config.minutes else "")
            short_jobs.setdefault((job.model, budget), []).append(job)
    # One entry per model and budget: its training scenes and seeds.
    short = [f"{model} ({budget}; {'; '.join(dict.fromkeys(j.trained_on for j in jobs))}; "
             f"seed{'s' if len({j.seed for j in jobs}) > 1 else ''} {', '.join(str(s) for s in sorted({j.seed for j in jobs}))})"
             for (model, budget), jobs in short_jobs.items()]
    lines = []
    if short:
        lines.append(f"**Full-profile evaluation, shorter training.** Trained on a smaller budget than the full profile's "
                     f"({recipe.epochs} epochs" + (f" or {recipe.minutes:g} minutes" if recipe.minutes else "") + ", or its plateau rule): "
                     + ", ".join(short) + ". Their rows rank what that budget learned, not what the full recipe would.")
    if other:
        lines.append("**Full-profile evaluation, other training.** Trained with other optimisation settings than the full profile's "
                     "(batch, rate, schedule): " + ", ".join(other) + ".")
    return [line for text in lines for line in (text, "")]


def _unmatched_lines(profile: Profile, out: Path) -> list[str]:
    """One line naming the base folder's evaluations made with other settings than this
    report's (`evaluate.unmatched_base_pairs`): their cells say "not evaluated"."""
    if profile.base is None:
        return []
    unmatched = unmatched_base_pairs(profile, out)
    if not unmatched:
        return []
    return [f"**Not compared:** {len(unmatched)} evaluation(s) of `{profile.base}`'s models were made with other evaluation settings than "
            f"this report's ({', '.join(dict.fromkeys(pair.label for pair in unmatched))}): they read \"not evaluated\", never mixed in."]


def _unrankable(out: Path) -> dict[str, str]:
    """`{scene: why}` from the reference convergence table beside the report
    (`<out>/convergence.csv`, written by `lgnn convergence`), if there is one."""
    path = out / "convergence.csv"
    if not path.exists():
        return {}
    return convergence.unrankable(read_table(path)[1])


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


def _summary_sections(profile: Profile, summary, unrankable: dict[str, str]) -> list[str]:
    """The summary tables of each track (`grid.TRACKS`: models trained on the paper's
    scenes, then on varied draws) and dimension's grid apart (`scene_groups`), each
    heading naming the grid and what its models were trained on (`track_rows`)."""
    pairs = evaluation_pairs(profile)
    lines = []
    for track in [t for t in TRACKS if t == PAPER_TRACK or any(p.job.track == t for p in pairs)]:
        track_pairs = [p for p in pairs if p.job.track == track]
        expected = {(pair.scene, pair.label) for pair in track_pairs}
        shown = track_rows(summary, pairs, track)
        modelled = shown[~shown["model"].isin(("ground truth", REST, EXACT_NO_DRAG))]["scene"] if not shown.empty else []
        groups = scene_groups([*modelled, *(pair.scene for pair in track_pairs)], track) if not shown.empty else {2: []}
        for dim, scenes in groups.items():
            trained = list(dict.fromkeys(pair.job.trained_on for pair in track_pairs if pair.scene in scenes))
            grid_name = (DIMENSION_NAMES.get(dim, f"{dim}D") + (", transfer track" if track == TRANSFER_TRACK else "")
                         + (f": trained on {', '.join(trained)}" if trained else ""))
            for metric, heading in summary_tables(profile.evaluate.references):
                table = summary_markdown(shown, metric, expected, unrankable, scenes, trained[0] if len(trained) == 1 else None,
                                         model_order(profile), profile.evaluate.references)
                lines += [f"## {heading} ({grid_name})", "", table]
    return lines


def _external_lines(pairs: list) -> list[str]:
    """The predictions made outside lgnn among the records (`lgnn.bench.stages.external`):
    what each is and which scenes it answers; none: no lines."""
    found: dict[str, list] = {}
    for pair, (_, meta) in pairs:
        if pair.job.external:
            found.setdefault(pair.label, []).append(meta)
    if not found:
        return []
    lines = ["## External predictions", "",
             f"Rows marked `{EXTERNAL_MARK.strip()}` are predictions made outside lgnn from the same exported initial conditions "
             "(`lgnn dataset export`), scored here against the same ground truth with the same metrics and divergence rule "
             "(`lgnn benchmark --add-predictions`; docs/formats.md, \"Predictions\"). They have no checkpoint, parameters or "
             "training time here, and are not in the training table.", "",
             "| model | scenes | file | about |", "|---|---|---|---|"]
    for label, metas in found.items():
        files = ", ".join(dict.fromkeys(f"`{m['file']}`" for m in metas))
        about = escape_markdown_cell("; ".join(dict.fromkeys(m["about"] for m in metas if m.get("about")))) or "—"
        lines.append(f"| {label} | {', '.join(m['scene'] for m in metas)} | {files} | {about} |")
    return [*lines, ""]


def _initial_states_text(profile: Profile) -> str:
    """Which of the profile's evaluation scenes start how (`lgnn.scene.initial_state_policy`)."""
    by_policy: dict[str, list[str]] = {}
    for scene in evaluation_scenes(profile):
        by_policy.setdefault(initial_state_policy(get_scene(scene)), []).append(scene)
    how = {CHAIN_SAMPLER: "the paper's chain sampler (in 3D the 3D chain sampler)", PROJECTED: "projected perturbations of their own state",
           OWN_STATE: "their own state, one initial condition"}
    return "; ".join(f"{how[policy]}: {', '.join(scenes)}" for policy, scenes in by_policy.items())


def readme(profile: Profile, out: Path, records: tuple, summary, speed_rows, mass_records, figures: list[str], env: dict[str, str],
           stage_lines: list[str] = (), command: str | None = None) -> str:
    p, t, e = profile, profile.training, profile.evaluate
    envs = sorted(set(summary["device"])) if not summary.empty else []
    unrankable = _unrankable(out)
    lines = [
        f"# Benchmark results ({p.name} profile)",
        "",
        f"Written by `{_command(p, command)}`; nothing here is edited by hand.",
        f"Report written at commit {env['commit']}" + (" (lgnn not run from a git checkout; `LGNN_COMMIT` names it)" if env["commit"] == "unknown" else "")
        + f"; {env['versions']}.",
        *([f"Records and checkpoints of `{p.base}` are read in place (never copied or written) beside this folder's; "
           "each record's folder and commit are under \"Where each record was made\"."] if p.base is not None else []),
        *_unmatched_lines(p, out),
        "Each number's own commit, versions and device are columns of `benchmark/summary.csv.gz` (the stages may run on different machines): "
        + "; ".join(envs) + ".",
        "",
        *banner(p),
        *_cut_off_lines(p, out),
        "## Settings",
        "",
        f"- Training: {t.data.n_trajectories} trajectories of {t.data.duration:g} s, a state every {t.data.sample_dt:g} s (75:25 split), "
        f"Adam {t.train.learning_rate:g}, batch {t.train.batch_size}, budget {t.train.epochs} epochs"
        + (f" or {t.train.minutes:g} minutes per model (whichever ends first; the paper's 10 000 epochs did not fit)" if t.train.minutes else "")
        + (f", plateau: stop when the best validation MSE has not improved by {t.train.min_improvement:.0%} in {t.train.patience} epochs"
           if t.train.min_improvement else f", patience {t.train.patience}")
        + f", seeds {', '.join(map(str, p.seeds))}.",
        f"- Evaluation: {e.initial_conditions} initial conditions per scene, seed {e.ic_seed}, {_initial_states_text(p)}, "
        f"{e.duration:g} s, frames every {e.frame_dt:g} s, RK4 at dt {e.dt:g} with projection for models and the Lagrangian ground truth"
        + "".join(f" ({scene}: dt {dt:g})" for scene, dt in e.scene_dts if scene in evaluation_scenes(p)) + "; "
        f"MuJoCo C at RK4 dt {e.mujoco_dt:g}. Chaos floor: initial positions perturbed by {e.floor_perturbation:g}.",
        "- Errors (SPEC): per frame `||q_hat - q|| / (||q_hat|| + ||q||)`; energy error the same on the true Hamiltonian; "
        "geometric mean over frames t > 0 and initial conditions, [bootstrap 95% interval over initial conditions]; "
        f"errors clipped to [{metrics.ERROR_FLOOR:g}, 1]; a rollout counts as diverged at the first frame whose state is non-finite, "
        f"whose true energy is {metrics.EXPLOSION_FACTOR:g} energy scales from the initial one, or where a node moved {metrics.EXPLOSION_FACTOR:g} "
        "structure sizes (plus a free fall's reach) from its start (`lgnn.metrics`, the rule that stops every engine): error 1 from then on, and the cell says when.",
        "- Per-node RMS position error `sqrt(mean over nodes |q_hat - q|^2)` (length units), beside the paper's normalised error, which "
        "shrinks as a structure grows: the same statistics; a diverged frame counts as the divergence rule's reach "
        f"({metrics.EXPLOSION_FACTOR:g} structure sizes), which also caps it; `Nx floor` is its ratio to the chaos floor's RMS error on the scene.",
        "- `rest`: the rest baseline, the initial state held (`lgnn.metrics.rest_rollouts`), scored like a model: its errors are the truth's own "
        "displacement from its start, the bar any model must clear. The chaos floor is not given (\"diverged\") on a scene where a "
        "perturbed run diverged: it is then no floor. \"not computed\": a record written before that metric existed.",
        "- `gns` rollouts are projected onto the constraints after every step, as the ground truth's and every Lagrangian model's "
        "(GNS's own accelerations know no constraints); `gns (unprojected)` is the same checkpoint without projection. "
        f"`{EXACT_NO_DRAG}` (drag scenes): the exact physics with the drag term removed, from the same states: what ignoring drag scores.",
        "- Several training seeds: a cell is the geometric mean over seeds and initial conditions with a two-level bootstrap 95% interval "
        "(seeds, then each seed's initial conditions), `(n seeds)`; each seed's own numbers are rows of `benchmark/summary.csv.gz`. "
        "\"not evaluated\": a pair of the grid with no record yet (`lgnn benchmark --stage evaluate` resumes there).",
        *(["- Not rankable (`results/convergence.md`, `lgnn convergence`): the reference itself does not converge in dt, so no "
           "model number on these scenes could rank models and none is reported"
           + (" (the full grid does not evaluate them; T2-slack and T3-slack, their ropes 0.1 % slack, converge and stand in for them)"
              if p.name == "full" else "") + ": " + "; ".join(f"{scene}: {why}" for scene, why in unrankable.items()) + "."]
          if unrankable else []),
        "",
        "## Training",
        "",
        *_training_lines(p, out),
        "",
        *_external_lines(records[1]),
        *_summary_sections(p, summary, unrankable),
    ]
    if mass_records:
        lines += ["## Learned mass matrix (LGNN)", "",
                  "Each scene's LGNN is the one trained on its dimension's training scene (" + ", ".join(
                      f"{DIMENSION_NAMES.get(dim, f'{dim}D')}: {scene}" for dim, scene in TRAINING_SCENES.items()) + "; checkpoint "
                  "column), against the rods' mass matrix (in 3D a thin rod has no spin about its own axis). "
                  "Percentage Frobenius error over the free node coordinates and on the constraint tangent space (the part the dynamics "
                  "see), as learned and after the least-squares overall factor: accelerations fix a Lagrangian only up to a factor.", "",
                  "| scene | checkpoint | % error | % error, tangent space | factor | % error x factor | % error x factor, tangent space |",
                  "|---|---|---|---|---|---|---|"]
        lines += [f"| {m['scene']} | {m['job']} | {m['percent_error']:.3g} | {m['tangent_percent_error']:.3g} | {m['scale']:.3g} | "
                  f"{m['scaled_percent_error']:.3g} | {m['scaled_tangent_percent_error']:.3g} |" for _, m in mass_records]
        lines.append("")
    if speed_rows:
        lines += [f"## Speed against error (single trajectory, {speed_rows[0]['horizon_s']:g} s horizon, compile apart)", "",
                  "Error: geometric-mean rollout error against MuJoCo C at a tenth of the smallest step. Each scene's row group was "
                  "timed by one process on its own CPU core (`taskset`), the learned models and the Lagrangian engine through XLA's CPU "
                  "backend (`JAX_PLATFORMS=cpu`), on:", "",
                  *[f"- {scene}: {device}" for scene, device in dict.fromkeys((r["scene"], r["device"]) for r in speed_rows)], "",
                  speed_markdown(speed_rows)]
    lines += stage_lines
    lines += ["## Where each record was made", "",
              "Every stage resumes from the records it finds, so stages may run apart, on several machines, and be assembled by the "
              f"report: `lgnn benchmark{' --full' if p.name == 'full' else ''} --stage train|evaluate|speed|mass|report "
              "[--scene S] [--job J] [--chunk N]`. `+dirty` marks a record written while the working tree had uncommitted "
              "changes. Each record also holds the versions (`benchmark/summary.csv.gz`).", "",
              *_provenance_lines(*records, speed_rows, mass_records, out), ""]
    lines += ["## Files", "", "| file | what |", "|---|---|",
              "| `benchmark/summary.csv.gz` | tidy summary: scene, model, seed, metric, statistic, value, commit, versions, device |",
              f"| `benchmark/curves.csv.gz` | per-frame geometric means and 95% bands (every {CURVE_DT:g} s; provenance: the matching `summary.csv.gz` rows) |",
              "| `benchmark/speed_error.csv`, `.md` | speed against error |",
              *(["| `performance.md` | the speed records read as ratios to MuJoCo C at equal accuracy, each 3D chain beside the planar one, "
                 "and cost against chain length in 2D and 3D |"] if speed_rows else []),
              "| `benchmark/mass_matrix.csv` | learned mass matrix errors |",
              "| `benchmark/checkpoints/` | the trained models (`lgnn rollout --model ...` runs them) |",
              "| `benchmark/runs/` | the per-stage records the tables are made from (resumable) |"]
    lines += [f"| `figures/{name}` | figure |" for name in figures]
    if p.name == "full" and p.base is None:  # the repository's results/ beside the report
        lines += [
            "| `crosscheck.csv`, `.md` | ground-truth engines against each other (`lgnn crosscheck chain4 chain8 chain16 chain100 T1 T2 T3 --duration 0.1 --out-dir DIR`, float64 on a CPU: the table's header names the machine; 0.1 s, as MJX's CPU compile takes 15-25 s a scene) |",
            "| `engines_speed_error.csv`, `.md` | engines' steps/s and error at dt 1e-3..1e-5 (`lgnn crosscheck --speed chain4 chain16 chain100 T1 --out-dir results`) |",
            "| `stability.md`, `.csv` | hard cases: long horizons, 1000 links, large steps, near-singular geometry, diverging models (`lgnn stability --out results/stability.md`) |",
        ]
    return "\n".join(lines) + "\n"


# Issue 7's accuracy bar for comparing engines' speed: a step whose rollout error
# against the reference is at most this (the default settings' max node error).
ACCURATE = 1e-6


def _fastest_accurate(rows: list[dict], scene: str, solver: str) -> dict | None:
    """`solver`'s fastest row on `scene` whose error is within ACCURATE."""
    ok = [r for r in rows if r["scene"] == scene and r["solver"] == solver and math.isfinite(r["wall_s_per_sim_s"])
          and math.isfinite(r["rollout_error"]) and r["rollout_error"] <= ACCURATE]
    return min(ok, key=lambda r: r["wall_s_per_sim_s"]) if ok else None


def _gpu_section(out: Path) -> list[str]:
    """The GPU tables under `out/gpu/` (written by `lgnn crosscheck --speed` on a lent
    GPU machine, commands in their headers): batched throughput, Lagrangian over MJX
    where a table has both; and the LGNN training-time summary if present."""
    import pandas as pd

    gpu = out / "gpu"
    tables = sorted(gpu.glob("*.csv")) if gpu.is_dir() else []
    if not tables:
        return ["Not measured in this output directory (no `gpu/` tables)."]
    lines = ["Batched ground truth on GPUs, RK4 at dt 1e-3, from the tables in `gpu/` (each `.md` names its command, machine and "
             "versions; `h200x2_*`: one and two H200s of one host, the batch split over the devices by `jax.sharding`).", "",
             "| table | scene | batch | dtype | Lagrangian steps/s | MJX steps/s | Lagrangian / MJX | MuJoCo C steps/s |", "|---" * 8 + "|"]
    for path in tables:
        frame = pd.read_csv(path, comment="#")
        batched = frame[frame["batch"] > 1]
        for (scene, batch), group in batched.groupby(["scene", "batch"], sort=False):
            rate = {r["engine"]: r["steps_per_s"] for _, r in group.iterrows()}
            dtype = group[group["engine"] == "lagrangian"]["dtype"].iloc[0] if "lagrangian" in rate else "—"
            ratio = rate["lagrangian"] / rate["mjx"] if "lagrangian" in rate and "mjx" in rate else float("nan")
            lines.append(f"| {path.stem} | {scene} | {batch} | {dtype} | {_fmt(rate.get('lagrangian', float('nan')))} | "
                         f"{_fmt(rate.get('mjx', float('nan')))} | {'—' if math.isnan(ratio) else f'{ratio:.3g}'} | {_fmt(rate.get('mujoco', float('nan')))} |")
    for path in sorted(gpu.glob("*training*.txt")):
        lines += ["", f"LGNN training on a GPU (`{path.name}`, written by `lgnn benchmark --full --stage train --job lgnn-chain4-s0` "
                  "in a fresh output directory, then `lgnn checkpoint ... --reference results/benchmark/checkpoints/lgnn-chain4-s0.npz`):",
                  "", "```", path.read_text().strip(), "```"]
    return lines


def _gpu_truth_section(out: Path) -> list[str]:
    """The GPU ground-truth tables under `out/gpu/truth/` (`lgnn gpu-truth`) read as
    issue 14's goal: the float32 Lagrangian against the fastest MuJoCo GPU engine that
    is finite and agrees with the reference, per scene and batch (`gpu_truth.against_mujoco`)."""
    rows = gpu_truth.against_mujoco(gpu_truth.load(out / "gpu" / "truth"))
    if not rows:
        return ["Not measured in this output directory (no `gpu/truth/` tables)."]
    lines = [f"lgnn's Lagrangian engine in float32 against the fastest MuJoCo GPU engine (MJX, MuJoCo Warp; either MJCF form) "
             f"that stayed finite in every world and within {gpu_truth.AGREEMENT_MAX:g} of the float64 reference, from the tables in `gpu/truth/` (`lgnn gpu-truth`: RK4 at dt 1e-3, 100 steps; "
             f"commands, machine and versions in each table and in `gpu/truth/README.md`). Error: max node error after the last "
             f"step against the float64 Lagrangian engine. The goal is a ratio of at least {gpu_truth.GOAL_RATIO:g}. Each ratio is "
             "within one run; the machine column says which GPU ran it.", "",
             "| scene | batch | Lagrangian f32 steps/s | its error | fastest agreeing MuJoCo GPU engine | its steps/s | its error | "
             f"ratio | >= {gpu_truth.GOAL_RATIO:g}? | tables | machine | left out |", "|---" * 12 + "|"]
    for r in rows:
        ratio = "—" if math.isnan(r["ratio"]) else f"{r['ratio']:.3g}"
        goal = "—" if math.isnan(r["ratio"]) else ("yes" if r["meets_goal"] else "no")
        lines.append(f"| {r['scene']} | {r['batch']} | {_fmt(r['lagrangian_steps_per_s'])} | {_fmt(r['lagrangian_error'])} | "
                     f"{r['mujoco_engine'] or '—'} | {_fmt(r['mujoco_steps_per_s'])} | {_fmt(r['mujoco_error'])} | {ratio} | {goal} | "
                     f"{r['tables']} | {r['machine'] or '—'} | {escape_markdown_cell(r['note']) or '—'} |")
    return lines


def _form(row: dict) -> str:
    """A MuJoCo speed row's MJCF form; records made before rows kept it say so."""
    return row.get("form") or "not recorded"


def _planar_twin(scene: str, scenes) -> str | None:
    """The planar scene among `scenes` that 3D `scene` adds a dimension to: a pinned chain
    of as many links (chain16 for chain16-3d); None for others."""
    structure = get_scene(scene)
    if structure.dim != 3 or not is_pinned_chain(structure):
        return None
    for other in scenes:
        twin = get_scene(other)
        if twin.dim == 2 and is_pinned_chain(twin) and twin.n_links == structure.n_links:
            return other
    return None


def _third_dimension_lines(rows: list[dict], dt: float) -> list[str]:
    """The speed records' 3D chains beside their planar twins (`_planar_twin`): each
    engine and learned model at the evaluation step `dt`, wall s per simulated s in 2D
    and 3D and their ratio (a model: the median over its seeds, each dimension's own
    grid's model)."""
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    pairs = [(twin, scene) for scene in scenes if (twin := _planar_twin(scene, scenes)) is not None]
    if not pairs:
        return []

    def cost(scene: str) -> dict[str, tuple[float, str]]:
        """`{solver: (median wall s per simulated s, MJCF form)}` at `dt` on `scene`."""
        trained_on = TRAINING_SCENES[get_scene(scene).dim]
        timed: dict[str, list[dict]] = {}
        for r in rows:
            if r["scene"] == scene and math.isclose(r["dt"], dt) and math.isfinite(r["wall_s_per_sim_s"]):
                timed.setdefault(_without_training_scene(r["solver"], trained_on), []).append(r)
        return {solver: (float(np.median([r["wall_s_per_sim_s"] for r in group])), _form(group[0])) for solver, group in timed.items()}

    def device(scene: str) -> str | None:
        return next((r.get("device") for r in rows if r["scene"] == scene), None)

    lines = ["", f"## The third dimension's cost (single trajectory, RK4 at dt {dt:g})", "",
             "Each 3D chain beside the planar chain of as many links: wall s per simulated s in each and their ratio. A learned "
             "model's cell is the median over its seeds, each trained on its own dimension's chain4 (— : not in that dimension's "
             "grid; MJX in the MJCF form it picks, maximal past tree depth 8). MuJoCo's joints: hinges in the plane (one DOF "
             "a link), balls in 3D (three). The two cells of a row come from two records (two processes; commits and machines "
             "in `README.md`), so a ratio carries their run-to-run noise (`benchmark/speed_error.md` gives each record's spread); "
             "a pair timed on different machines says so.",
             "", "| chains | solver | planar: wall s per simulated s | 3D: wall s per simulated s | 3D / planar | MJCF form (planar, 3D) |",
             "|---|---|---|---|---|---|"]
    for planar, spatial in pairs:
        flat, deep = cost(planar), cost(spatial)
        machines = "" if device(planar) == device(spatial) else " (different machines)"
        for solver in [s for s in ("lagrangian", "mujoco", "mjx") if s in flat or s in deep] + [
                s for s in dict.fromkeys([*flat, *deep]) if s not in ("lagrangian", "mujoco", "mjx")]:
            a, b = flat.get(solver, (math.nan, "")), deep.get(solver, (math.nan, ""))
            ratio = "—" if math.isnan(a[0]) or math.isnan(b[0]) else f"{b[0] / a[0]:.3g}{machines}"
            forms = f"{a[1] or '—'}, {b[1] or '—'}" if solver in ("mujoco", "mjx") else "—"
            cells = ("—" if math.isnan(x) else f"{x:.3g}" for x in (a[0], b[0]))
            lines.append(f"| {planar}, {spatial} | {solver} | {' | '.join(cells)} | {ratio} | {forms} |")
    return lines


def _size_lines(size: list[dict], dt: float) -> list[str]:
    """The scaling record's size rows: per solver, a row of seconds per step against
    chain length for each dimension, its fitted exponent, and a `3D / planar` row of
    their ratios. A row without `dim` is planar (records made before 3D rows held only
    planar chains: their key is that of no `spatial_lengths`, `scaling.scaling_key`)."""
    lengths, dims = sorted({r["n_links"] for r in size}), sorted({r.get("dim", 2) for r in size})
    lines = ["", f"## Cost per step against chain length (single trajectory, RK4 at dt {dt:g}, fitted exponent over "
             f"n = {', '.join(map(str, lengths))} links)", ""]
    if len(dims) > 1:
        lines += ["Planar chains and 3D chains of as many links, each with the LGNN of its own dimension's grid; the "
                  "`3D / planar` rows read off the third dimension's cost at each length.", ""]
    lines += ["| solver | chains | " + " | ".join(f"n = {n}: s per step" for n in lengths) + " | exponent | compile s (largest n) |",
              "|---" * (len(lengths) + 4) + "|"]
    for solver in dict.fromkeys(r["solver"] for r in size):
        per_dim = {}
        for dim in dims:
            timed = [r for r in size if r["solver"] == solver and r.get("dim", 2) == dim and math.isfinite(r["s_per_step"])]
            costs = per_dim[dim] = {r["n_links"]: r["s_per_step"] for r in timed}
            if not timed and not any(r["solver"] == solver and r.get("dim", 2) == dim for r in size):
                continue
            exponent = f"{fit_exponent(costs):.2f} (n = {min(costs)}..{max(costs)})" if len(costs) > 1 else "—"
            compile_s = f"{max(timed, key=lambda r: r['n_links'])['compile_s']:.1f}" if timed else "—"
            lines.append(f"| {solver} | {DIMENSION_NAMES.get(dim, f'{dim}D')} | " + " | ".join(f"{costs[n]:.3g}" if n in costs else "—" for n in lengths)
                         + f" | {exponent} | {compile_s} |")
        if per_dim.get(2) and per_dim.get(3):
            lines.append(f"| {solver} | 3D / planar | " + " | ".join(
                f"{per_dim[3][n] / per_dim[2][n]:.3g}" if n in per_dim[2] and n in per_dim[3] else "—" for n in lengths) + " | — | — |")
    lines += [f"- {r['solver']} on {r['scene']}: {r['note']}" for r in size if r.get("note")]
    return lines


def performance_markdown(profile: Profile, rows: list[dict], scaling_record: dict | None = None, out: Path | None = None) -> str:
    """`performance.md`: the speed records read as issue 7's ratios, the scaling record
    as cost against size and batched throughput, and the GPU tables."""
    lines = [
        "# Performance: ground truth and learned rollouts against MuJoCo",
        "",
        f"Written by the benchmark's report stage (`lgnn benchmark{' --full' if profile.name == 'full' else ''} --stage report`) "
        "from the speed-against-error records (`benchmark/runs/speed-error/`, made by `--stage speed`) and the scaling record "
        "(`benchmark/runs/scaling.json`, made by `--stage scaling`); nothing here is edited by hand. Every ratio but the third "
        "dimension's (two records, said there) compares rows timed in the same process on the same machine, compile apart; MuJoCo C is timed on its stepping alone (not the map "
        "from its joint coordinates to node states). Machines per record in `README.md`.",
        "",
        f"## Ground truth against MuJoCo C at equal accuracy (rollout error <= {ACCURATE:g} against the reference)",
        "",
        f"Single trajectory, {rows[0]['horizon_s']:g} s simulated." if rows else "No speed records.",
        "",
        "| scene | Lagrangian: dt, wall s per simulated s | MuJoCo C: dt, wall s per simulated s | Lagrangian / MuJoCo | "
        "Lagrangian compile s | MuJoCo C MJCF form |",
        "|---|---|---|---|---|---|",
    ]
    for scene in dict.fromkeys(r["scene"] for r in rows):
        ours, theirs = _fastest_accurate(rows, scene, "lagrangian"), _fastest_accurate(rows, scene, "mujoco")
        if ours is None or theirs is None:
            lines.append(f"| {scene} | {'—' if ours is None else ours['dt']} | {'—' if theirs is None else theirs['dt']} | — | — | — |")
            continue
        lines.append(f"| {scene} | {ours['dt']:g}, {ours['wall_s_per_sim_s']:.3g} | {theirs['dt']:g}, {theirs['wall_s_per_sim_s']:.3g} | "
                     f"{ours['wall_s_per_sim_s'] / theirs['wall_s_per_sim_s']:.3g} | {ours['compile_s']:.1f} | {_form(theirs)} |")
    lines += _third_dimension_lines(rows, profile.evaluate.dt)
    if scaling_record is not None:
        srows = scaling_record["rows"]
        batch = [r for r in srows if r["kind"] == "batch"]
        env = scaling_record.get("environment", {})
        lines += ["", f"## Batched ground truth against MuJoCo C ({batch[0]['batch'] if batch else 0} initial conditions at once, "
                  f"dt {profile.evaluate.dt:g}, {env.get('device', 'unknown device')})", "",
                  "| scene | Lagrangian steps/s | MuJoCo C steps/s (2 threads) | Lagrangian / MuJoCo |", "|---|---|---|---|"]
        for scene in dict.fromkeys(r["scene"] for r in batch):
            rate = {r["solver"]: r["batch"] / r["s_per_step"] for r in batch if r["scene"] == scene}
            lines.append(f"| {scene} | {rate['lagrangian']:.3g} | {rate['mujoco']:.3g} | {rate['lagrangian'] / rate['mujoco']:.3g} |")
        lines += _size_lines([r for r in srows if r["kind"] == "size"], profile.evaluate.dt)
    lines += [
        "",
        "## Learned rollouts",
        "",
        f"Every learned model is integrated with RK4 at dt {profile.evaluate.dt:g} (4 evaluations a step), not the paper's Verlet at "
        "1e-5; its wall time per simulated second and rollout error are the `learned` rows of `benchmark/speed_error.md`. "
        "LGNN's mass matrix couples only nearby nodes, so its solve uses coloured Hessian-vector products and, on long chains, "
        "the linear-time block elimination; LGN's is low rank plus local (`physics.MassStructure`).",
        "",
        "## GPUs",
        "",
        *(_gpu_section(out) if out is not None else ["Not measured."]),
        "",
        "## Ground truth on GPUs against MuJoCo's GPU engines",
        "",
        *(_gpu_truth_section(out) if out is not None else ["Not measured."]),
        "",
    ]
    return "\n".join(lines)


def stage_sections(profile: Profile, out: Path, sections) -> list[str]:
    """README lines of the registered stages' own sections, in registry order: `sections`
    holds `(name, settings, load, section)` of each stage that has one
    (`lgnn.bench.run.Stage`); each gives its `section(profile, out, load(profile, out))`
    lines, then every setting its records are keyed on (`grid.settings_key`)."""
    lines = []
    for name, settings, load, section in sections:
        lines += section(profile, out, None if load is None else load(profile, out))
        if settings is not None:
            keyed = settings_key(settings(profile))
            lines += ["", f"Settings of the {name} stage: " + "; ".join(f"`{key}` = {value!r}" for key, value in keyed.items()) + "."]
        lines.append("")
    return lines


def write(profile: Profile, out: Path, sections=(), command: str | None = None) -> Path:
    """Write every report file under `out` from the records there (and in the profile's
    `base` folder, read in place), with the registered stages' `sections`
    (`stage_sections`) before the provenance; `command`: what the header says wrote it
    (`_command`). Returns README.md's path."""
    import matplotlib

    matplotlib.use("Agg")
    import pandas as pd

    from lgnn.provenance import environment

    # The commit before this function writes anything: rewriting the committed report
    # files would otherwise mark the report's own header "+dirty".
    env = environment()
    out = Path(out)
    truths, pairs, externals = load_truths(profile, out), load_pairs(profile, out), load_externals(profile, out)
    summary, curves = tables(truths, pairs + externals, profile.evaluate.references)
    bench_dir = out / "benchmark"
    bench_dir.mkdir(parents=True, exist_ok=True)
    write_csv(summary, bench_dir / SUMMARY)
    # A summary written plain by an older lgnn would sit stale beside the new one.
    (bench_dir / "summary.csv").unlink(missing_ok=True)
    write_csv(curves, bench_dir / CURVES)
    speed_rows = load_speed_rows(profile, out)
    # Where each row was read from is the provenance table's, not a column of the table.
    write_csv(pd.DataFrame([{k: v for k, v in r.items() if k != "folder"} for r in speed_rows]), bench_dir / "speed_error.csv")
    write_text_atomic(bench_dir / "speed_error.md", speed_markdown(speed_rows))
    if speed_rows:
        write_text_atomic(out / "performance.md", performance_markdown(profile, speed_rows, load_scaling(profile, out), out))
    mass_records = load_mass(profile, out)
    write_csv(pd.DataFrame([{**{k: m[k] for k in MASS_COLUMNS}, **_env_columns(m)} for _, m in mass_records]),
               bench_dir / "mass_matrix.csv")
    figures_dir = out / "figures"
    figures = []
    # Every model's colour, fixed for the whole report: the profile's grid in order, then
    # any other model recorded (from an earlier grid), by name.
    recorded = sorted({pair.job.model for pair, _ in pairs + externals} | {r["solver"].split()[0] for r in speed_rows if r["kind"] != "engine"})
    colors = model_colors([*model_order(profile), *recorded])
    # Each figure draws its track's models (`track_rows`).
    recorded_pairs = [pair for pair, _ in pairs]
    plots = [
        *((group.file, lambda p, group=group: _plot_error_vs_time(track_rows(curves, recorded_pairs, group.track), list(group.scenes), p,
                                                                  group.trained_on, colors))
          for group in error_figures(profile)),
        ("mass_matrix.png", lambda p: _plot_mass_matrices(mass_records, p)),
        *((f"snapshots_{scene.replace('-', '_')}.png", lambda p, scene=scene: _plot_snapshots(scene, truths, pairs, p, colors))
          for scene in SNAPSHOT_SCENES),
        ("speed_error.png", lambda p: _plot_speed_error(speed_rows, p, colors)),
    ]
    for name, plot in plots:
        if not curves.empty or name in ("mass_matrix.png", "speed_error.png"):
            if plot(figures_dir / name):
                figures.append(name)
    # A figure an earlier report drew and this one does not (its scene left the grid, or
    # its records went) would sit in figures/ unnamed by README.md: removed. Files of
    # other names are never touched.
    for stale in figures_dir.glob("*.png") if figures_dir.is_dir() else ():
        if stale.name not in figures and any(fnmatch.fnmatch(stale.name, pattern) for pattern in REPORT_FIGURES):
            stale.unlink()
    path = out / "README.md"
    write_text_atomic(path, readme(profile, out, (truths, pairs + externals), summary, speed_rows, mass_records, figures, env,
                                   stage_sections(profile, out, sections), command))
    write_text_atomic(out / LEADERBOARD, leaderboard_markdown(profile, out, summary, env, command))
    return path


# ---------------------------------------------------------------------------------
# Leaderboard
# ---------------------------------------------------------------------------------

# The leaderboard's file under the output folder, beside README.md.
LEADERBOARD = "LEADERBOARD.md"
# The metric the leaderboard ranks by.
RANKED_METRIC = "rollout_error"


def write_leaderboard(profile: Profile, out: Path, command: str | None = None) -> Path:
    """Write `LEADERBOARD.md` under `out` alone, from the records there and in the
    profile's base (the statistics `tables` gives README.md's tables); its path."""
    from lgnn.provenance import environment

    env = environment()
    out = Path(out)
    summary, _ = tables(load_truths(profile, out), load_pairs(profile, out) + load_externals(profile, out), profile.evaluate.references)
    path = out / LEADERBOARD
    write_text_atomic(path, leaderboard_markdown(profile, out, summary, env, command))
    return path


def _cell_row(wide, scene: str, model: str) -> dict | None:
    """The summary row a table cell shows (`summary_markdown`): over every seed where
    several, else the one seed's, with its seed count (a trained model's)."""
    match = wide[(wide.scene == scene) & (wide.model == model) & (wide.metric == RANKED_METRIC)]
    if (match.seed == ALL_SEEDS).any():
        match = match[match.seed == ALL_SEEDS]
    if not len(match):
        return None
    row = match.iloc[0].to_dict()
    trained = model not in (REST, EXACT_NO_DRAG) and not model.endswith(EXTERNAL_MARK)
    return {**row, **({"seeds": 1} if trained and row["seed"] != ALL_SEEDS else {})}


def _ranks(values: dict[str, float]) -> dict[str, int]:
    """Competition ranks ("1, 2, 2, 4") of `{model: value}`, lower first; equal values share the better rank."""
    ordered = sorted(values.values())
    return {model: 1 + ordered.index(value) for model, value in values.items()}


def _trained(profile: Profile, out: Path) -> dict[str, tuple[str, str]]:
    """`{job label: (parameters, training)}` of the profile's trained models with checkpoints:
    learned parameters of the best epoch (training-set statistics apart) and the median
    over seeds of the recorded training minutes, with the device (GPU-minutes only on a
    GPU); "not recorded" where a checkpoint holds no time."""
    from lgnn.learn import checkpoints as checkpoint_files

    layout = store.layout(profile, out)
    found: dict[str, list] = {}
    for job, state in load_checkpoints(profile, out):
        meta, _ = checkpoint_files.read(layout.found(layout.checkpoint(job)))
        found.setdefault(job.label, []).append((job, state, meta))
    result = {}
    for model, runs in found.items():
        _, state, meta = runs[0]
        count = (checkpoint_files.learned_parameter_count(state.best_params) if checkpoint_files.has_parameters(meta)
                 else meta[checkpoint_files.WITHOUT_PARAMETERS]["parameters"])
        times = [state.elapsed_s for _, state, _ in runs if state.elapsed_s > 0]
        devices = sorted({meta.get("environment", {}).get("device", "unknown device").split(";")[0] for _, _, meta in runs})
        unit = "GPU-minutes" if all("(gpu)" in device for device in devices) else "minutes"
        training = (f"{np.median(times) / 60:.3g} {unit} ({len(times)} seed{'s' if len(times) != 1 else ''}, median; {', '.join(devices)})"
                    if times else "not recorded")
        result[model] = (f"{count:,}", training)
    return result


def leaderboards(pairs: list[Pair]) -> list[tuple[str, int, list[Pair]]]:
    """`(heading, dimension, pairs)` of each leaderboard: per dimension, the paper's
    track (models trained on its main training scene, `TRAINING_SCENES`), then the
    transfer track's (models trained on varied draws, `grid.TRANSFER_TRACK`) per
    dimension of the scenes they are evaluated on."""
    boards = [(f"{DIMENSION_NAMES.get(dim, f'{dim}D')}: trained on {main}", dim, [p for p in pairs if p.job.scene == main and not p.job.varied_draws])
              for dim, main in TRAINING_SCENES.items()]
    transfer: dict[int, list[Pair]] = {}
    for pair in pairs:
        if pair.job.track == TRANSFER_TRACK:
            transfer.setdefault(get_scene(pair.scene).dim, []).append(pair)
    for dim, board in transfer.items():
        sources = ", ".join(dict.fromkeys(p.job.trained_on for p in board))
        boards.append((f"{DIMENSION_NAMES.get(dim, f'{dim}D')}, transfer track: trained on {sources}", dim, board))
    return boards


# What a leaderboard cell without a record says (`_missing_cell`).
NOT_EVALUATED = "not evaluated"
FIXED_SIZE_CELL = "— (fixed size)"


def _missing_cell(label: str, scene: str, board: list[Pair]) -> str:
    """A leaderboard cell with no record: a pair of the board's grid not evaluated yet, a
    fixed-size model on a scene it cannot run (the grid evaluates it on its training
    system alone), or a pair outside the grid."""
    if any((pair.label, pair.scene) == (label, scene) for pair in board):
        return NOT_EVALUATED
    fixed = any(pair.label == label and get_spec(pair.job.model).fixed_size for pair in board if not pair.job.external)
    return FIXED_SIZE_CELL if fixed else "—"


def leaderboard_markdown(profile: Profile, out: Path, summary, env: dict, command: str | None = None) -> str:
    """`LEADERBOARD.md`: per leaderboard (`leaderboards`: each dimension's paper track
    and transfer track), one row per model it ranks and per external prediction, the rollout error
    cell of README.md's table on each scene of the grid with its rank there, parameters,
    training minutes, and the overall rank (module's rule, stated in the file)."""
    unrankable = _unrankable(out)
    wide = (summary.pivot_table(index=["scene", "model", "seed", "metric"], columns="statistic", values="value", aggfunc="first").reset_index()
            if not summary.empty else None)
    trained = _trained(profile, out)
    shown = "lgnn leaderboard" + (" --full" if profile.name == "full" else f" (profile {profile.name})")
    lines = [f"# Leaderboard ({profile.name} profile)", "",
             f"Written by `{command or shown}` from the benchmark's records (`benchmark/runs/` of this folder"
             + (f" and of `{profile.base}`" if profile.base else "") + "); nothing here is edited by hand. "
             f"Written at commit {env['commit']}. Every cell is the one of `README.md`'s table \"{metrics.METRICS[RANKED_METRIC].heading}\" "
             "(the same records and statistics, `benchmark/summary.csv.gz`): geometric mean over frames and initial conditions "
             "[bootstrap 95% interval], over every training seed where several; lower is better.", "",
             "**Ranks.** On each scene the models with a number are ranked by that geometric mean, lowest first; equal values share "
             "the better rank. A scene that cannot rank models (the reference does not converge in dt) ranks none. The overall rank "
             "orders the models with a number on every ranked scene of the table by the mean of their scene ranks; ties are broken by "
             "the geometric mean of their cells over those scenes, then by name. A model without a number on every scene has no "
             "overall rank and follows, by name. `rest` (the initial state held) is the bar any model must clear, never ranked. "
             f"\"{NOT_EVALUATED}\": a pair of the grid with no record yet; \"{FIXED_SIZE_CELL}\": a model tied to its training "
             "system's size (CLNN, CHNN), which the grid evaluates on that system alone; \"—\": a pair outside the grid "
             "(an external prediction answers only the scenes it was made for).", "",
             "**Parameters and training** come from the checkpoints: the learned parameters of the best epoch (training-set "
             "statistics apart) and the training minutes recorded in them (median over seeds; seeds trained together in one "
             "program share one wall time), with the device; GPU-minutes only where every seed trained on a GPU. Rows marked "
             f"`{EXTERNAL_MARK.strip()}` are predictions made outside lgnn from the same initial conditions (no checkpoint, "
             "parameters or training time here).", "",
             "**Add a row.** A model of your own (`docs/models.md`), trained with the full profile's recipe and ranked beside these "
             "results, read in place:", "", "```bash", "lgnn benchmark --full --add-model my_model.py:SPEC --with-results results", "```", "",
             "or predictions made in another framework from the exported initial conditions (`docs/benchmark.md`, \"Predictions made "
             "elsewhere\"):", "", "```bash", "lgnn benchmark --full --add-predictions chain8-mine.npz --with-results results", "```", "",
             "Then open a pull request adding what the command wrote under its output folder: the checkpoint "
             "(`benchmark/checkpoints/JOB.npz`) and records (`benchmark/runs/JOB/`) of a model, with its file and an `[[add]]` "
             "entry of the full profile, or the records `benchmark/runs/external/MODEL/` of predictions. This file is then "
             f"regenerated from the records: `{shown}`.", ""]
    if wide is None:
        return "\n".join([*lines, "(no results)", ""])
    for heading, dim, board in leaderboards(evaluation_pairs(profile)):
        scenes = [s for s in scene_groups([p.scene for p in board], board[0].job.track if board else PAPER_TRACK).get(dim, [])]
        if not scenes:
            continue
        names = {p.label: p.job.model + ("" if p.projected else " (unprojected)") for p in board if p.scene in scenes}
        labels = list(names)
        labels += sorted({m for m in wide.model.unique() if m.endswith(EXTERNAL_MARK) and m not in labels
                          and (wide[wide.model == m].scene.isin(scenes)).any()})
        cells = {label: {scene: _cell_row(wide, scene, label) for scene in scenes} for label in labels}
        ranked = [scene for scene in scenes if scene not in unrankable]
        ranks = {scene: _ranks({label: cells[label][scene]["gmean"] for label in labels if cells[label][scene] is not None
                                and math.isfinite(cells[label][scene].get("gmean", math.nan))}) for scene in ranked}
        complete = [label for label in labels if all(label in ranks[scene] for scene in ranked)]
        mean_rank = {label: float(np.mean([ranks[scene][label] for scene in ranked])) for label in complete}
        log_mean = {label: float(np.mean([math.log(cells[label][scene]["gmean"]) for scene in ranked])) for label in complete}
        order = sorted(complete, key=lambda label: (mean_rank[label], log_mean[label], label))
        order += sorted(label for label in labels if label not in complete)
        lines += [f"## {heading}", "",
                  "| rank | model | parameters | training | " + " | ".join(
                      f"{scene}{' (not rankable)' if scene in unrankable else ''}" for scene in scenes) + " | mean scene rank |",
                  "|---" * (len(scenes) + 5) + "|"]
        for k, label in enumerate(order):
            model = names.get(label, label)
            parameters, training = (("—", "— (external)") if label.endswith(EXTERNAL_MARK) else
                                    trained.get(label.removesuffix(" (unprojected)"), ("not recorded", "not recorded")))
            row = [str(k + 1) if label in mean_rank else "—", model, parameters, training]
            for scene in scenes:
                cell = cells[label][scene]
                row.append(_missing_cell(label, scene, board) if cell is None else "not rankable" if scene in unrankable
                           else f"{_interval(cell)} (rank {ranks[scene][label]})" if label in ranks[scene] else _interval(cell))
            row.append(f"{mean_rank[label]:.2f}" if label in mean_rank else f"— ({sum(label in ranks[s] for s in ranked)} of {len(ranked)} scenes)")
            lines.append("| " + " | ".join(row) + " |")
        rest = [_cell_row(wide, scene, REST) for scene in scenes]
        lines.append("| — | rest (baseline) | — | — | " + " | ".join("" if r is None else _interval(r) for r in rest) + " | — |")
        lines.append("")
    return "\n".join(lines)
