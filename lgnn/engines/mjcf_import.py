"""MJCF in: a model written for MuJoCo becomes a scene (`import_mjcf`), or is refused
in one line naming what lgnn does not model.

The file is compiled by MuJoCo itself (`mujoco.MjModel.from_xml_path`), so includes,
defaults, `inertiafromgeom`, `fromto` and composites mean what MuJoCo says, and the
compiled model is read at the initial state (the keyframe `key` names, else `qpos0` at
rest):

- **Bodies become links.** Every body with a joint (with the bodies welded to it, whose
  masses and inertias it carries) is one rod from its joint's anchor (a node) to its
  tip: the anchor its child bodies' joints share, or, for a body without children,
  the point beyond its centre of mass as far as the anchor is before it. A link's
  mass sits at its middle, so a body with children must have its centre of mass
  midway between its joint and theirs; a leaf body always does by that choice of tip
  (a pendulum whose bob is at 0.5 m becomes a rod of 1 m whose middle is the bob's
  centre: the same mass, centre and inertia, so the same motion).
- **Joints.** Hinges that all share one axis make a planar scene (motion in the plane
  normal to the axis; offsets along it change nothing); ball joints make a 3D one,
  whose rods must be symmetric about their axis (equal inertia about every normal to
  it, the axis a principal one) and start with no spin about it: a ball joint's rod
  then never spins (the joint forces act on its axis), and the node description,
  which has no axial spin, is exact. A body joined to its parent by no joint is
  welded to it; a body jointed to the world is pinned at its anchor.
- **Carts.** A body on a slide joint to the world (with what is welded to it) is a
  point mass on a rail (`Scene.point_masses`, `Scene.rails`): it never turns, so it is
  one node wherever its children's joints are, and the slide's damping is the rail's.
  The first cart's rail is the scene's x axis exactly and y is against gravity as
  far as it is normal to the rail, so gravity keeps any part along the rail (Gymnasium's
  inverted double pendulum's `1e-5`: `Scene.lateral_gravity`); other carts' slides
  must lie along a scene axis to round-off (`RAIL_TOLERANCE`).
- **Loops.** A `connect` equality tying two link ends (or a link end and the world)
  joins them in one node, exactly; MuJoCo's own connect is soft (`solref`), so the
  file's own simulation differs from the scene by that softness.
- **Axes.** The scene's y axis points against gravity (in a planar scene its component
  in the plane; the component along the hinges does no work), x completes a
  right-handed frame with the hinge axis (planar) or with the world's x axis (3D);
  with a cart, x is its rail (below).
  With no gravity the world's axes are kept as far as they fit.
- **Joint damping** of hinges becomes the scene's dampers (`Scene.dampers`: the same
  torque on the same two links); a ball joint's is refused, as it also acts about a
  rod's own axis, which a node description has no spin about.
- **Joint ranges** of hinges and slides become the scene's limits (`Scene.limits`), in
  the scene's angles and coordinates: lgnn does not model them, and its engine stops a
  rollout that leaves one, flagged, as at divergence.
- **Refused**, in one line naming the element: free joints, slides on moving bodies
  or off the scene's axes, ball joints' damping, nonlinear damping, stiffness, armature, friction loss, ball joints' ranges, limit margins wider than the range, contacts that could happen, tendons,
  flexes, plugins, mocap bodies, gravity compensation, fluid forces, equalities other
  than `connect`, actuators that push at zero control, hinges on different axes, and
  bodies whose mass is not a rod's as described. Actuators that do nothing at zero
  control are left out, and said so (`Imported.notes`): a scene is the passive system.

The written scene records where every node comes from (`lgnn.scene.SceneSource`), so
any import can be checked against MuJoCo on the original file.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np

from lgnn.engines.mjcf import DRAG_NUMERIC
from lgnn.errors import SceneError
from lgnn.scene import NodeSource, Scene, scene_from_dict

# Points closer than this (relative to the model's size) are one point; a centre of
# mass this close to a link's middle is at its middle; inertia components this small
# (relative to the largest) are zero. Loose enough for MJCF written to 6 digits.
RELATIVE_TOLERANCE = 1e-6
# A slide's axis further than this (radians) from every scene axis is refused: the
# scene's rails are along its axes exactly.
RAIL_TOLERANCE = 1e-9
# Largest MJCF file read (a model of thousands of bodies is a few MB).
MAX_MJCF_FILE_BYTES = 64 * 1024 * 1024
WORLD = "world"


@dataclasses.dataclass(frozen=True)
class Imported:
    """A scene imported from MJCF and what of the file it leaves out, one line each."""

    scene: Scene
    notes: tuple[str, ...]


def import_mjcf(path: str | os.PathLike, key: str | None = None) -> Scene:
    """The scene of the MJCF file `path` at keyframe `key` (default `qpos0`, at rest);
    `SceneError` naming what lgnn does not model (module docstring)."""
    return imported(path, key).scene


def imported(path: str | os.PathLike, key: str | None = None) -> Imported:
    """`import_mjcf` with the notes on what the scene leaves out (`Imported`)."""
    import mujoco

    path = Path(path)
    if not path.is_file():
        raise SceneError(f"{path}: no such MJCF file" if not path.exists() else f"{path}: not a regular file")
    if path.stat().st_size > MAX_MJCF_FILE_BYTES:
        raise SceneError(f"{path}: larger than the {MAX_MJCF_FILE_BYTES // 2**20} MiB limit for an MJCF file")
    try:
        model = mujoco.MjModel.from_xml_path(str(path))
    except ValueError as err:
        raise SceneError(f"{path}: MuJoCo cannot compile it: {' '.join(str(err).split())}") from None
    try:
        return _import(mujoco, model, path.name, key)
    except SceneError as err:
        raise SceneError(f"{path}: {err}") from None


def _name(mujoco, model, kind: str, index: int) -> str:
    name = mujoco.mj_id2name(model, getattr(mujoco.mjtObj, f"mjOBJ_{kind.upper()}"), index)
    return repr(name) if name else f"#{index}"


def _import(mujoco, model, file_name: str, key: str | None) -> Imported:
    disabled = int(model.opt.disableflags)
    off = lambda flag: bool(disabled & int(getattr(mujoco.mjtDisableBit, f"mjDSBL_{flag}")))  # noqa: E731
    notes = list(_refusals_and_notes(mujoco, model, off))
    data = mujoco.MjData(model)
    if key is not None:
        index = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, key)
        if index < 0:
            names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_KEY, k) for k in range(model.nkey)]
            raise SceneError(f"no keyframe {key!r} (the file has {', '.join(map(repr, names)) or 'none'})")
        mujoco.mj_resetDataKeyframe(model, data, index)
    mujoco.mj_forward(model, data)
    size = max(float(model.stat.extent), 1e-300)
    tolerance = RELATIVE_TOLERANCE * size

    jointed = [b for b in range(1, model.nbody) if model.body_jntnum[b] > 0]
    if not jointed:
        raise SceneError("no body has a joint: nothing moves")
    weld = np.asarray(model.body_weldid)
    slide = int(mujoco.mjtJoint.mjJNT_SLIDE)
    # A body on a slide joint to the world is a cart: a point mass on a rail, no rod.
    carts = [b for b in jointed if int(model.jnt_type[model.body_jntadr[b]]) == slide]
    for b in carts:
        if weld[model.body_parentid[b]] != 0:
            raise SceneError(f"joint {_name(mujoco, model, 'joint', model.body_jntadr[b])} slides a body that moves; "
                             "lgnn models slide joints to the world (a cart)")
    moving = [b for b in jointed if b not in carts]
    if not moving:
        raise SceneError("only slide joints: lgnn's scenes are rods, and a cart needs a hinged or ball-jointed body on it")
    kinds = {int(model.jnt_type[model.body_jntadr[b]]) for b in moving}
    hinge, ball = int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_BALL)
    if kinds == {hinge}:
        dim = 2
    elif kinds == {ball}:
        dim = 3
    else:
        raise SceneError("hinge and ball joints together: a scene is planar (hinges on one axis) or 3D (ball joints)")
    gravity = np.zeros(3) if off("GRAVITY") else np.array(model.opt.gravity, np.float64)
    if dim == 2:
        normal = _common_axis(mujoco, model, data, moving)
        axes, g = _planar_axes(normal, gravity)
    else:
        normal = None
        axes, g = _spatial_axes(gravity)
    if carts:
        # The first cart's rail is the x axis exactly; gravity keeps whatever part of
        # it lies along the rail (Gymnasium's inverted double pendulum's 1e-5).
        axes = _rail_axes(np.asarray(data.xaxis[model.body_jntadr[carts[0]]], np.float64), normal, np.asarray(axes))
        g = (np.asarray(axes) @ gravity).tolist()
    plane = np.eye(3) if normal is None else np.eye(3) - np.outer(normal, normal)

    # One rod per moving body: mass, centre of mass and inertia of its weld group.
    parent_of = {b: int(weld[model.body_parentid[b]]) for b in moving}
    anchors = {b: np.array(data.xanchor[model.body_jntadr[b]], np.float64) for b in moving}
    nodes: list[np.ndarray] = []  # world positions
    sources: list[NodeSource] = []
    velocities: list[np.ndarray] = []
    pins: list[int] = []

    def local(body: int, point: np.ndarray) -> tuple[float, float, float]:
        return tuple(float(x) for x in np.asarray(data.xmat[body]).reshape(3, 3).T @ (point - data.xpos[body]))

    def velocity(body: int, point: np.ndarray) -> np.ndarray:
        jacp = np.zeros((3, model.nv))
        mujoco.mj_jac(model, data, jacp, None, point, body)
        return jacp @ data.qvel

    def new_node(point: np.ndarray, body: int) -> int:
        nodes.append(point)
        sources.append(NodeSource(WORLD if body == 0 else mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, body) or f"#{body}",
                                  (tuple(float(x) for x in point) if body == 0 else local(body, point))))
        velocities.append(np.zeros(3) if body == 0 else velocity(body, point))
        if body == 0:
            pins.append(len(nodes) - 1)
        return len(nodes) - 1

    def same(p, q) -> bool:
        return float(np.linalg.norm(plane @ (p - q))) <= tolerance

    project = np.asarray(axes)
    cart_node, point_masses, rails = {}, [], []
    for b in carts:
        node, point_mass, rail = _cart(mujoco, model, data, weld, b, [anchors[c] for c in moving if parent_of[c] == b], same, project, off)
        cart_node[b] = new_node(node, b)
        point_masses.append((cart_node[b], point_mass))
        rails.append((cart_node[b], *rail))
    base_node, tip_node, links, link_of, dampers = {}, {}, [], {}, []
    for b in moving:  # parents before children (MuJoCo's body order)
        body = _name(mujoco, model, "body", b)
        p = parent_of[b]
        a = anchors[b]
        if p in cart_node:
            if not same(a, nodes[cart_node[p]]):
                raise SceneError(f"body {body}: its joint is not at the point of its cart where its siblings' are (a cart is one node)")
            base_node[b] = cart_node[p]
        elif p == 0:
            base_node[b] = next((k for k in pins if same(nodes[k], a)), None)
            if base_node[b] is None:
                base_node[b] = new_node(a, 0)
        elif same(a, anchors[p]):
            base_node[b] = base_node[p]
        elif p in tip_node and same(a, nodes[tip_node[p]]):
            base_node[b] = tip_node[p]
        else:
            raise SceneError(f"body {body}: its joint is at neither end of its parent's link (a link joins two nodes)")
        mass, centre, inertia = _weld_group(model, data, weld, b)
        if mass <= 0:
            raise SceneError(f"body {body}: no mass (with the bodies welded to it)")
        ends = [anchors[c] for c in moving if parent_of[c] == b and not same(anchors[c], a)]
        if ends and any(not same(end, ends[0]) for end in ends):
            raise SceneError(f"body {body}: its children's joints are at more than one point (a link joins two nodes)")
        if ends:
            tip = ends[0]
            arm = plane @ (tip - a)
            offset = plane @ (centre - a) - arm / 2
            if np.linalg.norm(offset) > tolerance:
                fraction = float(np.dot(plane @ (centre - a), arm) / np.dot(arm, arm))
                raise SceneError(f"body {body}: its centre of mass is not midway between its joint and its children's "
                                 f"(at {fraction:.3g} of the way; an lgnn link has its mass at the middle)")
        else:
            arm = plane @ (centre - a) * 2
            tip = a + arm
            if np.linalg.norm(arm) <= tolerance:
                raise SceneError(f"body {body}: its centre of mass is at its joint, so no rod stands for it")
        length = float(np.linalg.norm(arm))
        if dim == 2:
            link_inertia = float(normal @ inertia @ normal)
        else:
            link_inertia = _rod_inertia(body, inertia, arm / length)
            spin = np.zeros((3, model.nv))
            mujoco.mj_jac(model, data, None, spin, a, b)
            if abs(float(arm / length @ spin @ data.qvel)) > RELATIVE_TOLERANCE * (1 + float(np.linalg.norm(spin @ data.qvel))):
                raise SceneError(f"body {body}: spins about its own axis at the initial state (an lgnn rod has no spin)")
        tip_node[b] = new_node(tip, b)
        link_of[b] = len(links)
        links.append((base_node[b], tip_node[b], mass, max(link_inertia, 0.0)))
        damping = 0.0 if off("DAMPER") else float(model.dof_damping[model.jnt_dofadr[model.body_jntadr[b]]])
        if damping:
            # A cart does not turn, so a hinge on it is damped as one on a pin.
            dampers.append({"links": [link_of[b]] if p == 0 or p in cart_node else [link_of[b], link_of[p]], "damping": damping})

    ends_of = {**{b: [base_node[b], tip_node[b]] for b in moving}, **{b: [k] for b, k in cart_node.items()}}
    nodes_merged = _connected(mujoco, model, data, weld, nodes, pins, ends_of, same, lambda point: new_node(point, 0), off)
    order = sorted(set(nodes_merged))
    index = {k: n for n, k in enumerate(order)}
    drag = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_NUMERIC, DRAG_NUMERIC)
    if drag >= 0:
        drag = float(model.numeric_data[model.numeric_adr[drag]])
        notes.append(f"drag {drag:g} on link centres from the custom numeric {DRAG_NUMERIC!r} (lgnn's own element, which MuJoCo ignores)")
    scene_dict = {
        # The model's name is the first of MuJoCo's names (`<mujoco model=...>`).
        "name": bytes(model.names).split(b"\0", 1)[0].decode("utf-8", "replace").strip() or Path(file_name).stem,
        "gravity": g,
        "drag": max(drag, 0.0),
        "nodes": [(project @ nodes[k]).tolist() for k in order],
        "velocities": [(project @ velocities[k]).tolist() for k in order],
        "links": [{"nodes": [index[nodes_merged[i]], index[nodes_merged[j]]], "mass": m, "inertia": inertia} for i, j, m, inertia in links],
        "dampers": dampers,
        "point_masses": [{"node": index[nodes_merged[k]], "mass": m} for k, m in point_masses],
        "rails": [{"node": index[nodes_merged[k]], "axis": axis, "damping": damping} for k, axis, damping in rails],
        "source": {"mjcf": file_name, "axes": project.tolist(),
                   "nodes": [{"body": sources[k].body, "point": list(sources[k].point)} for k in order]},
    }
    # A node a connect ties to a pin is that pin.
    merged_pins = {index[nodes_merged[k]] for k in pins}
    scene_dict["pinned"] = sorted(merged_pins)
    limited = [(model.body_jntadr[b], {"links": [link_of[b]] if parent_of[b] == 0 or parent_of[b] in cart_node else [link_of[b], link_of[parent_of[b]]]})
               for b in moving] + [(model.body_jntadr[b], {"node": index[nodes_merged[cart_node[b]]]}) for b in carts]
    for k in merged_pins:
        scene_dict["velocities"][k] = [0.0] * dim
    for k, axis, _ in rails:
        node = index[nodes_merged[k]]
        if node in merged_pins:
            raise SceneError("a connect equality ties a cart to the world")
        # Off the rail's axis the projection leaves round-off only.
        scene_dict["velocities"][node] = [v if a == axis else 0.0 for a, v in enumerate(scene_dict["velocities"][node])]
    try:
        scene = scene_from_dict(scene_dict)
        if any(_limited(model, joint, off) for joint, _ in limited):
            scene = scene_from_dict({**scene_dict, "limits": _limits(mujoco, model, data, off, scene, limited, project)})
            notes.append("joint ranges kept as limits: lgnn does not model them, and an engine stops a rollout that leaves one")
    except SceneError as err:
        raise SceneError(f"the imported scene is not valid: {err}") from None
    return Imported(scene, tuple(notes))


def node_positions(scene: Scene, model, data) -> np.ndarray:
    """(N, D) the scene coordinates of an imported scene's nodes at MuJoCo's state `data`
    of the original file's `model` (`scene.source`: `axes @ p`, `p` each node's point
    in its body's frame, placed where that body is)."""
    import mujoco

    if scene.source is None:
        raise SceneError(f"scene {scene.name!r} was not imported from MJCF (it has no source)")
    points = []
    for node in scene.source.nodes:
        if node.body == WORLD:
            points.append(node.point)
            continue
        # An unnamed body is "#" and its index.
        body = int(node.body[1:]) if node.body[:1] == "#" and node.body[1:].isdigit() else mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, node.body)
        if not 0 < body < model.nbody:
            raise SceneError(f"the model has no body {node.body!r} (scene {scene.name!r} was imported from another file)")
        points.append(data.xpos[body] + np.asarray(data.xmat[body]).reshape(3, 3) @ np.asarray(node.point))
    return np.asarray(points, np.float64) @ np.asarray(scene.source.axes).T


