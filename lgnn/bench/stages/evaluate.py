"""Evaluation stage: every trained model on every scene, against the Lagrangian ground
truth and each reference engine.

`evaluate_scene` writes a scene's ground-truth record from its `GroundTruth`
(`lgnn.bench.stages.truth`): the Lagrangian ground truth (RK4 with projection, the same
integrator and step as the models), its chaos floor (initial positions perturbed by
`floor_perturbation`, projected back onto the constraints), each reference engine of
`EvaluateSettings.references` (MuJoCo C by default; `get_engine(name).rollout` at
`mujoco_dt`, frames at the same times), and the rest baseline (the initial state held: `lgnn.metrics.rest_rollouts`), scored as a
model is. `evaluate_pair` writes a (model, scene) record: the model's rollouts from
the same initial conditions (`evaluate_group`: a model's seeds in one program). Per
frame (t > 0) and initial condition, every metric of the registry
`lgnn.metrics.METRICS` against the Lagrangian ground truth (`lgnn.metrics.
score_rollouts`: rollout error `||q_hat - q|| / (||q_hat|| + ||q||)` over all node
coordinates, energy error (the same formula on the scene's true Hamiltonian of both
trajectories), per-node RMS position error `sqrt(mean over nodes |q_hat - q|^2)`), and
those marked `against_references` against each reference engine's trajectory
(`rollout_error_vs_<engine>`; `recorded_metrics`). The relative errors are clipped to
[1e-16, 1] (1 is their maximum; 1e-16 keeps an exact match from dominating a geometric
mean). A rollout *diverges* at the first frame the one divergence rule of
`lgnn.metrics` flags (non-finite, true energy or a node's reach beyond 10 times what
the scene allows), the rule that stops every engine; from that frame on its errors
count as their maximum (1; for the RMS error the divergence rule's reach) and the
divergence time is recorded. The chaos floor's divergence is recorded the same way
(the report then gives no floor).

Record arrays: `<metric>/<statistic>` (`lgnn.metrics.error_statistics`: `per_ic_log`
over every frame, and `gmean`, `low`, `high` at the times `t`, every `CURVE_DT` s) for
a model; `rest/...` and `exact_no_drag/...` likewise in the ground-truth record, beside
`chaos_floor` and `truth_vs_<engine>` (`scene_level_prefix`); `snapshot/...` on the
scenes the report draws (`snapshot`). A record written before a metric was registered
lacks its arrays: the stage recomputes it, the report shows "not computed". Records
made before MuJoCo's stale-frame fix, or keeping every frame's curves, are upgraded by
`tools/upgrade_records.py`, not here.

Keys: a ground-truth record depends on the scene's content and the profile's
`EvaluateSettings` as that scene uses them (`truth_key`); a pair record on that and the
checkpoint's content (`pair_key`). `load_truths` and `load_pairs` give the report the
records that match.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import numpy as np

from lgnn import metrics, records
from lgnn.bench import claims, store
from lgnn.bench.grid import SNAPSHOT_SCENES, Pair
from lgnn.bench.profiles import Profile, evaluation_pairs, evaluation_scenes
from lgnn.bench.stages.truth import (REFERENCE_VERSION, TRUE_DYNAMICS, GroundTruth, evaluation_count, evaluation_initial_states,
                                     ground_truth, truth_file, truth_key)
from lgnn.bench.store import Layout, log
from lgnn.engines.base import Trajectory
from lgnn.engines.rollouts import batched_rollouts, ground_truth_platform
from lgnn.errors import ConfigError, SimulationError
from lgnn.learn import models
from lgnn.learn.checkpoints import content_digest, load_model
from lgnn.runtime import in_background
from lgnn.scene import Scene, State, get_scene

# The reference a metric is scored against unless it names an engine: the Lagrangian
# ground truth (`lgnn.metrics.Scored.reference`).
TRUTH = "truth"
# Where the ground-truth record keeps the rest baseline's arrays: `rest/<metric>/...`.
REST = "rest"
# Where a drag scene's ground-truth record keeps the exact physics without drag (the
# scene's own Lagrangian, drag set to 0, from the same states), scored as a model: what
# a model that ignores drag would score (issue 13: the drag test barely tests drag).
NO_DRAG = "exact_no_drag"
# The chaos floor's arrays in the ground-truth record (its metrics: `Metric.floor`).
FLOOR = "chaos_floor"


@dataclasses.dataclass(frozen=True)
class RecordedMetric:
    """A registered metric as a record holds it: against the Lagrangian ground truth
    (`reference` TRUTH; arrays `<metric>/...`) or against a reference engine (arrays
    `<metric>_vs_<engine>/...`)."""

    metric: metrics.Metric
    reference: str = TRUTH

    @property
    def name(self) -> str:
        return recorded_name(self.metric.name, self.reference)


def recorded_name(metric: str, reference: str) -> str:
    """The record's name of `metric` scored against `reference` (TRUTH or an engine)."""
    return metric if reference == TRUTH else f"{metric}_vs_{reference}"


