"""The Lagrangian ground-truth engine: settings, trajectories and their `.npz` files.

`simulate(scene, config)` integrates the scene's exact constrained Lagrangian dynamics
from its initial state and returns a `Trajectory` (NumPy): `t` (F,), `q` and `qd`
(F, N, D), `energy` (F,), frame 0 being the initial state. Work is done in jitted
chunks of frames so long runs show progress, and a run stops at the first non-finite
or exploding frame (`lgnn.metrics.ExplosionBounds`) with a `SimulationError` that names its
time and carries the frames before it; a NaN trajectory is never returned.
`LagrangianEngine` is the `lgnn.engines.Engine` on top: batches of initial states, and
compiled timing. Other engines (MuJoCo, learned models) return the same type.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import zipfile
from typing import Callable, ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from lgnn import physics, sharding
from lgnn.engines.timing import time_compiled
from lgnn.files import atomic_path, check_regular_input
from lgnn.metrics import ExplosionBounds
from lgnn.errors import ConfigError, SceneError, SimulationError
from lgnn.integrate import INTEGRATORS, Integrator, advance, rollout
from lgnn.runtime import in_float64, precision
from lgnn.scene import Scene, State, scene_to_dict
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
    # RK4 at 1e-4 keeps max node error over 1 s below 1e-6 on the chains and T1
    # (tests/test_integrate.py::test_default_settings_are_accurate, and the MuJoCo
    # cross-check); not on the self-stressed T2/T3, whose references do not converge
    # in dt (issue 13). The paper's Verlet needs ~1e-5 for that.
    integrator: str = "rk4"
    dt: float = 1e-4
    # The paper saves a frame every 1e-3 s.
    frame_dt: float = 1e-3
    duration: float = 1.0
    # Projection keeps link lengths to round-off (per-link blocks: linear in a chain's length).
    project: bool = True

    def __post_init__(self):
        if self.integrator not in INTEGRATORS:
            raise ConfigError(f"unknown integrator {self.integrator!r} (choose from {', '.join(INTEGRATORS)})")
        for name in ("dt", "frame_dt", "duration"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ConfigError(f"{name.replace('_', '-')} must be a positive number, got {value}")
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

    def integrator_for(self, accel: physics.AccelerationFn, project=None) -> Integrator:
        return INTEGRATORS[self.integrator](accel, self.dt, project if self.project else None)


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


def trajectory_problem(t: np.ndarray, q: np.ndarray, qd: np.ndarray, energy: np.ndarray, metadata) -> str | None:
    """What makes arrays and metadata read from a file not one trajectory (`Trajectory`'s
    shapes, real finite numbers within a scene's `MAX_MAGNITUDE`, a JSON object of metadata whose
    `scene`, `model` and `engine` are objects), or None."""
    if not isinstance(metadata, dict):
        return f"metadata must be a JSON object, got {type(metadata).__name__}"
    for key in ("scene", "model", "engine"):
        if key in metadata and not isinstance(metadata[key], dict):
            return f"metadata {key!r} must be an object, got {metadata[key]!r:.40}"
    for name, array in zip(NPZ_KEYS, (t, q, qd, energy)):
        if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
            return f"{name} must hold real numbers, got dtype {array.dtype}"
        # Frames after a divergence are never kept (the engines stop there).
        if not np.all(np.abs(array) <= MAX_MAGNITUDE):
            return f"{name} holds values that are not finite or beyond {MAX_MAGNITUDE:g}"
    if t.ndim != 1 or len(t) < 1:
        return f"t must be (frames,), got shape {t.shape}"
    if q.ndim != 3 or q.shape[0] != len(t) or qd.shape != q.shape:
        return f"q and qd must be (frames, nodes, dim) with {len(t)} frames, got {q.shape} and {qd.shape}"
    if energy.shape != t.shape:
        return f"energy must be (frames,) = {t.shape}, got {energy.shape}"
    return None


def check_state(scene: Scene, state: State) -> State:
    """Validate an initial state's shape and finiteness against the scene."""
    q, qd = (np.asarray(a, np.float64) for a in state)
    expected = (scene.n_nodes, scene.dim)
    for name, value in (("q", q), ("qd", qd)):
        if value.shape != expected:
            raise SceneError(f"initial state {name}: expected shape {expected}, got {value.shape}")
        if not np.all(np.isfinite(value)):
            raise SceneError(f"initial state {name}: contains non-finite values")
    return State(q, qd)


