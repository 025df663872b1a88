"""Steps per second of the ground-truth engines (pytest-benchmark), compile apart.

Each case runs 0.01 s of simulated time (100 RK4 steps at dt 1e-4) after a warm-up
round that holds compilation. The default run takes well under a minute; MJX (whose
CPU compile alone is ~35 s for chain4) runs only with LGNN_BENCH_MJX=1. The full
speed-against-error table is `python -m lgnn.cli crosscheck --speed`
(results/engines_speed_error.md).
"""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lgnn.engines import mjx
from lgnn.engines import mujoco as lm
from lgnn.scene import State
from lgnn.scene import get_scene, sample_initial_states
from lgnn.engines.base import SimulationConfig

CONFIG = SimulationConfig(dt=1e-4, frame_dt=0.01, duration=0.01)
STEPS = 100


def _states(name, batch):
    scene = get_scene(name)
    states = sample_initial_states(scene, jax.random.key(0), batch)
    return scene, State(np.asarray(states.q), np.asarray(states.qd))


@pytest.mark.parametrize("batch", [1, 100])
@pytest.mark.parametrize("name", ["chain4", "chain16", "chain100", "T1"])
def test_mujoco_c(timing_benchmark, record_rate, name, batch):
    scene, states = _states(name, batch)
    lm.compile_scene(scene, CONFIG.dt)
    # MuJoCo's stepping alone (the map to node states is a Python loop, see MujocoEngine.timed_rollout).
    timing_benchmark.pedantic(lm.joint_rollout, args=(scene, CONFIG, states), kwargs={"threads": 2}, rounds=3, warmup_rounds=1)
    record_rate("steps", batch * STEPS, scene=scene.name, batch=batch)


@pytest.mark.skipif(os.environ.get("LGNN_BENCH_MJX") != "1", reason="MJX compile is ~35 s on CPU: set LGNN_BENCH_MJX=1")
@pytest.mark.parametrize("batch", [1, 100])
def test_mjx_chain4(timing_benchmark, record_rate, batch):
    scene, states = _states("chain4", batch)
    run = mjx.runner(scene, CONFIG, "float64")
    args = (jnp.asarray(states.q), jnp.asarray(states.qd))
    timing_benchmark.pedantic(lambda: jax.block_until_ready(run(*args)), rounds=3, warmup_rounds=1)
    record_rate("steps", batch * STEPS, scene=scene.name, batch=batch)