def _cart(mujoco, model, data, weld, body: int, child_anchors: list, same, project: np.ndarray, off):
    """A cart's node (world point), point mass and rail `(axis, damping)`: the node is
    where its children's joints are (a body that slides without turning is a point
    mass at any point of it), or its centre of mass if it has none; its slide's axis
    must be one of the scene's (`project`'s rows)."""
    name = _name(mujoco, model, "body", body)
    joint = model.body_jntadr[body]
    mass, centre, _ = _weld_group(model, data, weld, body)
    if mass <= 0:
        raise SceneError(f"body {name}: a cart without mass (with the bodies welded to it)")
    if child_anchors and any(not same(a, child_anchors[0]) for a in child_anchors):
        raise SceneError(f"body {name}: the joints on this cart are at more than one point (a cart is one node)")
    direction = project @ np.asarray(data.xaxis[joint], np.float64)
    axis = int(np.argmax(np.abs(direction)))
    off_axis = float(np.linalg.norm(np.delete(direction, axis)))
    if off_axis > RAIL_TOLERANCE:
        raise SceneError(f"joint {_name(mujoco, model, 'joint', joint)} slides {off_axis:.3g} rad off the scene's nearest axis "
                         "(y is against gravity, x horizontal in the plane of motion); a rail along no scene axis, "
                         "or gravity with a component along a rail, is not modelled yet")
    damping = 0.0 if off("DAMPER") else float(model.dof_damping[model.jnt_dofadr[joint]])
    return (child_anchors[0] if child_anchors else centre), mass, (axis, damping)


