"""The scene: one immutable description of an articulated structure, planar or spatial.

A scene is a graph. Nodes are joints with Cartesian positions; links (edges) are
uniform rigid rods between two nodes with a rest length, a mass, a physical moment
of inertia about the rod's centre, and a type label. Some nodes are pinned (fixed in
space at their initial position). Gravity acts along -y in 2D and 3D alike (so a
planar scene embedded at z = 0 moves exactly as the planar one); an optional linear
drag acts on each link's centre velocity. A scene is 2D or 3D throughout (`dim`).

`Scene` is a frozen dataclass registered as a JAX pytree, equal to (and hashing like)
any scene of the same content (`content_key`), so caches key on content:
- static (meta) fields fix the topology and the model structure and are hashable:
  `name`, `edges`, `pinned`, `link_types`, `drag` (whether a drag term exists at all
  changes the equations, so it is static), `dampers`, `point_masses`, `rails`, `source`;
- numeric fields are the leaves: `nodes` (N, D) and `velocities` (N, D), the initial
  state; `lengths`, `masses`, `inertias` (E,); `gravity` ().
Leaves are stored as NumPy float64 so a scene is exact whatever JAX's x64 setting;
computations convert them.

Scene files are JSON with exactly this schema (other tools depend on it):

    {"name": str, "gravity": float (magnitude along -y, default 10) or [gx, gy] /
     [gx, gy, gz] (the gravitational acceleration as a vector in the scene's axes),
     "drag": float (default 0), "nodes": [[x, y], ...] or [[x, y, z], ...],
     "velocities": [[vx, vy], ...] or [[vx, vy, vz], ...] (optional, default rest),
     "pinned": [node, ...],
     "links": [{"nodes": [i, j], "mass": float, "inertia": float,
                "length": float (optional, default the initial distance),
                "type": str (optional, default "link")}, ...],
     "dampers": [{"links": [e, p] or [e], "damping": float}, ...] (optional, planar
                 scenes: a joint's viscous damping, below),
     "point_masses": [{"node": k, "mass": float}, ...] (optional: mass at a node),
     "rails": [{"node": k, "axis": a, "damping": float (default 0)}, ...] (optional:
               a node that slides along one scene axis, below),
     "limits": [{"links": [e, p] or [e], "range": [low, high]} or
                {"node": k, "range": [low, high]}, ...] (optional: joint ranges, below),
     "source": {...} (optional: where an imported scene's nodes come from, below)}

A damper is a joint's viscous damping, as MuJoCo's joint `damping`: a torque
`-damping * (omega_e - omega_p)` on link `e` and its opposite on link `p` (they share a
node), or with one link `-damping * omega_e` on a link turning about a pin; `omega` is
a link's angular velocity. Planar scenes only: in 3D a joint's damping also acts about
a rod's own axis, which the node description has no spin about.

A point mass sits at a node (a cart, a bob): kinetic energy `1/2 m |qd_k|^2` and
potential `m g y_k`. A link may be massless (mass and inertia 0: a rigid rod joining
point masses, as Finzi et al.'s chain pendulums) where every free node still carries
mass, of a link with mass or a point mass. A rail holds a free node to the line through its initial position
along scene axis `axis` (0 = x, 1 = y, 2 = z), as MuJoCo's slide joint to the world (a
cart): its other coordinates are fixed as a pin's are, and `damping` is the slide's
viscous damping, a force `-damping * qd_k[axis]`.

A limit is a joint's range, which lgnn does not enforce: an engine stops a rollout that
leaves it and flags it, as it flags divergence (`lgnn.metrics.limit_violation`). With
links `[e, p]` (sharing a node n) it bounds the angle in radians from link p's
direction into n to link e's direction out of n, counter-clockwise in the x-y plane (0
when they continue straight on); with `[e]` (a link with a pinned end or a rail's
node, which does not turn) the angle of e's direction out of that node from the x
axis; with `node` (a rail's) the node's coordinate along its rail. Angles are planar
scenes' only.

A scene imported from MJCF (`lgnn.import_mjcf`) records its `source` (`SceneSource`):
`{"mjcf": the file's name, "axes": [[x, y, z], ...] (one orthonormal row per scene axis:
its direction in the world, so a node's scene coordinates are `axes @ p` of its world
position `p`, no shift), "nodes": [{"body": MuJoCo body name, "point": [x, y, z]}, ...]
(for each node in order, the point fixed in that body's frame that the node stands
for; "world" for a pin)}`, which makes the import checkable against MuJoCo on the
original file. It changes no physics.

`scene_from_dict` validates everything and raises `SceneError` with one line naming
the field and the problem.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
import os
from pathlib import Path
from typing import Any, NamedTuple

import jax
import numpy as np

from lgnn import archives
from lgnn.errors import SceneError

# Positions must satisfy the link lengths to this relative accuracy at load, and
# initial velocities must not stretch links faster than this (relative to the scene's
# speed scale). Tight enough to catch typos, loose enough for 15-digit JSON.
LENGTH_TOLERANCE = 1e-8
# Links shorter than this fraction of the longest link are rejected: the rod's
# rotational inertia divides by its squared length and the constraint row by its length.
MIN_RELATIVE_LENGTH = 1e-6
# Scene files above this size are refused before reading (a scene of a million nodes
# is ~100 MB of JSON; anything larger is almost certainly not a scene).
MAX_SCENE_FILE_BYTES = 256 * 1024 * 1024
DEFAULT_LINK_TYPE = "link"
# Largest magnitude of any number in a scene: energies multiply a few of them and
# square lengths, so beyond this float64 overflows (1e300 coordinates used to load,
# with lengths inf - inf = NaN slipping past the length check, and fail at step 1).
MAX_MAGNITUDE = 1e30
# A scene is planar (2) or spatial (3) throughout: every node and velocity has that
# many coordinates. Gravity acts along -y in both.
DIMENSIONS = (2, 3)


class State(NamedTuple):
    """Node positions `q` and velocities `qd`, each (..., N, D)."""

    q: Any
    qd: Any


@dataclasses.dataclass(frozen=True)
class NodeSource:
    """The point (x, y, z), fixed in MuJoCo body `body`'s frame, that a node stands for."""

    body: str
    point: tuple[float, float, float]


