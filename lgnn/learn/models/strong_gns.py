"""The strong GNS baseline: the public GNS-10-128 recipe on rod graphs.

The recipe is Sanchez-Gonzalez et al. 2020 (deepmind-research `learning_to_simulate`)
as LagrangeBench's GNS-10-128 sets it: encoder, `L` (10) unshared message-passing steps
with node and edge residuals, decoder; latent 128; every MLP has 2 hidden layers of 128
and ReLU, with LayerNorm after every MLP except the decoder's. It registers itself
as `gns-10-128`; the paper's tiny GNS stays `gns`.

Contract (pure functions; `config` is a `ModelConfig`, read for `latent`, `hidden`,
`message_passing`, `vocabulary` and `dim`):
- `statistics(config, scene, q, qd, qdd) -> {name: array}`: the training set's
  normalisation constants, from its states `q, qd` and targets `qdd`, each (S, N, D);
- `init(key, config) -> params`, with those constants at neutral placeholders (zero
  means, unit scales) under `params["statistics"]`, which training fills in once
  (`models.with_statistics`) and checkpoints keep like any leaf;
- `acceleration(config, params, scene) -> accel(q, qd) -> qdd` (N, D), zero at the
  pinned nodes (a known boundary condition).

Inputs, each normalised by the training set's statistics:
- nodes: velocity `(qd - velocity_mean) / velocity_std` (D) and a learned embedding
  (`TYPE_EMBEDDING` entries) of the node's type, pinned or free;
- edges (both directions of every link): relative displacement `(q_s - q_r) / length_scale`
  (D) and its norm, the rod's length (1), the link type one-hot (K), and the rod's mass
  and inertia over the training scene's means (2: the issue's rod features; constant on
  a uniform chain, they let a model trained on varied links tell them apart).
No absolute position enters, so predictions are invariant under a translation of every
node. The decoder's output is a normalised acceleration: `qdd = out * acceleration_std +
acceleration_mean`. Training minimises the mean squared error of `qdd` itself (the
library's one loss): with one scale per dimension of similar size this is the
recipe's normalised loss times a constant, which Adam does not see.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from lgnn.learn.graphs import edge_type_indices, graph_from_state
from lgnn.learn.models import kit
from lgnn.learn.models.registry import ModelSpec, register
from lgnn.scene import Scene
from lgnn.sharding import platform

# The recipe's node-type embedding size (learning_to_simulate: 16).
TYPE_EMBEDDING = 16
# Node types: the index of each row of the type embedding.
FREE, PINNED = 0, 1
# Hidden layers of every MLP (the recipe: 2).
HIDDEN_LAYERS = 2
# LayerNorm's epsilon (haiku's and flax's default).
LAYER_NORM_EPS = 1e-5


def processor_unroll() -> bool:
    """Whether the message-passing steps are written out in the compiled program rather
    than looped over their stacked parameters: on an accelerator, where each loop
    iteration (forward, and again backward) costs a launch and a wait for the host and
    a step's arithmetic takes microseconds. Measured on one H200, 3 seeds packed, batch
    100, float64 (results/gpu/training/README.md, "The message-passing loop"): an epoch
    of gns-10-128 0.325 -> 0.255 s (its floor, `gns_floor.py`, 0.260), of cgnode 0.341 ->
    0.271 s, for 2.6x the compile time (13 -> 34 s); on a CPU the loop stays, whose
    steps are arithmetic-bound and whose compile time is most of a short run. The same
    arithmetic either way, to round-off."""
    return platform() != "cpu"


def statistics(config, scene: Scene, q, qd, qdd) -> dict:
    """Normalisation constants of the training states `q, qd` and targets `qdd`, each
    (S, N, D) of `scene`: per dimension the mean and std (D,) of the free nodes'
    velocities and accelerations (pinned nodes are zero by construction and would only
    shrink the spread), the RMS link length () and the scene's mean link mass and
    inertia (). A spread of zero (a scene at rest) becomes 1, so it stays a scale."""
    free = list(scene.free_nodes)
    qd_free, qdd_free = np.asarray(qd)[:, free], np.asarray(qdd)[:, free]
    i, j = scene.edge_index.T
    dq = np.asarray(q)[:, i] - np.asarray(q)[:, j]

    def scale(value):
        return np.where(value > 0, value, 1.0)

    return {
        "velocity_mean": qd_free.mean((0, 1)),
        "velocity_std": scale(qd_free.std((0, 1))),
        "acceleration_mean": qdd_free.mean((0, 1)),
        "acceleration_std": scale(qdd_free.std((0, 1))),
        "length_scale": scale(np.sqrt(np.mean(np.sum(dq**2, -1)))),
        "mass_scale": scale(np.mean(scene.masses)),
        "inertia_scale": scale(np.mean(scene.inertias)),
    }


def _placeholder_statistics(dim: int) -> dict:
    zeros, ones = jnp.zeros(dim), jnp.ones(dim)
    return {"velocity_mean": zeros, "velocity_std": ones, "acceleration_mean": zeros, "acceleration_std": ones,
            "length_scale": jnp.ones(()), "mass_scale": jnp.ones(()), "inertia_scale": jnp.ones(())}


def _init_mlp(key, n_in: int, hidden: int, n_out: int, layer_norm: bool = True) -> dict:
    """An MLP `n_in -> hidden x HIDDEN_LAYERS -> n_out` (`kit.mlp`), with LayerNorm's
    scale and offset when `layer_norm`. Its layers sit under `"layers"`, beside
    `"norm"`, where the kit's MLP is a bare list: checkpoints keep leaves by pytree
    path, so this wrapper stays."""
    mlp = {"layers": kit.mlp(key, (n_in, *(hidden,) * HIDDEN_LAYERS, n_out))}
    if layer_norm:
        mlp["norm"] = {"scale": jnp.ones(n_out), "offset": jnp.zeros(n_out)}
    return mlp


def _apply_mlp(mlp: dict, x):
    x = kit.apply_mlp(mlp["layers"], x, jax.nn.relu)
    if "norm" not in mlp:
        return x
    mean = jnp.mean(x, -1, keepdims=True)
    variance = jnp.mean((x - mean) ** 2, -1, keepdims=True)
    return (x - mean) * jax.lax.rsqrt(variance + LAYER_NORM_EPS) * mlp["norm"]["scale"] + mlp["norm"]["offset"]


def _edge_inputs(config) -> int:
    """Edge input size: displacement (D), length (1), type one-hot (K), mass and inertia (2)."""
    return config.dim + 1 + len(config.vocabulary) + 2


def init(key, config) -> dict:
    """Parameters of the recipe's network for `config`'s sizes (module docstring); the
    `message_passing` steps' MLPs are stacked on a leading axis (one `lax.scan`)."""
    latent, hidden, d = config.latent, config.hidden, config.dim
    k_type, k_node, k_edge, k_steps, k_decoder = jax.random.split(key, 5)

    def step(k):
        k_e, k_n = jax.random.split(k)
        return {"edge_mlp": _init_mlp(k_e, 3 * latent, hidden, latent), "node_mlp": _init_mlp(k_n, 2 * latent, hidden, latent)}

    return {
        "type_embedding": jax.random.normal(k_type, (2, TYPE_EMBEDDING)),
        "node_encoder": _init_mlp(k_node, d + TYPE_EMBEDDING, hidden, latent),
        "edge_encoder": _init_mlp(k_edge, _edge_inputs(config), hidden, latent),
        "processor": jax.vmap(step)(jax.random.split(k_steps, config.message_passing)),
        "decoder": _init_mlp(k_decoder, latent, hidden, d, layer_norm=False),
        "statistics": _placeholder_statistics(d),
    }