def recorded_metrics(references: tuple[str, ...]) -> tuple[RecordedMetric, ...]:
    """What a model's (and the rest baseline's) record holds, in table order: every
    registered metric against the ground truth, then those `against_references`
    against each engine of `references`."""
    return (*(RecordedMetric(m) for m in metrics.METRICS.values()),
            *(RecordedMetric(metrics.METRICS[name], engine) for engine in references for name in _against_references()))


def scene_level_prefix(group: str, metric: str) -> str:
    """Where a ground-truth record keeps a scene-level score (`group`: FLOOR, or
    `truth_vs_<engine>`, the ground truth against a reference engine): the rollout
    error keeps the group's first name (`chaos_floor/gmean`), another metric is
    `<group>/<metric>/...`."""
    return group if metric == "rollout_error" else f"{group}/{metric}"


def truth_against(engine: str) -> str:
    """The ground-truth record's group of the Lagrangian ground truth scored against a
    reference engine."""
    return f"truth_vs_{engine}"


def scene_level_scores(references: tuple[str, ...]) -> tuple[tuple[str, str], ...]:
    """`(group, metric)` of every scene-level score a ground-truth record holds, in table
    order: the chaos floor on each registered `floor` metric, then the ground truth
    against each engine of `references` on each metric `against_references`."""
    return (*((FLOOR, name) for name in _floor_metrics()),
            *((truth_against(engine), name) for engine in references for name in _against_references()))
# The exact dynamics of every reference rollout here, with the solver that vectorises
# over a batch of initial conditions.


# Trajectories kept for figures: initial condition 0, a frame every SNAPSHOT_DT s, in
# the records of the scenes the report draws them for (`grid.SNAPSHOT_SCENES`; kept on
# every scene they were 70 % of the committed records' bytes).
SNAPSHOT_DT = 0.01
# A record keeps its per-frame statistics (`<metric>/gmean`, `low`, `high`, and `t`)
# every CURVE_DT s, what the report's curves and figures draw; its per-initial-condition
# statistics (`per_ic_log`, every table's number) are over every frame. At the 1 ms
# frames the whole curves were 90 % of the committed records' bytes, none of it read.
CURVE_DT = 0.01


def pair_key(profile: Profile, pair: Pair, checkpoint: Path) -> str:
    """Settings a pair's record depends on: its scene's ground truth, the checkpoint's
    content and, for an unprojected pair only (projected keys stay as they were), that."""
    unprojected = {} if pair.projected else {"projected": False}
    return records.digest({"truth": truth_key(profile, pair.scene), "checkpoint": content_digest(checkpoint), **unprojected})


def keeps_snapshots(scene_name: str) -> bool:
    """Whether a scene's records keep trajectory snapshots: the report draws its
    (`SNAPSHOT_SCENES`)."""
    return scene_name in SNAPSHOT_SCENES


def snapshot(profile: Profile, scene_name: str, name: str, trajectory: np.ndarray) -> dict:
    """`{"snapshot/<name>": IC 0 of a trajectory at every SNAPSHOT_DT s}` (float32) on a
    scene whose records keep snapshots (`keeps_snapshots`), else `{}`."""
    if not keeps_snapshots(scene_name):
        return {}
    stride = max(1, round(SNAPSHOT_DT / profile.evaluate.frame_dt))
    return {f"snapshot/{name}": np.asarray(trajectory[0, ::stride], np.float32)}


def _floor_metrics() -> tuple[str, ...]:
    """The registered metrics the chaos floor is scored on (`Metric.floor`)."""
    return tuple(m.name for m in metrics.METRICS.values() if m.floor)


