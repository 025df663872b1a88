"""The one rollout path of the JAX engines: a batch of initial conditions, compiled once.

`batched_rollouts(scene, config, accel_factory, states, params, integration=...)`
integrates initial states (B, N, D) with the accelerations `accel_factory(scene,
params)` by the `Integration` given (integrator and projection; a ground truth
ignores `params`: `Unparametrised(physics.true_acceleration_fn)`; a learned model's
factory is `lgnn.learn.models.AccelerationFactory`) and returns `Rollouts`: `q`, `qd`
(B, F+1, N, D), the scene's true `energy` (B, F+1), and the seconds spent compiling
and running. How:

- `vmap` over the initial conditions, the batch sharded over every local device
  (`lgnn.sharding`; padded to a multiple of the device count, padding dropped);
- one compiled program per (scene content, settings, integration, acceleration
  factory, batch size, dtype, frames per call, parameter shapes) (`compiled_programs`, cached): the
  parameters are an ARGUMENT of the program, never constants, so a second checkpoint
  of one model config compiles nothing;
- `stacked=True`: `params` holds S parameter sets of one model stacked along every
  leaf's first axis (a model's seeds), rolled out in the same program from the same
  initial conditions: `q`, `qd` (S, B, F+1, N, D), `energy` (S, B, F+1);
- frames in calls of `frames_per_call` (about 100), so a long run shows progress and a
  reference (`stop_at_divergence`) stops at the first non-finite or exploding frame of
  any member (`lgnn.metrics.ExplosionBounds`) with a `SimulationError` naming its time
  and carrying that member's frames before it (`err.trajectory`); a model's rollouts
  run on (their frames from divergence on count as each metric's maximum);
- at most `chunk` initial conditions per program; a chunk that runs out of device
  memory is halved (and recompiled) until it fits, and one line says so;
- compile time apart from run time: `compile_s` is what compiling the programs took
  (when they were compiled, perhaps by an earlier call; the halved chunks' added up),
  `run_s` the compiled calls alone.

`integration` (`lgnn.engines.base.Integration`) is a required argument: the caller
(an engine, a stage) says how it integrates; nothing falls back to a default here.

`platform` says where a batch runs: None, JAX's default device (learned models, and
every timing); `ground_truth_platform(batch)`, what the exact dynamics' rollouts pass
(the Lagrangian engine, the evaluation's ground truth): the host's CPU for a batch of at
most `HOST_BATCH_MAX` on a GPU machine (the constant's comment), the default device
otherwise. `Rollouts.platform` says where it ran.

`timed_rollouts` is the timing rule on top (a warm-up call, then timed repeats), for
`Engine.timed_rollout` and the benchmark's speed and scaling stages.
"""

from __future__ import annotations

import dataclasses
import functools
import sys
import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from lgnn import physics, sharding
from lgnn.engines.base import Integration, SimulationConfig, Trajectory
from lgnn.errors import SimulationError
from lgnn.integrate import advance
from lgnn.metrics import ExplosionBounds, first_outside_limits, limit_values
from lgnn.physics import solvers
from lgnn.runtime import precision
from lgnn.scene import Scene, State, scene_to_dict

# Frames per compiled call: a long run reports progress and is checked for divergence
# this often, at a cost of one host round trip per call.
FRAMES_PER_CALL = 100
# The exact dynamics' rollouts of a small batch run faster on the host's CPU than on a
# GPU, whose step is a chain of tiny kernels that costs their latency whatever the
# batch. Measured on one H200 and its 16-core host (results/gpu/host-rollouts/), ms per
# RK4 step of the vectorised solver: chain16 at batch 1, 0.078 on the host against 0.48
# on the GPU (vmapped; one trajectory with `lgnn simulate`'s solver: 0.35-0.44); T1 at
# 1, 0.27 against 1.9; chain16 at 16, 0.31 against 0.48; at 256 the GPU wins, 0.54
# against 4.7. Batches of at most this many run on the host (`ground_truth_platform`).
# Learned models stay on the default device: the GPU was ahead from 3 rollouts
# (lgnn-notebook, 3 seeds: T1 5.2 against 9.0 ms, chain16 1.55 against 2.38), and the
# evaluate stage's single-initial-condition parts took 100 s with their models on the
# GPU, 197 s on the host.
HOST_BATCH_MAX = 16


