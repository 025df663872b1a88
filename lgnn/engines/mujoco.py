"""MuJoCo (C) and MJX: independent ground-truth engines for any scene.

The only module of lgnn that imports `mujoco`. Contract:

- `scene_layout(scene)` is the scene's spanning tree (pure Python): every link is a
  body hinged at one of its end nodes (axis z, normal to the plane). The tree grows
  breadth-first from the pinned nodes (world-fixed); a component without pins gets a
  free planar root (slide x, slide y, hinge z). A link whose far node is already in
  the tree still becomes a body (it has mass) and closes its loop with a two-site
  `connect` equality from its tip to that node. Links between two pinned nodes never
  move and get no body.
- `scene_to_mjcf(scene, dt)` renders the MJCF text: explicit `<inertial>` (the link's
  mass at the rod's centre, the scene's moment of inertia about z), contacts off,
  gravity `(0, -g, 0)`, a site `node{k}` on every node, RK4. Loop equalities are made
  stiff with `solref` of `SOLREF_STEPS` time steps and `solimp` near 1, so the MJCF
  depends on `dt`.
- `state_to_qpos_qvel` and `node_states` map between node states `(q, qd)` (N, 2)
  and MuJoCo's `(qpos, qvel)` (nq,), (nv,) (hinge angles relative to the rendered
  pose, so `qpos = 0` is the scene's initial shape).
- `rollout(scene, config, states)` (C, `mujoco.rollout`) and `mjx_rollout(...)`
  (MJX, `vmap` over initial conditions) return node trajectories (B, F+1, N, 2);
  `simulate(scene, config, engine=...)` returns a `Trajectory` like the Lagrangian
  engine's, its energy computed by lgnn from node states (MJX has none).

Drag (chain4-drag) is an applied Cartesian force at each link's centre
(`xfrc_applied`), recomputed from the state before every step and held over the
step's RK4 stages: that lag is an O(dt) error of the drag force, so drag scenes agree
with the Lagrangian engine less closely than drag-free ones (measured, see tests).
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import functools
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from lgnn import physics
from lgnn.errors import ConfigError, SimulationError
from lgnn.scene import Scene, State, scene_to_dict

# Loop-closure stiffness: MuJoCo's constraint time constant in time steps (2 is the
# smallest MuJoCo accepts without clamping) and an impedance near 1 (nearly hard
# constraint). Measured on a closed 4-link loop: 5e-10 agreement with an exact solver.
SOLREF_STEPS = 2.0
SOLIMP = (0.9999, 0.9999, 0.001, 0.5, 2.0)
# Constraint solver: equality-only problems are quadratic, so Newton converges in one
# or two iterations; the tolerance only stops it at round-off.
SOLVER_TOLERANCE = 1e-14
SOLVER_ITERATIONS = 20
# Drawing sizes (viewer only, no physics): capsule and site radius per unit length.
GEOM_RADIUS = 0.03
SITE_RADIUS = 0.04
ENGINES = ("mujoco", "mjx")
# Doubles of per-step state `rollout` buffers per call (64 MB).
ROLLOUT_BUFFER_VALUES = 8_000_000


@dataclasses.dataclass(frozen=True)
class LinkBody:
    """One MuJoCo body: scene link `link` hinged at node `base`, far end at node `tip`.

    `parent` indexes `Layout.bodies` (-1: world). `free_root` bodies carry a planar
    free joint; `closes_loop` bodies end at a node owned by another body (or a pin)
    and are tied to it by a `connect` equality.
    """

    link: int
    base: int
    tip: int
    parent: int
    free_root: bool = False
    closes_loop: bool = False


@dataclasses.dataclass(frozen=True)
class Layout:
    """Spanning tree of a scene. `bodies` are in tree order (parents first);
    `node_body[k]` is the body carrying node k's site (-1: world, for pins);
    `static_links` join two pins and have no body."""

    bodies: tuple[LinkBody, ...]
    node_body: tuple[int, ...]
    static_links: tuple[int, ...]

    @property
    def depth(self) -> int:
        """Longest chain of bodies from the world (what MJX compile time grows with)."""
        depth = []
        for body in self.bodies:
            depth.append(1 + (depth[body.parent] if body.parent >= 0 else 0))
        return max(depth, default=0)


def scene_layout(scene: Scene) -> Layout:
    """Breadth-first spanning tree rooted at the pinned nodes (see module docstring)."""
    if scene.dim != 2:
        raise ConfigError(f"{scene.name}: the MuJoCo engines support planar (2D) scenes only, got {scene.dim}D")
    adjacency = [[] for _ in range(scene.n_nodes)]
    for e, (i, j) in enumerate(scene.edges):
        adjacency[i].append((e, j))
        adjacency[j].append((e, i))
    pinned = set(scene.pinned)
    static = tuple(e for e, (i, j) in enumerate(scene.edges) if i in pinned and j in pinned)
    used = set(static)
    node_body: list[int | None] = [None] * scene.n_nodes
    bodies: list[LinkBody] = []

    def grow(queue: collections.deque) -> None:
        while queue:
            a = queue.popleft()
            for e, b in adjacency[a]:
                if e in used:
                    continue
                used.add(e)
                closes = node_body[b] is not None
                bodies.append(LinkBody(e, a, b, node_body[a], closes_loop=closes))
                if not closes:
                    node_body[b] = len(bodies) - 1
                    queue.append(b)

    for p in scene.pinned:
        node_body[p] = -1
    grow(collections.deque(scene.pinned))
    for root in range(scene.n_nodes):
        if node_body[root] is not None:
            continue
        # An unpinned component: its first link carries the planar free joint and
        # owns both of its nodes (the root sits at the body's origin).
        e, b = adjacency[root][0]
        used.add(e)
        bodies.append(LinkBody(e, root, b, -1, free_root=True))
        node_body[root] = node_body[b] = len(bodies) - 1
        grow(collections.deque([root, b]))
    return Layout(tuple(bodies), tuple(node_body), static)


# ---------------------------------------------------------------------------------
# MJCF
# ---------------------------------------------------------------------------------


def _num(x) -> str:
    # Shortest repr that round-trips: the MJCF reproduces the scene exactly.
    x = float(x)
    return "0" if x == 0 else repr(x)


def _vec(*xs) -> str:
    return " ".join(_num(x) for x in xs)


def scene_to_mjcf(scene: Scene, dt: float = 1e-4) -> str:
    """The MJCF text of `scene` for time step `dt` (module docstring)."""
    layout = scene_layout(scene)
    nodes = np.asarray(scene.nodes, np.float64)
    scale = float(np.median(scene.lengths))
    children = collections.defaultdict(list)
    for k, body in enumerate(layout.bodies):
        children[body.parent].append(k)
    sites = collections.defaultdict(list)
    for k, owner in enumerate(layout.node_body):
        sites[owner].append(k)
    site_size = f"{SITE_RADIUS * scale:.3g}"

    def origin(index: int) -> np.ndarray:
        return nodes[layout.bodies[index].base] if index >= 0 else np.zeros(2)

    def node_sites(index: int, indent: str) -> list[str]:
        o = origin(index)
        return [
            f'{indent}<site name="node{k}" pos="{_vec(*(nodes[k] - o), 0)}" size="{site_size}"/>' for k in sites[index]
        ]

    def body_xml(index: int, indent: str) -> list[str]:
        body = layout.bodies[index]
        e = body.link
        pos = nodes[body.base] - origin(body.parent)
        tip = nodes[body.tip] - nodes[body.base]
        mass, inertia = float(scene.masses[e]), float(scene.inertias[e])
        # Only Izz acts on a planar hinge; Ixx = Iyy = Izz satisfies MuJoCo's triangle
        # inequality. A zero inertia (a point-mass rod) is raised to a negligible floor
        # because MuJoCo rejects zero principal moments.
        inertia = max(inertia, 1e-12 * mass * float(scene.lengths[e]) ** 2)
        inner = indent + "  "
        lines = [f'{indent}<body name="link{e}" pos="{_vec(*pos, 0)}">']
        if body.free_root:
            lines.append(f'{inner}<joint name="link{e}_x" type="slide" axis="1 0 0"/>')
            lines.append(f'{inner}<joint name="link{e}_y" type="slide" axis="0 1 0"/>')
        lines.append(f'{inner}<joint name="link{e}_hinge" type="hinge" axis="0 0 1"/>')
        lines.append(f'{inner}<inertial pos="{_vec(*(tip / 2), 0)}" mass="{_num(mass)}" diaginertia="{_vec(inertia, inertia, inertia)}"/>')
        lines.append(
            f'{inner}<geom name="link{e}" type="capsule" fromto="0 0 0 {_vec(*tip, 0)}" '
            f'size="{GEOM_RADIUS * scale:.3g}" rgba="{_link_color(scene.link_types[e])}"/>'
        )
        if body.closes_loop:
            lines.append(f'{inner}<site name="link{e}_tip" pos="{_vec(*tip, 0)}" size="{site_size}" rgba="1 0 0 1"/>')
        lines += node_sites(index, inner)
        for child in children[index]:
            lines += body_xml(child, inner)
        lines.append(f"{indent}</body>")
        return lines

    solref = f"{_num(SOLREF_STEPS * dt)} 1"
    solimp = _vec(*SOLIMP)
    lines = [
        f'<mujoco model="{scene.name}">',
        f"  <!-- Rendered by lgnn.engines.mujoco.scene_to_mjcf from scene {scene.name!r} "
        f"({scene.n_nodes} nodes, {scene.n_links} links, pins {list(scene.pinned)}); dt {dt:g}. -->",
    ]
    if layout.static_links:
        lines.append(f"  <!-- Links {list(layout.static_links)} join two pins: they never move and have no body. -->")
    if scene.drag:
        lines.append(f"  <!-- Drag {scene.drag:g} on link centre velocities is applied by lgnn (xfrc_applied), not modelled here. -->")
    lines += [
        '  <compiler angle="radian" autolimits="true"/>',
        f'  <option timestep="{_num(dt)}" integrator="RK4" gravity="0 {_num(-float(scene.gravity))} 0" '
        f'solver="Newton" tolerance="{_num(SOLVER_TOLERANCE)}" iterations="{SOLVER_ITERATIONS}" jacobian="dense">',
        '    <flag contact="disable"/>',
        "  </option>",
        '  <default><geom contype="0" conaffinity="0"/></default>',
        "  <worldbody>",
        f'    <light pos="0 0 {10 * scale:.3g}" dir="0 0 -1"/>',
        # A camera facing the plane of motion (the viewer's default assumes z up).
        f'    <camera name="front" pos="{" ".join(f"{x:.3g}" for x in nodes.mean(0))} {2 * max(np.ptp(nodes, 0).max(), scale):.3g}" xyaxes="1 0 0 0 1 0"/>',
    ]
    lines += node_sites(-1, "    ")
    for child in children[-1]:
        lines += body_xml(child, "    ")
    lines.append("  </worldbody>")
    loops = [body for body in layout.bodies if body.closes_loop]
    if loops:
        lines.append("  <equality>")
        for body in loops:
            lines.append(
                f'    <connect name="loop{body.link}" site1="link{body.link}_tip" site2="node{body.tip}" '
                f'solref="{solref}" solimp="{solimp}"/>'
            )
        lines.append("  </equality>")
    lines.append("</mujoco>")
    return "\n".join(lines) + "\n"


def _link_color(link_type: str) -> str:
    return "0.8 0.3 0.2 1" if link_type == "rod" else "0.2 0.4 0.8 1"


# ---------------------------------------------------------------------------------
# Compiled model and the state maps
# ---------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class Compiled:
    """A compiled `MjModel` of a scene with the index arrays of the state maps.

    `hinge` (B,) qpos/qvel address of each body's hinge; `parent` (B,) parent body
    (B: the world, a row of zeros appended); `base`, `tip` (B,) nodes; `rest_angle`
    (B,) link direction in the rendered pose; `root_body`, `root_x` (R,) free roots
    and the address of their x slide (y follows); `node_site` (N,) site ids.
    """

    scene: Scene
    layout: Layout
    model: mujoco.MjModel
    hinge: np.ndarray
    parent: np.ndarray
    base: np.ndarray
    tip: np.ndarray
    rest_angle: np.ndarray
    root_body: np.ndarray
    root_x: np.ndarray
    node_site: np.ndarray
    body_id: np.ndarray


@functools.lru_cache(maxsize=64)
def compile_scene(scene: Scene, dt: float = 1e-4) -> Compiled:
    """Render and compile the scene's model (cached per scene object and `dt`)."""
    layout = scene_layout(scene)
    try:
        text = scene_to_mjcf(scene, dt)
    except RecursionError:
        # The writer nests one <body> per tree level; MuJoCo's XML parser refuses such
        # depths anyway (measured: a 1000-link chain, "XML parse error 18").
        raise SimulationError(f"{scene.name}: spanning tree of depth {layout.depth} is too deep to render as nested MJCF bodies") from None
    try:
        model = mujoco.MjModel.from_xml_string(text)
    except ValueError as err:
        raise SimulationError(f"{scene.name}: MuJoCo rejected the rendered model: {str(err).splitlines()[0]}") from None
    assert model.nq == model.nv, "only hinge and slide joints are rendered"
    bodies = layout.bodies
    hinge = np.array([model.joint(f"link{b.link}_hinge").qposadr[0] for b in bodies], np.int64)
    parent = np.array([b.parent if b.parent >= 0 else len(bodies) for b in bodies], np.int64)
    base = np.array([b.base for b in bodies], np.int64)
    tip = np.array([b.tip for b in bodies], np.int64)
    d0 = scene.nodes[tip] - scene.nodes[base]
    roots = [k for k, b in enumerate(bodies) if b.free_root]
    root_x = np.array([model.joint(f"link{bodies[k].link}_x").qposadr[0] for k in roots], np.int64)
    node_site = np.array([model.site(f"node{k}").id for k in range(scene.n_nodes)], np.int64)
    body_id = np.array([model.body(f"link{b.link}").id for b in bodies], np.int64)
    return Compiled(
        scene, layout, model, hinge, parent, base, tip, np.arctan2(d0[:, 1], d0[:, 0]),
        np.array(roots, np.int64), root_x, node_site, body_id,
    )


