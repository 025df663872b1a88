"""LGNN (paper section 3 and appendix) and its message-passing variants: `lgnn`,
`lgnn-mp1`, `lgnn-mp2`.

Two graph networks (`kit.init_graph_net`), for T (node velocities; edge type one-hot
and `w = dq x dqd`) and V (node positions; edge type and `dq`). Embeddings `h =
squareplus(Linear(features))` of size 5, MLPs with one hidden layer of 10 units,
squareplus, `L` message-passing layers (paper Eqs.), per-edge energy `MLP(z_ij)` summed
over links, `L = T - V`. The three registered variants share this code:
- `lgnn` (`message_passing = 0`, this suite's per-edge variant; neither the paper's
  equations nor the authors' notebook): the read-out sees `z_ij = h_ij + W (h_i ||
  h_j)`, the edge-update input of the paper's first layer without its MLP, so a link's
  energy depends on its own features and its two end nodes (the paper's equations with
  L = 0 would read `h_ij` alone, which cannot express gravity `m g y_cm` nor
  translational kinetic energy);
- `lgnn-mp1`, `lgnn-mp2`: the paper's equations with L = 1 and 2 layers.
Per-link energies average the link's two orientations (`graphs` module). Drag scenes
add a learned per-link drag coefficient (one per edge type, `generic.init`): force
`-c v_cm`, split between the two nodes.

`lgnn_lagrangian_fn(scene, vocabulary, edge_energies)` is the read-out as a Lagrangian
of any per-edge energies (`lgnn-notebook` plugs in its own; the tests the exact ones).
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

from lgnn import physics
from lgnn.learn.graphs import edge_attributes, graph_from_state
from lgnn.learn.models import kit
from lgnn.learn.models.registry import ModelSpec, register
from lgnn.scene import Scene


def _edge_energy_reach(config) -> int:
    """The mass matrix's reach of a sum of per-edge energies read from the graph
    network's final edge embeddings: two nodes are coupled when one edge's embedding
    sees both, at most 2 s + 1 links apart."""
    return 2 * kit.graph_net_reach(config.message_passing)[1] + 1


def init(key, config) -> dict:
    k_types, d, w_dim = kit.feature_sizes(config)
    latent, hidden, layers = config.latent, config.hidden, config.message_passing
    keys = jax.random.split(key, 3)
    params = {
        "kinetic": kit.init_graph_net(keys[0], d, k_types + w_dim, latent, hidden, layers),
        "potential": kit.init_graph_net(keys[1], d, k_types + d, latent, hidden, layers),
    }
    params["kinetic"]["readout"] = kit.mlp(jax.random.fold_in(keys[0], 1), (latent, hidden, 1))
    params["potential"]["readout"] = kit.mlp(jax.random.fold_in(keys[1], 1), (latent, hidden, 1))
    params["kinetic"] = kit.convex_start(params["kinetic"])
    return params


def edge_energies(params: dict):
    """`energies(graph) -> (T, V)`, each (2E,): the two networks' per-edge read-outs."""
    def energies(graph):
        nodes, edges = graph.nodes, graph.edges
        out = []
        for net, node_x, edge_x in (
            ("kinetic", nodes["qd"], jnp.concatenate([edge_attributes(graph), edges["w"]], -1)),
            ("potential", nodes["q"], jnp.concatenate([edge_attributes(graph), edges["dq"]], -1)),
        ):
            _, z = kit.apply_graph_net(params[net], node_x, edge_x, graph.senders, graph.receivers)
            out.append(kit.apply_mlp(params[net]["readout"], z)[:, 0])
        return tuple(out)

    return energies


def lgnn_lagrangian_fn(scene: Scene, vocabulary, edge_energies: Callable, link_features: bool = False) -> physics.LagrangianFn:
    """LGNN's read-out as a Lagrangian: `edge_energies(graph) -> (T, V)`, each (2E,) one
    value per directed edge, is averaged over each link's two orientations and summed:
    `L = sum_links (T - V)`. The learned model plugs its networks in here; the tests plug
    in the exact per-link energies to show the pipeline is the physics pipeline."""

    def lagrangian(q, qd):
        kinetic, potential = edge_energies(graph_from_state(scene, q, qd, vocabulary, link_features))
        return 0.5 * jnp.sum(kinetic - potential)

    return lagrangian


def _spec(name: str, message_passing: int) -> ModelSpec:
    return ModelSpec(
        name, init, apply=lambda config, params, graph: edge_energies(params)(graph),
        lagrangian=lambda config, params, scene: lgnn_lagrangian_fn(scene, config.vocabulary, edge_energies(params), config.link_features),
        latent=5, hidden=10, message_passing=message_passing, link_features=True,
        # A link's energy sees its own two nodes only without message passing and after
        # one layer, nodes further away after more (`_edge_energy_reach`).
        mass=lambda config, params, scene: physics.MassStructure(_edge_energy_reach(config)),
    )


# Sizes are the paper appendix's; message-passing layers when not given: LGNN's
# per-edge variant (the true per-link energies need nothing more).
LGNN = register(_spec("lgnn", 0))
LGNN_MP1 = register(_spec("lgnn-mp1", 1))
LGNN_MP2 = register(_spec("lgnn-mp2", 2))
