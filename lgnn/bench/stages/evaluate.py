"""Evaluation stage: every trained model on every scene, against both ground truths.

`evaluate_scene` writes a scene's ground-truth record: the Lagrangian ground truth
(RK4 with projection, the same integrator and step as the models), its chaos floor
(initial positions perturbed by `floor_perturbation`, projected back onto the
constraints), MuJoCo C (RK4 at `mujoco_dt`, frames at the same times), and the rest
baseline (the initial state held: `lgnn.metrics.rest_rollouts`), scored as a model is.
`evaluate_pair` writes a (model, scene) record: the model's rollouts from the same
initial conditions (`evaluate_group`: a model's seeds in one program). Per frame (t > 0) and initial condition (`lgnn.metrics.
score_rollouts`): rollout error `||q_hat - q|| / (||q_hat|| + ||q||)` over all node
coordinates, energy error (the same formula on the scene's true Hamiltonian of both
trajectories), per-node RMS position error `sqrt(mean over nodes |q_hat - q|^2)`, and
the rollout error against MuJoCo's trajectory. The relative errors are clipped to
[1e-16, 1] (1 is their maximum; 1e-16 keeps an exact match from dominating a geometric
mean). A rollout *diverges* at the first frame the one divergence rule of
`lgnn.metrics` flags (non-finite, true energy or a node's reach beyond 10 times what
the scene allows), the rule that stops every engine; from that frame on its errors
count as their maximum (1; for the RMS error the divergence rule's reach) and the
divergence time is recorded. The chaos floor's divergence is recorded the same way
(the report then gives no floor).

Keys: a ground-truth record depends on the scene's content and the profile's
`EvaluateSettings` as that scene uses them (`truth_key`); a pair record on that and the
checkpoint's content (`pair_key`). `load_truths` and `load_pairs` give the report the
records that match.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import threading
import time
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from lgnn import metrics, physics, records
from lgnn.bench import store
from lgnn.bench.grid import Pair, Profile, evaluation_pairs, evaluation_scenes, settings_key
from lgnn.bench.store import Layout, log
from lgnn.engines.base import SimulationConfig
from lgnn.engines.rollouts import Unparametrised, batched_rollouts
from lgnn.errors import ConfigError, SimulationError
from lgnn.learn import models, train
from lgnn.scene import Scene, State, get_scene, is_catalogue_scene, is_pinned_chain, scene_to_dict

# Metrics recorded per frame and initial condition, for a model and the rest baseline.
METRICS = ("rollout_error", "energy_error", "rollout_error_vs_mujoco", "node_rms_error")
# What the chaos floor records (a position error only: energy is not its business).
FLOOR_METRICS = ("rollout_error", "node_rms_error")
# Where the ground-truth record keeps the rest baseline's arrays: `rest/<metric>/...`.
REST = "rest"
# Where a drag scene's ground-truth record keeps the exact physics without drag (the
# scene's own Lagrangian, drag set to 0, from the same states), scored as a model: what
# a model that ignores drag would score (issue 13: the drag test barely tests drag).
NO_DRAG = "exact_no_drag"
# Arrays that records written before the rest baseline and the RMS error lack: such a
# record is still read by the report ("not computed") but recomputed by the stage.
_TRUTH_NEEDS = (f"{REST}/node_rms_error/per_ic_log", "chaos_floor/node_rms_error/per_ic_log")
_PAIR_NEEDS = ("node_rms_error/per_ic_log",)
# Version of the MuJoCo C reference trajectories, in every record's meta. Version 1
# (records without the field): the last `mujoco.rollout` call of a batch of several
# drag-free trajectories left its frames stale (engines/mujoco.py, fixed at c0eb960), up
# to the last 18 % of frames, so every array scored against MuJoCo (`MUJOCO_ARRAYS`) of
# such a record is wrong; the rest of the record is not (MuJoCo enters nothing else).
MUJOCO_REFERENCE = 2
# Array name prefixes made from the MuJoCo reference.
MUJOCO_ARRAYS = ("truth_vs_mujoco", "rollout_error_vs_mujoco", f"{REST}/rollout_error_vs_mujoco", f"{NO_DRAG}/rollout_error_vs_mujoco",
                 "snapshot/mujoco")
# The exact dynamics of every reference rollout here, with the solver that vectorises
# over a batch of initial conditions.
TRUE_DYNAMICS = Unparametrised(physics.vectorised_true_acceleration_fn)
# Trajectories kept for figures: initial condition 0, a frame every SNAPSHOT_DT s.
SNAPSHOT_DT = 0.01


def evaluation_initial_states(profile: Profile, scene: Scene) -> State:
    """The evaluation initial conditions (C, N, D), seed `ic_seed` (`physics.benchmark_initial_states`):
    `initial_conditions` samples of the paper's chain sampler on a chain, or of
    `physics.sample_initial_conditions` on a user's scene; a built-in scene's own
    state (C = 1) otherwise (T1-T3)."""
    count = profile.evaluate.initial_conditions if is_pinned_chain(scene) or not is_catalogue_scene(scene) else 1
    return physics.benchmark_initial_states(scene, count, profile.evaluate.ic_seed)


def truth_key(profile: Profile, scene_name: str) -> str:
    """Settings a scene's ground-truth record depends on."""
    return records.digest({"evaluate": settings_key(profile.evaluate.for_scene(scene_name)), "scene": scene_to_dict(get_scene(scene_name))})