@dataclasses.dataclass(frozen=True)
class SceneSource:
    """Where an imported scene comes from (module docstring): the MJCF file's name, the
    scene's axes in the world (D rows of 3) and each node's body and point."""

    mjcf: str
    axes: tuple[tuple[float, float, float], ...]
    nodes: tuple[NodeSource, ...]

    def to_dict(self) -> dict:
        return {"mjcf": self.mjcf, "axes": [list(row) for row in self.axes],
                "nodes": [{"body": node.body, "point": list(node.point)} for node in self.nodes]}


class JointLimit(NamedTuple):
    """A joint's range (module docstring): of the angle between `links` (e, p), of link
    e's angle (e,), or of rail node `node`'s coordinate (`links` empty)."""

    links: tuple[int, ...]
    node: int
    low: float
    high: float

    def to_dict(self) -> dict:
        where = {"links": list(self.links)} if self.links else {"node": self.node}
        return {**where, "range": [self.low, self.high]}


@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
    """Immutable description of an articulated structure; see the module docstring."""

    name: str
    edges: tuple[tuple[int, int], ...]
    pinned: tuple[int, ...]
    link_types: tuple[str, ...]
    drag: float
    nodes: np.ndarray
    velocities: np.ndarray
    lengths: np.ndarray
    masses: np.ndarray
    inertias: np.ndarray
    gravity: np.ndarray
    # Where an imported scene's nodes come from (`SceneSource`); None for every other.
    source: SceneSource | None = None
    # Joint damping (module docstring): (link e, link p or -1 for a pin, damping) each.
    dampers: tuple[tuple[int, int, float], ...] = ()
    # Point masses at nodes (module docstring): (node, mass) each.
    point_masses: tuple[tuple[int, float], ...] = ()
    # Nodes sliding along a scene axis (module docstring): (node, axis, damping) each.
    rails: tuple[tuple[int, int, float], ...] = ()
    # Joint ranges, not enforced: a rollout leaving one stops (module docstring).
    limits: tuple["JointLimit", ...] = ()
    # Gravity's components along the axes other than y (x, then z in 3D), where it
    # does not act along -y alone; `gravity` is always its magnitude along -y.
    lateral_gravity: tuple[float, ...] = ()

    @property
    def gravity_vector(self) -> np.ndarray:
        """(D,) the gravitational acceleration in the scene's axes."""
        vector = np.zeros(self.dim)
        vector[1] = -float(self.gravity)
        if self.lateral_gravity:
            vector[[0, *range(2, self.dim)]] = self.lateral_gravity
        return vector

    @property
    def n_nodes(self) -> int:
        return len(self.nodes)

    @property
    def n_links(self) -> int:
        return len(self.edges)

    @property
    def dim(self) -> int:
        """2 (planar) or 3 (spatial): the coordinates of every node."""
        return self.nodes.shape[-1]

    @property
    def edge_index(self) -> np.ndarray:
        """(E, 2) int array of link end nodes."""
        return np.asarray(self.edges, dtype=np.int64).reshape(-1, 2)

    @property
    def free_nodes(self) -> tuple[int, ...]:
        pinned = set(self.pinned)
        return tuple(k for k in range(self.n_nodes) if k not in pinned)

    @property
    def dissipates(self) -> bool:
        """Whether anything in the scene takes energy out: drag, joint dampers, a damped rail."""
        return bool(self.drag or any(b for *_, b in self.dampers) or any(b for *_, b in self.rails))

    @property
    def grounded_nodes(self) -> tuple[int, ...]:
        """The nodes the world holds, pinned or on a rail: they do not move off their place
        or line, so a link with an end at one turns about the world (its angle is a joint's)."""
        return tuple(self.pinned) + tuple(node for node, _, _ in self.rails)

    @property
    def fixed_mask(self) -> np.ndarray:
        """(N, D) bool: the coordinates held at their initial values, every coordinate of
        a pinned node and those of a rail's node off its axis."""
        fixed = np.zeros(self.nodes.shape, bool)
        fixed[list(self.pinned)] = True
        for node, axis, _ in self.rails:
            fixed[node] = True
            fixed[node, axis] = False
        return fixed

    @property
    def node_mass_array(self) -> np.ndarray:
        """(N,) the point mass at each node (zero where there is none)."""
        masses = np.zeros(self.n_nodes)
        for node, mass in self.point_masses:
            masses[node] = mass
        return masses

    @property
    def pin_positions(self) -> np.ndarray:
        """(P, D) fixed positions of the pinned nodes (their initial positions)."""
        return self.nodes[list(self.pinned)]

    @property
    def initial_state(self) -> State:
        return State(self.nodes, self.velocities)

    def replace(self, **changes) -> "Scene":
        return dataclasses.replace(self, **changes)

    @functools.cached_property
    def content_key(self) -> str:
        """A digest of everything the scene holds (structure, parameters, initial
        state): two scenes with equal keys are the same scene. Equality and hashing use
        it, so caches keyed on a scene key on its content, never on the object."""
        digest = hashlib.sha256(repr((self.name, self.edges, self.pinned, self.link_types, float(self.drag))).encode())
        if self.source is not None:  # scenes without a source keep the keys their records were made with
            digest.update(repr(self.source).encode())
        if self.dampers:  # as scenes without dampers
            digest.update(repr(("dampers", self.dampers)).encode())
        if self.point_masses:
            digest.update(repr(("point_masses", self.point_masses)).encode())
        if self.rails:
            digest.update(repr(("rails", self.rails)).encode())
        if self.limits:
            digest.update(repr(("limits", tuple(tuple(limit) for limit in self.limits))).encode())
        if self.lateral_gravity:
            digest.update(repr(("lateral_gravity", self.lateral_gravity)).encode())
        for array in (self.nodes, self.velocities, self.lengths, self.masses, self.inertias, self.gravity):
            array = np.ascontiguousarray(array, np.float64)
            digest.update(repr(array.shape).encode())
            digest.update(array.tobytes())
        return digest.hexdigest()

    def __eq__(self, other) -> bool:
        return isinstance(other, Scene) and self.content_key == other.content_key

    def __hash__(self) -> int:
        return hash(self.content_key)

    def __repr__(self) -> str:
        return (
            f"Scene({self.name!r}, nodes={self.n_nodes}, links={self.n_links}, "
            f"pinned={len(self.pinned)}, gravity={float(self.gravity):g}, drag={self.drag:g})"
        )


