"""Benchmark setup: float64 as the ground truth runs, and the two profiles.

`pytest bench/` runs the quick profile (minutes on 2 CPU cores, part of CI) into a
folder of the test run's own, removed when it ends: a test run never reads or writes
the user's `lgnn-out/`. `pytest bench/ --benchmark` runs the full profile into
`results/`, the committed run it resumes and updates, as `lgnn benchmark --full` does.
`--bench-out DIR` names the folder instead (`pytest bench/ --bench-out lgnn-out/quick`
checks the records `lgnn benchmark` wrote there, resuming from them). The profiles
themselves are declared in `lgnn.bench.profiles.PROFILES`.
"""

import os
import time
from pathlib import Path

import pytest

# Set by the top-level conftest: the test run's own folder for the quick profile.
TEST_BENCH_OUT_ENV = "LGNN_TEST_BENCH_OUT"


def pytest_addoption(parser):
    parser.addoption("--benchmark", action="store_true", default=False, help="run the full benchmark profile")
    parser.addoption("--bench-out", default=None, metavar="DIR",
                     help="folder the benchmark's stages write into and resume from (default: results/ with --benchmark, "
                          "else a temporary folder of this test run's)")


def bench_out(config) -> Path:
    """The folder this session's benchmark writes into (the module docstring)."""
    if config.getoption("--bench-out"):
        return Path(config.getoption("--bench-out"))
    if config.getoption("--benchmark"):
        from lgnn.bench.profiles import get_profile
        from lgnn.bench.store import default_out

        return default_out(get_profile("full"))
    return Path(os.environ[TEST_BENCH_OUT_ENV]) / "quick"


@pytest.fixture(scope="session")
def full_profile(request) -> bool:
    return bool(request.config.getoption("--benchmark"))


@pytest.fixture(scope="session")
def out(request) -> Path:
    return bench_out(request.config)


@pytest.fixture
def timing_benchmark(benchmark):
    """`benchmark` for a test that only times (it checks nothing else): skipped where
    pytest-benchmark does not time (under xdist, as in CI), where it would compile and
    run for nothing. `pytest bench/` without `-n` times it."""
    if benchmark.disabled:
        pytest.skip("a timing only, and pytest-benchmark does not time under xdist: run pytest bench/ without -n")
    return benchmark


@pytest.fixture
def record_rate(benchmark):
    """`record_rate(unit, count, **info)`: store what a benchmark timed in `extra_info`,
    and `count / mean time` as `<unit>_per_s` when timings exist (pytest-benchmark
    disables timing under xdist, as in CI, and then has no stats)."""

    def record(unit: str, count: float, **info) -> None:
        benchmark.extra_info.update(info, **{unit: count})
        if benchmark.stats is not None:
            benchmark.extra_info[f"{unit}_per_s"] = count / benchmark.stats.stats.mean

    return record


def pytest_sessionstart(session):
    session.config._lgnn_started = time.time()


def pytest_terminal_summary(terminalreporter, config):
    """Print the benchmark's summary table after the run if this session wrote the report
    (also under xdist, where the report is written by a worker)."""
    from lgnn.bench.profiles import get_profile

    profile = get_profile("full" if config.getoption("--benchmark") else "quick")
    readme = bench_out(config) / "README.md"
    if readme.exists() and readme.stat().st_mtime >= getattr(config, "_lgnn_started", float("inf")):
        text = readme.read_text()
        start = text.find("## Rollout error against the Lagrangian ground truth")
        end = text.find("## Energy error")
        terminalreporter.write_sep("=", f"lgnn benchmark ({profile.name} profile): {readme}")
        terminalreporter.write_line(text[start:end].strip())
