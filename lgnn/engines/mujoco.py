"""MuJoCo C: an independent ground-truth engine for any planar or spatial scene.

The only modules of lgnn that import `mujoco` are this one and `lgnn.engines.mjx`
(built on it); `lgnn.engines` loads them on first use. Contract:

- `compile_scene(scene, dt, form)` compiles the scene's MJCF in `form`
  (`lgnn.engines.mjcf`: nested or maximal) into a `Compiled` model with the index
  arrays of the state maps (cached on the scene's content, `dt` and `form`);
  `best_form` is MuJoCo C's choice (nested while MuJoCo parses it, else maximal),
  `resolve_form` turns an engine's "auto" into it.
- `state_to_qpos_qvel` and `node_states` map between node states `(q, qd)` (N, dim)
  and MuJoCo's `(qpos, qvel)` (nq,), (nv,) (rotations relative to the rendered pose,
  so zero hinge angles / unit quaternions are the scene's initial shape; in 3D,
  quaternions with no spin about a link's axis, `qpos_rate` their time derivative).
- `rollout(scene, config, states)` (`mujoco.rollout`) returns node trajectories
  (B, F+1, N, dim): `joint_rollout` (MuJoCo's stepping, in joint coordinates) followed
  by `node_trajectories` (the map to nodes). `MujocoEngine` is the `lgnn.engines.Engine`
  on top: a `Trajectory` with lgnn's exact energy of the node states, stopped like
  the Lagrangian engine at the first non-finite or exploding frame (`checked_trajectory`).

Drag (chain4-drag) is an applied Cartesian force at each link's centre
(`xfrc_applied`), recomputed from the state before every step and held over the
step's RK4 stages: that lag is an O(dt) error of the drag force, so drag scenes agree
with the Lagrangian engine less closely than drag-free ones (measured, see tests).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
import os
import time
from typing import ClassVar

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from lgnn.engines.base import Engine, SimulationConfig, Trajectory
from lgnn.engines.mjcf import (MAX_BODY_DEPTH, MAXIMAL_SOLREF_STEPS, MODELLED_DURATION, SOLIMP, SOLREF_STEPS, Form, Layout, check_form,
                               error_model_holds, form_error, maximal_substeps, render, scene_layout)
from lgnn.errors import SceneError, SimulationError
from lgnn.metrics import ExplosionBounds, limit_violation, true_energies
from lgnn.runtime import precision
from lgnn.scene import Scene, State, scene_to_dict

# Doubles of per-step state `rollout` buffers per call (64 MB).
ROLLOUT_BUFFER_VALUES = 8_000_000
# MjData threads of a timed batch (the 2-core machine the results were measured on).
TIMING_THREADS = 2


@dataclasses.dataclass(frozen=True, eq=False)
class Compiled:
    """A compiled `MjModel` of a scene with the index arrays of the state maps.

    `rotation_qpos`, `rotation_dof` (B,) each body's rotation in qpos (planar: its
    hinge angle; spatial: the first of its quaternion's 4 numbers, of a ball joint or
    a free joint's rotation) and qvel (hinge rate; 3 angular velocity numbers in the
    body's frame); `parent` (B,) parent body (B: the world, a row appended); `base`,
    `tip` (B,) nodes; `rest_direction` (B, dim) link vector `tip - base` in the
    rendered pose; `root_body` (R,) free roots, their frame at `layout.origin_weight`
    along the link, `root_x`, `root_v` (R,) the first qpos / qvel address of their
    position (planar: x slide, y follows; spatial: a free joint's 3); `node_site` (N,)
    site ids; `body_id` (B,) body ids; `cart_node`, `cart_axis` (C,) each cart's rail
    node and scene axis, `cart_qpos`, `cart_dof` (C,) its slide's qpos and qvel address.
    """

    scene: Scene
    layout: Layout
    model: mujoco.MjModel
    rotation_qpos: np.ndarray
    rotation_dof: np.ndarray
    parent: np.ndarray
    base: np.ndarray
    tip: np.ndarray
    rest_direction: np.ndarray
    root_body: np.ndarray
    root_x: np.ndarray
    root_v: np.ndarray
    node_site: np.ndarray
    body_id: np.ndarray
    cart_node: np.ndarray
    cart_axis: np.ndarray
    cart_qpos: np.ndarray
    cart_dof: np.ndarray


def best_form(scene: Scene) -> Form:
    """MuJoCo C's form of `scene`: nested (exact joints: ~1e-13 from the Lagrangian
    engine on open chains) while MuJoCo can parse it, else maximal (no depth limit)."""
    return "nested" if scene_layout(scene).depth <= MAX_BODY_DEPTH else "maximal"


def resolve_form(scene: Scene, form: str, best=best_form) -> Form:
    """`form`, or with "auto" the engine's choice `best(scene)`; `ConfigError` for others."""
    if form == "auto":
        return best(scene)
    check_form(form)
    return form


