"""MJCF rendering of a scene: pure Python, no `import mujoco` (`lgnn.engines.mujoco`
compiles the text; `lgnn mjcf` writes the built-in scenes' files into mjcf/, nested,
and mjcf/maximal/: `write_builtin_files`).

`render(scene, dt, form)` writes one of two forms (`Form`), each from its
`scene_layout(scene, form)`:

- "maximal": every link joining a free node is a body directly under the world, its
  frame at the rod's centre, with slide x, slide y and hinge z (the planar free body;
  in 3D a <freejoint/>); a node's site sits on its first link (a pin's
  on the world), and every other link end at that node is tied to it by a two-site
  `connect` (`Layout.ties`). Depth 1 and a diagonal mass matrix, at any size and with
  any loops; the joints are as soft as `MAXIMAL_SOLREF_STEPS` (errors measured there).
- "nested", below.

- `scene_layout(scene)` (nested) is the scene's spanning tree: every link is a body hinged at
  one of its end nodes (axis z, normal to the plane). The tree grows breadth-first
  from the pinned nodes (world-fixed); a component without pins gets a free planar
  root (slide x, slide y, hinge z). A link whose far node is already in the tree
  still becomes a body (it has mass) and closes its loop with a two-site `connect`
  equality from its tip to that node. Links between two pinned nodes never move and
  get no body.
- Carts (nested form only, `nested_only`): a rail's node is a body `cart{k}` under the
  world on a slide along the rail's axis (its damping and, as a range, its limit),
  carrying the node's point mass; the tree also grows from it, as from a pin, and the
  links hinged there sit in it. Any other point mass is a body `mass{k}` welded at its
  node, so a link body's centre of mass (where drag acts) stays its rod's centre. A
  hinge's limit is its `range`, in MuJoCo's coordinates of the rendered model (zero at
  the scene's initial pose: `joint_ranges`); the MuJoCo engines run with limits off and
  stop where the Lagrangian engine does.
- Spatial (3D) scenes: the same layouts, with a ball joint for each hinge and a
  <freejoint/> for each free root; a rod's inertia is the scene's about every axis
  normal to it and `AXIAL_INERTIA_FRACTION` of that about its own axis (`rod_inertia`).
- `render(scene, dt)` (also `scene_to_mjcf`) renders the MJCF text: explicit `<inertial>` (the link's
  mass at the rod's centre, the scene's moment of inertia about z), contacts off,
  gravity `(0, -g, 0)` (or the scene's gravity vector), a site `node{k}` on every node, RK4, and the scene's initial
  velocities, where it has any, as the keyframe `INITIAL_KEY` (`initial_qvel`). Loop equalities are made
  stiff with `solref` of `SOLREF_STEPS` time steps and `solimp` near 1, so the MJCF
  depends on `dt`. Numbers are written as the shortest text that reads back to the
  same double, so the model reproduces the scene exactly (MuJoCo C agrees with the
  Lagrangian engine to ~1e-13 on open chains).
- Nesting: one `<body>` per tree level, and MuJoCo's XML parser (tinyxml2) refuses
  elements nested deeper than 500, so a tree deeper than `MAX_BODY_DEPTH` (496
  bodies, measured: chain496 compiles, chain497 is "XML parse error 18") cannot be
  rendered nested; `render` refuses it with a `SceneError` (the maximal form runs it).

`form_error(scene, form, h, duration)` is either form's expected max node position
error at MuJoCo step `h` (models fitted on open chains over 1 s,
`MAXIMAL_ERROR_COEFFICIENT`), and `maximal_substeps(scene, dt, tolerance)` the MuJoCo
steps per `dt` that bring the maximal form within `tolerance`: what the MuJoCo engines
state as their `accuracy` and how MJX and MuJoCo Warp step the maximal form.

Why a small string writer and not `mujoco.MjSpec` (issue 12 asked; measured on
mujoco 4.0.0, 2-core CPU): MjSpec builds and compiles chain1000 (4.0 s) but not
chain1024 ("depth limit exceeded in signature computation": its own limit is 1023
bodies), so it moves the nesting limit rather than lifting it; and its `to_xml`
writes 6 significant digits with no option for more (chain4's rendered positions off
by 4e-7), so the files in mjcf/ would no longer reproduce the scene, or the engine
and the files would come from two different writers. The string writer is the same
length, exact, and one path for both. MuJoCo C on chain1000 would also cost ~0.45 s
per RK4 step (dense nv = 1000; the Lagrangian engine ~3 ms, results/stability.md).
"""

from __future__ import annotations

import collections
import dataclasses
import math
import os
import re
from pathlib import Path
from typing import Literal, get_args
from xml.sax.saxutils import escape, quoteattr

import numpy as np

from lgnn.errors import ConfigError, SceneError
from lgnn.scene import Scene

