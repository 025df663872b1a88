"""MuJoCo Warp: MuJoCo's Warp engine on the scene's MuJoCo model, many worlds at once.

An optional extra (`pip install 'lgnn[mjwarp]'`: `mujoco-warp`, `warp-lang`); without
it, using this engine is a one-line `ConfigError`. Warp runs on a CUDA GPU, or on its
CPU backend where there is none (slow: ~200 s of kernel compilation on a 2-core CPU
the first time, cached on disk by Warp afterwards), so a machine without a GPU can
still check it.

- `Runner` holds the device model and a `Data` of B worlds for one (scene, config,
  batch, form); `runner(...)` builds it once per process (`lru_cache`).
- `Runner.run(q0, qd0)`: node states (B, N, dim) -> MuJoCo `(qpos, qvel)` by MuJoCo C's
  state map (`lgnn.engines.mujoco.state_to_qpos_qvel`), then `config.n_frames` frames
  of `steps_per_frame` `mjw.step`s (captured as one CUDA graph per frame on a GPU),
  the state of every frame kept on the device. `Runner.nodes(...)` maps them back
  with MuJoCo Warp's own kinematics: node positions are site positions, velocities
  the site velocities from each body's spatial velocity (`cvel`, about its tree's
  centre of mass, as `mj_objectVelocity`), so any MJCF form maps the same way.
- `MjwarpEngine` is the `lgnn.engines.Engine` on top.

Precision: MuJoCo Warp computes in float32 only (`dtype` is always "float32"); the
maps around it are float64. Solver settings are the MJCF's (Newton, equality rows
only) except the Jacobian: MuJoCo Warp refuses a dense one beyond 60 degrees of
freedom, so it gets MuJoCo's automatic choice (sparse from 60 on). Drag scenes are
refused: their force needs the state at every step, which MuJoCo C and MJX compute
outside the step (`xfrc_applied`) and this engine does not.

`form` is the MJCF form (`lgnn.engines.mjcf`): "nested" (joint coordinates, the
default), "maximal", or "auto", MJX's choice (`lgnn.engines.mjx.best_form`), so that
the two engines run a scene in the same form. In the maximal form MuJoCo Warp takes
the substeps MJX takes (`lgnn.engines.mujoco.stepped_config`: the error model's where
it holds, else those measured on the scene).
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import time
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from lgnn.engines.base import Engine, SimulationConfig, Trajectory
from lgnn.engines.mjcf import MAXIMAL_TOLERANCE, Form
from lgnn.engines.mjx import best_form
from lgnn.engines.mujoco import checked_trajectory, compile_scene, engine_metadata, resolve_form, state_to_qpos_qvel, stepped_config
from lgnn.engines.timing import time_runs
from lgnn.errors import ConfigError
from lgnn.scene import Scene, State

INSTALL_HINT = "pip install 'lgnn[mjwarp]' (mujoco-warp, warp-lang)"
# The MJCF form when none is given: the one `mjcf/` holds.
DEFAULT_FORM = "nested"


def _modules():
    """`(warp, mujoco_warp, mujoco)`, imported on first use; `ConfigError` when absent."""
    try:
        import mujoco
        import mujoco_warp
        import warp
    except ImportError as err:
        raise ConfigError(f"the mjwarp engine needs MuJoCo Warp, which is not installed ({err.name} missing): {INSTALL_HINT}") from None
    # Warp logs a line per compiled kernel module otherwise (dozens on a first run).
    warp.config.log_level = warp.LOG_WARNING
    return warp, mujoco_warp, mujoco


def available() -> bool:
    """Whether MuJoCo Warp can be imported (tests and the GPU measurement skip it otherwise)."""
    try:
        _modules()
    except ConfigError:
        return False
    return True


def versions() -> str:
    """`mujoco-warp X, warp-lang Y` of the installed packages."""
    warp, mujoco_warp, _ = _modules()
    return f"mujoco-warp {mujoco_warp.__version__}, warp-lang {warp.__version__}"


@dataclasses.dataclass(eq=False)
class Runner:
    """MuJoCo Warp's model and B worlds of one scene (module docstring). Mutable: its
    `data` holds the worlds' state between calls."""

    compiled: object
    config: SimulationConfig
    batch: int
    device: str
    model: object
    data: object
    qpos_frames: object  # (F+1, B, nq) on the device
    qvel_frames: object
    graph: object = None  # one frame of steps, captured on a CUDA device
    compile_s: float = float("nan")

    def _frame(self) -> None:
        _, mjw, _ = _modules()
        for _ in range(self.config.steps_per_frame):
            mjw.step(self.model, self.data)

    def prepare(self) -> float:
        """Compile the step's kernels (and capture a frame's CUDA graph): seconds taken,
        once per runner. Leaves the worlds' state to be reset by `run`."""
        if self.graph is None and np.isnan(self.compile_s):
            wp, mjw, _ = _modules()
            start = time.perf_counter()
            with wp.ScopedDevice(self.device):
                if wp.get_device(self.device).is_cuda:
                    mjw.step(self.model, self.data)  # loads the modules before the capture
                    with wp.ScopedCapture() as capture:
                        self._frame()
                    self.graph = capture.graph
                else:
                    mjw.step(self.model, self.data)
                wp.synchronize_device(self.device)
            self.compile_s = time.perf_counter() - start
        return self.compile_s

    def run(self, qpos: np.ndarray, qvel: np.ndarray) -> None:
        """Step the B worlds from `qpos` (B, nq), `qvel` (B, nv) through every frame,
        keeping each frame's state on the device; returns when the device is done."""
        wp, mjw, _ = _modules()
        self.prepare()
        with wp.ScopedDevice(self.device):
            mjw.reset_data(self.model, self.data)
            wp.copy(self.data.qpos, wp.array(np.asarray(qpos, np.float32), dtype=wp.float32))
            wp.copy(self.data.qvel, wp.array(np.asarray(qvel, np.float32), dtype=wp.float32))
            wp.copy(self.qpos_frames[0], self.data.qpos)
            wp.copy(self.qvel_frames[0], self.data.qvel)
            for f in range(1, self.config.n_frames + 1):
                if self.graph is not None:
                    wp.capture_launch(self.graph)
                else:
                    self._frame()
                wp.copy(self.qpos_frames[f], self.data.qpos)
                wp.copy(self.qvel_frames[f], self.data.qvel)
            wp.synchronize_device(self.device)

    def nodes(self, frames=None) -> State:
        """Node states (B, len(frames), N, dim) (float64) of the last `run`'s `frames`
        (default: all), by MuJoCo Warp's kinematics (module docstring)."""
        wp, mjw, _ = _modules()
        frames = range(self.config.n_frames + 1) if frames is None else frames
        c, m, d = self.compiled, self.model, self.data
        root = c.model.body_rootid[c.model.site_bodyid[c.node_site]]
        body = c.model.site_bodyid[c.node_site]
        qs, qds = [], []
        with wp.ScopedDevice(self.device):
            for f in frames:
                wp.copy(d.qpos, self.qpos_frames[f])
                wp.copy(d.qvel, self.qvel_frames[f])
                mjw.fwd_kinematics(m, d)
                mjw.fwd_velocity(m, d)  # cvel
                x = d.site_xpos.numpy()[:, c.node_site].astype(np.float64)
                cvel = d.cvel.numpy()[:, body].astype(np.float64)
                centre = d.subtree_com.numpy()[:, root].astype(np.float64)
                v = cvel[..., 3:] + np.cross(cvel[..., :3], x - centre)
                qs.append(x[..., : c.scene.dim])
                qds.append(v[..., : c.scene.dim])
        return State(np.stack(qs, 1), np.stack(qds, 1))


