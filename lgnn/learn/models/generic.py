"""What works on any registered model: its parameters (`init`, with a learned drag on
drag scenes), its training-set statistics in them (`training_statistics`,
`with_statistics`, `split_statistics`, `join_statistics`), its output (`apply`,
`lagrangian_fn`, `acceleration_fn`, `trainable_acceleration_fn`, `mass_matrix_fn`) and
its rollouts (`rollout`, `AccelerationFactory`, `ModelEngine`), by the model's spec
(`registry.ModelSpec`), never its name.

Statistics are constants in the params pytree (`params[STATISTICS]`): `init` makes
placeholders, training fills them in once from its training states and steps only the
rest, checkpoints keep them like any leaf, so inference needs nothing else. Every
Lagrangian model goes through `physics.acceleration_fn`, the very same constrained
Euler-Lagrange solve as the ground truth; an acceleration model predicts node
accelerations itself. A model rolls out as an engine (`ModelEngine(config,
params).rollout(scene, config, states)`; `rollout` for one state), through the ground
truth's one batched path and integrators with the params an argument of the compiled
run (`AccelerationFactory`), compiled once per scene, settings and model config.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from lgnn import physics
from lgnn.engines.base import Engine, Integration, SimulationConfig, Trajectory
from lgnn.engines.lagrangian import check_state
from lgnn.engines.rollouts import Rollouts, batched_rollouts, timed_rollouts
from lgnn.errors import ConfigError
from lgnn.learn.graphs import edge_type_indices
from lgnn.learn.models.registry import ModelConfig, check_compatible
from lgnn.scene import Scene, State


# The params key of a model's training-set statistics (`ModelSpec.statistics`):
# constants, never trained.
STATISTICS = "statistics"


def training_statistics(config: ModelConfig, scene: Scene, q, qd, qdd) -> dict | None:
    """The statistics `config`'s model normalises by, of training states `q, qd` and
    targets `qdd` (each (S, N, D)) of `scene` (None for a model without any)."""
    spec = config.spec
    if spec.statistics is None:
        return None
    return {name: jnp.asarray(value) for name, value in spec.statistics(config, scene, q, qd, qdd).items()}


def with_statistics(params: dict, statistics: dict | None) -> dict:
    """`params` with `statistics` (from `training_statistics`) in place of its own:
    the placeholders `init` made, of the same names and shapes (`ConfigError` if not)."""
    if statistics is None:
        return params
    placeholder = params.get(STATISTICS) if isinstance(params, dict) else None
    if placeholder is None or set(placeholder) != set(statistics) or any(np.shape(placeholder[k]) != np.shape(statistics[k]) for k in statistics):
        raise ConfigError(f"the model's init must hold placeholders of its statistics ({', '.join(sorted(statistics))}) under params[{STATISTICS!r}]")
    return {**params, STATISTICS: {k: jnp.asarray(v, jnp.asarray(placeholder[k]).dtype) for k, v in statistics.items()}}


def split_statistics(params) -> tuple:
    """`(trainable, statistics)`: what an optimiser steps, and the constants (None if none)."""
    if isinstance(params, dict) and STATISTICS in params:
        return {k: v for k, v in params.items() if k != STATISTICS}, params[STATISTICS]
    return params, None


def join_statistics(trainable, statistics):
    """The params `split_statistics` split."""
    return trainable if statistics is None else {**trainable, STATISTICS: statistics}


def init(key, config: ModelConfig) -> dict:
    """Fresh parameters of `config`'s model (float64 under x64); statistics, if the
    model has any, at `init`'s placeholders until `with_statistics`."""
    params = config.spec.init(key, config)
    if config.drag and config.spec.is_lagrangian:
        params["drag"] = jnp.zeros(len(config.vocabulary))
    return params


