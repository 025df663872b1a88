"""The engine contract: what every engine is, takes and returns; no engine owns it.

- `Engine`: the base class of every engine (the Lagrangian ground truth, MuJoCo C,
  MJX, MuJoCo Warp, a learned model's `lgnn.learn.models.ModelEngine`). An engine has
  a `name`, the precision it computes in (`dtype`, one of `DTYPES`), and
  - `rollout(scene, config, states) -> Trajectory`: initial states `q`, `qd`
    (B, N, D) integrated for `config.duration`; the trajectory's `q`, `qd` are
    (B, F+1, N, D) and `energy` (B, F+1) lgnn's exact energy, frame 0 the initial
    state. It raises `SimulationError` at the first non-finite or exploding frame
    (`lgnn.metrics.ExplosionBounds`), carrying the failing member's frames before it.
    The Lagrangian engine runs a small batch on the host's CPU on a GPU machine, where
    it is fastest (`lgnn.engines.rollouts.ground_truth_platform`);
  - `timed_rollout(scene, config, states) -> (compile_s, run_s, q)`: the same run
    timed with one-off costs (compilation, model building) apart, `q` (B, F+1, N, D),
    on JAX's default device (what a timing names);
  - `timed_batch(scene, config, states, repeats) -> (compile_s, [run_s, ...], q)`:
    `repeats` timed runs of a batch, `q` (B, N, D) the final positions (`lgnn
    gpu-truth`'s measurement); by default `repeats` `timed_rollout`s, the compile the
    first's; the Lagrangian engine, MJX and MuJoCo Warp compile once and time the
    compiled run `repeats` times;
  - `form_of(scene) -> str`: the MJCF form it runs `scene` in ("" for engines
    without MJCF, the default);
  - `accuracy(scene, config) -> float | None`: the maximum node position error it
    expects against the exact solution at these settings (None, the default: the
    engine states none).
- `SimulationConfig`: the rollout settings every engine takes (step, frame interval,
  duration).
- `Integration`: how a JAX engine (the Lagrangian engine, a learned model's
  `ModelEngine`) integrates: its integrator and whether it projects onto the
  constraints after each step; a field of those engines, never of the settings. The
  MuJoCo engines take none (they integrate with MuJoCo's RK4).
- `Trajectory`: the NumPy result of a rollout, and its `.npz` file; `save_rollout`
  saves a rollout's, or the frames before its divergence, flagged so.
"""

from __future__ import annotations

import dataclasses
import json
import os
import zipfile
from typing import Callable, ClassVar

import numpy as np

from lgnn import integrate, physics
from lgnn.errors import ConfigError, SimulationError, check_number
from lgnn.files import atomic_path, check_regular_input
from lgnn.integrate import INTEGRATORS, Integrator, Projection
from lgnn.scene import Scene, State
from lgnn.scene.schema import MAX_MAGNITUDE

NPZ_KEYS = ("t", "q", "qd", "energy")
# Precisions an engine can be asked to compute in (`lgnn.engines.get_engine`).
DTYPES = ("float64", "float32")
# Bounds of one run, refused before anything is allocated: 1e10 steps is days of
# integration on any device; 1e7 frames of a 100-node chain are 32 GB of positions
# and velocities.
MAX_STEPS = 1e10
MAX_FRAMES = 1e7


@dataclasses.dataclass(frozen=True)
class SimulationConfig:
    """The rollout settings every engine takes (module docstring): how an engine
    integrates is the engine's own (`Integration` for the JAX engines)."""

    # RK4 at 1e-4 keeps max node error over 1 s below 1e-6 on the chains and T1
    # (tests/test_integrate.py::test_default_settings_are_accurate, and the MuJoCo
    # cross-check); not on the self-stressed T2/T3, whose references do not converge
    # in dt (issue 13). The paper's Verlet needs ~1e-5 for that.
    dt: float = 1e-4
    # The paper saves a frame every 1e-3 s.
    frame_dt: float = 1e-3
    duration: float = 1.0

    def __post_init__(self):
        for name in ("dt", "frame_dt", "duration"):
            check_number(name.replace("_", "-"), getattr(self, name))
        # Ratios first: a duration of 1e308 or a dt of 5e-324 overflows a count of frames.
        if not self.frame_dt / self.dt <= MAX_STEPS or not self.duration / self.frame_dt * (self.frame_dt / self.dt) <= MAX_STEPS:
            raise ConfigError(f"duration {self.duration:g} at dt {self.dt:g} is more than {MAX_STEPS:.0e} steps")
        if not self.duration / self.frame_dt <= MAX_FRAMES:
            raise ConfigError(f"duration {self.duration:g} at frame-dt {self.frame_dt:g} is more than {MAX_FRAMES:.0e} frames (the trajectory is kept in memory)")
        if abs(self.steps_per_frame * self.dt - self.frame_dt) > 1e-9 * self.frame_dt:
            raise ConfigError(f"frame-dt {self.frame_dt:g} is not a whole multiple of dt {self.dt:g}")
        if abs(self.n_frames * self.frame_dt - self.duration) > 1e-9 * self.duration or self.n_frames < 1:
            raise ConfigError(f"duration {self.duration:g} is not a whole (positive) multiple of frame-dt {self.frame_dt:g}")

    @property
    def steps_per_frame(self) -> int:
        return max(1, round(self.frame_dt / self.dt))

    @property
    def n_frames(self) -> int:
        """Frames after the initial one."""
        return round(self.duration / self.frame_dt)