def _weld_group(model, data, weld: np.ndarray, body: int) -> tuple[float, np.ndarray, np.ndarray]:
    """Mass, centre of mass (3,) and inertia about it (3, 3, world axes) of `body` with
    the bodies welded to it, at the current state."""
    members = [b for b in range(model.nbody) if weld[b] == body]
    masses = np.array([model.body_mass[b] for b in members], np.float64)
    mass = float(masses.sum())
    centres = np.array([data.xipos[b] for b in members], np.float64)
    centre = masses @ centres / mass if mass > 0 else centres[0]
    inertia = np.zeros((3, 3))
    for m, c, b in zip(masses, centres, members):
        rotation = np.asarray(data.ximat[b]).reshape(3, 3)
        r = c - centre
        inertia += rotation @ np.diag(model.body_inertia[b]) @ rotation.T + m * (r @ r * np.eye(3) - np.outer(r, r))
    return mass, centre, inertia


def _rod_inertia(body: str, inertia: np.ndarray, axis: np.ndarray) -> float:
    """The moment of inertia about every normal of a body symmetric about `axis`."""
    normal = np.cross(axis, np.eye(3)[int(np.argmin(np.abs(axis)))])
    normal /= np.linalg.norm(normal)
    other = np.cross(axis, normal)
    scale = max(float(np.abs(inertia).max()), 1e-300)
    about = [float(normal @ inertia @ normal), float(other @ inertia @ other)]
    off_axis = inertia @ axis - float(axis @ inertia @ axis) * axis
    if abs(about[0] - about[1]) > RELATIVE_TOLERANCE * scale or abs(float(normal @ inertia @ other)) > RELATIVE_TOLERANCE * scale \
            or np.linalg.norm(off_axis) > RELATIVE_TOLERANCE * scale:
        raise SceneError(f"body {body}: its inertia is not symmetric about its rod's axis (a ball-jointed lgnn rod is)")
    return sum(about) / 2