def state_to_qpos_qvel(compiled: Compiled, q, qd):
    """Node state `q, qd` (N, 2) -> `qpos` (nq,), `qvel` (nv,) (jnp; vmappable).

    Each body's absolute rotation is its link's direction minus its rendered
    direction; the hinge holds the rotation relative to the parent body. A loop body's
    angle comes from its two end nodes, so its tip meets the node it is tied to.
    """
    c = compiled
    d = q[c.tip] - q[c.base]
    dd = qd[c.tip] - qd[c.base]
    angle = jnp.arctan2(d[:, 1], d[:, 0]) - c.rest_angle
    omega = (d[:, 0] * dd[:, 1] - d[:, 1] * dd[:, 0]) / jnp.sum(d * d, -1)
    angle_ext = jnp.concatenate([angle, jnp.zeros(1, angle.dtype)])
    omega_ext = jnp.concatenate([omega, jnp.zeros(1, omega.dtype)])
    rel = angle - angle_ext[c.parent]
    rel = jnp.arctan2(jnp.sin(rel), jnp.cos(rel))
    nq = c.model.nq
    qpos = jnp.zeros(nq, q.dtype).at[c.hinge].set(rel)
    qvel = jnp.zeros(nq, q.dtype).at[c.hinge].set(omega - omega_ext[c.parent])
    if len(c.root_body):
        root_nodes = c.base[c.root_body]
        shift = q[root_nodes] - jnp.asarray(c.scene.nodes[root_nodes], q.dtype)
        qpos = qpos.at[c.root_x].set(shift[:, 0]).at[c.root_x + 1].set(shift[:, 1])
        qvel = qvel.at[c.root_x].set(qd[root_nodes, 0]).at[c.root_x + 1].set(qd[root_nodes, 1])
    return qpos, qvel


