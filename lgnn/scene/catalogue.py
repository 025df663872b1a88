"""The built-in scenes of the paper, and the initial-condition sampler.

Each built-in is constructed by one function from a seed; `get_scene(name_or_path)`
resolves a built-in name or a user's scene JSON file.

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
from lgnn.scene.schema import Scene, State, is_pinned_chain, load_scene_file, scene_from_dict

# Paper's chain sampler (authors' code): each link hangs at (0, -1) rotated by an
# independent angle in [-15, 15] degrees, then the whole chain is rotated by +45
# degrees about the pinned node; released from rest.
CHAIN_LINK_ANGLE = np.deg2rad(15.0)
CHAIN_ROTATION = np.deg2rad(45.0)
PAPER_GRAVITY = 10.0
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


def sample_initial_states(scene: Scene, key: jax.Array, count: int) -> State:
    """`count` initial states (q, qd) each (count, N, D), for evaluation and training data.

    Chains pinned at node 0 use the paper's sampler (random link angles, released
    from rest, pin kept at the scene's pin position); every other scene has one
    initial condition, its own, repeated.
    """
    if not is_pinned_chain(scene):
        q = np.broadcast_to(scene.nodes, (count, *scene.nodes.shape))
        qd = np.broadcast_to(scene.velocities, q.shape)
        return State(jnp.asarray(q), jnp.asarray(qd))
    lengths = jnp.asarray(scene.lengths)
    angles = jax.random.uniform(key, (count, scene.n_links), lengths.dtype, -CHAIN_LINK_ANGLE, CHAIN_LINK_ANGLE)
    q = jax.vmap(lambda a: chain_positions(lengths, a))(angles) + jnp.asarray(scene.nodes[0])
    return State(q, jnp.zeros_like(q))


def _chain_dict(name: str, lengths, masses, inertias, seed: int, drag: float = 0.0) -> dict:
    rng = np.random.default_rng(seed)
    angles = rng.uniform(-CHAIN_LINK_ANGLE, CHAIN_LINK_ANGLE, len(lengths))
    nodes = chain_positions(np.asarray(lengths, np.float64), angles)
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


def chain4_varied(seed: int = 0) -> Scene:
    """The paper's 4-link chain with varied link properties (appendix). Physical inertia
    is the listed `I_k` times `l_k^4` (module docstring)."""
    inertias = [i * length**4 for i, length in zip(VARIED_PAPER_INERTIAS, VARIED_LENGTHS, strict=True)]
    return scene_from_dict(_chain_dict("chain4-varied", VARIED_LENGTHS, VARIED_MASSES, inertias, seed))


def chain4_drag(seed: int = 0) -> Scene:
    """The 4-link chain with linear drag 0.01 on each link's centre velocity."""
    return chain(4, seed, name="chain4-drag", drag=PAPER_DRAG)


@functools.cache
def _paper_structures() -> dict:
    text = resources.files("lgnn").joinpath("assets/paper_structures.json").read_text()
    return json.loads(text)


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


@dataclass(frozen=True)
class BuiltinScene:
    name: str
    description: str
    build: Callable[[], Scene]


BUILTIN_SCENES: dict[str, BuiltinScene] = {
    entry.name: entry
    for entry in [
        BuiltinScene("chain4", "4 unit links pinned at one end (training scene)", lambda: chain(4)),
        BuiltinScene("chain8", "8 unit links pinned at one end", lambda: chain(8)),
        BuiltinScene("chain16", "16 unit links pinned at one end", lambda: chain(16)),
        BuiltinScene("chain100", "100 unit links pinned at one end", lambda: chain(100)),
        BuiltinScene("chain4-varied", "4 links with the paper's varied lengths, masses, inertias", chain4_varied),
        BuiltinScene("chain4-drag", "4 unit links with linear drag 0.01", chain4_drag),
        BuiltinScene("T1", "tensegrity: two ropes, a braced rope frame, 6 rods (paper fig. D)", lambda: paper_structure("T1")),
        BuiltinScene("T2", "tensegrity: rope loop with one rod (paper fig. E)", lambda: paper_structure("T2")),
        BuiltinScene("T3", "lattice of ropes pinned at six nodes (paper fig. F)", lambda: paper_structure("T3")),
    ]
}


def get_scene(name_or_path: str) -> Scene:
    """A built-in scene by name, or a user's scene JSON file by path."""
    if name_or_path in BUILTIN_SCENES:
        return BUILTIN_SCENES[name_or_path].build()
    if name_or_path.endswith(".json") or Path(name_or_path).exists():
        return load_scene_file(name_or_path)
    raise SceneError(
        f"unknown scene {name_or_path!r}: not a built-in ({', '.join(BUILTIN_SCENES)}) nor a .json file"
    )
