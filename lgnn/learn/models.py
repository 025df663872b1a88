"""Learned dynamics: LGNN and the baselines GNS, LGN and CLNN.

A model is a `ModelConfig` (its architecture, the edge-type vocabulary and, for CLNN,
the system size; stored in checkpoints) and a params pytree (nested dicts of arrays):

    params = init(key, config)
    accel = acceleration_fn(config, params, scene)      # accel(q, qd) -> qdd, (N, D)

Every Lagrangian model (LGNN, LGN, CLNN) goes through `physics.acceleration_fn`, the
very same constrained Euler-Lagrange solve as the ground truth; GNS predicts node
accelerations directly (pinned nodes, a known boundary condition, get zero). Rollouts
use the ground truth's integrators: `simulate(scene, config, state,
accel_factory=lambda s: acceleration_fn(model, params, s))`.

Architectures (paper section 3 and appendix):
- LGNN: two graph networks, for T (node velocities; edge type one-hot and `w = dq x
  dqd`) and V (node positions; edge type and `dq`). Embeddings `h = squareplus(Linear
  (features))` of size 5, MLPs with one hidden layer of 10 units, squareplus, `L`
  message-passing layers (paper Eqs.), per-edge energy `MLP(z_ij)` summed over links,
  `L = T - V`. `message_passing = 0` is the authors' per-edge variant: the read-out sees
  `z_ij = h_ij + W (h_i || h_j)`, the edge-update input of the paper's first layer without
  its MLP, so a link's energy depends on its own features and its two end nodes (the
  paper's equations with L = 0 would read `h_ij` alone, which cannot express gravity
  `m g y_cm` nor translational kinetic energy). Per-link energies average the link's
  two orientations (`graphs` module). Drag scenes add a learned per-link drag
  coefficient (one per edge type): force `-c v_cm`, split between the two nodes.
- GNS: node (q, qd) and edge (type, dq, w) encoders to latent 8, the same message-passing
  layers with MLPs of 128 hidden units, a node decoder MLP to accelerations. No
  constraints.
- LGN: the same graph network, read out as one global Lagrangian `MLP(sum_i h_i ||
  sum_ij h_ij)`.
- CLNN: MLP with 2 hidden layers of 128 on the concatenated `(q, qd)` of a fixed-size
  system; refuses a scene of another size.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from lgnn import physics
from lgnn.errors import ConfigError
from lgnn.learn.graphs import edge_type_indices, graph_from_state
from lgnn.scene import Scene

MODEL_NAMES = ("lgnn", "gns", "lgn", "clnn")
LAGRANGIAN_MODELS = ("lgnn", "lgn", "clnn")
# Paper appendix: (embedding size, hidden units, hidden layers) of each model's MLPs.
PAPER_SIZES = {"lgnn": (5, 10, 1), "gns": (8, 128, 1), "lgn": (8, 128, 1), "clnn": (0, 128, 2)}
# Message-passing layers when not given: LGNN's per-edge variant (the true per-link
# energies need nothing more, and it is the authors' code); two layers let GNS and LGN
# nodes see their neighbours' neighbours (the paper does not give this number).
DEFAULT_MESSAGE_PASSING = {"lgnn": 0, "gns": 2, "lgn": 2, "clnn": 0}


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    # One of MODEL_NAMES.
    name: str = "lgnn"
    # Message-passing layers L (None: DEFAULT_MESSAGE_PASSING of the model).
    message_passing: int | None = None
    # Embedding size and MLP hidden units (None: the paper's, PAPER_SIZES).
    latent: int | None = None
    hidden: int | None = None
    # Edge-type vocabulary fixed at training time (graphs.edge_type_indices).
    vocabulary: tuple[str, ...] = ("link",)
    # Learn a per-link drag term (set when the training scene has drag).
    drag: bool = False
    # System size (nodes, dimension) of the training scene; CLNN is tied to it.
    n_nodes: int = 5
    dim: int = 2

    def __post_init__(self):
        if self.name not in MODEL_NAMES:
            raise ConfigError(f"unknown model {self.name!r} (choose from {', '.join(MODEL_NAMES)})")
        if self.message_passing is None:
            object.__setattr__(self, "message_passing", DEFAULT_MESSAGE_PASSING[self.name])
        latent, hidden, _ = PAPER_SIZES[self.name]
        object.__setattr__(self, "latent", self.latent or latent)
        object.__setattr__(self, "hidden", self.hidden or hidden)
        object.__setattr__(self, "vocabulary", tuple(self.vocabulary))
        if self.message_passing < 0:
            raise ConfigError(f"message-passing layers must be >= 0, got {self.message_passing}")

    @classmethod
    def for_scene(cls, name: str, scene: Scene, **overrides) -> "ModelConfig":
        """The config of a model trained on `scene` (its types, drag and size)."""
        settings = dict(vocabulary=tuple(sorted(set(scene.link_types))), drag=scene.drag > 0, n_nodes=scene.n_nodes, dim=scene.dim)
        return cls(name, **{**settings, **overrides})

    def to_dict(self) -> dict:
        return {**dataclasses.asdict(self), "vocabulary": list(self.vocabulary)}

    @classmethod
    def from_dict(cls, data: dict) -> "ModelConfig":
        fields = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - fields)
        if unknown:
            raise ConfigError(f"model config: unknown field {unknown[0]!r}")
        return cls(**{**data, "vocabulary": tuple(data.get("vocabulary", ("link",)))})


def check_compatible(config: ModelConfig, scene: Scene) -> None:
    """Raise `ConfigError` if the model cannot run on `scene` (size, dimension, types)."""
    if scene.dim != config.dim:
        raise ConfigError(f"model {config.name} was trained in {config.dim}D, scene {scene.name!r} is {scene.dim}D")
    if config.name == "clnn" and scene.n_nodes != config.n_nodes:
        raise ConfigError(
            f"clnn is tied to its training system size ({config.n_nodes} nodes); scene {scene.name!r} has {scene.n_nodes}"
        )
    edge_type_indices(scene, config.vocabulary)


# ---------------------------------------------------------------------------------
# Building blocks
# ---------------------------------------------------------------------------------


def squareplus(x):
    """`(x + sqrt(x^2 + 4)) / 2`: smooth, twice differentiable (the EL solve needs it)."""
    return 0.5 * (x + jnp.sqrt(x * x + 4.0))


def _linear(key, n_in: int, n_out: int, bias: bool = True) -> dict:
    w = jax.random.normal(key, (n_in, n_out)) / np.sqrt(n_in)
    return {"w": w, "b": jnp.zeros(n_out)} if bias else {"w": w}


def _apply_linear(p: dict, x):
    y = x @ p["w"]
    return y + p["b"] if "b" in p else y


def _mlp(key, sizes) -> list:
    keys = jax.random.split(key, len(sizes) - 1)
    return [_linear(k, a, b) for k, a, b in zip(keys, sizes[:-1], sizes[1:])]


def _apply_mlp(layers: list, x):
    for layer in layers[:-1]:
        x = squareplus(_apply_linear(layer, x))
    return _apply_linear(layers[-1], x)


# ---------------------------------------------------------------------------------
# The graph network shared by LGNN (twice), GNS and LGN
# ---------------------------------------------------------------------------------


def _init_graph_net(key, n_node_in: int, n_edge_in: int, latent: int, hidden: int, layers: int) -> dict:
    keys = jax.random.split(key, 3 + layers)
    params = {
        "node_embed": _linear(keys[0], n_node_in, latent),
        "edge_embed": _linear(keys[1], n_edge_in, latent),
        "layers": [],
    }
    if layers == 0:
        params["w_readout"] = _linear(keys[2], 2 * latent, latent, bias=False)
    for k in keys[3:]:
        k1, k2, k3, k4 = jax.random.split(k, 4)
        params["layers"].append(
            {
                "w_edge": _linear(k1, 2 * latent, latent, bias=False),
                "edge_mlp": _mlp(k2, (latent, hidden, latent)),
                "w_node": _linear(k3, latent, latent, bias=False),
                "node_mlp": _mlp(k4, (latent, hidden, latent)),
            }
        )
    return params


def _apply_graph_net(params: dict, node_x, edge_x, senders, receivers):
    """Paper Eqs.: embeddings, then L layers of edge and node updates. Returns final
    node (N, latent) and edge (E', latent) embeddings (for L = 0 the edges' read-out
    input `h_ij + W (h_i || h_j)`)."""
    h = squareplus(_apply_linear(params["node_embed"], node_x))
    e = squareplus(_apply_linear(params["edge_embed"], edge_x))
    if not params["layers"]:
        return h, e + _apply_linear(params["w_readout"], jnp.concatenate([h[senders], h[receivers]], -1))
    for layer in params["layers"]:
        e_next = squareplus(_apply_mlp(layer["edge_mlp"], e + _apply_linear(layer["w_edge"], jnp.concatenate([h[senders], h[receivers]], -1))))
        messages = jax.ops.segment_sum(_apply_linear(layer["w_node"], e), receivers, num_segments=h.shape[0])
        h = squareplus(_apply_mlp(layer["node_mlp"], h + messages))
        e = e_next
    return h, e



# ---------------------------------------------------------------------------------
# init / apply
# ---------------------------------------------------------------------------------


def init(key, config: ModelConfig) -> dict:
    """Fresh parameters of `config`'s model (float64 under x64)."""
    k_types, d = len(config.vocabulary), config.dim
    w_dim = 1 if d == 2 else d
    latent, hidden, layers = config.latent, config.hidden, config.message_passing
    keys = jax.random.split(key, 3)
    if config.name == "lgnn":
        params = {
            "kinetic": _init_graph_net(keys[0], d, k_types + w_dim, latent, hidden, layers),
            "potential": _init_graph_net(keys[1], d, k_types + d, latent, hidden, layers),
        }
        params["kinetic"]["readout"] = _mlp(jax.random.fold_in(keys[0], 1), (latent, hidden, 1))
        params["potential"]["readout"] = _mlp(jax.random.fold_in(keys[1], 1), (latent, hidden, 1))
    elif config.name in ("gns", "lgn"):
        params = {"net": _init_graph_net(keys[0], 2 * d, k_types + d + w_dim, latent, hidden, layers)}
        out = (latent, hidden, d) if config.name == "gns" else (2 * latent, hidden, 1)
        params["readout"] = _mlp(keys[1], out)
    else:
        n_in = 2 * config.n_nodes * d
        params = {"mlp": _mlp(keys[0], (n_in, hidden, hidden, 1))}
    if config.drag and config.name in LAGRANGIAN_MODELS:
        params["drag"] = jnp.zeros(k_types)
    return params