# Loop-closure stiffness: MuJoCo's constraint time constant in time steps (2 is the
# smallest MuJoCo accepts without clamping) and an impedance near 1 (nearly hard
# constraint). Measured on a closed 4-link loop: 5e-10 agreement with an exact solver.
SOLREF_STEPS = 2.0
# The maximal form's joints are all `connect` equalities, so its accuracy is set by
# this softness. Max node error against the Lagrangian engine over 0.5 s (RK4), dt 1e-4
# / 1e-3, solref 2 dt: tree 1.9e-9 / 1.9e-7, loop6 2.1e-7 / 2.4e-5, T1 9.1e-7 / 6.8e-5
# (~dt^2); 4 dt is 2-4x worse; solimp 0.9999 .. 0.999999 changes nothing; 1 dt (refsafe
# off, which MuJoCo otherwise clamps to 2 dt) gains 2.5x on T1 and nothing on loop6,
# 0.5 dt loses 100x: 2 dt, MuJoCo's safe minimum, is the default.
MAXIMAL_SOLREF_STEPS = 2.0
# A spatial rod's moment of inertia about its own axis, as a fraction of the one about
# its normals. The node description has no spin about a rod's axis and no force
# excites it (gravity and the joint forces act on the axis; the Euler equations of an
# axisymmetric body keep a zero axial spin zero), so the fraction does not change the
# motion: measured (MuJoCo C, RK4, dt 1e-3, 0.1 s, chain4-3d and chain16-3d) 1e-3, 1e-1
# and 1 agree with the Lagrangian engine alike (2.8e-12, 9.0e-11). But it sets the
# conditioning of the joint-space mass matrix, whose smallest eigenvalues are the
# rods' axial spins: at 1e-3 chain16-3d's was 2.2e8, beyond float32, and MuJoCo Warp's
# accelerations were NaN from the first step. At 1 (an isotropic inertia, as planar
# links get) 3D chains are conditioned as their planar ones (chain16 2.2e5, chain100
# 3e8); MuJoCo's triangle inequality caps the fraction at 2.
AXIAL_INERTIA_FRACTION = 1.0
SOLIMP = (0.9999, 0.9999, 0.001, 0.5, 2.0)
# Constraint solver: equality-only problems are quadratic, so Newton converges in one
# or two iterations; the tolerance only stops it at round-off.
SOLVER_TOLERANCE = 1e-14
SOLVER_ITERATIONS = 20
# The MuJoCo engines' error models: the max node position error (m) over a run of up
# to 1 s against exact motion, on an open chain or tree of alike links under gravity
# (`error_model_holds`), `depth` links deep (`scene_layout(scene).depth`), gravity g,
# link length l, MuJoCo step h (`form_error`):
#   nested (RK4 on exact joints):    NESTED_ERROR_COEFFICIENT[dim] * depth^5 * g^2 * h^4 / l
#   maximal (soft `connect` joints): MAXIMAL_ERROR_COEFFICIENT[dim] * depth^3 * g * h^2
# (the dimensionless error/l as a power of g h^2 / l). Each coefficient is 1.25x the
# largest measured over 1 s at dt 1e-4 by `tools/maximal_error.py` (its docstring has
# the commands): MuJoCo C on chain(N, seed), N = 4..64, seeds 0-3 and 5 (planar,
# released from rest), and spatial_chain(N, seed), N = 4..64, seeds 0-1 (3D, released
# spinning: up to 2x (maximal) and 90x (nested) the planar coefficients), against the
# nested form at dt / 4; MJX and MuJoCo Warp step the same model with the same
# arithmetic. Largest measured: maximal 5.8e-4 (2D), 1.27e-3 (3D); nested 6.5e-4 (2D,
# errors under 1e-12 are round-off and left out), 5.6e-2 (3D). The maximal error falls
# as h^2 (measured at h / 2: ratio 4.0). The largest coefficients come from short
# chains (4-24 links); on 64 links they are 1.3-40x smaller, so the models overstate
# long chains' errors by as much (and the maximal form's substeps by its square root).
# Other scenes differ by more than the margin (maximal form, dt 1e-4: a branching tree
# of unequal links 14x chain4's coefficient, chain8-mixed 70x), so the models say
# nothing of them.
MAXIMAL_ERROR_COEFFICIENT = {2: 7.2e-4, 3: 1.6e-3}
NESTED_ERROR_COEFFICIENT = {2: 8.2e-4, 3: 7e-2}
# The run length (s) the models hold for. Beyond it the chains' chaos amplifies the
# error faster than in proportion (chain(40, seed=1), maximal, dt 1e-4: 1.4e-6, 7.4e-6,
# 3.9e-5 after 1, 2, 3 s; `tools/maximal_error.py --links 40 --seeds 1 --substeps 1
# --duration 3`), so nothing is stated for longer runs.
MODELLED_DURATION = 1.0
# The tolerance the maximal form's step is chosen to meet (`maximal_substeps`), as the
# ground truth's max node error over 1 s (issue 29).
MAXIMAL_TOLERANCE = 1e-6
# A cart's mass where its rail's node has no point mass, as a fraction of the scene's
# mass: MuJoCo refuses a moving body without mass; the motion changes by about this.
CART_MASS_FLOOR = 1e-12
# The custom numeric holding a rendered scene's drag, which MuJoCo has no element for.
DRAG_NUMERIC = "lgnn_drag"
# The keyframe holding a rendered scene's initial velocities (`initial_qvel`).
INITIAL_KEY = "initial"
# Drawing sizes (viewer only, no physics): capsule and site radius per unit length.
GEOM_RADIUS = 0.03
SITE_RADIUS = 0.04
# Deepest body tree MuJoCo's XML parser accepts: its element depth limit (500) less
# <mujoco>, <worldbody> and the innermost body's children (measured, module docstring).
MAX_BODY_DEPTH = 496