@functools.lru_cache(maxsize=64)
def compile_scene(scene: Scene, dt: float = 1e-4, form: Form = "nested") -> Compiled:
    """Render `scene` in `form` and compile it (cached on the scene's content, `dt` and `form`)."""
    layout = scene_layout(scene, form)
    try:
        text = render(scene, dt, form)
    except SceneError as err:
        # Too deep to render (`mjcf.MAX_BODY_DEPTH`): this engine cannot run the scene,
        # which callers (the stability report) record like any stopped run.
        raise SimulationError(str(err)) from None
    try:
        model = mujoco.MjModel.from_xml_string(text)
    except ValueError as err:
        raise SimulationError(f"{scene.name}: MuJoCo rejected the rendered model: {str(err).splitlines()[0]}") from None
    # lgnn does not model joint limits: the file keeps their ranges, and the engines run
    # free of them and stop a rollout that leaves one (`checked_trajectory`), as the
    # Lagrangian engine does.
    model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_LIMIT)
    bodies = layout.bodies
    roots = [k for k, b in enumerate(bodies) if b.free_root]
    if scene.dim == 2:
        rotation_qpos = np.array([model.joint(f"link{b.link}_hinge").qposadr[0] for b in bodies], np.int64)
        rotation_dof = rotation_qpos  # hinges and slides: qpos and qvel alike
        root_x = np.array([model.joint(f"link{bodies[k].link}_x").qposadr[0] for k in roots], np.int64)
        root_v = root_x
    else:
        # A free joint holds its position (3) before its quaternion (4), its velocity
        # (3) before its angular velocity (3).
        joints = [model.joint(f"link{b.link}_{'free' if b.free_root else 'ball'}") for b in bodies]
        shift = np.array([3 if b.free_root else 0 for b in bodies], np.int64)
        rotation_qpos = np.array([j.qposadr[0] for j in joints], np.int64) + shift
        rotation_dof = np.array([j.dofadr[0] for j in joints], np.int64) + shift
        root_x = np.array([joints[k].qposadr[0] for k in roots], np.int64)
        root_v = np.array([joints[k].dofadr[0] for k in roots], np.int64)
    parent = np.array([b.parent if b.parent >= 0 else len(bodies) for b in bodies], np.int64)
    base = np.array([b.base for b in bodies], np.int64)
    tip = np.array([b.tip for b in bodies], np.int64)
    node_site = np.array([model.site(f"node{k}").id for k in range(scene.n_nodes)], np.int64)
    body_id = np.array([model.body(f"link{b.link}").id for b in bodies], np.int64)
    slides = [model.joint(f"cart{node}_slide") for node, _ in layout.carts]
    return Compiled(
        scene, layout, model, rotation_qpos, rotation_dof, parent, base, tip, scene.nodes[tip] - scene.nodes[base],
        np.array(roots, np.int64), root_x, root_v, node_site, body_id,
        np.array([node for node, _ in layout.carts], np.int64), np.array([axis for _, axis in layout.carts], np.int64),
        np.array([j.qposadr[0] for j in slides], np.int64), np.array([j.dofadr[0] for j in slides], np.int64),
    )


def state_to_qpos_qvel(compiled: Compiled, q, qd):
    """Node state `q, qd` (N, dim) -> `qpos` (nq,), `qvel` (nv,) (jnp; vmappable).

    Each body's absolute rotation takes its rendered link direction to its current
    one (planar: the angle between them; spatial: the shortest rotation, with no spin
    about the link, which the node state cannot see); a hinge or ball joint holds the
    rotation relative to the parent body, and its velocity the angular velocity
    `d x dd / |d|^2` (normal to the link) relative to the parent's (spatial: in the
    body's frame, as MuJoCo's ball and free joints). A loop body's rotation comes from
    its two end nodes, so its tip meets the node it is tied to.
    """
    c = compiled
    d = q[c.tip] - q[c.base]
    dd = qd[c.tip] - qd[c.base]
    if c.scene.dim == 2:
        qpos, qvel = _planar_rotations(c, d, dd, q.dtype)
    else:
        qpos, qvel = _spatial_rotations(c, d, dd, q.dtype)
    if len(c.root_body):
        # A free root's position is that of its frame: the base node (nested) or the
        # rod's centre (maximal); planar slides hold its displacement from the
        # rendered pose, a spatial free joint the position itself.
        w = c.layout.origin_weight
        base, tip = c.base[c.root_body], c.tip[c.root_body]

        def frame(x):
            return (1 - w) * x[base] + w * x[tip]

        position = frame(q) - jnp.asarray(frame(c.scene.nodes), q.dtype) if c.scene.dim == 2 else frame(q)
        at_x = c.root_x[:, None] + np.arange(c.scene.dim)
        at_v = c.root_v[:, None] + np.arange(c.scene.dim)
        qpos = qpos.at[at_x].set(position)
        qvel = qvel.at[at_v].set(frame(qd))
    if len(c.cart_node):
        # A cart's slide holds its node's displacement along the rail from the rendered pose.
        rest = jnp.asarray(c.scene.nodes[c.cart_node, c.cart_axis], q.dtype)
        qpos = qpos.at[c.cart_qpos].set(q[c.cart_node, c.cart_axis] - rest)
        qvel = qvel.at[c.cart_dof].set(qd[c.cart_node, c.cart_axis])
    return qpos, qvel