@functools.lru_cache(maxsize=8)
def runner(scene: Scene, config: SimulationConfig, batch: int, form: Form = DEFAULT_FORM, device: str | None = None) -> Runner:
    """The `Runner` of `batch` worlds stepping at `config.dt` (cached on the scene's
    content, settings, batch, form and device; default device: Warp's preferred, a GPU
    when there is one)."""
    wp, mjw, mujoco = _modules()
    if scene.drag:
        raise ConfigError(f"{scene.name}: the mjwarp engine does not model drag (use mujoco or mjx)")
    compiled = compile_scene(scene, config.dt, form)
    model = copy.copy(compiled.model)  # the compiled model is shared (cached): change a copy
    model.opt.jacobian = mujoco.mjtJacobian.mjJAC_AUTO
    device = str(wp.get_device(device))
    with wp.ScopedDevice(device):
        try:
            m = mjw.put_model(model)
            # MuJoCo Warp allocates a fixed number of constraint rows per world (njmax),
            # by default too few for the maximal form's `connect` equalities (3 rows
            # each: T1 overflowed 64). Scenes have no contacts, so MuJoCo C's count at
            # the initial state is the count at every step.
            probe = mujoco.MjData(model)
            mujoco.mj_forward(model, probe)
            d = mjw.make_data(model, nworld=batch, njmax=max(int(probe.nefc), 1))
        except (ValueError, NotImplementedError) as err:
            raise ConfigError(f"{scene.name}: MuJoCo Warp rejected the model: {str(err).splitlines()[0]}") from None
        frames = config.n_frames + 1
        qpos_frames = wp.zeros((frames, batch, model.nq), dtype=wp.float32)
        qvel_frames = wp.zeros((frames, batch, model.nv), dtype=wp.float32)
    return Runner(compiled, config, batch, device, m, d, qpos_frames, qvel_frames)