def rollout_fn(
    scene: Scene,
    config: SimulationConfig,
    accel_factory: Callable[[Scene], physics.AccelerationFn] = physics.true_acceleration_fn,
) -> Callable[[jax.Array, jax.Array], State]:
    """`run(q, qd) -> State` of the `config.n_frames + 1` frames from one initial state:
    the pure function behind `simulate`, for callers to `jit` and `vmap` over initial
    conditions (benchmarks, data generation)."""
    integrator = _integrator(scene, config, accel_factory)

    def run(q, qd):
        return rollout(integrator, State(q, qd), config.n_frames, config.steps_per_frame)

    return run


def params_rollout_fn(scene: Scene, config: SimulationConfig, accel_factory: Callable[..., physics.AccelerationFn]) -> Callable[..., State]:
    """`run(params, q, qd) -> State`: `rollout_fn` of a factory called as
    `accel_factory(scene, params)` (`learn.models.AccelerationFactory`), the parameters
    an argument, so one compiled function serves every parameter set of one shape (a
    model's training seeds, `vmap`ped over)."""
    project = physics.projection_fn(scene)

    def run(params, q, qd):
        return rollout(config.integrator_for(accel_factory(scene, params), project), State(q, qd), config.n_frames, config.steps_per_frame)

    return run


def _integrator(scene: Scene, config: SimulationConfig, accel_factory: Callable) -> Integrator:
    return config.integrator_for(accel_factory(scene), physics.projection_fn(scene))


@functools.lru_cache(maxsize=32)
def _chunk_runner(scene: Scene, config: SimulationConfig, accel_factory: Callable, with_params: bool):
    """Compiled `init(state, params) -> (carry, energy)` and `run(carry, params,
    n_frames) -> (carry, frames, energies)`, cached per scene content, settings and
    factory; `params` (None unless `with_params`) is an argument, not a constant."""
    project = physics.projection_fn(scene)
    fixed = None if with_params else config.integrator_for(accel_factory(scene), project)

    def integrator(params) -> Integrator:
        return config.integrator_for(accel_factory(scene, params), project) if with_params else fixed

    energy = jax.vmap(physics.energy_fn(scene))

    @jax.jit
    def init(state, params):
        carry = integrator(params).init_fn(state)
        return carry, energy(carry.state.q[None], carry.state.qd[None])

    @functools.partial(jax.jit, static_argnums=2)
    def run(carry, params, n_frames):
        carry, frames = advance(integrator(params), carry, n_frames, config.steps_per_frame)
        return carry, frames, energy(frames.q, frames.qd)

    return init, run


