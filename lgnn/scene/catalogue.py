"""The one catalogue of scenes and the initial-condition samplers.

`CATALOGUE` maps each built-in scene's name to its `CatalogueEntry`: a function that
builds it (from a fixed seed), a description, its tags (`TAGS`: its dimension,
where it comes from, whether `mjcf/` holds its MJCF) and its initial-state policy
(`INITIAL_STATE_POLICIES`: how training data and the benchmark start it). Every
built-in is in it once; `scene_names(*tags)` selects by tag. `get_scene(name_or_path)`
resolves a catalogue name or a user's scene JSON file; `initial_state_policy(scene)`
is the policy of a scene equal to a catalogue entry's (so the same scene as a file
starts alike), and for any other scene the chain sampler on a pinned chain and
projected perturbations otherwise.

Inertia convention (see SPEC.md): scenes carry the *physical* moment of inertia of
each rod about its centre. The authors' code computed the rotational energy as
`1/2 I w^2` with the unnormalised `w = cross(dq, dqd) = l^2 omega`, i.e. a physical
inertia `I l^4`. The paper's scenes are therefore defined with physical inertia
`I_paper * l^4`: `1/12` for unit-link chains, `l^4 / 12` for every T1-T3 link, and
`I_k l_k^4` for the varied chain's listed `I_k`. User scene files give the physical
inertia directly.
"""

from __future__ import annotations

import functools
import json
import math
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from lgnn.errors import SceneError
from lgnn.scene.schema import Scene, State, is_pinned_chain, load_scene_file, scene_from_dict, scene_to_dict

# Paper's chain sampler (authors' code): each link hangs at (0, -1) rotated by an
# independent angle in [-15, 15] degrees, then the whole chain is rotated by +45
# degrees about the pinned node; released from rest.
CHAIN_LINK_ANGLE = np.deg2rad(15.0)
CHAIN_ROTATION = np.deg2rad(45.0)
PAPER_GRAVITY = 10.0
# The 3D chain sampler: each link tilted from -y by a polar angle uniform in [0, 45]
# degrees (the 2D sampler's 45 degree swing) towards a uniform random azimuth, turning
# at a rate uniform in [0, 2] rad/s (below the unit pendulum's sqrt(g / l) ~ 3.2) about
# a uniformly random axis perpendicular to it.
SPATIAL_CHAIN_CONE = np.deg2rad(45.0)
SPATIAL_CHAIN_SPIN = 2.0
PAPER_DRAG = 0.01

# The varied-property 4-link chain (paper appendix; the fifth listed mass is unused).
VARIED_LENGTHS = (0.81331408, 1.15980562, 0.8647536, 1.17632355)
VARIED_MASSES = (1.83244264, 1.18182497, 1.30424224, 1.43194502)
VARIED_PAPER_INERTIAS = (1.21233911, 1.18340451, 1.52475643, 1.29122914)


def chain_positions(lengths, angles, rotation: float = CHAIN_ROTATION):
    """Node positions (n+1, 2) of a chain hanging from the origin.

    Link k points along (0, -1) rotated by `angles[k] + rotation` (radians, counter-
    clockwise). Works on NumPy or JAX arrays (so it can be vmapped).
    """
    xp = jnp if isinstance(angles, jax.Array) else np
    theta = angles + rotation
    steps = lengths[:, None] * xp.stack([xp.sin(theta), -xp.cos(theta)], axis=-1)
    return xp.concatenate([xp.zeros((1, 2), steps.dtype), xp.cumsum(steps, axis=0)], axis=0)


def spatial_chain_state(lengths, polar, azimuth, spin_direction, spin):
    """Node positions and velocities, each (n+1, 3), of a chain hanging from the origin.

    Link k points along -y tilted by `polar[k]` towards the azimuth `azimuth[k]` (in the
    x-z plane, from +x towards +z). It turns at `spin[k]` rad/s (its own angular
    velocity, not relative to link k-1) about an axis perpendicular to it, at the angle
    `spin_direction[k]` from the direction of increasing tilt: no spin about its own
    axis (the node description cannot see it), and every link length stationary
    (`dq . dqd = 0` exactly). Works on NumPy or JAX arrays (so it can be vmapped);
    radians throughout.
    """
    xp = jnp if isinstance(polar, jax.Array) else np
    sin_p, cos_p, sin_a, cos_a = xp.sin(polar), xp.cos(polar), xp.sin(azimuth), xp.cos(azimuth)
    direction = xp.stack([sin_p * cos_a, -cos_p, sin_p * sin_a], axis=-1)
    # The unit vectors of increasing tilt and of increasing azimuth: with `direction`
    # an orthonormal frame, so the spin axis is perpendicular to the link.
    tilting = xp.stack([cos_p * cos_a, sin_p, cos_p * sin_a], axis=-1)
    turning = xp.stack([-sin_a, xp.zeros_like(sin_a), cos_a], axis=-1)
    axis = xp.cos(spin_direction)[:, None] * tilting + xp.sin(spin_direction)[:, None] * turning
    steps = lengths[:, None] * direction
    step_velocities = xp.cross(spin[:, None] * axis, steps)
    origin = xp.zeros((1, 3), steps.dtype)
    return (xp.concatenate([origin, xp.cumsum(steps, axis=0)], axis=0),
            xp.concatenate([origin, xp.cumsum(step_velocities, axis=0)], axis=0))


def _spatial_chain_angles(uniform, n_links: int):
    """Polar angle, azimuth, spin direction and spin of each of `n_links` links from
    `uniform(low, high) -> (n_links,)` draws: the 3D chain sampler's distribution."""
    return (uniform(0.0, SPATIAL_CHAIN_CONE), uniform(0.0, 2 * np.pi), uniform(0.0, 2 * np.pi),
            uniform(0.0, SPATIAL_CHAIN_SPIN))


