"""Engines: one interface from a scene and a batch of initial states to a `Trajectory`.

The contract (`base`): an `Engine` has a `name`, the precision it computes in
(`dtype`), `rollout(scene, config, states) -> Trajectory` batched over initial states
(B, N, D) -> q, qd (B, F+1, N, D), `timed_rollout` (the same run with compile apart),
`form_of(scene)` (its MJCF form, "" without one) and `accuracy(scene, config)` (the
error it expects against the exact solution, None where it states none);
`SimulationConfig`, `Integration` and `Trajectory` are the shared types. The JAX engines roll out
through one batched path (`rollouts.batched_rollouts`: vmapped, sharded over the local
devices, one compiled program per scene and settings with the parameters an
argument, frames in calls of about 100, stopped at divergence for a reference).

`get_engine(name, dtype=..., progress=..., form=..., integration=...)` returns one
from the registry `ENGINES` (name -> `EngineEntry`: its factory, the precisions it
computes in, the MJCF forms it takes, whether it takes an `Integration`);
`register_engine` adds one:

- "lagrangian" (`lagrangian.LagrangianEngine`): the exact constrained Lagrangian
  engine (`simulate`, `rollout_fn`), float64 or float32, any `Integration`;
- "mujoco" (`mujoco.MujocoEngine`): MuJoCo C on the scene's MJCF (`mjcf`), float64;
- "mjx" (`mjx.MjxEngine`): MJX on the same model, float64 or float32;
- "mjwarp" (`mjwarp.MjwarpEngine`): MuJoCo Warp on the same model, many worlds at
  once, float32 only, GPU or Warp's CPU backend; an optional extra (`lgnn[mjwarp]`),
  a one-line `ConfigError` when it is not installed.

`get_engine` refuses in one line (`ConfigError`) a precision the engine does not
compute in, a `form` for an engine without MJCF and an `integration` for an engine
that does not take one (the MuJoCo engines integrate with MuJoCo's RK4); without `dtype` an engine computes
in its first (preferred) precision. The MuJoCo engines take the MJCF form
(`mjcf.Form`: "nested" or "maximal", or "auto" for the engine's own choice).

A learned model answers the same interface as `lgnn.learn.models.ModelEngine(config,
params)` (e.g. `ModelEngine(*load_model(checkpoint))`); it is not in `ENGINES`
because models live in a layer above the engines. `mujoco` is imported on first use
of a MuJoCo engine, never by importing this package. To add an engine: an `Engine`
subclass in its own module, and one `register_engine(EngineEntry(...))`.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from lgnn.engines.base import DTYPES, Engine, Integration, SimulationConfig, Trajectory
from lgnn.engines.lagrangian import LagrangianEngine
from lgnn.engines.mjcf import FORMS
from lgnn.errors import ConfigError
from lgnn.scene import Scene, State

# The `form` values a MuJoCo engine takes: its own choice per scene, or a fixed form.
MJCF_FORMS = ("auto", *FORMS)


@dataclasses.dataclass(frozen=True)
class EngineEntry:
    """One registered engine: `factory(dtype, progress, form, integration) -> Engine`
    (`form` None for an engine without MJCF forms, else one of `forms`; `integration`
    None for the engine's default or one that takes none), the precisions it computes
    in (`dtypes`, the first its default), the MJCF forms it takes (empty: none) and
    whether it takes an `Integration` (`integrates`)."""

    name: str
    factory: Callable[[str, bool, str | None, Integration | None], Engine]
    dtypes: tuple[str, ...]
    forms: tuple[str, ...] = ()
    integrates: bool = False

    def __post_init__(self):
        unknown = [dtype for dtype in self.dtypes if dtype not in DTYPES]
        if not self.dtypes or unknown:
            raise ConfigError(f"engine {self.name!r}: precisions must be some of {', '.join(DTYPES)}, got {self.dtypes}")


# Name -> entry. The MuJoCo factories import their module (and so `mujoco`) when called.
ENGINES: dict[str, EngineEntry] = {}


def register_engine(entry: EngineEntry) -> EngineEntry:
    """Make `entry` available as `get_engine(entry.name)`. Registering the same entry
    again does nothing; another entry under a taken name is a `ConfigError`."""
    known = ENGINES.get(entry.name)
    if known is not None and known != entry:
        raise ConfigError(f"engine {entry.name!r} is already registered")
    ENGINES[entry.name] = entry
    return entry


def _lagrangian(dtype: str, progress: bool, form: str | None, integration: Integration | None) -> Engine:
    return LagrangianEngine(dtype=dtype, progress=progress, integration=integration or Integration())


def _mujoco(dtype: str, progress: bool, form: str | None, integration: Integration | None) -> Engine:
    from lgnn.engines.mujoco import MujocoEngine

    return MujocoEngine(form=form or "auto")


def _mjx(dtype: str, progress: bool, form: str | None, integration: Integration | None) -> Engine:
    import sys

    from lgnn.engines.mjx import MjxEngine

    # progress: say before a compile starts (minutes on a CPU), on stderr.
    log = (lambda line: print(line, file=sys.stderr, flush=True)) if progress else None
    return MjxEngine(dtype=dtype, form=form or "auto", log=log)


def _mjwarp(dtype: str, progress: bool, form: str | None, integration: Integration | None) -> Engine:
    from lgnn.engines.mjwarp import MjwarpEngine

    return MjwarpEngine() if form is None else MjwarpEngine(form=form)


register_engine(EngineEntry("lagrangian", _lagrangian, ("float64", "float32"), integrates=True))
register_engine(EngineEntry("mujoco", _mujoco, ("float64",), MJCF_FORMS))
register_engine(EngineEntry("mjx", _mjx, ("float64", "float32"), MJCF_FORMS))
register_engine(EngineEntry("mjwarp", _mjwarp, ("float32",), MJCF_FORMS))


def get_engine(name: str, *, dtype: str | None = None, progress: bool = False, form: str | None = None,
               integration: Integration | None = None) -> Engine:
    """The engine `name` (a key of `ENGINES`) computing in `dtype` (None: its default;
    one it lacks is a `ConfigError`); `progress` shows progress where the engine has it
    (the Lagrangian engine's bars, MJX's compile notice); `form` picks the MJCF form of
    a MuJoCo engine ("nested", "maximal", or "auto": the engine's own choice; None: its
    default); `integration` how an engine that integrates itself does (None: its
    default; for one that does not, a `ConfigError`)."""
    entry = ENGINES.get(name)
    if entry is None:
        raise ConfigError(f"unknown engine {name!r} (choose from {', '.join(ENGINES)})")
    if dtype is None:
        dtype = entry.dtypes[0]
    if dtype not in entry.dtypes:
        raise ConfigError(f"engine {name!r} computes in {', '.join(entry.dtypes)} only, not {dtype!r}")
    if form is not None and not entry.forms:
        raise ConfigError(f"engine {name!r} has no MJCF form (only the MuJoCo engines take --form)")
    if form is not None and form not in entry.forms:
        raise ConfigError(f"unknown MJCF form {form!r} for engine {name!r} (choose from {', '.join(entry.forms)})")
    if integration is not None and not entry.integrates:
        takers = ", ".join(known for known, other in ENGINES.items() if other.integrates)
        raise ConfigError(f"engine {name!r} integrates its own way and takes no integrator or projection (those are for: {takers})")
    return entry.factory(dtype, progress, form, integration)


def form_of(engine: Engine, scene: Scene) -> str:
    """The MJCF form `engine` runs `scene` in ("" for engines without MJCF)."""
    return engine.form_of(scene)


def batch_of_one(state: State) -> State:
    """`state` (N, D) as a batch of one initial state (1, N, D), for `Engine.rollout`."""
    return State(np.asarray(state.q)[None], np.asarray(state.qd)[None])


__all__ = ["DTYPES", "ENGINES", "Engine", "EngineEntry", "Integration", "SimulationConfig", "Trajectory", "batch_of_one", "form_of", "get_engine",
           "register_engine"]
