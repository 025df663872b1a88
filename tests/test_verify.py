"""`lgnn leaderboard verify`: every committed row re-derived, and forged records,
checkpoints and summaries named in one line.

The forgery tests work on a copy of one committed row (LGNN on chain4, three seeds, its
chain4 records and ground-truth record), verified under the full profile narrowed to that
row, and change what a forger would: a number of a record with its checksum recomputed,
a parameter of a checkpoint with its checksum recomputed, a number of the summary.
"""

import gzip
import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from lgnn import records
from lgnn.bench import verify
from lgnn.bench.api import benchmark_profile
from lgnn.bench.report.summary import tables
from lgnn.bench.stages import evaluate
from lgnn.bench.tables import write_csv
from lgnn.cli import EXIT_CHECK_FAILED, main

RESULTS = Path(__file__).resolve().parents[1] / "results"
ROW = ("--set", "models=['lgnn']", "--set", "tracks=['paper']", "--set", "scenes=['chain4']")
JOBS = [f"lgnn-chain4-s{seed}" for seed in range(3)]


def _row_copy(folder: Path) -> Path:
    """The committed LGNN row on chain4 copied into `folder`."""
    bench = folder / "benchmark"
    for job in JOBS:
        (bench / "checkpoints").mkdir(parents=True, exist_ok=True)
        shutil.copy(RESULTS / "benchmark" / "checkpoints" / f"{job}.npz", bench / "checkpoints")
        (bench / "runs" / job).mkdir(parents=True, exist_ok=True)
        shutil.copy(RESULTS / "benchmark" / "runs" / job / "chain4.npz", bench / "runs" / job)
    (bench / "runs" / "ground-truth").mkdir(parents=True)
    shutil.copy(RESULTS / "benchmark" / "runs" / "ground-truth" / "chain4.npz", bench / "runs" / "ground-truth")
    return folder


def _profile():
    return benchmark_profile("full", settings=[ROW[k + 1] for k in range(0, len(ROW), 2)])


def _verify(folder, capsys, *extra):
    code = main(["leaderboard", "verify", str(folder), "--initial-conditions", "1", "--quiet", *ROW, *extra])
    return code, capsys.readouterr().out


def _resave(path: Path, change) -> None:
    """Rewrite a record with `change(arrays, meta)` applied and its checksum recomputed,
    as a forger would."""
    arrays, meta = records.read(path)
    change(arrays, meta)
    environment = meta.pop("environment", None)
    records.save(path, arrays, meta, environment)


@pytest.fixture(scope="module")
def row(tmp_path_factory):
    return _row_copy(tmp_path_factory.mktemp("row"))


def test_the_committed_row_verifies_and_is_marked(row, capsys):
    code, out = _verify(row, capsys)
    assert code == 0, out
    assert "lgnn: verified: 3 records keyed on their checkpoints; 3 seed(s) rolled out again on chain4 from 1 initial condition(s)" in out
    kept = verify.load(row)
    assert kept["conditions"] == 1 and kept["scenes"] == "smallest"
    board = (row / "LEADERBOARD.md").read_text()
    assert "| yes (chain4) |" in board and "**Verified** by `lgnn leaderboard verify" in board


def test_a_forged_record_is_named(tmp_path, capsys):
    folder = _row_copy(tmp_path)

    def forge(arrays, meta):  # the first initial condition's rollout error halved, as a row would want
        arrays["rollout_error/per_ic_log"][0] -= np.log(2)

    _resave(folder / "benchmark" / "runs" / JOBS[1] / "chain4.npz", forge)
    code, out = _verify(folder, capsys)
    assert code == EXIT_CHECK_FAILED
    line = next(line for line in out.splitlines() if line.startswith("lgnn: failed:"))
    assert f"{JOBS[1]} on chain4: rollout_error of initial condition 0 is" in line and "in the record" in line and "rolled out again" in line
    assert "| failed |" in (folder / "LEADERBOARD.md").read_text()


def test_a_forged_checkpoint_is_named(tmp_path, capsys):
    folder = _row_copy(tmp_path)
    checkpoint = folder / "benchmark" / "checkpoints" / f"{JOBS[2]}.npz"

    def forge(arrays, meta):  # one parameter changed
        name = next(name for name in sorted(arrays) if name.startswith("best/"))
        arrays[name] = arrays[name] * 1.01

    _resave(checkpoint, forge)
    code, out = _verify(folder, capsys)
    assert code == EXIT_CHECK_FAILED
    assert f"lgnn: failed: {JOBS[2]} on chain4: its record" in out and "was not made from this checkpoint" in out

    # A forger who also gives the record the new checkpoint's key is found by the rollout.
    profile = _profile()
    pair = next(p for p in verify.rows_of(profile)["lgnn"] if p.job.name == JOBS[2])
    record = folder / "benchmark" / "runs" / JOBS[2] / "chain4.npz"
    _resave(record, lambda arrays, meta: meta.update(key=evaluate.pair_key(profile, pair, checkpoint)))
    code, out = _verify(folder, capsys)
    assert code == EXIT_CHECK_FAILED
    assert f"lgnn: failed: {JOBS[2]} on chain4: " in out and "in the record" in out and "rolled out again" in out


