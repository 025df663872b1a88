"""LGN (`lgn`): the paper's graph network (`kit.init_graph_model`, on node `(q, qd)`
and edge `(type, dq, w)`), read out as one global Lagrangian `MLP(sum_i h_i ||
sum_ij h_ij)`, through the constrained Euler-Lagrange solve.
"""

from __future__ import annotations

import jax.numpy as jnp

from lgnn import physics
from lgnn.learn.graphs import graph_from_state
from lgnn.learn.models import kit
from lgnn.learn.models.registry import ModelSpec, register
from lgnn.scene import Scene


def init(key, config) -> dict:
    """LGN's graph network and read-out, started with `L` convex in the velocities
    (`kit.convex_start`): from the paper's random start its first epochs on chain4 ran at
    training MSE 1e5-1e6 (targets O(10)) and, at batch 100, settled on a plateau worse
    than the untrained model's (issue 13)."""
    params = kit.init_graph_model(key, config, (2 * config.latent, config.hidden, 1))
    return {"net": kit.convex_start(params["net"]), "readout": kit.nonnegative_weights(params["readout"])}


def _pooled(params: dict, graph):
    """LGN's read-out input: the summed node and summed edge embeddings (2 latent,)."""
    h, e = kit.graph_net_outputs(params, graph)
    return jnp.concatenate([jnp.sum(h, 0), jnp.sum(e, 0)])


def apply(config, params: dict, graph):
    """The global Lagrangian () on one graph."""
    return kit.apply_mlp(params["readout"], _pooled(params, graph))[0]


def lagrangian(config, params: dict, scene: Scene) -> physics.LagrangianFn:
    return lambda q, qd: apply(config, params, graph_from_state(scene, q, qd, config.vocabulary, config.link_features))


def _terms(params: dict, graph):
    """LGN's read-out input as a sum of local terms (T, 2 latent): each node's embedding
    in the first half, each edge's in the second (their sum is `_pooled`)."""
    h, e = kit.graph_net_outputs(params, graph)
    return jnp.concatenate([jnp.pad(h, ((0, 0), (0, e.shape[1]))), jnp.pad(e, ((0, 0), (h.shape[1], 0)))])


def mass(config, params: dict, scene: Scene) -> physics.MassStructure:
    """LGN's `L` is a read-out of summed embeddings: its mass matrix is low rank (the
    read-out's 2 latent inputs) plus local. A node's embedding couples nodes up to 2 r
    links apart, an edge's up to 2 s + 1 (`kit.graph_net_reach`)."""
    node, edge = kit.graph_net_reach(config.message_passing)
    return physics.MassStructure(
        max(2 * node, 2 * edge + 1),
        terms=lambda q, qd: _terms(params, graph_from_state(scene, q, qd, config.vocabulary, config.link_features)),
        supports=kit.graph_net_supports(scene, config.message_passing),
        readout=lambda pooled: kit.apply_mlp(params["readout"], pooled)[0],
    )


# GNS's sizes and layers (`gns`).
LGN = register(ModelSpec("lgn", init, apply=apply, lagrangian=lagrangian, mass=mass, latent=8, hidden=128, message_passing=2, link_features=True))