jax.tree_util.register_dataclass(
    Scene,
    data_fields=["nodes", "velocities", "lengths", "masses", "inertias", "gravity"],
    meta_fields=["name", "edges", "pinned", "link_types", "drag", "source", "dampers", "point_masses", "rails", "limits", "lateral_gravity"],
)


# ---------------------------------------------------------------------------------
# Construction and validation
# ---------------------------------------------------------------------------------

_TOP_KEYS = {"name", "gravity", "drag", "nodes", "velocities", "pinned", "links", "source", "dampers", "point_masses", "rails", "limits"}
_REQUIRED_TOP = {"name", "nodes", "pinned", "links"}
def is_pinned_chain(scene: Scene) -> bool:
    """True for a path 0-1-...-n pinned at node 0 only, in 2D or 3D: the scenes the chain
    samplers apply to, and whose constraint system physics solves in linear time."""
    n = scene.n_nodes - 1
    return scene.pinned == (0,) and not scene.rails and scene.edges == tuple((k, k + 1) for k in range(n))


_LINK_KEYS = {"nodes", "mass", "inertia", "length", "type"}
_REQUIRED_LINK = {"nodes", "mass", "inertia"}


def _fail(field: str, problem: str) -> SceneError:
    return SceneError(f"{field}: {problem}")


