"""Steps per second of the Lagrangian ground truth (RK4, dt 1e-4, projection on),
single trajectory and a batch of 100, compile time reported apart.

pytest-benchmark times a jitted, vmapped rollout of STEPS steps after a warm-up round
that holds compilation; `extra_info` records steps/s and the compile time. The quick
profile skips the chain100 batch (about a minute per round on 2 cores); the full
profile (`--benchmark`) runs it.
"""

import time

import jax
import jax.numpy as jnp
import pytest

from lgnn.scene import get_scene, sample_initial_states
from lgnn.engines.base import SimulationConfig
from lgnn.engines.lagrangian import rollout_fn

STEPS = 20
CONFIG = SimulationConfig(dt=1e-4, frame_dt=STEPS * 1e-4, duration=STEPS * 1e-4)


@pytest.mark.parametrize("batch", [1, 100])
@pytest.mark.parametrize("name", ["chain4", "chain16", "chain100", "T1"])
def test_lagrangian_rk4_steps_per_second(timing_benchmark, record_rate, full_profile, name, batch):
    if name == "chain100" and batch > 1 and not full_profile:
        pytest.skip("chain100 x 100 runs only in the full profile (--benchmark)")
    scene = get_scene(name)
    states = sample_initial_states(scene, jax.random.PRNGKey(0), batch)
    run = jax.jit(jax.vmap(rollout_fn(scene, CONFIG)))
    q, qd = jnp.asarray(states.q), jnp.asarray(states.qd)
    start = time.perf_counter()
    jax.block_until_ready(run(q, qd))
    compile_s = time.perf_counter() - start
    timing_benchmark.pedantic(lambda: jax.block_until_ready(run(q, qd)), rounds=5 if full_profile else 2, iterations=1)
    record_rate("steps", batch * STEPS, scene=name, batch=batch, compile_s=compile_s)
