"""CLNN (`clnn`): an MLP with 2 hidden layers of 128 on the concatenated `(q, qd)` of
a fixed-size system, read out as the Lagrangian, through the constrained
Euler-Lagrange solve; it refuses a scene of another size (`ModelSpec.fixed_size`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from lgnn import physics
from lgnn.learn.models import kit
from lgnn.learn.models.registry import ModelSpec, register
from lgnn.scene import Scene


def init(key, config) -> dict:
    """CLNN's MLP, started with `L` convex in the velocities (as LGN, `lgn.init`): every
    weight after the first layer non-negative."""
    keys = jax.random.split(key, 3)
    first, *rest = kit.mlp(keys[0], (2 * config.n_nodes * config.dim, config.hidden, config.hidden, 1))
    return {"mlp": [first, *kit.nonnegative_weights(rest)]}


def lagrangian(config, params: dict, scene: Scene) -> physics.LagrangianFn:
    return lambda q, qd: kit.apply_mlp(params["mlp"], jnp.concatenate([q.reshape(-1), qd.reshape(-1)]))[0]


CLNN = register(ModelSpec("clnn", init, lagrangian=lagrangian, hidden=128, fixed_size=True))