def apply(config: ModelConfig, params: dict, graph):
    """The model's output on one graph: LGNN `(T, V)` per directed edge, LGN the global
    Lagrangian (), GNS node accelerations (N, D). CLNN has no graph: use `lagrangian_fn`."""
    if config.spec.apply is None:
        raise ConfigError(f"model {config.name} does not work on graphs")
    return config.spec.apply(config, params, graph)


def lagrangian_fn(config: ModelConfig, params: dict, scene: Scene) -> physics.LagrangianFn:
    """The learned `L(q, qd)` of a Lagrangian model on `scene`."""
    check_compatible(config, scene)
    if not config.spec.is_lagrangian:
        raise ConfigError(f"model {config.name} has no Lagrangian")
    return config.spec.lagrangian(config, params, scene)


def _learned_drag_fn(config: ModelConfig, params: dict, scene: Scene):
    if "drag" not in params:
        return None
    return physics.drag_force_fn(scene, params["drag"][edge_type_indices(scene, config.vocabulary)])


def acceleration_fn(config: ModelConfig, params: dict, scene: Scene) -> physics.AccelerationFn:
    """`accel(q, qd) -> qdd` (N, D) of the model on `scene` (any size for graph models)."""
    check_compatible(config, scene)
    params = _constant_statistics(params)
    if not config.spec.is_lagrangian:
        return config.spec.acceleration(config, params, scene)
    lagrangian, drag, mass = _lagrangian_parts(config, params, scene)
    return physics.acceleration_fn(scene, lagrangian, drag, mass=mass)


def trainable_acceleration_fn(config: ModelConfig, scene: Scene) -> Callable:
    """`accel(params, q, qd) -> qdd` (N, D): `acceleration_fn(config, params, scene)(q,
    qd)` with the parameters an argument, what training differentiates. A
    Lagrangian model's derivative by them comes from the adjoint of the constrained
    equations (`physics.parametrised_acceleration_fn`): the same gradient, fewer
    operations."""
    check_compatible(config, scene)
    if not config.spec.is_lagrangian:
        return lambda params, q, qd: acceleration_fn(config, params, scene)(q, qd)
    accel = physics.parametrised_acceleration_fn(scene, lambda params: _lagrangian_parts(config, params, scene))
    return lambda params, q, qd: accel(_constant_statistics(params), q, qd)


def _constant_statistics(params):
    """`params` with its statistics constants: no gradient reaches them, whoever differentiates."""
    trainable, statistics = split_statistics(params)
    return join_statistics(trainable, None if statistics is None else jax.lax.stop_gradient(statistics))


def _lagrangian_parts(config: ModelConfig, params: dict, scene: Scene) -> tuple:
    """`(lagrangian, drag force or None, mass structure or None)` of a Lagrangian model."""
    mass = None if config.spec.mass is None else config.spec.mass(config, params, scene)
    return lagrangian_fn(config, params, scene), _learned_drag_fn(config, params, scene), mass


def mass_matrix_fn(config: ModelConfig, params: dict, scene: Scene):
    """`M(q, qd) = d2L/dqd2` (N*D, N*D) of a Lagrangian model: the paper's learned mass matrix."""
    if not config.spec.is_lagrangian:
        raise ConfigError(f"model {config.name} predicts accelerations directly and has no mass matrix")
    return physics.mass_matrix_fn(lagrangian_fn(config, params, scene))


@dataclasses.dataclass(frozen=True)
class AccelerationFactory:
    """`factory(scene, params) -> accel`: `acceleration_fn` of one model config as a
    value equal for equal configs, so a rollout (`simulate(..., accel_factory=factory,
    params=params)`) compiles once per scene, simulation settings and model config and
    takes the params as an argument."""

    config: ModelConfig

    def __call__(self, scene: Scene, params) -> physics.AccelerationFn:
        return acceleration_fn(self.config, params, scene)


