"""Learned dynamics: LGNN and the baselines GNS, LGN, CLNN, the strong GNS, CGNODE and CHGN, in a registry of models.

A model is a `ModelConfig` (its registered name, architecture, the edge-type vocabulary
and, for CLNN, the system size; stored in checkpoints) and a params pytree (nested
dicts of arrays):

    params = init(key, config)
    accel = acceleration_fn(config, params, scene)      # accel(q, qd) -> qdd, (N, D)

Each name maps to a `ModelSpec` (`register`, `get_spec`, `model_names`): its init, its
output (a Lagrangian or accelerations), its default sizes, whether it is tied to one
system size, the training-set statistics it normalises by and its training recipe
(weight decay, input noise). Statistics are constants in the params pytree
(`params[STATISTICS]`): `init` makes placeholders, training fills them in once from
its training states (`training_statistics`, `with_statistics`) and steps only the
rest (`split_statistics`), checkpoints keep them like any leaf, so inference needs
nothing else. Adding a model is one `register(ModelSpec(...))`; nothing else compares
names. Every Lagrangian model (LGNN, LGN, CLNN) goes through `physics.acceleration_fn`,
the very same constrained Euler-Lagrange solve as the ground truth; GNS predicts node
accelerations directly (pinned nodes, a known boundary condition, get zero). Rollouts
(`rollout`) use the ground truth's engine and integrators with the params as an
argument of the compiled run: `simulate(scene, config, state,
accel_factory=AccelerationFactory(model), params=params)`, compiled once per scene,
settings and model config.

Architectures (paper section 3 and appendix):
- LGNN: two graph networks, for T (node velocities; edge type one-hot and `w = dq x
  dqd`) and V (node positions; edge type and `dq`). Embeddings `h = squareplus(Linear
  (features))` of size 5, MLPs with one hidden layer of 10 units, squareplus, `L`
  message-passing layers (paper Eqs.), per-edge energy `MLP(z_ij)` summed over links,
  `L = T - V`. Three registered variants share this code:
  - `lgnn` (`message_passing = 0`, this suite's per-edge variant; neither the paper's
    equations nor the authors' notebook): the read-out sees `z_ij = h_ij + W (h_i ||
    h_j)`, the edge-update input of the paper's first layer without its MLP, so a
    link's energy depends on its own features and its two end nodes (the paper's
    equations with L = 0 would read `h_ij` alone, which cannot express gravity `m g
    y_cm` nor translational kinetic energy);
  - `lgnn-mp1`, `lgnn-mp2`: the paper's equations with L = 1 and 2 layers.
  Per-link energies average the link's two orientations (`graphs` module). Drag scenes
  add a learned per-link drag coefficient (one per edge type): force `-c v_cm`, split
  between the two nodes.
- `lgnn-notebook`: the authors' notebook variant (issue 13): no message passing; each
  link's centre-of-mass velocity `v_cm`, angular feature `w = dq x dqd` (`l^2 omega`)
  and centre of mass `r_cm`, each with the edge type, go to three separate MLPs
  (hidden 10): `T_link = |MLP_v(v_cm)|^2 + |MLP_w(w)|^2`, `V_link = MLP_r(r_cm)`. The
  MLPs for T output a vector of `latent` (5) entries and T is its squared norm (a
  scalar output squared has a rank-1 mass matrix, which cannot be `m I` in 2D); they
  start with T strictly convex in the velocities (`_positive_convex_start`).
- GNS: node (q, qd) and edge (type, dq, w) encoders to latent 8, the same message-passing
  layers with MLPs of 128 hidden units, a node decoder MLP to accelerations. No
  constraints.
- `gns-10-128` (`strong_gns`): the GNS-10-128 recipe (10 unshared message-passing
  steps with residuals, latent 128, LayerNorm, inputs normalised by training-set
  statistics, a node-type embedding, rod features).
- `cgnode` (`cgnode`): the strong GNS's network, its accelerations made to satisfy the
  link constraints at the acceleration level in the rods' mass metric (the engine's
  KKT solves).
- `chgn` (`chgn`): a Hamiltonian of node positions and momenta, its kinetic term from
  a learned positive per-rod mass and inertia (the ground truth's regular on-manifold
  node mass), its potential a graph network; the constrained Hamiltonian equations.
- LGN: the same graph network, read out as one global Lagrangian `MLP(sum_i h_i ||
  sum_ij h_ij)`.
- CLNN: MLP with 2 hidden layers of 128 on the concatenated `(q, qd)` of a fixed-size
  system; refuses a scene of another size.
- `chnn` (`chnn`): CHNN (Finzi et al. 2020), CLNN's Hamiltonian counterpart: a learned
  constant positive definite node mass and an MLP potential of the whole system's
  positions (fixed size), under the constrained Hamiltonian equations (CHGN's).
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import importlib.util
import os
import sys
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from lgnn import physics, records
from lgnn.engines.base import Engine, Integration, SimulationConfig, Trajectory
from lgnn.engines.lagrangian import simulate
from lgnn.engines.rollouts import batched_rollouts, timed_rollouts
from lgnn.errors import ConfigError
from lgnn.learn import cgnode, chgn, chnn, strong_gns
from lgnn.learn.graphs import LINK_FEATURES, edge_attributes, edge_type_indices, graph_from_state
from lgnn.scene import Scene, State


@dataclasses.dataclass(frozen=True)
class ModelSpec:
    """What the library needs to know about one model, registered under its name.

    A model outputs either a Lagrangian or accelerations, so exactly one of
    `lagrangian` and `acceleration` is given:
    - `lagrangian(config, params, scene) -> L(q, qd)`: the model's Lagrangian, which
      `acceleration_fn` sends through the constrained Euler-Lagrange solve (with a
      learned per-link drag when `config.drag`);
    - `acceleration(config, params, scene) -> accel(q, qd) -> qdd` (N, D): direct
      predictions (zero at pinned nodes).
    """

    # The name `ModelConfig.name` and checkpoints refer to it by.
    name: str
    # `init(key, config) -> params`, the model's own parameters (drag is added by `init`).
    init: Callable
    lagrangian: Callable | None = None
    acceleration: Callable | None = None
    # `apply(config, params, graph)`: the raw output on one graph (None: no graph).
    apply: Callable | None = None
    # Embedding size and MLP hidden units when the config leaves them unset (the
    # paper's appendix; hidden layers are fixed by `init`).
    latent: int = 0
    hidden: int = 0
    # Message-passing layers when the config leaves them unset.
    message_passing: int = 0
    # Tied to the training system's size (a fixed-length input): refuses other sizes.
    fixed_size: bool = False
    # `mass(config, params, scene) -> physics.MassStructure | None`: the structure of a
    # Lagrangian model's `d2L/dqd2` (graph-local of some reach, or a read-out of pooled
    # local features), so the Euler-Lagrange solve may assemble it from fewer products
    # (`physics.acceleration_fn`); None: none declared (the dense Hessian).
    mass: Callable | None = None
    # Whether its networks read `graphs.edge_attributes`, so `ModelConfig.link_features`
    # gives them each link's mass, inertia ratio and length (the transfer track).
    link_features: bool = False
    # `statistics(config, scene, q, qd, qdd) -> {name: array}`: constants the model
    # normalises by, computed once by training from its training states and targets
    # (each (S, N, D)) and kept in `params[STATISTICS]`, where `init` puts placeholders
    # of the same shapes (so a checkpoint restores them; `with_statistics`). None: none.
    statistics: Callable | None = None
    # The model's training recipe where it has one (`lgnn.learn.train`): AdamW's
    # decoupled weight decay (0: the paper's Adam), and the std of Gaussian noise added
    # to the training inputs' free-node velocities, as a fraction of the training
    # velocities' std per dimension (0: none).
    weight_decay: float = 0.0
    velocity_noise: float = 0.0

    def __post_init__(self):
        if (self.lagrangian is None) == (self.acceleration is None):
            raise ConfigError(f"model {self.name!r}: give exactly one of a Lagrangian and an acceleration")
        for name in ("weight_decay", "velocity_noise"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value < float("inf"):
                raise ConfigError(f"model {self.name!r}: {name.replace('_', ' ')} must be a finite number >= 0, got {value!r}")

    @property
    def is_lagrangian(self) -> bool:
        return self.lagrangian is not None


_REGISTRY: dict[str, ModelSpec] = {}


def register(spec: ModelSpec) -> ModelSpec:
    """Make `spec` available as `ModelConfig(spec.name)`. Registering the same spec
    again does nothing; another spec under a taken name is a `ConfigError` (compiled
    functions are cached per config, so a name must keep its meaning)."""
    known = _REGISTRY.get(spec.name)
    if known is not None and known is not spec:
        raise ConfigError(f"model {spec.name!r} is already registered")
    _REGISTRY[spec.name] = spec
    return spec


# Where the models defined outside lgnn came from (`load_spec`): name -> reference.
_SOURCES: dict[str, str] = {}


def load_spec(reference: str, base: str | os.PathLike | None = None) -> ModelSpec:
    """Import the `ModelSpec` at `module:attribute` (an importable module) or
    `path/to/file.py:attribute` (relative to `base`, default the working directory),
    register it, and return it: how a model defined outside lgnn enters training,
    the benchmark's grid and its tables. `ConfigError` (one line) if it cannot."""
    module_name, sep, attribute = reference.rpartition(":")
    if not sep or not module_name or not attribute:
        raise ConfigError(f"model reference {reference!r}: expected module:attribute or file.py:attribute")
    if module_name.endswith(".py"):
        path = (Path(base or ".") / module_name).resolve()
        if not path.is_file():
            raise ConfigError(f"model reference {reference!r}: no file {path}")
        module_name, reference = f"lgnn_user_model_{hashlib.sha256(str(path).encode()).hexdigest()[:12]}", f"{path}:{attribute}"
        if module_name not in sys.modules:
            loader = importlib.util.spec_from_file_location(module_name, path)
            module = importlib.util.module_from_spec(loader)
            sys.modules[module_name] = module
            try:
                loader.loader.exec_module(module)
            except Exception as err:
                del sys.modules[module_name]
                raise ConfigError(f"model reference {reference!r}: importing {path} failed ({type(err).__name__}: {err})") from None
    try:
        module = importlib.import_module(module_name)
    except Exception as err:
        raise ConfigError(f"model reference {reference!r}: cannot import {module_name!r} ({type(err).__name__}: {err})") from None
    spec = getattr(module, attribute, None)
    if not isinstance(spec, ModelSpec):
        raise ConfigError(f"model reference {reference!r}: {attribute!r} is not a lgnn.learn.models.ModelSpec")
    register(spec)
    _SOURCES[spec.name] = reference
    return spec