def pair_key(profile: Profile, pair: Pair, checkpoint: Path) -> str:
    """Settings a pair's record depends on: its scene's ground truth, the checkpoint's
    content and, for an unprojected pair only (projected keys stay as they were), that."""
    unprojected = {} if pair.projected else {"projected": False}
    return records.digest({"truth": truth_key(profile, pair.scene), "checkpoint": records.file_digest(checkpoint), **unprojected})


# The trajectories `ground_truth` keeps on disk (with `states`, its initial conditions).
TRUTH_TRAJECTORIES = ("q", "qd", "energy", "q_floor", "qd_floor", "q_mujoco")
# The ground truth's costs in seconds (JAX compile, JAX run, MuJoCo C's reference),
# kept with its trajectories and in its record.
TRUTH_TIMINGS = ("compile_s", "run_s", "mujoco_s")


def _in_background(call: Callable[[], object]) -> Callable[[], object]:
    """Start `call()` in a daemon thread; returns a function that waits for it and gives
    its value (or raises its exception). A daemon, so that an error or Ctrl-C in the
    caller does not wait out a long computation (a ground truth's MuJoCo reference)."""
    outcome: dict[str, object] = {}

    def run() -> None:
        try:
            outcome["value"] = call()
        except BaseException as error:  # handed to the caller, whatever it was
            outcome["error"] = error

    thread = threading.Thread(target=run, daemon=True)
    thread.start()

    def result() -> object:
        thread.join()
        if "error" in outcome:
            raise outcome["error"]
        return outcome["value"]

    return result


@functools.lru_cache(maxsize=2)
def ground_truth(profile: Profile, scene_name: str, progress: bool = True, out: Path | None = None) -> dict:
    """The ground truth of a scene's evaluation: `q`, `qd` (C, F, N, D) and true `energy`
    (C, F) of the Lagrangian ground truth, the chaos floor's `q_floor`, `qd_floor`
    (scored, divergence included, by `evaluate_scene`), MuJoCo's `q_mujoco`, the initial
    `states` and timings.

    With `out`, the trajectories are kept in `Layout(out).truth_trajectories` (key
    `truth_key`) and read back by every later process: MuJoCo C's reference alone takes
    15 minutes on 16 cores for chain100-3d (a serial chain's joint-space mass matrix is
    dense: O(nv^3) per step), which each process evaluating one of the scene's pairs
    would otherwise redo. Float64 as computed (the reference agrees with MuJoCo to
    1e-10 and better); about 1.2 GB for chain100-3d, in the git-ignored datasets folder."""
    if out is None:
        return _computed_ground_truth(profile, scene_name, progress)
    path, key = Layout(out).truth_trajectories(scene_name), truth_key(profile, scene_name)
    with store.exclusive(path):  # parallel workers on one scene: the first computes, the others read
        stored = store.load(path, key)
        if stored is not None and stored[1].get("mujoco_reference") == MUJOCO_REFERENCE:
            arrays, meta = stored
            log(f"ground truth {scene_name}: read from {path}")
            return dict(**{name: arrays[name] for name in TRUTH_TRAJECTORIES}, states=State(arrays["states/q"], arrays["states/qd"]),
                        **{name: meta[name] for name in TRUTH_TIMINGS})
        truth = _computed_ground_truth(profile, scene_name, progress)
        store.save(path, key, {**{name: truth[name] for name in TRUTH_TRAJECTORIES}, "states/q": np.asarray(truth["states"].q),
                                "states/qd": np.asarray(truth["states"].qd)},
                   dict(scene=scene_name, mujoco_reference=MUJOCO_REFERENCE, **{name: truth[name] for name in TRUTH_TIMINGS}))
        return truth