def _planar_rotations(c: Compiled, d, dd, dtype):
    # Hinge angles and rates relative to the parent body (`state_to_qpos_qvel`).
    rest_angle = np.arctan2(c.rest_direction[:, 1], c.rest_direction[:, 0])
    angle = jnp.arctan2(d[:, 1], d[:, 0]) - rest_angle
    omega = (d[:, 0] * dd[:, 1] - d[:, 1] * dd[:, 0]) / jnp.sum(d * d, -1)
    angle_ext = jnp.concatenate([angle, jnp.zeros(1, angle.dtype)])
    omega_ext = jnp.concatenate([omega, jnp.zeros(1, omega.dtype)])
    rel = angle - angle_ext[c.parent]
    rel = jnp.arctan2(jnp.sin(rel), jnp.cos(rel))
    qpos = jnp.zeros(c.model.nq, dtype).at[c.rotation_qpos].set(rel)
    qvel = jnp.zeros(c.model.nv, dtype).at[c.rotation_dof].set(omega - omega_ext[c.parent])
    return qpos, qvel


def _spatial_rotations(c: Compiled, d, dd, dtype):
    # Ball / free joint quaternions relative to the parent body and angular velocities
    # in the body's frame (`state_to_qpos_qvel`).
    absolute = _shortest_rotation(c.rest_direction, d)
    omega = jnp.cross(d, dd) / jnp.sum(d * d, -1, keepdims=True)
    absolute_ext = jnp.concatenate([absolute, jnp.array([[1.0, 0.0, 0.0, 0.0]], absolute.dtype)])
    omega_ext = jnp.concatenate([omega, jnp.zeros((1, 3), omega.dtype)])
    relative = quat_mul(_quat_conj(absolute_ext[c.parent]), absolute)
    local_omega = _quat_rotate(_quat_conj(absolute), omega - omega_ext[c.parent])
    qpos = jnp.zeros(c.model.nq, dtype).at[c.rotation_qpos[:, None] + np.arange(4)].set(relative)
    qvel = jnp.zeros(c.model.nv, dtype).at[c.rotation_dof[:, None] + np.arange(3)].set(local_omega)
    return qpos, qvel


def _shortest_rotation(rest: np.ndarray, d):
    """Unit quaternions (B, 4) (w, x, y, z) of the shortest rotations taking the
    directions `rest` (B, 3) (NumPy) to `d` (B, 3). Well conditioned at any angle: a
    direction more than 90 degrees from `rest` is reached from `-rest`, after a half
    turn about a fixed normal of `rest`."""
    u0 = rest / np.linalg.norm(rest, axis=-1, keepdims=True)
    u = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
    # A normal of u0: its cross product with the axis it has least of.
    normal = np.cross(u0, np.eye(3)[np.argmin(np.abs(u0), -1)])
    half_turn = np.concatenate([np.zeros((len(u0), 1)), normal / np.linalg.norm(normal, axis=-1, keepdims=True)], -1)
    far = jnp.sum(u0 * u, -1, keepdims=True) < 0
    start = jnp.where(far, -u0, u0)
    quat = jnp.concatenate([1 + jnp.sum(start * u, -1, keepdims=True), jnp.cross(start, u)], -1)
    quat = quat / jnp.linalg.norm(quat, axis=-1, keepdims=True)
    return jnp.where(far, quat_mul(quat, jnp.asarray(half_turn, quat.dtype)), quat)


def quat_mul(a, b):
    """Hamilton product of (..., 4) quaternions (w, x, y, z), MuJoCo's convention (jnp)."""
    aw, av, bw, bv = a[..., :1], a[..., 1:], b[..., :1], b[..., 1:]
    return jnp.concatenate([aw * bw - jnp.sum(av * bv, -1, keepdims=True), aw * bv + bw * av + jnp.cross(av, bv)], -1)


def _quat_conj(a):
    return a * jnp.array([1.0, -1.0, -1.0, -1.0], a.dtype)


def _quat_rotate(a, v):
    # The vectors v (..., 3) rotated by the unit quaternions a (..., 4).
    w, u = a[..., :1], a[..., 1:]
    t = 2 * jnp.cross(u, v)
    return v + w * t + jnp.cross(u, t)


def qpos_rate(compiled: Compiled, qpos, qvel):
    """The time derivative of `qpos` (nq,) at velocity `qvel` (nv,) (jnp): `qvel`
    itself for hinges and slides; a free joint's position rate is its velocity, a
    quaternion's `1/2 quat * (0, omega)` with `omega` in the body's frame. (What a
    `jvp` of positions in qpos takes as its tangent.)"""
    c = compiled
    if c.scene.dim == 2:
        return qvel
    at_x, at_v = c.root_x[:, None] + np.arange(3), c.root_v[:, None] + np.arange(3)
    at_quat, at_omega = c.rotation_qpos[:, None] + np.arange(4), c.rotation_dof[:, None] + np.arange(3)
    omega = jnp.concatenate([jnp.zeros((len(at_omega), 1), qvel.dtype), qvel[at_omega]], -1)
    rate = jnp.zeros(c.model.nq, qvel.dtype).at[at_x].set(qvel[at_v]).at[c.cart_qpos].set(qvel[c.cart_dof])
    return rate.at[at_quat].set(0.5 * quat_mul(qpos[at_quat], omega))


