"""Benchmark setup: float64 as the ground truth runs, and the two profiles.

`pytest bench/` runs the quick profile (minutes on 2 CPU cores, part of CI);
`pytest bench/ --benchmark` runs the full profile.
"""

import os

# before numpy/jax load OpenBLAS (see lgnn/__init__.py)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)


def pytest_addoption(parser):
    parser.addoption("--benchmark", action="store_true", default=False, help="run the full benchmark profile")


@pytest.fixture(scope="session")
def full_profile(request) -> bool:
    return bool(request.config.getoption("--benchmark"))