def sample_initial_states(scene: Scene, key: jax.Array, count: int) -> State:
    """`count` initial states (q, qd) each (count, N, D), for evaluation and training data.

    Planar chains pinned at node 0 use the paper's sampler (random link angles,
    released from rest), spatial ones the 3D chain sampler (links in a cone about -y
    with random azimuths and spins perpendicular to them, `spatial_chain_state`), the
    pin kept at the scene's pin position; every other scene has one initial condition,
    its own, repeated.
    """
    if not is_pinned_chain(scene):
        q = np.broadcast_to(scene.nodes, (count, *scene.nodes.shape))
        qd = np.broadcast_to(scene.velocities, q.shape)
        return State(jnp.asarray(q), jnp.asarray(qd))
    lengths = jnp.asarray(scene.lengths)
    if scene.dim == 3:
        keys = iter(jax.random.split(key, 4))
        uniform = lambda low, high: jax.random.uniform(next(keys), (count, scene.n_links), lengths.dtype, low, high)  # noqa: E731
        q, qd = jax.vmap(lambda *angles: spatial_chain_state(lengths, *angles))(*_spatial_chain_angles(uniform, scene.n_links))
        return State(q + jnp.asarray(scene.nodes[0]), qd)
    angles = jax.random.uniform(key, (count, scene.n_links), lengths.dtype, -CHAIN_LINK_ANGLE, CHAIN_LINK_ANGLE)
    q = jax.vmap(lambda a: chain_positions(lengths, a))(angles) + jnp.asarray(scene.nodes[0])
    return State(q, jnp.zeros_like(q))


def _chain_dict(name: str, lengths, masses, inertias, seed: int, drag: float = 0.0, rotation: float = CHAIN_ROTATION) -> dict:
    rng = np.random.default_rng(seed)
    angles = rng.uniform(-CHAIN_LINK_ANGLE, CHAIN_LINK_ANGLE, len(lengths))
    nodes = chain_positions(np.asarray(lengths, np.float64), angles, rotation)
    links = [
        {"nodes": [k, k + 1], "mass": m, "inertia": inertia, "length": length}
        for k, (length, m, inertia) in enumerate(zip(lengths, masses, inertias, strict=True))
    ]
    return {"name": name, "gravity": PAPER_GRAVITY, "drag": drag, "nodes": nodes.tolist(), "pinned": [0], "links": links}


def chain(n_links: int, seed: int = 0, name: str | None = None, drag: float = 0.0) -> Scene:
    """The paper's n-link chain: unit links (l = 1, m = 1, I = 1/12), node 0 pinned at the
    origin, initial shape from the paper's sampler with `seed`, released from rest."""
    if n_links < 1:
        raise SceneError(f"chain: need at least one link, got {n_links}")
    ones = [1.0] * n_links
    data = _chain_dict(name or f"chain{n_links}", ones, ones, [1.0 / 12.0] * n_links, seed, drag)
    return scene_from_dict(data)


def chain4_varied(seed: int = 0, dim: int = 2) -> Scene:
    """The paper's 4-link chain with varied link properties (appendix). Physical inertia
    is the listed `I_k` times `l_k^4` (module docstring). In 3D (`chain4-3d-varied`, the
    3D transfer track's training scene), the same links started by the 3D chain sampler."""
    inertias = [i * length**4 for i, length in zip(VARIED_PAPER_INERTIAS, VARIED_LENGTHS, strict=True)]
    return _chain_of_dim(dim, f"chain4{_dim_suffix(dim, 'varied chain')}-varied", VARIED_LENGTHS, VARIED_MASSES, inertias, seed)


def varied_chain(n_links: int, seed: int, name: str | None = None, dim: int = 2) -> Scene:
    """A chain of `n_links` links with varied properties, by one stated rule: each
    link's length, mass and paper inertia parameter drawn independently and uniformly
    between the smallest and the largest of the paper's varied 4-link chain's
    (`VARIED_LENGTHS`, `VARIED_MASSES`, `VARIED_PAPER_INERTIAS`), from NumPy's
    `default_rng(seed)`; physical inertia `I_k l_k^4` as the paper's varied chain's
    (module docstring); the initial shape from the chain sampler of its dimension `dim`
    (2 or 3) with the same seed. The built-ins `chain{8,16,100}-varied` and
    `chain{8,16,100}-3d-varied` are `varied_chain(n, seed=n)`: zero-shot transfer from
    varied 4-link chains to longer ones whose links it never saw."""
    if n_links < 1:
        raise SceneError(f"varied chain: need at least one link, got {n_links}")
    suffix = _dim_suffix(dim, "varied chain")
    rng = np.random.default_rng(seed)
    lengths, masses, paper_inertias = (rng.uniform(min(values), max(values), n_links)
                                       for values in (VARIED_LENGTHS, VARIED_MASSES, VARIED_PAPER_INERTIAS))
    inertias = paper_inertias * lengths**4
    name = name or f"chain{n_links}{suffix}-varied"
    return _chain_of_dim(dim, name, lengths.tolist(), masses.tolist(), inertias.tolist(), seed)


# A chain's name after its link count, by dimension (`chain8`, `chain8-3d`).
_DIM_SUFFIX = {2: "", 3: "-3d"}


def _dim_suffix(dim, what: str) -> str:
    if isinstance(dim, bool) or dim not in _DIM_SUFFIX:
        raise SceneError(f"{what}: dim must be 2 or 3, got {dim!r}")
    return _DIM_SUFFIX[dim]


def _chain_of_dim(dim: int, name: str, lengths, masses, inertias, seed: int) -> Scene:
    """A chain pinned at node 0 with these links, started by its dimension's sampler."""
    make = _chain_dict if dim == 2 else _spatial_chain_dict
    return scene_from_dict(make(name, lengths, masses, inertias, seed))