def _common_axis(mujoco, model, data, moving: list[int]) -> np.ndarray:
    """The hinges' shared axis (world, unit) at the initial state, or `SceneError`."""
    axes = [np.array(data.xaxis[model.body_jntadr[b]], np.float64) for b in moving]
    first = axes[0] / np.linalg.norm(axes[0])
    for b, axis in zip(moving, axes):
        if np.linalg.norm(np.cross(first, axis / np.linalg.norm(axis))) > RELATIVE_TOLERANCE:
            joint = _name(mujoco, model, "joint", model.body_jntadr[b])
            raise SceneError(f"joint {joint}: its hinge axis differs from the first hinge's (a planar scene's hinges share one axis)")
    return first


def _planar_axes(normal: np.ndarray, gravity: np.ndarray) -> tuple[list[list[float]], float]:
    """The two scene axes in the plane normal to `normal`, y against gravity's in-plane
    part, x = y cross normal (normal's sign chosen so that x leans on the world's axes'
    positive side), and that part's magnitude."""
    in_plane = gravity - (gravity @ normal) * normal
    g = float(np.linalg.norm(in_plane))
    if g > 0:
        up = -in_plane / g
    else:  # no gravity in the plane: the world's z (MuJoCo's up), else y, as far as they lie in it
        candidates = [e - (e @ normal) * normal for e in np.eye(3)[::-1]]
        up = max(candidates, key=np.linalg.norm)
        up /= np.linalg.norm(up)
    x = np.cross(up, normal)
    if x[int(np.argmax(np.abs(x)))] < 0:
        x = -x
    return [x.tolist(), up.tolist()], g