def model_source(name: str) -> str | None:
    """The `load_spec` reference of a model defined outside lgnn (None for the built-ins)."""
    return _SOURCES.get(name)


def get_spec(name: str) -> ModelSpec:
    """The registered spec of `name`; `ConfigError` (one line, the choices) if none."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ConfigError(f"unknown model {name!r} (choose from {', '.join(model_names())})") from None


def model_names() -> tuple[str, ...]:
    """Registered model names, built-ins first."""
    return tuple(_REGISTRY)


# Largest message-passing depth and layer width a model config may ask for: far beyond
# the paper's (L <= 2, widths 5-16), still seconds to initialise.
MAX_MESSAGE_PASSING = 64
MAX_WIDTH = 4096


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    # A registered model name (`model_names()`).
    name: str = "lgnn"
    # Message-passing layers L (None: the model's default, `ModelSpec.message_passing`).
    message_passing: int | None = None
    # Embedding size and MLP hidden units (None: the paper's, `ModelSpec.latent/hidden`).
    latent: int | None = None
    hidden: int | None = None
    # Edge-type vocabulary fixed at training time (graphs.edge_type_indices).
    vocabulary: tuple[str, ...] = ("link",)
    # Learn a per-link drag term (set when the training scene has drag).
    drag: bool = False
    # System size (nodes, dimension) of the training scene; CLNN is tied to it.
    n_nodes: int = 5
    dim: int = 2
    # Edges also carry each link's mass, inertia ratio and length (`graphs.link_attributes`):
    # a model trained on varied draws can then tell links apart (the paper's features
    # hold no mass). Only for models that read them (`ModelSpec.link_features`). In a
    # checkpoint's config only when set, so configs saved before it compare equal.
    link_features: bool = dataclasses.field(default=False, metadata=records.KEY_UNLESS_DEFAULT)

    def __post_init__(self):
        if not isinstance(self.name, str):
            raise ConfigError(f"model name must be a string, got {self.name!r}")
        spec = self.spec
        if self.message_passing is None:
            object.__setattr__(self, "message_passing", spec.message_passing)
        object.__setattr__(self, "latent", self.latent or spec.latent)
        object.__setattr__(self, "hidden", self.hidden or spec.hidden)
        if not isinstance(self.vocabulary, (list, tuple)) or not all(isinstance(v, str) for v in self.vocabulary):
            raise ConfigError(f"model vocabulary must be a list of link types, got {self.vocabulary!r}")
        object.__setattr__(self, "vocabulary", tuple(self.vocabulary))
        # The same bounds wherever a config comes from (a command, a config file, a
        # checkpoint's meta): a million layers would run for hours before failing. Widths
        # may be 0: a spec without a network (a cheating model) has none.
        for name, low, high in (("message_passing", 0, MAX_MESSAGE_PASSING), ("latent", 0, MAX_WIDTH), ("hidden", 0, MAX_WIDTH),
                                ("n_nodes", 2, None), ("dim", 2, 3)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < low or (high is not None and value > high):
                bounds = f"from {low} to {high}" if high is not None else f">= {low}"
                raise ConfigError(f"model {name.replace('_', '-')} must be a whole number {bounds}, got {value!r}")
        if not isinstance(self.drag, bool):
            raise ConfigError(f"model drag must be true or false, got {self.drag!r}")
        if not isinstance(self.link_features, bool):
            raise ConfigError(f"model link-features must be true or false, got {self.link_features!r}")
        if self.link_features and not spec.link_features:
            raise ConfigError(f"model {self.name} does not read link features")

    @property
    def spec(self) -> ModelSpec:
        return get_spec(self.name)

    @classmethod
    def for_scene(cls, name: str, scene: Scene, **overrides) -> "ModelConfig":
        """The config of a model trained on `scene` (its types, drag and size)."""
        settings = dict(vocabulary=tuple(sorted(set(scene.link_types))), drag=scene.drag > 0, n_nodes=scene.n_nodes, dim=scene.dim)
        return cls(name, **{**settings, **overrides})

    def to_dict(self) -> dict:
        """The config as checkpoints keep it (`records.settings_key`)."""
        return {**records.settings_key(self), "vocabulary": list(self.vocabulary)}

    @classmethod
    def from_dict(cls, data: dict) -> "ModelConfig":
        fields = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - fields)
        if unknown:
            raise ConfigError(f"model config: unknown field {unknown[0]!r}")
        return cls(**{**data, "vocabulary": data.get("vocabulary", ("link",))})  # a list: a tuple in __post_init__


def check_compatible(config: ModelConfig, scene: Scene) -> None:
    """Raise `ConfigError` if the model cannot run on `scene` (size, dimension, types)."""
    if scene.dim != config.dim:
        raise ConfigError(f"model {config.name} was trained in {config.dim}D, scene {scene.name!r} is {scene.dim}D")
    if config.spec.fixed_size and scene.n_nodes != config.n_nodes:
        raise ConfigError(
            f"{config.name} is tied to its training system size ({config.n_nodes} nodes); scene {scene.name!r} has {scene.n_nodes}"
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


def graph_net_reach(layers: int) -> tuple[int, int]:
    """How far `_apply_graph_net`'s outputs see: (r, s) such that a node's final
    embedding depends on nodes at most r links from it, and an edge's on nodes at most s
    links from either of its ends. A layer's edge update reads its own edge and its
    ends' node embeddings (s' = max(s, r)); its node update reads its own embedding and
    the incident edges' embeddings of the layer before (r' = max(r, s + 1))."""
    node, edge = 0, 0
    for _ in range(layers):
        node, edge = max(node, edge + 1), max(edge, node)
    return node, edge


def _edge_energy_reach(config: ModelConfig) -> int:
    """The mass matrix's reach of a sum of per-edge energies read from the graph
    network's final edge embeddings: two nodes are coupled when one edge's embedding
    sees both, at most 2 s + 1 links apart."""
    return 2 * graph_net_reach(config.message_passing)[1] + 1



# ---------------------------------------------------------------------------------
# The built-in models
# ---------------------------------------------------------------------------------


def _feature_sizes(config: ModelConfig) -> tuple[int, int, int]:
    """(edge attributes A: the K types and, with link features, the link's attributes
    (`graphs.edge_attributes`); dimension D; size W of `w = dq x dqd`: 1 in 2D, D in 3D)."""
    d = config.dim
    return len(config.vocabulary) + (LINK_FEATURES if config.link_features else 0), d, 1 if d == 2 else d


def _init_lgnn(key, config: ModelConfig) -> dict:
    k_types, d, w_dim = _feature_sizes(config)
    latent, hidden, layers = config.latent, config.hidden, config.message_passing
    keys = jax.random.split(key, 3)
    params = {
        "kinetic": _init_graph_net(keys[0], d, k_types + w_dim, latent, hidden, layers),
        "potential": _init_graph_net(keys[1], d, k_types + d, latent, hidden, layers),
    }
    params["kinetic"]["readout"] = _mlp(jax.random.fold_in(keys[0], 1), (latent, hidden, 1))
    params["potential"]["readout"] = _mlp(jax.random.fold_in(keys[1], 1), (latent, hidden, 1))
    params["kinetic"] = _convex_start(params["kinetic"])
    return params


def _convex_start(net: dict) -> dict:
    """The kinetic network with every weight after the embeddings made non-negative.

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
    (`_nonnegative_weights` after their first affine map of `(q, qd)`): their `L` is
    then convex in `(q, qd)` jointly, so in the velocities too."""

    embeddings = {k: net[k] for k in ("node_embed", "edge_embed")}
    rest = {k: v for k, v in net.items() if k not in embeddings}
    return {**embeddings, **_nonnegative_weights(rest)}


def _nonnegative_weights(params):
    """`params` with every weight matrix (leaf `w`) replaced by its absolute value."""
    return jax.tree_util.tree_map_with_path(lambda path, leaf: jnp.abs(leaf) if path[-1].key == "w" else leaf, params)


def _lgnn_edge_energies(params: dict):
    def energies(graph):
        nodes, edges = graph.nodes, graph.edges
        out = []
        for net, node_x, edge_x in (
            ("kinetic", nodes["qd"], jnp.concatenate([edge_attributes(graph), edges["w"]], -1)),
            ("potential", nodes["q"], jnp.concatenate([edge_attributes(graph), edges["dq"]], -1)),
        ):
            _, z = _apply_graph_net(params[net], node_x, edge_x, graph.senders, graph.receivers)
            out.append(_apply_mlp(params[net]["readout"], z)[:, 0])
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


def _init_graph_model(key, config: ModelConfig, readout: tuple[int, ...]) -> dict:
    """GNS and LGN: one graph network on node `(q, qd)` and edge `(type, dq, w)`."""
    k_types, d, w_dim = _feature_sizes(config)
    keys = jax.random.split(key, 3)
    return {
        "net": _init_graph_net(keys[0], 2 * d, k_types + d + w_dim, config.latent, config.hidden, config.message_passing),
        "readout": _mlp(keys[1], readout),
    }


def _graph_net_outputs(params: dict, graph):
    nodes, edges = graph.nodes, graph.edges
    node_x = jnp.concatenate([nodes["q"], nodes["qd"]], -1)
    edge_x = jnp.concatenate([edge_attributes(graph), edges["dq"], edges["w"]], -1)
    return _apply_graph_net(params["net"], node_x, edge_x, graph.senders, graph.receivers)


def _init_lgn(key, config: ModelConfig) -> dict:
    """LGN's graph network and read-out, started with `L` convex in the velocities
    (`_convex_start`): from the paper's random start its first epochs on chain4 ran at
    training MSE 1e5-1e6 (targets O(10)) and, at batch 100, settled on a plateau worse
    than the untrained model's (issue 13)."""
    params = _init_graph_model(key, config, (2 * config.latent, config.hidden, 1))
    return {"net": _convex_start(params["net"]), "readout": _nonnegative_weights(params["readout"])}