def _against_references() -> tuple[str, ...]:
    """The registered metrics scored against each reference engine (`Metric.against_references`)."""
    return tuple(m.name for m in metrics.METRICS.values() if m.against_references)


def curve_frames(frame_dt: float) -> slice:
    """The frames t > 0 at which a record keeps its curves: every CURVE_DT s (the last
    frame of each CURVE_DT), or every frame when frames are CURVE_DT or more apart."""
    stride = max(1, round(CURVE_DT / frame_dt))
    return slice(stride - 1, None, stride)


def curve_times(n_frames: int, frame_dt: float) -> np.ndarray:
    """A record's `t`: the times (s) of its curves' frames, of `n_frames` frames t >= 0."""
    return (np.arange(1, n_frames) * frame_dt)[curve_frames(frame_dt)]


def _statistics_arrays(prefix: str, errors: np.ndarray, frame_dt: float) -> dict:
    """`<prefix>/<statistic>` of clean errors (C, F - 1) (`lgnn.metrics.error_statistics`),
    the per-frame ones at the curves' frames (`curve_frames`)."""
    return {f"{prefix}/{k}": v if k == "per_ic_log" else v[curve_frames(frame_dt)] for k, v in metrics.error_statistics(errors).items()}


def score_against_truth(profile: Profile, scene: Scene, predicted: Trajectory, truth: GroundTruth) -> list[metrics.Scored]:
    """A predicted trajectory batch (C, F, N, D; its true energies, `metrics.trajectory_of`)
    scored (`lgnn.metrics.score_rollouts`) against the scene's ground truth with every
    registered metric, then against each reference engine's trajectory with those
    `against_references`."""
    scored = [metrics.score_rollouts(scene, predicted, truth.truth, reference_name=TRUTH)]
    if _against_references():
        scored += [metrics.score_rollouts(scene, predicted, truth.references[engine], reference_name=engine, names=_against_references())
                   for engine in profile.evaluate.references]
    return scored


def record_arrays(prefix: str, scored: list[metrics.Scored], frame_dt: float) -> dict:
    """The arrays of a model's (or a baseline's, under `prefix`) scores: statistics of
    every recorded metric (`recorded_name`) and `diverged_at` (s, NaN for none)."""
    arrays = {k: v for item in scored for metric, errors in item.errors.items()
              for k, v in _statistics_arrays(prefix + recorded_name(metric, item.reference), errors, frame_dt).items()}
    arrays[f"{prefix}diverged_at"] = np.where(scored[0].diverged >= 0, scored[0].diverged * frame_dt, np.nan)
    return arrays


def _scene_level_arrays(group: str, scored: metrics.Scored, frame_dt: float) -> dict:
    """The arrays of a scene-level score (`scene_level_prefix`)."""
    return {k: v for name, errors in scored.errors.items()
            for k, v in _statistics_arrays(scene_level_prefix(group, name), errors, frame_dt).items()}


def has_arrays(record: tuple[dict, dict] | None, names: tuple[str, ...]) -> bool:
    return record is not None and all(name in record[0] for name in names)


def _truth_needs(profile: Profile, scene: Scene) -> tuple[str, ...]:
    """The arrays a ground-truth record of the current metrics holds (a record written
    before a metric was registered lacks some: recomputed)."""
    recorded = [m.name for m in recorded_metrics(profile.evaluate.references)]
    groups = [REST, *([NO_DRAG] if scene.drag > 0 else [])]
    return (*(f"{group}/{name}/per_ic_log" for group in groups for name in recorded),
            *(f"{scene_level_prefix(group, name)}/per_ic_log" for group, name in scene_level_scores(profile.evaluate.references)))


def pair_needs(profile: Profile) -> tuple[str, ...]:
    """The arrays a pair record of the current metrics holds."""
    return tuple(f"{m.name}/per_ic_log" for m in recorded_metrics(profile.evaluate.references))


def evaluate_scene(profile: Profile, scene_name: str, out: Path, progress: bool = True) -> Path:
    """The ground-truth record of a scene: chaos floor, rest baseline and the ground
    truth against each reference engine (module docstring)."""
    path = store.layout(profile, out).truth_record(scene_name)
    with claims.once(path):  # processes on one scene: the first writes it
        return _evaluated_scene(profile, scene_name, out, progress, path)