def node_states(compiled: Compiled, qpos: np.ndarray, qvel: np.ndarray, data: mujoco.MjData | None = None) -> State:
    """MuJoCo states `qpos, qvel` (F, nq) -> node `q, qd` (F, N, 2), by MuJoCo's own
    kinematics: node positions are the sites' `site_xpos`, velocities `J_site qvel`."""
    model = compiled.model
    data = mujoco.MjData(model) if data is None else data
    qpos, qvel = np.atleast_2d(qpos), np.atleast_2d(qvel)
    frames, n = len(qpos), compiled.scene.n_nodes
    q, qd = np.empty((frames, n, 2)), np.empty((frames, n, 2))
    jac = np.empty((3, model.nv))
    for f in range(frames):
        data.qpos[:] = qpos[f]
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        q[f] = data.site_xpos[compiled.node_site, :2]
        for k, site in enumerate(compiled.node_site):
            mujoco.mj_jacSite(model, data, jac, None, site)
            qd[f, k] = jac[:2] @ qvel[f]
    return State(q, qd)


def mass_matrix(compiled: Compiled, qpos: np.ndarray) -> np.ndarray:
    """MuJoCo's joint-space mass matrix (nv, nv) at `qpos` (for the mapping tests)."""
    model, data = compiled.model, mujoco.MjData(compiled.model)
    data.qpos[:] = qpos
    mujoco.mj_forward(model, data)
    full = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, full)
    return full


