"""Initial conditions of any scene, consistent with its constraints.

Contract: `sample_states(scene, key, count)` returns `count` initial states `(q, qd)`,
each (count, N, D), that satisfy every link length and pin (to the projection's
round-off) and keep them stationary:

- chains pinned at node 0 use the paper's sampler (`lgnn.scene.sample_initial_states`:
  random link angles, released from rest), as the benchmark does;
- every other scene (T1-T3, a user's scene file) gets random perturbations of its own
  state (`perturbed_states`): Gaussian noise on every free node's position and
  velocity, then the orthogonal projection back onto the constraint manifold
  (`lgnn.physics.projection`), so no two initial conditions are one trajectory.

Tolerances and why: the constants below. `PerturbationScales` holds the noise levels, relative to the scene's own scales so
one default fits scenes of any size.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from lgnn.errors import SceneError
from lgnn.physics.constraints import constraint_violation, velocity_constraint_violation
from lgnn.physics.projection import projection_fn
from lgnn.scene import Scene, State, is_pinned_chain, sample_initial_states

# The position projection is repeated (each call its few Gauss-Newton steps) until the
# link and pin errors are below POSITION_TOLERANCE mean link lengths, at most
# PROJECTION_ROUNDS times. Regular scenes reach round-off in one or two rounds; on the
# self-stressed T2/T3 a perturbation lands near a singular configuration, where the
# projection's Levenberg-Marquardt shift makes convergence linear and slow (T2: 1e-8
# lengths after 30 rounds from a 0.1-length perturbation). 1e-6 lengths is far below
# any error the benchmark resolves (learned rollout errors are >= 1e-4).
PROJECTION_ROUNDS = 100
# Link errors at this many lengths are round-off in float64.
ROUND_OFF = 1e-14
POSITION_TOLERANCE = 1e-6
# Velocities are projected onto a linear constraint at the projected positions, exact
# at regular ones; near T2/T3's singular configurations the shifted solve leaves
# length rates of ~4e-6 speed scales (T2), so the same relative tolerance applies.
VELOCITY_TOLERANCE = 1e-5


@dataclasses.dataclass(frozen=True)
class PerturbationScales:
    # Position noise per coordinate, in mean link lengths: enough to change the
    # motion visibly, small enough that the projection stays near the given shape.
    position: float = 0.1
    # Velocity noise per coordinate, in sqrt(g * mean link length) (the speed a drop of
    # one link gives; one length per second without gravity).
    velocity: float = 0.1

    def __post_init__(self):
        for name in ("position", "velocity"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise SceneError(f"perturbation {name} scale must be a non-negative number, got {value}")


def speed_scale(scene: Scene) -> float:
    """sqrt(g * mean link length), or mean link length per second without gravity."""
    length = float(np.mean(scene.lengths))
    return math.sqrt(abs(float(scene.gravity)) * length) if scene.gravity else length


def perturbed_states(scene: Scene, key: jax.Array, count: int, scales: PerturbationScales = PerturbationScales()) -> State:
    """`count` states (count, N, D): the scene's own state plus Gaussian noise (`scales`)
    on the free nodes, projected onto the constraints. `SceneError` (one line) if a
    projection does not reach the constraints (a perturbation too large for the
    scene's geometry)."""
    if count < 1:
        raise SceneError(f"need at least one initial condition, got {count}")
    q0, qd0 = (np.asarray(a, np.float64) for a in scene.initial_state)
    free = np.ones((scene.n_nodes, 1))
    free[list(scene.pinned)] = 0.0
    length = float(np.mean(scene.lengths))
    position_key, velocity_key = jax.random.split(key)
    shape = (count, *q0.shape)
    q = q0 + scales.position * length * free * np.asarray(jax.random.normal(position_key, shape, jnp.float64))
    qd = qd0 + scales.velocity * speed_scale(scene) * free * np.asarray(jax.random.normal(velocity_key, shape, jnp.float64))
    # Compiled once per call: the rounds repeat one function on the whole batch.
    project = jax.jit(jax.vmap(projection_fn(scene)))
    violation = jax.jit(jax.vmap(lambda x, v: (constraint_violation(scene, x), velocity_constraint_violation(scene, x, v))))
    q, qd = jnp.asarray(q), jnp.asarray(qd)
    previous = np.inf
    for _ in range(PROJECTION_ROUNDS):
        q, qd = project(q, qd)
        position_error, rate_error = (np.asarray(a) for a in violation(q, qd))
        worst = float(np.max(position_error))
        # Regular scenes go on to round-off; slowly converging ones stop once within
        # the tolerance and no longer halving their error.
        if worst <= ROUND_OFF * length or (worst <= POSITION_TOLERANCE * length and worst > previous / 2):
            break
        previous = worst
    bad = (position_error > POSITION_TOLERANCE * length) | (rate_error > VELOCITY_TOLERANCE * speed_scale(scene))
    if bad.any():
        k = int(np.argmax(bad))
        raise SceneError(
            f"{scene.name}: perturbed initial condition {k} did not project onto the constraints (link error "
            f"{position_error[k]:.2g}, rate error {rate_error[k]:.2g} after {PROJECTION_ROUNDS} projections): use smaller "
            f"perturbation scales than position {scales.position:g}, velocity {scales.velocity:g}"
        )
    q, qd = np.asarray(q), np.asarray(qd)
    return State(q, qd)


def sample_states(scene: Scene, key: jax.Array, count: int, scales: PerturbationScales = PerturbationScales()) -> State:
    """`count` initial conditions (count, N, D) of any scene (module docstring): the
    paper's sampler for chains pinned at node 0, constrained perturbations otherwise."""
    if count < 1:
        raise SceneError(f"need at least one initial condition, got {count}")
    if is_pinned_chain(scene):
        states = sample_initial_states(scene, key, count)
        return State(np.asarray(states.q, np.float64), np.asarray(states.qd, np.float64))
    return perturbed_states(scene, key, count, scales)
