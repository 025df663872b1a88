"""The constrained Hamiltonian graph network (`chgn`): a Hamiltonian learned by graph
networks in Cartesian node coordinates, its dynamics the constrained Hamiltonian
equations with the scene's known link constraints.

The Hamiltonian, in node positions `q` and momenta `p` (N, D):

    H(q, p) = 1/2 p_f^T M_f^-1 p_f + V(q),

- kinetic term: `M` is assembled from a learned per-rod mass and inertia form, each
  rod adding `m/4 + I/l^2` to its two nodes' diagonal blocks and `m/4 - I/l^2` to
  their coupling (`cgnode.node_mass`), times the D x D identity. `(m, I)` per rod are
  `softplus` outputs (strictly positive) of an edge network on the rod's features
  (link type one-hot, length, mass, inertia, each over the training scene's scale):
  a rod's inertia is its own, so no message passing. Each rod's block is positive
  definite, so `M` is positive definite on the free coordinates `f` (every free node
  on a rod) and `M_f^-1 p_f` is a Cholesky solve. Why this form: the rods' exact mass
  matrix in node coordinates, `d2T/dqd2`, is singular (stretching a rod costs no
  kinetic energy), so `p = M qd` could not be inverted; the ground truth meets the
  same singularity by its on-manifold equivalent, the constant node mass of
  `physics.constant_mass_lagrangian_fn` (equal to the exact kinetic energy wherever
  link lengths are kept, regular off them), and this is that formulation with `m`
  and `I` learned. The form does not depend on `q`, as the exact on-manifold one does
  not, so `p = M qd` and `qdd = M^-1 pdot`.
- potential term `V(q)`: a graph network on node positions over the training length
  scale and a pinned/free one-hot (absolute positions: gravity needs them, as LGNN's
  potential), edges with the relative displacement, its norm and the rod features;
  encoders, `L` message-passing steps with residuals, and a read-out per directed
  edge `MLP(e_ij || h_i || h_j)` summed over both orientations and halved, times the
  training set's energy scale. Its MLPs have one hidden layer (LGNN's) and softplus
  activations (smooth: the dynamics need `dV/dq`, training its derivative again).

The dynamics, over the free coordinates, with constraint rows `A(q)` (the kept
link-length rows, `physics.Constraints`) and multipliers `lam`:

    qd = dH/dp = M^-1 p,    pdot = -dH/dq + F - A^T lam,    A qdd + Adot qd = 0,

(the velocity constraint `A qd = 0` differentiated in time), where `F` is a learned
linear drag (one coefficient per link type, `physics.drag_force_fn`) on drag scenes and
nothing otherwise. With `M` constant, `qdd = M^-1 pdot`, so the accelerations solve
the KKT system `[[M, A^T], [A, 0]] [qdd; lam] = [-dH/dq + F; -Adot qd]`, solved by
the engine's solvers (`cgnode.constrained_solve_fn`: `solvers.solve_kkt`, or
`solvers.chain_kkt_solve` on long pinned chains). `dH/dq` is the autodiff gradient of
the whole learned `H` at fixed `p`. The model answers the common interface in the
state `(q, qd)`: the momentum is the Legendre map `p = M qd`, so rollouts use the
ground truth's integrators and per-step projection like every model's, and the learned
Hamiltonian `H(q, M qd)` (`energy_fn`) is conserved by the exact flow of a conservative
scene (constraint forces do no work on velocities with `A qd = 0`).

Contract (pure functions; `config` is a `ModelConfig`, read for `latent`, `hidden`,
`message_passing`, `vocabulary`, `dim` and `drag`):
- `statistics(config, scene, q, qd, qdd) -> {name: ()}`: length, mass, inertia and
  energy scales of the training set; `init` holds placeholders (ones);
- `init(key, config) -> params` (with `params["drag"]` (K,) zeros on drag scenes);
- `acceleration(config, params, scene) -> accel(q, qd) -> qdd` (N, D), zero at pins;
- `rod_form(config, params, scene) -> (masses, inertias)` (E,) the learned kinetic form;
- `hamiltonian_fn(config, params, scene) -> H(q, p)`, `momentum_fn(...) -> p(q, qd)`,
  `energy_fn(...) -> H(q, p(q, qd))`;
- the formulation apart from the networks: `separable_hamiltonian_fn(scene, mass_fn,
  potential) -> H(q, p)` and `constrained_hamiltonian_fn(scene, mass_fn, hamiltonian,
  force_fn) -> accel`, which with the scene's own rods, gravity and drag give the
  ground truth (tested).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from lgnn import physics
from lgnn.learn.graphs import edge_type_indices, graph_from_state
from lgnn.learn.models import kit
from lgnn.learn.models.cgnode import constrained_solve_fn, node_mass
from lgnn.learn.models.registry import ModelSpec, register
from lgnn.scene import Scene

# Node types of the potential's one-hot: free, pinned.
NODE_TYPES = 2
# softplus(SOFTPLUS_ONE) = 1: a zero network output gives a rod the training scene's
# mean mass and inertia.
SOFTPLUS_ONE = float(np.log(np.e - 1.0))


def statistics(config, scene: Scene, q, qd, qdd) -> dict:
    """Scales of the training states and targets (each (S, N, D)) of `scene`: the RMS
    link length, the mean mass per link (the point masses' counted: a chain of bobs on
    massless rods has its mass there) and the mean inertia, and an energy scale, that
    mass times the RMS free-node acceleration times the length scale (gravity's `m g l`
    on a chain at rest). A zero scale becomes 1."""
    i, j = scene.edge_index.T
    q = np.asarray(q)
    qdd_free = np.asarray(qdd)[:, list(scene.free_nodes)]
    length = np.sqrt(np.mean(np.sum((q[:, i] - q[:, j]) ** 2, -1)))
    mass, inertia = (np.sum(scene.masses) + np.sum(scene.node_mass_array)) / scene.n_links, np.mean(scene.inertias)
    energy = mass * np.sqrt(np.mean(qdd_free**2)) * length

    def scale(value):
        return np.asarray(value if value > 0 else 1.0, np.float64)

    return {"length_scale": scale(length), "mass_scale": scale(mass), "inertia_scale": scale(inertia), "energy_scale": scale(energy)}


def _mlp(key, n_in: int, hidden: int, n_out: int) -> list:
    """One hidden layer (`kit.mlp`)."""
    return kit.mlp(key, (n_in, hidden, n_out))


def _apply_mlp(layers: list, x):
    return kit.apply_mlp(layers, x, jax.nn.softplus)


def _rod_inputs(config) -> int:
    """Rod features: type one-hot (K), length, mass, inertia (3)."""
    return len(config.vocabulary) + 3


def init(key, config) -> dict:
    """Parameters for `config`'s sizes; the message-passing steps' MLPs stacked on a
    leading axis (one `lax.scan`)."""
    latent, hidden, d, rod = config.latent, config.hidden, config.dim, _rod_inputs(config)
    k_kinetic, k_node, k_edge, k_steps, k_readout = jax.random.split(key, 5)

    def step(k):
        k_e, k_n = jax.random.split(k)
        return {"edge_mlp": _mlp(k_e, 3 * latent, hidden, latent), "node_mlp": _mlp(k_n, 2 * latent, hidden, latent)}

    params = {
        "kinetic": _mlp(k_kinetic, rod, hidden, 2),
        "potential": {
            "node_encoder": _mlp(k_node, d + NODE_TYPES, hidden, latent),
            "edge_encoder": _mlp(k_edge, d + 1 + rod, hidden, latent),
            "processor": jax.vmap(step)(jax.random.split(k_steps, config.message_passing)),
            "readout": _mlp(k_readout, 3 * latent, hidden, 1),
        },
        "statistics": {name: jnp.ones(()) for name in ("length_scale", "mass_scale", "inertia_scale", "energy_scale")},
    }
    if config.drag:
        params["drag"] = jnp.zeros(len(config.vocabulary))
    return params


def _rod_features(config, scene: Scene, stats: dict):
    """(E, K + 3) each link's type one-hot, length, mass and inertia over the scales."""
    onehot = np.eye(len(config.vocabulary))[edge_type_indices(scene, config.vocabulary)]
    values = jnp.stack([jnp.asarray(scene.lengths), jnp.asarray(scene.masses), jnp.asarray(scene.inertias)], -1)
    return jnp.concatenate([jnp.asarray(onehot, values.dtype), values / jnp.stack([stats["length_scale"], stats["mass_scale"], stats["inertia_scale"]])], -1)


