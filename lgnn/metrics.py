"""One definition of each measure of a trajectory, used by every command and the benchmark.

- `energy_scale(scene, state)`: the energy a motion of the scene from `state` can
  involve: its mass times (its largest possible drop `g * size`, the initial squared
  speed, and a floor of moving its own size per second). It cannot vanish (a scene at
  rest without gravity still has one), unlike the initial energy, which is zero for a
  pendulum released horizontally.
- `energy_drift(scene, trajectory)`: `max_t |E(t) - E(0)| / energy_scale`, the
  maximum over the whole trajectory (not its last frame).
- `ExplosionBounds` and `divergence_frames`: the one divergence rule. A frame has
  diverged when its state is non-finite, or its true energy is more than
  `EXPLOSION_FACTOR` energy scales from the initial one (the true `H` is conserved or
  lost to drag), or a node is farther from its start than `EXPLOSION_FACTOR` sizes
  plus the distance a free fall covers (`v0 t + g t^2 / 2`, which only an unpinned
  body can approach). `size` is the sum of the link lengths plus the initial extent.
  Far enough that no correct run, however inaccurate, gets there; close enough to stop
  a diverging run long before overflow. Engines stop at the first such frame; the
  benchmark scores every frame from it on as the metric's maximum.
- `Metric`, `register_metric`, `METRICS`: the registry of per-frame errors (name,
  error function, unit, heading, axis label, maximum after divergence) that scoring,
  the benchmark's records, its report and `lgnn evaluate` all iterate: a metric is
  added here and nowhere else. `score_rollouts` scores a predicted `Trajectory`
  against one reference with each of them and returns a `Scored`; `trajectory_of`
  gives bare states their true energies.
- `relative_error`, `node_rms_error`, `clean_errors`, `rest_rollouts`,
  `error_statistics`, `summarise`, `gmean_error`: the benchmark's errors and their
  geometric-mean statistics with intervals. The paper's rollout and
  energy errors `||a - b|| / (||a|| + ||b||)` are normalised by the whole state, so they
  shrink as a structure grows; the per-node RMS position error `sqrt(mean over nodes
  |q_hat - q|^2)` (in lengths) does not. A diverged frame counts as each metric's
  maximum from its divergence on (1 for the relative errors, `diverged_node_error` for
  the RMS error); the rest baseline (`rest_rollouts`, the initial state held) is scored
  like any model.
- `max_constraint_violation`: the largest link-length or pin error over frames.

Arrays are NumPy; `q`, `qd` are (..., F, N, D) and energies (..., F) with frame 0 the
initial state.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from lgnn import physics
from lgnn.scene import Scene, State
from lgnn.trajectory import Trajectory

# How many scales beyond anything the scene's physics allows a state is "exploded".
EXPLOSION_FACTOR = 10.0
# Errors are clipped to [ERROR_FLOOR, 1]: 1 is the relative error's maximum, and the
# floor keeps an exact match from dominating a geometric mean.
ERROR_FLOOR = 1e-16


def structure_size(scene: Scene, q0: np.ndarray) -> float:
    """The sum of the link lengths plus the initial extent of the nodes `q0` (N, D)."""
    return float(np.sum(scene.lengths) + np.max(np.ptp(np.asarray(q0, np.float64), axis=0)))


def energy_scale(scene: Scene, state: State) -> float:
    """The energy a motion of `scene` from `state` can involve (module docstring)."""
    size = structure_size(scene, state.q)
    speed0 = float(np.max(np.linalg.norm(np.asarray(state.qd, np.float64), axis=-1)))
    mass = float(np.sum(scene.masses)) + float(np.sum(scene.node_mass_array))
    return mass * (float(np.linalg.norm(scene.gravity_vector)) * size + speed0**2 + size**2)


def energy_drift(scene: Scene, trajectory) -> float:
    """`max_t |E(t) - E(0)| / energy_scale` of a trajectory (anything with `q`, `qd`
    (F, N, D) and true energies `energy` (F,), frame 0 its initial state); NaN for an
    empty one."""
    energy = np.asarray(trajectory.energy, np.float64)
    if energy.size == 0:
        return math.nan
    scale = energy_scale(scene, State(trajectory.q[0], trajectory.qd[0]))
    return float(np.max(np.abs(energy - energy[0])) / scale)


@dataclasses.dataclass(frozen=True)
class ExplosionBounds:
    """What a correct motion of the scene from one initial state cannot exceed (the
    divergence rule of the module docstring)."""

    energy0: float
    energy_scale: float
    q0: np.ndarray
    size: float
    speed0: float
    gravity: float

    @classmethod
    def of(cls, scene: Scene, state: State, energy0: float) -> "ExplosionBounds":
        q0, qd0 = np.asarray(state.q, np.float64), np.asarray(state.qd, np.float64)
        speed0 = float(np.max(np.linalg.norm(qd0, axis=-1)))
        return cls(float(energy0), energy_scale(scene, state), q0, structure_size(scene, q0), speed0, float(np.linalg.norm(scene.gravity_vector)))

    def violations(self, t: np.ndarray, q: np.ndarray, qd: np.ndarray, energy: np.ndarray):
        """`(non_finite, energy_out, position_out)`, each (F,) booleans, for frames at
        times `t` (F,) with states `q`, `qd` (F, N, D) and true energies (F,)."""
        finite = np.isfinite(q).all(axis=(-1, -2)) & np.isfinite(qd).all(axis=(-1, -2)) & np.isfinite(energy)
        with np.errstate(invalid="ignore", over="ignore"):
            energy_out = np.abs(energy - self.energy0) > EXPLOSION_FACTOR * self.energy_scale
            reach = EXPLOSION_FACTOR * self.size + self.speed0 * t + 0.5 * self.gravity * t**2
            position_out = np.max(np.linalg.norm(q - self.q0, axis=-1), axis=-1) > reach
        return ~finite, energy_out & finite, position_out & finite

    def first_violation(self, t: np.ndarray, q: np.ndarray, qd: np.ndarray, energy: np.ndarray) -> tuple[int, str] | None:
        """(index, reason) of the first frame that is non-finite or exploding; None if
        every frame is fine."""
        non_finite, energy_out, position_out = self.violations(t, q, qd, energy)
        bad = non_finite | energy_out | position_out
        if not bad.any():
            return None
        k = int(np.argmax(bad))
        if non_finite[k]:
            return k, "became non-finite"
        if energy_out[k]:
            return k, f"exploded (true energy {energy[k]:.3g}, initial {self.energy0:.3g}, scale {self.energy_scale:.3g})"
        return k, f"exploded (a node moved {np.max(np.linalg.norm(q[k] - self.q0, axis=-1)):.3g} from its start, size {self.size:.3g})"


def divergence_frames(scene: Scene, t: np.ndarray, q: np.ndarray, qd: np.ndarray, energy: np.ndarray) -> np.ndarray:
    """(C,) index of the first diverged frame of each trajectory `q`, `qd` (C, F, N, D)
    with true energies (C, F) at times `t` (F,), or -1: `ExplosionBounds` from each
    trajectory's frame 0."""
    first = np.full(len(q), -1)
    for c in range(len(q)):
        bounds = ExplosionBounds.of(scene, State(q[c, 0], qd[c, 0]), float(energy[c, 0]))
        violation = bounds.first_violation(t, q[c], qd[c], energy[c])
        if violation is not None:
            first[c] = violation[0]
    return first