# The two MJCF forms of a scene (module docstring): "nested" (joint coordinates, one
# body per tree level) and "maximal" (every link a body under the world, joined by
# `connect` equalities). Engines take a `Form` or "auto" (their own best choice).
Form = Literal["nested", "maximal"]
FORMS: tuple[str, ...] = get_args(Form)


@dataclasses.dataclass(frozen=True)
class LinkBody:
    """One MuJoCo body: scene link `link` hinged at node `base`, far end at node `tip`.

    `parent` indexes `Layout.bodies` (-1: world, or a cart, which never turns).
    `free_root` bodies carry a planar free joint; `closes_loop` bodies end at a node
    owned by another body (or a pin, or a cart) and are tied to it by a `connect`
    equality; `cart` indexes `Layout.carts` for a body hinged at a rail's node, which
    sits in that cart's body (-1: none).
    """

    link: int
    base: int
    tip: int
    parent: int
    free_root: bool = False
    closes_loop: bool = False
    cart: int = -1


@dataclasses.dataclass(frozen=True)
class Layout:
    """Spanning tree of a scene. `bodies` are in tree order (parents first);
    `node_body[k]` is the body carrying node k's site (-1: world, for pins, and a
    cart, for a rail's node); `static_links` join two pins and have no body; `carts`
    are the scene's rails, `(node, axis)`, each a body of its own on a slide joint
    under the world (nested form only)."""

    bodies: tuple[LinkBody, ...]
    node_body: tuple[int, ...]
    static_links: tuple[int, ...]
    form: Form = "nested"
    carts: tuple[tuple[int, int], ...] = ()

    @property
    def origin_weight(self) -> float:
        """Where a body's frame sits on its link, from `base` (0) to `tip` (1): nested
        bodies hinge at their base node, maximal ones sit at the rod's centre (a
        diagonal mass matrix)."""
        return 0.5 if self.form == "maximal" else 0.0

    @property
    def ties(self) -> tuple[tuple[int, int], ...]:
        """`(body, node)` pairs joined by a `connect` equality: the body's end at `node`
        to the site of the node's owner (a pin: the world). Nested: loop-closing tips;
        maximal: every link end the link does not own."""
        ties = []
        for k, body in enumerate(self.bodies):
            ends = (body.base, body.tip) if self.form == "maximal" else (body.tip,) if body.closes_loop else ()
            ties += [(k, node) for node in ends if self.node_body[node] != k]
        return tuple(ties)

    @property
    def cart_of_node(self) -> dict[int, int]:
        """`{rail node: index in carts}`."""
        return {node: c for c, (node, _) in enumerate(self.carts)}

    def children(self) -> tuple[dict, dict]:
        """`(children, on_cart)`: the indices of `bodies` under each body (-1: the world),
        and those sitting in each cart (by index in `carts`), in tree order; both
        `defaultdict(list)`."""
        children, on_cart = collections.defaultdict(list), collections.defaultdict(list)
        for k, body in enumerate(self.bodies):
            (on_cart[body.cart] if body.cart >= 0 else children[body.parent]).append(k)
        return children, on_cart

    @property
    def depth(self) -> int:
        """Longest chain of bodies from the world (what MJX compile time grows with)."""
        depth = []
        for body in self.bodies:
            depth.append(1 + (depth[body.parent] if body.parent >= 0 else 0))
        return max(depth, default=0)


def scene_layout(scene: Scene, form: Form = "nested") -> Layout:
    """The bodies of `form`: nested, the breadth-first spanning tree rooted at the
    pinned nodes and the rails' nodes (carts); maximal, one free body per moving link
    (module docstring). `SceneError` for rails, point masses and joint limits in the
    maximal form (rendered in the nested form only)."""
    check_form(form)
    if form == "maximal":
        if nested_only(scene):
            raise SceneError(f"{scene.name}: joint damping, rails, point masses and joint limits are rendered in the nested form only "
                             "(the maximal form's joints are connect equalities)")
        return _maximal_layout(scene)
    adjacency = [[] for _ in range(scene.n_nodes)]
    for e, (i, j) in enumerate(scene.edges):
        adjacency[i].append((e, j))
        adjacency[j].append((e, i))
    pinned = set(scene.pinned)
    static = tuple(e for e, (i, j) in enumerate(scene.edges) if i in pinned and j in pinned)
    used = set(static)
    node_body: list[int | None] = [None] * scene.n_nodes
    bodies: list[LinkBody] = []

    cart_of = {node: c for c, (node, _, _) in enumerate(scene.rails)}

    def grow(queue: collections.deque) -> None:
        while queue:
            a = queue.popleft()
            for e, b in adjacency[a]:
                if e in used:
                    continue
                used.add(e)
                closes = node_body[b] is not None
                bodies.append(LinkBody(e, a, b, node_body[a], closes_loop=closes, cart=cart_of.get(a, -1)))
                if not closes:
                    node_body[b] = len(bodies) - 1
                    queue.append(b)

    # Pins and carts hold their nodes: the tree grows from both (`Scene.grounded_nodes`).
    for p in scene.grounded_nodes:
        node_body[p] = -1
    grow(collections.deque(scene.grounded_nodes))
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
    return Layout(tuple(bodies), tuple(node_body), static, carts=tuple((node, axis) for node, axis, _ in scene.rails))


