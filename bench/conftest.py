"""Benchmark setup: float64 as the ground truth runs, and the two profiles.

`pytest bench/` runs the quick profile (minutes on 2 CPU cores, part of CI; outputs in
`lgnn-out/quick/`); `pytest bench/ --benchmark` runs the full profile (outputs in
`results/`). The profiles themselves are declared in `lgnn.bench.grid.PROFILES`.
"""

import time

import pytest


def pytest_addoption(parser):
    parser.addoption("--benchmark", action="store_true", default=False, help="run the full benchmark profile")


@pytest.fixture(scope="session")
def full_profile(request) -> bool:
    return bool(request.config.getoption("--benchmark"))


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
    from lgnn.bench.grid import get_profile
    from lgnn.bench.store import default_out

    profile = get_profile("full" if config.getoption("--benchmark") else "quick")
    readme = default_out(profile) / "README.md"
    if readme.exists() and readme.stat().st_mtime >= getattr(config, "_lgnn_started", float("inf")):
        text = readme.read_text()
        start = text.find("## Rollout error against the Lagrangian ground truth")
        end = text.find("## Energy error")
        terminalreporter.write_sep("=", f"lgnn benchmark ({profile.name} profile): {readme}")
        terminalreporter.write_line(text[start:end].strip())
