"""Batched, timed rollouts: the benchmark's one way to run many initial conditions.

`compiled_rollouts` compiles a vmapped rollout once per (scene content, settings,
acceleration factory, batch size, dtype), sharded over every local device
(`lgnn.sharding`), and says how long the compile took; `batched_rollouts` runs it over
any number of initial conditions in chunks of that size (the last padded, so one
compile serves all) and times the runs apart from the compile; `stacked_rollouts` does
the same for several parameter sets of one model at once (its seeds). Both halve the
chunk when a call runs out of device memory. Single-trajectory
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
from lgnn.bench.store import log
from lgnn.errors import SimulationError
from lgnn.engines.lagrangian import SimulationConfig, params_rollout_fn, rollout_fn
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
    return _fitting_rollouts(lambda size: compiled_rollouts(scene, config, accel_factory, size, str(states.q.dtype)), states, chunk, 0, label,
                             progress)


def stacked_rollouts(scene: Scene, config: SimulationConfig, accel_factory: Callable, params, states: State, chunk: int, label: str,
                     progress: bool):
    """`(q, qd, compile_s, run_s)`: trajectories (S, C, F+1, N, D) of S parameter sets
    `params` (a pytree, S stacked along every leaf's first axis; `accel_factory(scene,
    params)` as `learn.models.AccelerationFactory`), each from the same C initial
    `states`, in one compiled program per chunk of `chunk` initial conditions: a model's
    seeds compile once and share every call (`batched_rollouts` compiles per parameter
    set, its parameters constants)."""
    run = sharding.shared_batch_jit(jax.vmap(jax.vmap(params_rollout_fn(scene, config, accel_factory), in_axes=(None, 0, 0)),
                                             in_axes=(0, None, None)), 2)
    params = jax.tree.map(jnp.asarray, params)

    def compiled(size: int):
        shape = jax.ShapeDtypeStruct((size, scene.n_nodes, scene.dim), states.q.dtype)
        start = time.perf_counter()
        program = run.lower(params, shape, shape).compile()
        return functools.partial(program, params), time.perf_counter() - start

    return _fitting_rollouts(compiled, states, chunk, 1, label, progress)


def _fitting_rollouts(compiled: Callable[[int], tuple[Callable, float]], states: State, chunk: int, axis: int, label: str, progress: bool):
    """`(q, qd, compile_s, run_s)` of `compiled(size) -> (run, compile_s)` over `states`
    in chunks of at most `chunk`, halved (and recompiled) whenever a call runs out of
    device memory: a chunk that suits one model's rollouts may not suit another's (LGN's
    dense mass matrix for three seeds x 100 initial conditions of chain100-3d asks an
    H100 for 108 GiB). Compile times add up; run time counts the run that finished."""
    chunk = sharding.padded_size(min(chunk, len(states.q)))
    compile_total = 0.0
    while True:
        run, compile_s = compiled(chunk)
        compile_total += compile_s
        try:
            q, qd, run_s = _run_chunks(run, states, chunk, axis, label, progress)
            return q, qd, compile_total, run_s
        except jax.errors.JaxRuntimeError as err:
            if "RESOURCE_EXHAUSTED" not in str(err):
                raise
            smaller = sharding.padded_size(max(1, chunk // 2))
            if smaller >= chunk:
                raise SimulationError(f"{label}: out of device memory even with {chunk} rollouts per call (a larger device, or fewer models "
                                      "at once: --job)") from None
            log(f"{label}: out of device memory with {chunk} initial conditions per call; retrying with {smaller}")
            chunk = smaller


def _run_chunks(compiled: Callable, states: State, chunk: int, axis: int, label: str, progress: bool):
    """`(q, qd, run_s)`: `compiled(q, qd) -> State` over `states` in chunks of `chunk`
    (the last padded), outputs concatenated along their batch `axis`, padding dropped."""
    from tqdm.auto import tqdm

    count = len(states.q)
    pad = lambda a, start: jnp.asarray(sharding.pad_batch(a[start : start + chunk], chunk))  # noqa: E731
    qs, qds = [], []
    run_s = 0.0
    with tqdm(total=count, desc=label, unit="IC", disable=not progress, leave=False, file=sys.stderr) as bar:
        for start in range(0, count, chunk):
            t0 = time.perf_counter()
            out = jax.block_until_ready(compiled(pad(states.q, start), pad(states.qd, start)))
            run_s += time.perf_counter() - t0
            take = (slice(None),) * axis + (slice(0, min(chunk, count - start)),)
            qs.append(np.asarray(out.q[take]))
            qds.append(np.asarray(out.qd[take]))
            bar.update(take[-1].stop)
    return np.concatenate(qs, axis), np.concatenate(qds, axis), run_s