def nested_only(scene: Scene) -> bool:
    """Whether only the nested form renders `scene`: it has joint damping, rails, point
    masses or joint limits, which sit on the nested form's joints and bodies."""
    return bool(scene.dampers or scene.rails or scene.point_masses or scene.limits)


def _maximal_layout(scene: Scene) -> Layout:
    # Every link joining a free node is a body under the world; a node's site sits on
    # the first such link (edge order) or, pinned, on the world.
    pinned = set(scene.pinned)
    static = tuple(e for e, (i, j) in enumerate(scene.edges) if i in pinned and j in pinned)
    node_body = [-1 if k in pinned else None for k in range(scene.n_nodes)]
    bodies = []
    for e, (i, j) in enumerate(scene.edges):
        if e in static:
            continue
        for node in (i, j):
            if node_body[node] is None:
                node_body[node] = len(bodies)
        tied = node_body[i] != len(bodies) or node_body[j] != len(bodies)
        bodies.append(LinkBody(e, i, j, -1, free_root=True, closes_loop=tied))
    return Layout(tuple(bodies), tuple(node_body), static, "maximal")


def rod_inertia(inertia: float, direction: np.ndarray) -> tuple[float, ...]:
    """MJCF `fullinertia` (Ixx, Iyy, Izz, Ixy, Ixz, Iyz) of a thin rod along
    `direction` (3,): `inertia` about every axis normal to it and
    `AXIAL_INERTIA_FRACTION * inertia` about its own axis."""
    u = np.asarray(direction, np.float64) / np.linalg.norm(direction)
    tensor = inertia * (np.eye(3) - (1 - AXIAL_INERTIA_FRACTION) * np.outer(u, u))
    return (*np.diag(tensor), tensor[0, 1], tensor[0, 2], tensor[1, 2])


def error_model_holds(scene: Scene) -> bool:
    """Whether the error models (`form_error`) were fitted on scenes like `scene`: an open
    chain or tree (no loop, also none through the world between two pins), no drag,
    gravity, every link alike (length, mass, inertia), and none of the nested form's
    own parts (joint damping, carts, point masses, limits: `nested_only`)."""
    if nested_only(scene):
        return False
    layout = scene_layout(scene)
    alike = all(np.ptp(values) <= 1e-12 * np.max(np.abs(values)) for values in (scene.lengths, scene.masses, scene.inertias))
    loops = layout.static_links or any(body.closes_loop for body in layout.bodies)
    return alike and not loops and not scene.drag and not scene.lateral_gravity and float(scene.gravity) > 0


def form_error(scene: Scene, form: Form, h: float, duration: float = MODELLED_DURATION) -> float | None:
    """The expected max node position error (m) of `scene` in `form` at MuJoCo step `h`
    over a run of `duration` seconds (the models above `MAXIMAL_ERROR_COEFFICIENT`);
    None where they do not hold (`error_model_holds`, runs longer than
    `MODELLED_DURATION`)."""
    check_form(form)
    if not error_model_holds(scene) or duration > MODELLED_DURATION:
        return None
    depth, g, length = scene_layout(scene).depth, float(scene.gravity), float(scene.lengths[0])
    if form == "maximal":
        return MAXIMAL_ERROR_COEFFICIENT[scene.dim] * depth**3 * g * h**2
    return NESTED_ERROR_COEFFICIENT[scene.dim] * depth**5 * g**2 * h**4 / length


def maximal_substeps(scene: Scene, dt: float, tolerance: float = MAXIMAL_TOLERANCE) -> int:
    """MuJoCo steps per step `dt` in the maximal form: the fewest `s` whose step `dt / s`
    has `form_error(scene, "maximal", dt / s) <= tolerance` over `MODELLED_DURATION`
    (the error falls as h^2; longer runs step the same); 1 where the model does not
    hold (nothing is promised there)."""
    if not (np.isfinite(tolerance) and tolerance > 0):
        raise ConfigError(f"tolerance must be a positive number, got {tolerance}")
    error = form_error(scene, "maximal", dt)
    if error is None:
        return 1
    substeps = max(1, math.ceil(math.sqrt(error / tolerance)))
    while form_error(scene, "maximal", dt / substeps) > tolerance:  # round-off of the square root
        substeps += 1
    return substeps


