"""Shared test setup: float64 everywhere (accuracy is the point of these tests)."""

import os

# before numpy/jax load OpenBLAS (see lgnn/__init__.py)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402
import pytest

jax.config.update("jax_enable_x64", True)


@pytest.fixture(scope="session")
def x64():
    assert jax.config.jax_enable_x64
