"""Learned dynamics: LGNN and the baselines in a registry of models, one module each.

A model is a `ModelConfig` (its registered name, architecture sizes, the edge-type
vocabulary and, for the fixed-size models, the system size; stored in checkpoints)
and a params pytree (nested dicts and lists of arrays):

    params = init(key, config)
    accel = acceleration_fn(config, params, scene)      # accel(q, qd) -> qdd, (N, D)

- `registry`: `ModelSpec`, `register`, `get_spec`, `model_names`, `load_spec`,
  `ModelConfig`, `check_compatible`;
- `generic`: what works on any registered model (`init`, `acceleration_fn`,
  training-set statistics, `rollout`, `ModelEngine`);
- `kit`: the one MLP and graph-network kit the built-ins share;
- one module per built-in model, each registering its `ModelSpec` on import: `lgnn`
  (`lgnn`, `lgnn-mp1`, `lgnn-mp2`), `lgnn_notebook`, `gns`, `lgn`, `clnn`,
  `strong_gns` (`gns-10-128`), `cgnode`, `chgn`, `chnn`, `finzi_clnn` (`finzi-clnn`,
  Finzi et al.'s own CLNN, `lgnn papers`'). They are imported here in
  that order, which is `model_names()`'s and the benchmark tables' column order; any
  other module of this folder after them, in name order, so a new model is one file.
"""

import importlib
import pkgutil

# The built-in models register themselves on import, in this order.
from lgnn.learn.models import lgnn, lgnn_notebook, gns, lgn, clnn, strong_gns, cgnode, chgn, chnn, finzi_clnn  # isort: skip
from lgnn.learn.models.generic import (
    STATISTICS, AccelerationFactory, ModelEngine, acceleration_fn, apply, init, join_statistics, lagrangian_fn, mass_matrix_fn, rollout,
    split_statistics, trainable_acceleration_fn, training_statistics, with_statistics,
)
from lgnn.learn.models.kit import graph_net_reach, graph_net_supports, squareplus
from lgnn.learn.models.lgnn import lgnn_lagrangian_fn
from lgnn.learn.models.registry import (
    MAX_MESSAGE_PASSING, MAX_WIDTH, ModelConfig, ModelSpec, check_compatible, get_spec, load_spec, model_names, model_source, register,
)

__all__ = [
    "MAX_MESSAGE_PASSING", "MAX_WIDTH", "STATISTICS", "AccelerationFactory", "ModelConfig", "ModelEngine", "ModelSpec", "acceleration_fn",
    "apply", "cgnode", "check_compatible", "chgn", "chnn", "clnn", "finzi_clnn", "get_spec", "gns", "graph_net_reach", "graph_net_supports", "init",
    "join_statistics", "lagrangian_fn", "lgn", "lgnn", "lgnn_lagrangian_fn", "lgnn_notebook", "load_spec", "mass_matrix_fn",
    "model_names", "model_source", "register", "rollout", "split_statistics", "squareplus", "strong_gns", "trainable_acceleration_fn",
    "training_statistics", "with_statistics",
]

# A model module added to this folder registers itself after the built-ins, with no edit here.
for _module in pkgutil.iter_modules(__path__):
    importlib.import_module(f"{__name__}.{_module.name}")
del _module