def check_form(form: str) -> None:
    """`ConfigError` unless `form` is one of `FORMS`."""
    if form not in FORMS:
        raise ConfigError(f"unknown MJCF form {form!r} (choose from {', '.join(FORMS)})")


def _num(x) -> str:
    # Shortest repr that round-trips: the MJCF reproduces the scene exactly.
    x = float(x)
    return "0" if x == 0 else repr(x)


def _vec(*xs) -> str:
    return " ".join(_num(x) for x in xs)


def render(scene: Scene, dt: float = 1e-4, form: Form = "nested") -> str:
    """The MJCF text of `scene` in `form` for time step `dt` (module docstring)."""
    layout = scene_layout(scene, form)
    damping = joint_damping(scene, layout)
    hinge_range, slide_range = joint_ranges(scene, layout)
    if layout.depth > MAX_BODY_DEPTH:
        raise SceneError(
            f"{scene.name}: spanning tree of depth {layout.depth} is too deep to render as nested MJCF bodies "
            f"(MuJoCo parses at most {MAX_BODY_DEPTH}; the maximal form has no such limit)"
        )
    maximal = form == "maximal"
    nodes = np.asarray(scene.nodes, np.float64)
    scale = float(np.median(scene.lengths))
    children, on_cart = layout.children()
    cart_of = layout.cart_of_node
    sites = collections.defaultdict(list)  # a cart's node's site is written in its cart's body
    for k, owner in enumerate(layout.node_body):
        if k not in cart_of:
            sites[owner].append(k)
    # A point mass sits on the body carrying its node's site, as a body welded there
    # (so a link body's own centre of mass, where drag acts, stays its rod's centre);
    # a cart's is the cart's own mass, and a pin's never moves.
    pinned = set(scene.pinned)
    welded = collections.defaultdict(list)
    for node, mass in scene.point_masses:
        if node not in cart_of and node not in pinned:
            welded[layout.node_body[node]].append((node, mass))
    point_mass = dict(scene.point_masses)
    ties = collections.defaultdict(list)
    for k, node in layout.ties:
        ties[k].append(node)
    site_size = f"{SITE_RADIUS * scale:.3g}"
    total_mass = float(np.sum(scene.masses)) + sum(mass for _, mass in scene.point_masses)

    spatial = scene.dim == 3

    def pos3(x) -> str:
        # A scene point as MJCF's 3D vector (planar scenes lie at z = 0).
        return _vec(*x) if spatial else _vec(*x, 0)

    def origin(index: int) -> np.ndarray:
        if index < 0:
            return np.zeros(scene.dim)
        body = layout.bodies[index]
        return nodes[body.base] + layout.origin_weight * (nodes[body.tip] - nodes[body.base])

    def parent_origin(body: LinkBody) -> np.ndarray:
        return nodes[layout.carts[body.cart][0]] if body.cart >= 0 else origin(body.parent)

    def node_sites(index: int, indent: str) -> list[str]:
        o = origin(index)
        return [
            f'{indent}<site name="node{k}" pos="{pos3(nodes[k] - o)}" size="{site_size}"/>' for k in sites[index]
        ]

    def body_xml(index: int, indent: str) -> list[str]:
        body = layout.bodies[index]
        e = body.link
        o = origin(index)
        pos = o - parent_origin(body)
        base, tip = nodes[body.base] - o, nodes[body.tip] - o
        mass, inertia = float(scene.masses[e]), float(scene.inertias[e])
        centre_point = (0.5 - layout.origin_weight) * (tip - base)
        points = welded[index]
        if mass == 0:
            # MuJoCo refuses a moving body without mass: a massless rod's body carries
            # its welded point masses itself, their inertia about their centre of mass.
            if not points:
                raise SceneError(f"scene {scene.name!r}: link {e} is massless and no point mass moves with its MuJoCo body, "
                                 "which MuJoCo refuses (give its tip node a point mass)")
            if scene.drag:
                raise SceneError(f"scene {scene.name!r}: drag on massless link {e} acts at its rod's centre, which its "
                                 "MuJoCo body (its point masses') does not have")
            weights = np.asarray([point for _, point in points])
            offsets = np.asarray([nodes[node] - o for node, _ in points])
            mass = float(weights.sum())
            centre_point = weights @ offsets / mass
            spread = np.pad(offsets - centre_point, ((0, 0), (0, 3 - scene.dim)))
            # Their inertia tensor about it (a point's own is zero); planar hinges see Izz.
            points_tensor = np.einsum("k,kij->ij", weights, np.einsum("ka,ka->k", spread, spread)[:, None, None] * np.eye(3)
                                      - np.einsum("ki,kj->kij", spread, spread))
            inertia = float(points_tensor[2, 2])
            points = []
        else:
            points_tensor = None
        # A zero inertia (a point-mass rod, point masses at one place) is raised to a
        # negligible floor because MuJoCo rejects zero principal moments.
        inertia = max(inertia, 1e-12 * mass * float(scene.lengths[e]) ** 2)
        inner = indent + "  "
        lines = [f'{indent}<body name="link{e}" pos="{pos3(pos)}">']
        centre = pos3(centre_point)
        if spatial:
            # A free root: a <freejoint/> (position and orientation of the body frame);
            # every other body turns about its base node in a ball joint.
            lines.append(f'{inner}<freejoint name="link{e}_free"/>' if body.free_root else f'{inner}<joint name="link{e}_ball" type="ball"/>')
            floor = 1e-12 * mass * float(scene.lengths[e]) ** 2
            tensor = (rod_inertia(inertia, tip - base) if points_tensor is None
                      else [*(np.diag(points_tensor) + floor), points_tensor[0, 1], points_tensor[0, 2], points_tensor[1, 2]])
            lines.append(f'{inner}<inertial pos="{centre}" mass="{_num(mass)}" fullinertia="{_vec(*tensor)}"/>')
        else:
            if body.free_root:
                lines.append(f'{inner}<joint name="link{e}_x" type="slide" axis="1 0 0"/>')
                lines.append(f'{inner}<joint name="link{e}_y" type="slide" axis="0 1 0"/>')
            damped = f' damping="{_num(damping[index])}"' if damping[index] else ""
            ranged = f' range="{_vec(*hinge_range[index])}"' if hinge_range[index] else ""
            lines.append(f'{inner}<joint name="link{e}_hinge" type="hinge" axis="0 0 1"{damped}{ranged}/>')
            # Only Izz acts on a planar hinge; Ixx = Iyy = Izz satisfies MuJoCo's
            # triangle inequality.
            lines.append(f'{inner}<inertial pos="{centre}" mass="{_num(mass)}" diaginertia="{_vec(inertia, inertia, inertia)}"/>')
        lines.append(
            f'{inner}<geom name="link{e}" type="capsule" fromto="{pos3(base)} {pos3(tip)}" '
            f'size="{GEOM_RADIUS * scale:.3g}" rgba="{_link_color(scene.link_types[e])}"/>'
        )
        for node in ties[index]:
            lines.append(f'{inner}<site name="{_tie_site(body, node)}" pos="{pos3(nodes[node] - o)}" size="{site_size}" rgba="1 0 0 1"/>')
        lines += node_sites(index, inner)
        for node, point in points:
            # A point has no moment of inertia of its own (MuJoCo allows that on a
            # body without joints).
            lines.append(f'{inner}<body name="mass{node}" pos="{pos3(nodes[node] - o)}"><inertial pos="0 0 0" mass="{_num(point)}" '
                         'diaginertia="0 0 0"/></body>')
        for child in children[index]:
            lines += body_xml(child, inner)
        lines.append(f"{indent}</body>")
        return lines

    def cart_xml(c: int, indent: str) -> list[str]:
        # A rail's node: a body on a slide joint along its scene axis, carrying the
        # node's point mass (MuJoCo refuses a moving body without mass: one without
        # gets `CART_MASS_FLOOR` of the scene's), the slide's damping and its range.
        node, axis = layout.carts[c]
        inner = indent + "  "
        damped = next((f' damping="{_num(b)}"' for k, _, b in scene.rails if k == node and b), "")
        ranged = f' range="{_vec(*slide_range[c])}"' if slide_range[c] else ""
        mass = point_mass.get(node, CART_MASS_FLOOR * total_mass)
        floor = _num(CART_MASS_FLOOR * mass * scale**2)  # it never turns: any inertia will do
        return [
            f'{indent}<body name="cart{node}" pos="{pos3(nodes[node])}">',
            f'{inner}<joint name="cart{node}_slide" type="slide" axis="{pos3(np.eye(scene.dim)[axis])}"{damped}{ranged}/>',
            f'{inner}<inertial pos="0 0 0" mass="{_num(mass)}" diaginertia="{floor} {floor} {floor}"/>',
            f'{inner}<geom name="cart{node}" type="box" size="{2 * GEOM_RADIUS * scale:.3g} {GEOM_RADIUS * scale:.3g} {GEOM_RADIUS * scale:.3g}" '
            'rgba="0.3 0.3 0.3 1"/>',
            f'{inner}<site name="node{node}" pos="0 0 0" size="{site_size}"/>',
            *(line for child in on_cart[c] for line in body_xml(child, inner)),
            f"{indent}</body>",
        ]

    # In front of the scene along +z (the viewer's default assumes z up).
    camera = np.concatenate([nodes.mean(0)[:2], [(nodes[:, 2].max() if spatial else 0.0) + 2 * max(np.ptp(nodes, 0).max(), scale)]])
    solref = f"{_num((MAXIMAL_SOLREF_STEPS if maximal else SOLREF_STEPS) * dt)} 1"
    solimp = _vec(*SOLIMP)
    what = "maximal coordinates: every link a body under the world, joined by connect equalities" if maximal else "nested bodies"
    lines = [
        f"<mujoco model={quoteattr(scene.name)}>",
        # "--" may not appear inside an XML comment.
        f"  <!-- Rendered by lgnn.engines.mjcf.render from scene {escape(repr(scene.name)).replace('--', '- -')} "
        f"({scene.n_nodes} nodes, {scene.n_links} links, pins {list(scene.pinned)}); dt {dt:g}"
        + (f"; {what}. -->" if maximal else ". -->"),
    ]
    if layout.static_links:
        lines.append(f"  <!-- Links {list(layout.static_links)} join two pins: they never move and have no body. -->")
    if scene.drag:
        lines.append(f"  <!-- Drag {scene.drag:g} on link centre velocities is applied by lgnn (xfrc_applied), not modelled here. -->")
        # Kept for `lgnn scene import` (MuJoCo ignores custom numerics).
        lines += ["  <custom>", f'    <numeric name="{DRAG_NUMERIC}" data="{_num(scene.drag)}"/>', "  </custom>"]
    lines += [
        '  <compiler angle="radian" autolimits="true"/>',
        f'  <option timestep="{_num(dt)}" integrator="RK4" gravity="{_vec(*np.pad(scene.gravity_vector, (0, 3 - scene.dim)))}" '
        f'solver="Newton" tolerance="{_num(SOLVER_TOLERANCE)}" iterations="{SOLVER_ITERATIONS}" jacobian="{"sparse" if maximal else "dense"}">',
        '    <flag contact="disable"/>',
        "  </option>",
        '  <default><geom contype="0" conaffinity="0"/></default>',
        "  <worldbody>",
        f'    <light pos="0 0 {10 * scale:.3g}" dir="0 0 -1"/>',
        f'    <camera name="front" pos="{" ".join(f"{x:.3g}" for x in camera)}" xyaxes="1 0 0 0 1 0"/>',
    ]
    lines += node_sites(-1, "    ")
    for c in range(len(layout.carts)):
        lines += cart_xml(c, "    ")
    for child in children[-1]:
        lines += body_xml(child, "    ")
    lines.append("  </worldbody>")
    if layout.ties:
        lines.append("  <equality>")
        for k, node in layout.ties:
            body = layout.bodies[k]
            name = f"link{body.link}_node{node}" if maximal else f"loop{body.link}"
            lines.append(
                f'    <connect name="{name}" site1="{_tie_site(body, node)}" site2="node{node}" '
                f'solref="{solref}" solimp="{solimp}"/>'
            )
        lines.append("  </equality>")
    qvel = initial_qvel(scene, layout)
    if np.any(qvel):
        # The scene's initial velocities (its positions are the rendered pose, qpos0).
        lines += ["  <keyframe>", f'    <key name="{INITIAL_KEY}" qvel="{_vec(*qvel)}"/>', "  </keyframe>"]
    lines.append("</mujoco>")
    return "\n".join(lines) + "\n"


