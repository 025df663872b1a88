"""Pictures of trajectories: an animation of the motion, and error and energy against time.

- `animate(paths, out)`: the trajectory files drawn over each other (the first, usually
  the ground truth, underneath in a thick light line; the others, learned models, over
  it), rods as lines between nodes, pinned nodes as black triangles, a legend entry per
  file and a time stamp, as a GIF (Pillow) or MP4 (ffmpeg, if installed).
- `plot(paths, out, metric)`: a registered metric (`lgnn.metrics.METRICS`; default the
  per-node RMS position error, m) against the first file, log scale, and true energy
  (J) against time (s), one line per file.

The drawing takes node positions of shape (frames, nodes, dim) and maps them to the
picture plane with a `projection` ((..., dim) -> (..., 2)); `planar` is the identity on
the planar scenes of today, and a 3D scene needs only a projection of its own.
Scenes and frame times come from the files (`lgnn.bench.evaluation.load_trajectories`).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

import numpy as np

from lgnn import metrics
from lgnn.bench.evaluation import file_reference, load_trajectories
from lgnn.engines.base import Trajectory
from lgnn.errors import ConfigError
from lgnn.files import atomic_path, check_writable

Projection = Callable[[np.ndarray], np.ndarray]
# Playback: frames per second of the animation, and simulated seconds per real second.
FPS = 30
SPEED = 1.0
# Margin around the reference's extent, in fractions of that extent.
MARGIN = 0.1
ANIMATION_SUFFIXES = (".gif", ".mp4")


def planar(q: np.ndarray) -> np.ndarray:
    """The picture-plane projection of planar positions (..., 2): the identity."""
    if np.shape(q)[-1] != 2:
        raise ConfigError(f"positions of dimension {np.shape(q)[-1]}: only planar (2D) trajectories can be drawn for now")
    return np.asarray(q)


def label(path: str | os.PathLike, trajectory: Trajectory) -> str:
    """Legend entry of a trajectory file: its name and what made it (a model, an engine)."""
    if "model" in trajectory.metadata:
        source = f"model {trajectory.metadata['model'].get('name', '?')}"
    else:
        source = trajectory.metadata.get("engine", {}).get("name", "lagrangian")
    return f"{Path(path).name} ({source})"


def frame_indices(t: np.ndarray, frames: int, fps: float, speed: float) -> np.ndarray:
    """Indices of the trajectory frames shown: one every `speed / fps` simulated seconds
    (at least every frame), from the first to the last of `frames`."""
    frame_dt = float(t[1] - t[0]) if frames > 1 else 1.0
    stride = max(1, round(speed / (fps * frame_dt)))
    return np.arange(0, frames, stride)


def _limits(points: np.ndarray) -> tuple[tuple[float, float], tuple[float, float]]:
    """Square-ish axis limits around the finite `points` (..., 2) with a margin."""
    flat = points.reshape(-1, 2)
    flat = flat[np.isfinite(flat).all(axis=1)]
    low, high = flat.min(axis=0), flat.max(axis=0)
    pad = MARGIN * max(float(np.max(high - low)), 1e-9)
    return (low[0] - pad, high[0] + pad), (low[1] - pad, high[1] + pad)


def _writer(out: Path, fps: float):
    from matplotlib import animation

    if out.suffix == ".gif":
        return animation.PillowWriter(fps=fps)
    if out.suffix == ".mp4":
        if not animation.writers.is_available("ffmpeg"):
            raise ConfigError(f"{out}: writing .mp4 needs ffmpeg, which is not installed: write a .gif instead (--out {out.with_suffix('.gif')})")
        return animation.FFMpegWriter(fps=fps)
    raise ConfigError(f"{out}: an animation is a .gif or .mp4 file, got {out.suffix or 'no suffix'!r}")


def animate(paths, out: str | os.PathLike, fps: float = FPS, speed: float = SPEED, projection: Projection = planar) -> int:
    """Write the animation of the trajectory files `paths` (module docstring) to `out`
    (.gif or .mp4), atomically; the number of animation frames."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import animation

    out = check_writable(out)
    writer = _writer(out, fps)
    scene, trajectories, frames = load_trajectories(paths)
    points = [projection(np.asarray(trajectory.q[:frames], np.float64)) for trajectory in trajectories]
    shown = frame_indices(trajectories[0].t, frames, fps, speed)
    i, j = np.asarray(scene.edge_index).T
    figure, axes = plt.subplots(figsize=(5, 5), dpi=80)
    xlim, ylim = _limits(points[0])
    axes.set(xlim=xlim, ylim=ylim, aspect="equal", xlabel="x (m)", ylabel="y (m)", title=scene.name)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    rods = []
    for k, (path, trajectory) in enumerate(zip(paths, trajectories)):
        # The first file (the reference) underneath, thick and light; the others over it.
        width, alpha = (6, 0.35) if k == 0 else (2, 1.0)
        lines = axes.plot(np.full((2, len(i)), np.nan), np.full((2, len(i)), np.nan), color=colours[k % len(colours)],
                          linewidth=width, alpha=alpha, solid_capstyle="round", zorder=1 + k)
        lines[0].set_label(label(path, trajectory))
        rods.append(lines)
    pins = axes.plot(*points[0][0, list(scene.pinned)].T.reshape(2, -1), "k^", markersize=9, zorder=10, label="pinned node")[0]
    # Below the axes: inside them, long file names would cover the time stamp or the motion.
    axes.legend(loc="upper center", bbox_to_anchor=(0.5, -0.12), fontsize=7)
    figure.subplots_adjust(bottom=0.25)
    stamp = axes.text(0.03, 0.96, "", transform=axes.transAxes, va="top", family="monospace")

    def draw(frame: int):
        for lines, xy in zip(rods, points):
            for line, a, b in zip(lines, xy[frame, i], xy[frame, j]):
                line.set_data([a[0], b[0]], [a[1], b[1]])
        stamp.set_text(f"t = {trajectories[0].t[frame]:.3f} s")
        return [*sum(rods, []), pins, stamp]

    movie = animation.FuncAnimation(figure, draw, frames=shown, blit=False)
    try:
        with atomic_path(out) as tmp:
            movie.save(tmp, writer=writer)
    finally:
        plt.close(figure)
    return len(shown)


