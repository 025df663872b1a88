"""Test setup shared by `tests/` and `bench/`: lgnn's process settings before anything
loads JAX, a persistent compilation cache of the test run's, a dataset cache of each test's own, and
compiled programs released once a worker holds too many."""

import atexit
import os
import shutil
import tempfile

from lgnn.runtime import COMPILATION_CACHE_ENV, configure, enable_compilation_cache, release_compiled_programs

# Where a test run's workers find the compilation cache they share (below).
SHARED_JAX_CACHE_ENV = "LGNN_TEST_JAX_CACHE"

# The tests compile thousands of small programs that each run for milliseconds, so XLA's
# optimisation passes cost more than they save (a third of a model test's time). They
# change no arithmetic the tests check: results are IEEE either way, and every tolerance
# holds at both levels. Read as JAX loads, here and in the `lgnn` processes tests start.
os.environ.setdefault("JAX_DISABLE_MOST_OPTIMIZATIONS", "1")
configure()  # then: thread counts and XLA flags before numpy and JAX load; float64
# Datasets of module- and session-scoped fixtures: a folder of this worker's, never the
# user's cache (each test then gets one of its own, `_own_dataset_cache`).
os.environ["LGNN_CACHE"] = tempfile.mkdtemp(prefix="lgnn-test-cache-")
atexit.register(shutil.rmtree, os.environ["LGNN_CACHE"], ignore_errors=True)
# A persistent compilation cache of this test run's, never the user's, shared by its
# xdist workers, in-process and in the `lgnn` processes tests start: tests compile the
# same programs again and again (each `lgnn` process its scene's, each test its own
# closures, in whichever worker its file runs), and a cache hit is the program XLA
# compiled before. `lgnn benchmark --workers` shares one cache between processes the
# same way. The run's first process (the xdist controller, or pytest without xdist)
# makes it and removes it when it exits, after its workers; it starts empty, so every
# program is compiled at least once per run; a test that asks for another (or none)
# sets its own.
if SHARED_JAX_CACHE_ENV not in os.environ or "PYTEST_XDIST_WORKER" not in os.environ:
    os.environ[SHARED_JAX_CACHE_ENV] = tempfile.mkdtemp(prefix="lgnn-test-jax-")
    atexit.register(shutil.rmtree, os.environ[SHARED_JAX_CACHE_ENV], ignore_errors=True)
os.environ[COMPILATION_CACHE_ENV] = os.environ[SHARED_JAX_CACHE_ENV]
enable_compilation_cache()
# Where `bench/`'s quick profile writes its records and resumes from (`bench/conftest.py`):
# a folder of this test run's, made by its first process as the compilation cache is and
# shared by its workers, never the user's `lgnn-out/` (which `lgnn benchmark` wrote and a
# test run must neither read nor touch). `pytest bench/ --bench-out DIR` names another.
TEST_BENCH_OUT_ENV = "LGNN_TEST_BENCH_OUT"
if TEST_BENCH_OUT_ENV not in os.environ or "PYTEST_XDIST_WORKER" not in os.environ:
    os.environ[TEST_BENCH_OUT_ENV] = tempfile.mkdtemp(prefix="lgnn-test-bench-")
    atexit.register(shutil.rmtree, os.environ[TEST_BENCH_OUT_ENV], ignore_errors=True)

import pytest  # noqa: E402


# Tests that run their programs long (MJX's steps, thousands of them) compile them with
# XLA's optimisations, as users do: there the optimised program pays for itself.
@pytest.fixture(autouse=True)
def _optimised_compiles_where_marked(request):
    if request.node.get_closest_marker("xla_optimised") is None:
        yield
        return
    import jax

    jax.config.update("jax_disable_most_optimizations", False)
    try:
        yield
    finally:
        jax.config.update("jax_disable_most_optimizations", True)


# Each test (and the `lgnn` processes it starts) caches datasets in a folder of its own,
# as every test has its own output folder: no test reads another's data, and none
# writes to the user's cache.
@pytest.fixture(autouse=True)
def _own_dataset_cache(tmp_path_factory, monkeypatch):
    monkeypatch.setenv("LGNN_CACHE", str(tmp_path_factory.mktemp("lgnn-cache")))


# A test worker compiles thousands of programs, each holding memory mappings until
# released, and would die inside XLA's compile at the kernel's limit on mappings
# (`lgnn.runtime.MAPPINGS_KEPT`): a test that leaves the process above that many
# releases every compiled program; below it, tests keep sharing what they compiled.
@pytest.fixture(autouse=True)
def _release_compiled_programs():
    yield
    release_compiled_programs()