def truth_recorded(profile: Profile, scene_name: str, out: Path) -> bool:
    """Whether the scene's ground-truth record of the current settings and metrics is
    written (`evaluate_scene` would compute nothing)."""
    layout = store.layout(profile, out)
    return has_arrays(layout.load(layout.truth_record(scene_name), truth_key(profile, scene_name)), _truth_needs(profile, get_scene(scene_name)))


def truth_cost(profile: Profile, scene_name: str) -> float:
    """A scene's ground-truth cost in arbitrary units, to start the costliest first: its
    initial conditions times the cube of its coordinates (MuJoCo C factorises a serial
    chain's dense joint-space mass matrix every step: on one H200's 16 cores
    chain100-3d's reference took 431 s, the paper track's whole truth stage 452 s)."""
    scene = get_scene(scene_name)
    return evaluation_count(profile, scene) * float(scene.n_nodes * scene.dim) ** 3


def _evaluated_scene(profile: Profile, scene_name: str, out: Path, progress: bool, path: Path) -> Path:
    if truth_recorded(profile, scene_name, out):
        return path
    key = truth_key(profile, scene_name)
    scene = get_scene(scene_name)
    truth = ground_truth(profile, scene_name, progress, out)
    references = profile.evaluate.references
    frame_dt = profile.evaluate.frame_dt
    t = truth.truth.t
    floor = metrics.score_rollouts(scene, metrics.trajectory_of(scene, t, *truth.floor), truth.truth, names=_floor_metrics())
    arrays = {
        "t": curve_times(len(t), frame_dt),
        **_scene_level_arrays(FLOOR, floor, frame_dt),
        f"{FLOOR}/diverged_at": np.where(floor.diverged >= 0, floor.diverged * frame_dt, np.nan),
        **record_arrays(f"{REST}/", score_against_truth(profile, scene, metrics.rest_rollouts(truth.truth), truth), frame_dt),
        **snapshot(profile, scene_name, "truth", truth.truth.q),
        "mid_state": np.stack([truth.truth.q[0, len(t) // 2], truth.truth.qd[0, len(t) // 2]]),
    }
    for engine in references:
        # The ground truth never diverges (it stops at divergence: `batched_rollouts`), so neither side's
        # errors are capped.
        versus = metrics.score_rollouts(scene, truth.truth, truth.references[engine], names=_against_references())
        arrays.update(_scene_level_arrays(truth_against(engine), versus, frame_dt))
        arrays.update(snapshot(profile, scene_name, engine, truth.references[engine].q))
    if scene.drag > 0:
        no_drag = scene.replace(drag=0.0)
        runs = batched_rollouts(no_drag, profile.evaluate.simulation(scene_name), TRUE_DYNAMICS, truth.states,
                                integration=profile.evaluate.integration, chunk=profile.evaluate.chunk, label=f"{scene_name} without drag",
                                progress=progress, platform=ground_truth_platform(len(truth.states.q)))
        arrays.update(record_arrays(f"{NO_DRAG}/", score_against_truth(profile, scene, metrics.trajectory_of(scene, t, runs.q, runs.qd), truth),
                                    frame_dt))
    meta = dict(scene=scene_name, initial_conditions=len(truth.states.q), mujoco_reference=REFERENCE_VERSION, platform=truth.platform,
                **truth.timings())
    store.save(path, key, arrays, meta)
    return path


def evaluate_pair(profile: Profile, pair: Pair, out: Path, progress: bool = True) -> Path:
    """The evaluation record of a trained model on a scene (module docstring)."""
    return evaluate_group(profile, [pair], out, progress)[0]


def evaluate_group(profile: Profile, pairs: list[Pair], out: Path, progress: bool = True) -> list[Path]:
    """The evaluation records of `pairs` (module docstring), those not yet recorded
    computed together: pairs on one scene whose models share a configuration (the seeds
    of one training job, projected alike) roll out in one compiled program
    (`models.ModelEngine`, stacked): one compile instead of one per seed, and the GPU's
    batch as wide as the seeds times the initial conditions. Each pair keeps its own
    record, as `evaluate_pair` writes it. A pair whose checkpoint is the base folder's
    (`Profile.base`) is never evaluated here: its record is the base's, or there is none
    (one made with other settings is named on stderr: `unmatched_base_pairs`)."""
    layout = store.layout(profile, out)
    paths, todo = [], []
    unmatched = unmatched_base_pairs(profile, out, pairs)
    if unmatched:
        log(f"evaluate: {len(unmatched)} pair(s) of the base folder's checkpoints were evaluated there with other settings "
            f"({', '.join(sorted(f'{p.label} s{p.job.seed} on {p.scene}' for p in unmatched))}): left out, never recomputed or mixed")
    for pair in pairs:
        checkpoint = layout.found(layout.checkpoint(pair.job))
        if not checkpoint.exists():
            raise ConfigError(f"no checkpoint for {pair.job.name} at {checkpoint}: run the training stage first")
        path, key = layout.pair_record(pair), pair_key(profile, pair, checkpoint)
        paths.append(path)
        # The base's models are not this run's: a pair of one without a record (there or here) is not evaluated here.
        from_base = not layout.checkpoint(pair.job).exists()
        if not from_base and not has_arrays(layout.load(path, key), pair_needs(profile)):
            todo.append((pair, path, key, checkpoint))
    # Each pair claimed (`lgnn.bench.claims`): one evaluated by another process is waited
    # for and read, or evaluated here if that process failed.
    claims.each_once(todo, lambda item: item[1], lambda claimed: _evaluate_claimed(profile, layout, claimed, progress, out), "evaluate")
    return paths


def _evaluate_claimed(profile: Profile, layout: Layout, claimed: list, progress: bool, out: Path) -> None:
    """Evaluate the claimed `(pair, path, key, checkpoint)` whose records are not whole
    (another process may have written them meanwhile), those sharing a scene, model
    configuration and projection stacked in one program."""
    stacks = {}
    for pair, path, key, checkpoint in claimed:
        if not has_arrays(layout.load(path, key), pair_needs(profile)):
            model, params = load_model(checkpoint)
            shared = (pair.scene, pair.projected, records.digest(model.to_dict()))
            stacks.setdefault(shared, []).append((pair, path, key, model, params))
    for group in stacks.values():
        _evaluate_stacked(profile, group, progress, out)


def stacked_rollouts(profile: Profile, model, parameter_sets: list, scene_name: str, projected: bool, states: State, label: str,
                     progress: bool = True):
    """A model configuration's rollouts on a scene from `states` (`models.ModelEngine`,
    stacked): every parameter set of `parameter_sets` in one program, as the evaluation
    rolls a training group's seeds out (`q`, `qd`, `energy` (S, C, F, ...), its costs)."""
    scene = get_scene(scene_name)
    integration = dataclasses.replace(profile.evaluate.integration, project=projected)
    stacked = jax.tree.map(lambda *leaves: np.stack(leaves), *parameter_sets)
    engine = models.ModelEngine(model, stacked, progress=progress, integration=integration, stop_at_divergence=False,
                                chunk=profile.evaluate.chunk, stacked=True)
    return engine.rollouts(scene, profile.evaluate.simulation(scene_name), states, label=label)


def pair_arrays(profile: Profile, scene_name: str, predicted: Trajectory, truth: GroundTruth) -> dict:
    """A pair record's arrays of a model's rollouts from the ground truth's initial
    conditions: `t`, every recorded metric's statistics and `diverged_at`
    (`record_arrays`), and the scene's snapshot (`snapshot`)."""
    scored = score_against_truth(profile, get_scene(scene_name), predicted, truth)
    frame_dt = profile.evaluate.frame_dt
    return {"t": curve_times(predicted.q.shape[1], frame_dt), **record_arrays("", scored, frame_dt),
            **snapshot(profile, scene_name, "model", predicted.q)}


def _evaluate_stacked(profile: Profile, group: list, progress: bool, out: Path) -> None:
    """Roll out a group of `(pair, path, key, model, params)` (one scene, one model
    configuration, one projection) from the scene's initial conditions, all parameter
    sets in one program, and save each pair's record."""
    pair = group[0][0]
    scene = get_scene(pair.scene)
    config = profile.evaluate.simulation(pair.scene)
    # The models need only the initial conditions; the ground truth (chain100-3d's MuJoCo
    # C reference: 8-14 minutes on 16 cores, beside 20 GPU minutes of LGN's rollouts) is
    # computed or read meanwhile, and waited for only to score.
    truth_when_done = in_background(lambda: ground_truth(profile, pair.scene, progress, out))
    states = evaluation_initial_states(profile, scene)
    seeds = ", ".join(f"s{p.job.seed}" for p, *_ in group)
    log(f"evaluate {pair.label} {seeds} on {pair.scene}: {len(states.q)} initial conditions")
    runs = stacked_rollouts(profile, group[0][3], [params for *_, params in group], pair.scene, pair.projected, states,
                            f"{pair.label} {seeds} on {pair.scene}", progress)
    compile_s, run_s = runs.compile_s, runs.run_s
    truth = truth_when_done()
    if not np.allclose(truth.states.q, states.q, rtol=1e-9, atol=1e-12):
        raise SimulationError(f"{pair.scene}: the stored ground truth starts from other initial conditions than the evaluation's; "
                              f"remove {truth_file(profile, pair.scene)} to recompute it")
    steps = len(group) * len(states.q) * config.n_frames * config.steps_per_frame
    for (pair, path, key, _, _), q, qd, energy in zip(group, runs.q, runs.qd, runs.energy):
        arrays = pair_arrays(profile, pair.scene, Trajectory(truth.truth.t, q, qd, energy), truth)
        # Compile and run times are the group's (`stacked` models rolled out together).
        meta = dict(job=pair.job.name, model=pair.job.model, label=pair.label, projected=pair.projected, train_scene=pair.job.scene, seed=pair.job.seed,
                    scene=pair.scene, initial_conditions=len(q), mujoco_reference=REFERENCE_VERSION, compile_s=compile_s, run_s=run_s,
                    steps_per_s=steps / run_s, stacked=len(group), platform=runs.platform)
        store.save(path, key, arrays, meta)
        n_div = int(np.sum(~np.isnan(arrays["diverged_at"])))
        log(f"evaluate {pair.label} s{pair.job.seed} on {pair.scene}: rollout error {metrics.summarise(arrays['rollout_error/per_ic_log'])[0]:.3g}"
            + (f", {n_div} diverged" if n_div else "") + f" ({run_s:.1f} s + compile {compile_s:.1f} s for {len(group)})")


def unmatched_base_pairs(profile: Profile, out: Path, pairs: list[Pair] | None = None) -> list[Pair]:
    """The pairs (of `pairs`, default the profile's) whose checkpoint is the base
    folder's (`Profile.base`) and whose record there was made with other evaluation
    settings than this profile's (and none under `out` with them): results never mixed
    with these and never recomputed (the base's models are not this run's)."""
    layout = store.layout(profile, out)
    return [pair for pair in (evaluation_pairs(profile) if pairs is None else pairs)
            if not layout.checkpoint(pair.job).exists() and layout.in_base(layout.checkpoint(pair.job)) is not None
            and layout.in_base(layout.pair_record(pair)) is not None
            and not has_arrays(layout.load(layout.pair_record(pair), pair_key(profile, pair, layout.found(layout.checkpoint(pair.job)))),
                         pair_needs(profile))]


def load_truth(profile: Profile, scene_name: str, out: Path) -> tuple[dict, dict] | None:
    """`(arrays, meta)` of a scene's ground-truth record if it matches the profile, else None."""
    layout = store.layout(profile, out)
    return layout.load(layout.truth_record(scene_name), truth_key(profile, scene_name))


def load_pair(profile: Profile, pair: Pair, out: Path) -> tuple[dict, dict] | None:
    """`(arrays, meta)` of a pair's record if it matches the profile and checkpoint, else None."""
    layout = store.layout(profile, out)
    checkpoint = layout.found(layout.checkpoint(pair.job))
    if not checkpoint.exists():
        return None
    return layout.load(layout.pair_record(pair), pair_key(profile, pair, checkpoint))


def load_truths(profile: Profile, out: Path) -> dict[str, tuple[dict, dict]]:
    """Ground-truth records by scene, those that exist and match the profile."""
    found = {scene: load_truth(profile, scene, out) for scene in evaluation_scenes(profile)}
    return {scene: record for scene, record in found.items() if record is not None}


def load_pairs(profile: Profile, out: Path) -> list[tuple[Pair, tuple[dict, dict]]]:
    """`(pair, (arrays, meta))` of every pair record that exists and matches the profile."""
    found = [(pair, load_pair(profile, pair, out)) for pair in evaluation_pairs(profile)]
    return [(pair, record) for pair, record in found if record is not None]