def acceleration(config, params: dict, scene: Scene):
    """`accel(q, qd) -> qdd` (N, D) of the network on `scene` (module docstring)."""
    node_type = np.full(scene.n_nodes, FREE)
    node_type[list(scene.pinned)] = PINNED
    free = jnp.asarray(node_type == FREE, float)[:, None]
    link_features = jnp.stack([jnp.asarray(scene.masses), jnp.asarray(scene.inertias)], -1)
    # Both directions of every link, in `graph_from_state`'s edge order.
    link_features = jnp.concatenate([link_features, link_features])
    edge_type_indices(scene, config.vocabulary)  # refuses an unseen link type in one line
    stats = params["statistics"]

    def accel(q, qd):
        graph = graph_from_state(scene, q, qd, config.vocabulary)
        displacement = graph.edges["dq"] / stats["length_scale"]
        rod = link_features / jnp.stack([stats["mass_scale"], stats["inertia_scale"]])
        edge_x = jnp.concatenate([displacement, jnp.linalg.norm(displacement, axis=-1, keepdims=True), graph.edges["type"], rod], -1)
        node_x = jnp.concatenate([(qd - stats["velocity_mean"]) / stats["velocity_std"], params["type_embedding"][node_type]], -1)
        h, e = _apply_mlp(params["node_encoder"], node_x), _apply_mlp(params["edge_encoder"], edge_x)

        def message_passing(carry, step):
            h, e = carry
            e = e + _apply_mlp(step["edge_mlp"], jnp.concatenate([e, h[graph.senders], h[graph.receivers]], -1))
            received = jax.ops.segment_sum(e, graph.receivers, num_segments=h.shape[0])
            h = h + _apply_mlp(step["node_mlp"], jnp.concatenate([h, received], -1))
            return (h, e), None

        (h, _), _ = jax.lax.scan(message_passing, (h, e), params["processor"], unroll=processor_unroll())
        normalised = _apply_mlp(params["decoder"], h)
        return (normalised * stats["acceleration_std"] + stats["acceleration_mean"]) * free

    return accel


# The GNS-10-128 recipe's sizes, LagrangeBench's AdamW weight decay (1e-8) and noise of
# 5e-4 of the normalised velocities (the recipe's 3e-4..7e-4).
GNS_10_128 = register(ModelSpec(
    "gns-10-128", init, acceleration=acceleration, statistics=statistics,
    latent=128, hidden=128, message_passing=10, weight_decay=1e-8, velocity_noise=5e-4,
))