def chain4_drag(seed: int = 0) -> Scene:
    """The 4-link chain with linear drag 0.01 on each link's centre velocity."""
    return chain(4, seed, name="chain4-drag", drag=PAPER_DRAG)


@functools.cache
def _paper_structures() -> dict:
    text = resources.files("lgnn").joinpath("assets/paper_structures.json").read_text()
    return json.loads(text)


# The scenes lgnn writes in MJCF from published models' parameters (dm_control's suite,
# Gymnasium) and imports: the source files in lgnn/assets/mjcf/, each imported at its
# one keyframe by `lgnn scene import` into lgnn/assets/imported/ (a test holds each file
# to a fresh import), read here without MuJoCo.
IMPORTED = {
    "pendulum-bob": "dm_control's pendulum: a 1 kg bob on a massless 0.5 m pole, hinge damping 0.1",
    "acrobot": "dm_control's acrobot: two 1 m arms of 1 kg, joint damping 0.05",
    "cartpole": "dm_control's cart-pole: a 1 kg cart on a damped slider (+-1.8 m), a 1 m pole of 0.1 kg",
    "cartpole-2": "dm_control's cart-pole with two poles",
    "cartpole-3": "dm_control's cart-pole with three poles",
    "inverted-double-pendulum": "Gymnasium's inverted double pendulum: a 10.5 kg cart (+-0.99 m), two 0.6 m poles, gravity tilted 1e-5",
}
# The 3D ones (ball joints).
IMPORTED_3D = {
    "rope-capsules-3d": "a rope of ten ball-jointed capsules (0.1 m, 35 g) pinned at its top, released bent and twisted",
}


def imported_scene(name: str) -> Scene:
    """The built-in imported scene `name` (`IMPORTED`, `IMPORTED_3D`)."""
    return scene_from_dict(json.loads(resources.files("lgnn").joinpath(f"assets/imported/{name}.json").read_text()))


def paper_structure(name: str) -> Scene:
    """T1, T2 or T3 (paper figure D-F), geometry from the authors' notebooks.

    Every link has m = 1 and the paper's inertia parameter 1/12, i.e. physical
    inertia `l^4 / 12`; long compression members are typed "rod", the rope segments
    "link". Released from rest under gravity 10.
    """
    data = _paper_structures()[name]
    nodes = np.asarray(data["nodes"], np.float64)
    for node, position in data["pinned"].items():
        if not np.allclose(nodes[int(node)], position, rtol=0, atol=1e-12):
            raise SceneError(f"{name}: pinned node {node} is not at its listed position")
    rods = {frozenset(edge) for edge in data["rods"]}
    links = []
    for i, j in data["edges"]:
        # math.hypot, not np.linalg.norm: the same last bit on every machine (as the
        # default length in scene_from_dict), so mjcf/ and the records keyed on the
        # scene do not depend on where they were made.
        length = math.hypot(*(float(x) for x in nodes[i] - nodes[j]))
        link_type = "rod" if frozenset((i, j)) in rods else "link"
        links.append({"nodes": [i, j], "mass": 1.0, "inertia": length**4 / 12.0, "type": link_type})
    pinned = sorted(int(k) for k in data["pinned"])
    return scene_from_dict(
        {"name": name, "gravity": PAPER_GRAVITY, "drag": 0.0, "nodes": nodes.tolist(), "pinned": pinned, "links": links}
    )


# ---------------------------------------------------------------------------------
# Hard cases (`lgnn stability`) and small scenes for the physics tests
# ---------------------------------------------------------------------------------


def taut_chain(n_links: int = 4, fraction: float = 0.999) -> Scene:
    """n unit links hanging between two pins `fraction * n` apart (a shallow V).

    `fraction = 1` is exactly taut: a straight line, where the length constraints lose
    a rank (one self-stress) and the inextensible model's exact motion is rest.
    """
    if not 0 < fraction <= 1:
        raise ValueError(f"fraction must be in (0, 1], got {fraction}")
    sag = math.sqrt(max(0.0, 1.0 - fraction**2))
    nodes = [[k * fraction, -sag * min(k, n_links - k)] for k in range(n_links + 1)]
    return scene_from_dict({
        # "exact", not "1": the name the catalogue lists it by (`catalogue_entry` matches names).
        "name": f"taut{n_links}-{'exact' if fraction == 1 else f'{fraction:g}'}",
        "nodes": nodes,
        "pinned": [0, n_links],
        "links": [{"nodes": [k, k + 1], "mass": 1.0, "inertia": 1 / 12, "length": 1.0} for k in range(n_links)],
    })


def folded_chain(n_links: int = 4) -> Scene:
    """n unit links folded flat on each other (zig-zag along x, every other node on the
    pin): all links collinear, so the rod mass matrix is singular, released from rest."""
    nodes = [[float(k % 2), 0.0] for k in range(n_links + 1)]
    return scene_from_dict({
        "name": f"folded{n_links}",
        "nodes": nodes,
        "pinned": [0],
        "links": [{"nodes": [k, k + 1], "mass": 1.0, "inertia": 1 / 12, "length": 1.0} for k in range(n_links)],
    })


def pinned_triangle() -> Scene:
    """A rigid triangle pinned at two corners: 3 links + 2 pins on 3 nodes (redundant)."""
    return scene_from_dict({
        "name": "pinned-triangle",
        "nodes": [[0.0, 0.0], [1.0, 0.0], [0.5, -0.8]],
        "pinned": [0, 1],
        "links": [{"nodes": list(e), "mass": 1.0, "inertia": 0.1} for e in ((0, 1), (1, 2), (2, 0))],
    })


