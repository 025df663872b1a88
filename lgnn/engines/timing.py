"""Timing of compiled runs: compile apart from running, one-off costs dropped.

`time_compiled(run, *args)` is what every speed measurement of lgnn reports (the
engines' `timed_rollout`, the stability cost per step, the benchmark's speed and
scaling stages), so their numbers mean the same thing.
"""

from __future__ import annotations

import time

import jax


def time_compiled(run, *args):
    """`(compile_s, run_s, out)` of a jitted `run(*args)`: compile apart, then one
    untimed run (its one-off costs, ~0.1 s for LGNN) and one timed run."""
    start = time.perf_counter()
    compiled = run.lower(*args).compile()
    compile_s = time.perf_counter() - start
    jax.block_until_ready(compiled(*args))
    start = time.perf_counter()
    out = jax.block_until_ready(compiled(*args))
    return compile_s, time.perf_counter() - start, out