def test_a_damaged_record_and_a_missing_seed_are_named(tmp_path, capsys):
    folder = _row_copy(tmp_path)
    record = folder / "benchmark" / "runs" / JOBS[0] / "chain4.npz"
    data = bytearray(record.read_bytes())
    data[len(data) // 2] ^= 0xFF
    record.write_bytes(bytes(data))
    code, out = _verify(folder, capsys)
    assert code == EXIT_CHECK_FAILED and "lgnn: failed: " in out and str(record) in out
    (folder / "benchmark" / "checkpoints" / f"{JOBS[1]}.npz").unlink()
    code, out = _verify(folder, capsys)
    assert code == EXIT_CHECK_FAILED and f"lgnn: failed: {JOBS[1]}: no checkpoint at" in out


def test_a_forged_summary_is_named_and_a_changed_row_loses_its_mark(tmp_path, capsys):
    folder = _row_copy(tmp_path)
    profile = _profile()
    summary, _ = tables(evaluate.load_truths(profile, folder), evaluate.load_pairs(profile, folder), profile.evaluate.references)
    path = folder / "benchmark" / "summary.csv.gz"
    write_csv(summary, path)
    code, out = _verify(folder, capsys)
    assert code == 0 and f"(the folder): verified: {path}: its" in out

    # A record changed after the verification: the leaderboard no longer marks its row.
    _resave(folder / "benchmark" / "runs" / JOBS[0] / "chain4.npz", lambda arrays, meta: meta.update(key="0" * 64))
    main(["leaderboard", "--full", "--out-dir", str(folder), *ROW])
    assert "| no: records changed since |" in (folder / "LEADERBOARD.md").read_text()

    table = pd.read_csv(path)
    where = (table.model == "lgnn") & (table.metric == "rollout_error") & (table.statistic == "gmean") & (table.seed == -1)
    table.loc[where, "value"] *= 0.5
    path.write_bytes(gzip.compress(table.to_csv(index=False, float_format="%.6g").encode()))
    _resave(folder / "benchmark" / "runs" / JOBS[0] / "chain4.npz",
            lambda arrays, meta: meta.update(key=evaluate.pair_key(profile, verify.rows_of(profile)["lgnn"][0],
                                                                   folder / "benchmark" / "checkpoints" / f"{JOBS[0]}.npz")))
    code, out = _verify(folder, capsys)
    assert code == EXIT_CHECK_FAILED
    assert f"(the folder): failed: {path}: scene chain4, model lgnn, seed -1, metric rollout_error, statistic gmean is" in out


def test_verifying_one_row_keeps_the_others_findings(tmp_path, capsys):
    folder = _row_copy(tmp_path)
    kept = {"format": verify.FORMAT, "rows": [{"row": "other", "status": "verified", "detail": "", "digest": "d", "mark": "yes (x)"}]}
    (folder / "benchmark" / verify.VERIFICATION).write_text(json.dumps(kept))
    code, out = _verify(folder, capsys, "--row", "lgnn")
    assert code == 0 and out.startswith("lgnn: verified: ")
    assert [row["row"] for row in verify.load(folder)["rows"]] == ["other", "lgnn"]


def test_a_row_kept_without_parameters_is_unverified(tmp_path, capsys):
    from lgnn.learn import checkpoints

    folder = _row_copy(tmp_path)
    for job in JOBS:
        path = folder / "benchmark" / "checkpoints" / f"{job}.npz"
        checkpoints.without_parameters(path, path)
    code, out = _verify(folder, capsys)
    assert code == 0
    assert "lgnn: unverified: the checkpoints of lgnn-chain4-s0, lgnn-chain4-s1, lgnn-chain4-s2 are kept without their parameters" in out
    assert "| no: parameters not kept |" in (folder / "LEADERBOARD.md").read_text()


def test_verify_refuses_what_it_cannot_read(tmp_path, capsys):
    assert main(["leaderboard", "verify", str(tmp_path / "absent")]) == 2
    assert "results folder" in capsys.readouterr().err
    assert main(["leaderboard", "--initial-conditions", "2"]) == 2
    assert "--initial-conditions is an option of lgnn leaderboard verify" in capsys.readouterr().err


def test_the_committed_verification_is_of_the_committed_records():
    """The committed `verification.json` names every row of the committed grid and its
    records as they are: changing a record without verifying again fails here (the
    leaderboard would mark the row "no: records changed since")."""
    profile = benchmark_profile("full")
    kept, marks = verify.marks(profile, RESULTS)
    assert kept is not None and set(marks) == set(verify.rows_of(profile)), set(verify.rows_of(profile)) ^ set(marks)
    assert all(mark.startswith("yes") or mark == "no: parameters not kept" for mark in marks.values()), marks
    board = (RESULTS / "LEADERBOARD.md").read_text()
    assert "| yes (" in board and "| no: records changed since |" not in board and "| not checked |" not in board
