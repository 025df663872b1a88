"""The Lagrangian ground-truth engine: the scene's exact constrained dynamics.

`simulate(scene, config, integration=...)` integrates the scene's exact constrained
Lagrangian dynamics from its initial state (RK4 with projection unless another
`Integration` is given) and returns a `Trajectory` (NumPy): `t` (F,), `q` and `qd`
(F, N, D), `energy` (F,), frame 0 being the initial state. It is a batch of one of the
one rollout path (`lgnn.engines.rollouts.batched_rollouts`): frames in compiled calls
so long runs show progress, stopped at the first non-finite or exploding frame
(`lgnn.metrics.ExplosionBounds`) with a `SimulationError` that names its time and
carries the frames before it; a NaN trajectory is never returned.
`LagrangianEngine` is the `lgnn.engines.Engine` on top: a batch of initial states in
one compiled, vmapped program, and its timings (`timed_rollout`, and `timed_batch`
for `lgnn gpu-truth`); its `integration` field says how it integrates. `rollout_fn` is the pure per-state run
for callers that compile their own batch (data generation).
"""

from __future__ import annotations

import dataclasses
from typing import Callable, ClassVar

import jax
import numpy as np

from lgnn import physics
from lgnn.engines.base import Engine, Integration, SimulationConfig, Trajectory
from lgnn.engines.rollouts import Unparametrised, batched_rollouts, ground_truth_platform, timed_rollouts
from lgnn.errors import SceneError
from lgnn.integrate import rollout
from lgnn.runtime import in_float64
from lgnn.scene import Scene, State


def check_state(scene: Scene, state: State) -> State:
    """Validate an initial state's shape and finiteness against the scene."""
    q, qd = (np.asarray(a, np.float64) for a in state)
    expected = (scene.n_nodes, scene.dim)
    for name, value in (("q", q), ("qd", qd)):
        if value.shape != expected:
            raise SceneError(f"initial state {name}: expected shape {expected}, got {value.shape}")
        if not np.all(np.isfinite(value)):
            raise SceneError(f"initial state {name}: contains non-finite values")
    return State(q, qd)


def rollout_fn(
    scene: Scene,
    config: SimulationConfig,
    accel_factory: Callable[[Scene], physics.AccelerationFn] = physics.true_acceleration_fn,
    integration: Integration = Integration(),
) -> Callable[[jax.Array, jax.Array], State]:
    """`run(q, qd) -> State` of the `config.n_frames + 1` frames from one initial state
    integrated by `integration`: the pure function behind `simulate`, for callers to
    `jit` and `vmap` over initial conditions (benchmarks, data generation)."""
    integrator = integration.integrator_for(accel_factory(scene), config.dt, physics.projection_fn(scene))

    def run(q, qd):
        return rollout(integrator, State(q, qd), config.n_frames, config.steps_per_frame)

    return run


@in_float64  # the ground truth's accuracy, whatever jax_enable_x64 says
def simulate(
    scene: Scene,
    config: SimulationConfig = SimulationConfig(),
    state: State | None = None,
    *,
    integration: Integration = Integration(),
    accel_factory: Callable[..., physics.AccelerationFn] = physics.true_acceleration_fn,
    params=None,
    chunk_frames: int = 100,
    progress: bool = False,
    hint: str = "try a smaller dt",
) -> Trajectory:
    """Integrate from `state` (default: the scene's initial state) for `config.duration`
    by `integration` (its integrator and projection).

    `accel_factory(scene) -> accel` selects the dynamics (ground truth by default; a
    learned model's factory gives its rollout). With `params`, the factory is called as
    `accel_factory(scene, params)` and the params are an argument of the compiled run:
    a factory equal for equal models (`learn.models.AccelerationFactory`) compiles once
    whatever the params. Frames come `chunk_frames` per compiled call. Raises
    `SimulationError` at the first non-finite or exploding frame (`ExplosionBounds`),
    naming its time (`err.time`) and carrying the frames before it (`err.trajectory`);
    `hint` ends its message. Computes in float64 whether or not `lgnn.configure()` was
    called (`lgnn.runtime.precision`).
    """
    state = check_state(scene, scene.initial_state if state is None else state)
    factory = accel_factory if params is not None else Unparametrised(accel_factory)
    runs = batched_rollouts(scene, config, factory, State(state.q[None], state.qd[None]), params, integration=integration,
                            frames_per_call=chunk_frames, stop_at_divergence=True, progress=progress, hint=hint,
                            platform=None if params is not None else ground_truth_platform(1))
    return runs.trajectory(scene, config, integration).member(0)


@dataclasses.dataclass(frozen=True)
class LagrangianEngine(Engine):
    """The exact Lagrangian engine as an `lgnn.engines.Engine`: a batch of initial
    states in one compiled, vmapped program in `dtype` (`rollouts.batched_rollouts`),
    spread over every local device, stopped at divergence, integrated by
    `integration`; a progress bar if `progress`."""

    name: ClassVar[str] = "lagrangian"
    dtype: str = "float64"
    progress: bool = False
    integration: Integration = Integration()

    def rollout(self, scene: Scene, config: SimulationConfig, states: State) -> Trajectory:
        """`Trajectory` of initial states (B, N, D): q, qd (B, F+1, N, D), energy (B, F+1)."""
        for q, qd in zip(states.q, states.qd):
            check_state(scene, State(q, qd))
        runs = batched_rollouts(scene, config, _ground_truth(len(states.q)), states, integration=self.integration, dtype=self.dtype,
                                stop_at_divergence=True, progress=self.progress, platform=ground_truth_platform(len(states.q)))
        return runs.trajectory(scene, config, self.integration)

    def timed_rollout(self, scene: Scene, config: SimulationConfig, states: State) -> tuple[float, float, np.ndarray]:
        """`(compile_s, run_s, q (B, F+1, N, D))` of the compiled batch (`rollouts.timed_rollouts`)."""
        compile_s, (run_s,), runs = timed_rollouts(scene, config, _ground_truth(len(states.q)), states, integration=self.integration,
                                                   dtype=self.dtype)
        return compile_s, run_s, runs.q

    def timed_batch(self, scene: Scene, config: SimulationConfig, states: State, repeats: int = 1) -> tuple[float, list[float], np.ndarray]:
        """`(compile_s, run_s, q (B, N, D))`: the batch compiled once and timed `repeats`
        times (`rollouts.timed_rollouts`), the last run's final positions."""
        compile_s, run_s, runs = timed_rollouts(scene, config, _ground_truth(len(states.q)), states, integration=self.integration,
                                                repeats=repeats, dtype=self.dtype)
        return compile_s, run_s, runs.q[:, -1]


def _ground_truth(batch: int) -> Unparametrised:
    # The exact accelerations with the solver that vectorises over a batch (the same
    # accelerations to round-off, `physics.true_acceleration_fn`).
    return Unparametrised(physics.vectorised_true_acceleration_fn if batch > 1 else physics.true_acceleration_fn)
