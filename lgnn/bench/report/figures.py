"""The report's figures: error against time, learned mass matrices, snapshots of the
motion and speed against error, each a PNG of at most 256 colours under `figures/`, in
each model's fixed colour (`model_colors`)."""

from __future__ import annotations

import fnmatch
import math
import os
from pathlib import Path

import numpy as np

from lgnn import metrics
from lgnn.bench.grid import SNAPSHOT_SCENES, TRAINING_SCENES
from lgnn.bench.profiles import Profile, error_figures, model_order
from lgnn.bench.stages.evaluate import SNAPSHOT_DT
from lgnn.bench.report.summary import track_rows, without_training_scene
from lgnn.files import atomic_path
from lgnn.scene import get_scene

# The built-in models' colours and the rest baseline's (the committed figures use them).
COLORS = {"lgnn": "C0", "gns": "C1", "lgn": "C2", "clnn": "C3", "rest": "0.5", "lgnn-mp1": "C4", "lgnn-mp2": "C5", "lgnn-notebook": "C6",
          "gns-10-128": "C8", "cgnode": "C9", "chgn": "#7b4173", "chnn": "#393b79"}
# Colours no built-in has (tab20b's darker shades; not C7, a grey beside the rest
# baseline's), given in turn to every other model (`model_colors`).
SPARE_COLORS = ("#637939", "#843c39", "#8c6d31", "#5254a3", "#8ca252", "#bd9e39", "#ad494a", "#a55194")
# How error figures draw a model rolled out without projection (`Pair.projected`): its
# projected row's colour, dashed.
UNPROJECTED_STYLE = "--"
# The names of the figures the report draws under `figures/` (and removes when it no
# longer draws them).
REPORT_FIGURES = ("error_vs_time_*.png", "snapshots_*.png", "mass_matrix.png", "speed_error.png")


def model_colors(models) -> dict[str, str]:
    """`{model: colour}`: a built-in's own (`COLORS`); every other of `models`, in the
    order given, the next of `SPARE_COLORS` (repeating only past the last of them)."""
    others = [model for model in dict.fromkeys(models) if model not in COLORS]
    return {**COLORS, **{model: SPARE_COLORS[k % len(SPARE_COLORS)] for k, model in enumerate(others)}}


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


def _plot_error_vs_time(curves, scenes: list[str], path: Path, trained_on: str, colors: dict[str, str] | None = None,
                        labels: dict[str, str] | None = None) -> bool:
    """Error against time of every model on `scenes` (those with curves; the title
    names them, so a profile without some scenes is not mislabelled), a line per
    training seed in the model's colour (`colors`, default `model_colors` of the curves'
    models), a row per metric of `labels` (default `error_axis_labels()`)."""
    import matplotlib.pyplot as plt

    scenes = [s for s in scenes if s in set(curves["scene"].unique())]
    if not scenes:
        return False
    title = (f"Error against time: {', '.join(scenes)} (trained on {trained_on})\n"
             f"errors are clipped to [{metrics.ERROR_FLOOR:g}, 1]: 1 means diverged (or no better than that); band: interval over initial conditions")
    colors = colors or model_colors(model.split()[0] for model in curves["model"].unique())
    labels = labels or error_axis_labels()
    fig, axes = plt.subplots(len(labels), len(scenes), figsize=(4.2 * len(scenes), 3.2 * len(labels)), squeeze=False, sharex=True)
    # Each panel's rows, split once (rows in the curves' order): filtering the whole table
    # per panel was a fifth of the full report's time.
    panels = {key: rows for key, rows in curves.groupby(["scene", "metric"], sort=False)}
    empty = curves.iloc[:0]
    for col, scene in enumerate(scenes):
        for row, metric in enumerate(labels):
            ax = axes[row, col]
            sub = panels.get((scene, metric), empty)
            for model in sub["model"].unique():
                if model == "ground truth":
                    continue
                kind, name = model.split()[0], without_training_scene(model, trained_on)
                # One line per seed (the model's label on the first only), never one
                # line running from the last frame of a seed back to t = 0 of the next.
                for k, (_, m) in enumerate(sub[sub.model == model].groupby("seed", sort=True)):
                    g = m[m.statistic == "gmean"]
                    ax.plot(g.t, g.value, UNPROJECTED_STYLE if "(unprojected)" in model else "-", color=colors.get(kind),
                            label=(name.upper() if kind == name else name) if k == 0 else None)
                    lo, hi = m[m.statistic == "low"], m[m.statistic == "high"]
                    if np.isfinite(lo.value.to_numpy()).any():
                        ax.fill_between(lo.t, lo.value, hi.value, color=colors.get(kind), alpha=0.2, linewidth=0)
            floor = panels.get((scene, "chaos_floor"), empty)
            floor = floor[floor.statistic == "gmean"]
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
        label = without_training_scene(pair.label, trained_on).upper()
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


