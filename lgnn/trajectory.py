"""A trajectory: the NumPy result of any rollout, and its `.npz` file.

`Trajectory` (`t` (F,), `q`, `qd` (F, N, D), `energy` (F,), frame 0 the initial
state; or a batch (B, F, N, D) and (B, F)) is what every engine's `rollout` returns
(`lgnn.engines.base`, which re-exports it), what the metrics score
(`lgnn.metrics.Metric.error_fn(scene, predicted, reference)`) and what the benchmark's
ground truth keeps per reference engine. It lives here, below the metrics and the
engines, because both read it. `trajectory_problem` says what makes arrays read from a
file not one trajectory.
"""

from __future__ import annotations

import dataclasses
import json
import os
import zipfile

import numpy as np

from lgnn import archives
from lgnn.errors import ConfigError
from lgnn.files import atomic_path, check_regular_input
from lgnn.scene.schema import MAX_MAGNITUDE

# The arrays of a trajectory file (beside a JSON `metadata` string).
NPZ_KEYS = ("t", "q", "qd", "energy")


@dataclasses.dataclass(frozen=True)
class Trajectory:
    """A simulated or predicted trajectory (NumPy arrays), frame 0 the initial state:
    `t` (F,), `q`, `qd` (F, N, D), `energy` (F,); an engine's `rollout` returns a batch,
    `q`, `qd` (B, F, N, D) and `energy` (B, F), whose `member(b)` is one trajectory."""

    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    energy: np.ndarray
    metadata: dict = dataclasses.field(default_factory=dict)

    def member(self, index: int) -> "Trajectory":
        """Trajectory `index` of a batch (B, F, N, D)."""
        if np.ndim(self.q) != 4:
            raise ValueError(f"member() of a batch (B, F, N, D), got q of shape {np.shape(self.q)}")
        return Trajectory(self.t, self.q[index], self.qd[index], self.energy[index], self.metadata)

    def save(self, path: str | os.PathLike) -> None:
        """Write the `.npz` layout (`t, q, qd, energy` + a JSON `metadata` string), atomically."""
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as handle:
                np.savez(handle, t=self.t, q=self.q, qd=self.qd, energy=self.energy, metadata=json.dumps(self.metadata))

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Trajectory":
        """The trajectory file at `path`, its arrays and metadata checked (`trajectory_problem`);
        `ConfigError` (one line) for anything else."""
        check_regular_input(path, "trajectory file")
        problem = archives.npz_problem(path)
        if problem:
            raise ConfigError(f"{path}: not a trajectory file: {problem}")
        try:
            with np.load(path, allow_pickle=False) as data:
                if not isinstance(data, np.lib.npyio.NpzFile):
                    raise ConfigError(f"{path}: not a trajectory file (an .npz of {', '.join(NPZ_KEYS)})")
                missing = [key for key in NPZ_KEYS if key not in data]
                if missing:
                    raise ConfigError(f"{path}: not a trajectory file (missing {', '.join(missing)})")
                metadata = json.loads(str(data["metadata"])) if "metadata" in data else {}
                arrays = [np.asarray(data[key]) for key in NPZ_KEYS]
        except (AttributeError, TypeError):  # np.load of a .npy: a bare array, no context manager
            raise ConfigError(f"{path}: not a trajectory file (an .npz of {', '.join(NPZ_KEYS)})") from None
        except RecursionError:
            raise ConfigError(f"{path}: trajectory metadata nested too deeply") from None
        except json.JSONDecodeError as err:
            raise ConfigError(f"{path}: trajectory metadata is not JSON ({err.msg})") from None
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
            raise ConfigError(f"{path}: cannot read trajectory: {err}") from None
        problem = archives.json_depth_problem(metadata) or trajectory_problem(*arrays, metadata)
        if problem:
            raise ConfigError(f"{path}: not a valid trajectory: {problem}")
        return cls(*arrays, metadata=metadata)


def trajectory_problem(t: np.ndarray, q: np.ndarray, qd: np.ndarray, energy: np.ndarray, metadata) -> str | None:
    """What makes arrays and metadata read from a file not one trajectory (`Trajectory`'s
    shapes, real finite numbers (times and states within a scene's `MAX_MAGNITUDE`), a
    JSON object of metadata whose
    `scene`, `model` and `engine` are objects), or None."""
    if not isinstance(metadata, dict):
        return f"metadata must be a JSON object, got {type(metadata).__name__}"
    for key in ("scene", "model", "engine"):
        if key in metadata and not isinstance(metadata[key], dict):
            return f"metadata {key!r} must be an object, got {metadata[key]!r:.40}"
    for name, array in zip(NPZ_KEYS, (t, q, qd, energy)):
        if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
            return f"{name} must hold real numbers, got dtype {array.dtype}"
        # Frames after a divergence are never kept (the engines stop there). An energy
        # multiplies a few of a scene's numbers (a mass of 1e30 is one), so it need only
        # be finite.
        if name == "energy" and not np.isfinite(array).all():
            return "energy holds values that are not finite"
        if name != "energy" and not np.all(np.abs(array) <= MAX_MAGNITUDE):
            return f"{name} holds values that are not finite or beyond {MAX_MAGNITUDE:g}"
    if t.ndim != 1 or len(t) < 1:
        return f"t must be (frames,), got shape {t.shape}"
    if q.ndim != 3 or q.shape[0] != len(t) or qd.shape != q.shape:
        return f"q and qd must be (frames, nodes, dim) with {len(t)} frames, got {q.shape} and {qd.shape}"
    if energy.shape != t.shape:
        return f"energy must be (frames,) = {t.shape}, got {energy.shape}"
    return None
