"""Work claimed once: a claim file beside a record says which process is computing it.

Before a process computes a record (a training job's checkpoint, an evaluation pair's
record, a scene's ground truth), it creates `<record>.claim` with O_CREAT | O_EXCL:
of several processes, on one machine or several sharing the folder, exactly one
creates it (also on NFS v3 and later, where fcntl locks are unreliable or absent).
The claim holds the claimant's host, pid, start time and a heartbeat timestamp that a
thread of the claimant rewrites every `HEARTBEAT_S` while it works. Another process
finding the claim leaves the record to it, unless the claim is stale: its heartbeat
older than `STALE_AFTER_S` (the claimant's machine died or it froze), or its pid dead on
this same host. A stale claim is taken over: removed by one taker at a time (a lock file
beside it), then created afresh with O_EXCL, which one process wins. The claim is removed when
its block ends, the record written (atomically: `lgnn.records`) or the work failed.

`claim(path)` tries once; `once(path)` waits while a live claim elsewhere holds the
record, then holds it (one process computes a shared record, the others then read it);
`each_once(items, path_of, compute)` computes a stage's parts, each claimed, waiting
for those held elsewhere and taking up any whose claimant failed.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import threading
import time
import uuid
from pathlib import Path
from typing import Callable, Iterator, TypeVar

from lgnn.bench.store import log

SUFFIX = ".claim"
# A claimant rewrites its heartbeat this often while it works.
HEARTBEAT_S = 10.0
# A claim whose heartbeat is older than this is stale: 18 missed heartbeats, and room
# for the clocks of a cluster's nodes to disagree (heartbeats are wall-clock times).
STALE_AFTER_S = 180.0
# A takeover lock (`_take_over`) older than this was left by a taker that died.
TAKEOVER_LOCK_S = 30.0
TAKEOVER_SUFFIX = ".takeover"
# How often a process waiting for a claim held elsewhere looks again.
POLL_S = 2.0
# The claim's content is padded to this size, so a heartbeat rewrites it in place
# (one write at offset 0) without truncating it first.
CLAIM_BYTES = 256

Item = TypeVar("Item")


def claim_path(record: Path) -> Path:
    """The claim file of the record at `record`."""
    record = Path(record)
    return record.with_name(record.name + SUFFIX)


class Claim:
    """A claim this process holds on one record: its heartbeat runs until `release`."""

    def __init__(self, path: Path, fd: int, content: dict):
        self.path, self._fd, self.content = path, fd, content
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._beat, name=f"claim {path.name}", daemon=True)
        self._thread.start()

    def _beat(self) -> None:
        while not self._stop.wait(HEARTBEAT_S):
            if not self.held():
                log(f"warning: the claim {self.path} was taken over by another process (this one was silent for over "
                    f"{STALE_AFTER_S:g} s); finishing anyway, the record is written atomically")
                return
            with contextlib.suppress(OSError):
                os.pwrite(self._fd, _encoded({**self.content, "heartbeat": time.time()}), 0)

    def held(self) -> bool:
        """Whether the claim file is still the one this process created."""
        try:
            return os.stat(self.path).st_ino == os.fstat(self._fd).st_ino
        except OSError:
            return False

    def release(self) -> None:
        """Stop the heartbeat and remove the claim file (unless another process took it over)."""
        self._stop.set()
        self._thread.join()
        if self.held():
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.path)
        os.close(self._fd)


def claim(record: Path, stale_after: float = STALE_AFTER_S) -> Claim | None:
    """A claim on `record` for this process, or None while a live claim of another
    process (or thread) holds it. A stale claim is taken over."""
    path = claim_path(record)
    path.parent.mkdir(parents=True, exist_ok=True)
    content = {"host": socket.gethostname(), "pid": os.getpid(), "started": time.time(), "token": uuid.uuid4().hex}
    while True:
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            seen = _inspect(path)
            if seen is None:
                continue  # released meanwhile: try again
            if not _stale(*seen, stale_after):
                return None
            if _take_over(path, seen, stale_after):
                log(f"taking over the stale claim {path} ({describe(seen[0])})")
            continue
        os.write(fd, _encoded({**content, "heartbeat": time.time()}))
        return Claim(path, fd, content)


def holder(record: Path) -> dict | None:
    """The content of the claim on `record` (None: no claim, or one still being written)."""
    seen = _inspect(claim_path(record))
    return None if seen is None else seen[0]


def describe(content: dict | None) -> str:
    """A claim's claimant in words: `host pid N since HH:MM:SS`."""
    if not content:
        return "a claim being written"
    return f"{content.get('host')} pid {content.get('pid')} since {time.strftime('%H:%M:%S', time.localtime(content.get('started', 0)))}"