@functools.lru_cache(maxsize=16)
def _to_mj_fn(compiled):
    # Cached: a fresh jit per call would recompile on every rollout.
    return jax.jit(jax.vmap(lambda q, qd: state_to_qpos_qvel(compiled, q, qd)))


def initial_qpos_qvel(compiled, states: State) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo states (B, nq), (B, nv) of node states (B, N, dim), mapped in float64."""
    qpos, qvel = _to_mj_fn(compiled)(jnp.asarray(states.q, jnp.float64), jnp.asarray(states.qd, jnp.float64))
    return np.asarray(qpos, np.float64), np.asarray(qvel, np.float64)


def rollout(scene: Scene, config: SimulationConfig, states: State, form: Form = DEFAULT_FORM, device: str | None = None) -> State:
    """Node trajectories (B, F+1, N, dim) (float64 of MuJoCo Warp's float32) from initial
    node states (B, N, dim). Non-finite states are returned as they are."""
    run = runner(scene, config, len(states.q), form, device)
    run.run(*initial_qpos_qvel(run.compiled, states))
    return run.nodes()


@dataclasses.dataclass(frozen=True)
class MjwarpEngine(Engine):
    """MuJoCo Warp as an `lgnn.engines.Engine`: float32 always (MuJoCo Warp has no
    other precision), on the MJCF `form` ("auto": MJX's `best_form`), on Warp's
    `device` (default: its preferred); the maximal form meets `tolerance` as MJX's does."""

    name: ClassVar[str] = "mjwarp"
    dtype: ClassVar[str] = "float32"
    form: str = DEFAULT_FORM
    device: str | None = None
    tolerance: float = MAXIMAL_TOLERANCE

    def form_of(self, scene: Scene) -> Form:
        """The MJCF form this engine runs `scene` in."""
        return resolve_form(scene, self.form, best_form)

    def stepped(self, scene: Scene, config: SimulationConfig) -> tuple[Form, SimulationConfig]:
        """The form this engine runs `scene` in and the settings MuJoCo Warp steps at."""
        form = self.form_of(scene)
        return form, stepped_config(scene, config, form, self.tolerance)

    def accuracy(self, scene: Scene, config: SimulationConfig) -> float | None:
        """None: not stated. The form's error model (`mjcf.form_error`) holds in float64,
        and MuJoCo Warp's float32 round-off is not modelled (measured: 7.6e-7 on chain4
        after 100 steps, `tests/test_mjwarp.py`)."""
        return None

    def rollout(self, scene: Scene, config: SimulationConfig, states: State) -> Trajectory:
        """`Trajectory` of initial states (B, N, dim): q, qd (B, F+1, N, dim), energy (B, F+1)
        (lgnn's exact energy of the node states); stopped at the first non-finite or
        exploding frame like every engine."""
        form, stepped = self.stepped(scene, config)
        start = time.perf_counter()
        nodes = rollout(scene, stepped, states, form, self.device)
        metadata = engine_metadata(scene, config, self.name, self.dtype, time.perf_counter() - start, form, step=stepped.dt)
        metadata["engine"].update(mujoco_warp=versions())
        return checked_trajectory(scene, config, nodes, metadata, self.name)  # frames before a divergence kept

    def timed_rollout(self, scene: Scene, config: SimulationConfig, states: State) -> tuple[float, float, np.ndarray]:
        """`(compile_s, run_s, q (B, F+1, N, dim))`: compile is the kernels' compilation
        (and graph capture) when the runner was built (as `lgnn.engines.rollouts` reports a
        cached compile); run is the stepping alone, after one untimed run
        (`lgnn.engines.timing.time_runs`); `q` may be non-finite."""
        form, stepped = self.stepped(scene, config)
        run = runner(scene, stepped, len(states.q), form, self.device)
        compile_s = run.prepare()
        qpos, qvel = initial_qpos_qvel(run.compiled, states)
        (run_s,), _ = time_runs(lambda: run.run(qpos, qvel))
        return compile_s, run_s, run.nodes().q

    def timed_batch(self, scene: Scene, config: SimulationConfig, states: State, repeats: int = 1) -> tuple[float, list[float], np.ndarray]:
        """`(compile_s, run_s, q (B, N, dim))`: compile as `timed_rollout`'s, then
        `repeats` timed runs after an untimed one (`time_runs`), and the final positions
        (may be non-finite). It steps at `config.dt` in either form, as `lgnn
        gpu-truth`'s tables were measured (`rollout` and `timed_rollout` substep the
        maximal form)."""
        run = runner(scene, config, len(states.q), self.form_of(scene), self.device)
        compile_s = run.prepare()
        qpos, qvel = initial_qpos_qvel(run.compiled, states)
        run_s, _ = time_runs(lambda: run.run(qpos, qvel), repeats)
        return compile_s, run_s, run.nodes(frames=[config.n_frames]).q[:, 0]