def _computed_ground_truth(profile: Profile, scene_name: str, progress: bool) -> dict:
    """`ground_truth`, computed. MuJoCo C's reference runs in a thread beside the
    Lagrangian ground truth and chaos floor (`mujoco.rollout` releases the GIL): on a GPU
    the two overlap, which saves chain100-3d's 6 minutes of JAX rollouts."""
    settings = profile.evaluate
    scene = get_scene(scene_name)
    states = evaluation_initial_states(profile, scene)
    config = settings.simulation(scene_name)
    mj_config = SimulationConfig("rk4", settings.mujoco_dt, settings.frame_dt, settings.duration, True)
    log(f"ground truth {scene_name}: {len(states.q)} initial conditions, RK4 dt {config.dt:g}, {config.duration:g} s; "
        f"MuJoCo C at dt {mj_config.dt:g} alongside")
    # A daemon thread: an error or Ctrl-C here does not wait out MuJoCo's minutes.
    mujoco_when_done = _in_background(lambda: _mujoco_reference(scene, mj_config, states))
    # A reference that diverged would turn every error into 1 for every model: it stops there.
    truth = batched_rollouts(scene, config, TRUE_DYNAMICS, states, chunk=settings.chunk, stop_at_divergence=True, label=f"truth {scene_name}",
                             progress=progress, hint="give the scene a smaller step (EvaluateSettings.scene_dts)")
    noise = settings.floor_perturbation * jax.random.normal(jax.random.PRNGKey(settings.ic_seed + 1000), states.q.shape)
    perturbed = State(*map(np.asarray, jax.vmap(physics.projection_fn(scene))(jnp.asarray(states.q) + noise, jnp.asarray(states.qd))))
    # The perturbed runs are not references: one that diverges (T2/T3's perturbed
    # self-stressed states need dt <= 2.5e-5) is recorded as such, like a model's.
    floor = batched_rollouts(scene, config, TRUE_DYNAMICS, perturbed, chunk=settings.chunk, label=f"floor {scene_name}", progress=progress)
    q_mj, mujoco_s = mujoco_when_done()
    return dict(q=truth.q, qd=truth.qd, energy=truth.energy, q_floor=floor.q, qd_floor=floor.qd, q_mujoco=q_mj, states=states,
                compile_s=truth.compile_s, run_s=truth.run_s, mujoco_s=mujoco_s)


def _mujoco_reference(scene: Scene, config: SimulationConfig, states: State) -> tuple[np.ndarray, float]:
    """MuJoCo C's node trajectories `q` (C, F, N, D) from `states`, checked like the
    Lagrangian ground truth, and the seconds they took."""
    from lgnn.engines import mujoco as lm

    start = time.perf_counter()
    q_mj, qd_mj = lm.rollout(scene, config, State(np.asarray(states.q), np.asarray(states.qd)), threads=os.cpu_count() or 1)
    mujoco_s = time.perf_counter() - start
    _check_reference(scene, config, "MuJoCo reference", q_mj, qd_mj, metrics.true_energies(scene, q_mj, qd_mj))
    return q_mj, mujoco_s


def _divergence(scene: Scene, config: SimulationConfig, q: np.ndarray, qd: np.ndarray, energy: np.ndarray) -> np.ndarray:
    """(C,) first diverged frame of each trajectory (`lgnn.metrics`' one rule), or -1."""
    return metrics.divergence_frames(scene, np.arange(q.shape[1]) * config.frame_dt, q, qd, energy)


def _check_reference(scene: Scene, config: SimulationConfig, what: str, q: np.ndarray, qd: np.ndarray, energy: np.ndarray) -> None:
    """A reference trajectory that diverged would turn every error into 1 for every
    model: stop with one line instead of recording meaningless numbers."""
    diverged = _divergence(scene, config, q, qd, energy)
    if (diverged >= 0).any():
        first = int(np.argmax(diverged >= 0))
        raise SimulationError(
            f"{scene.name}: the {what} diverged at t = {diverged[first] * config.frame_dt:g} s (initial condition {first}, "
            f"RK4 dt {config.dt:g}): give the scene a smaller step (EvaluateSettings.scene_dts)"
        )