@contextlib.contextmanager
def held(record: Path, stale_after: float = STALE_AFTER_S) -> Iterator[bool]:
    """True for the block if this process claimed `record` (released when the block
    ends, however it ends), False if a live claim elsewhere holds it."""
    mine = claim(record, stale_after)
    try:
        yield mine is not None
    finally:
        if mine is not None:
            mine.release()


@contextlib.contextmanager
def once(record: Path, stale_after: float = STALE_AFTER_S) -> Iterator[None]:
    """Hold the claim on `record` for the block, first waiting while a live claim
    elsewhere holds it: processes that need one shared record compute it once (the
    first) and read it (the others, who check for it inside the block)."""
    mine = _claimed_when_free(record, stale_after)
    try:
        yield
    finally:
        mine.release()


def each_once(items: list[Item], path_of: Callable[[Item], Path], compute: Callable[[list[Item]], None], what: str,
              stale_after: float = STALE_AFTER_S) -> None:
    """`compute(claimed)` on the `items` whose records (`path_of(item)`) this process
    claims, their claims released afterwards (the records written, or `compute`
    failed); then, for the items claimed elsewhere, wait until their claims end and
    do the same with them: a claimant that finished leaves a whole record (which
    `compute` finds and reuses), one that failed none (computed here). `compute` itself
    skips records already whole. `what` names the items in the log."""
    pending = list(items)
    while pending:
        mine, elsewhere = [], []
        for item in pending:
            found = claim(path_of(item), stale_after)
            (mine if found is not None else elsewhere).append((item, found))
        try:
            if mine:
                compute([item for item, _ in mine])
        finally:
            for _, found in mine:
                found.release()
        for item, _ in elsewhere:
            path = path_of(item)
            log(f"{what} {path.name}: being computed by {describe(holder(path))}; waiting for it")
            _wait_until_free(path, stale_after)
        pending = [item for item, _ in elsewhere]


def _claimed_when_free(record: Path, stale_after: float) -> Claim:
    said = False
    while True:
        mine = claim(record, stale_after)
        if mine is not None:
            return mine
        if not said:
            log(f"{Path(record).name}: being computed by {describe(holder(record))}; waiting for it")
            said = True
        time.sleep(POLL_S)


def _wait_until_free(record: Path, stale_after: float) -> None:
    """Return once no live claim holds `record` (released, or stale)."""
    path = claim_path(record)
    while True:
        seen = _inspect(path)
        if seen is None or _stale(*seen, stale_after):
            return
        time.sleep(POLL_S)


def _encoded(content: dict) -> bytes:
    return json.dumps(content).encode().ljust(CLAIM_BYTES - 1) + b"\n"


def _inspect(path: Path) -> tuple[dict | None, os.stat_result] | None:
    """`(content, stat)` of a claim file (content None while it is being written, or
    damaged), None if there is none."""
    try:
        stat = os.stat(path)
        text = path.read_bytes()
    except FileNotFoundError:
        return None
    try:
        return json.loads(text), stat
    except ValueError:
        return None, stat


def _stale(content: dict | None, stat: os.stat_result, stale_after: float) -> bool:
    """Whether a claim's claimant is gone: its heartbeat (the file's time while its
    content is unreadable) older than `stale_after`, or its pid dead on this host."""
    heartbeat = stat.st_mtime if content is None else content.get("heartbeat", stat.st_mtime)
    if time.time() - heartbeat > stale_after:
        return True
    if content is not None and content.get("host") == socket.gethostname():
        try:
            os.kill(int(content["pid"]), 0)
        except ProcessLookupError:
            return True
        except (PermissionError, KeyError, ValueError, TypeError):
            return False
    return False


def _take_over(path: Path, seen: tuple[dict | None, os.stat_result], stale_after: float) -> bool:
    """Remove the stale claim `seen` at `path`; whether this process removed it.

    Takers go one at a time, through a lock file created with O_EXCL beside the claim
    (a lock older than `TAKEOVER_LOCK_S` was left by a taker that died, and is
    removed). Under it, the claim is looked at again and removed only if it is still
    the one judged stale and still stale (its claimant may have beaten its heartbeat
    meanwhile, in place). Without the lock, a taker that saw the stale claim could move
    aside the fresh claim another taker had just made, and two would hold the record."""
    lock = path.with_name(path.name + TAKEOVER_SUFFIX)
    try:
        fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
    except FileExistsError:
        with contextlib.suppress(FileNotFoundError):
            if time.time() - os.stat(lock).st_mtime > TAKEOVER_LOCK_S:
                os.unlink(lock)
        time.sleep(0.01)  # another taker is at it: look again shortly
        return False
    try:
        now = _inspect(path)
        if now is None or now[1].st_ino != seen[1].st_ino or not _stale(*now, stale_after):
            return False
        os.unlink(path)
        return True
    finally:
        os.close(fd)
        os.unlink(lock)
