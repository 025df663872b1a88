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
- `Trajectory`: the NumPy result of a rollout, and its `.npz` file (defined in
  `lgnn.trajectory`, below the metrics that score it; importable from here);
  `save_rollout` saves a rollout's, or the frames before its divergence, flagged so.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Callable, ClassVar

import numpy as np

from lgnn import integrate, physics
from lgnn.errors import ConfigError, SimulationError, check_number
from lgnn.integrate import INTEGRATORS, Integrator, Projection
from lgnn.scene import Scene, State
from lgnn.trajectory import NPZ_KEYS, Trajectory, trajectory_problem  # noqa: F401 (the engine contract's type, defined below the metrics)

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
