"""Shared test setup: float64 everywhere (accuracy is the point of these tests)."""

import lgnn  # noqa: F401  (first: sets the XLA and OpenBLAS environment before JAX starts)
import jax
import pytest

jax.config.update("jax_enable_x64", True)


@pytest.fixture(scope="session")
def x64():
    assert jax.config.jax_enable_x64
