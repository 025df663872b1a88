"""`lgnn benchmark --executor ray` (`lgnn.bench.ray_executor`) on a local Ray cluster of
2 CPUs: two drivers sharing an output folder compute each part once, and their records
and `summary.csv.gz` are the local executor's; a task whose worker is killed mid-training
is retried and its checkpoint is whole. A reduced selection (one model, one seed, one
scene, one epoch) keeps it near a minute per run on 2 cores."""

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

ray = pytest.importorskip("ray")

from lgnn.bench import claims, profiles  # noqa: E402

from lgnn.bench.report import summary as report_summary
from lgnn.bench.stages import evaluate  # noqa: E402
from lgnn.cli import main  # noqa: E402
from lgnn.learn import train  # noqa: E402

# One model (GNS: projected and unprojected pairs), one seed, chain4 only, one epoch of
# 15 states: what costs is each child's imports and compiles.
PROFILE_ARGV = ["--set", 'models=["gns"]', "--set", 'scenes=["chain4"]', "--set", "training.train.epochs=1",
                "--set", "training.data.n_trajectories=4", "--set", "training.data.duration=0.1", "--set", "training.data.sample_dt=0.02",
                "--set", "training.data.dt=1e-3"]
STAGES = ["--set", 'stages=["train","evaluate","report"]']
# The drivers' stages: the ground truths too, queued behind the training groups (`lgnn.bench.run._train`).
SPLIT_STAGES = ["--set", 'stages=["train","truth","evaluate","report"]']
TIMINGS = {"compile_s", "run_s", "steps_per_s", "mujoco_s", "elapsed_s"}
# The drivers' tasks and the local run are other processes: the same numbers to
# round-off, not bit for bit. Parameters: one epoch of Adam (as tests/test_models.py's
# packed seeds). Records: errors (relative, or node distances in m) of 0.1 s rollouts
# move by about the trajectories' own round-off, ~1e-15, absolute (1e-13), which is
# under 1e-9 relative for every error above round-off (>= 5e-5 here); a per-IC mean
# log error is compared as the error it is the log of (an error at round-off, 1e-14,
# may have any log). The summary keeps 6 significant digits: values a round-off apart
# may round a unit of the 6th apart (2e-5 relative).
PARAMS_RTOL, PARAMS_ATOL = 1e-9, 1e-12
RECORD_RTOL, RECORD_ATOL = 1e-9, 1e-13
SUMMARY_RTOL = 2e-5


@pytest.fixture(scope="module")
def cluster():
    """A Ray of 2 CPUs started for this file's tests (no dashboard) and stopped after
    them (the killed worker's test runs last); its address."""
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        yield ray.get_runtime_context().gcs_address
    finally:
        ray.shutdown()


def _profile():
    return profiles.load_profile("quick", PROFILE_ARGV[1::2])


def _driver(out: Path, address: str, cache: Path) -> subprocess.Popen:
    """A driver process whose dataset cache (`$LGNN_CACHE`, which its tasks use too) is `cache`."""
    return subprocess.Popen([sys.executable, "-m", "lgnn", "benchmark", *PROFILE_ARGV, *SPLIT_STAGES, "--executor", "ray", "--address", address,
                             "--workers", "2", "--out-dir", str(out), "--quiet"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "LGNN_CACHE": str(cache)})


@pytest.fixture(scope="module")
def local(tmp_path_factory):
    """The undisturbed run of the local executor, the reference of every Ray run here."""
    out = tmp_path_factory.mktemp("local") / "out"
    assert main(["benchmark", *PROFILE_ARGV, *STAGES, "--out-dir", str(out), "--quiet"]) == 0
    return out


def _same_summary(ours: Path, theirs: Path) -> None:
    """Two runs' `summary.csv.gz`: every column but the values equal, the values to round-off."""
    summaries = [pd.read_csv(out / "benchmark" / report_summary.SUMMARY, keep_default_na=False) for out in (ours, theirs)]
    assert list(summaries[0].columns) == list(summaries[1].columns) and len(summaries[0]) == len(summaries[1])
    for column in summaries[0].columns:
        if column != "value":
            assert summaries[0][column].tolist() == summaries[1][column].tolist(), column
    values = [pd.to_numeric(summary["value"], errors="coerce").to_numpy() for summary in summaries]
    np.testing.assert_allclose(values[0], values[1], rtol=SUMMARY_RTOL, atol=RECORD_ATOL, equal_nan=True)