def _kinematics(model: mujoco.MjModel, data: mujoco.MjData) -> None:
    # Positions, then the frames `mj_jacSite`/`mj_jacBodyCom` read: what node states
    # and drag need, without the dynamics of a full `mj_forward`.
    mujoco.mj_kinematics(model, data)
    mujoco.mj_comPos(model, data)


def _posed(compiled: Compiled, qpos: np.ndarray, data: mujoco.MjData | None = None, *, forward: bool = False) -> mujoco.MjData:
    """`data` (default: a fresh MjData) at `qpos` with positions and Jacobian frames
    computed, or with `forward` everything `mj_forward` computes (mass matrix,
    constraint rows) at the velocity `data` holds (zero when fresh)."""
    data = mujoco.MjData(compiled.model) if data is None else data
    data.qpos[:] = qpos
    if forward:
        mujoco.mj_forward(compiled.model, data)
    else:
        _kinematics(compiled.model, data)
    return data


def node_states(compiled: Compiled, qpos: np.ndarray, qvel: np.ndarray, data: mujoco.MjData | None = None) -> State:
    """MuJoCo states `qpos, qvel` (F, nq) -> node `q, qd` (F, N, dim), by MuJoCo's own
    kinematics: node positions are the sites' `site_xpos`; velocities are the sites'
    linear velocities from their bodies' `cvel` (what `mj_objectVelocity` computes,
    `J_site qvel`): `v + w x (site - subtree_com[root])`.

    MuJoCo runs per frame (positions, then the body velocities, in C); the per-site
    arithmetic runs once over all frames: one `mj_jacSite` call and product per node and
    frame cost 20 s of Python on 100 x 1000 frames of a 16-link chain."""
    model = compiled.model
    data = mujoco.MjData(model) if data is None else data
    qpos, qvel = np.atleast_2d(qpos), np.atleast_2d(qvel)
    frames, dim, sites = len(qpos), compiled.scene.dim, compiled.node_site
    bodies = model.site_bodyid[sites]
    roots = model.body_rootid[bodies]
    site_x, cvel, root_com = np.empty((frames, len(sites), 3)), np.empty((frames, len(sites), 6)), np.empty((frames, len(sites), 3))
    for f in range(frames):
        data.qpos[:], data.qvel[:] = qpos[f], qvel[f]
        _kinematics(model, data)
        mujoco.mj_comVel(model, data)
        site_x[f], cvel[f], root_com[f] = data.site_xpos[sites], data.cvel[bodies], data.subtree_com[roots]
    # cvel: (angular, linear) velocity of each body at its root's subtree centre of mass.
    velocity = cvel[..., 3:] + np.cross(cvel[..., :3], site_x - root_com)
    return State(site_x[..., :dim], velocity[..., :dim])


def mass_matrix(compiled: Compiled, qpos: np.ndarray) -> np.ndarray:
    """MuJoCo's joint-space mass matrix (nv, nv) at `qpos` (for the mapping tests)."""
    model, data = compiled.model, _posed(compiled, qpos, forward=True)
    full = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, full)
    return full


def site_jacobian(compiled: Compiled, qpos: np.ndarray) -> np.ndarray:
    """(N*dim, nv) Jacobian of node positions with respect to qvel (planar: = qpos)."""
    model, data = compiled.model, _posed(compiled, qpos)
    rows, jac = [], np.empty((3, model.nv))
    for site in compiled.node_site:
        mujoco.mj_jacSite(model, data, jac, None, site)
        rows.append(jac[: compiled.scene.dim].copy())
    return np.concatenate(rows)


def equality_jacobian(compiled: Compiled, qpos: np.ndarray) -> np.ndarray:
    """(n_eq_rows, nv) Jacobian of the loop-closure equalities at `qpos`."""
    model, data = compiled.model, _posed(compiled, qpos, forward=True)
    rows = data.efc_type == mujoco.mjtConstraint.mjCNSTR_EQUALITY
    if not mujoco.mj_isSparse(model):
        return data.efc_J.reshape(data.nefc, model.nv)[rows]
    # The maximal form stores constraint rows sparse (its `jacobian="sparse"`).
    dense = np.zeros((data.nefc, model.nv))
    mujoco.mju_sparse2dense(dense, data.efc_J, data.efc_J_rownnz, data.efc_J_rowadr, data.efc_J_colind)
    return dense[rows]


# ---------------------------------------------------------------------------------
# MuJoCo C engine
# ---------------------------------------------------------------------------------