@dataclasses.dataclass(frozen=True)
class Unparametrised:
    """`factory(scene) -> accel` (e.g. `physics.true_acceleration_fn`) as the
    `(scene, params) -> accel` factory `batched_rollouts` takes, ignoring `params`;
    equal for equal factories, so its programs are cached like any other."""

    factory: Callable[[Scene], physics.AccelerationFn]

    def __call__(self, scene: Scene, params) -> physics.AccelerationFn:
        return self.factory(scene)


@dataclasses.dataclass(frozen=True)
class Rollouts:
    """`q`, `qd` (B, F+1, N, D) and true `energy` (B, F+1; None where not asked for),
    float64, frame 0 the initial state (with a leading S axis when stacked);
    `compile_s` and `run_s` (seconds); the `platform` they ran on."""

    q: np.ndarray
    qd: np.ndarray
    energy: np.ndarray | None
    compile_s: float
    run_s: float
    platform: str  # where the programs ran ("cpu", "gpu", ...)

    def trajectory(self, scene: Scene, config: SimulationConfig, integration: Integration, metadata: dict | None = None) -> Trajectory:
        """The rollouts as a `Trajectory` batch (not stacked), with the scene, settings
        and integration in its metadata (and `metadata`); rollouts made `with_energy`."""
        if self.energy is None:
            raise ValueError("a Trajectory carries energies: roll out with_energy")
        t = np.arange(self.q.shape[-3]) * config.frame_dt
        meta = {**run_metadata(scene, config, integration), **(metadata or {})}
        return Trajectory(t, self.q, self.qd, self.energy, meta)


@dataclasses.dataclass(frozen=True)
class _Programs:
    start: Callable  # (params, q, qd) -> (carry, energy0)
    step: Callable  # (params, carry) -> (carry, q, qd, energy), `frames` frames
    frames: int
    compile_s: float
    with_energy: bool
    integration: Integration  # what the programs integrate by (named in a divergence's message)


def params_signature(params) -> tuple:
    """A hashable description of `params`' structure, shapes and dtypes."""
    leaves, treedef = jax.tree.flatten(params)
    return treedef, tuple((np.shape(leaf), str(np.asarray(leaf).dtype)) for leaf in leaves)


def run_metadata(scene: Scene, config: SimulationConfig, integration: Integration) -> dict:
    """A JAX rollout's `Trajectory.metadata`: the scene, the settings (`config`) and
    the integration that ran (`integration`)."""
    return {"scene": scene_to_dict(scene), "config": dataclasses.asdict(config), "integration": dataclasses.asdict(integration)}


def _one_trajectory_on_cpu(batch: int) -> bool:
    """Whether a program of `batch` trajectories steps one trajectory on a CPU: it runs
    unvmapped, so that a `lax.cond` inside it is a real branch (`_over_batch`), and its
    steps are cheap enough that RK4's stage loop would cost a fifth of them
    (`integrate.rk4`)."""
    return batch == 1 and sharding.platform() == "cpu"


def _over_batch(fn: Callable, in_axes: tuple, batch: int) -> Callable:
    """`fn` mapped over a leading batch axis of the arguments `in_axes` marks: `vmap`,
    or for a batch of one on a CPU `fn` itself with the axis taken off and put back, so
    that a `lax.cond` inside stays a branch (under `vmap` both of its branches run: one
    trajectory's guarded Schur solve, `solvers.guarded_spd_solve`). An accelerator
    always takes `vmap`: there the batch-of-one program was never faster, and with the
    vectorised chain solve it took 1 s per chain16 RK4 step against 0.48 ms vmapped
    (one H200, results/gpu/host-rollouts/batch-of-one.jsonl)."""
    if not _one_trajectory_on_cpu(batch):
        return jax.vmap(fn, in_axes=in_axes)

    def one(*args):
        args = [arg if axis is None else jax.tree.map(lambda x: x[0], arg) for arg, axis in zip(args, in_axes)]
        return jax.tree.map(lambda x: x[None], fn(*args))

    return one


