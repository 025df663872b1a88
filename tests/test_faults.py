"""Faults injected into a real benchmark run (a small grid of the quick profile: GNS on
chain4, projected and unprojected, one seed), nothing lost and nothing done twice:

- stopped inside the training stage by Ctrl-C once its first checkpoint is written, then
  resumed stage by stage (every stage boundary a stop), the run ends with the numbers
  of an undisturbed run;
- the disk filling during a write (`RLIMIT_FSIZE`): the run stops in one line, leaves
  no partial file, and resumes to the same numbers;
- the dataset cache damaged (a byte flipped, a file truncated): detected by its
  checksum, regenerated, never used.

A killed Ray worker is tests/test_ray_executor.py's. The runs are other processes than
the undisturbed one: the same numbers to round-off (tolerances as there), not bit for bit.
"""

import os
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from lgnn import records
from lgnn.bench import profiles
from lgnn.bench.stages import evaluate
from lgnn.learn import data, train

# Enough epochs (about 0.1 s each after compiling) that a Ctrl-C lands between checkpoints.
EPOCHS = 200
SETTINGS = ['models=["gns"]', 'scenes=["chain4"]', f"training.train.epochs={EPOCHS}", "training.train.patience=100000",
            "training.train.checkpoint_every=10", "training.data.n_trajectories=4", "training.data.duration=0.1",
            "training.data.sample_dt=0.02", "training.data.dt=1e-3", 'stages=["train","truth","evaluate","report"]']
ARGV = [arg for setting in SETTINGS for arg in ("--set", setting)]
PARAMS_RTOL, PARAMS_ATOL = 1e-9, 1e-12
RECORD_RTOL, RECORD_ATOL = 1e-9, 1e-13
SUMMARY_RTOL = 2e-5
TIMEOUT_S = 600


def _env(cache: Path) -> dict:
    return {**os.environ, "LGNN_CACHE": str(cache), "LGNN_JAX_CACHE": "off"}


def _benchmark(out: Path, cache: Path, *extra, limit_kib: int | None = None) -> subprocess.Popen:
    """`lgnn benchmark` of the small grid into `out`; `limit_kib`: no file it writes may
    grow past that many KiB (the shell's `ulimit -f`, RLIMIT_FSIZE, set before Python
    starts: Python ignores SIGXFSZ, so a write past it fails with EFBIG)."""
    command = [sys.executable, "-m", "lgnn", "benchmark", *ARGV, "--out-dir", str(out), "--quiet", *extra]
    if limit_kib is not None:
        command = ["sh", "-c", f'ulimit -f {limit_kib} && exec "$0" "$@"', *command]
    return subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=_env(cache))


def _finished(child: subprocess.Popen) -> tuple[int, str]:
    err = child.communicate(timeout=TIMEOUT_S)[1]
    return child.returncode, err


@pytest.fixture(scope="module")
def undisturbed(tmp_path_factory):
    root = tmp_path_factory.mktemp("undisturbed")
    code, err = _finished(_benchmark(root / "out", root / "cache"))
    assert code == 0, err
    return root / "out"


def _same_numbers(ours: Path, theirs: Path) -> None:
    """The run in `ours` holds the numbers of `theirs`: checkpoints' best parameters,
    every pair record's arrays, the summary."""
    profile = profiles.load_profile("quick", SETTINGS)
    for job in profiles.training_jobs(profile):
        name = f"benchmark/checkpoints/{job.name}.npz"
        (mine, _), (other, _) = train.load_checkpoint(ours / name), train.load_checkpoint(theirs / name)
        assert mine.epoch == other.epoch == EPOCHS and mine.best_epoch == other.best_epoch
        best = [{k: v for k, v in records.read(folder / name)[0].items() if k.startswith("best/")} for folder in (ours, theirs)]
        assert best[0].keys() == best[1].keys()
        for key in best[0]:
            np.testing.assert_allclose(best[0][key], best[1][key], rtol=PARAMS_RTOL, atol=PARAMS_ATOL, err_msg=key)
    for pair in profiles.evaluation_pairs(profile):
        mine, other = evaluate.load_pair(profile, pair, ours), evaluate.load_pair(profile, pair, theirs)
        assert mine is not None and other is not None, pair
        for key in evaluate.pair_needs(profile):
            np.testing.assert_allclose(np.exp(mine[0][key]), np.exp(other[0][key]), rtol=RECORD_RTOL, atol=RECORD_ATOL, err_msg=f"{pair} {key}")
    index = ["scene", "model", "seed", "metric", "statistic"]
    mine, other = (pd.read_csv(folder / "benchmark" / "summary.csv.gz").set_index(index)["value"].sort_index() for folder in (ours, theirs))
    assert mine.index.equals(other.index)
    np.testing.assert_allclose(mine.to_numpy(), other.to_numpy(), rtol=SUMMARY_RTOL, equal_nan=True)
    assert not list(ours.rglob("*.claim*")) and not list(ours.rglob("*.tmp*"))