def _number(value, field: str) -> float:
    # bool is an int subclass in Python; `true` is never a valid number in a scene.
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _fail(field, f"expected a number, got {type(value).__name__} {_short(value)}")
    try:
        value = float(value)
    except OverflowError:  # a JSON integer of hundreds of digits
        raise _fail(field, f"magnitude {_short(value)} is beyond {MAX_MAGNITUDE:g} (float64 would overflow)") from None
    if not math.isfinite(value):
        raise _fail(field, f"must be finite, got {value}")
    if abs(value) > MAX_MAGNITUDE:
        raise _fail(field, f"magnitude {value:g} is beyond {MAX_MAGNITUDE:g} (float64 would overflow)")
    return value


def _index(value, field: str, n_nodes: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise _fail(field, f"expected a node index (integer), got {_short(value)}")
    if not 0 <= value < n_nodes:
        raise _fail(field, f"node index {value} out of range 0..{n_nodes - 1}")
    return value


def _short(value) -> str:
    text = json.dumps(value) if not isinstance(value, float) else repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _points(value, field: str, dim: int | None) -> np.ndarray:
    """(N, dim) points of `field`; with `dim` None the scene's dimension is the number of
    coordinates most points have (2 or 3), so a single odd point is the one named."""
    if not isinstance(value, list):
        raise _fail(field, f"expected a list of [x, y] or [x, y, z] points, got {type(value).__name__}")
    rows = []
    for k, point in enumerate(value):
        if not isinstance(point, list):
            raise _fail(f"{field}[{k}]", f"expected [x, y] or [x, y, z], got {_short(point)}")
        rows.append([_number(c, f"{field}[{k}]") for c in point])
    if dim is None:
        counts = [len(r) for r in rows]
        # Ties go to the first point's count; an empty list keeps the planar default.
        dim = max(counts, key=counts.count) if counts else 2
        if dim not in DIMENSIONS:
            first = counts.index(dim)
            raise _fail(f"{field}[{first}]", f"expected 2 (planar) or 3 (spatial) coordinates, got {dim}")
    bad = next((k for k, r in enumerate(rows) if len(r) != dim), None)
    if bad is not None:
        raise _fail(f"{field}[{bad}]", f"expected {dim} coordinates, got {len(rows[bad])} (a scene is {dim}D throughout)")
    return np.asarray(rows, dtype=np.float64).reshape(len(rows), dim)


def scene_from_dict(data: Any) -> Scene:
    """Validate a scene dictionary (the JSON schema above) and build the `Scene`.

    Raises `SceneError` naming the first offending field.
    """
    if not isinstance(data, dict):
        raise _fail("scene", f"expected a JSON object, got {type(data).__name__}")
    unknown = sorted(set(data) - _TOP_KEYS)
    if unknown:
        raise _fail(unknown[0], f"unknown key (allowed: {', '.join(sorted(_TOP_KEYS))})")
    missing = sorted(_REQUIRED_TOP - set(data))
    if missing:
        raise _fail(missing[0], "missing required key")

    name = data["name"]
    if not isinstance(name, str) or not name.strip():
        raise _fail("name", f"expected a non-empty string, got {_short(name)}")
    if not name.isprintable():
        # It names files, tables and MJCF models: no control characters, no half of a UTF-16 pair.
        raise _fail("name", f"expected printable text, got {name.encode('unicode_escape', 'backslashreplace').decode()}")
    gravity_value = data.get("gravity", 10.0)
    drag = _number(data.get("drag", 0.0), "drag")
    if drag < 0:
        raise _fail("drag", f"must be >= 0, got {drag}")

    nodes = _points(data["nodes"], "nodes", None)
    gravity, lateral_gravity = _gravity(gravity_value, nodes.shape[1] if nodes.ndim == 2 else None)
    n_nodes = len(nodes)
    if n_nodes < 2:
        raise _fail("nodes", f"need at least 2 nodes, got {n_nodes}")
    if "velocities" in data:
        velocities = _points(data["velocities"], "velocities", nodes.shape[1])
        if len(velocities) != n_nodes:
            raise _fail("velocities", f"expected {n_nodes} entries (one per node), got {len(velocities)}")
    else:
        velocities = np.zeros_like(nodes)

    pinned_raw = data["pinned"]
    if not isinstance(pinned_raw, list):
        raise _fail("pinned", f"expected a list of node indices, got {_short(pinned_raw)}")
    pinned = tuple(_index(p, f"pinned[{k}]", n_nodes) for k, p in enumerate(pinned_raw))
    if len(set(pinned)) != len(pinned):
        dup = next(p for p in pinned if pinned.count(p) > 1)
        raise _fail("pinned", f"node {dup} listed twice")

    links_raw = data["links"]
    if not isinstance(links_raw, list) or not links_raw:
        raise _fail("links", "expected a non-empty list of links")
    edges, masses, inertias, lengths, types = [], [], [], [], []
    seen: dict[frozenset, int] = {}
    for k, link in enumerate(links_raw):
        where = f"links[{k}]"
        if not isinstance(link, dict):
            raise _fail(where, f"expected an object, got {_short(link)}")
        unknown = sorted(set(link) - _LINK_KEYS)
        if unknown:
            raise _fail(f"{where}.{unknown[0]}", f"unknown key (allowed: {', '.join(sorted(_LINK_KEYS))})")
        missing = sorted(_REQUIRED_LINK - set(link))
        if missing:
            raise _fail(f"{where}.{missing[0]}", "missing required key")
        pair = link["nodes"]
        if not isinstance(pair, list) or len(pair) != 2:
            raise _fail(f"{where}.nodes", f"expected [i, j], got {_short(pair)}")
        i, j = (_index(v, f"{where}.nodes", n_nodes) for v in pair)
        if i == j:
            raise _fail(f"{where}.nodes", f"self link: both ends are node {i}")
        key = frozenset((i, j))
        if key in seen:
            raise _fail(f"{where}.nodes", f"duplicate link: nodes {i}-{j} already joined by links[{seen[key]}]")
        seen[key] = k
        mass = _number(link["mass"], f"{where}.mass")
        if mass < 0:
            raise _fail(f"{where}.mass", f"must be >= 0, got {mass}")
        inertia = _number(link["inertia"], f"{where}.inertia")
        if inertia < 0:
            raise _fail(f"{where}.inertia", f"must be >= 0, got {inertia}")
        if mass == 0 and inertia > 0:
            raise _fail(f"{where}.inertia", f"a massless link has no inertia, got {inertia}")
        # math.hypot is correctly rounded on every platform; np.linalg.norm's last bit
        # depends on the CPU's FMA path, which would make a scene (and every record
        # keyed on it) differ between machines.
        distance = math.hypot(*(float(x) for x in nodes[i] - nodes[j]))
        length = _number(link["length"], f"{where}.length") if "length" in link else distance
        if length <= 0:
            raise _fail(f"{where}.length", f"must be > 0, got {length}")
        link_type = link.get("type", DEFAULT_LINK_TYPE)
        if not isinstance(link_type, str) or not link_type:
            raise _fail(f"{where}.type", f"expected a non-empty string, got {_short(link_type)}")
        edges.append((i, j))
        masses.append(mass)
        inertias.append(inertia)
        lengths.append(length)
        types.append(link_type)

    rails = _rails(data["rails"], n_nodes, pinned, nodes.shape[1]) if "rails" in data else ()
    scene = Scene(
        name=name,
        edges=tuple(edges),
        pinned=pinned,
        link_types=tuple(types),
        drag=drag,
        nodes=nodes,
        velocities=velocities,
        lengths=np.asarray(lengths, np.float64),
        masses=np.asarray(masses, np.float64),
        inertias=np.asarray(inertias, np.float64),
        gravity=np.asarray(gravity, np.float64),
        source=_source(data["source"], n_nodes, nodes.shape[1]) if "source" in data else None,
        point_masses=_point_masses(data["point_masses"], n_nodes) if "point_masses" in data else (),
        rails=rails,
        lateral_gravity=lateral_gravity,
    )
    # Joints are read against the scene's grounded nodes: a link with an end at a pin or
    # on a rail has a joint (a damper, a limit) of its own.
    if "dampers" in data:
        scene = scene.replace(dampers=_dampers(data["dampers"], edges, scene.grounded_nodes, scene.dim))
    if "limits" in data:
        scene = scene.replace(limits=_limits(data["limits"], edges, scene.grounded_nodes, rails, scene.dim))
    check_scene(scene)
    return scene


def _point_masses(value, n_nodes: int) -> tuple[tuple[int, float], ...]:
    """The validated point masses (module docstring): one per node at most, mass > 0."""
    if not isinstance(value, list):
        raise _fail("point_masses", f"expected a list of point masses, got {_short(value)}")
    masses, seen = [], set()
    for k, entry in enumerate(value):
        where = f"point_masses[{k}]"
        if not isinstance(entry, dict) or set(entry) != {"node", "mass"}:
            raise _fail(where, f'expected {{"node": k, "mass": number}}, got {_short(entry)}')
        node = _index(entry["node"], f"{where}.node", n_nodes)
        if node in seen:
            raise _fail(f"{where}.node", f"node {node} already has a point mass")
        seen.add(node)
        mass = _number(entry["mass"], f"{where}.mass")
        if mass <= 0:
            raise _fail(f"{where}.mass", f"must be > 0, got {mass}")
        masses.append((node, mass))
    return tuple(masses)


def _rails(value, n_nodes: int, pinned: tuple, dim: int) -> tuple[tuple[int, int, float], ...]:
    """The validated rails (module docstring): one per free node at most, on one of the
    scene's axes, damping >= 0."""
    if not isinstance(value, list):
        raise _fail("rails", f"expected a list of rails, got {_short(value)}")
    rails, seen = [], set()
    for k, entry in enumerate(value):
        where = f"rails[{k}]"
        if not isinstance(entry, dict) or not {"node", "axis"} <= set(entry) <= {"node", "axis", "damping"}:
            raise _fail(where, f'expected {{"node": k, "axis": a, "damping": number (optional)}}, got {_short(entry)}')
        node = _index(entry["node"], f"{where}.node", n_nodes)
        if node in pinned:
            raise _fail(f"{where}.node", f"node {node} is pinned")
        if node in seen:
            raise _fail(f"{where}.node", f"node {node} already has a rail")
        seen.add(node)
        axis = entry["axis"]
        if isinstance(axis, bool) or not isinstance(axis, int) or not 0 <= axis < dim:
            raise _fail(f"{where}.axis", f"expected a scene axis 0..{dim - 1}, got {_short(axis)}")
        damping = _number(entry.get("damping", 0.0), f"{where}.damping")
        if damping < 0:
            raise _fail(f"{where}.damping", f"must be >= 0, got {damping}")
        rails.append((node, axis, damping))
    return tuple(rails)


def _gravity(value, dim: int | None) -> tuple[float, tuple[float, ...]]:
    """`(magnitude along -y, lateral components)` of the JSON `gravity`: a number, or a
    vector of the scene's dimension (module docstring)."""
    if not isinstance(value, list):
        return _number(value, "gravity"), ()
    if dim is None or len(value) != dim:
        raise _fail("gravity", f"expected a number or a vector of {dim} coordinates (as the nodes have), got {_short(value)}")
    vector = [_number(v, f"gravity[{k}]") for k, v in enumerate(value)]
    lateral = tuple(vector[a] for a in (0, *range(2, dim)))
    return -vector[1], (lateral if any(lateral) else ())


def _limits(value, edges: list, fixed_ends: tuple, rails: tuple, dim: int) -> tuple[JointLimit, ...]:
    """The validated limits (module docstring): a joint's angle (`_joint_links`;
    planar), or a rail node's coordinate."""
    if not isinstance(value, list):
        raise _fail("limits", f"expected a list of limits, got {_short(value)}")
    limits, seen = [], set()
    rail_nodes = {node for node, _, _ in rails}
    for k, entry in enumerate(value):
        where = f"limits[{k}]"
        if not isinstance(entry, dict) or set(entry) not in ({"links", "range"}, {"node", "range"}):
            raise _fail(where, f'expected {{"links": [e, p] or [e], "range": [low, high]}} or {{"node": k, "range": [low, high]}}, got {_short(entry)}')
        bounds = entry["range"]
        if not isinstance(bounds, list) or len(bounds) != 2:
            raise _fail(f"{where}.range", f"expected [low, high], got {_short(bounds)}")
        low, high = (_number(b, f"{where}.range") for b in bounds)
        if not low < high:
            raise _fail(f"{where}.range", f"low must be below high, got [{low}, {high}]")
        if "node" in entry:
            node = entry["node"]
            if isinstance(node, bool) or not isinstance(node, int) or node not in rail_nodes:
                raise _fail(f"{where}.node", f"expected the node of a rail ({sorted(rail_nodes) or 'the scene has none'}), got {_short(node)}")
            key, limit = ("node", node), JointLimit((), node, low, high)
        else:
            if dim != 2:
                raise _fail(where, "joint angle limits are for planar scenes only")
            links = _joint_links(entry["links"], f"{where}.links", edges, fixed_ends)
            key, limit = ("links", *links), JointLimit(tuple(links), -1, low, high)
        if key in seen:
            raise _fail(where, "a second limit of the same joint")
        seen.add(key)
        limits.append(limit)
    return tuple(limits)


def _dampers(value, edges: list, fixed_ends: tuple, dim: int) -> tuple[tuple[int, int, float], ...]:
    """The validated dampers (module docstring): each on a joint (`_joint_links`)."""
    if not isinstance(value, list):
        raise _fail("dampers", f"expected a list of dampers, got {_short(value)}")
    if value and dim != 2:
        raise _fail("dampers", "joint damping is for planar scenes only (in 3D it would spin rods about their own axes)")
    dampers, seen = [], set()
    for k, damper in enumerate(value):
        where = f"dampers[{k}]"
        if not isinstance(damper, dict) or set(damper) != {"links", "damping"}:
            raise _fail(where, f'expected {{"links": [e, p] or [e], "damping": number}}, got {_short(damper)}')
        links = _joint_links(damper["links"], f"{where}.links", edges, fixed_ends)
        key = frozenset(links)
        if key in seen:
            raise _fail(f"{where}.links", f"links {links} already have a damper")
        seen.add(key)
        damping = _number(damper["damping"], f"{where}.damping")
        if damping < 0:
            raise _fail(f"{where}.damping", f"must be >= 0, got {damping}")
        dampers.append((links[0], links[1] if len(links) == 2 else -1, damping))
    return tuple(dampers)


def _joint_links(links, where: str, edges: list, fixed_ends: tuple) -> list[int]:
    """The link list of a joint named at `where` (a damper's or a limit's), validated: two
    links meeting at a node, or one link with an end in `fixed_ends` (the nodes that do
    not move off their place: pins and rails' nodes), whose angle is then its own."""
    if not isinstance(links, list) or len(links) not in (1, 2):
        raise _fail(where, f"expected [e, p] or [e], got {_short(links)}")
    if any(isinstance(e, bool) or not isinstance(e, int) or not 0 <= e < len(edges) for e in links):
        raise _fail(where, f"expected link indices 0..{len(edges) - 1}, got {_short(links)}")
    if len(links) == 2 and links[0] == links[1]:
        raise _fail(where, f"link {links[0]} twice (a joint joins two links)")
    if len(links) == 2 and not set(edges[links[0]]) & set(edges[links[1]]):
        raise _fail(where, f"links {links[0]} and {links[1]} share no node (a joint joins links at a node)")
    if len(links) == 1 and not set(edges[links[0]]) & set(fixed_ends):
        raise _fail(where, f"link {links[0]} has no pinned end and no end on a rail (a joint of one link turns it about a pin or a rail's node)")
    return links


_SOURCE_KEYS = {"mjcf", "axes", "nodes"}
# Rows of a source's `axes` must be orthonormal to this accuracy (15-digit JSON passes).
AXES_TOLERANCE = 1e-9


def _source(value, n_nodes: int, dim: int) -> SceneSource:
    """The validated `source` of an imported scene (module docstring)."""
    if not isinstance(value, dict):
        raise _fail("source", f"expected an object, got {_short(value)}")
    if set(value) != _SOURCE_KEYS:
        wrong = sorted(set(value) ^ _SOURCE_KEYS)[0]
        raise _fail(f"source.{wrong}", "unknown key" if wrong in value else "missing required key")
    mjcf = value["mjcf"]
    if not isinstance(mjcf, str) or not mjcf:
        raise _fail("source.mjcf", f"expected the MJCF file's name, got {_short(mjcf)}")
    axes = _points(value["axes"], "source.axes", 3)
    if len(axes) != dim:
        raise _fail("source.axes", f"expected {dim} rows (one per scene axis), got {len(axes)}")
    if not np.allclose(axes @ axes.T, np.eye(dim), rtol=0, atol=AXES_TOLERANCE):
        raise _fail("source.axes", "rows must be orthonormal (unit directions at right angles)")
    nodes = value["nodes"]
    if not isinstance(nodes, list) or len(nodes) != n_nodes:
        raise _fail("source.nodes", f"expected {n_nodes} entries (one per node), got {_short(nodes)}")
    points = []
    for k, node in enumerate(nodes):
        where = f"source.nodes[{k}]"
        if not isinstance(node, dict) or set(node) != {"body", "point"}:
            raise _fail(where, f'expected {{"body": NAME, "point": [x, y, z]}}, got {_short(node)}')
        if not isinstance(node["body"], str) or not node["body"]:
            raise _fail(f"{where}.body", f"expected a body name, got {_short(node['body'])}")
        (point,) = _points([node["point"]], f"{where}.point", 3)
        points.append(NodeSource(node["body"], tuple(float(x) for x in point)))
    return SceneSource(mjcf, tuple(tuple(float(x) for x in row) for row in axes), tuple(points))


def check_scene(scene: Scene) -> None:
    """Physical consistency of a scene's arrays; raises `SceneError` on the first problem."""
    lengths = scene.lengths
    longest = float(lengths.max())
    for k, length in enumerate(lengths):
        if length < MIN_RELATIVE_LENGTH * longest:
            raise _fail(f"links[{k}].length", f"{length:g} is (nearly) zero: below {MIN_RELATIVE_LENGTH:g} of the longest link")
    # Every free node carries mass, of a link with mass or a point mass, so the mass
    # matrix on the constraints is positive definite (a node joined by massless links
    # alone would move at no cost).
    massive = {n for edge, mass in zip(scene.edges, scene.masses) if mass > 0 for n in edge} | {node for node, _ in scene.point_masses}
    for node in scene.free_nodes:
        if node not in massive:
            joined = any(node in edge for edge in scene.edges)
            raise _fail("nodes", f"free node {node} has no mass: it belongs to {'massless links only' if joined else 'no link'} "
                                 "and has no point mass")
    i, j = scene.edge_index.T
    dq = scene.nodes[i] - scene.nodes[j]
    distance = np.linalg.norm(dq, axis=-1)
    stretch = np.abs(distance - lengths) / lengths
    k = int(np.argmax(~(stretch <= LENGTH_TOLERANCE)))  # NaN counts as a violation
    if not stretch[k] <= LENGTH_TOLERANCE:
        raise _fail(
            f"links[{k}]",
            f"initial positions violate the link length: nodes {i[k]}-{j[k]} are {float(distance[k])!r} apart, length is {float(lengths[k])!r}",
        )
    pinned = list(scene.pinned)
    if pinned and np.any(scene.velocities[pinned] != 0):
        bad = next(p for p in pinned if np.any(scene.velocities[p] != 0))
        raise _fail(f"velocities[{bad}]", "a pinned node must have zero velocity")
    for node, axis, _ in scene.rails:
        if np.any(np.delete(scene.velocities[node], axis) != 0):
            raise _fail(f"velocities[{node}]", f"node {node} slides along axis {axis} only: its other velocity components must be zero")
    dqd = scene.velocities[i] - scene.velocities[j]
    speed = max(float(np.abs(scene.velocities).max()), 1.0)
    rate = np.abs(np.sum(dq * dqd, axis=-1)) / lengths / speed
    k = int(np.argmax(~(rate <= LENGTH_TOLERANCE)))
    if not rate[k] <= LENGTH_TOLERANCE:
        raise _fail(
            "velocities",
            f"initial velocities stretch links[{k}] (nodes {i[k]}-{j[k]}): rate of length change {rate[k] * speed:.3g}",
        )


def scene_to_dict(scene: Scene) -> dict:
    """The JSON schema form of a scene; `scene_from_dict(scene_to_dict(s))` reproduces `s` exactly."""
    data = {
        "name": scene.name,
        "gravity": scene.gravity_vector.tolist() if scene.lateral_gravity else float(scene.gravity),
        "drag": float(scene.drag),
        "nodes": scene.nodes.tolist(),
        "velocities": scene.velocities.tolist(),
        "pinned": list(scene.pinned),
        "links": [
            {"nodes": list(edge), "mass": float(m), "inertia": float(inertia), "length": float(length), "type": t}
            for edge, m, inertia, length, t in zip(
                scene.edges, scene.masses, scene.inertias, scene.lengths, scene.link_types, strict=True
            )
        ],
    }
    if scene.dampers:
        data["dampers"] = [{"links": [e] if p < 0 else [e, p], "damping": damping} for e, p, damping in scene.dampers]
    if scene.point_masses:
        data["point_masses"] = [{"node": node, "mass": mass} for node, mass in scene.point_masses]
    if scene.rails:
        data["rails"] = [{"node": node, "axis": axis, "damping": damping} for node, axis, damping in scene.rails]
    if scene.limits:
        data["limits"] = [limit.to_dict() for limit in scene.limits]
    if scene.source is not None:
        data["source"] = scene.source.to_dict()
    return data


def scene_to_json(scene: Scene) -> str:
    return json.dumps(scene_to_dict(scene), indent=1) + "\n"


def load_scene_file(path: str | os.PathLike) -> Scene:
    """Read and validate a scene JSON file; every failure is one `SceneError` line."""
    path = Path(path)
    if not path.exists():
        raise SceneError(f"{path}: no such scene file")
    if not path.is_file():
        raise SceneError(f"{path}: not a regular file")
    size = path.stat().st_size
    if size > MAX_SCENE_FILE_BYTES:
        raise SceneError(f"{path}: file is {size / 2**20:.0f} MiB, larger than the {MAX_SCENE_FILE_BYTES // 2**20} MiB limit for a scene")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise SceneError(f"{path}: not a text (UTF-8) file") from None
    except OSError as err:
        raise SceneError(f"{path}: cannot read: {err.strerror}") from None
    try:
        data = json.loads(text, parse_constant=_reject_constant)
    except RecursionError:
        raise SceneError(f"{path}: not a scene: JSON nested too deeply") from None
    except json.JSONDecodeError as err:
        raise SceneError(f"{path}: not valid JSON: {err.msg} at line {err.lineno} column {err.colno}") from None
    except ValueError as err:
        raise SceneError(f"{path}: {err}") from None
    deep = archives.json_depth_problem(data)
    if deep:
        raise SceneError(f"{path}: not a scene: {deep}")
    try:
        return scene_from_dict(data)
    except SceneError as err:
        raise SceneError(f"{path}: {err}") from None


def _reject_constant(name: str):
    # JSON has no NaN/Infinity; Python's json accepts them unless told otherwise.
    raise ValueError(f"not valid JSON: {name} is not a JSON number (scene values must be finite)")