def _apply_gns(config: ModelConfig, params: dict, graph):
    h, _ = _graph_net_outputs(params, graph)
    return _apply_mlp(params["readout"], h)


def _gns_acceleration(config: ModelConfig, params: dict, scene: Scene) -> physics.AccelerationFn:
    free = np.ones((scene.n_nodes, 1))
    free[list(scene.pinned)] = 0.0

    def accel(q, qd):
        return _apply_gns(config, params, graph_from_state(scene, q, qd, config.vocabulary, config.link_features)) * free

    return accel


def _lgn_pooled(params: dict, graph):
    """LGN's read-out input: the summed node and summed edge embeddings (2 latent,)."""
    h, e = _graph_net_outputs(params, graph)
    return jnp.concatenate([jnp.sum(h, 0), jnp.sum(e, 0)])


def _apply_lgn(config: ModelConfig, params: dict, graph):
    return _apply_mlp(params["readout"], _lgn_pooled(params, graph))[0]


def _lgn_lagrangian(config: ModelConfig, params: dict, scene: Scene) -> physics.LagrangianFn:
    return lambda q, qd: _apply_lgn(config, params, graph_from_state(scene, q, qd, config.vocabulary, config.link_features))


def _lgn_terms(params: dict, graph):
    """LGN's read-out input as a sum of local terms (T, 2 latent): each node's embedding
    in the first half, each edge's in the second (their sum is `_lgn_pooled`)."""
    h, e = _graph_net_outputs(params, graph)
    return jnp.concatenate([jnp.pad(h, ((0, 0), (0, e.shape[1]))), jnp.pad(e, ((0, 0), (h.shape[1], 0)))])