def test_two_ray_drivers_on_one_folder_compute_each_part_once_as_the_local_executor_does(cluster, local, tmp_path, capsys):
    """Two drivers started at once on one output folder: each training job, model
    evaluation and ground truth is computed by one of them (the other's task waits for
    its claim, then reads the record), the ground truth by a truth task queued behind
    training; the records' arrays, the checkpoint's parameters and `summary.csv.gz` are
    the local executor's to round-off, their settings, counts and the truth's key
    exactly (timings apart; locally the evaluate stage computed the ground truth); the
    tasks use the drivers' dataset cache; no claim is left."""
    shared, cache = tmp_path / "ray", tmp_path / "drivers-cache"
    # The drivers' own cache: they compute the ground truth again, rather than read the local run's.
    drivers = [_driver(shared, cluster, cache) for _ in range(2)]
    for driver in drivers:
        assert driver.wait(timeout=600) == 0, driver.stderr.read()
    logs = shared / "benchmark" / "logs"
    train_log = (logs / "train-gns-chain4.log").read_text()
    evaluate_log = (logs / "evaluate-chain4-gns-chain4.log").read_text()
    truth_log = (logs / "truth-chain4.log").read_text()
    assert train_log.count("# lgnn benchmark") == 2 and evaluate_log.count("# lgnn benchmark") == 2  # a task of each driver
    assert train_log.count("train gns-chain4-s0: 1 epochs in") == 1
    assert evaluate_log.count("evaluate gns s0 on chain4: rollout error") == 1
    assert evaluate_log.count("evaluate gns (unprojected) s0 on chain4: rollout error") == 1
    assert truth_log.count("ground truth chain4: 3 initial conditions") == 1 and "ground truth chain4: 3 initial" not in evaluate_log
    assert len(list((cache / "datasets" / "ground-truth").glob("chain4-*.npz"))) == 1
    assert not list(shared.rglob("*.claim*")) and not list(cache.rglob("*.claim*"))

    _same_summary(shared, local)
    profile = _profile()
    # Each folder's records load under the key of its own checkpoint (`load_pairs`); the
    # keys hash the parameters, which two processes need not train bit for bit.
    ours, theirs = dict(evaluate.load_pairs(profile, shared)), dict(evaluate.load_pairs(profile, local))
    assert len(ours) == len(theirs) == 2
    for pair, (arrays, meta) in ours.items():
        _assert_same(arrays, meta, *theirs[pair], ignore=TIMINGS | {"folder", "key"})
    _assert_same(*evaluate.load_truth(profile, "chain4", shared), *evaluate.load_truth(profile, "chain4", local), ignore=TIMINGS | {"folder"})
    (state, meta), (reference, reference_meta) = (train.load_checkpoint(out / "benchmark" / "checkpoints" / "gns-chain4-s0.npz") for out in (shared, local))
    for ours_leaf, theirs_leaf in zip(*(train.jax.tree.leaves(s.params) for s in (state, reference))):
        np.testing.assert_allclose(ours_leaf, theirs_leaf, rtol=PARAMS_RTOL, atol=PARAMS_ATOL)
    _assert_close_meta({k: v for k, v in meta.items() if k not in TIMINGS}, {k: v for k, v in reference_meta.items() if k not in TIMINGS}, PARAMS_RTOL)


def _assert_same(arrays, meta, reference_arrays, reference_meta, ignore):
    assert sorted(arrays) == sorted(reference_arrays)
    for name in arrays:
        ours, theirs = np.asarray(arrays[name]), np.asarray(reference_arrays[name])
        if ours.dtype.kind != "f":
            np.testing.assert_array_equal(ours, theirs, err_msg=name)
            continue
        if name.endswith("/per_ic_log"):
            ours, theirs = np.exp(ours), np.exp(theirs)
        np.testing.assert_allclose(ours, theirs, rtol=RECORD_RTOL, atol=RECORD_ATOL, equal_nan=True, err_msg=name)
    _assert_close_meta({k: v for k, v in meta.items() if k not in ignore}, {k: v for k, v in reference_meta.items() if k not in ignore}, RECORD_RTOL)


def _assert_close_meta(ours, theirs, rtol, path="meta"):
    """Metadata equal but for its floats (a loss, a settings' value), which agree to `rtol`."""
    if isinstance(ours, dict) and isinstance(theirs, dict):
        assert sorted(ours) == sorted(theirs), path
        for key in ours:
            _assert_close_meta(ours[key], theirs[key], rtol, f"{path}[{key!r}]")
    elif isinstance(ours, (list, tuple)) and isinstance(theirs, (list, tuple)):
        assert len(ours) == len(theirs), path
        for k, (a, b) in enumerate(zip(ours, theirs)):
            _assert_close_meta(a, b, rtol, f"{path}[{k}]")
    elif isinstance(ours, float) or isinstance(theirs, float):
        assert ours == pytest.approx(theirs, rel=rtol, nan_ok=True), path
    else:
        assert ours == theirs, path


def test_a_training_task_whose_worker_is_killed_is_retried_and_its_checkpoint_is_whole(cluster, local, tmp_path, capsys):
    """The Ray worker running the training task is killed (SIGKILL) once the child has
    claimed its job: the child stops with it (its claim released), Ray runs the task
    again, the run completes with one whole, finished checkpoint and no claim left, and
    its summary is the undisturbed local run's."""
    out = tmp_path / "out"
    checkpoint = out / "benchmark" / "checkpoints" / "gns-chain4-s0.npz"
    killed = []

    def kill_the_worker():
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            holder = claims.holder(checkpoint)
            if holder is not None:
                worker = int(Path(f"/proc/{holder['pid']}/stat").read_text().rsplit(")", 1)[1].split()[1])  # its parent
                os.kill(worker, 9)
                killed.append(worker)
                return
            time.sleep(0.05)

    killer = threading.Thread(target=kill_the_worker)
    killer.start()
    try:
        code = main(["benchmark", *PROFILE_ARGV, *STAGES, "--executor", "ray", "--out-dir", str(out), "--quiet"])
    finally:
        killer.join()
    assert code == 0, capsys.readouterr().err
    assert killed
    log = (out / "benchmark" / "logs" / "train-gns-chain4.log").read_text()
    assert log.count("# lgnn benchmark") == 2, log  # the task, then its retry
    state, _ = train.load_checkpoint(checkpoint)
    assert state.epoch == 1
    assert not list(out.rglob("*.claim*")) and not list(out.rglob("*.tmp*"))
    _same_summary(out, local)