def site_jacobian(compiled: Compiled, qpos: np.ndarray) -> np.ndarray:
    """(N*2, nv) Jacobian of node positions with respect to qpos (= qvel here)."""
    model, data = compiled.model, mujoco.MjData(compiled.model)
    data.qpos[:] = qpos
    mujoco.mj_kinematics(model, data)
    mujoco.mj_comPos(model, data)
    rows, jac = [], np.empty((3, model.nv))
    for site in compiled.node_site:
        mujoco.mj_jacSite(model, data, jac, None, site)
        rows.append(jac[:2].copy())
    return np.concatenate(rows)


def equality_jacobian(compiled: Compiled, qpos: np.ndarray) -> np.ndarray:
    """(n_eq_rows, nv) Jacobian of the loop-closure equalities at `qpos`."""
    model, data = compiled.model, mujoco.MjData(compiled.model)
    data.qpos[:] = qpos
    mujoco.mj_forward(model, data)
    rows = data.efc_type == mujoco.mjtConstraint.mjCNSTR_EQUALITY
    return data.efc_J.reshape(data.nefc, model.nv)[rows]


# ---------------------------------------------------------------------------------
# MuJoCo C engine
# ---------------------------------------------------------------------------------


def _check_config(scene: Scene, config) -> None:
    if config.integrator != "rk4":
        raise ConfigError(f"the MuJoCo engines integrate with RK4 only, got integrator {config.integrator!r}")


