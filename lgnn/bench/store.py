"""Where the benchmark's records live, and how a stage reuses them.

Under `<out>/benchmark/`: `checkpoints/<job>.npz` (`lgnn.learn.train`) and `runs/`,
the stage records. Datasets (training data and each scene's ground-truth trajectories)
go to lgnn's one dataset cache (`lgnn.learn.data.default_cache_dir`: `datasets/` in
`$LGNN_CACHE`, else `$XDG_CACHE_HOME/lgnn`, else `~/.cache/lgnn`), which `lgnn train`
and `lgnn dataset export` use too, each file named by the digest of its settings.
Every record is an `lgnn.records` record (arrays) or JSON record whose meta holds the
settings `key` it was made with (`lgnn.bench.stages`). `load` and `load_json` return a
record only if it is whole and has the wanted key: an absent or stale one is None
(recomputed), a damaged one too, with a warning on stderr. Progress goes to stderr
(`log`). Processes that share the folder claim a record before computing it
(`lgnn.bench.claims`), so each is computed once.

A profile's `base` (e.g. the committed `results/`) is a second folder of the same
layout, read in place and never written (`layout(profile, out)`): every record and
checkpoint path a `Layout` gives is under `out`, where records are written;
`Layout.found` and `Layout.load` read a file from `out`, else from `base`, so a record
or checkpoint the base holds with the wanted key is reused as it is, and one it lacks
or holds with other settings is made under `out`.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

from lgnn import records
from lgnn.errors import ConfigError
from lgnn.files import DEFAULT_OUT
from lgnn.bench.grid import Pair, TrainingJob
from lgnn.bench.profiles import Profile
from lgnn.learn.data import default_cache_dir

# Layout of a stage record's meta; records of another format are recomputed.
RECORD_FORMAT = 1


def log(message: str) -> None:
    print(f"[benchmark] {message}", file=sys.stderr, flush=True)


@dataclasses.dataclass(frozen=True)
class Layout:
    """Where a profile's outputs live under `out` (written), and the read-only `base`
    folder of the same layout read beside it (module docstring)."""

    out: Path
    base: Path | None = None

    @property
    def bench(self) -> Path:
        return self.out / "benchmark"

    def checkpoint(self, job: TrainingJob) -> Path:
        return self.bench / "checkpoints" / f"{file_name(job.name)}.npz"

    def pair_record(self, pair: Pair) -> Path:
        stem = file_name(pair.scene) + ("" if pair.projected else "-unprojected")
        return self.bench / "runs" / file_name(pair.job.name) / f"{stem}.npz"

    def external_record(self, model: str, scene: str) -> Path:
        """The record of predictions made outside lgnn (`lgnn.bench.stages.external`)."""
        return self.bench / "runs" / "external" / file_name(model) / f"{file_name(scene)}.npz"

    def external_records(self, scene: str) -> list[Path]:
        """Every external record of `scene` under `out` and the base, as paths under
        `out` (`load` reads `out`'s, else the base's), by model."""
        found = {}
        for folder in (self.out, self.base):
            if folder is not None:
                for path in (folder / "benchmark" / "runs" / "external").glob(f"*/{file_name(scene)}.npz"):
                    found.setdefault(path.parent.name, self.external_record(path.parent.name, scene))
        return [found[name] for name in sorted(found)]

    def truth_record(self, scene: str) -> Path:
        return self.bench / "runs" / "ground-truth" / f"{file_name(scene)}.npz"

    @property
    def scaling_record(self) -> Path:
        return self.bench / "runs" / "scaling.json"

    def speed_record(self, scene: str) -> Path:
        return self.bench / "runs" / "speed-error" / f"{scene}.json"

    def mass_record(self, scene: str) -> Path:
        return self.bench / "runs" / "mass-matrix" / f"{scene}.npz"

    @property
    def datasets(self) -> Path:
        """lgnn's dataset cache (module docstring), shared by every output folder."""
        return default_cache_dir()

    def in_base(self, path: Path) -> Path | None:
        """The file of the base folder at `path`'s place under `out`, if the base has it."""
        if self.base is None:
            return None
        copy = self.base / Path(path).relative_to(self.out)
        return copy if copy.exists() else None

    def found(self, path: Path) -> Path:
        """`path` (under `out`) if it exists, else the base's file in its place if that
        exists, else `path`."""
        return path if path.exists() else self.in_base(path) or path

    def load(self, path: Path, key: str | None = None) -> tuple[dict, dict] | None:
        """`load` of the record at `path` under `out`, else of the base's in its place.
        The meta's `folder` says which folder it was read from."""
        for where, candidate in ((self.out, path), (self.base, self.in_base(path))):
            record = None if candidate is None else load(candidate, key)
            if record is not None:
                return record[0], {**record[1], "folder": str(where)}
        return None

    def load_json(self, path: Path, key: str) -> dict | None:
        """`load_json` of the record at `path` under `out`, else of the base's in its
        place; its `folder` says which folder it was read from."""
        for where, candidate in ((self.out, path), (self.base, self.in_base(path))):
            record = None if candidate is None else load_json(candidate, key)
            if record is not None:
                return {**record, "folder": str(where)}
        return None