@in_float64  # the ground truth's accuracy, whatever jax_enable_x64 says
def simulate(
    scene: Scene,
    config: SimulationConfig = SimulationConfig(),
    state: State | None = None,
    *,
    accel_factory: Callable[..., physics.AccelerationFn] = physics.true_acceleration_fn,
    params=None,
    chunk_frames: int = 100,
    progress: bool = False,
    hint: str = "try a smaller dt",
) -> Trajectory:
    """Integrate from `state` (default: the scene's initial state) for `config.duration`.

    `accel_factory(scene) -> accel` selects the dynamics (ground truth by default; a
    learned model's factory gives its rollout). With `params`, the factory is called as
    `accel_factory(scene, params)` and the params are an argument of the compiled run:
    a factory equal for equal models (`learn.models.AccelerationFactory`) compiles once
    whatever the params. Raises `SimulationError` at the first non-finite or exploding
    frame (`ExplosionBounds`), naming its time (`err.time`) and carrying the frames
    before it (`err.trajectory`); `hint` ends its message. Computes in float64 whether
    or not `lgnn.configure()` was called (`lgnn.runtime.precision`).
    """
    state = check_state(scene, scene.initial_state if state is None else state)
    init, run = _chunk_runner(scene, config, accel_factory, params is not None)
    carry, initial_energy = init(State(jnp.asarray(state.q), jnp.asarray(state.qd)), params)
    qs, qds, energies = [np.asarray(state.q)[None]], [np.asarray(state.qd)[None]], [np.asarray(initial_energy)]
    bounds = ExplosionBounds.of(scene, state, float(initial_energy[0]))
    metadata = {"scene": scene_to_dict(scene), "config": dataclasses.asdict(config)}
    done = 0
    bar = _progress_bar(config.n_frames, scene.name, progress)
    try:
        while done < config.n_frames:
            count = min(chunk_frames, config.n_frames - done)
            carry, frames, chunk_energy = run(carry, params, count)
            q, qd, chunk_energy = np.asarray(frames.q), np.asarray(frames.qd), np.asarray(chunk_energy)
            t = (done + 1 + np.arange(count)) * config.frame_dt
            violation = bounds.first_violation(t, q, qd, chunk_energy)
            if violation is not None:
                k, reason = violation
                qs.append(q[:k])
                qds.append(qd[:k])
                energies.append(chunk_energy[:k])
                frames_before = sum(len(a) for a in qs)
                partial = Trajectory(np.arange(frames_before) * config.frame_dt, np.concatenate(qs), np.concatenate(qds), np.concatenate(energies), metadata)
                raise SimulationError(
                    f"{scene.name}: state {reason} at t = {t[k]:.6g} s ({config.integrator}, dt = {config.dt:g}); {hint}",
                    time=float(t[k]),
                    trajectory=partial,
                )
            qs.append(q)
            qds.append(qd)
            energies.append(chunk_energy)
            done += count
            bar.update(count)
    finally:
        bar.close()
    t = np.arange(config.n_frames + 1) * config.frame_dt
    return Trajectory(t, np.concatenate(qs), np.concatenate(qds), np.concatenate(energies), metadata)


def _progress_bar(total: int, label: str, enabled: bool):
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=label, unit="frame", disable=not enabled, leave=False)


@dataclasses.dataclass(frozen=True)
class LagrangianEngine:
    """The exact Lagrangian engine as an `lgnn.engines.Engine`.

    `rollout` runs `simulate` on each initial state (float64, in chunks, a progress
    bar per state if `progress`); `timed_rollout` times the batch as one compiled,
    `vmap`ped `rollout_fn` in `dtype`, spread over every local device."""

    name: ClassVar[str] = "lagrangian"
    dtype: str = "float64"
    progress: bool = False

    def rollout(self, scene: Scene, config: SimulationConfig, states: State) -> Trajectory:
        """`Trajectory` of initial states (B, N, D): q, qd (B, F+1, N, D), energy (B, F+1)."""
        runs = [simulate(scene, config, State(q, qd), progress=self.progress) for q, qd in zip(states.q, states.qd)]
        q, qd, energy = (np.stack([getattr(run, field) for run in runs]) for field in ("q", "qd", "energy"))
        return Trajectory(runs[0].t, q, qd, energy, runs[0].metadata)

    def timed_rollout(self, scene: Scene, config: SimulationConfig, states: State) -> tuple[float, float, np.ndarray]:
        """`(compile_s, run_s, q (B, F+1, N, D))` of the compiled batch (`time_compiled`)."""
        with precision(self.dtype):
            return self._timed_rollout(scene, config, states)

    def _timed_rollout(self, scene: Scene, config: SimulationConfig, states: State) -> tuple[float, float, np.ndarray]:
        batch = len(states.q)
        factory = physics.vectorised_true_acceleration_fn if batch > 1 else physics.true_acceleration_fn
        rollouts = jax.vmap(rollout_fn(scene, config, factory))
        # A batch is spread over every local device (`sharding`; on one device this is plain `jit`).
        run = sharding.batch_jit(rollouts) if batch % sharding.device_count() == 0 else jax.jit(rollouts)
        compile_s, run_s, (q, _) = time_compiled(run, jnp.asarray(states.q, self.dtype), jnp.asarray(states.qd, self.dtype))
        return compile_s, run_s, np.asarray(q, np.float64)