def lgnn_lagrangian_fn(scene: Scene, vocabulary, edge_energies: Callable) -> physics.LagrangianFn:
    """LGNN's read-out as a Lagrangian: `edge_energies(graph) -> (T, V)`, each (2E,) one
    value per directed edge, is averaged over each link's two orientations and summed:
    `L = sum_links (T - V)`. The learned model plugs its networks in here; the tests plug
    in the exact per-link energies to show the pipeline is the physics pipeline."""

    def lagrangian(q, qd):
        kinetic, potential = edge_energies(graph_from_state(scene, q, qd, vocabulary))
        return 0.5 * jnp.sum(kinetic - potential)

    return lagrangian


def _lgnn_edge_energies(params: dict):
    def energies(graph):
        nodes, edges = graph.nodes, graph.edges
        out = []
        for net, node_x, edge_x in (
            ("kinetic", nodes["qd"], jnp.concatenate([edges["type"], edges["w"]], -1)),
            ("potential", nodes["q"], jnp.concatenate([edges["type"], edges["dq"]], -1)),
        ):
            _, z = _apply_graph_net(params[net], node_x, edge_x, graph.senders, graph.receivers)
            out.append(_apply_mlp(params[net]["readout"], z)[:, 0])
        return tuple(out)

    return energies


def _graph_net_outputs(config: ModelConfig, params: dict, graph):
    nodes, edges = graph.nodes, graph.edges
    node_x = jnp.concatenate([nodes["q"], nodes["qd"]], -1)
    edge_x = jnp.concatenate([edges["type"], edges["dq"], edges["w"]], -1)
    return _apply_graph_net(params["net"], node_x, edge_x, graph.senders, graph.receivers)