@functools.lru_cache(maxsize=64)
def _to_mj_fn(compiled: Compiled):
    # Cached: a fresh jit per call would recompile on every rollout.
    return jax.jit(jax.vmap(lambda q, qd: state_to_qpos_qvel(compiled, q, qd)))


def _initial_mj_states(compiled: Compiled, states: State) -> tuple[np.ndarray, np.ndarray]:
    qpos, qvel = _to_mj_fn(compiled)(jnp.asarray(states.q, jnp.float64), jnp.asarray(states.qd, jnp.float64))
    return np.asarray(qpos, np.float64), np.asarray(qvel, np.float64)


def _drag_forces(compiled: Compiled, data: mujoco.MjData, jac: np.ndarray) -> None:
    """Set `xfrc_applied` to `-drag * v_cm` on every link body at the current state."""
    model = compiled.model
    mujoco.mj_kinematics(model, data)
    mujoco.mj_comPos(model, data)
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


def rollout(scene: Scene, config, states: State | None = None, *, threads: int = 1) -> State:
    """MuJoCo C trajectories from initial node states (B, N, 2) (default: the scene's
    own, B = 1): node `State` (B, F+1, N, 2), frame 0 the initial state. The stepping
    (`joint_rollout`) followed by the node map (`node_states`)."""
    return node_trajectories(*joint_rollout(scene, config, states, threads=threads))