def joint_damping(scene: Scene, layout: Layout) -> list[float]:
    """Each body's hinge damping: the scene's damper between its link and its parent's
    (a pin's or a cart's: the world); `SceneError` for a damper no hinge of `layout`
    carries (one between two links of which neither is the other's parent in the
    spanning tree)."""
    damping = [0.0] * len(layout.bodies)
    if not scene.dampers:
        return damping
    body_of = {body.link: k for k, body in enumerate(layout.bodies)}
    for e, p, value in scene.dampers:
        for child, parent in ((e, p), (p, e)):
            k = body_of.get(child)
            if k is not None and not layout.bodies[k].free_root and parent == (layout.bodies[layout.bodies[k].parent].link if layout.bodies[k].parent >= 0 else -1):
                damping[k] = value
                break
        else:
            raise SceneError(f"{scene.name}: the damper between links {e} and {p} is on no joint of the nested MJCF's spanning tree")
    return damping


def joint_ranges(scene: Scene, layout: Layout) -> tuple[list, list]:
    """`(hinge, slide)`: each body's hinge range and each cart's slide range (None where
    the scene has no limit there), in MuJoCo's coordinates of the rendered model, which
    are zero at the scene's initial pose: the scene's limit (`Scene.limits`, its angle
    or coordinate) less its initial value, in the hinge's sense. `SceneError` for a
    limit no hinge of `layout` carries (as `joint_damping`)."""
    hinge, slide = [None] * len(layout.bodies), [None] * len(layout.carts)
    if not scene.limits:
        return hinge, slide
    from lgnn.metrics import limit_values

    initial = limit_values(scene, np.asarray(scene.nodes, np.float64)[None])[0]
    cart_of = layout.cart_of_node
    body_of = {body.link: k for k, body in enumerate(layout.bodies)}

    def parent_link(k: int) -> int:
        parent = layout.bodies[k].parent
        return layout.bodies[parent].link if parent >= 0 else -1

    for limit, value in zip(scene.limits, initial):
        low, high = limit.low - value, limit.high - value
        if not limit.links:
            slide[cart_of[limit.node]] = (low, high)
            continue
        e, p = limit.links if len(limit.links) == 2 else (limit.links[0], -1)
        # The scene's angle turns link e from link p (a hinge's sense, +z); the other
        # way round where p is the child.
        for child, parent, sense in ((e, p, 1.0), (p, e, -1.0)):
            k = body_of.get(child)
            if k is not None and not layout.bodies[k].free_root and parent_link(k) == parent:
                hinge[k] = (low, high) if sense > 0 else (-high, -low)
                break
        else:
            raise SceneError(f"{scene.name}: the limit of links {list(limit.links)} is on no joint of the nested MJCF's spanning tree")
    return hinge, slide