def rollout(config: ModelConfig, params: dict, scene: Scene, simulation: SimulationConfig | None = None, state=None, *,
            integration: Integration = Integration(), progress: bool = False) -> Trajectory:
    """The model's predicted `Trajectory` of `scene` from one `state` (N, D) (default:
    the scene's own): `ModelEngine.rollout` of a batch of one, integrated by
    `integration`; its `energy` is the scene's true Hamiltonian of the predicted
    states. A prediction that becomes non-finite or explodes stops with
    `SimulationError` naming the time."""
    state = check_state(scene, scene.initial_state if state is None else state)
    engine = ModelEngine(config, params, progress=progress, integration=integration)
    return engine.rollout(scene, simulation or SimulationConfig(), State(np.asarray(state.q)[None], np.asarray(state.qd)[None])).member(0)


@dataclasses.dataclass(frozen=True, eq=False)
class ModelEngine(Engine):
    """A learned model as an `lgnn.engines.Engine`: the same `rollout(scene, config,
    states) -> Trajectory` and `timed_rollout` as the ground-truth engines, through the
    one rollout path (`lgnn.engines.rollouts.batched_rollouts`: the batch vmapped in one
    program, the params an argument of it), so cross-checks and tools treat a model like
    any other engine, integrated by `integration` (RK4 with projection, as the ground
    truth, by default). Its trajectories' `energy` is the scene's true Hamiltonian of
    the predicted states; `rollout` stops at divergence like every engine, unless
    `stop_at_divergence` is off (scoring: the frames from a divergence on count as each
    metric's maximum), and rolls out `chunk` initial conditions per program (None:
    all). `rollouts` gives the batch with its costs, and rolls out a model's seeds
    together (`stacked`)."""

    config: ModelConfig
    params: dict
    dtype: str = "float64"
    progress: bool = False
    integration: Integration = Integration()
    stop_at_divergence: bool = True
    chunk: int | None = None
    # `params` holds S parameter sets of the model stacked along every leaf's first axis
    # (a model's seeds), rolled out in one program: trajectories (S, B, F+1, N, D).
    stacked: bool = False

    def __post_init__(self):
        if self.stacked and self.stop_at_divergence:
            raise ValueError("stacked parameter sets roll out past a divergence (scoring caps the frames from it): pass stop_at_divergence=False")

    @property
    def name(self) -> str:
        return self.config.name

    def rollouts(self, scene: Scene, config: SimulationConfig, states: State, label: str = "") -> Rollouts:
        """The batch's `lgnn.engines.rollouts.Rollouts` (positions, velocities, true
        energies, compile and run seconds, platform) from initial states (B, N, D),
        stacked (S, ...) where the engine is; `label` names it in progress and messages."""
        check_compatible(self.config, scene)
        return batched_rollouts(scene, config, AccelerationFactory(self.config), states, self.params, integration=self.integration,
                                dtype=self.dtype, chunk=self.chunk, stop_at_divergence=self.stop_at_divergence,
                                with_energy=True, stacked=self.stacked, progress=self.progress, label=label or f"{self.config.name} on {scene.name}",
                                hint=f"the {self.config.name} model's predicted dynamics diverge (its rollout stops there)")

    def rollout(self, scene: Scene, config: SimulationConfig, states: State) -> Trajectory:
        """Predicted trajectories from initial states (B, N, D): q, qd (B, F+1, N, D), energy (B, F+1)."""
        if self.stacked:
            raise ValueError("a stacked model's rollout is rollouts(): one Trajectory holds one parameter set's")
        return self.rollouts(scene, config, states).trajectory(scene, config, self.integration, {"model": self.config.to_dict()})

    def timed_rollout(self, scene: Scene, config: SimulationConfig, states: State) -> tuple[float, float, np.ndarray]:
        """`(compile_s, run_s, q (B, F+1, N, D))` of the batch (`rollouts.timed_rollouts`)."""
        check_compatible(self.config, scene)
        compile_s, (run_s,), runs = timed_rollouts(scene, config, AccelerationFactory(self.config), states, self.params,
                                                   integration=self.integration, dtype=self.dtype)
        return compile_s, run_s, runs.q
