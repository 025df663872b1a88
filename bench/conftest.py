"""Benchmark setup: float64, as the ground truth runs."""

import jax

jax.config.update("jax_enable_x64", True)
