"""Benchmark setup: float64, as the ground truth runs."""

import os

# before numpy/jax load OpenBLAS (see lgnn/__init__.py)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