def _rail_axes(rail: np.ndarray, normal: np.ndarray | None, axes: np.ndarray) -> list[list[float]]:
    """Scene axes whose x is `rail` (world, sign kept towards the axes' own x) and whose
    y is the axes' y (against gravity) made normal to it; in a planar scene the rail
    must lie in the plane of motion."""
    rail = rail / np.linalg.norm(rail)
    if normal is not None and abs(float(rail @ normal)) > RAIL_TOLERANCE:
        raise SceneError("a slide joint's axis leaves the plane of the hinges' motion")
    x = rail if rail @ axes[0] >= 0 else -rail
    y = axes[1] - (axes[1] @ x) * x
    if np.linalg.norm(y) < 0.5:  # a rail along gravity: y from the axes' x instead
        y = axes[0] - (axes[0] @ x) * x
    y /= np.linalg.norm(y)
    return [x.tolist(), y.tolist()] if normal is not None else [x.tolist(), y.tolist(), np.cross(x, y).tolist()]


def _spatial_axes(gravity: np.ndarray) -> tuple[list[list[float]], float]:
    """Three scene axes: y against gravity, x the world's x made normal to it (the world's
    z where x is along gravity), z = x cross y; and gravity's magnitude."""
    g = float(np.linalg.norm(gravity))
    if g == 0:
        return np.eye(3).tolist(), 0.0
    up = -gravity / g
    x = np.eye(3)[0] if abs(up[0]) < 0.9 else np.eye(3)[2]
    x = x - (x @ up) * up
    x /= np.linalg.norm(x)
    return [x.tolist(), up.tolist(), np.cross(x, up).tolist()], g