def _snapshot(profile: Profile, trajectory: np.ndarray) -> np.ndarray:
    """IC 0 of a trajectory at every SNAPSHOT_DT s (figures), float32."""
    stride = max(1, round(SNAPSHOT_DT / profile.evaluate.frame_dt))
    return np.asarray(trajectory[0, ::stride], np.float32)


def _metric_arrays(prefix: str, errors: np.ndarray) -> dict:
    stats = metrics.error_statistics(errors)
    return {f"{prefix}/{k}": v for k, v in stats.items()}


def _scores(profile: Profile, scene: Scene, q: np.ndarray, qd: np.ndarray, truth: dict) -> tuple[dict, np.ndarray]:
    """`({metric: clean errors (C, F - 1)} for every metric of METRICS, diverged (C,))`
    of trajectories `q`, `qd` (C, F, N, D) against the scene's ground truth."""
    t = np.arange(q.shape[1]) * profile.evaluate.frame_dt
    scores, diverged = metrics.score_rollouts(scene, t, q, qd, truth["q"], truth["energy"])
    scores["rollout_error_vs_mujoco"] = metrics.clean_errors(metrics.relative_error(q, truth["q_mujoco"], 2), diverged)[:, 1:]
    return scores, diverged


def _has(record: tuple[dict, dict] | None, names: tuple[str, ...]) -> bool:
    return record is not None and not _stale_mujoco(record[1]) and all(name in record[0] for name in names)


def _stale_mujoco(meta: dict) -> bool:
    """Whether a record's MuJoCo-scored arrays came from a stale reference
    (`MUJOCO_REFERENCE`): version 1, several initial conditions, a drag-free scene (a
    single trajectory's buffer was contiguous; drag scenes step in Python)."""
    return meta.get("mujoco_reference", 1) < MUJOCO_REFERENCE and meta.get("initial_conditions", 1) > 1 and not get_scene(meta["scene"]).drag


def _reported(record: tuple[dict, dict] | None) -> tuple[dict, dict] | None:
    """A record as the report may read it: without the MuJoCo-scored arrays of a stale
    reference (they show as "not computed"; `lgnn benchmark --stage evaluate` recomputes
    the record)."""
    if record is None or not _stale_mujoco(record[1]):
        return record
    arrays, meta = record
    return {k: v for k, v in arrays.items() if not k.startswith(MUJOCO_ARRAYS)}, meta


def evaluate_scene(profile: Profile, scene_name: str, out: Path, progress: bool = True) -> Path:
    """The ground-truth record of a scene: chaos floor and Lagrangian-vs-MuJoCo errors."""
    path = Layout(out).truth_record(scene_name)
    with store.exclusive(path):  # parallel workers on one scene: the first writes it
        return _evaluated_scene(profile, scene_name, out, progress, path)


