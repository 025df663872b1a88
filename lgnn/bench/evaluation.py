"""Scoring anything against anything: a checkpoint on any scene, or two trajectory files.

The benchmark's evaluation stage (`lgnn.bench.stages.evaluate`) scores the grid's
models on the grid's scenes; this module gives the same metrics through the same
function (`lgnn.metrics.score_rollouts`: every metric of the registry
`lgnn.metrics.METRICS`, divergence; their geometric mean over frames and initial
conditions with a bootstrap interval, `lgnn.metrics.summarise`) to the `lgnn
evaluate` and `lgnn compare` commands.

- `evaluate_model(model, params, scene, config, states)`: the model's rollouts from the
  initial `states` (C, N, D), as an engine (`ModelEngine`), scored against the Lagrangian engine and MuJoCo C run
  with the same settings. The model's rollout is not stopped at divergence (its frames
  from there count as each metric's maximum, as in the benchmark); a reference that
  diverges stops with `SimulationError` (an error against it would mean nothing).
- `compare_trajectories(reference, other)`: one trajectory file against another (the
  scene from the reference's metadata).
- Every score is a `lgnn.metrics.Scored` of `score_rollouts` (the evaluate stage's
  type too); `frame_csv`
  (tidy: `scene, model, reference, initial_condition, t, metric, value`) and
  `summary_rows` turn a list of them into tables; `write_outputs` writes them.

Units: positions in the scene's length unit (m), energies in its energy unit (J),
times in s; the relative errors are dimensionless.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from pathlib import Path

import numpy as np

from lgnn import metrics, sharding
from lgnn.bench.profiles import ROLLOUTS_PER_CALL
from lgnn.bench.tables import write_table
from lgnn.engines import ENGINES, get_engine
from lgnn.engines.base import Integration, SimulationConfig, Trajectory
from lgnn.errors import ConfigError
from lgnn.files import write_text_atomic
from lgnn.learn import models
from lgnn.metrics import Scored
from lgnn.runtime import in_background
from lgnn.scene import Scene, State, scene_from_dict

# Initial conditions per compiled model rollout (`batched_rollouts`) on a CPU: the
# benchmark's evaluate stage's (8 cost 1.4x the stage's time per initial condition on
# chain8, 2 cores). On an accelerator the whole batch is one program: a rollout there is
# latency-bound, so 8 per call took 13x the calls (chain16 x 100 on an H100: 43 s of a
# 78 s `lgnn evaluate`).
CPU_CHUNK = ROLLOUTS_PER_CALL
# What `lgnn evaluate` scores a model against: the exact Lagrangian engine and MuJoCo C,
# run with the model's settings.
REFERENCES = ("lagrangian", "mujoco")


def evaluate_model(model: models.ModelConfig, params: dict, scene: Scene, config: SimulationConfig, states: State,
                   integration: Integration = Integration(), progress: bool = False) -> tuple[list[Scored], dict[str, Trajectory]]:
    """The model's rollouts from `states` (C, N, D) scored against the Lagrangian engine
    and MuJoCo C (the same `config`; the model and the Lagrangian engine integrated by
    `integration`, MuJoCo by its RK4), and the three trajectories of initial condition 0
    (`{"model", "lagrangian", "mujoco"}`, for `lgnn animate` and `lgnn plot`)."""
    models.check_compatible(model, scene)
    states = State(np.asarray(states.q, np.float64), np.asarray(states.qd, np.float64))
    # The references run beside the model's rollouts (MuJoCo C's batch on every core
    # while JAX runs the model), waited for only to score.
    references_when_done = {name: in_background(functools.partial(_reference, name, scene, config, states, integration, progress))
                            for name in REFERENCES}
    # The model is an engine, rolled out as the references are; it is not stopped at a
    # divergence (the frames from there count as each metric's maximum). The params are
    # an argument of the compiled program: another checkpoint of the same model config
    # compiles nothing.
    chunk = CPU_CHUNK if sharding.platform() == "cpu" else None
    engine = models.ModelEngine(model, params, progress=progress, integration=integration, stop_at_divergence=False, chunk=chunk)
    predicted = engine.rollout(scene, config, states)
    references = {name: when_done() for name, when_done in references_when_done.items()}
    # The engine's trajectories carry their true energies: scored as they are against each reference.
    scored = [metrics.score_rollouts(scene, predicted, truth, model.name, name) for name, truth in references.items()]
    kept = dataclasses.replace(predicted.member(0), metadata={**references["lagrangian"].metadata, "model": model.to_dict()})
    return scored, {"model": kept, **{name: truth.member(0) for name, truth in references.items()}}


def evaluate_on_scenes(model: models.ModelConfig, params: dict, scenes: list[Scene], config: SimulationConfig, initial_conditions: int = 1,
                       seed: int = 0, integration: Integration = Integration(), progress: bool = False) -> tuple[list[Scored], dict[tuple[str, str], Trajectory]]:
    """`evaluate_model` on each scene from its initial states
    (`physics.own_or_sampled_states`: its own for 1, else `initial_conditions` sampled
    by `seed`), every scene checked against the model before any rollout: the scores,
    and the trajectories of initial condition 0 by `(scene name, engine)` (`lgnn
    evaluate`, `lgnn.evaluate`)."""
    from lgnn import physics

    for scene in scenes:
        models.check_compatible(model, scene)
    scored, trajectories = [], {}
    for scene in scenes:
        states = physics.own_or_sampled_states(scene, initial_conditions, seed)
        scene_scores, kept = evaluate_model(model, params, scene, config, states, integration, progress=progress)
        scored += scene_scores
        trajectories.update({(scene.name, engine): trajectory for engine, trajectory in kept.items()})
    return scored, trajectories


def _reference(name: str, scene: Scene, config: SimulationConfig, states: State, integration: Integration, progress: bool) -> Trajectory:
    """Engine `name`'s rollouts, with `integration` where the engine takes one."""
    return get_engine(name, progress=progress, integration=integration if ENGINES[name].integrates else None).rollout(scene, config, states)


