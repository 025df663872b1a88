"""GNS, the paper's baseline graph network simulator (`gns`): node `(q, qd)` and edge
`(type, dq, w)` encoders to latent 8, the paper's message-passing layers
(`kit.init_graph_model`) with MLPs of 128 hidden units, a node decoder MLP to
accelerations. No constraints: it predicts node accelerations directly, and pinned
nodes (a known boundary condition) get zero. The strong GNS-10-128 recipe is
`strong_gns`.
"""

from __future__ import annotations

import numpy as np

from lgnn import physics
from lgnn.learn.graphs import graph_from_state
from lgnn.learn.models import kit
from lgnn.learn.models.registry import ModelSpec, register
from lgnn.scene import Scene


def init(key, config) -> dict:
    return kit.init_graph_model(key, config, (config.latent, config.hidden, config.dim))


def apply(config, params: dict, graph):
    """Node accelerations (N, D) on one graph."""
    h, _ = kit.graph_net_outputs(params, graph)
    return kit.apply_mlp(params["readout"], h)


def acceleration(config, params: dict, scene: Scene) -> physics.AccelerationFn:
    free = np.ones((scene.n_nodes, 1))
    free[list(scene.pinned)] = 0.0

    def accel(q, qd):
        return apply(config, params, graph_from_state(scene, q, qd, config.vocabulary, config.link_features)) * free

    return accel


# The paper appendix's sizes; two message-passing layers let a node see its neighbours'
# neighbours (the paper does not give this number).
GNS = register(ModelSpec("gns", init, apply=apply, acceleration=acceleration, latent=8, hidden=128, message_passing=2, link_features=True))
