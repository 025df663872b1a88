"""Batched, timed rollouts: the benchmark's one way to run many initial conditions.

`compiled_rollouts` compiles a vmapped rollout once per (scene content, settings,
acceleration factory, batch size, dtype), sharded over every local device
(`lgnn.sharding`), and says how long the compile took; `batched_rollouts` runs it over
any number of initial conditions in chunks of that size (the last padded, so one
compile serves all) and times the runs apart from the compile. Single-trajectory
timings are `lgnn.engines.timing.time_compiled` and `Engine.timed_rollout`.
"""

from __future__ import annotations

import functools
import sys
import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from lgnn import sharding
from lgnn.engines.lagrangian import SimulationConfig, rollout_fn
from lgnn.scene import Scene, State


@functools.lru_cache(maxsize=64)
def compiled_rollouts(scene: Scene, config: SimulationConfig, accel_factory: Callable, chunk: int, dtype: str):
    """`(compiled, compile_s)`: the jitted, vmapped rollout of `chunk` initial
    conditions (a multiple of the device count: they are sharded over every local
    device), compiled once per (scene, settings, acceleration factory); a scene is a
    cache key by content."""
    run = sharding.batch_jit(jax.vmap(rollout_fn(scene, config, accel_factory)))
    shape = jax.ShapeDtypeStruct((chunk, scene.n_nodes, scene.dim), jnp.dtype(dtype))
    start = time.perf_counter()
    compiled = run.lower(shape, shape).compile()
    return compiled, time.perf_counter() - start


def batched_rollouts(scene: Scene, config: SimulationConfig, accel_factory: Callable, states: State, chunk: int, label: str, progress: bool):
    """`(q, qd, compile_s, run_s)`: trajectories (C, F+1, N, D) from the C initial
    `states`, in vmapped chunks of `chunk` (the last padded), with the compile and run times."""
    from tqdm.auto import tqdm

    count = len(states.q)
    chunk = sharding.padded_size(min(chunk, count))
    compiled, compile_s = compiled_rollouts(scene, config, accel_factory, chunk, str(states.q.dtype))
    pad = lambda a, start: jnp.asarray(sharding.pad_batch(a[start : start + chunk], chunk))  # noqa: E731
    qs, qds = [], []
    run_s = 0.0
    with tqdm(total=count, desc=label, unit="IC", disable=not progress, leave=False, file=sys.stderr) as bar:
        for start in range(0, count, chunk):
            t0 = time.perf_counter()
            out = jax.block_until_ready(compiled(pad(states.q, start), pad(states.qd, start)))
            run_s += time.perf_counter() - t0
            take = min(chunk, count - start)
            qs.append(np.asarray(out.q[:take]))
            qds.append(np.asarray(out.qd[:take]))
            bar.update(take)
    return np.concatenate(qs), np.concatenate(qds), compile_s, run_s