def pendulum(angle: float = 0.3, length: float = 1.0, mass: float = 1.0, gravity: float = 10.0):
    """One uniform rod pinned at node 0, released from rest at `angle` from the vertical."""
    tip = [length * np.sin(angle), -length * np.cos(angle)]
    return scene_from_dict(
        {
            "name": "pendulum",
            "gravity": gravity,
            "nodes": [[0.0, 0.0], tip],
            "pinned": [0],
            "links": [{"nodes": [0, 1], "mass": mass, "inertia": mass * length**2 / 12}],
        }
    )


# Finzi et al. (2020)'s chain pendulums (their code's `ChainPendulum(n)`): n point
# masses joined by massless rods, the first tethered to a pivot at the origin, gravity
# 9.81. Their masses and lengths are 0.6 + 0.8 U(0, 1), drawn by NumPy's legacy
# generator seeded 0 (n masses, then n lengths) and taken from the end of each list:
# the bob nearest the pivot gets the last mass drawn, its rod the last length.
FINZI_GRAVITY = 9.81
FINZI_PENDULUMS = {
    1: ((1.039050803142,), (1.172151493098,)),
    2: ((1.172151493098, 1.039050803142), (1.035906546398, 1.082210700857)),
    3: ((1.082210700857, 1.172151493098, 1.039050803142), (1.116715290453, 0.938923839471, 1.035906546398)),
    5: ((0.938923839471, 1.035906546398, 1.082210700857, 1.172151493098, 1.039050803142),
        (0.906753215061, 1.370930208401, 1.313418400626, 0.95006976901, 1.116715290453)),
}


def finzi_pendulum(n_bobs: int) -> Scene:
    """Finzi et al.'s `n_bobs`-pendulum (`FINZI_PENDULUMS`): node 0 the pivot, node k
    the k-th bob from it, hanging straight down at rest (the mean of their initial-state
    distribution, `lgnn.bench.papers.finzi_initial_states`)."""
    masses, lengths = FINZI_PENDULUMS[n_bobs]
    depths = np.cumsum(lengths)
    return scene_from_dict({
        "name": f"finzi-pendulum{n_bobs}",
        "gravity": FINZI_GRAVITY,
        "nodes": [[0.0, 0.0], *([0.0, -float(depth)] for depth in depths)],
        "pinned": [0],
        "links": [{"nodes": [k, k + 1], "mass": 0.0, "inertia": 0.0, "length": length} for k, length in enumerate(lengths)],
        "point_masses": [{"node": k + 1, "mass": mass} for k, mass in enumerate(masses)],
    })


def free_triangle():
    """An unpinned triangle with some spin: a free rigid body (no pins, no pin rows)."""
    nodes = np.array([[0.0, 0.0], [1.0, 0.0], [0.5, 0.8]])
    centre = nodes.mean(0)
    spin = 1.3
    velocities = spin * np.stack([-(nodes[:, 1] - centre[1]), nodes[:, 0] - centre[0]], -1) + [0.2, 0.5]
    return scene_from_dict(
        {
            "name": "free-triangle",
            "gravity": 10.0,
            "nodes": nodes.tolist(),
            "velocities": velocities.tolist(),
            "pinned": [],
            "links": [
                {"nodes": [0, 1], "mass": 1.0, "inertia": 0.1},
                {"nodes": [1, 2], "mass": 2.0, "inertia": 0.3},
                {"nodes": [2, 0], "mass": 0.5, "inertia": 0.05},
            ],
        }
    )


def double_pinned_chain(n_links: int = 4, sag: float = 0.5):
    """A chain of unit links hanging between two pins (a closed loop through the ground)."""
    half = n_links // 2
    xs = np.concatenate([np.arange(half + 1) * np.sqrt(1 - sag**2), half * np.sqrt(1 - sag**2) + np.arange(1, n_links - half + 1) * np.sqrt(1 - sag**2)])
    ys = np.concatenate([-np.arange(half + 1) * sag, -half * sag + np.arange(1, n_links - half + 1) * sag])
    nodes = np.stack([xs, ys], -1)
    return scene_from_dict(
        {
            "name": "double-pinned",
            "nodes": nodes.tolist(),
            "pinned": [0, n_links],
            "links": [{"nodes": [k, k + 1], "mass": 1.0, "inertia": 1 / 12} for k in range(n_links)],
        }
    )


# A chain of alternately long, heavy and short, light links (issue 14, item 6: the
# Lagrangian engine against MuJoCo C at equal dt on mixed lengths and masses): a 20x
# spread of lengths and a 1000x spread of masses, released from rest near horizontal
# so that it swings fast enough for RK4's error at dt 1e-3 to be far above round-off.
MIXED_LENGTHS = (2.0, 0.1, 1.5, 0.15, 1.0, 0.1, 1.8, 0.2)
MIXED_MASSES = (10.0, 0.01, 5.0, 0.02, 8.0, 0.01, 3.0, 0.05)


def mixed_chain(seed: int = 0) -> Scene:
    """8 links of mixed lengths and masses (`MIXED_LENGTHS`, `MIXED_MASSES`; uniform rods,
    `I = m l^2 / 12`), pinned at node 0, each link within 15 degrees of a line 0.2 rad
    below the horizontal (seeded), at rest."""
    inertias = [m * length**2 / 12 for length, m in zip(MIXED_LENGTHS, MIXED_MASSES, strict=True)]
    return scene_from_dict(_chain_dict("chain8-mixed", MIXED_LENGTHS, MIXED_MASSES, inertias, seed, rotation=np.pi / 2 - 0.2))


# Slack of the ropes of the slackened structures (a fraction of each rope link's length).
ROPE_SLACK = 1e-3


# Decimals kept of a slackened scene's solved node positions (`slackened`).
SLACK_DECIMALS = 12