def rod_form(config, params: dict, scene: Scene):
    """`(masses, inertias)` (E,) of the learned kinetic form, each strictly positive."""
    stats = params["statistics"]
    out = jax.nn.softplus(_apply_mlp(params["kinetic"], _rod_features(config, scene, stats)) + SOFTPLUS_ONE)
    return out[:, 0] * stats["mass_scale"], out[:, 1] * stats["inertia_scale"]


def _potential_fn(config, params: dict, scene: Scene):
    """`V(q) -> ()`, the learned potential (module docstring)."""
    stats, net = params["statistics"], params["potential"]
    node_type = np.zeros((scene.n_nodes, NODE_TYPES))
    node_type[:, 0] = 1.0
    node_type[list(scene.pinned)] = (0.0, 1.0)
    rod = _rod_features(config, scene, stats)
    rod = jnp.concatenate([rod, rod])  # both directions, in `graph_from_state`'s edge order

    def potential(q):
        graph = graph_from_state(scene, q, jnp.zeros_like(q), config.vocabulary)
        s, r = graph.senders, graph.receivers
        displacement = graph.edges["dq"] / stats["length_scale"]
        edge_x = jnp.concatenate([displacement, jnp.sqrt(jnp.sum(displacement**2, -1, keepdims=True)), rod], -1)
        node_x = jnp.concatenate([q / stats["length_scale"], jnp.asarray(node_type, q.dtype)], -1)
        h, e = _apply_mlp(net["node_encoder"], node_x), _apply_mlp(net["edge_encoder"], edge_x)

        def message_passing(carry, step):
            h, e = carry
            e = e + _apply_mlp(step["edge_mlp"], jnp.concatenate([e, h[s], h[r]], -1))
            h = h + _apply_mlp(step["node_mlp"], jnp.concatenate([h, jax.ops.segment_sum(e, r, num_segments=h.shape[0])], -1))
            return (h, e), None

        if config.message_passing:
            (h, e), _ = jax.lax.scan(message_passing, (h, e), net["processor"])
        per_edge = _apply_mlp(net["readout"], jnp.concatenate([e, h[s], h[r]], -1))[:, 0]
        return 0.5 * jnp.sum(per_edge) * stats["energy_scale"]

    return potential


