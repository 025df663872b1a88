"""The one MLP and graph-network kit of the built-in models: params are plain pytrees
(lists and dicts of arrays), initialised LeCun-normal with zero biases.

- `linear(key, n_in, n_out, bias) -> {"w", "b"}`, `apply_linear(p, x)`;
- `mlp(key, sizes) -> [linear, ...]`, `apply_mlp(layers, x, activation=squareplus)`:
  the activation between layers, none after the last (the strong GNS uses ReLU, CHGN
  and CHNN softplus, the others squareplus);
- the paper's graph network, shared by LGNN (twice), GNS and LGN: `init_graph_net`,
  `apply_graph_net`, and what its outputs see (`graph_net_reach`,
  `graph_net_supports`); GNS's and LGN's use of it on node `(q, qd)` and edge
  `(type, dq, w)` (`init_graph_model`, `graph_net_outputs`);
- the feature sizes of a config (`feature_sizes`) and the convex starts of the
  Lagrangian models (`convex_start`, `nonnegative_weights`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from lgnn import physics
from lgnn.learn.graphs import LINK_FEATURES, edge_attributes
from lgnn.scene import Scene


def squareplus(x):
    """`(x + sqrt(x^2 + 4)) / 2`: smooth, twice differentiable (the EL solve needs it)."""
    return 0.5 * (x + jnp.sqrt(x * x + 4.0))


def linear(key, n_in: int, n_out: int, bias: bool = True) -> dict:
    """`{"w": (n_in, n_out), "b": (n_out,)}`: LeCun-normal weights, zero biases."""
    w = jax.random.normal(key, (n_in, n_out)) / np.sqrt(n_in)
    return {"w": w, "b": jnp.zeros(n_out)} if bias else {"w": w}


def apply_linear(p: dict, x):
    y = x @ p["w"]
    return y + p["b"] if "b" in p else y


def mlp(key, sizes) -> list:
    """Layers `sizes[0] -> sizes[1] -> ... -> sizes[-1]`, one `linear` each."""
    keys = jax.random.split(key, len(sizes) - 1)
    return [linear(k, a, b) for k, a, b in zip(keys, sizes[:-1], sizes[1:])]


def apply_mlp(layers: list, x, activation=squareplus):
    """`layers` on `x` (..., sizes[0]) -> (..., sizes[-1]), `activation` after every
    layer but the last."""
    for layer in layers[:-1]:
        x = activation(apply_linear(layer, x))
    return apply_linear(layers[-1], x)


def init_graph_net(key, n_node_in: int, n_edge_in: int, latent: int, hidden: int, layers: int) -> dict:
    keys = jax.random.split(key, 3 + layers)
    params = {
        "node_embed": linear(keys[0], n_node_in, latent),
        "edge_embed": linear(keys[1], n_edge_in, latent),
        "layers": [],
    }
    if layers == 0:
        params["w_readout"] = linear(keys[2], 2 * latent, latent, bias=False)
    for k in keys[3:]:
        k1, k2, k3, k4 = jax.random.split(k, 4)
        params["layers"].append(
            {
                "w_edge": linear(k1, 2 * latent, latent, bias=False),
                "edge_mlp": mlp(k2, (latent, hidden, latent)),
                "w_node": linear(k3, latent, latent, bias=False),
                "node_mlp": mlp(k4, (latent, hidden, latent)),
            }
        )
    return params


def apply_graph_net(params: dict, node_x, edge_x, senders, receivers):
    """Paper Eqs.: embeddings, then L layers of edge and node updates. Returns final
    node (N, latent) and edge (E', latent) embeddings (for L = 0 the edges' read-out
    input `h_ij + W (h_i || h_j)`)."""
    h = squareplus(apply_linear(params["node_embed"], node_x))
    e = squareplus(apply_linear(params["edge_embed"], edge_x))
    if not params["layers"]:
        return h, e + apply_linear(params["w_readout"], jnp.concatenate([h[senders], h[receivers]], -1))
    for layer in params["layers"]:
        e_next = squareplus(apply_mlp(layer["edge_mlp"], e + apply_linear(layer["w_edge"], jnp.concatenate([h[senders], h[receivers]], -1))))
        messages = jax.ops.segment_sum(apply_linear(layer["w_node"], e), receivers, num_segments=h.shape[0])
        h = squareplus(apply_mlp(layer["node_mlp"], h + messages))
        e = e_next
    return h, e


def graph_net_reach(layers: int) -> tuple[int, int]:
    """How far `apply_graph_net`'s outputs see: (r, s) such that a node's final
    embedding depends on nodes at most r links from it, and an edge's on nodes at most s
    links from either of its ends. A layer's edge update reads its own edge and its
    ends' node embeddings (s' = max(s, r)); its node update reads its own embedding and
    the incident edges' embeddings of the layer before (r' = max(r, s + 1))."""
    node, edge = 0, 0
    for _ in range(layers):
        node, edge = max(node, edge + 1), max(edge, node)
    return node, edge


def graph_net_supports(scene: Scene, layers: int) -> tuple[tuple[int, ...], ...]:
    """The nodes each of `apply_graph_net`'s outputs depends on, in its output order:
    each node's embedding (nodes at most r links away), then each directed edge's of
    `graph_from_state` (at most s links from either end; `graph_net_reach`)."""
    node_reach, edge_reach = graph_net_reach(layers)
    nodes = physics.neighbourhoods(scene, node_reach)
    near_edge = physics.neighbourhoods(scene, edge_reach)
    i, j = scene.edge_index.T
    edges = [near_edge[a] | near_edge[b] for a, b in zip(np.concatenate([i, j]), np.concatenate([j, i]))]
    return tuple(tuple(sorted(support)) for support in nodes + edges)


def feature_sizes(config) -> tuple[int, int, int]:
    """(edge attributes A: the K types and, with link features, the link's attributes
    (`graphs.edge_attributes`); dimension D; size W of `w = dq x dqd`: 1 in 2D, D in 3D)
    of a `ModelConfig`."""
    d = config.dim
    return len(config.vocabulary) + (LINK_FEATURES if config.link_features else 0), d, 1 if d == 2 else d


def init_graph_model(key, config, readout: tuple[int, ...]) -> dict:
    """GNS and LGN: one graph network on node `(q, qd)` and edge `(type, dq, w)`, and a
    read-out MLP of sizes `readout`."""
    k_types, d, w_dim = feature_sizes(config)
    keys = jax.random.split(key, 3)
    return {
        "net": init_graph_net(keys[0], 2 * d, k_types + d + w_dim, config.latent, config.hidden, config.message_passing),
        "readout": mlp(keys[1], readout),
    }


def graph_net_outputs(params: dict, graph):
    """`(h (N, latent), e (E', latent))` of `init_graph_model`'s network on `graph`."""
    nodes, edges = graph.nodes, graph.edges
    node_x = jnp.concatenate([nodes["q"], nodes["qd"]], -1)
    edge_x = jnp.concatenate([edge_attributes(graph), edges["dq"], edges["w"]], -1)
    return apply_graph_net(params["net"], node_x, edge_x, graph.senders, graph.receivers)