def _evaluated_scene(profile: Profile, scene_name: str, out: Path, progress: bool, path: Path) -> Path:
    key = truth_key(profile, scene_name)
    scene = get_scene(scene_name)
    if _has(store.load(path, key), _TRUTH_NEEDS + ((f"{NO_DRAG}/rollout_error/per_ic_log",) if scene.drag > 0 else ())):
        return path
    truth = ground_truth(profile, scene_name, progress, out)
    frame_dt = profile.evaluate.frame_dt
    none = np.full(len(truth["q"]), -1)
    floor, floor_diverged = _scores(profile, scene, truth["q_floor"], truth["qd_floor"], truth)
    rest, rest_diverged = _scores(profile, scene, *metrics.rest_rollouts(truth["q"], truth["qd"]), truth)
    arrays = {
        "t": np.arange(1, truth["q"].shape[1]) * frame_dt,
        # The chaos floor's rollout error keeps its first name (`chaos_floor/gmean`, ...).
        **_metric_arrays("chaos_floor", floor["rollout_error"]),
        **_metric_arrays("chaos_floor/node_rms_error", floor["node_rms_error"]),
        "chaos_floor/diverged_at": np.where(floor_diverged >= 0, floor_diverged * frame_dt, np.nan),
        **{k: v for metric in METRICS for k, v in _metric_arrays(f"{REST}/{metric}", rest[metric]).items()},
        f"{REST}/diverged_at": np.where(rest_diverged >= 0, rest_diverged * frame_dt, np.nan),
        **_metric_arrays("truth_vs_mujoco", metrics.clean_errors(metrics.relative_error(truth["q"], truth["q_mujoco"], 2), none)[:, 1:]),
        "snapshot/truth": _snapshot(profile, truth["q"]),
        "snapshot/mujoco": _snapshot(profile, truth["q_mujoco"]),
        "mid_state": np.stack([truth["q"][0, truth["q"].shape[1] // 2], truth["qd"][0, truth["qd"].shape[1] // 2]]),
    }
    if scene.drag > 0:
        no_drag = scene.replace(drag=0.0)
        runs = batched_rollouts(no_drag, profile.evaluate.simulation(scene_name), TRUE_DYNAMICS, truth["states"], chunk=profile.evaluate.chunk,
                                label=f"{scene_name} without drag", progress=progress)
        scores, diverged = _scores(profile, scene, runs.q, runs.qd, truth)
        arrays.update({k: v for metric in METRICS for k, v in _metric_arrays(f"{NO_DRAG}/{metric}", scores[metric]).items()})
        arrays[f"{NO_DRAG}/diverged_at"] = np.where(diverged >= 0, diverged * frame_dt, np.nan)
    meta = dict(scene=scene_name, initial_conditions=len(truth["q"]), mujoco_reference=MUJOCO_REFERENCE,
                **{name: truth[name] for name in TRUTH_TIMINGS})
    store.save(path, key, arrays, meta)
    return path


def evaluate_pair(profile: Profile, pair: Pair, out: Path, progress: bool = True) -> Path:
    """The evaluation record of a trained model on a scene (module docstring)."""
    return evaluate_group(profile, [pair], out, progress)[0]


def evaluate_group(profile: Profile, pairs: list[Pair], out: Path, progress: bool = True) -> list[Path]:
    """The evaluation records of `pairs` (module docstring), those not yet recorded
    computed together: pairs on one scene whose models share a configuration (the seeds
    of one training job, projected alike) roll out in one compiled program
    (`rollouts.batched_rollouts`, stacked): one compile instead of one per seed, and the GPU's
    batch as wide as the seeds times the initial conditions. Each pair keeps its own
    record, as `evaluate_pair` writes it."""
    layout = Layout(out)
    paths, todo = [], {}
    for pair in pairs:
        checkpoint = layout.checkpoint(pair.job)
        if not checkpoint.exists():
            raise ConfigError(f"no checkpoint for {pair.job.name} at {checkpoint}: run the training stage first")
        path, key = layout.pair_record(pair), pair_key(profile, pair, checkpoint)
        paths.append(path)
        if not _has(store.load(path, key), _PAIR_NEEDS):
            model, params = train.load_model(checkpoint)
            shared = (pair.scene, pair.projected, records.digest(model.to_dict()))
            todo.setdefault(shared, []).append((pair, path, key, model, params))
    for group in todo.values():
        _evaluate_stacked(profile, group, progress, out)
    return paths


def _evaluate_stacked(profile: Profile, group: list, progress: bool, out: Path) -> None:
    """Roll out a group of `(pair, path, key, model, params)` (one scene, one model
    configuration, one projection) from the scene's initial conditions, all parameter
    sets in one program, and save each pair's record."""
    pair = group[0][0]
    scene = get_scene(pair.scene)
    config = dataclasses.replace(profile.evaluate.simulation(pair.scene), project=pair.projected)
    # The models need only the initial conditions; the ground truth (chain100-3d's MuJoCo
    # C reference: 8-14 minutes on 16 cores, beside 20 GPU minutes of LGN's rollouts) is
    # computed or read meanwhile, and waited for only to score.
    truth_when_done = _in_background(lambda: ground_truth(profile, pair.scene, progress, out))
    states = evaluation_initial_states(profile, scene)
    seeds = ", ".join(f"s{p.job.seed}" for p, *_ in group)
    log(f"evaluate {pair.label} {seeds} on {pair.scene}: {len(states.q)} initial conditions")
    stacked = jax.tree.map(lambda *leaves: np.stack(leaves), *(params for *_, params in group))
    runs = batched_rollouts(scene, config, models.AccelerationFactory(group[0][3]), states, stacked, stacked=True, chunk=profile.evaluate.chunk,
                            label=f"{pair.label} {seeds} on {pair.scene}", progress=progress)
    q_all, qd_all, compile_s, run_s = runs.q, runs.qd, runs.compile_s, runs.run_s
    truth = truth_when_done()
    if not np.allclose(truth["states"].q, states.q, rtol=1e-9, atol=1e-12):
        raise SimulationError(f"{pair.scene}: the stored ground truth starts from other initial conditions than the evaluation's; "
                              f"remove {Layout(out).truth_trajectories(pair.scene)} to recompute it")
    steps = len(group) * len(states.q) * config.n_frames * config.steps_per_frame
    for (pair, path, key, _, _), q, qd in zip(group, q_all, qd_all):
        scores, diverged = _scores(profile, scene, q, qd, truth)
        arrays = {
            "t": np.arange(1, q.shape[1]) * profile.evaluate.frame_dt,
            **{k: v for metric in METRICS for k, v in _metric_arrays(metric, scores[metric]).items()},
            "diverged_at": np.where(diverged >= 0, diverged * profile.evaluate.frame_dt, np.nan),
            "snapshot/model": _snapshot(profile, q),
        }
        # Compile and run times are the group's (`stacked` models rolled out together).
        meta = dict(job=pair.job.name, model=pair.job.model, label=pair.label, projected=pair.projected, train_scene=pair.job.scene, seed=pair.job.seed,
                    scene=pair.scene, initial_conditions=len(q), mujoco_reference=MUJOCO_REFERENCE, compile_s=compile_s, run_s=run_s,
                    steps_per_s=steps / run_s, stacked=len(group))
        store.save(path, key, arrays, meta)
        n_div = int(np.sum(diverged >= 0))
        log(f"evaluate {pair.label} s{pair.job.seed} on {pair.scene}: rollout error {metrics.summarise(arrays['rollout_error/per_ic_log'])[0]:.3g}"
            + (f", {n_div} diverged" if n_div else "") + f" ({run_s:.1f} s + compile {compile_s:.1f} s for {len(group)})")


def load_truth(profile: Profile, scene_name: str, out: Path) -> tuple[dict, dict] | None:
    """`(arrays, meta)` of a scene's ground-truth record if it matches the profile, else
    None; without MuJoCo-scored arrays of a stale reference (`_reported`)."""
    return _reported(store.load(Layout(out).truth_record(scene_name), truth_key(profile, scene_name)))


def load_pair(profile: Profile, pair: Pair, out: Path) -> tuple[dict, dict] | None:
    """`(arrays, meta)` of a pair's record if it matches the profile and checkpoint, else
    None; without MuJoCo-scored arrays of a stale reference (`_reported`)."""
    layout = Layout(out)
    checkpoint = layout.checkpoint(pair.job)
    if not checkpoint.exists():
        return None
    return _reported(store.load(layout.pair_record(pair), pair_key(profile, pair, checkpoint)))


def load_truths(profile: Profile, out: Path) -> dict[str, tuple[dict, dict]]:
    """Ground-truth records by scene, those that exist and match the profile."""
    found = {scene: load_truth(profile, scene, out) for scene in evaluation_scenes(profile)}
    return {scene: record for scene, record in found.items() if record is not None}


def load_pairs(profile: Profile, out: Path) -> list[tuple[Pair, tuple[dict, dict]]]:
    """`(pair, (arrays, meta))` of every pair record that exists and matches the profile."""
    found = [(pair, load_pair(profile, pair, out)) for pair in evaluation_pairs(profile)]
    return [(pair, record) for pair, record in found if record is not None]


def timed_rollout_fn(profile: Profile, pair: Pair, out: Path):
    """`(run, steps)`: a no-argument call running the pair's model alone on the first
    chunk of the evaluation's initial conditions (through the one rollout path, its
    programs compiled by the first call), and the RK4 steps it takes; for
    pytest-benchmark."""
    scene = get_scene(pair.scene)
    states = evaluation_initial_states(profile, scene)
    chunk = min(profile.evaluate.chunk, len(states.q))
    first = State(states.q[:chunk], states.qd[:chunk])
    model, params = train.load_model(Layout(out).checkpoint(pair.job))
    config = profile.evaluate.simulation(pair.scene)
    steps = chunk * config.n_frames * config.steps_per_frame
    return (lambda: batched_rollouts(scene, config, models.AccelerationFactory(model), first, params, chunk=chunk)), steps