def _interrupted_once_checkpointed(out: Path, cache: Path) -> int:
    """Start the run and interrupt it (Ctrl-C) once its first checkpoint is whole; the
    epoch that checkpoint holds."""
    checkpoint = out / "benchmark" / "checkpoints" / "gns-chain4-s0.npz"
    child = _benchmark(out, cache)
    deadline = time.monotonic() + TIMEOUT_S
    while not checkpoint.exists() and child.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    child.send_signal(signal.SIGINT)
    code, err = _finished(child)
    assert code == 130 and err.strip().endswith("lgnn: interrupted"), (code, err)
    state, _ = train.load_checkpoint(checkpoint)
    return state.epoch


def test_a_run_stopped_inside_training_and_at_every_stage_boundary_resumes_to_the_same_numbers(undisturbed, tmp_path):
    out, cache = tmp_path / "out", tmp_path / "cache"
    epoch = _interrupted_once_checkpointed(out, cache)
    assert 10 <= epoch < EPOCHS, epoch  # stopped between checkpoints, not at the end
    for stage in ("train", "truth", "evaluate", "report"):
        code, err = _finished(_benchmark(out, cache, "--stage", stage))
        assert code == 0, (stage, err)
        if stage == "train":
            assert f"resuming at epoch {epoch}" in err, err
    _same_numbers(out, undisturbed)


def test_a_full_disk_stops_the_run_in_one_line_and_it_resumes_to_the_same_numbers(undisturbed, tmp_path):
    out, cache = tmp_path / "out", tmp_path / "cache"
    # Past the dataset cache's and the first records' sizes, short of a checkpoint's.
    code, err = _finished(_benchmark(out, cache, limit_kib=96))
    lines = [line for line in err.strip().splitlines() if not line.startswith("[benchmark]")]
    assert code == 2 and len(lines) == 1 and lines[0].startswith("lgnn: error: cannot write ") and "File too large" in lines[0], err
    assert "benchmark/checkpoints/gns-chain4-s0.npz" in lines[0], err  # the first checkpoint, inside the training stage
    assert "Traceback" not in err
    assert not [path for path in out.rglob("*") if ".tmp" in path.name]
    assert not [path for path in cache.rglob("*") if ".tmp" in path.name]
    code, err = _finished(_benchmark(out, cache))
    assert code == 0, err
    _same_numbers(out, undisturbed)


@pytest.mark.parametrize("damage", ["flipped", "truncated"])
def test_a_damaged_dataset_cache_is_detected_and_regenerated(tmp_path, damage, capsys):
    config = data.DataConfig(n_trajectories=2, duration=0.04, sample_dt=0.01, dt=1e-3)
    first = data.load_or_generate(config, tmp_path)
    path = data.cache_path(config, tmp_path)
    raw = bytearray(path.read_bytes())
    if damage == "flipped":  # one bit of the largest array's data, past its zip and .npy headers
        with zipfile.ZipFile(path) as archive:
            member = max(archive.infolist(), key=lambda info: info.file_size)
        start = member.header_offset + 30 + len(member.filename.encode()) + len(member.extra)
        raw[start + 128 + member.file_size // 2 - 64] ^= 0x01
    else:
        raw = raw[: len(raw) // 2]
    path.write_bytes(bytes(raw))
    again = data.load_or_generate(config, tmp_path)
    err = capsys.readouterr().err
    # A flipped bit fails the member's zip CRC before the record's checksum is reached.
    assert "not a readable lgnn data cache" in err and "regenerating" in err, err
    np.testing.assert_array_equal(again.q, first.q)
    data.load(config, path)  # the regenerated file is whole