@functools.lru_cache(maxsize=64)
def _to_mj_fn(compiled: Compiled):
    # Cached: a fresh jit per call would recompile on every rollout.
    return jax.jit(jax.vmap(lambda q, qd: state_to_qpos_qvel(compiled, q, qd)))


def _initial_mj_states(compiled: Compiled, states: State) -> tuple[np.ndarray, np.ndarray]:
    with precision("float64"):  # MuJoCo C is float64: its initial state must be too
        qpos, qvel = _to_mj_fn(compiled)(jnp.asarray(states.q, jnp.float64), jnp.asarray(states.qd, jnp.float64))
    return np.asarray(qpos, np.float64), np.asarray(qvel, np.float64)


def _drag_forces(compiled: Compiled, data: mujoco.MjData, jac: np.ndarray) -> None:
    """Set `xfrc_applied` to `-drag * v_cm` on every link body at the current state."""
    model = compiled.model
    _kinematics(model, data)
    for body in compiled.body_id:
        mujoco.mj_jacBodyCom(model, data, jac, None, body)
        data.xfrc_applied[body, :3] = -compiled.scene.drag * (jac @ data.qvel)


# MuJoCo's instability warnings. On any of them MuJoCo C resets the state to the
# model's rest pose and carries on (its "autoreset"), which here is the scene's initial
# shape: the run would continue as if nothing happened (measured: T3 at dt 1e-2 then
# looked perfectly at rest, energy drift 2e-5). So each one is an error.
_INSTABILITY_WARNINGS = (mujoco.mjtWarning.mjWARN_BADQACC, mujoco.mjtWarning.mjWARN_BADQPOS, mujoco.mjtWarning.mjWARN_BADQVEL)


@contextlib.contextmanager
def _warnings_as_counters():
    """Silence MuJoCo's warning printer for the duration: by default it prints each
    warning and appends it to MUJOCO_LOG.TXT in the working directory. The counters in
    `MjData.warning` still count, and `_check_warnings` turns them into one error."""
    previous = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(lambda message: None)
    try:
        yield
    finally:
        mujoco.set_mju_user_warning(previous)


def _reset_frame(config, start_time: np.ndarray, steps_out: np.ndarray, first_frame: int) -> int:
    """The frame by which MuJoCo reset a run within a `rollout` call (its time restarts
    at zero when it resets an unstable state): `steps_out` (B, steps, nstate) holds the
    call's per-step FULLPHYSICS states, time first; the call's last frame if no restart
    shows."""
    steps = steps_out.shape[1]
    expected = start_time[:, None] + config.dt * np.arange(1, steps + 1)[None, :]
    off = np.abs(steps_out[:, :, 0] - expected).max(axis=0) > config.dt / 2
    step = int(np.argmax(off)) if off.any() else steps - 1
    return first_frame + step // config.steps_per_frame + 1


def _check_warnings(scene: Scene, config, datas, frame: int) -> None:
    """Raise `SimulationError` if MuJoCo flagged (and reset) an unstable state by `frame`."""
    for data in datas:
        bad = [w for w in _INSTABILITY_WARNINGS if data.warning[w].number > 0]
        if bad:
            what = mujoco.mjtWarning(bad[0]).name.removeprefix("mjWARN_BAD").lower()
            t = frame * config.frame_dt
            raise SimulationError(
                f"{scene.name}: MuJoCo found a non-finite or huge {what} by t = {t:.6g} s (dt = {config.dt:g}); try a smaller dt",
                time=t,
            )


def rollout(scene: Scene, config, states: State | None = None, *, threads: int = 1, form: Form = "nested") -> State:
    """MuJoCo C trajectories from initial node states (B, N, dim) (default: the scene's
    own, B = 1) on the scene's MJCF in `form`: node `State` (B, F+1, N, dim), frame 0 the
    initial state. The stepping (`joint_rollout`) followed by the node map (`node_states`)."""
    return node_trajectories(*joint_rollout(scene, config, states, threads=threads, form=form))


def node_trajectories(compiled: Compiled, qpos: np.ndarray, qvel: np.ndarray) -> State:
    """`node_states` of a batch: (B, F, nq), (B, F, nv) -> `State` (B, F, N, dim)."""
    data = mujoco.MjData(compiled.model)
    qs, qds = zip(*(node_states(compiled, qpos[b], qvel[b], data) for b in range(len(qpos))))
    return State(np.stack(qs), np.stack(qds))


