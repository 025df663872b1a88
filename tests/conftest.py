"""Shared test setup: float64 everywhere (accuracy is the point of these tests)."""

import os

from lgnn.runtime import COMPILATION_CACHE_ENV, configure

configure()  # first: thread counts and XLA flags before numpy and JAX load; float64
# No persistent compilation cache, in-process or in the `lgnn` processes tests start,
# unless a test asks for one (`lgnn.runtime.enable_compilation_cache`).
os.environ[COMPILATION_CACHE_ENV] = "off"

import jax
import pytest


@pytest.fixture(scope="session")
def x64():
    assert jax.config.jax_enable_x64