def _refusals_and_notes(mujoco, model, off):
    """Raise `SceneError` for the first feature of `model` lgnn does not model; yield a
    note for each one it leaves out (module docstring)."""
    hinge, ball, slide = (int(getattr(mujoco.mjtJoint, f"mjJNT_{kind}")) for kind in ("HINGE", "BALL", "SLIDE"))
    kind_name = {int(mujoco.mjtJoint.mjJNT_FREE): "free"}
    for b in range(1, model.nbody):
        body = _name(mujoco, model, "body", b)
        if model.body_mocapid[b] >= 0:
            raise SceneError(f"body {body} is a mocap body (moved by the user, not by physics)")
        if model.body_gravcomp[b] != 0:
            raise SceneError(f"body {body} has gravity compensation, which lgnn does not model")
        if model.body_jntnum[b] > 1:
            raise SceneError(f"body {body} has {model.body_jntnum[b]} joints; lgnn models one hinge, ball or slide joint per body")
    for j in range(model.njnt):
        joint = _name(mujoco, model, "joint", j)
        kind = int(model.jnt_type[j])
        if kind not in (hinge, ball, slide):
            raise SceneError(f"joint {joint} is a {kind_name.get(kind, str(kind))} joint; lgnn models hinge, ball and slide joints")
        dofs = range(model.jnt_dofadr[j], model.jnt_dofadr[j] + (3 if kind == ball else 1))
        if not off("DAMPER") and any(x for d in dofs for x in model.dof_dampingpoly[d]):
            raise SceneError(f"joint {joint} has nonlinear damping (dampingpoly); lgnn models linear joint damping")
        if not off("DAMPER") and kind == ball and any(model.dof_damping[d] for d in dofs):
            raise SceneError(f"joint {joint} is a ball joint with damping, which also spins its rod about its own axis; "
                             "lgnn models the damping of planar hinges")
        if not off("SPRING") and (model.jnt_stiffness[j] or any(model.jnt_stiffnesspoly[j])):
            raise SceneError(f"joint {joint} has stiffness {model.jnt_stiffness[j]:g}: joint springs are not modelled yet")
        if any(model.dof_armature[d] for d in dofs):
            raise SceneError(f"joint {joint} has armature; lgnn does not model it")
        if not off("FRICTIONLOSS") and not off("CONSTRAINT") and any(model.dof_frictionloss[d] for d in dofs):
            raise SceneError(f"joint {joint} has friction loss; lgnn does not model it")
        if _limited(model, j, off) and kind == ball:
            raise SceneError(f"joint {joint} is a ball joint with a range (a cone limit); lgnn flags hinge and slide ranges only")
        if _limited(model, j, off) and not model.jnt_range[j][0] + model.jnt_margin[j] < model.jnt_range[j][1] - model.jnt_margin[j]:
            raise SceneError(f"joint {joint}: its limit margin {model.jnt_margin[j]:g} leaves no range where the limit is inactive")
    for what, count in (("tendon", model.ntendon), ("flex", model.nflex), ("plugin", model.nplugin)):
        if count:
            raise SceneError(f"{count} {what}{'s' if count > 1 else ''}: lgnn does not model {what}s")
    if model.opt.density or model.opt.viscosity:
        raise SceneError("fluid forces (option density or viscosity): lgnn does not model them")
    if not off("EQUALITY") and not off("CONSTRAINT"):
        for e in range(model.neq):
            equality = _name(mujoco, model, "equality", e)
            if int(model.eq_type[e]) != int(mujoco.mjtEq.mjEQ_CONNECT):
                raise SceneError(f"equality {equality} is a {mujoco.mjtEq(int(model.eq_type[e])).name[5:].lower()}; lgnn models connect equalities only")
            if not model.eq_active0[e]:
                raise SceneError(f"equality {equality} starts inactive; lgnn has no constraints that switch on")
    if not off("CONTACT") and not off("CONSTRAINT"):
        pair = _possible_contact(model, off("FILTERPARENT"))
        if pair is not None:
            first, second = (_name(mujoco, model, "geom", g) for g in pair)
            raise SceneError(f"geoms {first} and {second} can collide; lgnn has no contacts "
                             '(disable them: <flag contact="disable"/>, or contype="0" conaffinity="0")')
    if model.nu and not off("ACTUATION"):
        pushing = [u for u in range(model.nu) if int(model.actuator_biastype[u]) != int(mujoco.mjtBias.mjBIAS_NONE)]
        if pushing:
            raise SceneError(f"actuator {_name(mujoco, model, 'actuator', pushing[0])} pushes at zero control (it has a bias); lgnn scenes are passive")
        names = ", ".join(_name(mujoco, model, "actuator", u) for u in range(model.nu))
        yield f"left out: actuator{'s' if model.nu > 1 else ''} {names} (no force at zero control; a scene is the passive system)"