def joint_rollout(scene: Scene, config, states: State | None = None, *, threads: int = 1, form: Form = "nested"):
    """The stepping of `rollout`: `(compiled, qpos (B, F+1, nq), qvel (B, F+1, nv))` in
    MuJoCo's joint coordinates (what a timing of MuJoCo itself should measure).

    Drag-free scenes run through `mujoco.rollout` (many frames per call, `threads`
    MjData for batches); drag scenes step in Python to update the drag force. An
    unstable state (MuJoCo's bad-qacc/qpos/qvel warning, after which MuJoCo would
    silently reset) or a non-finite one raises `SimulationError` with the time by
    which it happened.
    """
    compiled = compile_scene(scene, config.dt, form)
    model = compiled.model
    if states is None:
        states = State(scene.nodes[None], scene.velocities[None])
    qpos, qvel = _initial_mj_states(compiled, states)
    batch, spf = len(qpos), config.steps_per_frame
    frames_qpos = np.empty((batch, config.n_frames + 1, model.nq))
    frames_qvel = np.empty((batch, config.n_frames + 1, model.nv))
    frames_qpos[:, 0], frames_qvel[:, 0] = qpos, qvel
    datas = [mujoco.MjData(model) for _ in range(max(1, min(threads, batch)))]
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    with _warnings_as_counters():
        if scene.drag:
            data, jac = datas[0], np.empty((3, model.nv))
            for b in range(batch):
                mujoco.mj_resetData(model, data)
                data.qpos[:], data.qvel[:] = qpos[b], qvel[b]
                for f in range(config.n_frames):
                    for _ in range(spf):
                        _drag_forces(compiled, data, jac)
                        mujoco.mj_step(model, data)
                    _check_warnings(scene, config, [data], f + 1)
                    frames_qpos[b, f + 1], frames_qvel[b, f + 1] = data.qpos, data.qvel
        else:
            from mujoco import rollout as mj_rollout

            nstate = mujoco.mj_stateSize(model, spec)
            data = datas[0]
            state = np.empty((batch, nstate))
            for b in range(batch):
                data.qpos[:], data.qvel[:], data.time = qpos[b], qvel[b], 0.0
                mujoco.mj_getState(model, data, state[b], spec)
            # Many frames per call, so that timing MuJoCo measures its stepping rather
            # than a Python call per frame (which cost more than a chain4 step), with
            # the per-step output buffer bounded.
            frames_per_call = max(1, min(config.n_frames, ROLLOUT_BUFFER_VALUES // (batch * spf * nstate)))
            out = np.empty((batch, frames_per_call * spf, nstate))
            with mj_rollout.Rollout(nthread=len(datas) if len(datas) > 1 else 0) as runner:
                for first in range(0, config.n_frames, frames_per_call):
                    count = min(frames_per_call, config.n_frames - first)
                    # A buffer of exactly this call's steps: `out[:, :count * spf]` of a
                    # batch is not contiguous, and `mujoco.rollout` then writes into a copy
                    # of it, silently leaving the last call's frames stale.
                    steps = out if count == frames_per_call else np.empty((batch, count * spf, nstate))
                    runner.rollout(model, datas, state, nstep=count * spf, state=steps)
                    _check_warnings(scene, config, datas, _reset_frame(config, state[:, 0], steps, first))
                    frames = steps[:, spf - 1 :: spf]
                    state = frames[:, -1].copy()
                    # FULLPHYSICS layout: time, qpos, qvel, ...
                    frames_qpos[:, first + 1 : first + count + 1] = frames[:, :, 1 : 1 + model.nq]
                    frames_qvel[:, first + 1 : first + count + 1] = frames[:, :, 1 + model.nq : 1 + model.nq + model.nv]
    finite = np.isfinite(frames_qpos).all(axis=(0, 2)) & np.isfinite(frames_qvel).all(axis=(0, 2))
    if not finite.all():
        t = int(np.argmin(finite)) * config.frame_dt
        raise SimulationError(f"{scene.name}: MuJoCo state became non-finite at t = {t:.6g} s (dt = {config.dt:g}); try a smaller dt", time=t)
    return compiled, frames_qpos, frames_qvel




# ---------------------------------------------------------------------------------
# The engine
# ---------------------------------------------------------------------------------


def checked_trajectory(scene: Scene, config: SimulationConfig, states: State, metadata: dict, engine: str) -> Trajectory:
    """The `Trajectory` of node trajectories `states` (B, F+1, N, dim), with lgnn's exact
    energies (B, F+1). Raises, like the Lagrangian engine, `SimulationError` at the
    first non-finite or exploding frame (`lgnn.metrics.ExplosionBounds`) of any initial
    state, or its first frame outside a joint limit (`lgnn.metrics.limit_violation`),
    carrying that state's frames before it (unbatched)."""
    q, qd = states
    with precision("float64"):
        energy = true_energies(scene, q, qd)
    t = np.arange(config.n_frames + 1) * config.frame_dt
    member = ", initial condition {}" if len(q) > 1 else ""
    for b in range(len(q)):
        bounds = ExplosionBounds.of(scene, State(q[b, 0], qd[b, 0]), float(energy[b, 0]))
        violation = bounds.first_violation(t, q[b], qd[b], energy[b])
        outside = limit_violation(scene, t, q[b])
        if outside is not None and (violation is None or outside[0] < violation[0]):
            k, reason = outside
            end = max(k, 1)  # an initial state outside a limit: that frame alone
            raise SimulationError(f"{scene.name}: {engine} state {reason}{member.format(b)}", time=float(t[k]),
                                  trajectory=Trajectory(t[:end], q[b, :end], qd[b, :end], energy[b, :end], metadata))
        if violation is not None:
            k, reason = violation
            raise SimulationError(
                f"{scene.name}: {engine} state {reason} at t = {t[k]:.6g} s (dt = {config.dt:g}); try a smaller dt",
                time=float(t[k]),
                trajectory=Trajectory(t[:k], q[b, :k], qd[b, :k], energy[b, :k], metadata),
            )
    return Trajectory(t, q, qd, energy, metadata)


def frames_before(err: SimulationError, scene: Scene, config: SimulationConfig, states: State, form: Form, metadata: dict) -> SimulationError:
    """`err` (MuJoCo's instability, or a non-finite state, by `err.time`) carrying the
    first initial state's frames before that time, rolled out again to just before it
    (MuJoCo C is deterministic; MuJoCo itself resets an unstable state, so the frames it
    stepped past it are not kept). An error that carries frames, or no time, is
    returned as it is."""
    if err.trajectory is not None or err.time is None:
        return err
    kept = max(1, int(round(err.time / config.frame_dt)))  # frames at t < err.time
    first = State(np.asarray(states.q)[:1], np.asarray(states.qd)[:1])
    if kept > 1:
        nodes = rollout(scene, dataclasses.replace(config, duration=(kept - 1) * config.frame_dt), first, form=form)
        q, qd = nodes.q[0], nodes.qd[0]
    else:
        q, qd = first.q, first.qd
    with precision("float64"):
        energy = np.asarray(true_energies(scene, q, qd))
    return SimulationError(str(err), time=err.time, trajectory=Trajectory(np.arange(kept) * config.frame_dt, q, qd, energy, metadata))


def engine_metadata(scene: Scene, config: SimulationConfig, engine: str, dtype: str, wall_s: float, form: Form = "nested",
                    step: float | None = None, accuracy: float | None = None) -> dict:
    """A MuJoCo engine's `Trajectory.metadata`: the scene, the settings, and the engine
    (version, precision, stepping wall time, MJCF form, MuJoCo's `step` (default
    `config.dt`), constraint stiffness, its stated `accuracy`)."""
    return {
        "scene": scene_to_dict(scene),
        "config": dataclasses.asdict(config),
        "engine": {"name": engine, "mujoco": mujoco.__version__, "dtype": dtype, "wall_s": wall_s, "form": form,
                   "step": config.dt if step is None else step, "accuracy": accuracy,
                   "solref_steps": MAXIMAL_SOLREF_STEPS if form == "maximal" else SOLREF_STEPS, "solimp": list(SOLIMP)},
    }


def stepped_config(scene: Scene, config: SimulationConfig, form: Form, tolerance: float) -> SimulationConfig:
    """The settings MuJoCo steps at (MJX and MuJoCo Warp): in the maximal form `config`
    with its step divided by the substeps that meet `tolerance` (frames and duration
    unchanged): `mjcf.maximal_substeps` where the error model holds, else those
    `measured_maximal_substeps` finds on the scene itself; nested: `config`."""
    if form != "maximal":
        return config
    if error_model_holds(scene):
        substeps = maximal_substeps(scene, config.dt, tolerance)
    else:
        substeps = measured_maximal_substeps(scene, config.dt, config.frame_dt, tolerance)[0]
    return config if substeps == 1 else dataclasses.replace(config, dt=config.dt / substeps)


# Most substeps per step the measured step rule takes; where even they miss the
# tolerance, nothing is stated and the engine steps at them.
MAX_MEASURED_SUBSTEPS = 64


@functools.lru_cache(maxsize=64)
def measured_maximal_substeps(scene: Scene, dt: float, frame_dt: float, tolerance: float) -> tuple[int, float | None]:
    """`(substeps, error)` of the maximal form on a scene its error model does not cover
    (`mjcf.error_model_holds`: unequal links, trees, loops, drag), measured on the scene:
    MuJoCo C (the same model and arithmetic as MJX and MuJoCo Warp) runs the scene's own
    state over `mjcf.MODELLED_DURATION`. The maximal form's error falls as h^2 (`mjcf`), so
    the largest node distance `d` between runs at `dt / s` and `dt / 2s` puts the error at
    `dt / 2s` near `d / 3`. Runs at 1 and 2 substeps give the error at one, and the
    substeps `s` it predicts for `tolerance`; then runs at `s / 2` and `s` check it, `s`
    doubling until the check passes. Returns the substeps and their estimated error, or
    `(MAX_MEASURED_SUBSTEPS, None)` where none up to that passes. Measured from the
    scene's own state only. Measured against a converged Lagrangian reference: on
    40-link chains of varied links (`varied_chain(40, 1)`, `(40, 40)`) one substep, the
    estimate within 0.1 % of the error (1.9e-7); on a 40-link chain of mixed links (5
    times chain8-mixed's) errors falling as h^2 within 1 % from 1 to 8 substeps (3.9e-4
    to 6.1e-6), and 22 substeps taken, estimated 8.1e-7."""
    config = SimulationConfig(dt=dt, frame_dt=frame_dt, duration=MODELLED_DURATION)

    def nodes(substeps: int) -> np.ndarray:
        try:
            return rollout(scene, dataclasses.replace(config, dt=dt / substeps), form="maximal").q[0]
        except SimulationError:  # unstable at that step: no estimate from it
            return np.full((config.n_frames + 1, scene.n_nodes, scene.dim), np.nan)

    def finer_error(coarse: np.ndarray, fine: np.ndarray) -> float:
        # The error of `fine`, at half `coarse`'s step: (e - e/4) / ... = d / 3.
        distance = float(np.max(np.abs(fine - coarse)))
        return distance / 3 if np.isfinite(distance) else np.inf

    one, two = nodes(1), nodes(2)
    error = finer_error(one, two)
    if 4 * error <= tolerance:
        return 1, 4 * error
    if error <= tolerance:
        return 2, error
    # The error at one substep is 4 times that at two; it falls as 1 / s^2.
    substeps = 2 * math.ceil(math.sqrt(4 * error / tolerance) / 2) if np.isfinite(error) else 4
    while substeps <= MAX_MEASURED_SUBSTEPS:
        error = finer_error(nodes(substeps // 2), nodes(substeps))
        if error <= tolerance:
            return substeps, error
        substeps *= 2
    return MAX_MEASURED_SUBSTEPS, None


def stated_accuracy(scene: Scene, config: SimulationConfig, form: Form, tolerance: float) -> float | None:
    """The expected max node position error (m) of a float64 run of MJX or MuJoCo Warp's
    arithmetic at `config` in `form` (the step `stepped_config` takes): the error model
    (`mjcf.form_error`) where it holds, the measured estimate of the maximal form
    (`measured_maximal_substeps`) where not; None for a run longer than
    `mjcf.MODELLED_DURATION` or where neither states one."""
    if config.duration > MODELLED_DURATION:
        return None
    if form == "maximal" and not error_model_holds(scene):
        return measured_maximal_substeps(scene, config.dt, config.frame_dt, tolerance)[1]
    return form_error(scene, form, stepped_config(scene, config, form, tolerance).dt, config.duration)


@dataclasses.dataclass(frozen=True)
class MujocoEngine(Engine):
    """MuJoCo C as an `lgnn.engines.Engine`: float64 always (MuJoCo C has no other
    precision), `threads` MjData for a batch's rollout (default: one per core; timing
    uses `TIMING_THREADS`), the MJCF `form` ("auto": `best_form`)."""

    name: ClassVar[str] = "mujoco"
    dtype: ClassVar[str] = "float64"
    threads: int = dataclasses.field(default_factory=lambda: os.cpu_count() or 1)
    form: str = "auto"

    def form_of(self, scene: Scene) -> Form:
        """The MJCF form this engine runs `scene` in."""
        return resolve_form(scene, self.form, best_form)

    def accuracy(self, scene: Scene, config: SimulationConfig) -> float | None:
        """The expected max node position error (m) of a run at `config` against exact
        motion: `mjcf.form_error` of its form at `config.dt` (MuJoCo C steps at the step
        it is given); None where the error model does not hold."""
        return form_error(scene, self.form_of(scene), config.dt, config.duration)

    def rollout(self, scene: Scene, config: SimulationConfig, states: State) -> Trajectory:
        """`Trajectory` of initial states (B, N, dim): q, qd (B, F+1, N, dim), energy (B, F+1).
        A run MuJoCo flags as unstable raises `SimulationError` carrying the first
        initial state's frames before it (`frames_before`), as the JAX engines do."""
        form = self.form_of(scene)
        start = time.perf_counter()
        try:
            nodes = rollout(scene, config, states, threads=self.threads, form=form)
        except SimulationError as err:
            raise frames_before(err, scene, config, states, form, self._metadata(scene, config, form, start)) from None
        return checked_trajectory(scene, config, nodes, self._metadata(scene, config, form, start), self.name)

    def _metadata(self, scene: Scene, config: SimulationConfig, form: Form, start: float) -> dict:
        return engine_metadata(scene, config, self.name, self.dtype, time.perf_counter() - start, form, accuracy=self.accuracy(scene, config))

    def timed_rollout(self, scene: Scene, config: SimulationConfig, states: State) -> tuple[float, float, np.ndarray]:
        """`(compile_s, run_s, q (B, F+1, N, dim))`. Compile: a one-step warm-up run, which
        compiles the model. Run: MuJoCo's stepping alone; the map to node states after
        it is a Python loop over frames and nodes that would otherwise dominate small
        scenes (the JAX engines' timings include it, compiled into their rollout)."""
        form = self.form_of(scene)
        start = time.perf_counter()
        joint_rollout(scene, dataclasses.replace(config, frame_dt=config.dt, duration=config.dt), states, threads=TIMING_THREADS, form=form)
        compile_s = time.perf_counter() - start
        start = time.perf_counter()
        compiled, qpos, qvel = joint_rollout(scene, config, states, threads=TIMING_THREADS, form=form)
        run_s = time.perf_counter() - start
        return compile_s, run_s, node_trajectories(compiled, qpos, qvel).q