# The committed figures' marker of each built-in engine, and where its dt labels sit
# (a side per engine, so the engines' labels at one dt do not overprint each other).
ENGINE_MARKERS = {"lagrangian": ("o", (4, 3)), "mujoco": ("s", (4, -9)), "mjx": ("^", (-26, 3))}
# Markers and label sides given in turn to every other engine (`engine_markers`).
SPARE_MARKERS = (("D", (4, 9)), ("v", (-26, -9)), ("P", (6, 0)), ("X", (-28, 0)), ("h", (4, 15)), ("*", (-26, 15)))


def engine_markers(engines) -> tuple[dict[str, str], dict[str, tuple[int, int]]]:
    """`({engine: marker}, {engine: dt label offset})`: a built-in's own
    (`ENGINE_MARKERS`); every other of `engines`, in the order given, the next of
    `SPARE_MARKERS` (an engine registered by a researcher is drawn like the built-ins)."""
    others = [engine for engine in dict.fromkeys(engines) if engine not in ENGINE_MARKERS]
    styles = {**ENGINE_MARKERS, **{engine: SPARE_MARKERS[k % len(SPARE_MARKERS)] for k, engine in enumerate(others)}}
    return {engine: marker for engine, (marker, _) in styles.items()}, {engine: offset for engine, (_, offset) in styles.items()}


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

    markers, offsets = engine_markers(r["solver"] for r in rows if r["kind"] == "engine")
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


# The figures are drawn in processes of their own (one per usable core) when the curves
# have this many rows: the full profile's 18 figures (a million rows of curves) were two
# thirds of its report's time, while a process costs seconds to start (it imports lgnn
# and matplotlib), more than all of the quick profile's small figures take.
PARALLEL_CURVE_ROWS = 100_000


def _drawn(plots: list, figures_dir: Path, parallel: bool) -> list[bool]:
    """Each `(name, plot, arguments)` drawn as `plot(path=figures_dir / name,
    **arguments)`, whether it drew, in order: in processes of their own where
    `parallel` and the host has more than one usable core, else one after another. A
    figure is the same file either way (matplotlib's drawing is deterministic)."""
    workers = min(len(plots), len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)
    if not parallel or workers < 2:
        return [plot(path=figures_dir / name, **arguments) for name, plot, arguments in plots]
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    # Spawned, not forked: the parent holds JAX's threads, which a fork would copy stopped.
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = [pool.submit(plot, path=figures_dir / name, **arguments) for name, plot, arguments in plots]
        return [future.result() for future in futures]


def draw(profile: Profile, figures_dir: Path, truths: dict, pairs: list, externals: list, curves, speed_rows: list[dict],
         mass_records: list) -> list[str]:
    """Draw every figure the records allow under `figures_dir` (an error figure per
    `profiles.error_figures` group, the mass matrices, the snapshots of `SNAPSHOT_SCENES`,
    speed against error), remove the ones an earlier report drew and this one does not,
    and return the names drawn, in order."""
    # Every model's colour, fixed for the whole report: the profile's grid in order, then
    # any other model recorded (from an earlier grid), by name.
    recorded = sorted({pair.job.model for pair, _ in pairs + externals} | {r["solver"].split()[0] for r in speed_rows if r["kind"] != "engine"})
    colors = model_colors([*model_order(profile), *recorded])
    # Each figure draws its track's models (`track_rows`); a snapshot figure its scene's
    # records only (each plot's arguments go to another process whole).
    recorded_pairs = [pair for pair, _ in pairs]
    labels = error_axis_labels()
    plots = [
        *((group.file, _plot_error_vs_time, dict(curves=track_rows(curves, recorded_pairs, group.track), scenes=list(group.scenes),
                                                  trained_on=group.trained_on, colors=colors, labels=labels))
          for group in error_figures(profile)),
        ("mass_matrix.png", _plot_mass_matrices, dict(records=mass_records)),
        *((f"snapshots_{scene.replace('-', '_')}.png", _plot_snapshots,
           dict(scene=scene, truths={s: r for s, r in truths.items() if s == scene}, pairs=[(p, r) for p, r in pairs if p.scene == scene],
                colors=colors))
          for scene in SNAPSHOT_SCENES),
        ("speed_error.png", _plot_speed_error, dict(rows=speed_rows, colors=colors)),
    ]
    plots = [plot for plot in plots if not curves.empty or plot[0] in ("mass_matrix.png", "speed_error.png")]
    figures = [name for (name, _, _), drawn in zip(plots, _drawn(plots, figures_dir, parallel=len(curves) >= PARALLEL_CURVE_ROWS)) if drawn]
    # A figure an earlier report drew and this one does not (its scene left the grid, or
    # its records went) would sit in figures/ unnamed by README.md: removed. Files of
    # other names are never touched.
    for stale in figures_dir.glob("*.png") if figures_dir.is_dir() else ():
        if stale.name not in figures and any(fnmatch.fnmatch(stale.name, pattern) for pattern in REPORT_FIGURES):
            stale.unlink()
    return figures