def node_trajectories(compiled: Compiled, qpos: np.ndarray, qvel: np.ndarray) -> State:
    """`node_states` of a batch: (B, F, nq), (B, F, nv) -> `State` (B, F, N, 2)."""
    data = mujoco.MjData(compiled.model)
    qs, qds = zip(*(node_states(compiled, qpos[b], qvel[b], data) for b in range(len(qpos))))
    return State(np.stack(qs), np.stack(qds))


def joint_rollout(scene: Scene, config, states: State | None = None, *, threads: int = 1):
    """The stepping of `rollout`: `(compiled, qpos (B, F+1, nq), qvel (B, F+1, nv))` in
    MuJoCo's joint coordinates (what a timing of MuJoCo itself should measure).

    Drag-free scenes run through `mujoco.rollout` (many frames per call, `threads`
    MjData for batches); drag scenes step in Python to update the drag force. An
    unstable state (MuJoCo's bad-qacc/qpos/qvel warning, after which MuJoCo would
    silently reset) or a non-finite one raises `SimulationError` with the time by
    which it happened.
    """
    _check_config(scene, config)
    compiled = compile_scene(scene, config.dt)
    model = compiled.model
    if states is None:
        states = State(scene.nodes[None], scene.velocities[None])
    qpos, qvel = _initial_mj_states(compiled, states)
    batch, spf = len(qpos), config.steps_per_frame
    frames_qpos = np.empty((batch, config.n_frames + 1, model.nq))
    frames_qvel = np.empty_like(frames_qpos)
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
                    runner.rollout(model, datas, state, nstep=count * spf, state=out[:, : count * spf])
                    _check_warnings(scene, config, datas, _reset_frame(config, state[:, 0], out[:, : count * spf], first))
                    frames = out[:, spf - 1 : count * spf : spf]
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
# MJX engine
# ---------------------------------------------------------------------------------


@functools.lru_cache(maxsize=16)
def mjx_runner(scene: Scene, config, dtype: str = "float64"):
    """Compiled-on-first-call `run(q0, qd0) -> (q, qd)`: MJX trajectories, `vmap`ped
    over initial node states (B, N, 2) -> (B, F+1, N, 2). Cached per scene object,
    config and dtype, so compilation (slow on CPU) happens once per process."""
    from mujoco import mjx

    _check_config(scene, config)
    if dtype not in ("float64", "float32"):
        raise ConfigError(f"MJX dtype must be float64 or float32, got {dtype!r}")
    if dtype == "float64" and not jax.config.jax_enable_x64:
        raise ConfigError("MJX float64 needs jax_enable_x64 (the CLI and tests enable it)")
    compiled = compile_scene(scene, config.dt)
    if dtype == "float32":
        # Traced under `mjx_precision` (x64 off), the index arrays would be converted to
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
        return d.site_xpos[sites, :2] if which == "sites" else d.xipos[bodies]

    def to_nodes(qpos, qvel):
        # qpos derivative = qvel for hinge and slide joints: site velocity is a jvp.
        return jax.jvp(lambda p: positions(p, "sites"), (qpos,), (qvel,))

    def step(d):
        if drag:
            _, v_cm = jax.jvp(lambda p: positions(p, "com"), (d.qpos,), (d.qvel,))
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


