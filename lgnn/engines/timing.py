"""Timing of compiled runs: compile apart from running, one-off costs dropped.

`time_compiled(run, *args)` is the timing rule of lgnn's speed measurements: compile
apart, one untimed run, then timed runs; `lgnn.engines.rollouts.timed_rollouts` applies
the same rule to the one rollout path (the Lagrangian engine, learned models, the
benchmark's speed and scaling stages), and MJX's `timed_rollout` uses it directly, so
their numbers mean the same thing. `time_runs(call, repeats)` is its running half for
anything already compiled (a cached executable, MuJoCo Warp's captured step), with
repeats for a spread.
"""

from __future__ import annotations

import time

import jax


def time_runs(call, repeats: int = 1):
    """`(run_s, out)`: one untimed `call()` (its one-off costs, ~0.1 s for LGNN), then
    `repeats` timed calls, each waited for (`jax.block_until_ready`); `run_s` is the
    list of their seconds and `out` the last call's result."""
    jax.block_until_ready(call())
    run_s = []
    for _ in range(repeats):
        start = time.perf_counter()
        out = jax.block_until_ready(call())
        run_s.append(time.perf_counter() - start)
    return run_s, out


def compile_timed(run, *args):
    """`(compiled, compile_s)`: the jitted `run` compiled for `args`, and how long it took."""
    start = time.perf_counter()
    compiled = run.lower(*args).compile()
    return compiled, time.perf_counter() - start


def time_compiled(run, *args):
    """`(compile_s, run_s, out)` of a jitted `run(*args)`: compile apart, then one
    untimed run and one timed run (`time_runs`)."""
    compiled, compile_s = compile_timed(run, *args)
    (run_s,), out = time_runs(lambda: compiled(*args))
    return compile_s, run_s, out