def _mass_fn(config, params: dict, scene: Scene):
    """`() -> (N, N)` the learned constant node mass (`cgnode.node_mass`)."""
    return lambda: node_mass(scene, *rod_form(config, params, scene))


def momentum_fn(config, params: dict, scene: Scene):
    """`p(q, qd) -> (N, D)`: the Legendre map `p = M qd` (zero at the pins)."""
    mass = _mass_fn(config, params, scene)
    return lambda q, qd: mass().astype(qd.dtype) @ qd


def separable_hamiltonian_fn(scene: Scene, mass_fn, potential):
    """`H(q, p) -> ()`: `1/2 p_f^T M_f^-1 p_f + V(q)` over the free nodes `f`, for a
    constant node mass `mass_fn() -> (N, N)` (positive definite on the free nodes) and
    a potential `V(q) -> ()`. The learned model's (`hamiltonian_fn`), and with the
    scene's own rods and gravity the exact on-manifold Hamiltonian (tested)."""
    free = np.asarray(scene.free_nodes)

    def hamiltonian(q, p):
        m = mass_fn().astype(q.dtype)[free[:, None], free[None, :]]
        p_free = p[free]
        kinetic = 0.5 * jnp.sum(p_free * jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(m), p_free))
        return kinetic + potential(q)

    return hamiltonian


def constrained_hamiltonian_fn(scene: Scene, mass_fn, hamiltonian, force_fn=None):
    """`accel(q, qd) -> qdd` (N, D) of the constrained Hamiltonian equations (module
    docstring) of `hamiltonian(q, p)` whose kinetic term is `1/2 p^T M^-1 p` with the
    constant node mass `mass_fn() -> (N, N)`, under non-conservative forces `force_fn(q,
    qd) -> (N, D)` (None: none): `p = M qd`, `pdot = -dH/dq + F - A^T lam`, `qdd = M^-1
    pdot`, `A qdd = -Adot qd`; zero at the pins."""
    solve = constrained_solve_fn(scene)

    def accel(q, qd):
        m = mass_fn().astype(q.dtype)
        force = -jax.grad(hamiltonian)(q, m @ qd)
        if force_fn is not None:
            force = force + force_fn(q, qd)
        return solve(m, q, qd, force)

    return accel


def hamiltonian_fn(config, params: dict, scene: Scene):
    """`H(q, p) -> ()`: the learned Hamiltonian (module docstring)."""
    return separable_hamiltonian_fn(scene, _mass_fn(config, params, scene), _potential_fn(config, params, scene))


def energy_fn(config, params: dict, scene: Scene):
    """`E(q, qd) -> ()`: the learned Hamiltonian at the state's momentum."""
    hamiltonian, momentum = hamiltonian_fn(config, params, scene), momentum_fn(config, params, scene)
    return lambda q, qd: hamiltonian(q, momentum(q, qd))


def acceleration(config, params: dict, scene: Scene):
    """`accel(q, qd) -> qdd` (N, D) of the learned Hamiltonian's constrained equations
    with the learned drag on drag scenes (module docstring), zero at the pins."""
    drag = None if "drag" not in params else physics.drag_force_fn(scene, params["drag"][edge_type_indices(scene, config.vocabulary)])
    return constrained_hamiltonian_fn(scene, _mass_fn(config, params, scene), hamiltonian_fn(config, params, scene), drag)


# LGNN's sizes (the paper's appendix) and recipe for the energy model it parallels; an
# acceleration model to the library, since its dynamics are the constrained Hamiltonian
# equations, not the Euler-Lagrange solve.
CHGN = register(ModelSpec("chgn", init, acceleration=acceleration, statistics=statistics, latent=5, hidden=10, message_passing=0))