def graph_net_supports(scene: Scene, layers: int) -> tuple[tuple[int, ...], ...]:
    """The nodes each of `_apply_graph_net`'s outputs depends on, in its output order:
    each node's embedding (nodes at most r links away), then each directed edge's of
    `graph_from_state` (at most s links from either end; `graph_net_reach`)."""
    node_reach, edge_reach = graph_net_reach(layers)
    nodes = physics.neighbourhoods(scene, node_reach)
    near_edge = physics.neighbourhoods(scene, edge_reach)
    i, j = scene.edge_index.T
    edges = [near_edge[a] | near_edge[b] for a, b in zip(np.concatenate([i, j]), np.concatenate([j, i]))]
    return tuple(tuple(sorted(support)) for support in nodes + edges)


def _lgn_mass(config: ModelConfig, params: dict, scene: Scene) -> physics.MassStructure:
    """LGN's `L` is a read-out of summed embeddings: its mass matrix is low rank (the
    read-out's 2 latent inputs) plus local. A node's embedding couples nodes up to 2 r
    links apart, an edge's up to 2 s + 1 (`graph_net_reach`)."""
    node, edge = graph_net_reach(config.message_passing)
    return physics.MassStructure(
        max(2 * node, 2 * edge + 1),
        terms=lambda q, qd: _lgn_terms(params, graph_from_state(scene, q, qd, config.vocabulary, config.link_features)),
        supports=graph_net_supports(scene, config.message_passing),
        readout=lambda pooled: _apply_mlp(params["readout"], pooled)[0],
    )


