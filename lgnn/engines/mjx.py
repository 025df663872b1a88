"""MJX: MuJoCo's JAX engine on the scene's MuJoCo model (`lgnn.engines.mujoco`).

`runner(scene, config, dtype)` is the compiled, `vmap`ped rollout from initial node
states (B, N, dim) to node trajectories (B, F+1, N, dim): node states map to MJX's
`(qpos, qvel)` with MuJoCo C's state map, and back through MJX's kinematics (site
positions, and their velocities as a `jvp` along `qpos_rate`). Drag is applied as in MuJoCo C
(`xfrc_applied` at link centres, held over a step). `MjxEngine` is the
`lgnn.engines.Engine` on top. MJX compiles slowly on CPU in the nested form (~35 s for
chain4, over 10 minutes for 12 links), far less in the maximal form (12 links: ~30 s
of CPU time; MJX has no tree depth there), so the engine runs the nested form to
`NESTED_MAX_DEPTH` and the maximal form beyond (`best_form`), says so before
compiling (`log`), and `runner` is cached.

Spatial scenes run the same way (ball and free joints; `qpos_rate` turns qvel into
the quaternions' rates for the velocity `jvp`). Measured on chain4-3d, float64, 0.05 s
at dt 1e-4 (2-core CPU under load): nested compiles in ~50 s wall and departs from
MuJoCo C and the Lagrangian engine alike by 3e-9 (MJX steps ball joints a little
differently: 3e-12 after 1 ms on chain2-3d, growing about linearly; hinges agree to
round-off); maximal compiles in ~37 s and departs by 3e-7 (MJX's `connect`, as in 2D;
MuJoCo C's maximal form: 1e-9).

`dtype` float32 runs with JAX's x64 off, float64 with it on (`lgnn.runtime.precision`,
entered here whatever the global setting).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import io
import time
from typing import Callable, ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from lgnn.engines.lagrangian import DTYPES, SimulationConfig, Trajectory
from lgnn.engines.mjcf import Form, scene_layout
from lgnn.engines.mujoco import check_rk4, checked_trajectory, compile_scene, engine_metadata, qpos_rate, resolve_form, state_to_qpos_qvel
from lgnn.engines.timing import time_compiled
from lgnn.errors import ConfigError, SimulationError
from lgnn.runtime import precision
from lgnn.scene import Scene, State


# Deepest tree MJX runs in the nested form by default: its compile time grows steeply
# with depth (2-core CPU: ~35 s for chain4, minutes beyond 12 links, 459 s for the
# kinematics alone of 100), the maximal form's barely (measured, module docstring).
NESTED_MAX_DEPTH = 8


@functools.lru_cache(maxsize=16)
def runner(scene: Scene, config: SimulationConfig, dtype: str = "float64", form: Form = "nested"):
    """Compiled-on-first-call `run(q0, qd0) -> (q, qd)`: MJX trajectories of the
    scene's MJCF in `form`, `vmap`ped over initial node states (B, N, dim) -> (B, F+1,
    N, dim). Cached on the scene's content, config, dtype and form, so compilation (slow on
    CPU) happens once per process.
    Call it inside `lgnn.runtime.precision(dtype)`."""
    with contextlib.redirect_stdout(io.StringIO()):
        # MJX prints "Failed to import mujoco_warp: ..." on import without the optional
        # `warp` package, which lgnn does not use.
        from mujoco import mjx

    check_rk4(config)
    if dtype not in DTYPES:
        raise ConfigError(f"MJX dtype must be one of {', '.join(DTYPES)}, got {dtype!r}")
    if dtype == "float64" and not jax.config.jax_enable_x64:
        raise ConfigError("MJX float64 needs jax_enable_x64 (the CLI and tests enable it)")
    compiled = compile_scene(scene, config.dt, form)
    if dtype == "float32":
        # Traced under `precision` (x64 off), the index arrays would be converted to
        # int32 once, and JAX reuses that conversion for the same NumPy objects in later
        # float64 traces (MuJoCo C's state map then failed with int32 + int64): give
        # this runner its own copies.
        compiled = dataclasses.replace(compiled, **{f.name: getattr(compiled, f.name).copy() for f in dataclasses.fields(compiled)
                                                    if isinstance(getattr(compiled, f.name), np.ndarray)})
    dt_ = jnp.dtype(dtype)

    def cast(tree):
        return jax.tree.map(lambda x: x.astype(dt_) if isinstance(x, jax.Array) and jnp.issubdtype(x.dtype, jnp.floating) else x, tree)

    mx = cast(mjx.put_model(compiled.model))
    d0 = cast(mjx.make_data(mx))
    sites = jnp.asarray(compiled.node_site)
    bodies = jnp.asarray(compiled.body_id)
    drag = float(scene.drag)

    def positions(qpos, which):
        d = mjx.kinematics(mx, d0.replace(qpos=qpos))
        return d.site_xpos[sites, : scene.dim] if which == "sites" else d.xipos[bodies]

    def velocities(qpos, qvel, which):
        # Positions and their velocities: a jvp along qpos's rate (qvel itself for
        # hinges and slides; quaternions turn at 1/2 quat * omega).
        return jax.jvp(lambda p: positions(p, which), (qpos,), (qpos_rate(compiled, qpos, qvel),))

    def to_nodes(qpos, qvel):
        return velocities(qpos, qvel, "sites")

    def step(d):
        if drag:
            _, v_cm = velocities(d.qpos, d.qvel, "com")
            d = d.replace(xfrc_applied=d.xfrc_applied.at[bodies, :3].set(-drag * v_cm))
        return mjx.step(mx, d)

    def one(q0, qd0):
        qpos, qvel = state_to_qpos_qvel(compiled, q0.astype(dt_), qd0.astype(dt_))
        d = d0.replace(qpos=qpos, qvel=qvel)

        def frame(d, _):
            d = jax.lax.fori_loop(0, config.steps_per_frame, lambda _, d: step(d), d)
            return d, to_nodes(d.qpos, d.qvel)

        _, (q, qd) = jax.lax.scan(frame, d, None, length=config.n_frames)
        q_first, qd_first = to_nodes(qpos, qvel)
        return jnp.concatenate([q_first[None], q]), jnp.concatenate([qd_first[None], qd])

    return jax.jit(jax.vmap(one))


def rollout(scene: Scene, config: SimulationConfig, states: State, dtype: str = "float64", form: Form = "nested") -> State:
    """MJX node trajectories (B, F+1, N, dim) from initial node states (B, N, dim), on the
    scene's MJCF in `form`."""
    # float32 needs x64 off: MJX builds float64 constants under x64 (its RK4 tableau,
    # for one) that would promote the float32 state and break its scans.
    with precision(dtype):
        run = runner(scene, config, dtype, form)
        q, qd = run(jnp.asarray(states.q, dtype), jnp.asarray(states.qd, dtype))
    q, qd = np.asarray(q, np.float64), np.asarray(qd, np.float64)
    if not (np.isfinite(q).all() and np.isfinite(qd).all()):
        raise SimulationError(f"{scene.name}: MJX state became non-finite (dt = {config.dt:g}, {dtype}); try a smaller dt")
    return State(q, qd)


