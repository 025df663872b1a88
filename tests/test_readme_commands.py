"""The README's two commands in the order it gives them: `lgnn benchmark` (the quick
profile, into `./lgnn-out/quick/`), then the test suite, in one home folder.

The test suite never reads or writes a user's `lgnn-out/` (its quick benchmark runs in a
folder of its own, `bench/conftest.py`), and `pytest bench/ --bench-out DIR` checks the
records a run of `lgnn benchmark` left in DIR, resuming from them: that must pass as a
fresh run does. Here the first command runs as a user's own process would (its own
caches in a fresh home, none of the test run's settings), restricted to the training of jobs
whose check once failed on a resumed checkpoint (the statistics the graph networks
normalise by, compared bit for bit with ones computed in another program); then those
tests run in a second process, on the first's records.
"""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from lgnn.bench import profiles, store

ROOT = Path(__file__).resolve().parents[1]
# Two of the four quick-profile jobs whose check failed (every model that normalises by
# training statistics computes them by one function, `models.training_statistics`): the
# strong GNS's and the Hamiltonian graph network's.
JOBS = ("gns-10-128-chain4-s0", "chgn-chain4-s0")
# What the test run's own processes set (the root conftest) and a user's shell does not.
TEST_ONLY_ENV = ("JAX_DISABLE_MOST_OPTIMIZATIONS", "LGNN_CACHE", "LGNN_JAX_CACHE", "LGNN_TEST_JAX_CACHE",
                 "LGNN_TEST_BENCH_OUT", "PYTEST_XDIST_WORKER", "PYTEST_XDIST_WORKER_COUNT", "PYTEST_CURRENT_TEST")


def _user_env(home: Path) -> dict:
    env = {key: value for key, value in os.environ.items() if key not in TEST_ONLY_ENV and not key.startswith("XDG_")}
    return {**env, "HOME": str(home)}


@pytest.mark.slow
def test_the_tests_pass_on_the_records_lgnn_benchmark_left_in_a_fresh_home(tmp_path):
    home = tmp_path / "home"
    home.mkdir()
    env = _user_env(home)
    first = subprocess.run([sys.executable, "-m", "lgnn", "benchmark", "--quiet", "--stage", "train", *(f"--job={j}" for j in JOBS)],
                           cwd=home, env=env, capture_output=True, text=True, timeout=1200)
    assert first.returncode == 0, first.stdout[-3000:] + first.stderr[-3000:]
    out = home / "lgnn-out" / "quick"
    jobs = {job.name: job for job in profiles.training_jobs(profiles.PROFILES["quick"])}
    checkpoints = [store.Layout(out).checkpoint(jobs[name]) for name in JOBS]
    written = [path.read_bytes() for path in checkpoints]
    selected = [f"bench/test_benchmark.py::test_training[{job}]" for job in JOBS]
    second = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--benchmark-disable",
                             "-o", "addopts=", f"--bench-out={out}", *selected],
                            cwd=ROOT, env=env, capture_output=True, text=True, timeout=1200)
    report = second.stdout[-5000:] + second.stderr[-2000:]
    assert second.returncode == 0, report
    assert f"{len(JOBS)} passed" in second.stdout, report
    # It checked the first command's checkpoints, not ones of its own, and left them as they were.
    assert [path.read_bytes() for path in checkpoints] == written