def _init_clnn(key, config: ModelConfig) -> dict:
    """CLNN's MLP, started with `L` convex in the velocities (as LGN, `_init_lgn`): every
    weight after the first layer non-negative."""
    keys = jax.random.split(key, 3)
    first, *rest = _mlp(keys[0], (2 * config.n_nodes * config.dim, config.hidden, config.hidden, 1))
    return {"mlp": [first, *_nonnegative_weights(rest)]}


def _clnn_lagrangian(config: ModelConfig, params: dict, scene: Scene) -> physics.LagrangianFn:
    return lambda q, qd: _apply_mlp(params["mlp"], jnp.concatenate([q.reshape(-1), qd.reshape(-1)]))[0]


def _init_lgnn_notebook(key, config: ModelConfig) -> dict:
    """The notebook variant's three MLPs, the two of `T` started convex and positive
    (`_positive_convex_start`)."""
    k_types, d, w_dim = _feature_sizes(config)
    keys = jax.random.split(key, 3)
    return {
        "v_cm": _positive_convex_start(_mlp(keys[0], (k_types + d, config.hidden, config.latent))),
        "w": _positive_convex_start(_mlp(keys[1], (k_types + w_dim, config.hidden, config.latent))),
        "r_cm": _mlp(keys[2], (k_types + d, config.hidden, 1)),
    }