@dataclasses.dataclass(frozen=True)
class Integration:
    """How a JAX engine integrates (module docstring)."""

    # RK4 at the default step meets the ground truth's tolerance (`SimulationConfig`);
    # "verlet" is the paper's.
    integrator: str = "rk4"
    # Projection keeps link lengths to round-off (per-link blocks: linear in a chain's length).
    project: bool = True

    def __post_init__(self):
        if self.integrator not in INTEGRATORS:
            raise ConfigError(f"unknown integrator {self.integrator!r} (choose from {', '.join(INTEGRATORS)})")
        if not isinstance(self.project, bool):
            raise ConfigError(f"project must be true or false, got {self.project!r}")

    def integrator_for(self, accel: physics.AccelerationFn, dt: float, project: Projection | None = None, *,
                       cheap_steps: bool = False) -> Integrator:
        """The integrator stepping `accel` by `dt`, projecting with `project` (a scene's
        `physics.projection_fn`) where this integration projects. `cheap_steps`: a step
        costs microseconds (one trajectory on a CPU), where RK4's stages are written out
        rather than looped (`integrate.CHEAP_STEP_FORMS`)."""
        return integrate.integrator(self.integrator, accel, dt, project if self.project else None, cheap_steps=cheap_steps)


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
        problem = trajectory_problem(*arrays, metadata)
        if problem:
            raise ConfigError(f"{path}: not a valid trajectory: {problem}")
        return cls(*arrays, metadata=metadata)


def save_rollout(run: Callable[[], Trajectory], path: str | os.PathLike) -> Trajectory:
    """`run()`'s trajectory saved to `path` and returned. If it diverges (a
    `SimulationError` carrying frames), the frames before the failure are saved, flagged
    `diverged` (its time and error) in the metadata, and the error is raised again
    naming the file; one carrying no frames is raised as it is, nothing written."""
    try:
        trajectory = run()
    except SimulationError as err:
        if err.trajectory is None or len(err.trajectory.t) == 0:
            raise
        partial = err.trajectory
        partial = dataclasses.replace(partial, metadata={**partial.metadata, "diverged": {"time": err.time, "error": str(err)}})
        partial.save(path)
        raise SimulationError(f"{err}; kept the {len(partial.t)} frames before it in {path} (metadata 'diverged')",
                              time=err.time, trajectory=partial) from None
    trajectory.save(path)
    return trajectory


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


class Engine:
    """What every engine answers (module docstring). Subclasses set `name` (a class
    attribute or a property) and `dtype`, and implement `rollout` and `timed_rollout`;
    `timed_batch` has a default built on `timed_rollout`, and `form_of` and `accuracy`
    defaults for engines without MJCF or a stated accuracy."""

    name: ClassVar[str] = ""
    dtype: str = "float64"

    def rollout(self, scene: Scene, config: SimulationConfig, states: State) -> Trajectory:
        """`Trajectory` of initial states (B, N, D): q, qd (B, F+1, N, D), energy (B, F+1)."""
        raise NotImplementedError

    def timed_rollout(self, scene: Scene, config: SimulationConfig, states: State) -> tuple[float, float, np.ndarray]:
        """`(compile_s, run_s, q (B, F+1, N, D))` of the same run, one-off costs apart."""
        raise NotImplementedError

    def timed_batch(self, scene: Scene, config: SimulationConfig, states: State, repeats: int = 1) -> tuple[float, list[float], np.ndarray]:
        """`(compile_s, run_s, q (B, N, D))` of `repeats` timed runs of the batch `states`:
        their seconds (one-off costs apart) and the last run's final positions. Here
        `repeats` `timed_rollout`s, `compile_s` the first's."""
        timed = [self.timed_rollout(scene, config, states) for _ in range(repeats)]
        return timed[0][0], [run_s for _, run_s, _ in timed], np.asarray(timed[-1][2])[:, -1]

    def form_of(self, scene: Scene) -> str:
        """The MJCF form this engine runs `scene` in; "" for an engine without MJCF."""
        return ""

    def accuracy(self, scene: Scene, config: SimulationConfig) -> float | None:
        """The maximum node position error (scene length units) this engine expects
        against the exact solution of `scene` at `config`; None: it states none."""
        return None