def _limited(model, joint: int, off) -> bool:
    """Whether MuJoCo enforces `joint`'s range (lgnn flags its crossing instead)."""
    return bool(model.jnt_limited[joint]) and not off("LIMIT") and not off("CONSTRAINT")


def _limits(mujoco, model, data, off, scene: Scene, joints: list[tuple[int, dict]], axes: np.ndarray) -> list[dict]:
    """The scene's `limits` entries of the limited hinges and slides among `joints`
    ((joint, its limit's "links" or "node")): MuJoCo's range of the joint's `qpos`
    less its margin at each end (where MuJoCo's limit starts to act),
    moved to the scene's angle (or rail coordinate) by their values at the initial
    state, in the scene's sense of rotation (or the rail's direction)."""
    from lgnn.metrics import limit_values
    from lgnn.scene import JointLimit

    normal = np.cross(axes[0], axes[1]) if len(axes) == 2 else None
    entries = []
    for joint, where in joints:
        if not _limited(model, joint, off):
            continue
        if "node" in where:
            sense = float(np.sign(axes @ np.asarray(data.xaxis[joint], np.float64))[next(a for k, a, _ in scene.rails if k == where["node"])])
            probe = JointLimit((), where["node"], -np.pi, np.pi)
        else:
            sense = float(np.sign(normal @ np.asarray(data.xaxis[joint], np.float64)))
            probe = JointLimit(tuple(where["links"]), -1, -np.pi, np.pi)
        initial = float(limit_values(scene.replace(limits=(probe,)), scene.nodes[None])[0, 0])
        value = float(data.qpos[model.jnt_qposadr[joint]])
        # MuJoCo's limit acts from `margin` inside its range on: the scene's range ends there.
        margin = float(model.jnt_margin[joint])
        low, high = float(model.jnt_range[joint][0]) + margin, float(model.jnt_range[joint][1]) - margin
        ends = sorted(initial + sense * (bound - value) for bound in (low, high))
        entries.append({**where, "range": ends})
    return entries