def trajectory_scene(trajectory: Trajectory, path: str | os.PathLike) -> Scene:
    """The scene a trajectory file was made on (its metadata's `scene`)."""
    if "scene" not in trajectory.metadata:
        raise ConfigError(f"{path}: the trajectory file names no scene (write it with lgnn simulate or lgnn rollout)")
    return scene_from_dict(trajectory.metadata["scene"])


def load_trajectories(paths) -> tuple[Scene, list[Trajectory], int]:
    """`(scene, trajectories, frames)`: the files at `paths`, the first one's scene, and
    the frames they share. `ConfigError` (one line) if their shapes or frame times
    differ (a shorter file, a rollout that stopped, is compared over its frames)."""
    trajectories = [Trajectory.load(path) for path in paths]
    scene = trajectory_scene(trajectories[0], paths[0])
    for path, trajectory in zip(paths, trajectories):
        if trajectory.q.ndim != 3 or trajectory.q.shape[1:] != (scene.n_nodes, scene.dim):
            raise ConfigError(f"{path}: positions of shape {trajectory.q.shape}, expected (frames, {scene.n_nodes}, {scene.dim}) "
                              f"as in {paths[0]}")
    frames = min(len(trajectory.t) for trajectory in trajectories)
    for path, trajectory in zip(paths[1:], trajectories[1:]):
        if not np.allclose(trajectory.t[:frames], trajectories[0].t[:frames], rtol=1e-9, atol=1e-12):
            raise ConfigError(f"{path}: frame times differ from {paths[0]}'s (simulate both with the same --frame-dt)")
    return scene, trajectories, frames


def compare_trajectories(paths) -> tuple[Scored, list[str]]:
    """The second file of `paths` (two trajectory files) scored against the first, over
    the frames they share, and notes on what differs (frame counts, scenes)."""
    scene, (reference, other), frames = load_trajectories(paths)
    notes = []
    if len(reference.t) != len(other.t):
        notes.append(f"compared over the {frames} frames both files have ({len(reference.t)} and {len(other.t)})")
    if "scene" in other.metadata and other.metadata["scene"] != reference.metadata["scene"]:
        notes.append(f"the files' scenes differ; energies are {scene.name}'s (from {paths[0]})")
    scored = metrics.score_rollouts(scene, file_reference(scene, other, frames), file_reference(scene, reference, frames),
                                    Path(paths[1]).name, Path(paths[0]).name)
    return scored, notes