def slackened(scene: Scene, slack: float = ROPE_SLACK, seed: int = 0) -> Scene:
    """`scene` with every rope link (type "link") `1 + slack` times longer, started from
    a configuration that satisfies the new lengths: each free node lowered by
    `sqrt(slack)` times a uniform factor in [0.5, 1] (seeded; generic, so no rope stays
    straight), then Gauss-Newton (minimum-norm steps) back onto the lengths.

    T2 and T3 start with straight ropes between pins: self-stressed, singular for the
    inextensible model, whose reference does not converge in dt there
    (`lgnn.bench.convergence`). With a little slack they hang off that singular
    configuration (no self-stress) and their reference converges at RK4's order. Masses
    and inertias are kept."""
    data = scene_to_dict(scene)
    lengths = np.array([link["length"] * (1 + slack if link["type"] == "link" else 1.0) for link in data["links"]])
    edges, q = scene.edge_index, np.array(scene.nodes, np.float64)
    free = np.ones(len(q), bool)
    free[list(scene.pinned)] = False
    q[free, 1] -= math.sqrt(slack) * np.random.default_rng(seed).uniform(0.5, 1.0, free.sum())
    rows = np.arange(len(edges))
    for _ in range(50):
        r = q[edges[:, 0]] - q[edges[:, 1]]
        phi = (np.sum(r * r, axis=1) - lengths**2) / (2 * lengths)
        if np.max(np.abs(phi)) < 1e-15:
            break
        jac = np.zeros((len(edges), *q.shape))
        jac[rows, edges[:, 0]] = r / lengths[:, None]
        jac[rows, edges[:, 1]] = -r / lengths[:, None]
        q[free] += np.linalg.lstsq(jac[:, free].reshape(len(edges), -1), -phi, rcond=None)[0].reshape(-1, q.shape[1])
    else:
        raise SceneError(f"{scene.name}: no configuration found with the ropes {slack:g} slack")
    for link, length in zip(data["links"], lengths):
        link["length"] = float(length)
    # Rounded: LAPACK's least squares differs between machines in the last bits, and a
    # scene is keyed by its content (records made on a GPU machine must match here).
    # The links then close to ~1e-12, which the engines' projection absorbs.
    return scene_from_dict({**data, "name": f"{scene.name}-slack", "nodes": np.round(q, SLACK_DECIMALS).tolist()})


# ---------------------------------------------------------------------------------
# Spatial (3D) scenes
# ---------------------------------------------------------------------------------


def spatial_chain(n_links: int, seed: int = 0, name: str | None = None) -> Scene:
    """n unit links (l = 1, m = 1, I = 1/12) in 3D, node 0 pinned at the origin, started
    by the 3D chain sampler (`spatial_chain_state`) with `seed`: hanging in a cone about
    -y, turning perpendicular to the links."""
    if n_links < 1:
        raise SceneError(f"spatial chain: need at least one link, got {n_links}")
    ones = [1.0] * n_links
    return scene_from_dict(_spatial_chain_dict(name or f"chain{n_links}-3d", ones, ones, [1.0 / 12.0] * n_links, seed))


