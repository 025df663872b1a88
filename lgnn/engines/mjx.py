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

In the maximal form the engine steps at `dt / mjcf.maximal_substeps(...)` (the fewest
MuJoCo steps per `dt` whose soft joints meet its `tolerance`, 1e-6 over 1 s by
default, where the error model holds: open chains of alike links), elsewhere at the
substeps MuJoCo C runs of the scene measure (`mujoco.measured_maximal_substeps`), and
`MjxEngine.accuracy(scene, config)` states the expected error at the step taken
(`mujoco.stated_accuracy`).

Spatial scenes run the same way (ball and free joints; `qpos_rate` turns qvel into
the quaternions' rates for the velocity `jvp`).

Steps are not MJX's `mjx.step` but `make_step`: MuJoCo C 4.0's RK4 (with its
Runge-Kutta-Munthe-Kaas correction for ball and free joints) and its connect rows
(with the `Jdot v` term in their reference acceleration) on MJX's own stages, which
mujoco-mjx 3.17 lacks (section "MuJoCo C's step on MJX's stages" below). With
`mjx.step`, chain4-3d departed from MuJoCo C by 3e-8 over 0.5 s and the maximal
loops by 1e-6 .. 2e-4 over 0.1 s; with `make_step` both agree with MuJoCo C to
round-off per step (`tools/mjx_vs_c.py`).

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
import mujoco
import numpy as np

from lgnn.engines.base import DTYPES, Engine, SimulationConfig, Trajectory
from lgnn.engines.mjcf import MAXIMAL_TOLERANCE, Form, error_model_holds, nested_only, scene_layout
from lgnn.engines.mujoco import (checked_trajectory, compile_scene, engine_metadata, qpos_rate, quat_mul, resolve_form,
                                 stated_accuracy, state_to_qpos_qvel, stepped_config)
from lgnn.engines.timing import compile_timed, time_compiled, time_runs
from lgnn.errors import ConfigError
from lgnn.runtime import precision
from lgnn.scene import Scene, State


# Deepest tree MJX runs in the nested form by default: its compile time grows steeply
# with depth (2-core CPU: ~35 s for chain4, minutes beyond 12 links, 459 s for the
# kinematics alone of 100), the maximal form's barely (measured, module docstring).
NESTED_MAX_DEPTH = 8


# ------------------------------------------------- MuJoCo C's step on MJX's stages
# MJX's forward dynamics and RK4 step, brought up to MuJoCo C's (4.0) arithmetic.
#
# mujoco-mjx 3.17 (its JAX implementation) departs from MuJoCo C 4.0 in two places that
# matter to lgnn's models (measured, `tools/mjx_vs_c.py`):
#
# 1. RK4 for ball and free joints. MuJoCo C (since 4.0, commit 9a7f240f0, changelog
#    "fourth-order accurate for the orientations") maps each RK stage's angular
#    velocity to the rate of the stage's rotation vector (the Runge-Kutta-Munthe-Kaas
#    correction, `dexp^-1`: `w + 1/2 r x w + c(|r|) r x (r x w)`, `c` the Bortz
#    coefficient) before combining the stages; MJX's `rungekutta4` sums the raw angular
#    velocities (second order in the orientation). On chain4-3d (dt 1e-4) that is
#    7e-13 in qpos per step, 3e-8 over 0.5 s.
# 2. Connect and weld equality rows. MuJoCo C (since 3.7.0, commit 412cee20) adds the
#    centripetal term `Jdot v` to their reference acceleration
#    (`aref = -b J v - k r - Jdot v`); MJX's `make_constraint` does not, so a `connect`
#    on a turning body is pulled towards a different trajectory (a maximal four-bar
#    started with velocities 0.3 x N(0, 1): 1e-6 in qvel after one step).
#
# `forward(m, d)` is MJX's `forward` (no sensors: lgnn's models have none) with
# `-Jdot v` added to the equality rows' `efc_aref` before the solve (`Jdot v` as a
# `jvp` of `efc_J v` along the rate of `qpos`), and `rk4(m, d)` is MuJoCo C's RK4 with
# the RKMK correction on `forward`. Both are built from MJX's public stages
# (`fwd_position` .. `solve`); `make_step(model)` returns `step(mx, d)` for an
# `MjModel` whose equalities are connects and welds (the only ones MuJoCo C adds the
# term to). With both, MJX matches MuJoCo C to round-off over one step.

@functools.cache
def _mjx():
    # `mujoco.mjx`, imported on first use: it prints "Failed to import mujoco_warp: ..."
    # without the optional `warp` package, which lgnn does not use.
    # A broken install (MJX's own dependencies missing) is one line naming what is
    # missing, and `lgnn gpu-truth` makes it a row's note, not a traceback.
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            from mujoco import mjx
    except ImportError as err:
        raise ConfigError(f"the mjx engine cannot import MuJoCo MJX ({err.name or err} missing): pip install 'mujoco-mjx' and its "
                          "dependencies") from None
    return mjx


# MuJoCo's classic RK4 tableau: stage i (1..3) is evaluated at h * A[i-1] along the
# previous stage's rate; B weights the four stages.
RK4_A = (0.5, 0.5, 1.0)
RK4_B = (1.0 / 6.0, 1.0 / 3.0, 1.0 / 3.0, 1.0 / 6.0)
# Below this squared angle the Bortz coefficient is its Taylor series (the closed form
# cancels); its next term, 2.1e-8 x^8, is below 1e-19 there.
BORTZ_SERIES_MAX = 0.25


class JointMaps:
    """Static index arrays of an `MjModel`'s joints: `lin_q`, `lin_v` the qpos / qvel
    numbers integrated linearly (hinges, slides, free positions); `quat_q` (K, 4) the
    quaternions (ball and free joints), `rot_v` (K, 3) their angular velocities (in
    the body's frame)."""

    def __init__(self, model: mujoco.MjModel):
        lin_q, lin_v, quat_q, rot_v = [], [], [], []
        for j in range(model.njnt):
            kind, q, v = model.jnt_type[j], int(model.jnt_qposadr[j]), int(model.jnt_dofadr[j])
            if kind == mujoco.mjtJoint.mjJNT_FREE:
                lin_q += range(q, q + 3)
                lin_v += range(v, v + 3)
                quat_q.append(range(q + 3, q + 7))
                rot_v.append(range(v + 3, v + 6))
            elif kind == mujoco.mjtJoint.mjJNT_BALL:
                quat_q.append(range(q, q + 4))
                rot_v.append(range(v, v + 3))
            else:
                lin_q.append(q)
                lin_v.append(v)
        self.lin_q, self.lin_v = np.array(lin_q, np.int64), np.array(lin_v, np.int64)
        self.quat_q = np.array(quat_q, np.int64).reshape(-1, 4)
        self.rot_v = np.array(rot_v, np.int64).reshape(-1, 3)


def integrate_pos(maps: JointMaps, qpos, qvel, h):
    """`qpos` advanced by `qvel` over time `h` (MuJoCo's `mj_integratePos`): linear
    coordinates by `h qvel`, quaternions (normalized first) rotated by the body-frame
    angle `h |omega|` about `omega`."""
    out = qpos.at[maps.lin_q].add(h * qvel[maps.lin_v])
    if not len(maps.quat_q):
        return out
    quat, omega = qpos[maps.quat_q], qvel[maps.rot_v]
    quat = quat / jnp.linalg.norm(quat, axis=-1, keepdims=True)
    norm = jnp.linalg.norm(omega, axis=-1, keepdims=True)
    axis = omega / jnp.where(norm > 0, norm, 1)
    half = 0.5 * h * norm
    rotation = jnp.concatenate([jnp.cos(half), jnp.sin(half) * axis], -1)
    return out.at[maps.quat_q].set(quat_mul(quat, rotation))


def joint_qpos_rate(maps: JointMaps, qpos, qvel):
    """d qpos / dt at `qvel`: `qvel` for linear coordinates, `1/2 quat * (0, omega)`
    for quaternions (the tangent a `jvp` in qpos takes)."""
    rate = jnp.zeros_like(qpos).at[maps.lin_q].set(qvel[maps.lin_v])
    if not len(maps.quat_q):
        return rate
    omega = qvel[maps.rot_v]
    pure = jnp.concatenate([jnp.zeros_like(omega[:, :1]), omega], -1)
    return rate.at[maps.quat_q].set(0.5 * quat_mul(qpos[maps.quat_q], pure))


def _bortz(xx):
    # c(x) = (1 - (x/2) cot(x/2)) / x^2 at x^2 = xx: Taylor series near 0, else closed.
    series = 1 / 12 + xx * (1 / 720 + xx * (1 / 30240 + xx / 1209600))
    safe = jnp.where(xx < BORTZ_SERIES_MAX, 1.0, xx)
    x = jnp.sqrt(safe)
    return jnp.where(xx < BORTZ_SERIES_MAX, series, (1 - 0.5 * x / jnp.tan(0.5 * x)) / safe)


def rkmk_velocity(maps: JointMaps, rotation, qvel):
    """`qvel` with each angular velocity `w` replaced by the rate of the rotation
    vector `r` (`rotation`, rows of `maps.rot_v`) of a body at `quat0 * exp(r)`:
    `w + 1/2 r x w + c(|r|) r x (r x w)` (`dexp^-1`), `r` first reduced to an angle
    in (-pi, pi]."""
    if not len(maps.rot_v):
        return qvel
    r, w = rotation[maps.rot_v], qvel[maps.rot_v]
    xx = jnp.sum(r * r, -1, keepdims=True)
    x = jnp.sqrt(jnp.where(xx > np.pi**2, xx, 1.0))
    r = jnp.where(xx > np.pi**2, r * (x - 2 * np.pi * jnp.floor(x / (2 * np.pi) + 0.5)) / x, r)
    xx = jnp.sum(r * r, -1, keepdims=True)
    rxw = jnp.cross(r, w)
    return qvel.at[maps.rot_v].set(w + 0.5 * rxw + _bortz(xx) * jnp.cross(r, rxw))


def check_equalities(model: mujoco.MjModel) -> None:
    """`ConfigError` unless every equality is a connect or a weld (the rows MuJoCo C
    adds `Jdot v` to; `forward` adds it to every equality row)."""
    kinds = {mujoco.mjtEq.mjEQ_CONNECT, mujoco.mjtEq.mjEQ_WELD}
    other = sorted({mujoco.mjtEq(int(t)).name for t in model.eq_type} - {k.name for k in kinds})
    if other:
        raise ConfigError(f"lgnn's MJX step adds MuJoCo C's Jdot v to connect and weld equalities only, the model has {', '.join(other)}")


def forward(mx, maps: JointMaps, d):
    """MJX's `forward` without sensors, with MuJoCo C's `-Jdot v` in the equality rows'
    reference acceleration."""
    mjx = _mjx()
    d = mjx.fwd_position(mx, d)
    d = mjx.fwd_velocity(mx, d)
    d = mjx.fwd_actuation(mx, d)
    d = mjx.fwd_acceleration(mx, d)
    if d._impl.efc_J.shape[0] == 0:
        return d.replace(qacc=d.qacc_smooth)

    def jacobian_times_qvel(qpos):
        dq = mjx.com_pos(mx, mjx.kinematics(mx, d.replace(qpos=qpos)))
        return mjx.make_constraint(mx, dq)._impl.efc_J @ d.qvel

    _, jdot_v = jax.jvp(jacobian_times_qvel, (d.qpos,), (joint_qpos_rate(maps, d.qpos, d.qvel),))
    equality = d._impl.efc_type == int(mujoco.mjtConstraint.mjCNSTR_EQUALITY)
    d = d.tree_replace({"_impl.efc_aref": d._impl.efc_aref - jnp.where(equality, jdot_v, 0)})
    return mjx.solve(mx, d)


def rk4(mx, maps: JointMaps, d):
    """One step of MuJoCo C's RK4 (`mj_RungeKutta`, 4.0): stages at `q0 (+) h A v`,
    `v0 + h A a` of the previous stage's (corrected) velocity `v` and acceleration
    `a`; each stage's angular velocities mapped by `rkmk_velocity` to rotation-vector
    rates; the step `q0 (+) h sum B v`, `v0 + h sum B a`. `d` is forwarded first (as
    MJX's `step` does); the returned `qacc` is the stages' weighted sum and
    `qacc_warmstart` the last stage's, as in MuJoCo C."""
    h = mx.opt.timestep
    q0, v0, t0 = d.qpos, d.qvel, d.time
    d = forward(mx, maps, d)
    v_sum, a_sum = RK4_B[0] * v0, RK4_B[0] * d.qacc

    def stage(carry, tableau):
        d, v_prev, v_sum, a_sum = carry
        a, b = tableau[0], tableau[1]
        qpos = integrate_pos(maps, q0, v_prev, a * h)
        qvel = v0 + a * h * d.qacc
        d = forward(mx, maps, d.replace(qpos=qpos, qvel=qvel, time=t0 + a * h))
        v_stage = rkmk_velocity(maps, a * h * v_prev, qvel)
        return (d, v_stage, v_sum + b * v_stage, a_sum + b * d.qacc), None

    tableau = jnp.array([RK4_A, RK4_B[1:]], dtype=v0.dtype).T
    (d, _, v_sum, a_sum), _ = jax.lax.scan(stage, (d, v0, v_sum, a_sum), tableau)
    return d.replace(qpos=integrate_pos(maps, q0, v_sum, h), qvel=v0 + h * a_sum, time=t0 + h,
                     qacc=a_sum, qacc_warmstart=d.qacc)


def make_step(model: mujoco.MjModel):
    """`step(mx, d)`: one MuJoCo-C-equivalent RK4 step of MJX data `d` of `model`
    (`mx` its `mjx.put_model`)."""
    if model.opt.integrator != mujoco.mjtIntegrator.mjINT_RK4:
        raise ConfigError("lgnn's MJX step is RK4 only")
    check_equalities(model)
    maps = JointMaps(model)
    return lambda mx, d: rk4(mx, maps, d)


@functools.lru_cache(maxsize=16)
def runner(scene: Scene, config: SimulationConfig, dtype: str = "float64", form: Form = "nested"):
    """Compiled-on-first-call `run(q0, qd0) -> (q, qd)`: MJX trajectories of the
    scene's MJCF in `form`, `vmap`ped over initial node states (B, N, dim) -> (B, F+1,
    N, dim). Cached on the scene's content, config, dtype and form, so compilation (slow on
    CPU) happens once per process.
    Call it inside `lgnn.runtime.precision(dtype)`."""
    mjx = _mjx()
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
    mjc_step = make_step(compiled.model)
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
        return mjc_step(mx, d)

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
    scene's MJCF in `form`; non-finite from where a run diverged (the engine checks)."""
    # float32 needs x64 off: MJX builds float64 constants under x64 (its RK4 tableau,
    # for one) that would promote the float32 state and break its scans.
    with precision(dtype):
        run = runner(scene, config, dtype, form)
        q, qd = run(jnp.asarray(states.q, dtype), jnp.asarray(states.qd, dtype))
    return State(np.asarray(q, np.float64), np.asarray(qd, np.float64))


def best_form(scene: Scene) -> Form:
    """MJX's form of `scene`: nested (exact joints) up to `NESTED_MAX_DEPTH`, else
    maximal (compile time nearly flat in the number of links); always nested with
    joint damping, rails, point masses or limits (`mjcf.nested_only`)."""
    return "nested" if nested_only(scene) or scene_layout(scene).depth <= NESTED_MAX_DEPTH else "maximal"


@dataclasses.dataclass(frozen=True)
class MjxEngine(Engine):
    """MJX as an `lgnn.engines.Engine`, computing in `dtype`, on the MJCF `form`
    ("auto": `best_form`); `log` (e.g. `print`) is told before a compile starts. In
    the maximal form MuJoCo steps so that the run meets `tolerance`: by the error model
    where it holds, else by the step measured on the scene (`mujoco.stepped_config`)."""

    name: ClassVar[str] = "mjx"
    dtype: str = "float64"
    form: str = "auto"
    log: Callable[[str], None] | None = None
    tolerance: float = MAXIMAL_TOLERANCE

    def form_of(self, scene: Scene) -> Form:
        """The MJCF form this engine runs `scene` in."""
        return resolve_form(scene, self.form, best_form)

    def accuracy(self, scene: Scene, config: SimulationConfig) -> float | None:
        """The expected max node position error (m) of a run at `config` against exact
        motion (`mujoco.stated_accuracy`: the error model, or the maximal form's step
        measured on the scene); None where neither states one, and in float32 (its
        round-off is not modelled)."""
        if self.dtype != "float64":
            return None
        return stated_accuracy(scene, config, self.form_of(scene), self.tolerance)

    def _announced_form(self, scene: Scene, config: SimulationConfig) -> tuple[Form, SimulationConfig]:
        # The form and the settings MuJoCo steps at, told to `log` first when this
        # process has no runner for them yet.
        form = self.form_of(scene)
        if self.log is not None and form == "maximal" and not error_model_holds(scene):
            self.log(f"MJX: choosing {scene.name}'s step in the maximal form by MuJoCo C runs of it (its links are not alike: "
                     "mujoco.measured_maximal_substeps); on a long chain this can take a minute")
        stepped = stepped_config(scene, config, form, self.tolerance)
        if self.log is not None and not _has_runner(scene, stepped, self.dtype, form):
            nv = compile_scene(scene, stepped.dt, form).model.nv
            substeps = f", {stepped.steps_per_frame // config.steps_per_frame} steps per dt" if stepped is not config else ""
            self.log(f"MJX: compiling {scene.name} ({form} form, {nv} degrees of freedom, {self.dtype}, "
                     f"{jax.default_backend()}{substeps}); on a CPU this can take minutes")
        return form, stepped

    def rollout(self, scene: Scene, config: SimulationConfig, states: State) -> Trajectory:
        """`Trajectory` of initial states (B, N, dim): q, qd (B, F+1, N, dim), energy (B, F+1)
        (lgnn's exact energy in float64 of the node states; MJX has none)."""
        form, stepped = self._announced_form(scene, config)
        start = time.perf_counter()
        nodes = rollout(scene, stepped, states, self.dtype, form)
        metadata = engine_metadata(scene, config, self.name, self.dtype, time.perf_counter() - start, form,
                                   step=stepped.dt, accuracy=self.accuracy(scene, config))
        return checked_trajectory(scene, config, nodes, metadata, self.name)

    def timed_rollout(self, scene: Scene, config: SimulationConfig, states: State) -> tuple[float, float, np.ndarray]:
        """`(compile_s, run_s, q (B, F+1, N, dim))` of the compiled runner (`time_compiled`)."""
        form, stepped = self._announced_form(scene, config)
        with precision(self.dtype):
            run = runner(scene, stepped, self.dtype, form)
            compile_s, run_s, (q, _) = time_compiled(run, jnp.asarray(states.q, self.dtype), jnp.asarray(states.qd, self.dtype))
        return compile_s, run_s, np.asarray(q, np.float64)

    def timed_batch(self, scene: Scene, config: SimulationConfig, states: State, repeats: int = 1) -> tuple[float, list[float], np.ndarray]:
        """`(compile_s, run_s, q (B, N, dim))`: the runner compiled once
        (`timing.compile_timed`) and timed `repeats` times after an untimed run
        (`timing.time_runs`), the last run's final positions. It steps at `config.dt` in
        either form, as `lgnn gpu-truth`'s tables were measured (`rollout` and
        `timed_rollout` substep the maximal form), and announces no compile."""
        form = self.form_of(scene)
        with precision(self.dtype):
            run = runner(scene, config, self.dtype, form)
            q, qd = jnp.asarray(states.q, self.dtype), jnp.asarray(states.qd, self.dtype)
            compiled, compile_s = compile_timed(run, q, qd)
            run_s, (q_out, _) = time_runs(lambda: compiled(q, qd), repeats)
        return compile_s, run_s, np.asarray(q_out[:, -1], np.float64)


def _has_runner(scene: Scene, config: SimulationConfig, dtype: str, form: Form) -> bool:
    # Whether `runner` holds this one already (then nothing compiles): lru_cache keys
    # on the call's arguments, so a probe call that is not a hit would build it.
    hits = runner.cache_info().hits
    with precision(dtype):
        runner(scene, config, dtype, form)
    return runner.cache_info().hits > hits