def best_form(scene: Scene) -> Form:
    """MJX's form of `scene`: nested (exact joints) up to `NESTED_MAX_DEPTH`, else
    maximal (compile time nearly flat in the number of links)."""
    return "nested" if scene_layout(scene).depth <= NESTED_MAX_DEPTH else "maximal"


@dataclasses.dataclass(frozen=True)
class MjxEngine:
    """MJX as an `lgnn.engines.Engine`, computing in `dtype`, on the MJCF `form`
    ("auto": `best_form`); `log` (e.g. `print`) is told before a compile starts."""

    name: ClassVar[str] = "mjx"
    dtype: str = "float64"
    form: str = "auto"
    log: Callable[[str], None] | None = None

    def form_of(self, scene: Scene) -> Form:
        """The MJCF form this engine runs `scene` in."""
        return resolve_form(scene, self.form, best_form)

    def _announced_form(self, scene: Scene, config: SimulationConfig) -> Form:
        # The form, told to `log` first when this process has no runner for it yet.
        form = self.form_of(scene)
        if self.log is not None and not _has_runner(scene, config, self.dtype, form):
            nv = compile_scene(scene, config.dt, form).model.nv
            self.log(f"MJX: compiling {scene.name} ({form} form, {nv} degrees of freedom, {self.dtype}, "
                     f"{jax.default_backend()}); on a CPU this can take minutes")
        return form

    def rollout(self, scene: Scene, config: SimulationConfig, states: State) -> Trajectory:
        """`Trajectory` of initial states (B, N, dim): q, qd (B, F+1, N, dim), energy (B, F+1)
        (lgnn's exact energy in float64 of the node states; MJX has none)."""
        form = self._announced_form(scene, config)
        start = time.perf_counter()
        nodes = rollout(scene, config, states, self.dtype, form)
        metadata = engine_metadata(scene, config, self.name, self.dtype, time.perf_counter() - start, form)
        return checked_trajectory(scene, config, nodes, metadata, self.name)

    def timed_rollout(self, scene: Scene, config: SimulationConfig, states: State) -> tuple[float, float, np.ndarray]:
        """`(compile_s, run_s, q (B, F+1, N, dim))` of the compiled runner (`time_compiled`)."""
        form = self._announced_form(scene, config)
        with precision(self.dtype):
            run = runner(scene, config, self.dtype, form)
            compile_s, run_s, (q, _) = time_compiled(run, jnp.asarray(states.q, self.dtype), jnp.asarray(states.qd, self.dtype))
        return compile_s, run_s, np.asarray(q, np.float64)


def _has_runner(scene: Scene, config: SimulationConfig, dtype: str, form: Form) -> bool:
    # Whether `runner` holds this one already (then nothing compiles): lru_cache keys
    # on the call's arguments, so a probe call that is not a hit would build it.
    hits = runner.cache_info().hits
    with precision(dtype):
        runner(scene, config, dtype, form)
    return runner.cache_info().hits > hits