def limit_values(scene: Scene, q: np.ndarray, after: np.ndarray | None = None) -> np.ndarray:
    """(F, L) each of the scene's joint limits' quantity (`Scene.limits`: an angle in
    radians or a rail node's coordinate) at frames `q` (F, N, D) of one trajectory,
    angles unwrapped along the frames. `after` (L,) holds the values at the frame just
    before `q[0]`, so that a trajectory read in parts unwraps as it does whole; without
    it, frame 0 takes the turn nearest the middle of each range."""
    q = np.asarray(q, np.float64)
    values = []
    for which, limit in enumerate(scene.limits):
        if not limit.links:
            axis = next(a for node, a, _ in scene.rails if node == limit.node)
            values.append(q[:, limit.node, axis])
            continue
        e = limit.links[0]
        if len(limit.links) == 2:
            p = limit.links[1]
            (node,) = set(scene.edges[e]) & set(scene.edges[p])
            into = q[:, node] - q[:, _other_end(scene, p, node)]
        else:
            node = next(n for n in scene.edges[e] if n in scene.grounded_nodes)
            into = np.broadcast_to(np.array([1.0, 0.0]), q[:, node].shape)
        out = q[:, _other_end(scene, e, node)] - q[:, node]
        angle = np.arctan2(into[:, 0] * out[:, 1] - into[:, 1] * out[:, 0], np.sum(into * out, -1))
        if after is not None:
            values.append(np.unwrap(np.concatenate([[after[which]], angle]))[1:])
            continue
        angle = np.unwrap(angle)
        middle = 0.5 * (limit.low + limit.high)
        values.append(angle + 2 * np.pi * np.round((middle - angle[0]) / (2 * np.pi)))
    return np.stack(values, -1) if values else np.zeros((len(q), 0))


