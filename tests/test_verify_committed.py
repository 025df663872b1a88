"""Every row of the committed results re-derived (`lgnn leaderboard verify`), apart from
tests/test_verify.py so that its minutes run beside that file's tests (pytest -n auto
--dist loadfile gives each file to one worker)."""

from pathlib import Path

import pytest

from lgnn.bench import verify
from lgnn.bench.api import benchmark_profile
from lgnn.bench.stages import external

RESULTS = Path(__file__).resolve().parents[1] / "results"


@pytest.mark.slow
@pytest.mark.xla_optimised  # 32 rows of 1000-frame rollouts: optimised programs save more than they cost
def test_every_committed_row_verifies():
    """The acceptance: every row of the committed results re-derived (its smallest scene,
    one initial condition), none failed; the rows whose checkpoints were kept without
    their parameters are unverified, and only those."""
    outcome = verify.verify(benchmark_profile("full"), RESULTS, conditions=1)
    assert not outcome.failed, [f.line() for f in outcome.failed]
    unverified = [f.row for f in outcome.findings if f.status == verify.UNVERIFIED]
    assert unverified and all(row.startswith(("gns-10-128", "cgnode")) for row in unverified), unverified
    assert external.load_externals(benchmark_profile("full"), RESULTS) == []
