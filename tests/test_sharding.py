"""Evaluation and data generation shard their batch over every local device.

The check runs in a subprocess with two forced CPU host devices
(`XLA_FLAGS=--xla_force_host_platform_device_count=2`: JAX reads it once, at start-up):
the sharded rollouts and data must equal the single-device results of this process,
with odd batch sizes so that padding is exercised.
"""

import json
import os
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path

import jax
import numpy as np

from lgnn.engines.rollouts import Unparametrised, batched_rollouts
from lgnn.learn import data
from lgnn import physics, sharding
from lgnn.scene import get_scene, sample_initial_states
from lgnn.engines.base import Integration, SimulationConfig

TRUE = Unparametrised(physics.true_acceleration_fn)
CONFIG = SimulationConfig(dt=1e-3, frame_dt=5e-3, duration=0.02)
DATA = data.DataConfig(n_trajectories=3, duration=0.04, sample_dt=0.01, chunk=3)

SHARDED = """
import json, sys
import lgnn, jax
lgnn.configure()
import numpy as np
from lgnn.engines import rollouts
from lgnn.learn import data
from lgnn import physics, sharding
from lgnn.scene import get_scene, sample_initial_states
from lgnn.engines.base import Integration, SimulationConfig
assert jax.device_count() == 2, jax.devices()
config = SimulationConfig(**json.loads(sys.argv[1]))
scene = get_scene("chain4")
states = sample_initial_states(scene, jax.random.PRNGKey(3), 3)
true = rollouts.Unparametrised(physics.true_acceleration_fn)
q = rollouts.batched_rollouts(scene, config, true, states, integration=Integration(), chunk=3).q
programs = rollouts.compiled_programs(scene, config, Integration(), true, 4, "float64", config.n_frames, False, rollouts.params_signature(None))
q0, qd0 = (jax.numpy.asarray(sharding.pad_batch(np.asarray(a), 4)) for a in states)
carry, _ = programs.start(None, q0, qd0)
devices = sorted(d.id for d in carry.state.q.sharding.device_set)
# Two parameter sets (ignored by the factory) sharing the sharded initial conditions.
stacked = rollouts.batched_rollouts(scene, config, true, states, np.zeros((2, 1)), integration=Integration(), stacked=True, chunk=3).q
assert stacked.shape == (2,) + q.shape and np.abs(stacked - q).max() < 1e-13, "stacked, sharded"
dataset = data.generate(data.DataConfig(**json.loads(sys.argv[2])))
np.savez(sys.argv[3], q=q, data_q=dataset.q, data_qdd=dataset.qdd)
print(json.dumps({"devices": devices}))
"""


def test_rollouts_and_data_sharded_over_two_devices_equal_one_device(tmp_path):
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2").strip()
    out = tmp_path / "sharded.npz"
    result = subprocess.run(
        [sys.executable, "-c", SHARDED, json.dumps(asdict(CONFIG)), json.dumps(asdict(DATA)), str(out)],
        capture_output=True, text=True, env=env, cwd=Path(__file__).resolve().parents[1], timeout=600,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert json.loads(result.stdout.splitlines()[-1])["devices"] == [0, 1], "the batch spans both devices"
    sharded = np.load(out)

    assert sharding.device_count() == 1
    scene = get_scene("chain4")
    states = sample_initial_states(scene, jax.random.PRNGKey(3), 3)
    q = batched_rollouts(scene, CONFIG, TRUE, states, integration=Integration(), chunk=3).q
    np.testing.assert_allclose(sharded["q"], q, rtol=0, atol=1e-13)
    dataset = data.generate(DATA)
    np.testing.assert_allclose(sharded["data_q"], dataset.q, rtol=0, atol=1e-13)
    np.testing.assert_allclose(sharded["data_qdd"], dataset.qdd, rtol=0, atol=1e-10)
    assert len(dataset.q) == DATA.n_trajectories * DATA.states_per_trajectory


def test_pad_batch_repeats_the_last_element():
    padded = sharding.pad_batch(np.arange(3.0)[:, None], 5)
    np.testing.assert_array_equal(padded[:, 0], [0, 1, 2, 2, 2])
    size = sharding.padded_size(3)
    assert size >= 3 and size % sharding.device_count() == 0 and size - 3 < sharding.device_count()


def test_seeds_rolled_out_together_equal_each_alone():
    """A stacked rollout (one compiled program for several parameter sets of one model,
    the evaluation's seeds) gives each set's trajectories as a rollout of that set
    alone does, with a padded last chunk."""
    from lgnn.learn import models

    scene = get_scene("chain4")
    config = models.ModelConfig("lgnn", latent=4, hidden=8)
    seeds = [models.init(jax.random.PRNGKey(seed), config) for seed in (0, 1)]
    states = sample_initial_states(scene, jax.random.PRNGKey(3), 3)
    stacked = jax.tree.map(lambda *leaves: np.stack(leaves), *seeds)
    factory = models.AccelerationFactory(config)
    runs = batched_rollouts(scene, CONFIG, factory, states, stacked, integration=Integration(), stacked=True, chunk=2, with_energy=True)
    q, qd = runs.q, runs.qd
    assert q.shape == (2, 3, CONFIG.n_frames + 1, scene.n_nodes, scene.dim) and runs.energy.shape == (2, 3, CONFIG.n_frames + 1)
    for params, q_seed, qd_seed in zip(seeds, q, qd):
        alone = batched_rollouts(scene, CONFIG, factory, states, params, integration=Integration(), chunk=2)
        np.testing.assert_allclose(q_seed, alone.q, rtol=0, atol=1e-12)
        np.testing.assert_allclose(qd_seed, alone.qd, rtol=0, atol=1e-10)
    assert np.abs(q[0] - q[1]).max() > 1e-6, "the two seeds' models differ"


def test_a_chunk_that_runs_out_of_device_memory_is_halved_and_the_last_one_is_a_clear_error(monkeypatch, capsys):
    """`batched_rollouts` (stacked or not, through the same loop): a call that
    runs out of device memory (a stand-in for XLA's RESOURCE_EXHAUSTED above 2 initial
    conditions per call) is retried with half the chunk, the trajectories unchanged; out
    of memory at the smallest chunk is one line, not a traceback from inside JAX."""
    import pytest

    from lgnn.engines import rollouts
    from lgnn.errors import SimulationError

    scene = get_scene("chain4")
    states = sample_initial_states(scene, jax.random.PRNGKey(3), 5)
    whole = batched_rollouts(scene, CONFIG, TRUE, states, integration=Integration(), chunk=8).q
    real = rollouts._run

    def limited(scene, config, programs, params, states, size, *args, limit=2):
        if size > limit:
            raise jax.errors.JaxRuntimeError(f"RESOURCE_EXHAUSTED: Out of memory while trying to allocate {size} GiB")
        return real(scene, config, programs, params, states, size, *args)

    monkeypatch.setattr(rollouts, "_run", limited)
    halved = batched_rollouts(scene, CONFIG, TRUE, states, integration=Integration(), chunk=8, label="halved").q
    # Chunks of 2 and of 8 are two compiled programs: round-off apart (as above).
    np.testing.assert_allclose(halved, whole, rtol=0, atol=1e-13)
    assert "halved: out of device memory with 5 initial conditions per call; retrying with 2" in capsys.readouterr().err
    monkeypatch.setattr(rollouts, "_run", lambda *args: limited(*args, limit=0))
    with pytest.raises(SimulationError, match="^none: out of device memory even with 1 rollouts per call"):
        batched_rollouts(scene, CONFIG, TRUE, states, integration=Integration(), chunk=8, label="none")