def convex_start(net: dict) -> dict:
    """A graph network (LGNN's kinetic one, LGN's) with every weight after the
    embeddings made non-negative.

    Why: with the paper's random initialisation the learned mass matrix `d2T/dqd2` is
    indefinite on the constraint tangent space (chain4, seeds 0-2: 45-100 % of the
    training states, smallest |eigenvalue| ~1e-3 of the largest), so the Euler-Lagrange
    solve returns accelerations up to 4e4 (targets are O(10)), gradient norms reach 1e9,
    and Adam's first epochs swing by orders of magnitude (issue 13). Here each node's
    embedding `squareplus(qd_i W + b)` is strictly convex in `qd_i` (squareplus is
    convex; W has rank D), the edge embedding is convex in `qd` (`w` is linear in it),
    and sums and squareplus with non-negative weights keep convexity: the initial `T`
    is strictly convex in the velocities, so its mass matrix is positive definite
    everywhere, on the tangent space included, for any number of message-passing
    layers. Only the starting point changes (same architecture, same parameter
    shapes; training may move weights below zero). LGN and CLNN start the same way
    (`nonnegative_weights` after their first affine map of `(q, qd)`): their `L` is
    then convex in `(q, qd)` jointly, so in the velocities too."""

    embeddings = {k: net[k] for k in ("node_embed", "edge_embed")}
    rest = {k: v for k, v in net.items() if k not in embeddings}
    return {**embeddings, **nonnegative_weights(rest)}


def nonnegative_weights(params):
    """`params` with every weight matrix (leaf `w`) replaced by its absolute value."""
    return jax.tree_util.tree_map_with_path(lambda path, leaf: jnp.abs(leaf) if path[-1].key == "w" else leaf, params)

