"""Test setup shared by `tests/` and `bench/`: lgnn's process settings before anything
loads JAX, no persistent compilation cache, and compiled programs released once a
worker holds too many."""

import os

from lgnn.runtime import COMPILATION_CACHE_ENV, configure, release_compiled_programs

configure()  # first: thread counts and XLA flags before numpy and JAX load; float64
# No persistent compilation cache, in-process or in the `lgnn` processes tests start,
# unless a test asks for one (`lgnn.runtime.enable_compilation_cache`).
os.environ[COMPILATION_CACHE_ENV] = "off"

import pytest  # noqa: E402


# A test worker compiles thousands of programs, each holding memory mappings until
# released, and would die inside XLA's compile at the kernel's limit on mappings
# (`lgnn.runtime.MAPPINGS_KEPT`): a test that leaves the process above that many
# releases every compiled program; below it, tests keep sharing what they compiled.
@pytest.fixture(autouse=True)
def _release_compiled_programs():
    yield
    release_compiled_programs()
