"""One record format for datasets, checkpoints and benchmark records.

An array record is an `.npz` of named arrays plus two strings: `meta`, a JSON object
(whatever the writer describes the arrays with, and the `environment` that made them:
`lgnn.provenance.environment()`), and `checksum`, a sha256 over the meta text and
every array's name, dtype, shape and bytes (`checksum`). `save` writes it atomically
(`lgnn.files.atomic_path`): a reader sees the old file or the new one, never half of
one. `read` returns `(arrays, meta)` or raises `RecordError` with one line naming the
file; it checks the checksum only, each kind of record checks its own `format` and
`key` in the meta.

A JSON record (`save_json`, `load_json`) is one JSON object: the settings `key` it was
made with, its fields, and the environment.

`digest(value)` is the sha256 of a JSON-able value (sorted keys): the key of a record is
the digest of the settings it depends on, `settings_key(settings)` of a settings
dataclass (fields marked `NOT_IN_KEY` left out, and those marked `KEY_UNLESS_DEFAULT`
while at their default, so records made before such a field existed keep their keys). `file_digest(path)` is the sha256 of a file's
bytes (a record depending on an input file keys on its content, not its name; on a
checkpoint, on `lgnn.learn.checkpoints.content_digest`).

The checksum is the algorithm every earlier record used, so committed checkpoints and
benchmark records stay readable and their checksums valid.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import zipfile
import zlib
from pathlib import Path

from lgnn import archives
from lgnn.errors import LgnnError
from lgnn.files import atomic_path


class RecordError(LgnnError):
    """A record file is missing, unreadable or corrupt; the message names the file."""


# Field metadata of a setting that does not change what a record holds.
NOT_IN_KEY = {"in_key": False}
# Field metadata of a setting added after records were made: in the key only when it
# differs from its default (which is what those records were made with), so they keep
# their keys.
KEY_UNLESS_DEFAULT = {"in_key": "unless default"}


def settings_key(settings) -> dict:
    """A settings dataclass as a JSON-able dict of every field not declared `NOT_IN_KEY`
    (nor `KEY_UNLESS_DEFAULT` at its default; nested settings dataclasses likewise)."""
    return {
        field.name: settings_key(value) if dataclasses.is_dataclass(value) else value
        for field in dataclasses.fields(settings)
        if field.metadata.get("in_key", True)
        for value in (getattr(settings, field.name),)
        if not (field.metadata.get("in_key") == KEY_UNLESS_DEFAULT["in_key"] and value == field.default)
    }


def digest(value) -> str:
    """sha256 (hex) of a JSON-able value, keys sorted (non-JSON values by `str`)."""
    return hashlib.sha256(json.dumps(value, sort_keys=True, default=str).encode()).hexdigest()


def file_digest(path: str | os.PathLike) -> str:
    """sha256 (hex) of a file's bytes."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def checksum(arrays: dict, meta_text: str) -> str:
    """sha256 (hex) over `meta_text` and every array's name, dtype, shape and bytes, in name order."""
    import numpy as np

    value_digest = hashlib.sha256(meta_text.encode())
    for name in sorted(arrays):
        value = np.ascontiguousarray(arrays[name])
        value_digest.update(f"{name}:{value.dtype.str}:{value.shape};".encode())
        value_digest.update(value.tobytes())
    return value_digest.hexdigest()


def _with_environment(meta: dict, environment: dict | None) -> dict:
    from lgnn import provenance

    return {**meta, "environment": provenance.environment() if environment is None else environment}


def save(path: str | os.PathLike, arrays: dict, meta: dict, environment: dict | None = None, compressed: bool = False) -> None:
    """Write an array record atomically: `arrays`, `meta` plus the `environment` that made
    them (default: this process's), and the checksum; `compressed`: every entry deflated
    (`np.savez_compressed`; `read` needs no telling). The parent directory must exist
    (`lgnn.files.check_writable` says so in one line)."""
    import numpy as np

    meta_text = json.dumps(_with_environment(meta, environment), sort_keys=True, default=float)
    write = np.savez_compressed if compressed else np.savez
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as handle:
            write(handle, meta=meta_text, checksum=checksum(arrays, meta_text), **arrays)


def read(path: str | os.PathLike, what: str = "record") -> tuple[dict, dict]:
    """`(arrays, meta)` of the array record at `path`; `RecordError` (one line naming the
    file and `what` it should be) if it is absent, unreadable or fails its checksum."""
    import numpy as np

    path = Path(path)
    if not path.is_file():
        raise RecordError(f"{path}: no such {what} file")
    problem = archives.npz_problem(path)
    if problem:
        raise RecordError(f"{path}: not a readable lgnn {what}: {problem}")
    try:
        with np.load(path, allow_pickle=False) as stored:
            arrays = {k: np.asarray(stored[k]) for k in stored.files if k not in ("meta", "checksum")}
            meta_text, stored_checksum = str(stored["meta"]), str(stored["checksum"])
        meta = json.loads(meta_text)
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error, RecursionError) as err:
        raise RecordError(f"{path}: not a readable lgnn {what} ({type(err).__name__})") from None
    except (AttributeError, TypeError):  # np.load of a .npy: a bare array, not an archive
        raise RecordError(f"{path}: not a readable lgnn {what} (not an .npz archive)") from None
    if not isinstance(meta, dict):
        raise RecordError(f"{path}: not a readable lgnn {what} (meta is not an object)")
    problem = archives.json_depth_problem(meta)
    if problem:
        raise RecordError(f"{path}: not a readable lgnn {what} (its meta is {problem})")
    if checksum(arrays, meta_text) != stored_checksum:
        raise RecordError(f"{path}: corrupt {what} (checksum mismatch)")
    return arrays, meta


def save_json(path: str | os.PathLike, key: str, fields: dict, environment: dict | None = None) -> None:
    """Write a JSON record atomically: the settings `key`, `fields` and the `environment`
    that made them (default: this process's)."""
    text = json.dumps(_with_environment({"key": key, **fields}, environment), indent=1, default=float)
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text)


def load_json(path: str | os.PathLike, key: str | None = None) -> dict | None:
    """The JSON record at `path` if it exists and was made with the settings `key` (any
    key if None), else None; `RecordError` (one line) if it is unreadable."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        stored = json.loads(path.read_text())
    except (OSError, ValueError, RecursionError) as err:
        raise RecordError(f"{path}: not a readable JSON record ({type(err).__name__})") from None
    if not isinstance(stored, dict):
        raise RecordError(f"{path}: not a readable JSON record (not an object)")
    problem = archives.json_depth_problem(stored)
    if problem:
        raise RecordError(f"{path}: not a readable JSON record ({problem})")
    return stored if key is None or stored.get("key") == key else None
