"""Shared test setup: float64 everywhere (accuracy is the point of these tests)."""

from lgnn.runtime import configure

configure()  # first: thread counts and XLA flags before numpy and JAX load; float64

import jax
import pytest


@pytest.fixture(scope="session")
def x64():
    assert jax.config.jax_enable_x64
