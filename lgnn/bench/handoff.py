"""A benchmark run handed from one job to the next (docs/benchmark.md, "Resuming across
jobs").

A preemptible slot runs the benchmark in jobs of minutes, on machines that may be lost
between them with everything on them, and hands back a few files. `pack(profile, out,
dest)` writes what a fresh machine needs to go on from the output folder `out` into
`dest`, within `Limits` (by default at most 8 files of at most 16 MiB, 64 MiB in all);
`unpack(dest, out)` puts it back into a folder without a run. `lgnn benchmark` then
resumes there as on the machine that stopped: every stage reuses the finished work it
finds, and training goes on from each checkpoint.

What is handed back: one tar stream of files under `out`, cut into parts
(`handoff.tar.000`, ...), and a manifest (`handoff.json`: the commit and profile that
packed it, each part's size and sha256, each member's size and role):

- every record under `benchmark/runs/`, and `benchmark/run.json`;
- each training job's checkpoint: whole (its latest parameters and optimiser state) while
  training goes on; once finished, its best parameters alone
  (`checkpoints.for_inference`) while a stage still rolls it out (an evaluation pair
  not yet recorded, a model the speed stage times, the LGNN the mass stage reads); after
  that its meta and history alone (`checkpoints.without_parameters`), which the report
  reads.

Not handed back, since the next machine makes them again from their settings: the
dataset cache (training data and ground truths are regenerated, deterministically), the
compilation cache, the report's files, logs and claims. Where the rest exceeds the
limits, unfinished checkpoints are left out, the largest first, each named in the
manifest and on stderr: those jobs train again from their start. If what remains still
exceeds them, nothing is written, and `ConfigError` says by how much.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import os
import shutil
import tarfile
import tempfile
from pathlib import Path

from lgnn import archives, provenance
from lgnn.bench import store
from lgnn.bench.profiles import Profile, evaluation_pairs, lgnn_job, training_jobs
from lgnn.errors import CheckpointError, ConfigError

MANIFEST = "handoff.json"
PART_PREFIX = "handoff.tar."
# What a preemptible job of this project's slot can hand back (issue 60).
MIB = 2**20
DEFAULT_FILES, DEFAULT_FILE_BYTES, DEFAULT_TOTAL_BYTES = 8, 16 * MIB, 64 * MIB
# The manifest's own size is counted against the total at most this large.
MANIFEST_RESERVE = 256 * 1024
# The roles of handed-back members (the manifest's `role`).
RECORD, TRAINING, INFERENCE, HISTORY = "record", "training", "for inference", "history only"
_TAR_BLOCK, _TAR_RECORD = 512, 20 * 512


@dataclasses.dataclass(frozen=True)
class Limits:
    """What a job may hand back: at most `files` files (the manifest among them) of at
    most `file_bytes` each, `total_bytes` in all."""

    files: int = DEFAULT_FILES
    file_bytes: int = DEFAULT_FILE_BYTES
    total_bytes: int = DEFAULT_TOTAL_BYTES

    def __post_init__(self):
        if self.files < 2 or self.file_bytes < MANIFEST_RESERVE or self.total_bytes < MANIFEST_RESERVE:
            raise ConfigError(f"hand-back limits too small: {self.files} files of {self.file_bytes} bytes, {self.total_bytes} in all "
                              f"(at least 2 files, the manifest among them, and {MANIFEST_RESERVE} bytes)")

    @property
    def stream_bytes(self) -> int:
        """The largest tar stream that fits: parts of `file_bytes` in the files the
        manifest leaves, and the total less the manifest's reserve."""
        return min((self.files - 1) * self.file_bytes, self.total_bytes - MANIFEST_RESERVE)