# The metric `plot` draws unless told: in lengths, so it does not shrink as a structure grows.
PLOT_METRIC = "node_rms_error"


def plot(paths, out: str | os.PathLike, metric: str = PLOT_METRIC) -> None:
    """Write the error and energy figure of the trajectory files `paths` (module
    docstring), the error `metric` (a name of `lgnn.metrics.METRICS`), to `out` (any
    format matplotlib writes: .png, .pdf, .svg), atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from matplotlib.backends.backend_agg import FigureCanvasAgg

    out = check_writable(out)
    # The format is the suffix's, checked here: matplotlib would otherwise read it off the temporary file's name.
    formats = FigureCanvasAgg.get_supported_filetypes()
    if out.suffix.lstrip(".").lower() not in formats:
        raise ConfigError(f"{out}: a figure is one of {', '.join('.' + f for f in sorted(formats))}, got {out.suffix or 'no suffix'!r}")
    scene, trajectories, frames = load_trajectories(paths)
    reference = trajectories[0]
    t = reference.t[:frames]
    figure, (error_axes, energy_axes) = plt.subplots(2, 1, figsize=(6, 6), sharex=True, dpi=100)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for k, (path, trajectory) in enumerate(zip(paths, trajectories)):
        colour, name = colours[k % len(colours)], label(path, trajectory)
        batch = file_reference(scene, trajectory, frames)
        energy_axes.plot(t, batch.energy[0], color=colour, label=name, linewidth=3 if k == 0 else 1.5, alpha=0.5 if k == 0 else 1.0)
        if k == 0:
            truth = batch
            continue
        scored = metrics.score_rollouts(scene, batch, truth, name, Path(paths[0]).name, names=(metric,))
        error_axes.semilogy(scored.t, scored.errors[metric][0], color=colour, label=name)
        if scored.diverged[0] >= 0:
            error_axes.axvline(t[scored.diverged[0]], color=colour, linestyle=":", label=f"{Path(path).name} diverged")
    if len(trajectories) > 1:
        error_axes.legend(fontsize=7)
    else:
        error_axes.text(0.5, 0.5, "one file: nothing to compare", transform=error_axes.transAxes, ha="center")
    drawn = metrics.METRICS[metric]
    error_axes.set(ylabel=drawn.title[0].lower() + drawn.title[1:] + ("" if drawn.unit == "1" else f" ({drawn.unit})"), title=f"{scene.name}: error against {Path(paths[0]).name}")
    energy_axes.set(xlabel="time (s)", ylabel="true energy H = T + V (J)")
    energy_axes.ticklabel_format(axis="y", useOffset=False)  # a conserved energy's tiny range reads as values, not an offset
    energy_axes.legend(fontsize=7)
    figure.tight_layout()
    try:
        with atomic_path(out) as tmp:
            figure.savefig(tmp, format=out.suffix.lstrip(".").lower())
    finally:
        plt.close(figure)
