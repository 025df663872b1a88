"""CHNN, the constrained Hamiltonian neural network of Finzi et al. (2020), "Simplifying
Hamiltonian and Lagrangian Neural Networks via Explicit Constraints": a Hamiltonian
learned by plain networks over the whole state of a system of fixed size, in Cartesian
node coordinates, its dynamics the constrained Hamiltonian equations with the known
link constraints. It is CLNN's Hamiltonian counterpart, as CHGN (`chgn`) is LGNN's.

The Hamiltonian, in node positions `q` and momenta `p` (N, D):

    H(q, p) = 1/2 p_f^T M_f^-1 p_f + V(q),

- kinetic term: `M` is one learned constant node mass matrix (times the D x D
  identity), `M = L L^T` with `L` lower triangular, its diagonal a `softplus` (strictly
  positive), times the training scene's mean link mass; `M_f` is its free-node block. Finzi et
  al. learn the mass matrix as a constant because in Cartesian coordinates it is one;
  a dense one over the nodes can be the rods' exact on-manifold node mass
  (`cgnode.node_mass`, which is not diagonal), where CHGN's is assembled per rod. The
  rods' own mass matrix `d2T/dqd2` is singular (stretching costs no kinetic energy), so
  CHNN, like the ground truth and CHGN, uses the on-manifold form, positive definite
  by construction (chgn's docstring has why that is the same physics).
- potential term `V(q)`: an MLP of the flattened node positions over the training
  length scale (CLNN's size: two hidden layers of `hidden` units, softplus: the
  dynamics need `dV/dq` and training its derivative again), times the training set's
  energy scale.

The dynamics are CHGN's (`chgn.constrained_hamiltonian_fn`): `p = M qd`, `pdot =
-dH/dq + F - A^T lam`, `A qdd + Adot qd = 0`, solved as one KKT system by the engine's
solvers, with a learned linear drag (one coefficient per link type) on drag scenes. The
networks see every node at once, so the model is tied to its training system's size
(`ModelSpec.fixed_size`), as CLNN.

Contract (pure functions; `config` is a `ModelConfig`, read for `hidden`, `n_nodes`,
`dim`, `vocabulary` and `drag`):
- `statistics(config, scene, q, qd, qdd)`: `chgn.statistics`;
- `init(key, config) -> params` (with `params["drag"]` (K,) zeros on drag scenes);
- `node_mass_fn(config, params, scene) -> () -> (N, N)` the learned constant node mass;
- `hamiltonian_fn(...) -> H(q, p)`, `momentum_fn(...) -> p(q, qd)`, `energy_fn(...)`;
- `acceleration(config, params, scene) -> accel(q, qd) -> qdd` (N, D), zero at pins.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from lgnn import physics
from lgnn.learn.graphs import edge_type_indices
from lgnn.learn.models import chgn, kit
from lgnn.learn.models.registry import ModelSpec, register
from lgnn.scene import Scene

statistics = chgn.statistics


def init(key, config) -> dict:
    """The mass factor starts near the identity (a small off-diagonal, `softplus` of
    `chgn.SOFTPLUS_ONE` = 1 on the diagonal: each node the mean link mass), the
    potential MLP LeCun-normal with zero biases."""
    k_potential, k_mass = jax.random.split(key)
    n, hidden = config.n_nodes, config.hidden
    potential = kit.mlp(k_potential, (n * config.dim, hidden, hidden, 1))
    params = {
        "mass_factor": chgn.SOFTPLUS_ONE * jnp.eye(n) + 1e-3 * jnp.tril(jax.random.normal(k_mass, (n, n)), -1),
        "potential": potential,
        "statistics": {name: jnp.ones(()) for name in ("length_scale", "mass_scale", "inertia_scale", "energy_scale")},
    }
    if config.drag:
        params["drag"] = jnp.zeros(len(config.vocabulary))
    return params


def node_mass_fn(config, params: dict, scene: Scene):
    """`() -> (N, N)`: the learned node mass `L L^T` (module docstring), positive
    definite, so its free-node block is too."""
    factor = params["mass_factor"]

    def node_mass():
        lower = jnp.tril(factor, -1) + jnp.diag(jax.nn.softplus(jnp.diag(factor)))
        return lower @ lower.T * params["statistics"]["mass_scale"]

    return node_mass


def _potential_fn(config, params: dict, scene: Scene):
    stats = params["statistics"]

    def potential(q):
        x = (q / stats["length_scale"]).reshape(-1)
        return kit.apply_mlp(params["potential"], x, jax.nn.softplus)[0] * stats["energy_scale"]

    return potential


def hamiltonian_fn(config, params: dict, scene: Scene):
    """`H(q, p) -> ()`: the learned Hamiltonian (module docstring)."""
    return chgn.separable_hamiltonian_fn(scene, node_mass_fn(config, params, scene), _potential_fn(config, params, scene))


def momentum_fn(config, params: dict, scene: Scene):
    """`p(q, qd) -> (N, D)`: the Legendre map `p = M qd`."""
    mass = node_mass_fn(config, params, scene)
    return lambda q, qd: mass().astype(qd.dtype) @ qd


def energy_fn(config, params: dict, scene: Scene):
    """`E(q, qd) -> ()`: the learned Hamiltonian at the state's momentum."""
    hamiltonian, momentum = hamiltonian_fn(config, params, scene), momentum_fn(config, params, scene)
    return lambda q, qd: hamiltonian(q, momentum(q, qd))


def acceleration(config, params: dict, scene: Scene):
    """`accel(q, qd) -> qdd` (N, D) of the learned Hamiltonian's constrained equations
    with the learned drag on drag scenes, zero at the pins."""
    drag = None if "drag" not in params else physics.drag_force_fn(scene, params["drag"][edge_type_indices(scene, config.vocabulary)])
    return chgn.constrained_hamiltonian_fn(scene, node_mass_fn(config, params, scene), hamiltonian_fn(config, params, scene), drag)


# CLNN's potential width (the paper's 128) for the MLP it parallels.
CHNN = register(ModelSpec("chnn", init, acceleration=acceleration, statistics=statistics, hidden=128, fixed_size=True))