def _possible_contact(model, filter_parent_off: bool) -> tuple[int, int] | None:
    """The first pair of geoms MuJoCo could collide (contype/conaffinity, different weld
    bodies, not a parent and its child unless that filter is off, not excluded), or an
    explicit <pair>; None if there is none."""
    if model.npair:
        return int(model.pair_geom1[0]), int(model.pair_geom2[0])
    if model.ngeom < 2:
        return None
    weld = np.asarray(model.body_weldid)[np.asarray(model.geom_bodyid)]
    parent = np.asarray(model.body_weldid)[np.asarray(model.body_parentid)][weld]
    contype, conaffinity = np.asarray(model.geom_contype), np.asarray(model.geom_conaffinity)
    can = ((contype[:, None] & conaffinity[None, :]) | (conaffinity[:, None] & contype[None, :])) != 0
    can &= weld[:, None] != weld[None, :]
    if not filter_parent_off:
        # MuJoCo never filters the world against its children.
        related = ((parent[:, None] == weld[None, :]) & (weld[None, :] != 0)) | ((parent[None, :] == weld[:, None]) & (weld[:, None] != 0))
        can &= ~related
    excluded = {int(s) for s in model.exclude_signature}
    for g1, g2 in zip(*np.nonzero(np.triu(can, 1))):
        b1, b2 = sorted((int(model.geom_bodyid[g1]), int(model.geom_bodyid[g2])))
        if (b1 << 16) + b2 not in excluded:
            return int(g1), int(g2)
    return None


def _connected(mujoco, model, data, weld, nodes, pins, ends_of, same, new_pin, off) -> list[int]:
    """Each node's representative once the `connect` equalities have joined the link ends
    they tie (union-find); a tie to the world at a point that is no pin yet makes one."""
    parent = list(range(len(nodes)))

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    if not (off("EQUALITY") or off("CONSTRAINT")):
        site = int(mujoco.mjtObj.mjOBJ_SITE)
        for e in range(model.neq):
            equality = _name(mujoco, model, "equality", e)
            found = []
            for which, obj in ((0, model.eq_obj1id[e]), (1, model.eq_obj2id[e])):
                if int(model.eq_objtype[e]) == site:
                    body, point = int(model.site_bodyid[obj]), np.array(data.site_xpos[obj], np.float64)
                else:
                    body = int(obj)
                    rotation = np.asarray(data.xmat[body]).reshape(3, 3)
                    point = data.xpos[body] + rotation @ np.asarray(model.eq_data[e][3 * which: 3 * which + 3], np.float64)
                body = int(weld[body])
                ends = pins if body == 0 else ends_of[body]
                node = next((k for k in ends if same(nodes[k], point)), None)
                if node is None and body == 0:
                    node = new_pin(point)
                    parent.append(node)
                if node is None:
                    raise SceneError(f"equality {equality} ties body {_name(mujoco, model, 'body', body)} at a point that is neither end of its link "
                                     "(an lgnn joint joins link ends)")
                found.append(node)
            if not same(nodes[found[0]], nodes[found[1]]):
                raise SceneError(f"equality {equality}: its two points are apart at the initial state (an lgnn joint holds them together)")
            a, b = root(found[0]), root(found[1])
            if a != b:
                parent[max(a, b)] = min(a, b)
    return [root(k) for k in range(len(nodes))]