def apply(config: ModelConfig, params: dict, graph):
    """The model's output on one graph: LGNN `(T, V)` per directed edge, LGN the global
    Lagrangian (), GNS node accelerations (N, D). CLNN has no graph: use `lagrangian_fn`."""
    if config.name == "lgnn":
        return _lgnn_edge_energies(params)(graph)
    h, e = _graph_net_outputs(config, params, graph)
    if config.name == "gns":
        return _apply_mlp(params["readout"], h)
    pooled = jnp.concatenate([jnp.sum(h, 0), jnp.sum(e, 0)])
    return _apply_mlp(params["readout"], pooled)[0]


def lagrangian_fn(config: ModelConfig, params: dict, scene: Scene) -> physics.LagrangianFn:
    """The learned `L(q, qd)` of a Lagrangian model on `scene`."""
    check_compatible(config, scene)
    if config.name == "lgnn":
        return lgnn_lagrangian_fn(scene, config.vocabulary, _lgnn_edge_energies(params))
    if config.name == "lgn":
        return lambda q, qd: apply(config, params, graph_from_state(scene, q, qd, config.vocabulary))
    if config.name == "clnn":
        return lambda q, qd: _apply_mlp(params["mlp"], jnp.concatenate([q.reshape(-1), qd.reshape(-1)]))[0]
    raise ConfigError(f"model {config.name} has no Lagrangian")