def _positive_convex_start(mlp: list) -> list:
    """A one-hidden-layer MLP `f(x) = W2 squareplus(W1 x + b1) + b2` whose squared norm
    `|f(x)|^2` is strictly convex in `x`: `W2` non-negative, `b2` zero (as `_linear` makes it).

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
    return [first, *_nonnegative_weights(rest)]


def _lgnn_notebook_edge_energies(params: dict):
    def energies(graph):
        s, r, kind = graph.senders, graph.receivers, edge_attributes(graph)
        v_cm = 0.5 * (graph.nodes["qd"][s] + graph.nodes["qd"][r])
        r_cm = 0.5 * (graph.nodes["q"][s] + graph.nodes["q"][r])
        kinetic = sum(jnp.sum(_apply_mlp(params[k], jnp.concatenate([kind, x], -1)) ** 2, -1) for k, x in (("v_cm", v_cm), ("w", graph.edges["w"])))
        return kinetic, _apply_mlp(params["r_cm"], jnp.concatenate([kind, r_cm], -1))[:, 0]

    return energies


def _lgnn_spec(name: str, message_passing: int) -> ModelSpec:
    return ModelSpec(
        name, _init_lgnn, apply=lambda config, params, graph: _lgnn_edge_energies(params)(graph),
        lagrangian=lambda config, params, scene: lgnn_lagrangian_fn(scene, config.vocabulary, _lgnn_edge_energies(params), config.link_features),
        latent=5, hidden=10, message_passing=message_passing, link_features=True,
        # A link's energy sees its own two nodes only without message passing and after
        # one layer, nodes further away after more (`_edge_energy_reach`).
        mass=lambda config, params, scene: physics.MassStructure(_edge_energy_reach(config)),
    )


# Sizes are the paper appendix's; message-passing layers when not given: LGNN's
# per-edge variant (the true per-link energies need nothing more); two layers let GNS
# and LGN nodes see their neighbours' neighbours (the paper does not give this number).
register(_lgnn_spec("lgnn", 0))
register(_lgnn_spec("lgnn-mp1", 1))
register(_lgnn_spec("lgnn-mp2", 2))
register(ModelSpec(
    "lgnn-notebook", _init_lgnn_notebook, apply=lambda config, params, graph: _lgnn_notebook_edge_energies(params)(graph),
    lagrangian=lambda config, params, scene: lgnn_lagrangian_fn(scene, config.vocabulary, _lgnn_notebook_edge_energies(params), config.link_features),
    latent=5, hidden=10, mass=lambda config, params, scene: physics.LOCAL, link_features=True,
))
register(ModelSpec(
    "gns", lambda key, config: _init_graph_model(key, config, (config.latent, config.hidden, config.dim)),
    apply=_apply_gns, acceleration=_gns_acceleration, latent=8, hidden=128, message_passing=2, link_features=True,
))
register(ModelSpec(
    "lgn", _init_lgn,
    apply=_apply_lgn, lagrangian=_lgn_lagrangian, mass=_lgn_mass, latent=8, hidden=128, message_passing=2, link_features=True,
))
register(ModelSpec("clnn", _init_clnn, lagrangian=_clnn_lagrangian, hidden=128, fixed_size=True))
# The strong GNS (`strong_gns`): the GNS-10-128 recipe's sizes, LagrangeBench's AdamW
# weight decay (1e-8) and noise of 5e-4 of the normalised velocities (the recipe's
# 3e-4..7e-4).
register(ModelSpec(
    "gns-10-128", strong_gns.init, acceleration=strong_gns.acceleration, statistics=strong_gns.statistics,
    latent=128, hidden=128, message_passing=10, weight_decay=1e-8, velocity_noise=5e-4,
))
# The constrained graph neural ODE (`cgnode`): the strong GNS's network and recipe,
# its accelerations made to satisfy the constraints in the rods' mass metric.
register(ModelSpec(
    "cgnode", cgnode.init, acceleration=cgnode.acceleration, statistics=cgnode.statistics,
    latent=128, hidden=128, message_passing=10, weight_decay=1e-8, velocity_noise=5e-4,
))
# The constrained Hamiltonian graph network (`chgn`): LGNN's sizes (the paper's appendix)
# and recipe for the energy model it parallels; an acceleration model to the library,
# since its dynamics are the constrained Hamiltonian equations, not the Euler-Lagrange solve.
register(ModelSpec(
    "chgn", chgn.init, acceleration=chgn.acceleration, statistics=chgn.statistics,
    latent=5, hidden=10, message_passing=0,
))
# CHNN (`chnn`): CLNN's potential width (the paper's 128) for the MLP it parallels.
register(ModelSpec(
    "chnn", chnn.init, acceleration=chnn.acceleration, statistics=chnn.statistics,
    hidden=128, fixed_size=True,
))


# ---------------------------------------------------------------------------------
# Any registered model
# ---------------------------------------------------------------------------------


# The params key of a model's training-set statistics (`ModelSpec.statistics`):
# constants, never trained.
STATISTICS = "statistics"


def training_statistics(config: ModelConfig, scene: Scene, q, qd, qdd) -> dict | None:
    """The statistics `config`'s model normalises by, of training states `q, qd` and
    targets `qdd` (each (S, N, D)) of `scene` (None for a model without any)."""
    spec = config.spec
    if spec.statistics is None:
        return None
    return {name: jnp.asarray(value) for name, value in spec.statistics(config, scene, q, qd, qdd).items()}


def with_statistics(params: dict, statistics: dict | None) -> dict:
    """`params` with `statistics` (from `training_statistics`) in place of its own:
    the placeholders `init` made, of the same names and shapes (`ConfigError` if not)."""
    if statistics is None:
        return params
    placeholder = params.get(STATISTICS) if isinstance(params, dict) else None
    if placeholder is None or set(placeholder) != set(statistics) or any(np.shape(placeholder[k]) != np.shape(statistics[k]) for k in statistics):
        raise ConfigError(f"the model's init must hold placeholders of its statistics ({', '.join(sorted(statistics))}) under params[{STATISTICS!r}]")
    return {**params, STATISTICS: {k: jnp.asarray(v, jnp.asarray(placeholder[k]).dtype) for k, v in statistics.items()}}


def split_statistics(params) -> tuple:
    """`(trainable, statistics)`: what an optimiser steps, and the constants (None if none)."""
    if isinstance(params, dict) and STATISTICS in params:
        return {k: v for k, v in params.items() if k != STATISTICS}, params[STATISTICS]
    return params, None


def join_statistics(trainable, statistics):
    """The params `split_statistics` split."""
    return trainable if statistics is None else {**trainable, STATISTICS: statistics}


def init(key, config: ModelConfig) -> dict:
    """Fresh parameters of `config`'s model (float64 under x64); statistics, if the
    model has any, at `init`'s placeholders until `with_statistics`."""
    params = config.spec.init(key, config)
    if config.drag and config.spec.is_lagrangian:
        params["drag"] = jnp.zeros(len(config.vocabulary))
    return params


