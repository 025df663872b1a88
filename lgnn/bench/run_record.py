"""`OUT/benchmark/run.json`: what a benchmark run of `OUT` cost, and where it ran.

A run resumes across invocations (a preemptible job of minutes, a killed process, a
second machine), so the record is a list of invocations, one entry each, appended when
the invocation ends (also when it fails or is interrupted, marked so): its command,
commit, versions, device, start and end (UTC, ISO 8601), wall seconds and each stage's
wall seconds. The top level sums them: `wall_s` and `stages` over every invocation,
`started` the first's start, `ended` the last's end, and `commit`, `versions` and
`device` the one value every invocation shares, else `"mixed: A; B"`, so a run that
changed machine or tree part-way says so at the top. Child processes of a split run
(`lgnn.runtime.BENCHMARK_CHILD`) write nothing: their parent's invocation times them.
Invocations that end at once on one folder each append theirs (a lock on the folder).
"""

from __future__ import annotations

import contextlib
import datetime
import json
import os
import time
from pathlib import Path
from typing import Callable, Iterator

from lgnn import provenance
from lgnn.files import write_text_atomic
from lgnn.runtime import BENCHMARK_CHILD

RUN_RECORD = "run.json"
FORMAT = 1


def path(out: Path) -> Path:
    return Path(out) / "benchmark" / RUN_RECORD


def _now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def _shared(values: list[str]) -> str:
    distinct = list(dict.fromkeys(values))
    return distinct[0] if len(distinct) == 1 else "mixed: " + "; ".join(distinct)


def read(out: Path) -> dict | None:
    """The run record of `out`, or None where there is none or it is unreadable."""
    try:
        record = json.loads(path(out).read_text())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) and record.get("format") == FORMAT else None


def _summary(invocations: list[dict]) -> dict:
    stages: dict[str, float] = {}
    for invocation in invocations:
        for name, seconds in invocation["stages"].items():
            stages[name] = round(stages.get(name, 0.0) + seconds, 3)
    return {
        "format": FORMAT,
        "commit": _shared([i["commit"] for i in invocations]),
        "versions": _shared([i["versions"] for i in invocations]),
        "device": _shared([i["device"] for i in invocations]),
        "started": invocations[0]["started"],
        "ended": invocations[-1]["ended"],
        "wall_s": round(sum(i["wall_s"] for i in invocations), 3),
        "stages": stages,
        "invocations": invocations,
    }


@contextlib.contextmanager
def recording(out: Path, command: str | None) -> Iterator[Callable[[str], contextlib.AbstractContextManager]]:
    """For one invocation of `run`: yields `stage(name)`, a context that times one
    stage; on leaving, this invocation is appended to `out`'s run record (atomically,
    with `outcome` "completed", "failed" or "interrupted")."""
    if os.environ.get(BENCHMARK_CHILD) == "1":
        yield lambda name: contextlib.nullcontext()
        return
    started, start = _now(), time.perf_counter()
    stages: dict[str, float] = {}

    @contextlib.contextmanager
    def stage(name: str) -> Iterator[None]:
        begin = time.perf_counter()
        try:
            yield
        finally:
            stages[name] = round(stages.get(name, 0.0) + time.perf_counter() - begin, 3)

    outcome = "failed"
    try:
        yield stage
        outcome = "completed"
    except KeyboardInterrupt:
        outcome = "interrupted"
        raise
    finally:
        invocation = {"command": command, "outcome": outcome, "commit": provenance.commit(), "versions": provenance.versions(),
                      "device": provenance.device(), "started": started, "ended": _now(),
                      "wall_s": round(time.perf_counter() - start, 3), "stages": stages}
        path(out).parent.mkdir(parents=True, exist_ok=True)
        with _locked(path(out).parent):  # two invocations on one folder at once each append theirs
            earlier = (read(out) or {}).get("invocations", [])
            write_text_atomic(path(out), json.dumps(_summary([*earlier, invocation]), indent=1) + "\n")


@contextlib.contextmanager
def _locked(folder: Path) -> Iterator[None]:
    """An exclusive lock on `folder` itself (no lock file left behind), where the system
    has `flock`."""
    try:
        import fcntl
    except ImportError:  # not POSIX: no lock
        yield
        return
    descriptor = os.open(folder, os.O_RDONLY)
    try:
        fcntl.flock(descriptor, fcntl.LOCK_EX)
        yield
    finally:
        os.close(descriptor)