def mjx_precision(dtype: str):
    """Context to trace and run an `mjx_runner` of `dtype` in: float32 runs need x64 off,
    since MJX builds float64 constants under x64 (its RK4 tableau, for one) that would
    promote the float32 state and break its scans."""
    return jax.enable_x64(False) if dtype == "float32" else contextlib.nullcontext()


def mjx_rollout(scene: Scene, config, states: State | None = None, dtype: str = "float64") -> State:
    """MJX trajectories (B, F+1, N, 2) from initial node states (B, N, 2)."""
    if states is None:
        states = State(scene.nodes[None], scene.velocities[None])
    runner = mjx_runner(scene, config, dtype)
    with mjx_precision(dtype):
        q, qd = runner(jnp.asarray(states.q, dtype), jnp.asarray(states.qd, dtype))
    q, qd = np.asarray(q, np.float64), np.asarray(qd, np.float64)
    if not (np.isfinite(q).all() and np.isfinite(qd).all()):
        raise SimulationError(f"{scene.name}: MJX state became non-finite (dt = {config.dt:g}, {dtype}); try a smaller dt")
    return State(q, qd)


def simulate(scene: Scene, config, state: State | None = None, *, engine: str = "mujoco", dtype: str = "float64"):
    """One trajectory of `engine` ("mujoco" or "mjx") as a `Trajectory` (the `.npz`
    layout of the Lagrangian engine), with lgnn's exact energy of the node states.
    Stops, like the Lagrangian engine, at the first non-finite or exploding frame
    (`lgnn.metrics.ExplosionBounds`) with a `SimulationError` carrying the frames before it."""
    from lgnn.engines.lagrangian import Trajectory
    from lgnn.metrics import ExplosionBounds

    if engine not in ENGINES:
        raise ConfigError(f"unknown MuJoCo engine {engine!r} (choose from {', '.join(ENGINES)})")
    states = None if state is None else State(np.asarray(state.q)[None], np.asarray(state.qd)[None])
    start = time.perf_counter()
    if engine == "mujoco":
        traj = rollout(scene, config, states)
    else:
        traj = mjx_rollout(scene, config, states, dtype)
    wall = time.perf_counter() - start
    q, qd = traj.q[0], traj.qd[0]
    energy = np.asarray(jax.jit(jax.vmap(physics.energy_fn(scene)))(q, qd))
    t = np.arange(config.n_frames + 1) * config.frame_dt
    metadata = {
        "scene": scene_to_dict(scene),
        "config": dataclasses.asdict(config),
        "engine": {"name": engine, "mujoco": mujoco.__version__, "dtype": dtype if engine == "mjx" else "float64",
                   "wall_s": wall, "solref_steps": SOLREF_STEPS, "solimp": list(SOLIMP)},
    }
    violation = ExplosionBounds.of(scene, State(q[0], qd[0]), float(energy[0])).first_violation(t, q, qd, energy)
    if violation is not None:
        k, reason = violation
        raise SimulationError(
            f"{scene.name}: {engine} state {reason} at t = {t[k]:.6g} s (dt = {config.dt:g}); try a smaller dt",
            time=float(t[k]),
            trajectory=Trajectory(t[:k], q[:k], qd[:k], energy[:k], metadata),
        )
    return Trajectory(t, q, qd, energy, metadata)