def apply(config: ModelConfig, params: dict, graph):
    """The model's output on one graph: LGNN `(T, V)` per directed edge, LGN the global
    Lagrangian (), GNS node accelerations (N, D). CLNN has no graph: use `lagrangian_fn`."""
    if config.spec.apply is None:
        raise ConfigError(f"model {config.name} does not work on graphs")
    return config.spec.apply(config, params, graph)


def lagrangian_fn(config: ModelConfig, params: dict, scene: Scene) -> physics.LagrangianFn:
    """The learned `L(q, qd)` of a Lagrangian model on `scene`."""
    check_compatible(config, scene)
    if not config.spec.is_lagrangian:
        raise ConfigError(f"model {config.name} has no Lagrangian")
    return config.spec.lagrangian(config, params, scene)


def _learned_drag_fn(config: ModelConfig, params: dict, scene: Scene):
    if "drag" not in params:
        return None
    return physics.drag_force_fn(scene, params["drag"][edge_type_indices(scene, config.vocabulary)])


def acceleration_fn(config: ModelConfig, params: dict, scene: Scene) -> physics.AccelerationFn:
    """`accel(q, qd) -> qdd` (N, D) of the model on `scene` (any size for graph models)."""
    check_compatible(config, scene)
    params = _constant_statistics(params)
    if not config.spec.is_lagrangian:
        return config.spec.acceleration(config, params, scene)
    lagrangian, drag, mass = _lagrangian_parts(config, params, scene)
    return physics.acceleration_fn(scene, lagrangian, drag, mass=mass)


