"""Random initial conditions of any scene, consistent with its constraints.

Contract: `sample_initial_conditions(scene, count, seed) -> State` of NumPy arrays
(count, N, D): the scene's own state with every free node moved by Gaussian noise
(standard deviation `position_scale` times the mean link length per coordinate) and
Gaussian velocities added (standard deviation `velocity_scale` times the scene's
characteristic speed `sqrt(g l)`, or `l` per second without gravity), then put back on
the constraint manifold by `projection_fn` (Gauss-Newton on the positions, then the
orthogonal projection of the velocities onto the tangent space): link lengths hold,
pins stay put and at rest. It is the sampler for scenes the paper's chain sampler
(`lgnn.scene.sample_initial_states`, pinned chains only) does not cover: a user's scene
file gets `count` different trajectories, not `count` copies of one.

`sample_states(scene, count, seed)`: the paper's chain sampler on a pinned chain,
`sample_initial_conditions` otherwise. `own_or_sampled_states(scene, count, seed)`:
`lgnn evaluate`'s rule, the scene's own state for one initial condition, `sample_states`
for more. `benchmark_initial_states(scene, count, seed)` is the one rule the training
data and the benchmark's evaluation use: the scene's initial-state policy
(`lgnn.scene.initial_state_policy`: a catalogue entry's own, e.g. the paper's rest
states of T1-T3; for any other scene the chain sampler on a pinned chain,
`sample_initial_conditions` otherwise).

The projection is repeated while the worst violation still halves (linear convergence
near the self-stressed T2/T3, whose float64 tolerance is the looser
`SINGULAR_TOLERANCE`: what the Lagrangian engine keeps there itself). A sample it
could not bring onto the constraints (a perturbation across a singular configuration)
raises `SceneError` naming the scene, never a state that breaks them. Unlike the rest of `lgnn.physics` this function compiles its batch
(`jax.jit`, cached per scene content): it returns checked NumPy arrays, so it is never
traced by a caller, and run eagerly its vmapped Gauss-Newton steps took 20-45 s per call.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from lgnn.errors import ConfigError, SceneError
from lgnn.physics.constraints import constraint_violation, velocity_constraint_violation
from lgnn.physics.projection import projection_fn
from lgnn.physics.system import prepare
from lgnn.scene import CHAIN_SAMPLER, OWN_STATE, Scene, State, initial_state_policy, is_pinned_chain, sample_initial_states

# Position noise per coordinate, in mean link lengths: large enough that trajectories
# differ visibly, small enough that Gauss-Newton from the perturbed state converges
# to the nearby branch of the constraint manifold.
POSITION_SCALE = 0.05
# Velocity noise per coordinate, in units of the characteristic speed sqrt(g l).
VELOCITY_SCALE = 0.1
# Gauss-Newton steps of one projection round: quadratic convergence from a 5 %
# perturbation reaches round-off in about 5 (0.05, 3e-3, 6e-6, 4e-11); the rest is margin.
PROJECTION_ITERATIONS = 8
# Rounds are repeated while the worst violation still halves, at most this many: near
# the self-stressed (singular) T2/T3 the projection's Levenberg-Marquardt shift makes
# convergence linear (T2, 5 samples: 1e-4, 1e-5, 4e-7, 1e-7 after 8, 16, 32, 64 steps).
MAX_PROJECTION_ROUNDS = 16
# Largest constraint violation accepted, relative to the mean link length (and to the
# characteristic speed for velocities), in float64 and (without `lgnn.configure()`) float32.
TOLERANCE = {"float64": 1e-9, "float32": 1e-4}
# The float64 tolerance of a scene self-stressed at its own state (`self_stresses > 0`:
# T2, T3), where the shifted steps stop halving the violation near 1e-5 (worst of 20
# samples, seed 0: T2 6e-6, T3 8e-6; the median 1e-6): the benchmark's chaos-floor
# perturbation (`EvaluateSettings.floor_perturbation`, 1e-4 of a unit link), a
# difference it already counts as indistinguishable initial conditions; the engine's
# projection at every step then holds the constraints as on any T2/T3 run.
SINGULAR_TOLERANCE = 1e-4


def sample_initial_conditions(
    scene: Scene, count: int, seed: int, *, position_scale: float = POSITION_SCALE, velocity_scale: float = VELOCITY_SCALE
) -> State:
    """`count` random initial states (q, qd), each (count, N, D), near the scene's own
    and consistent with its constraints (module docstring). Same `seed`, same states."""
    if count < 1:
        raise ConfigError(f"need at least one initial condition, got {count}")
    if position_scale < 0 or velocity_scale < 0:
        raise ConfigError("sampler scales must be >= 0")
    length = float(np.mean(scene.lengths)) if scene.n_links else 1.0
    gravity = float(np.linalg.norm(scene.gravity_vector))
    speed = float(np.sqrt(gravity * length)) if gravity > 0 else length
    free = (~scene.fixed_mask).astype(np.float64)  # pins and rails' fixed coordinates stay
    key_q, key_qd = jax.random.split(jax.random.PRNGKey(seed))
    shape = (count, *scene.nodes.shape)
    q = scene.nodes + position_scale * length * free * np.asarray(jax.random.normal(key_q, shape, jnp.float64))
    qd = scene.velocities + velocity_scale * speed * free * np.asarray(jax.random.normal(key_qd, shape, jnp.float64))
    return projected_states(scene, q, qd, f"seed {seed}", hint="try a smaller position scale")


def projected_states(scene: Scene, q, qd, what: str, hint: str = "draw states nearer the constraints") -> State:
    """States `(q, qd)` (count, N, D) put on the scene's constraints: the projection
    (`projection_fn`) repeated while it still halves the worst violation, to the
    tolerance of their dtype (`TOLERANCE`). `SceneError` naming the state of `what` (the
    draw they came from) that cannot be put there."""
    q, qd = np.asarray(q), np.asarray(qd)
    length = float(np.mean(scene.lengths)) if scene.n_links else 1.0
    gravity = float(np.linalg.norm(scene.gravity_vector))
    speed = float(np.sqrt(gravity * length)) if gravity > 0 else length
    singular = prepare(scene).constraints.self_stresses > 0
    tolerance = SINGULAR_TOLERANCE if singular and q.dtype == np.float64 else TOLERANCE[str(q.dtype)]
    project = _projection(scene)
    worst_before = np.inf
    for _ in range(MAX_PROJECTION_ROUNDS):
        q, qd, position_error, velocity_error = map(np.asarray, project(jnp.asarray(q), jnp.asarray(qd)))
        worst = np.maximum(np.nan_to_num(position_error / length, nan=np.inf), np.nan_to_num(velocity_error / speed, nan=np.inf))
        if not scene.n_links or worst.max() <= tolerance or not worst.max() < 0.5 * worst_before:
            break
        worst_before = worst.max()
    if scene.n_links and worst.max() > tolerance:
        k = int(np.argmax(worst))
        raise SceneError(
            f"scene {scene.name!r}: initial condition {k} of {what} could not be put on the constraints "
            f"(relative violation {float(worst[k]):.1e} > {tolerance:g}, no longer halving per projection round); {hint}"
        )
    return State(np.asarray(q), np.asarray(qd))


def sample_states(scene: Scene, count: int, seed: int) -> State:
    """`count` different initial states (count, N, D) of any scene: the paper's sampler
    on a pinned chain, `sample_initial_conditions` on every other scene."""
    return _chain_sampler_states(scene, count, seed) if is_pinned_chain(scene) else sample_initial_conditions(scene, count, seed)


def _chain_sampler_states(scene: Scene, count: int, seed: int) -> State:
    if count < 1:
        raise ConfigError(f"need at least one initial condition, got {count}")
    states = sample_initial_states(scene, jax.random.PRNGKey(seed), count)
    return State(np.asarray(states.q), np.asarray(states.qd))


def own_or_sampled_states(scene: Scene, count: int, seed: int) -> State:
    """The scene's own state (count 1) or `count` sampled initial conditions
    (`sample_states` with `seed`), (count, N, D) float64: `lgnn evaluate`'s rule.
    Sampled on the CPU whatever the default device: the same states on every machine
    (an accelerator's sin and cos may differ in the last bit), and a few small
    operations that an accelerator would first compile one by one (7 s of an H100)."""
    if count == 1:
        return State(np.asarray(scene.nodes, np.float64)[None], np.asarray(scene.velocities, np.float64)[None])
    with jax.default_device(jax.devices("cpu")[0]):
        return sample_states(scene, count, seed)


def benchmark_initial_states(scene: Scene, count: int, seed: int) -> State:
    """`count` initial states (count, N, D) of training data or the benchmark's evaluation,
    by the scene's initial-state policy (`lgnn.scene.initial_state_policy`): its own
    state repeated, the chain sampler, or `sample_initial_conditions`."""
    policy = initial_state_policy(scene)
    if policy == OWN_STATE:
        return State(np.broadcast_to(scene.nodes, (count, *scene.nodes.shape)), np.broadcast_to(scene.velocities, (count, *scene.nodes.shape)))
    if policy == CHAIN_SAMPLER:
        if not is_pinned_chain(scene):
            raise SceneError(f"scene {scene.name!r}: the chain sampler needs a chain pinned at node 0")
        return _chain_sampler_states(scene, count, seed)
    return sample_initial_conditions(scene, count, seed)


@functools.lru_cache(maxsize=8)
def _projection(scene: Scene):
    """Jitted batch projection, returning the projected states and their position and
    velocity constraint violations (C,), cached per scene content."""
    project = projection_fn(scene, PROJECTION_ITERATIONS)

    def run(q, qd):
        q, qd = jax.vmap(project)(q, qd)
        violations = jax.vmap(lambda x, v: (constraint_violation(scene, x), velocity_constraint_violation(scene, x, v)))(q, qd)
        return (q, qd, *violations)

    return jax.jit(run)
