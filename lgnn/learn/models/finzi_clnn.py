"""Finzi et al. (2020)'s own CLNN ("Simplifying Hamiltonian and Lagrangian Neural
Networks via Explicit Constraints"): a Lagrangian with the kinetic energy's form given,

    L(q, qd) = 1/2 sum_k m_k |qd_k|^2 - V(q),

a learned positive mass per node (`exp` of a parameter: the authors' moments of point
bodies) and a potential `V`, an MLP of the flattened node positions with 3 hidden
layers of 256 tanh units (the authors' `CLNN`), through the constrained Euler-Lagrange
solve with the known link constraints, as every Lagrangian model. lgnn's `clnn` is the
LGNN paper's CLNN, an MLP Lagrangian of the whole state that must learn the kinetic
energy's quadratic form itself; this is the CLNN of the paper that introduced it, which
`lgnn papers` checks against that paper's published cells.

As the authors': orthogonal weights, PyTorch's default uniform biases, the log-masses
0.1 times a standard normal, and no normalisation (the network sees the coordinates as
they are). Tied to its system's size (`ModelSpec.fixed_size`): the network sees every
node at once.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from lgnn.learn.models import kit
from lgnn.learn.models.registry import ModelSpec, register
from lgnn.scene import Scene

# The authors' potential: 3 hidden layers (of `ModelConfig.hidden`, 256 by default).
HIDDEN_LAYERS = 3


def _layer(key, n_in: int, n_out: int) -> dict:
    """An orthogonal weight and a bias uniform in +-1/sqrt(n_in) (PyTorch's `Linear`)."""
    k_w, k_b = jax.random.split(key)
    bound = 1.0 / np.sqrt(n_in)
    return {"w": jax.nn.initializers.orthogonal()(k_w, (n_in, n_out)), "b": jax.random.uniform(k_b, (n_out,), minval=-bound, maxval=bound)}


def init(key, config) -> dict:
    k_mass, k_potential = jax.random.split(key)
    sizes = (config.n_nodes * config.dim, *(config.hidden,) * HIDDEN_LAYERS, 1)
    keys = jax.random.split(k_potential, len(sizes) - 1)
    return {"log_mass": 0.1 * jax.random.normal(k_mass, (config.n_nodes,)),
            "potential": [_layer(k, a, b) for k, a, b in zip(keys, sizes[:-1], sizes[1:])]}


def lagrangian(config, params: dict, scene: Scene):
    def lagrangian_of(q, qd):
        mass = jnp.exp(params["log_mass"]).astype(qd.dtype)
        kinetic = 0.5 * jnp.sum(mass[:, None] * qd**2)
        return kinetic - kit.apply_mlp(params["potential"], q.reshape(-1), jnp.tanh)[0]

    return lagrangian_of


FINZI_CLNN = register(ModelSpec("finzi-clnn", init, lagrangian=lagrangian, hidden=256, fixed_size=True))
