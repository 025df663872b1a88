"""Benchmark setup: float64 as the ground truth runs, and the two profiles.

`pytest bench/` runs the quick profile (minutes on 2 CPU cores, part of CI);
`pytest bench/ --benchmark` runs the full profile.
"""

import lgnn  # noqa: F401  (first: sets the XLA and OpenBLAS environment before JAX starts)
import jax
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)


def pytest_addoption(parser):
    parser.addoption("--benchmark", action="store_true", default=False, help="run the full benchmark profile")


@pytest.fixture(scope="session")
def full_profile(request) -> bool:
    return bool(request.config.getoption("--benchmark"))