def trainable_acceleration_fn(config: ModelConfig, scene: Scene) -> Callable:
    """`accel(params, q, qd) -> qdd` (N, D): `acceleration_fn(config, params, scene)(q,
    qd)` with the parameters an argument, what training differentiates. A
    Lagrangian model's derivative by them comes from the adjoint of the constrained
    equations (`physics.parametrised_acceleration_fn`): the same gradient, fewer
    operations."""
    check_compatible(config, scene)
    if not config.spec.is_lagrangian:
        return lambda params, q, qd: acceleration_fn(config, params, scene)(q, qd)
    accel = physics.parametrised_acceleration_fn(scene, lambda params: _lagrangian_parts(config, params, scene))
    return lambda params, q, qd: accel(_constant_statistics(params), q, qd)


def _constant_statistics(params):
    """`params` with its statistics constants: no gradient reaches them, whoever differentiates."""
    trainable, statistics = split_statistics(params)
    return join_statistics(trainable, None if statistics is None else jax.lax.stop_gradient(statistics))


def _lagrangian_parts(config: ModelConfig, params: dict, scene: Scene) -> tuple:
    """`(lagrangian, drag force or None, mass structure or None)` of a Lagrangian model."""
    mass = None if config.spec.mass is None else config.spec.mass(config, params, scene)
    return lagrangian_fn(config, params, scene), _learned_drag_fn(config, params, scene), mass


def mass_matrix_fn(config: ModelConfig, params: dict, scene: Scene):
    """`M(q, qd) = d2L/dqd2` (N*D, N*D) of a Lagrangian model: the paper's learned mass matrix."""
    if not config.spec.is_lagrangian:
        raise ConfigError(f"model {config.name} predicts accelerations directly and has no mass matrix")
    return physics.mass_matrix_fn(lagrangian_fn(config, params, scene))


@dataclasses.dataclass(frozen=True)
class AccelerationFactory:
    """`factory(scene, params) -> accel`: `acceleration_fn` of one model config as a
    value equal for equal configs, so a rollout (`simulate(..., accel_factory=factory,
    params=params)`) compiles once per scene, simulation settings and model config and
    takes the params as an argument."""

    config: ModelConfig

    def __call__(self, scene: Scene, params) -> physics.AccelerationFn:
        return acceleration_fn(self.config, params, scene)


def rollout(config: ModelConfig, params: dict, scene: Scene, simulation: SimulationConfig | None = None, state=None, *,
            integration: Integration = Integration(), progress: bool = False) -> Trajectory:
    """The model's predicted `Trajectory` of `scene` from `state` (default: the scene's
    own), through the ground truth's integrators (`engines.lagrangian.simulate`, by
    `integration`); its
    `energy` is the scene's true Hamiltonian of the predicted states. A prediction that
    becomes non-finite or explodes stops with `SimulationError` naming the time."""
    check_compatible(config, scene)
    trajectory = simulate(
        scene,
        simulation or SimulationConfig(),
        state,
        integration=integration,
        accel_factory=AccelerationFactory(config),
        params=params,
        progress=progress,
        hint=f"the {config.name} model's predicted dynamics diverge (its rollout stops there)",
    )
    return dataclasses.replace(trajectory, metadata={**trajectory.metadata, "model": config.to_dict()})


@dataclasses.dataclass(frozen=True, eq=False)
class ModelEngine(Engine):
    """A learned model as an `lgnn.engines.Engine`: the same `rollout(scene, config,
    states) -> Trajectory` and `timed_rollout` as the ground-truth engines, through the
    one rollout path (`lgnn.engines.rollouts.batched_rollouts`: the batch vmapped in one
    program, the params an argument of it), so cross-checks and tools treat a model like
    any other engine, integrated by `integration` (RK4 with projection, as the ground
    truth, by default). Its trajectories' `energy` is the scene's true Hamiltonian of
    the predicted states; `rollout` stops at divergence like every engine."""

    config: ModelConfig
    params: dict
    dtype: str = "float64"
    progress: bool = False
    integration: Integration = Integration()

    @property
    def name(self) -> str:
        return self.config.name

    def rollout(self, scene: Scene, config: SimulationConfig, states: State) -> Trajectory:
        """Predicted trajectories from initial states (B, N, D): q, qd (B, F+1, N, D), energy (B, F+1)."""
        check_compatible(self.config, scene)
        runs = batched_rollouts(scene, config, AccelerationFactory(self.config), states, self.params, integration=self.integration,
                                dtype=self.dtype, stop_at_divergence=True, progress=self.progress, label=f"{self.config.name} on {scene.name}",
                                hint=f"the {self.config.name} model's predicted dynamics diverge (its rollout stops there)")
        return runs.trajectory(scene, config, self.integration, {"model": self.config.to_dict()})

    def timed_rollout(self, scene: Scene, config: SimulationConfig, states: State) -> tuple[float, float, np.ndarray]:
        """`(compile_s, run_s, q (B, F+1, N, D))` of the batch (`rollouts.timed_rollouts`)."""
        check_compatible(self.config, scene)
        compile_s, (run_s,), runs = timed_rollouts(scene, config, AccelerationFactory(self.config), states, self.params,
                                                   integration=self.integration, dtype=self.dtype)
        return compile_s, run_s, runs.q