def initial_qvel(scene: Scene, layout: Layout) -> np.ndarray:
    """MuJoCo's `qvel` of `scene`'s initial velocities in the rendered model of `layout`,
    whose pose is the scene's initial one (every body frame aligned with the world):
    a hinge or ball joint's rate is its link's angular velocity less its parent's
    (`d x dd / |d|^2`, no spin about a rod's axis), a free root's the velocity of its
    frame's origin (world) and its angular velocity (the body's frame, here the world's)."""
    nodes, velocities = np.asarray(scene.nodes, np.float64), np.asarray(scene.velocities, np.float64)
    spatial = scene.dim == 3
    omegas, per_body = [], []
    for body in layout.bodies:
        d = nodes[body.tip] - nodes[body.base]
        dd = velocities[body.tip] - velocities[body.base]
        omega = np.cross(d, dd) / (d @ d) if spatial else np.array([d[0] * dd[1] - d[1] * dd[0]]) / (d @ d)
        omegas.append(omega)
        if body.free_root:
            w = layout.origin_weight
            per_body.append([*(velocities[body.base] + w * dd), *omega])
        else:
            per_body.append(list(omega - (omegas[body.parent] if body.parent >= 0 else 0)))
    per_cart = [[velocities[node, axis]] for node, axis in layout.carts]
    # MuJoCo numbers the joints in the file's order, depth first (`xml_order`).
    return np.asarray([v for kind, k in xml_order(layout) for v in (per_cart[k] if kind == "cart" else per_body[k])], np.float64)


