"""Speed of learned models: one training step (batch 10) and one learned rollout step.

Compilation is done before timing; each benchmark times the jitted call only (a fixed
number of rounds keeps the default run under a minute; LGN and CLNN are left out for
that reason: on 2 CPU cores an LGN training step took ~55 ms, CLNN ~2.6 ms, LGNN ~3 ms).
Run: `python -m pytest bench/test_models_bench.py --benchmark-only`.
"""

import jax
import jax.numpy as jnp
import optax
import pytest

from lgnn import models, physics, train
from lgnn.integrate import rk4
from lgnn.scene import State
from lgnn.scenes import get_scene, sample_initial_states

ROUNDS = 50


def _batch(scene, count):
    q, _ = sample_initial_states(scene, jax.random.PRNGKey(0), count)
    qd = 0.1 * jax.random.normal(jax.random.PRNGKey(1), q.shape)
    q, qd = jax.vmap(physics.projection_fn(scene))(q, qd)
    return q, qd, jax.vmap(physics.true_acceleration_fn(scene))(q, qd)


@pytest.mark.parametrize("name", ["lgnn", "gns"])
def test_training_step(benchmark, name):
    scene = get_scene("chain4")
    model = models.ModelConfig.for_scene(name, scene)
    params = models.init(jax.random.PRNGKey(0), model)
    opt = optax.adam(1e-3)
    loss = train.loss_fn(model, scene)

    @jax.jit
    def step(params, opt_state, q, qd, qdd):
        grads = jax.grad(loss)(params, q, qd, qdd)
        updates, opt_state = opt.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state

    batch = _batch(scene, 10)
    args = (params, opt.init(params), *batch)
    jax.block_until_ready(step(*args))
    benchmark.pedantic(lambda: jax.block_until_ready(step(*args)), rounds=ROUNDS)


@pytest.mark.parametrize("name", ["lgnn", "gns"])
def test_learned_rollout_step(benchmark, name):
    scene = get_scene("chain4")
    model = models.ModelConfig.for_scene(name, scene)
    accel = models.acceleration_fn(model, models.init(jax.random.PRNGKey(0), model), scene)
    integrator = rk4(accel, 1e-4, physics.projection_fn(scene))
    step = jax.jit(integrator.step_fn)
    carry = integrator.init_fn(State(jnp.asarray(scene.nodes), jnp.asarray(scene.velocities)))
    jax.block_until_ready(step(carry))
    benchmark.pedantic(lambda: jax.block_until_ready(step(carry)), rounds=ROUNDS)