def as_batch(trajectory: Trajectory, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """A trajectory file's first `frames` positions and velocities in float64, as a batch
    of one initial condition (1, F, N, D)."""
    return tuple(np.asarray(a[:frames], np.float64)[None] for a in (trajectory.q, trajectory.qd))


def file_reference(scene: Scene, trajectory: Trajectory, frames: int) -> Trajectory:
    """A trajectory file's first `frames` frames as a batch of one, its energies
    recomputed as `scene`'s true `H` (`metrics.trajectory_of`): a file may come from
    another program, whose energies need not be this scene's."""
    return metrics.trajectory_of(scene, trajectory.t[:frames], *as_batch(trajectory, frames), trajectory.metadata)


FRAME_COLUMNS = ("scene", "model", "reference", "initial_condition", "t", "metric", "unit", "value", "diverged")


def frame_csv(scored: list[Scored]) -> str:
    """Tidy per-frame table as CSV text, floats `%.6g`: `FRAME_COLUMNS`, one row per
    scored frame of each initial condition and metric (diverged: the frame is at or
    after the prediction's divergence, so `value` is the metric's maximum). Written by
    hand, not by pandas: 100 initial conditions of 1000 frames are 800 000 rows, which
    pandas' `float_format` formats at a third of the speed."""
    import csv
    import io

    head = io.StringIO()
    csv.writer(head, lineterminator="\n").writerow(FRAME_COLUMNS)
    lines = [head.getvalue()]
    for item in scored:
        times = [f"{t:.6g}" for t in np.asarray(item.t).tolist()]
        for metric, errors in item.errors.items():
            fixed = io.StringIO()  # the constant columns, quoted where a name needs it
            csv.writer(fixed, lineterminator="").writerow([item.scene, item.model, item.reference])
            unit = metrics.METRICS[metric].unit
            for ic, row in enumerate(np.asarray(errors, np.float64).tolist()):
                start = int(item.diverged[ic])
                lines += [f"{fixed.getvalue()},{ic},{t},{metric},{unit},{value:.6g},{start >= 0 and frame >= start}\n"
                          for frame, (t, value) in enumerate(zip(times, row), start=1)]
    return "".join(lines)


SUMMARY_COLUMNS = ("scene", "model", "reference", "metric", "unit", "initial_conditions", "gmean", "low", "high", "final", "diverged")


def summary_rows(scored: list[Scored], seed: int = 0) -> list[dict]:
    """One row per (scene, model, reference, metric): the geometric mean over frames and
    initial conditions with its bootstrap 95% interval (`metrics.summarise`; NaN for one
    initial condition), the geometric mean over initial conditions at the last frame,
    and how many initial conditions diverged."""
    rows = []
    for item in scored:
        for metric, errors in item.errors.items():
            statistics = metrics.error_statistics(errors)
            gmean, low, high = metrics.summarise(statistics["per_ic_log"], seed)
            rows.append(dict(scene=item.scene, model=item.model, reference=item.reference, metric=metric, unit=metrics.METRICS[metric].unit,
                             initial_conditions=len(errors), gmean=gmean, low=low, high=high, final=float(statistics["gmean"][-1]),
                             diverged=int(np.sum(item.diverged >= 0))))
    return rows


def format_summary(rows: list[dict]) -> str:
    """The summary rows as an aligned text table, for the terminal."""
    header = ("scene", "model", "reference", "metric", "gmean", "95% interval", "final", "diverged")
    lines = [[r["scene"], r["model"], r["reference"], f"{r['metric']} ({r['unit']})", f"{r['gmean']:.3e}",
              "-" if np.isnan(r["low"]) else f"[{r['low']:.2e}, {r['high']:.2e}]", f"{r['final']:.3e}",
              f"{r['diverged']}/{r['initial_conditions']}"] for r in rows]
    widths = [max(len(str(cell)) for cell in column) for column in zip(header, *lines)]
    return "\n".join("  ".join(str(cell).ljust(width) for cell, width in zip(line, widths)).rstrip() for line in [header, *lines])


def write_outputs(scored: list[Scored], out_dir: str | os.PathLike, stem: str, title: str, header=(), notes=()) -> list[Path]:
    """Write `STEM_frames.csv` (`frame_csv`) and `STEM_summary.csv` / `.md`
    (`summary_rows`) into `out_dir`, atomically; the paths written."""
    out = Path(out_dir)
    frames, summary_csv, summary_md = out / f"{stem}_frames.csv", out / f"{stem}_summary.csv", out / f"{stem}_summary.md"
    write_text_atomic(frames, frame_csv(scored))
    notes = ("gmean: geometric mean over frames t > 0 and initial conditions; low, high: bootstrap 95% interval over initial "
             "conditions (empty for one); final: geometric mean at the last frame; from a diverged frame on, an error counts "
             "as its maximum (1, or for node_rms_error the divergence rule's reach)", *notes)
    write_table(summary_rows(scored), SUMMARY_COLUMNS, summary_csv, summary_md, title, header, notes)
    return [frames, summary_csv, summary_md]

