"""Committed rows re-derived by today's code (`lgnn leaderboard verify --row`), apart from
tests/test_verify.py so that its minute runs beside that file's tests (pytest -n auto
--dist loadfile gives each file to one worker)."""

from pathlib import Path

import pytest

from lgnn.bench import verify
from lgnn.bench.api import benchmark_profile
from lgnn.bench.stages import external
from lgnn.errors import ConfigError

RESULTS = Path(__file__).resolve().parents[1] / "results"


# One row of each track and dimension, each of another model family (a projected and an
# unprojected stack, a fixed-size model): the whole grid takes about 4 minutes on 2 cores,
# past CI's budget, and is `lgnn leaderboard verify results`, whose outcome is committed
# (results/benchmark/verification.json; tests/test_verify.py holds it to the records).
ROWS = ("lgnn", "gns (chain4-3d)", "chnn (chain4-3d)", "chgn (chain4-varied, 5 draws)", "lgnn-notebook (chain4-3d-varied, 5 draws)")


@pytest.mark.xla_optimised  # 1000-frame rollouts: optimised programs save more than they cost
def test_committed_rows_of_every_track_and_dimension_verify():
    """Committed rows re-derived by today's code (their smallest scene, one initial
    condition): each verified, within the tolerance, by the same command as the
    committed verification."""
    outcome = verify.verify(benchmark_profile("full"), RESULTS, conditions=1, rows=ROWS)
    assert [f.row for f in outcome.findings] == list(ROWS)
    assert all(f.status == verify.VERIFIED for f in outcome.findings), [f.line() for f in outcome.findings]
    assert external.load_externals(benchmark_profile("full"), RESULTS) == []


def test_an_unknown_row_is_one_line():
    with pytest.raises(ConfigError, match="no row 'nope' in the full profile's grid"):
        verify.verify(benchmark_profile("full"), RESULTS, rows=("nope",))