def xml_order(layout: Layout) -> list[tuple[str, int]]:
    """`("cart", c)` and `("body", k)` (indices of `layout.carts` and `layout.bodies`) in
    the order `render` writes them: each cart with the bodies on it, then the world's
    bodies, each depth first with its children in tree order. This is MuJoCo's order
    of bodies, joints and dofs; `layout.bodies` is breadth first, which differs on a
    branching tree."""
    children, on_cart = layout.children()
    order = []

    def depth_first(k: int) -> None:
        order.append(("body", k))
        for child in children[k]:
            depth_first(child)

    for c in range(len(layout.carts)):
        order.append(("cart", c))
        for k in on_cart[c]:
            depth_first(k)
    for k in children[-1]:
        depth_first(k)
    return order


# The nested renderer's earlier name (other modules and branches call it).
scene_to_mjcf = render


def _tie_site(body: LinkBody, node: int) -> str:
    # The end of `body` at `node` that a `connect` ties to the node's owner.
    return f"link{body.link}_tip" if node == body.tip else f"link{body.link}_base"


def _link_color(link_type: str) -> str:
    return "0.8 0.3 0.2 1" if link_type == "rod" else "0.2 0.4 0.8 1"




def builtin_files(forms: tuple[str, ...] = FORMS) -> dict[str, str]:
    """The committed `mjcf/` files of the catalogue's scenes tagged "mjcf": relative path
    -> text (nested: NAME.xml, maximal: maximal/NAME.xml; a scene only the nested form
    renders, `nested_only`, has no maximal file), at the default dt."""
    from lgnn.scene import CATALOGUE, scene_names

    files = {}
    for form in forms:
        check_form(form)
        folder = "" if form == "nested" else f"{form}/"
        for name in scene_names("mjcf"):
            scene = CATALOGUE[name].build()
            if form == "nested" or not nested_only(scene):
                files[f"{folder}{name}.xml"] = render(scene, form=form)
    return files


def write_builtin_files(directory: str | os.PathLike, forms: tuple[str, ...] = FORMS, *, check: bool = False) -> tuple[int, list[str]]:
    """Write `builtin_files(forms)` into `directory` (atomically, their subfolders created),
    or with `check` only compare: `(how many files, the paths missing or differing)`
    (none without `check`)."""
    from lgnn.files import write_text_atomic

    files = builtin_files(forms)
    stale = []
    for name, text in files.items():
        path = Path(directory) / name
        if check:
            if not path.exists() or not same_up_to_rounding(path.read_text(), text):
                stale.append(str(path))
        else:
            path.parent.mkdir(exist_ok=True)
            write_text_atomic(path, text)
    return len(files), stale


_NUMBER = re.compile(r"-?\d+\.?\d*(?:e[-+]?\d+)?")


def same_up_to_rounding(committed: str, rendered: str) -> bool:
    """The same MJCF text with the same numbers to 1e-12 relative: the numbers are
    computed (a catalogue scene's velocities go through XLA), and a machine with other
    vector instructions may round their last bit differently."""
    if _NUMBER.split(committed) != _NUMBER.split(rendered):
        return False
    a = np.array([float(x) for x in _NUMBER.findall(committed)])
    b = np.array([float(x) for x in _NUMBER.findall(rendered)])
    return a.shape == b.shape and np.allclose(a, b, rtol=1e-12, atol=1e-14)