def _other_end(scene: Scene, link: int, node: int) -> int:
    i, j = scene.edges[link]
    return j if i == node else i


def limit_violation(scene: Scene, t: np.ndarray, q: np.ndarray) -> tuple[int, str] | None:
    """(index, reason) of the first frame of `q` (F, N, D) at times `t` (F,) outside a
    joint limit of the scene (`Scene.limits`, which lgnn does not enforce: an engine
    stops there, as at divergence), or None."""
    if not scene.limits:
        return None
    return first_outside_limits(scene, t, limit_values(scene, q))


def first_outside_limits(scene: Scene, t: np.ndarray, values: np.ndarray) -> tuple[int, str] | None:
    """`limit_violation` of the limits' values (F, L) (`limit_values`) at times `t` (F,)."""
    low, high = (np.array([getattr(limit, name) for limit in scene.limits]) for name in ("low", "high"))
    outside = (values < low) | (values > high)
    if not outside.any():
        return None
    k = int(np.argmax(outside.any(-1)))
    which = int(np.argmax(outside[k]))
    limit = scene.limits[which]
    joint = f"the rail of node {limit.node}" if not limit.links else f"the joint of links {list(limit.links)}"
    return k, f"left the range of {joint} at t = {t[k]:.6g} s ({values[k, which]:.6g} outside [{limit.low:.6g}, {limit.high:.6g}]; lgnn does not model joint limits)"


