"""Test setup shared by `tests/` and `bench/`: lgnn's process settings before anything
loads JAX, no persistent compilation cache, and each test module's compiled programs
released when it ends."""

import os

from lgnn.runtime import COMPILATION_CACHE_ENV, configure

configure()  # first: thread counts and XLA flags before numpy and JAX load; float64
# No persistent compilation cache, in-process or in the `lgnn` processes tests start,
# unless a test asks for one (`lgnn.runtime.enable_compilation_cache`).
os.environ[COMPILATION_CACHE_ENV] = "off"

import jax  # noqa: E402
import pytest  # noqa: E402


# Every compiled XLA:CPU program holds a few memory mappings until JAX's caches let it
# go, and a process may hold at most `vm.max_map_count` of them (65530 by default). A
# test worker compiles thousands of programs: one held 49 000 mappings two-thirds of
# the way through the suite, and workers died inside XLA's compile near the end
# (SIGABRT; the message lost to pytest's output capture). Releasing the compiled
# programs after each test module bounds a worker's mappings by what one module
# compiles (measured: 300 small programs, 970 mappings, all returned by
# `jax.clear_caches`).
@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    yield
    jax.clear_caches()
