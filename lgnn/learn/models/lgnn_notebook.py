"""`lgnn-notebook`: the authors' notebook variant of LGNN (issue 13).

No message passing; each link's centre-of-mass velocity `v_cm`, angular feature `w = dq
x dqd` (`l^2 omega`) and centre of mass `r_cm`, each with the edge type, go to three
separate MLPs (hidden 10): `T_link = |MLP_v(v_cm)|^2 + |MLP_w(w)|^2`, `V_link =
MLP_r(r_cm)`, read out as LGNN's Lagrangian (`lgnn.lgnn_lagrangian_fn`). The MLPs for T
output a vector of `latent` (5) entries and T is its squared norm (a scalar output
squared has a rank-1 mass matrix, which cannot be `m I` in 2D); they start with T
strictly convex in the velocities (`_positive_convex_start`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from lgnn import physics
from lgnn.learn.graphs import edge_attributes
from lgnn.learn.models import kit
from lgnn.learn.models.lgnn import lgnn_lagrangian_fn
from lgnn.learn.models.registry import ModelSpec, register


def init(key, config) -> dict:
    """The notebook variant's three MLPs, the two of `T` started convex and positive
    (`_positive_convex_start`)."""
    k_types, d, w_dim = kit.feature_sizes(config)
    keys = jax.random.split(key, 3)
    return {
        "v_cm": _positive_convex_start(kit.mlp(keys[0], (k_types + d, config.hidden, config.latent))),
        "w": _positive_convex_start(kit.mlp(keys[1], (k_types + w_dim, config.hidden, config.latent))),
        "r_cm": kit.mlp(keys[2], (k_types + d, config.hidden, 1)),
    }


def _positive_convex_start(mlp: list) -> list:
    """A one-hidden-layer MLP `f(x) = W2 squareplus(W1 x + b1) + b2` whose squared norm
    `|f(x)|^2` is strictly convex in `x`: `W2` non-negative, `b2` zero (as `kit.linear` makes it).

    Why: the notebook's `T = |MLP_v(v_cm)|^2 + |MLP_w(w)|^2` is a sum of squares, yet
    its Hessian `2 sum_i (grad f_i grad f_i^T + f_i Hess f_i)` is indefinite wherever an
    output `f_i` is negative and `Hess f_i` is not small. From the random start on
    chain4-3d the mass matrix on the constraint tangent space was indefinite at 1-17 % of
    the validation states for seeds 0, 4, 5 (of 0-5; their untrained validation MSE
    5e2-1e4, the others' 1e2-3e2), seeds 4 and 5 stalled at 1e4 and 3e3 on 10
    trajectories, and at the full profile seeds 0 and 1 stalled from the first epochs at
    2e3 and 3e2 while seed 2 reached 7e-6. With this start every seed's tangent mass
    matrix is positive definite (smallest eigenvalue >= 0.5), the untrained MSE is
    1e2-2e2, and all six seeds train alike. Here each hidden unit is strictly convex
    and positive (squareplus is, of an affine map), so each `f_i`, a non-negative
    combination of them, is positive and convex, with `Hess f_i = W1 diag(W2[:, i] squareplus'') W1^T`
    positive definite (every `W2` entry positive, `W1`'s input rows of full rank):
    `f_i^2` is strictly convex. `v_cm` and `w = dq x dqd` are linear in the velocities
    and together fix both nodes' velocities on motions that keep the link's length, so
    the initial mass matrix is positive definite on the tangent space. Only the start
    changes (same architecture and shapes; training may move weights below zero)."""
    first, *rest = mlp
    return [first, *kit.nonnegative_weights(rest)]


def edge_energies(params: dict):
    def energies(graph):
        s, r, kind = graph.senders, graph.receivers, edge_attributes(graph)
        v_cm = 0.5 * (graph.nodes["qd"][s] + graph.nodes["qd"][r])
        r_cm = 0.5 * (graph.nodes["q"][s] + graph.nodes["q"][r])
        kinetic = sum(jnp.sum(kit.apply_mlp(params[k], jnp.concatenate([kind, x], -1)) ** 2, -1) for k, x in (("v_cm", v_cm), ("w", graph.edges["w"])))
        return kinetic, kit.apply_mlp(params["r_cm"], jnp.concatenate([kind, r_cm], -1))[:, 0]

    return energies


LGNN_NOTEBOOK = register(ModelSpec(
    "lgnn-notebook", init, apply=lambda config, params, graph: edge_energies(params)(graph),
    lagrangian=lambda config, params, scene: lgnn_lagrangian_fn(scene, config.vocabulary, edge_energies(params), config.link_features),
    latent=5, hidden=10, mass=lambda config, params, scene: physics.LOCAL, link_features=True,
))