def _learned_drag_fn(config: ModelConfig, params: dict, scene: Scene):
    if "drag" not in params:
        return None
    return physics.drag_force_fn(scene, params["drag"][edge_type_indices(scene, config.vocabulary)])


def acceleration_fn(config: ModelConfig, params: dict, scene: Scene) -> physics.AccelerationFn:
    """`accel(q, qd) -> qdd` (N, D) of the model on `scene` (any size for graph models)."""
    check_compatible(config, scene)
    if config.name == "gns":
        free = np.ones((scene.n_nodes, 1))
        free[list(scene.pinned)] = 0.0

        def accel(q, qd):
            return apply(config, params, graph_from_state(scene, q, qd, config.vocabulary)) * free

        return accel
    # LGNN without message passing sums per-link energies of each link's own two nodes,
    # so its mass matrix couples only linked nodes: the solve can use that structure.
    local_mass = config.name == "lgnn" and config.message_passing == 0
    return physics.acceleration_fn(scene, lagrangian_fn(config, params, scene), _learned_drag_fn(config, params, scene), local_mass=local_mass)


def mass_matrix_fn(config: ModelConfig, params: dict, scene: Scene):
    """`M(q, qd) = d2L/dqd2` (N*D, N*D) of a Lagrangian model: the paper's learned mass matrix."""
    if config.name not in LAGRANGIAN_MODELS:
        raise ConfigError(f"model {config.name} predicts accelerations directly and has no mass matrix")
    return physics.mass_matrix_fn(lagrangian_fn(config, params, scene))


def rollout(config: ModelConfig, params: dict, scene: Scene, simulation=None, state=None, *, progress: bool = False):
    """The model's predicted `Trajectory` of `scene` from `state` (default: the scene's
    own), through the ground truth's integrators (`simulate.simulate`); its `energy` is
    the scene's true Hamiltonian of the predicted states. A prediction that becomes
    non-finite or explodes stops with `SimulationError` naming the time."""
    from lgnn.engines.lagrangian import SimulationConfig, simulate

    check_compatible(config, scene)
    trajectory = simulate(
        scene,
        simulation or SimulationConfig(),
        state,
        accel_factory=lambda s: acceleration_fn(config, params, s),
        progress=progress,
        hint=f"the {config.name} model's predicted dynamics diverge (its rollout stops there)",
    )
    return dataclasses.replace(trajectory, metadata={**trajectory.metadata, "model": config.to_dict()})