def _spatial_chain_dict(name: str, lengths, masses, inertias, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    n_links = len(lengths)
    angles = _spatial_chain_angles(lambda low, high: rng.uniform(low, high, n_links), n_links)
    nodes, velocities = spatial_chain_state(np.asarray(lengths, np.float64), *angles)
    links = [
        {"nodes": [k, k + 1], "mass": m, "inertia": inertia, "length": length}
        for k, (length, m, inertia) in enumerate(zip(lengths, masses, inertias, strict=True))
    ]
    return {"name": name, "gravity": PAPER_GRAVITY, "nodes": nodes.tolist(), "velocities": velocities.tolist(), "pinned": [0], "links": links}


def spatial_net(rows: int = 4, columns: int = 4, seed: int = 0) -> Scene:
    """A square net of `rows` x `columns` nodes joined by links to their grid neighbours
    (closed loops everywhere), hung from its two top corners, released from rest.

    It starts as a curved sheet: rows go down and away in z, the top edge sags between
    the pins (no straight rope run between pins, which would be self-stressed, T2/T3),
    and every node is moved by up to 5 % of the spacing (seeded), so the start is a
    generic, regular configuration. Link lengths are the initial distances (each about
    1), masses 1 and inertias `l^2 / 12` (uniform rods)."""
    if rows < 2 or columns < 2:
        raise SceneError(f"spatial net: need at least 2 x 2 nodes, got {rows} x {columns}")
    r, c = np.meshgrid(np.arange(rows), np.arange(columns), indexing="ij")
    across = np.sin(np.pi * c / (columns - 1))
    nodes = np.stack([c, -0.8 * r - 0.4 * across, 0.6 * r + 0.3 * across * np.sin(np.pi * r / (rows - 1))], -1).astype(np.float64)
    nodes += 0.05 * np.random.default_rng(seed).uniform(-1.0, 1.0, nodes.shape)
    top_corners = [(0, 0), (0, columns - 1)]
    for corner in top_corners:
        nodes[corner] = [corner[1], 0.0, 0.0]
    index = lambda row, column: row * columns + column  # noqa: E731
    edges = [(index(a, b), index(a, b + 1)) for a in range(rows) for b in range(columns - 1)]
    edges += [(index(a, b), index(a + 1, b)) for a in range(rows - 1) for b in range(columns)]
    flat = nodes.reshape(-1, 3)
    links = []
    for i, j in edges:
        length = math.hypot(*(float(x) for x in flat[i] - flat[j]))
        links.append({"nodes": [i, j], "mass": 1.0, "inertia": length**2 / 12})
    return scene_from_dict({
        "name": f"net{rows}x{columns}-3d", "gravity": PAPER_GRAVITY, "nodes": flat.tolist(),
        "pinned": [index(*corner) for corner in top_corners], "links": links,
    })


# Rope and rope chains of the spatial scenes: uniform line density 1 (a link's mass is
# its length, its inertia that of a uniform rod, m l^2 / 12), as for the rods.
ROPE_LINKS = 30
ROPE_LINK_LENGTH = 0.1


def _uniform_links(flat: np.ndarray, edges, types=None) -> list[dict]:
    """Links of density 1 along `edges` of the nodes `flat` (M, 3), each as long as its
    initial distance (math.hypot: the same last bit everywhere, as in `paper_structure`)."""
    links = []
    for k, (i, j) in enumerate(edges):
        length = math.hypot(*(float(x) for x in flat[i] - flat[j]))
        link = {"nodes": [int(i), int(j)], "mass": length, "inertia": length**3 / 12}
        if types is not None:
            link["type"] = types[k]
        links.append(link)
    return links


def spatial_rope(n_links: int = ROPE_LINKS, link_length: float = ROPE_LINK_LENGTH, name: str = "rope-3d") -> Scene:
    """A rope of `n_links` short links (density 1) pinned at the origin, released from
    rest as a loose helix: each link 60 degrees from -y, its azimuth turning by 1.5
    turns along the rope, so the rope starts curved, never straight or taut, and falls
    and swings in all three directions."""
    if n_links < 1:
        raise SceneError(f"spatial rope: need at least one link, got {n_links}")
    k = np.arange(n_links)
    nodes, _ = spatial_chain_state(np.full(n_links, link_length), np.full(n_links, np.deg2rad(60.0)),
                                   3 * np.pi * k / n_links, np.zeros(n_links), np.zeros(n_links))
    return scene_from_dict({
        "name": name, "gravity": PAPER_GRAVITY, "nodes": nodes.tolist(), "pinned": [0],
        "links": _uniform_links(nodes, [(j, j + 1) for j in range(n_links)]),
    })


def _sagging_rope(start: np.ndarray, end: np.ndarray, n_links: int, sag: float, rng) -> np.ndarray:
    """The n_links - 1 inner nodes (n_links - 1, 3) of a rope from `start` to `end`
    hanging in a bow: `sag` times the span below the straight run at mid-span (sideways
    for a vertical run), each node moved by up to 2 % of the span so no rope is planar."""
    span = end - start
    along = span / np.linalg.norm(span)
    down = np.array([0.0, -1.0, 0.0]) - along[1] * along
    if np.linalg.norm(down) < 0.3:  # a nearly vertical run bows sideways
        down = np.cross(along, [0.0, 0.0, 1.0])
    down /= np.linalg.norm(down)
    t = np.arange(1, n_links)[:, None] / n_links
    return start + t * span + sag * np.linalg.norm(span) * np.sin(np.pi * t) * down + 0.02 * np.linalg.norm(span) * rng.uniform(-1, 1, (n_links - 1, 3))


def spatial_tensegrity(rope_links: int = 3, seed: int = 0) -> Scene:
    """A three-rod tensegrity prism of rope chains, hung from three pins, released from
    rest: rods (density 1, type "rod") from each bottom corner to the next top corner of
    a twisted triangular prism (radius 1, height 1.5, twist 150 degrees); the two
    triangles, the three verticals and three hangers (from pins 1 above the top
    corners) are rope chains of `rope_links` links (type "link").

    Every rope starts slack, bowed by 15 % of its span (`_sagging_rope`): a straight
    rope run between pinned or rod-held nodes would be self-stressed, singular for the
    inextensible model (T2, T3). So the prism is loose, not prestressed: it sags and
    swings into its hangers."""
    rng = np.random.default_rng(seed)
    angles = 2 * np.pi * np.arange(3) / 3
    circle = lambda y, turn: np.stack([np.cos(angles + turn), np.full(3, y), np.sin(angles + turn)], -1)  # noqa: E731
    top, bottom = circle(-1.0, np.deg2rad(150.0)), circle(-2.5, 0.0)
    pins = top + [0.0, 1.0, 0.0]
    nodes = [*pins, *top, *bottom]  # pins 0-2, top corners 3-5, bottom corners 6-8
    edges, types = [], []
    for i in range(3):
        edges.append((6 + i, 3 + (i + 1) % 3))
        types.append("rod")
    runs = [(i, 3 + i) for i in range(3)]  # hangers
    runs += [(3 + i, 3 + (i + 1) % 3) for i in range(3)] + [(6 + i, 6 + (i + 1) % 3) for i in range(3)] + [(6 + i, 3 + i) for i in range(3)]
    for a, b in runs:
        inner = _sagging_rope(np.asarray(nodes[a]), np.asarray(nodes[b]), rope_links, 0.15, rng)
        chain_nodes = [a, *range(len(nodes), len(nodes) + len(inner)), b]
        nodes += list(inner)
        edges += list(zip(chain_nodes[:-1], chain_nodes[1:]))
        types += ["link"] * rope_links
    flat = np.asarray(nodes, np.float64)
    return scene_from_dict({
        "name": "tensegrity-3d", "gravity": PAPER_GRAVITY, "nodes": flat.tolist(), "pinned": [0, 1, 2],
        "links": _uniform_links(flat, edges, types),
    })


def embedded_in_3d(scene: Scene) -> Scene:
    """A planar scene as a spatial one at z = 0 (gravity along -y in both): the same
    motion, exactly (tested to round-off)."""
    if scene.dim != 2:
        raise SceneError(f"{scene.name}: only a planar scene can be embedded in 3D, got {scene.dim}D")
    pad = lambda points: np.concatenate([points, np.zeros((len(points), 1))], axis=1).tolist()  # noqa: E731
    data = scene_to_dict(scene)
    return scene_from_dict({**data, "name": f"{scene.name}-z0", "nodes": pad(scene.nodes), "velocities": pad(scene.velocities)})


# ---------------------------------------------------------------------------------
# The catalogue
# ---------------------------------------------------------------------------------

# Tags of the catalogue's entries: each entry has one dimension tag (matching its
# scene's `dim`) and one origin tag.
TAGS = {
    "planar": "2D",
    "3d": "3D",
    "paper": "the paper's scenes (chains, the varied and drag chains, T1-T3)",
    "hard": "hard cases: lgnn stability, the physics tests, the stand-ins T2-slack and T3-slack, scaling",
    "transfer": "scenes made for zero-shot transfer: 3D ones from the 3D 4-link chain, longer varied chains (planar and 3D) from varied 4-link ones",
    "imported": "written in MJCF (from published models' parameters: dm_control, Gymnasium; a rope of capsules of lgnn's own) and imported (lgnn scene import)",
    "papers": "other papers' systems as their authors' code defines them (Finzi et al. 2020's chain pendulums: lgnn papers)",
    "mjcf": "its MJCF is committed in mjcf/ (lgnn mjcf --check)",
}
DIMENSION_TAGS = {2: "planar", 3: "3d"}

# How training data and the benchmark's evaluation start a scene
# (`lgnn.physics.benchmark_initial_states`):
# the scene's own state, one initial condition (the paper's T1-T3 rest states);
OWN_STATE = "own state"
# the paper's chain sampler (`sample_initial_states`; in 3D the 3D chain sampler),
# for pinned chains only;
CHAIN_SAMPLER = "chain sampler"
# random perturbations of the scene's own state put back on its constraints
# (`lgnn.physics.sample_initial_conditions`), for any scene.
PROJECTED = "projected perturbations"
INITIAL_STATE_POLICIES = (OWN_STATE, CHAIN_SAMPLER, PROJECTED)


@dataclass(frozen=True)
class CatalogueEntry:
    """A built-in scene: `build() -> Scene` (the same scene every call), what it is,
    its tags (`TAGS`) and its initial-state policy (`INITIAL_STATE_POLICIES`)."""

    name: str
    description: str
    build: Callable[[], Scene]
    tags: tuple[str, ...]
    initial_states: str

    def __post_init__(self):
        unknown = [tag for tag in self.tags if tag not in TAGS]
        if unknown:
            raise SceneError(f"catalogue entry {self.name!r}: unknown tag {unknown[0]!r} (choose from {', '.join(TAGS)})")
        if self.initial_states not in INITIAL_STATE_POLICIES:
            raise SceneError(f"catalogue entry {self.name!r}: unknown initial-state policy {self.initial_states!r} "
                             f"(choose from {', '.join(INITIAL_STATE_POLICIES)})")


def _planar(origin: str, *more: str) -> tuple[str, ...]:
    return ("planar", origin, *more)


CATALOGUE: dict[str, CatalogueEntry] = {
    entry.name: entry
    for entry in [
        CatalogueEntry("chain4", "4 unit links pinned at one end (training scene)", lambda: chain(4), _planar("paper", "mjcf"), CHAIN_SAMPLER),
        CatalogueEntry("chain8", "8 unit links pinned at one end", lambda: chain(8), _planar("paper", "mjcf"), CHAIN_SAMPLER),
        CatalogueEntry("chain16", "16 unit links pinned at one end", lambda: chain(16), _planar("paper", "mjcf"), CHAIN_SAMPLER),
        CatalogueEntry("chain100", "100 unit links pinned at one end", lambda: chain(100), _planar("paper", "mjcf"), CHAIN_SAMPLER),
        CatalogueEntry("chain4-varied", "4 links with the paper's varied lengths, masses, inertias", chain4_varied, _planar("paper", "mjcf"),
                       CHAIN_SAMPLER),
        CatalogueEntry("chain4-drag", "4 unit links with linear drag 0.01", chain4_drag, _planar("paper", "mjcf"), CHAIN_SAMPLER),
        CatalogueEntry("T1", "tensegrity: two ropes, a braced rope frame, 6 rods (paper fig. D)", lambda: paper_structure("T1"),
                       _planar("paper", "mjcf"), OWN_STATE),
        CatalogueEntry("T2", "tensegrity: rope loop with one rod (paper fig. E)", lambda: paper_structure("T2"), _planar("paper", "mjcf"), OWN_STATE),
        CatalogueEntry("T3", "lattice of ropes pinned at six nodes (paper fig. F)", lambda: paper_structure("T3"), _planar("paper", "mjcf"), OWN_STATE),
        *(CatalogueEntry(f"chain{n}-varied", f"{n} links of varied lengths, masses, inertias (`varied_chain`, seed {n})",
                         functools.partial(varied_chain, n, n), _planar("transfer"), CHAIN_SAMPLER) for n in (8, 16, 100)),
        CatalogueEntry("chain1000", "1000 unit links pinned at one end (scaling)", lambda: chain(1000), _planar("hard"), CHAIN_SAMPLER),
        CatalogueEntry("taut4-0.999", "4 links hanging between two pins 0.999 x 4 apart (nearly taut)", lambda: taut_chain(4, 0.999),
                       _planar("hard"), OWN_STATE),
        CatalogueEntry("taut4-exact", "4 links pulled exactly taut between two pins (one self-stress)", lambda: taut_chain(4, 1.0),
                       _planar("hard"), OWN_STATE),
        CatalogueEntry("folded4", "4 links folded flat on each other (singular rod mass matrix)", lambda: folded_chain(4), _planar("hard"),
                       CHAIN_SAMPLER),
        CatalogueEntry("pinned-triangle", "a rigid triangle pinned at two corners (a redundant constraint)", pinned_triangle, _planar("hard"),
                       OWN_STATE),
        CatalogueEntry("chain8-mixed", "8 links of mixed lengths (0.1-2) and masses (0.01-10) released near horizontal", mixed_chain,
                       _planar("hard"), CHAIN_SAMPLER),
        CatalogueEntry("pendulum", "one rod pinned at one end, released at 0.3 rad", pendulum, _planar("hard"), CHAIN_SAMPLER),
        CatalogueEntry("free-triangle", "an unpinned spinning triangle (a free rigid body)", free_triangle, _planar("hard"), OWN_STATE),
        CatalogueEntry("double-pinned", "4 links hanging between two pins (a loop through the ground)", double_pinned_chain, _planar("hard"),
                       OWN_STATE),
        CatalogueEntry("T2-slack", "T2 with its ropes 0.1 % slack, hanging off the self-stressed start", lambda: slackened(paper_structure("T2")),
                       _planar("hard"), OWN_STATE),
        CatalogueEntry("T3-slack", "T3 with its ropes 0.1 % slack, hanging off the self-stressed start", lambda: slackened(paper_structure("T3")),
                       _planar("hard"), OWN_STATE),
        CatalogueEntry("chain4-3d", "4 unit links in 3D pinned at one end, turning in a cone about -y", lambda: spatial_chain(4),
                       ("3d", "transfer", "mjcf"), CHAIN_SAMPLER),
        CatalogueEntry("chain8-3d", "8 unit links in 3D pinned at one end", lambda: spatial_chain(8), ("3d", "transfer", "mjcf"), CHAIN_SAMPLER),
        CatalogueEntry("chain16-3d", "16 unit links in 3D pinned at one end", lambda: spatial_chain(16), ("3d", "transfer", "mjcf"), CHAIN_SAMPLER),
        CatalogueEntry("chain100-3d", "100 unit links in 3D pinned at one end", lambda: spatial_chain(100), ("3d", "transfer", "mjcf"),
                       CHAIN_SAMPLER),
        CatalogueEntry("chain4-3d-varied", "the varied chain's 4 links in 3D, turning in a cone about -y", functools.partial(chain4_varied, dim=3),
                       ("3d", "transfer"), CHAIN_SAMPLER),
        *(CatalogueEntry(f"chain{n}-3d-varied", f"{n} links of varied lengths, masses, inertias in 3D (`varied_chain`, seed {n})",
                         functools.partial(varied_chain, n, n, dim=3), ("3d", "transfer"), CHAIN_SAMPLER) for n in (8, 16, 100)),
        CatalogueEntry("net4x4-3d", "a 4 x 4 net of links (9 closed loops) hung from two corners", spatial_net, ("3d", "transfer", "mjcf"),
                       OWN_STATE),
        # A pinned chain of short links: the 3D chain sampler's cone and spins, not its helix.
        CatalogueEntry("rope-3d", "a rope of 30 links 0.1 long pinned at one end, released as a loose helix", spatial_rope,
                       ("3d", "transfer", "mjcf"), CHAIN_SAMPLER),
        CatalogueEntry("tensegrity-3d", "a loose three-rod tensegrity prism of slack rope chains hung from three pins", spatial_tensegrity,
                       ("3d", "transfer", "mjcf"), OWN_STATE),
        *(CatalogueEntry(name, description, functools.partial(imported_scene, name), _planar("imported", "mjcf"), PROJECTED)
          for name, description in IMPORTED.items()),
        *(CatalogueEntry(name, description, functools.partial(imported_scene, name), ("3d", "imported", "mjcf"), PROJECTED)
          for name, description in IMPORTED_3D.items()),
        *(CatalogueEntry(f"finzi-pendulum{n}", f"Finzi et al. (2020)'s {n}-pendulum: {n} point mass{'es' if n > 1 else ''} on massless rods",
                         functools.partial(finzi_pendulum, n), _planar("papers"), PROJECTED) for n in FINZI_PENDULUMS),
    ]
}


def scene_names(*tags: str) -> tuple[str, ...]:
    """Names of the catalogue's entries that carry every one of `tags`, in catalogue order."""
    unknown = [tag for tag in tags if tag not in TAGS]
    if unknown:
        raise SceneError(f"unknown scene tag {unknown[0]!r} (choose from {', '.join(TAGS)})")
    return tuple(name for name, entry in CATALOGUE.items() if set(tags) <= set(entry.tags))


@functools.cache
def _built(entry: CatalogueEntry) -> Scene:
    # Cached per entry (scenes are immutable), so comparing a scene with the catalogue
    # builds each entry once (chain1000's build is not free).
    return entry.build()


def catalogue_entry(scene: Scene) -> CatalogueEntry | None:
    """The catalogue entry `scene` is (same name and content: a user's file may reuse a
    name with other content), or None."""
    entry = CATALOGUE.get(scene.name)
    return entry if entry is not None and _built(entry) == scene else None


def initial_state_policy(scene: Scene) -> str:
    """How training data and the benchmark start `scene` (`INITIAL_STATE_POLICIES`): its
    catalogue entry's policy; for any other scene the chain sampler on a pinned chain,
    projected perturbations otherwise."""
    entry = catalogue_entry(scene)
    if entry is not None:
        return entry.initial_states
    return CHAIN_SAMPLER if is_pinned_chain(scene) else PROJECTED


def check_scene_name(name_or_path: str) -> None:
    """`SceneError` unless `get_scene(name_or_path)` finds a scene: a catalogue name
    (not built: checking a profile's names at import must not build every scene), or a
    scene file that loads."""
    if name_or_path not in CATALOGUE:
        get_scene(name_or_path)


def get_scene(name_or_path: str) -> Scene:
    """A catalogue scene by name (`CATALOGUE`), or a user's scene JSON file by path."""
    if name_or_path in CATALOGUE:
        return CATALOGUE[name_or_path].build()
    if name_or_path.endswith(".json") or Path(name_or_path).exists():
        return load_scene_file(name_or_path)
    raise SceneError(f"unknown scene {name_or_path!r}: not in the catalogue (`lgnn scenes` lists it: {', '.join(CATALOGUE)}) nor a .json file")
