"""Work claimed once (`lgnn.bench.claims`): processes racing for one record compute it
once, a stale claim is taken over, and a claimant killed mid-work leaves no record,
only a claim the next process takes over."""

import json
import os
import socket
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np

from lgnn.bench import claims, run_record, store

# A process computing three records through `claims.each_once`: each computation is
# logged (one line appended to `done.log`: pid and item), takes a second, and writes
# its record through the store (atomically). `KILL_BEFORE_RENAME` set: the process
# kills itself (SIGKILL) just before its first record's rename, mid-write.
WORKER = textwrap.dedent("""
    import os, signal, sys, time
    from pathlib import Path
    import numpy as np
    from lgnn import files
    from lgnn.bench import claims, store

    root = Path(sys.argv[1])
    if os.environ.get("KILL_BEFORE_RENAME"):
        os.replace = lambda *args: os.kill(os.getpid(), signal.SIGKILL)

    def compute(items):
        for item in items:
            path = root / f"{item}.npz"
            if store.load(path, "k") is not None:
                continue  # written by the process that held it
            with open(root / "done.log", "a") as log:
                log.write(f"{os.getpid()} {item}\\n")
            time.sleep(1.0)
            store.save(path, "k", {"x": np.arange(1000.0)}, {"item": item})

    (root / f"ready-{os.getpid()}").touch()
    while not (root / "go").exists():
        time.sleep(0.01)
    claims.each_once(["a", "b", "c"], lambda item: root / f"{item}.npz", compute, "test")
""")


def _workers(root: Path, n: int, **env) -> list[subprocess.Popen]:
    """`n` processes running WORKER on `root`, released together once all are ready."""
    repo = Path(__file__).resolve().parents[1]
    environment = {**os.environ, "PYTHONPATH": str(repo), **env}
    processes = [subprocess.Popen([sys.executable, "-c", WORKER, str(root)], env=environment, stderr=subprocess.PIPE, text=True)
                 for _ in range(n)]
    deadline = time.monotonic() + 120
    while len(list(root.glob("ready-*"))) < n and time.monotonic() < deadline:
        time.sleep(0.05)
    (root / "go").touch()
    return processes


def test_processes_racing_for_the_same_records_compute_each_once(tmp_path):
    """Three processes released at once on the same three records: each record is
    computed by exactly one of them, every record is whole and no claim is left."""
    processes = _workers(tmp_path, 3)
    for process in processes:
        assert process.wait(timeout=120) == 0, process.stderr.read()
    done = [line.split()[1] for line in (tmp_path / "done.log").read_text().splitlines()]
    assert sorted(done) == ["a", "b", "c"]
    for item in "abc":
        arrays, meta = store.load(tmp_path / f"{item}.npz", "k")
        assert meta["item"] == item and np.array_equal(arrays["x"], np.arange(1000.0))
    assert not list(tmp_path.glob("*.claim*"))


def test_a_crash_mid_write_leaves_no_record_and_its_claim_is_taken_over(tmp_path):
    """A process killed (SIGKILL) while writing its first record leaves no record at
    that path (the write is atomic) and a claim naming its dead pid; the next process
    takes the claim over and computes every record, each whole."""
    crashed, = _workers(tmp_path, 1, KILL_BEFORE_RENAME="1")
    assert crashed.wait(timeout=120) == -9
    first = (tmp_path / "done.log").read_text().split()[1]
    assert not (tmp_path / f"{first}.npz").exists()
    left = json.loads(claims.claim_path(tmp_path / f"{first}.npz").read_text())
    assert left["pid"] == crashed.pid
    (tmp_path / "go").unlink()
    survivor, = _workers(tmp_path, 1)
    assert survivor.wait(timeout=120) == 0, survivor.stderr.read()
    assert "taking over the stale claim" in survivor.stderr.read()
    for item in "abc":
        assert store.load(tmp_path / f"{item}.npz", "k")[1]["item"] == item
    assert not list(tmp_path.glob("*.claim*"))


def _write_claim(record: Path, **content) -> None:
    claims.claim_path(record).write_text(json.dumps({"host": socket.gethostname(), "pid": os.getpid(), "started": time.time(),
                                                     "heartbeat": time.time(), "token": "theirs", **content}))


def test_a_live_claim_is_left_alone_a_stale_one_taken_over(tmp_path):
    """A claim with a fresh heartbeat of a live process (this one, another thread) is
    left to it; one whose heartbeat is older than the timeout (another host, silent),
    or whose pid is dead on this host, is taken over: the new claim is this process's."""
    record = tmp_path / "r.npz"
    _write_claim(record)
    assert claims.claim(record) is None
    assert claims.holder(record)["token"] == "theirs"

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    for stale in (dict(host="elsewhere", pid=1, heartbeat=time.time() - 600), dict(pid=dead.pid)):
        _write_claim(record, **stale)
        with claims.held(record, stale_after=300) as mine:
            assert mine and claims.holder(record)["pid"] == os.getpid() and claims.holder(record)["token"] != "theirs"
        assert not claims.claim_path(record).exists()


def test_threads_taking_over_one_stale_claim_end_with_one_holder(tmp_path):
    """Eight threads find one stale claim at once: exactly one of them holds the record."""
    record = tmp_path / "r.npz"
    _write_claim(record, host="elsewhere", heartbeat=time.time() - 600)
    barrier, held = threading.Barrier(8), []

    def contend():
        barrier.wait()
        found = claims.claim(record, stale_after=300)
        if found is not None:
            held.append(found)

    threads = [threading.Thread(target=contend) for _ in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert len(held) == 1 and held[0].held()
    held[0].release()
    assert not list(tmp_path.iterdir())


def test_a_heartbeat_keeps_a_long_claim_live(tmp_path, monkeypatch):
    """The claimant's heartbeat is rewritten while it works, so a claim older than the
    timeout stays live as long as its claimant beats."""
    monkeypatch.setattr(claims, "HEARTBEAT_S", 0.05)
    record = tmp_path / "r.npz"
    mine = claims.claim(record)
    try:
        first = claims.holder(record)["heartbeat"]
        time.sleep(0.5)
        assert claims.holder(record)["heartbeat"] > first
        assert claims.claim(record, stale_after=0.3) is None
    finally:
        mine.release()


def test_two_benchmark_processes_on_one_folder_run_each_task_once(tmp_path, tiny_benchmark_config):
    """Two `lgnn benchmark` processes started at once on one output folder (the local
    executor): the training job, the ground truth and each evaluation are computed by
    one of them (their logs say so once between them), both exit 0, and no claim is
    left."""
    config, out = tiny_benchmark_config("gns", epochs=2), tmp_path / "out"
    command = [sys.executable, "-m", "lgnn", "benchmark", "--config", str(config), "--out-dir", str(out), "--quiet"]
    processes = [subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    logs = [process.communicate(timeout=600)[1] for process in processes]
    assert [process.returncode for process in processes] == [0, 0], logs
    both = "".join(logs)
    assert both.count("train gns-chain4-s0: 2 epochs in") == 1, both
    assert both.count("ground truth chain4:") == 1, both
    assert both.count("evaluate gns s0 on chain4: rollout error") == 1, both
    assert not list(out.rglob("*.claim*"))
    # Each says what it cost in the run record, neither losing the other's entry.
    record = run_record.read(out)
    assert [i["outcome"] for i in record["invocations"]] == ["completed", "completed"]
