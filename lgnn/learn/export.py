"""Training and evaluation data for other frameworks: one documented file.

`export_dataset(path, dataset, config, evaluation)` writes, and `load_exported(path)`
reads back exactly, an `.npz` (always; an `lgnn.records` record, so `np.load` reads it
too) or an `.h5` (HDF5, needs the `hdf5` extra: `pip install lgnn[hdf5]`) holding:

- arrays: `q`, `qd`, `qdd` (S, N, D) float64 states and exact accelerations,
  `trajectory` (S,) the trajectory of each state, `t` (S,) its time in that trajectory
  (s), `train`, `val` index arrays of the split, `eval_q0`, `eval_qd0` (C, N, D) the
  benchmark's evaluation initial conditions;
- `meta` (JSON text; an HDF5 root attribute): `format` (`EXPORT_FORMAT`), `scene` (the
  scene file's JSON object, `lgnn.scene.scene_from_dict` reads it), `data` (the
  generating `DataConfig`), `evaluation` (how the evaluation rolls out: `dt`,
  `frame_dt`, `duration`, `seed`, integrator), and `environment` (the provenance: commit,
  versions, machine); in HDF5 also `checksum` (`lgnn.records.checksum` of the arrays
  and meta, as in the npz).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from lgnn import archives, records
from lgnn.errors import ConfigError
from lgnn.files import atomic_path

EXPORT_FORMAT = 1
ARRAYS = ("q", "qd", "qdd", "trajectory", "t", "train", "val", "eval_q0", "eval_qd0")
SUFFIXES = (".npz", ".h5", ".hdf5")


class Exported(NamedTuple):
    """An exported file's `arrays` (name -> array, `ARRAYS`) and `meta` (module docstring)."""

    arrays: dict
    meta: dict


def _h5py():
    try:
        import h5py
    except ImportError:
        raise ConfigError("HDF5 export needs h5py: pip install 'lgnn[hdf5]' (or write .npz)") from None
    return h5py


def check_path(path: str | os.PathLike) -> Path:
    """`path` if its suffix names a format (`.npz`, `.h5`); `ConfigError` otherwise."""
    path = Path(path)
    if path.suffix not in SUFFIXES:
        raise ConfigError(f"--out must end in {', '.join(SUFFIXES)}, got {path}")
    if path.suffix != ".npz":
        _h5py()
    return path


def export_dataset(path: str | os.PathLike, arrays: dict, meta: dict) -> None:
    """Write `arrays` (every name of `ARRAYS`) and `meta` to `path` atomically, with the
    provenance of this process."""
    path = check_path(path)
    if set(arrays) != set(ARRAYS):
        raise ConfigError(f"export needs arrays {', '.join(ARRAYS)}")
    meta = {**meta, "format": EXPORT_FORMAT}
    if path.suffix == ".npz":
        records.save(path, arrays, meta)
        return
    h5py = _h5py()
    from lgnn import provenance

    text = json.dumps({**meta, "environment": provenance.environment()}, sort_keys=True, default=float)
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as handle:
            for name in ARRAYS:
                handle.create_dataset(name, data=np.asarray(arrays[name]))
            handle.attrs["meta"] = text
            handle.attrs["checksum"] = records.checksum(arrays, text)


def load_exported(path: str | os.PathLike) -> Exported:
    """The arrays and meta of a file written by `export_dataset`, checksum verified;
    `ConfigError` (one line naming the file) if it is not one or is damaged."""
    path = Path(path)
    if path.suffix == ".npz":
        try:
            arrays, meta = records.read(path, "exported dataset")
        except records.RecordError as err:
            raise ConfigError(str(err)) from None
    elif path.suffix in SUFFIXES:
        h5py = _h5py()
        try:
            with h5py.File(path, "r") as handle:
                arrays = {name: handle[name][()] for name in handle}
                text, stored = str(handle.attrs["meta"]), str(handle.attrs["checksum"])
        except (OSError, KeyError) as err:
            raise ConfigError(f"{path}: not a readable exported dataset ({err})") from None
        if records.checksum(arrays, text) != stored:
            raise ConfigError(f"{path}: checksum mismatch (damaged exported dataset)")
        try:
            meta = json.loads(text)
        except (ValueError, RecursionError) as err:
            raise ConfigError(f"{path}: not a readable exported dataset (its meta: {type(err).__name__})") from None
    else:
        raise ConfigError(f"{path}: not an exported dataset (suffix {path.suffix or 'none'})")
    if not isinstance(meta, dict) or archives.json_depth_problem(meta) or meta.get("format") != EXPORT_FORMAT or set(arrays) != set(ARRAYS):
        raise ConfigError(f"{path}: not an lgnn exported dataset of format {EXPORT_FORMAT}")
    return Exported(arrays, meta)