def true_energies(scene: Scene, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
    """The scene's true `H = T + V` of states `q`, `qd` (..., N, D) -> (...); NaN where a
    state is non-finite."""
    q, qd = np.asarray(q), np.asarray(qd)
    lead = q.shape[:-2]
    flat_q, flat_qd = q.reshape(-1, *q.shape[-2:]), qd.reshape(-1, *qd.shape[-2:])
    with np.errstate(invalid="ignore"):
        finite = np.isfinite(flat_q).all(axis=(-1, -2)) & np.isfinite(flat_qd).all(axis=(-1, -2))
    safe_q = np.where(finite[:, None, None], flat_q, scene.nodes)  # any finite state: masked below
    safe_qd = np.where(finite[:, None, None], flat_qd, 0.0)
    energy = np.asarray(jax.jit(jax.vmap(physics.energy_fn(scene)))(jnp.asarray(safe_q), jnp.asarray(safe_qd)))
    return np.where(finite, energy, np.nan).reshape(lead)


def max_constraint_violation(scene: Scene, q: np.ndarray) -> float:
    """Largest link-length or pin error over frames `q` (F, N, D); NaN for none."""
    if len(q) == 0:
        return math.nan
    return float(np.max(jax.jit(jax.vmap(lambda x: physics.constraint_violation(scene, x)))(jnp.asarray(q))))


def relative_error(a: np.ndarray, b: np.ndarray, trailing: int) -> np.ndarray:
    """`||a - b|| / (||a|| + ||b||)` over the last `trailing` axes. A diverged frame's
    huge values may overflow to inf or NaN here, silently: `clean_errors` sets every
    frame from divergence on, and every non-finite error, to the maximum."""
    axes = tuple(range(-trailing, 0))
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        diff = np.sqrt(np.sum((a - b) ** 2, axis=axes))
        scale = np.sqrt(np.sum(a**2, axis=axes)) + np.sqrt(np.sum(b**2, axis=axes))
        return diff / scale


def node_rms_error(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-node RMS position error `sqrt(mean over nodes |a - b|^2)` of positions
    (..., N, D) -> (...), in the scene's length unit."""
    return np.sqrt(np.mean(np.sum((np.asarray(a) - np.asarray(b)) ** 2, axis=-1), axis=-1))


def diverged_node_error(scene: Scene, q0: np.ndarray) -> float:
    """What a diverged frame's per-node RMS error counts as, and its cap: the distance
    `EXPLOSION_FACTOR * structure_size` at which the divergence rule calls a node lost."""
    return EXPLOSION_FACTOR * structure_size(scene, q0)


def clean_errors(errors: np.ndarray, diverged: np.ndarray, maximum: float | np.ndarray = 1.0) -> np.ndarray:
    """Errors (C, F) with every frame from divergence (`diverged` (C,) frame indices
    into these errors, -1 for none) on, and every non-finite one, set to `maximum` (a
    scalar or one per trajectory (C,): 1 for the relative errors); clipped to
    [ERROR_FLOOR * maximum, maximum]."""
    maximum = np.broadcast_to(np.asarray(maximum, np.float64), (errors.shape[0],))[:, None]
    frames = np.arange(errors.shape[1])
    after = (diverged[:, None] >= 0) & (frames[None] >= diverged[:, None])
    with np.errstate(invalid="ignore"):
        errors = np.where(after | ~np.isfinite(errors), maximum, errors)
    return np.clip(errors, ERROR_FLOOR * maximum, maximum)


def _relative_maximum(scene: Scene, q0: np.ndarray) -> float:
    """The relative errors' maximum: `||a - b|| / (||a|| + ||b||)` never exceeds 1."""
    return 1.0


@dataclasses.dataclass(frozen=True)
class Metric:
    """One per-frame error of predicted trajectories against a reference, as scoring,
    records, the report and the CLI all read it (`register_metric`).

    `error_fn(scene, predicted, reference) -> (C, F)`: raw errors per initial condition
    and frame of two batches of `lgnn.trajectory.Trajectory` (`t` (F,), `q`, `qd`
    (C, F, N, D), `energy` (C, F): the scene's true `H` of each's states), so a metric
    may read positions, velocities, energies and the scene's masses, lengths and
    gravity (NaN or inf where a state is non-finite: scoring sets those to the
    maximum). `maximum_fn(scene, q0) -> float`: what a diverged frame counts as and the
    cap of every frame, from an initial state's positions (N, D)."""

    name: str
    error_fn: Callable[[Scene, Trajectory, Trajectory], np.ndarray]
    # Unit in tables ("1": dimensionless).
    unit: str
    # Table heading against the Lagrangian ground truth, and the short title a heading
    # against another reference engine starts with ("<title> against MuJoCo").
    heading: str
    title: str
    # Y-axis label of its row in the error-against-time figures (None: not drawn).
    label: str | None = None
    maximum_fn: Callable[[Scene, np.ndarray], float] = _relative_maximum
    # A position error: the chaos floor (perturbed initial positions) is scored on it.
    floor: bool = False
    # Also scored against every reference engine of the benchmark (`<name>_vs_<engine>`).
    against_references: bool = False


# Every metric by name, in table order: `score_rollouts` scores each of them.
METRICS: dict[str, Metric] = {}


def register_metric(metric: Metric) -> Metric:
    """Add `metric` to `METRICS` (replacing one of the same name); returns it."""
    METRICS[metric.name] = metric
    return metric


register_metric(Metric("rollout_error", lambda scene, predicted, reference: relative_error(predicted.q, reference.q, 2), "1",
                       "Rollout error against the Lagrangian ground truth", "Rollout error", "rollout error (geometric mean)",
                       floor=True, against_references=True))
register_metric(Metric("node_rms_error", lambda scene, predicted, reference: node_rms_error(predicted.q, reference.q), "m",
                       "Per-node RMS position error against the Lagrangian ground truth", "Per-node RMS position error",
                       maximum_fn=lambda scene, q0: diverged_node_error(scene, q0), floor=True))
register_metric(Metric("energy_error", lambda scene, predicted, reference: relative_error(predicted.energy, reference.energy, 0), "1",
                       "Energy error", "Energy error", "energy error (geometric mean)"))


@dataclasses.dataclass(frozen=True)
class Scored:
    """Scores of predicted trajectories against one reference: `t` (F - 1,) frame times
    after the initial one, `errors` {metric name: clean errors (C, F - 1)}, `diverged`
    (C,) the prediction's first diverged frame (an index into the full trajectory,
    frame 0 the initial state) or -1; `scene`, `model` and `reference` name them."""

    scene: str
    model: str
    reference: str
    t: np.ndarray
    errors: dict[str, np.ndarray]
    diverged: np.ndarray


def trajectory_of(scene: Scene, t: np.ndarray, q: np.ndarray, qd: np.ndarray, metadata: dict | None = None) -> Trajectory:
    """States `q`, `qd` (C, F, N, D) at times `t` (F,) as a float64 `Trajectory` batch with
    the scene's true energies (`true_energies`): how states that carry no energies of
    their own (a file, the rest baseline, a stacked rollout) are scored."""
    q, qd = np.asarray(q, np.float64), np.asarray(qd, np.float64)
    return Trajectory(np.asarray(t), q, qd, true_energies(scene, q, qd), metadata or {})


def score_rollouts(scene: Scene, predicted: Trajectory, reference: Trajectory, model: str = "", reference_name: str = "",
                   names: tuple[str, ...] | None = None) -> Scored:
    """The scores of a predicted trajectory batch against a reference batch (both
    `Trajectory`: `q`, `qd` (C, F, N, D), the scene's true energies (C, F); frame 0 the
    initial states; `trajectory_of` makes one of bare states): every metric of
    `METRICS` (or those `names`) over frames t > 0. `diverged` is each prediction's first
    diverged frame (`divergence_frames`); from it on every error counts as the metric's
    maximum (`clean_errors`). Score one prediction against several references with the
    same `predicted`: its energies are computed once, by whoever made it."""
    diverged = divergence_frames(scene, predicted.t, predicted.q, predicted.qd, predicted.energy)
    errors = {}
    for name in METRICS if names is None else names:
        metric = METRICS[name]
        maximum = np.array([metric.maximum_fn(scene, q0) for q0 in predicted.q[:, 0]])
        errors[name] = clean_errors(metric.error_fn(scene, predicted, reference), diverged, maximum)[:, 1:]
    return Scored(scene.name, model, reference_name, np.asarray(predicted.t)[1:], errors, diverged)


def rest_rollouts(reference: Trajectory) -> Trajectory:
    """The rest baseline's prediction of a trajectory batch (C, F, N, D): every frame the
    initial state and its energy (the reference's frame 0), held. Scored against the
    truth its errors are the truth's own displacement from its start."""
    def held(a):
        return np.broadcast_to(np.asarray(a)[:, :1], np.shape(a))

    return Trajectory(reference.t, held(reference.q), held(reference.qd), held(reference.energy))


def error_statistics(errors: np.ndarray) -> dict:
    """From clean errors (C, F) over frames t > 0: per-IC mean log error (C,), and per
    frame the geometric mean over ICs with a normal-approximation 95% band (NaN for C = 1)."""
    logs = np.log(errors)
    mean = logs.mean(axis=0)
    half = 1.96 * logs.std(axis=0, ddof=1) / np.sqrt(len(logs)) if len(logs) > 1 else np.full_like(mean, np.nan)
    return {"per_ic_log": logs.mean(axis=1), "gmean": np.exp(mean), "low": np.exp(mean - half), "high": np.exp(mean + half)}


def summarise(per_ic_log: np.ndarray, seed: int = 0, resamples: int = 2000) -> tuple[float, float, float]:
    """Geometric mean over frames and ICs with a bootstrap 95% interval over ICs (NaN for one IC)."""
    value = float(np.exp(per_ic_log.mean()))
    if len(per_ic_log) < 2:
        return value, float("nan"), float("nan")
    rng = np.random.default_rng(seed)
    boots = per_ic_log[rng.integers(0, len(per_ic_log), (resamples, len(per_ic_log)))].mean(axis=1)
    low, high = np.percentile(boots, [2.5, 97.5])
    return value, float(np.exp(low)), float(np.exp(high))


def summarise_seeds(per_ic_logs, seed: int = 0, resamples: int = 2000) -> tuple[float, float, float]:
    """Geometric mean over training seeds, frames and ICs (each seed weighs the same)
    with a two-level bootstrap 95% interval: seeds resampled, then each resampled
    seed's ICs. `per_ic_logs`: one (C,) per-IC mean log error per seed. One seed: its
    `summarise`; one IC per seed: the interval is over seeds alone."""
    logs = [np.asarray(a, float) for a in per_ic_logs]
    if len(logs) == 1:
        return summarise(logs[0], seed, resamples)
    value = float(np.exp(np.mean([a.mean() for a in logs])))
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, len(logs), (resamples, len(logs)))
    sizes = {len(a) for a in logs}
    (size,) = sizes if len(sizes) == 1 else (None,)
    # The draws of every resampled seed's ICs in one call: the same numbers, in the same
    # order, as one call per seed (what this did in a loop, 2 million NumPy calls over the
    # full report), because a bounded draw of C values from a range of at least 2 takes C
    # 32-bit halves of C / 2 64-bit outputs when C is even, and a range of 1 draws nothing.
    # Other sizes keep the call per seed.
    if size is not None and (size == 1 or size % 2 == 0):
        stacked = np.stack(logs)
        ics = rng.integers(0, size, (resamples, len(logs), size))
        boots = stacked[picks[..., None], ics].mean(axis=-1).mean(axis=-1)
    else:
        boots = np.array([np.mean([logs[k][rng.integers(0, len(logs[k]), len(logs[k]))].mean() for k in pick]) for pick in picks])
    low, high = np.percentile(boots, [2.5, 97.5])
    return value, float(np.exp(low)), float(np.exp(high))


def gmean_error(q: np.ndarray, reference: np.ndarray) -> float:
    """Geometric mean over frames t > 0 of the rollout error of one trajectory `q`
    (F, N, D) against `reference`."""
    errors = clean_errors(relative_error(q, reference, 2)[None, 1:], np.array([-1]))
    return float(np.exp(np.mean(np.log(errors))))