@dataclasses.dataclass(frozen=True)
class Member:
    """A file handed back: its path under the output folder, where its bytes come from
    (the file itself, or a slimmer copy of a checkpoint made for the hand-back), its
    size and role."""

    name: str
    source: Path
    size: int
    role: str

    @property
    def tar_bytes(self) -> int:
        # A tar member: a header block, then its bytes padded to whole blocks.
        return _TAR_BLOCK + -(-self.size // _TAR_BLOCK) * _TAR_BLOCK


def stream_size(members: list[Member]) -> int:
    """The bytes of the tar stream of `members` (the format's blocks, its two closing
    blocks, and its padding to whole records)."""
    size = sum(member.tar_bytes for member in members) + 2 * _TAR_BLOCK
    return -(-size // _TAR_RECORD) * _TAR_RECORD


def pack(profile: Profile, out: Path, dest: Path, limits: Limits = Limits(), log=store.log) -> dict:
    """Write the hand-back of the run in `out` into `dest` (module docstring) and return
    its manifest. `ConfigError` (nothing written) where it cannot fit `limits`."""
    out, dest = Path(out), Path(dest)
    if not (out / "benchmark").is_dir():
        raise ConfigError(f"{out} holds no benchmark run (no {out / 'benchmark'} folder)")
    with tempfile.TemporaryDirectory(prefix="lgnn-handoff-") as staging:
        members = _records(out) + _checkpoints(profile, out, Path(staging), log)
        members, dropped = _within(members, limits)
        for member in dropped:
            log(f"hand-back: left out {member.name} ({member.size / MIB:.1f} MiB, {member.role}): over the limit of "
                f"{limits.total_bytes / MIB:g} MiB; that job trains again from its start")
        dest.mkdir(parents=True, exist_ok=True)
        manifest = _write(members, dropped, profile, dest, limits)
    log(f"hand-back: {len(members)} files, {manifest['bytes'] / MIB:.1f} MiB in {len(manifest['parts'])} parts, into {dest}/")
    return manifest


def _records(out: Path) -> list[Member]:
    # Every finished stage record and the run's record; claims are not records, nor are
    # the temporaries of writes a killed process left (`files.atomic_path`: ".name...").
    paths = [out / "benchmark" / "run.json"] if (out / "benchmark" / "run.json").is_file() else []
    runs = out / "benchmark" / "runs"
    paths += sorted(p for p in runs.rglob("*") if p.is_file() and p.suffix in (".npz", ".json") and not p.name.startswith(".")) if runs.is_dir() else []
    return [Member(p.relative_to(out).as_posix(), p, p.stat().st_size, RECORD) for p in paths]


def _checkpoints(profile: Profile, out: Path, staging: Path, log) -> list[Member]:
    """The profile's training checkpoints under `out`, each as the module docstring says:
    whole while training goes on, slimmer copies (made in `staging`) once finished; what
    is left out is told to `log`."""
    from lgnn.bench.stages.evaluate import load_pair
    from lgnn.bench.stages.speed import timed_jobs
    from lgnn.bench.stages.train import job_settings, made_with
    from lgnn.learn import checkpoints, protocol, train

    layout = store.Layout(out)
    jobs = training_jobs(profile)
    pairs = evaluation_pairs(profile)
    stages = profile.stages or ("speed", "mass")  # (None: every stage)
    read_later = {job for scene in profile.speed.scenes for job in timed_jobs(profile, scene)} if "speed" in stages else set()
    read_later |= {lgnn_job(profile, scene) for scene in profile.mass.scenes} if "mass" in stages else set()
    members = []
    known = {layout.checkpoint(job) for job in jobs}
    strangers = sorted(p.name for p in (out / "benchmark" / "checkpoints").glob("*.npz") if p not in known and not p.name.startswith("."))
    if strangers:
        log(f"hand-back: {len(strangers)} checkpoints belong to no job of the {profile.name} profile given, left out: {', '.join(strangers[:5])}"
            + (", ..." if len(strangers) > 5 else "") + " (pack with the run's own profile options)")
    for job in jobs:
        path = layout.checkpoint(job)
        if not path.is_file():
            continue
        name = path.relative_to(out).as_posix()
        try:
            state, meta = train.load_checkpoint(path)
        except CheckpointError as err:
            log(f"hand-back: warning: {err}; left out (that job trains again)")
            continue
        settings = job_settings(profile, job)
        if not made_with(meta, settings):
            log(f"hand-back: {name} was trained with other settings; left out (that job trains again)")
            continue
        if not protocol.finished(state, settings[3]):
            if checkpoints.resumable(meta):
                members.append(Member(name, path, path.stat().st_size, TRAINING))
            else:
                log(f"hand-back: {name} is unfinished and cannot be resumed; left out (that job trains again)")
            continue
        needed = job in read_later or any(pair.job == job and load_pair(profile, pair, out) is None for pair in pairs)
        if not checkpoints.has_parameters(meta) or needed and not checkpoints.resumable(meta):
            # Already as slim as it will be handed back.
            members.append(Member(name, path, path.stat().st_size, INFERENCE if checkpoints.has_parameters(meta) else HISTORY))
            continue
        slim = staging / name
        slim.parent.mkdir(parents=True, exist_ok=True)
        (checkpoints.for_inference if needed else checkpoints.without_parameters)(path, slim)
        members.append(Member(name, slim, slim.stat().st_size, INFERENCE if needed else HISTORY))
    return members


def _within(members: list[Member], limits: Limits) -> tuple[list[Member], list[Member]]:
    """`(kept, dropped)`: `members` less the largest unfinished checkpoints until the
    stream fits `limits`; `ConfigError` if it cannot."""
    kept, dropped = list(members), []
    training = sorted((m for m in members if m.role == TRAINING), key=lambda m: m.size, reverse=True)
    while stream_size(kept) > limits.stream_bytes and training:
        dropped.append(training.pop(0))
        kept.remove(dropped[-1])
    if stream_size(kept) > limits.stream_bytes:
        raise ConfigError(f"the run's records and finished checkpoints take {stream_size(kept) / MIB:.1f} MiB, over the "
                          f"{limits.stream_bytes / MIB:.1f} MiB that {limits.files} files of {limits.file_bytes / MIB:g} MiB "
                          f"({limits.total_bytes / MIB:g} MiB in all) hold with the manifest; nothing written")
    return kept, dropped


def _write(members: list[Member], dropped: list[Member], profile: Profile, dest: Path, limits: Limits) -> dict:
    """Write the parts and then the manifest into `dest`, replacing an earlier hand-back
    there only once the new one is whole."""
    with tempfile.TemporaryDirectory(prefix=".handoff-", dir=dest) as fresh:
        parts = _PartWriter(Path(fresh), limits.file_bytes)
        # USTAR: one 512-byte header a member (`Member.tar_bytes`); the benchmark's names fit it.
        with tarfile.open(fileobj=parts, mode="w|", format=tarfile.USTAR_FORMAT) as archive:
            for member in members:
                info = tarfile.TarInfo(member.name)
                info.size, info.mode, info.mtime = member.size, 0o644, 0
                with open(member.source, "rb") as handle:
                    archive.addfile(info, handle)
        parts.finish()
        written = sum(part["bytes"] for part in parts.written)
        if written != stream_size(members):  # the limits were checked on this size
            raise RuntimeError(f"hand-back stream of {written} bytes, {stream_size(members)} expected")
        manifest = {
            "format": 1,
            "commit": provenance.commit(),
            "profile": profile.name,
            "bytes": written,
            "parts": parts.written,
            "members": [{"name": m.name, "bytes": m.size, "role": m.role} for m in members],
            "left_out": [{"name": m.name, "bytes": m.size, "role": m.role} for m in dropped],
        }
        (Path(fresh) / MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
        for old in [*dest.glob(f"{PART_PREFIX}*"), dest / MANIFEST]:
            old.unlink(missing_ok=True)
        for part in parts.written:
            os.replace(Path(fresh) / part["name"], dest / part["name"])
        os.replace(Path(fresh) / MANIFEST, dest / MANIFEST)  # last: a manifest names whole parts only
    return manifest


class _PartWriter(io.RawIOBase):
    """A write-only stream cut into files `handoff.tar.000`, ... of at most `part_bytes`
    under `folder`, each one's size and sha256 kept in `written`."""

    def __init__(self, folder: Path, part_bytes: int):
        self.folder, self.part_bytes, self.written = folder, part_bytes, []
        self._handle, self._hash, self._size = None, None, 0

    def writable(self) -> bool:
        return True

    def write(self, data) -> int:
        view, total = memoryview(data), len(data)
        while len(view):
            if self._handle is None or self._size == self.part_bytes:
                self._next()
            take = min(len(view), self.part_bytes - self._size)
            self._handle.write(view[:take])
            self._hash.update(view[:take])
            self._size += take
            view = view[take:]
        return total

    def _next(self) -> None:
        self._close_part()
        name = f"{PART_PREFIX}{len(self.written):03d}"
        self._handle, self._hash, self._size = open(self.folder / name, "wb"), hashlib.sha256(), 0
        self.written.append({"name": name})

    def _close_part(self) -> None:
        if self._handle is not None:
            self._handle.close()
            self.written[-1].update(bytes=self._size, sha256=self._hash.hexdigest())
            self._handle = None

    def finish(self) -> None:
        self._close_part()


def unpack(source: Path, out: Path, log=store.log) -> dict:
    """Put the hand-back in `source` (`pack`) into the output folder `out`, which must
    hold no run yet; its manifest. `ConfigError` (one line, nothing written into `out`)
    for a missing or damaged part, a member outside `benchmark/`, or a run already there."""
    source, out = Path(source), Path(out)
    manifest = _read_manifest(source)
    if (out / "benchmark").exists():
        raise ConfigError(f"{out} already holds a run ({out / 'benchmark'}): unpack a hand-back into a folder without one")
    for part in manifest["parts"]:
        path = source / part["name"]
        if not path.is_file() or path.stat().st_size != part["bytes"] or _sha256(path) != part["sha256"]:
            raise ConfigError(f"{path}: missing or damaged (its size or sha256 differs from {source / MANIFEST})")
    out.mkdir(parents=True, exist_ok=True)
    expected = {member["name"]: member["bytes"] for member in manifest["members"]}
    with tempfile.TemporaryDirectory(prefix=".unpack-", dir=out) as staging:
        found = {}
        with _PartReader([source / part["name"] for part in manifest["parts"]]) as stream, tarfile.open(fileobj=stream, mode="r|") as archive:
            for info in archive:
                name = Path(info.name)
                if not info.isfile() or name.is_absolute() or ".." in name.parts or name.parts[:1] != ("benchmark",):
                    raise ConfigError(f"{source}: member {info.name!r} is not a file under benchmark/; nothing unpacked")
                # Written by hand, not `extract`: no link, device or mode of the archive's is kept.
                target = Path(staging) / name
                target.parent.mkdir(parents=True, exist_ok=True)
                with archive.extractfile(info) as data, open(target, "wb") as handle:
                    shutil.copyfileobj(data, handle)
                found[info.name] = info.size
        if found != expected:
            raise ConfigError(f"{source}: its parts hold other files than {MANIFEST} lists; nothing unpacked")
        os.replace(Path(staging) / "benchmark", out / "benchmark")
    log(f"unpacked {len(manifest['members'])} files of a hand-back (commit {manifest['commit']}) into {out}/"
        + (f"; {len(manifest['left_out'])} unfinished checkpoints were left out of it" if manifest["left_out"] else ""))
    return manifest


def _read_manifest(source: Path) -> dict:
    path = source / MANIFEST
    try:
        manifest = json.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{source}: no hand-back there (no {MANIFEST})") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as err:
        raise ConfigError(f"{path}: not a readable hand-back manifest ({type(err).__name__}: {err})") from None
    parts = manifest.get("parts") if isinstance(manifest, dict) else None
    if not isinstance(manifest, dict) or archives.json_depth_problem(manifest) or manifest.get("format") != 1 or not isinstance(parts, list) or not all(
            isinstance(p, dict) and isinstance(p.get("name"), str) and p["name"].startswith(PART_PREFIX) and "/" not in p["name"]
            and isinstance(p.get("bytes"), int) and isinstance(p.get("sha256"), str) for p in parts):
        raise ConfigError(f"{path}: not a hand-back manifest of format 1")
    return manifest


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(MIB), b""):
            digest.update(block)
    return digest.hexdigest()


class _PartReader(io.RawIOBase):
    """The parts read back to back as one stream."""

    def __init__(self, paths: list[Path]):
        self._paths, self._handle = list(paths), None

    def readable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:
        while True:
            if self._handle is None:
                if not self._paths:
                    return 0
                self._handle = open(self._paths.pop(0), "rb")
            count = self._handle.readinto(buffer)
            if count:
                return count
            self._handle.close()
            self._handle = None

    def close(self) -> None:
        if self._handle is not None:
            self._handle.close()
        super().close()