def adaptive_projection(batch: int, stacked: bool) -> bool:
    """Whether a program's projection skips its second step and pass where the first
    reached round-off (`physics.projection_fn`'s `adaptive`): for one trajectory on a
    CPU, where that is a branch (`_over_batch`). It never skips a step a state needs,
    so any dynamics may take it; the exact dynamics' drift over a small step is
    round-off, so the ground truth mostly skips, a learned model's seldom. The same
    flag has the projection solve its tridiagonal Gram systems by LAPACK's `gtsv`, one
    call, where a batch's sweeps vectorise (`physics.solvers.LinkGram.solve_fn`)."""
    return _one_trajectory_on_cpu(batch) and not stacked


def ground_truth_platform(rollouts: int) -> str | None:
    """Where the exact dynamics' batch of `rollouts` runs fastest: "cpu" (the host)
    for at most `HOST_BATCH_MAX` where JAX's default backend is an accelerator, else
    None (the default device)."""
    return "cpu" if rollouts <= HOST_BATCH_MAX and jax.default_backend() != "cpu" else None


@functools.lru_cache(maxsize=64)
def compiled_programs(scene: Scene, config: SimulationConfig, integration: Integration, accel_factory: Callable, batch: int, dtype: str,
                      frames: int, stacked: bool, signature: tuple, with_energy: bool = True, platform: str | None = None) -> _Programs:
    """The compiled `start` and `step` programs of `batched_rollouts` for `batch`
    initial conditions (a multiple of the device count) and parameters of
    `signature` (`params_signature`), `frames` frames per `step`, the true energy of
    each frame computed `with_energy` (else None: about a quarter of a small scene's
    compile time), for the devices of `platform` (the caller's `sharding.platform()`,
    inside whose context they run); cached (a scene is a key by content), so
    `compiled_programs.cache_info().misses` counts compilations."""
    project = physics.projection_fn(scene, adaptive=adaptive_projection(batch, stacked))
    true_energy = physics.energy_fn(scene)

    def energy(q, qd):
        return true_energy(q, qd) if with_energy else None

    def integrator(params):
        return integration.integrator_for(accel_factory(scene, params), config.dt, project, cheap_steps=_one_trajectory_on_cpu(batch))

    def start(params, q, qd):
        carry = integrator(params).init_fn(State(q, qd))
        return carry, energy(carry.state.q, carry.state.qd)

    def step(params, carry):
        carry, states = advance(integrator(params), carry, frames, config.steps_per_frame)
        return carry, states.q, states.qd, jax.vmap(energy)(states.q, states.qd) if with_energy else None

    start, step = _over_batch(start, (None, 0, 0), batch), _over_batch(step, (None, 0), batch)
    if stacked:
        start, step = jax.vmap(start, in_axes=(0, None, None)), jax.vmap(step, in_axes=(0, 0))
    whole, ics, batched = sharding.axis_sharding(None), sharding.axis_sharding(0), sharding.axis_sharding(1 if stacked else 0)
    treedef, leaves = signature
    params = jax.tree.unflatten(treedef, [jax.ShapeDtypeStruct(shape, dtype_) for shape, dtype_ in leaves])
    state = jax.ShapeDtypeStruct((batch, scene.n_nodes, scene.dim), jnp.dtype(dtype))
    # The solves inside see one system; the chain elimination is chosen for how many
    # the program solves at once on each device.
    systems = batch * (leaves[0][0][0] if stacked else 1) // sharding.device_count()
    began = time.perf_counter()
    with solvers.systems_at_once(systems):
        start = jax.jit(start, in_shardings=(whole, ics, ics), out_shardings=batched).lower(params, state, state)
        carry = start.out_info[0]
        start = start.compile()
        step = jax.jit(step, in_shardings=(whole, batched), out_shardings=batched).lower(params, carry).compile()
    return _Programs(start, step, frames, time.perf_counter() - began, with_energy, integration)