def truth_trajectories(scene: str, key: str) -> Path:
    """A scene's ground-truth trajectories under the settings `key`
    (`lgnn.bench.stages.truth.ground_truth`): large, not a result, in the dataset cache of every output
    folder."""
    return default_cache_dir() / "ground-truth" / f"{file_name(scene)}-{key[:16]}.npz"


def layout(profile: Profile, out: Path) -> Layout:
    """The layout of a profile's outputs under `out`, with its `base` folder read beside
    them; `ConfigError` if `out` is the base (the base is never written)."""
    if profile.base is None:
        return Layout(Path(out))
    base = Path(profile.base)
    if not base.is_dir():
        raise ConfigError(f"base results folder {base} is not a folder")
    if Path(out).resolve() == base.resolve():
        raise ConfigError(f"the output folder {out} is the base results folder, which is read, never written: give another output folder")
    return Layout(Path(out), base)


def file_name(name: str) -> str:
    """A job or scene name as one file name: built-in names as they are; a name holding
    a scene file's path (a user's config) with its separators replaced and a digest of
    the path appended, so records stay under `out` and two files of one name in
    different directories do not share records."""
    if all(c.isalnum() or c in "-_." for c in name) and not name.startswith("."):
        return name
    safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in name)[-48:].lstrip("_")
    return f"{safe}-{records.digest(name)[:8]}"


def default_out(profile: Profile) -> Path:
    """The full profile's records are the repository's committed `results/` (a run
    resumes and updates them) unless it reads a `base` folder; any other profile, and a
    profile with a base, writes under `lgnn.files.DEFAULT_OUT`."""
    return Path("results") if profile.name == "full" and profile.base is None else DEFAULT_OUT / profile.name


def save(path: Path, key: str, arrays: dict, meta: dict) -> None:
    """A stage's array record: `arrays` and `meta` with the settings `key`."""
    path.parent.mkdir(parents=True, exist_ok=True)
    records.save(path, arrays, {**meta, "key": key, "format": RECORD_FORMAT})


def load(path: Path, key: str | None = None) -> tuple[dict, dict] | None:
    """`(arrays, meta)` of a valid record with settings `key` (any key if None); None
    (with a warning for a damaged file) when it is absent, damaged or stale."""
    if not path.exists():
        return None
    try:
        arrays, meta = records.read(path)
    except records.RecordError as err:
        log(f"warning: {err}; recomputing")
        return None
    if meta.get("format") != RECORD_FORMAT or (key is not None and meta.get("key") != key):
        return None
    return arrays, meta


def save_json(path: Path, key: str, **fields) -> None:
    """A stage's JSON record: the settings `key` and `fields`."""
    path.parent.mkdir(parents=True, exist_ok=True)
    records.save_json(path, key, fields)


def load_json(path: Path, key: str) -> dict | None:
    """The JSON record at `path` if it was made with the settings `key`; None when it is
    absent, stale or damaged (with a warning)."""
    try:
        return records.load_json(path, key)
    except records.RecordError as err:
        log(f"warning: {err}; recomputing")
        return None
