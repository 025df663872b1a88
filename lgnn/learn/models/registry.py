"""The model registry: `ModelSpec` (what the library needs to know about one model),
`register`, `get_spec`, `model_names`, `load_spec` (a model defined outside lgnn), and
`ModelConfig`, the model's name and sizes as checkpoints keep them.

Each name maps to one `ModelSpec`: its init, its output (a Lagrangian or
accelerations), its default sizes, whether it is tied to one system size, the
training-set statistics it normalises by and its training recipe (weight decay, input
noise). Nothing else compares names: training, checkpoints, rollouts and `ModelEngine`
use the spec. The built-in models register themselves, each in its own module of this
package, in the order the package imports them (`model_names()`, which orders the
benchmark's columns).
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

from lgnn import records
from lgnn.errors import ConfigError
from lgnn.learn.graphs import edge_type_indices
from lgnn.scene import Scene


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
    """Raise `ConfigError` if the model cannot run on `scene` (size, dimension, types,
    rails: the models' graphs know pinned and free nodes, not a node that slides)."""
    if scene.rails:
        raise ConfigError(f"scene {scene.name!r} has rails (nodes sliding along an axis), which the learned models do not take yet")
    if scene.dim != config.dim:
        raise ConfigError(f"model {config.name} was trained in {config.dim}D, scene {scene.name!r} is {scene.dim}D")
    if config.spec.fixed_size and scene.n_nodes != config.n_nodes:
        raise ConfigError(
            f"{config.name} is tied to its training system size ({config.n_nodes} nodes); scene {scene.name!r} has {scene.n_nodes}"
        )
    edge_type_indices(scene, config.vocabulary)