def batched_rollouts(scene: Scene, config: SimulationConfig, accel_factory: Callable, states: State, params=None, *,
                     integration: Integration, stacked: bool = False, dtype: str = "float64", chunk: int | None = None,
                     frames_per_call: int = FRAMES_PER_CALL, stop_at_divergence: bool = False, with_energy: bool = False, label: str = "",
                     progress: bool = False, hint: str = "try a smaller dt", platform: str | None = None) -> Rollouts:
    """Rollouts of initial `states` (B, N, D) under `accel_factory(scene, params)`
    (module docstring) integrated by `integration` (its integrator and projection):
    at most `chunk` (None: all) initial conditions per program, computed in `dtype`
    on the devices of `platform` (None: the default's; `ground_truth_platform`);
    `stop_at_divergence` for a reference, `hint` ending its error; the true energies
    `with_energy` or `stop_at_divergence` (else `Rollouts.energy` is None); `label`
    names the run in progress bars and messages (default: the scene's name)."""
    if stop_at_divergence and stacked:
        raise ValueError("stop_at_divergence is for a reference's rollouts, not stacked parameter sets")
    label = label or scene.name
    count = len(states.q)
    calls = -(-config.n_frames // max(1, frames_per_call))
    frames = -(-config.n_frames // calls)  # the last call runs past the end; its extra frames are dropped
    with sharding.on_platform(platform), precision(dtype):
        params = None if params is None else jax.tree.map(lambda leaf: jnp.asarray(leaf, _param_dtype(leaf, dtype)), params)
        q0, qd0 = (np.asarray(a, dtype) for a in states)
        signature = params_signature(params)
        size = sharding.padded_size(min(chunk or count, count))
        compile_total = 0.0
        while True:
            try:
                programs = compiled_programs(scene, config, integration, accel_factory, size, dtype, frames, stacked, signature,
                                             with_energy or stop_at_divergence, sharding.platform())
                compile_total += programs.compile_s
                out, run_s = _run(scene, config, programs, params, State(q0, qd0), size, stacked, stop_at_divergence, label, progress, hint)
                return Rollouts(*out, compile_s=compile_total, run_s=run_s, platform=sharding.platform())
            except jax.errors.JaxRuntimeError as err:
                if "RESOURCE_EXHAUSTED" not in str(err):
                    raise
                smaller = sharding.padded_size(max(1, size // 2))
                if smaller >= size:
                    raise SimulationError(f"{label}: out of device memory even with {size} rollouts per call (a larger device, or fewer "
                                          "models at once: --job)") from None
                print(f"{label}: out of device memory with {size} initial conditions per call; retrying with {smaller}", file=sys.stderr,
                      flush=True)
                size = smaller


def _param_dtype(leaf, dtype: str):
    # Floating parameters compute in the rollout's precision; integer ones stay as they are.
    return dtype if jnp.issubdtype(jnp.asarray(leaf).dtype, jnp.floating) else jnp.asarray(leaf).dtype


def _run(scene: Scene, config: SimulationConfig, programs: _Programs, params, states: State, size: int, stacked: bool, stop: bool,
         label: str, progress: bool, hint: str):
    """`((q, qd, energy), run_s)` of `programs` over `states` in chunks of `size`
    initial conditions (the last padded), `programs.frames` frames per call."""
    from tqdm.auto import tqdm

    count, n_frames = len(states.q), config.n_frames
    lead = (len(jax.tree.leaves(params)[0]),) if stacked else ()
    q_all = np.empty(lead + (count, n_frames + 1, scene.n_nodes, scene.dim))
    qd_all = np.empty_like(q_all)
    energy_all = np.empty(lead + (count, n_frames + 1)) if programs.with_energy else None
    run_s = 0.0
    ics = (slice(None),) * len(lead)
    with tqdm(total=count * n_frames, desc=label, unit="frame", disable=not progress, leave=False, file=sys.stderr) as bar:
        for first in range(0, count, size):
            taken = min(size, count - first)
            batch = (*ics, slice(first, first + taken))
            padded = [jnp.asarray(sharding.pad_batch(a[first:first + taken], size)) for a in states]
            began = time.perf_counter()
            carry, energy0 = jax.block_until_ready(programs.start(params, *padded))
            run_s += time.perf_counter() - began
            q_all[batch + (0,)], qd_all[batch + (0,)] = states.q[first:first + taken], states.qd[first:first + taken]
            if energy_all is not None:
                energy_all[batch + (0,)] = np.asarray(energy0)[(*ics, slice(0, taken))]
            bounds = [ExplosionBounds.of(scene, State(states.q[c], states.qd[c]), float(energy_all[(c, 0)]))
                      for c in range(first, first + taken)] if stop else None
            # Each initial condition's joint-limit values at the last frame read (if the
            # scene has limits), so that each chunk's angles unwrap on from the last
            # (`limit_values`).
            limits_at = [limit_values(scene, states.q[c][None])[0] for c in range(first, first + taken)] if stop and scene.limits else None
            done = 0
            while done < n_frames:
                began = time.perf_counter()
                carry, q, qd, energy = jax.block_until_ready(programs.step(params, carry))
                run_s += time.perf_counter() - began
                kept = min(programs.frames, n_frames - done)
                frames = slice(done + 1, done + 1 + kept)
                part = (*ics, slice(0, taken), slice(0, kept))
                q_all[batch + (frames,)], qd_all[batch + (frames,)] = np.asarray(q)[part], np.asarray(qd)[part]
                if energy_all is not None:
                    energy_all[batch + (frames,)] = np.asarray(energy)[part]
                if bounds is not None:
                    limits_at = _stop_at_divergence(scene, config, programs.integration, bounds, limits_at, first, q_all, qd_all,
                                                    energy_all, done, kept, label, hint)
                done += kept
                bar.update(taken * kept)
    return (q_all, qd_all, energy_all), run_s


def _stop_at_divergence(scene: Scene, config: SimulationConfig, integration: Integration, bounds: list[ExplosionBounds],
                        limits_at: list[np.ndarray] | None, first: int, q: np.ndarray, qd: np.ndarray, energy: np.ndarray, done: int,
                        kept: int, label: str, hint: str) -> list[np.ndarray] | None:
    """Raise `SimulationError` at the first non-finite or exploding frame, or the first
    frame outside a joint limit, among frames `done + 1 ... done + kept` of initial
    conditions `first, first + 1, ...`; else return their joint-limit values at frame
    `done + kept` (`limits_at` holds them at frame `done`; None for a scene without
    limits, which gets None back)."""
    frames = slice(done + 1, done + 1 + kept)
    t = (done + 1 + np.arange(kept)) * config.frame_dt
    found = [(violation[0], c, violation[1]) for c, member in enumerate(bounds, first)
             if (violation := member.first_violation(t, q[c, frames], qd[c, frames], energy[c, frames])) is not None]
    # A joint limit (which the engines do not model) stops a run as divergence does; a
    # scene without limits (`limits_at` None) has none to read.
    values, limits = [], []
    if limits_at is not None:
        values = [limit_values(scene, q[c, frames], after=at) for c, at in enumerate(limits_at, first)]
        checked, limit_t = values, t
        if done == 0:  # an initial state outside a limit stops the run at that frame alone (k = -1)
            checked, limit_t = [np.concatenate([at[None], part]) for at, part in zip(limits_at, values)], np.concatenate([[0.0], t])
        limits = [(violation[0] - (done == 0), c, violation[1]) for c, part in enumerate(checked, first)
                  if (violation := first_outside_limits(scene, limit_t, part)) is not None]
    if not found and not limits:
        return None if limits_at is None else [part[-1] for part in values]
    k, c, reason = min(found + limits)
    end = max(done + 1 + k, 1)
    partial = Trajectory(np.arange(end) * config.frame_dt, q[c, :end].copy(), qd[c, :end].copy(), energy[c, :end].copy(),
                         run_metadata(scene, config, integration))
    member = f", initial condition {c}" if len(q) > 1 else ""
    if (k, c, reason) in limits:
        raise SimulationError(f"{label}: state {reason}{member}", time=float(t[k]) if k >= 0 else 0.0, trajectory=partial)
    raise SimulationError(f"{label}: state {reason} at t = {t[k]:.6g} s ({integration.integrator}, dt = {config.dt:g}{member}); {hint}",
                          time=float(t[k]), trajectory=partial)


def timed_rollouts(scene: Scene, config: SimulationConfig, accel_factory: Callable, states: State, params=None, *, repeats: int = 1,
                   **options) -> tuple[float, list[float], Rollouts]:
    """`(compile_s, run_s, rollouts)`: `batched_rollouts` (same options) once to compile
    and warm up (its one-off costs dropped), then `repeats` timed calls; `run_s` lists
    their seconds and `rollouts` is the last call's."""
    warm = batched_rollouts(scene, config, accel_factory, states, params, **options)
    timed = [batched_rollouts(scene, config, accel_factory, states, params, **options) for _ in range(repeats)]
    return warm.compile_s, [run.run_s for run in timed], timed[-1]
