"""Graphs of a scene's state: the paper's node and edge features as `jraph.GraphsTuple`.

`graph_from_state(scene, q, qd, vocabulary, link_features)` returns one graph (no batching):
- nodes: `{"q": (N, D), "qd": (N, D)}` positions and velocities (absolute, as in the
  paper: the potential network sees absolute positions, so gravity is learnable);
- edges: `{"type": (2E, K)` one-hot over `vocabulary`, `"dq": (2E, D)` = `q_s - q_r`,
  `"dqd": (2E, D)` = `qd_s - qd_r`, `"w": (2E, W)` = `dq x dqd` (W = 1 in 2D, 3 in 3D)`}`
  for sender s and receiver r; with `link_features`, also `"link": (2E, 3)` each link's
  mass, inertia ratio `I / (m l^2)` (1/12 for a uniform rod) and length
  (`link_attributes`: what tells the links of a varied chain apart, which the paper's
  features cannot: they hold no mass);
- every link appears as two directed edges: first `i -> j` for every link in the
  scene's order, then `j -> i` (senders, receivers). So nothing a model computes can
  depend on which end a scene file names first: per-link read-outs average the two
  orientations, node updates receive one message from every incident link.
The functions are pure in `(q, qd)`, so models built on them can be differentiated
twice (the constrained Euler-Lagrange solve needs `d2L/dqd2`).

Edge types. A model's type vocabulary is fixed when it is trained (stored in its
checkpoint). `edge_type_indices` maps a scene's link types onto it: a model trained on a
single type treats every edge as that type (the authors' code fed the same features to
every edge, which is what made their zero-shot transfer from chains to T1-T3 possible);
a model trained on several types refuses a type it never saw.

`edge_attributes(graph)`: what a model reads of each edge before the state, its type and,
where the graph has them, its link's attributes.

Batching: `pad_batch(graphs, ...)` concatenates graphs and pads them with
`jraph.pad_with_graphs` to fixed sizes, so one compiled function serves graphs of
different sizes. Training on one scene uses `vmap` over states instead.
"""

from __future__ import annotations

from typing import Sequence

import jax.numpy as jnp
import jraph
import numpy as np

from lgnn.errors import ConfigError
from lgnn.scene import Scene


def edge_type_indices(scene: Scene, vocabulary: Sequence[str]) -> np.ndarray:
    """(E,) index of each link's type in `vocabulary` (module docstring for unseen types)."""
    vocabulary = tuple(vocabulary)
    if len(vocabulary) == 1:
        return np.zeros(scene.n_links, np.int64)
    unseen = sorted(set(scene.link_types) - set(vocabulary))
    if unseen:
        raise ConfigError(
            f"scene {scene.name!r} has link type {unseen[0]!r} the model was not trained on "
            f"(known: {', '.join(vocabulary)})"
        )
    return np.asarray([vocabulary.index(t) for t in scene.link_types], np.int64)


# Columns of `link_attributes`: mass, inertia ratio, length.
LINK_FEATURES = 3


def link_attributes(scene: Scene) -> np.ndarray:
    """(2E, LINK_FEATURES) each link's mass, inertia ratio `I / (m l^2)` (0 for a massless
    or pointlike link) and length, once per orientation (`graph_from_state`'s order)."""
    masses, inertias, lengths = (np.asarray(a, np.float64) for a in (scene.masses, scene.inertias, scene.lengths))
    scale = masses * lengths**2
    ratio = np.divide(inertias, scale, out=np.zeros_like(scale), where=scale > 0)
    return np.tile(np.stack([masses, ratio, lengths], -1), (2, 1))


def edge_attributes(graph: jraph.GraphsTuple):
    """(2E, K [+ LINK_FEATURES]) the one-hot types, then the link attributes where the
    graph holds them."""
    if "link" not in graph.edges:
        return graph.edges["type"]
    return jnp.concatenate([graph.edges["type"], graph.edges["link"]], -1)


def cross(a, b):
    """`a x b` over the last axis, kept as a vector: (..., 1) in 2D, (..., 3) in 3D."""
    if a.shape[-1] == 2:
        return (a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0])[..., None]
    return jnp.cross(a, b)


def graph_from_state(scene: Scene, q, qd, vocabulary: Sequence[str] = ("link",), link_features: bool = False) -> jraph.GraphsTuple:
    """The graph of `(q, qd)`, each (N, D), with the paper's features and, with
    `link_features`, each link's attributes (module docstring)."""
    i, j = scene.edge_index.T
    senders, receivers = jnp.asarray(np.concatenate([i, j])), jnp.asarray(np.concatenate([j, i]))
    onehot = np.tile(np.eye(len(vocabulary))[edge_type_indices(scene, vocabulary)], (2, 1))
    dq = q[senders] - q[receivers]
    dqd = qd[senders] - qd[receivers]
    edges = {"type": jnp.asarray(onehot, q.dtype), "dq": dq, "dqd": dqd, "w": cross(dq, dqd)}
    if link_features:
        edges["link"] = jnp.asarray(link_attributes(scene), q.dtype)
    return jraph.GraphsTuple(
        nodes={"q": q, "qd": qd},
        edges=edges,
        senders=senders,
        receivers=receivers,
        n_node=jnp.asarray([scene.n_nodes]),
        n_edge=jnp.asarray([2 * scene.n_links]),
        globals=None,
    )


def pad_batch(graphs: Sequence[jraph.GraphsTuple], n_node: int, n_edge: int, n_graph: int | None = None) -> jraph.GraphsTuple:
    """Batch `graphs` into one `GraphsTuple` padded to `n_node` nodes, `n_edge` edges and
    `n_graph` graphs (default: one more than given, jraph's padding graph). Use
    `jraph.get_graph_padding_mask` to drop the padding from per-graph results."""
    batch = jraph.batch(list(graphs))
    return jraph.pad_with_graphs(batch, n_node, n_edge, n_graph or len(graphs) + 1)
