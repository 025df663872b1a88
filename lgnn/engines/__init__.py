"""Engines: one interface from a scene and a batch of initial states to a `Trajectory`.

An `Engine` has a `name`, the precision it computes in (`dtype`), and

- `rollout(scene, config, states) -> Trajectory`: initial states `q`, `qd` (B, N, D)
  integrated for `config.duration` (a `SimulationConfig`); the trajectory's `q`, `qd`
  are (B, F+1, N, D) and `energy` (B, F+1) lgnn's exact energy, frame 0 the initial
  state (`Trajectory.member(b)` is one of them). It raises `SimulationError` at the
  first non-finite or exploding frame (`lgnn.metrics.ExplosionBounds`), carrying the
  failing state's frames before it;
- `timed_rollout(scene, config, states) -> (compile_s, run_s, q)`: the same run timed
  with one-off costs (compilation, model building) apart, `q` (B, F+1, N, D).

`get_engine(name, dtype=..., progress=...)` returns one from the registry `ENGINES`:

- "lagrangian" (`lagrangian.LagrangianEngine`): the exact constrained Lagrangian
  engine (`simulate`, `rollout_fn`), with `SimulationConfig` and `Trajectory`;
- "mujoco" (`mujoco.MujocoEngine`): MuJoCo C on the scene's MJCF (`mjcf`), float64;
- "mjx" (`mjx.MjxEngine`): MJX on the same model, float64 or float32;
- "mjwarp" (`mjwarp.MjwarpEngine`): MuJoCo Warp on the same model, many worlds at
  once, float32 only, GPU or Warp's CPU backend; an optional extra (`lgnn[mjwarp]`),
  a one-line `ConfigError` when it is not installed.

The MuJoCo engines take the MJCF form (`mjcf.Form`: "nested" or "maximal", or "auto"
for the engine's own choice), through `get_engine(..., form=...)`; `form_of(engine,
scene)` says which form an engine runs a scene in ("" for the others).

A learned model answers the same interface as `lgnn.learn.models.ModelEngine(config,
params)` (e.g. `ModelEngine(*load_model(checkpoint))`); it is not in `ENGINES`
because models live in a layer above the engines.

`dtype` is the precision of the JAX computations an engine has a choice over (MJX;
the Lagrangian engine's timed batch); MuJoCo C and `simulate` are float64, and
`Engine.dtype` says what the engine uses. `mujoco` is imported on first use of a
MuJoCo engine, never by importing this package. To add an engine: a class with these
members in its own module, and one entry in `ENGINES`.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Protocol

import numpy as np

from lgnn.engines.mjcf import FORMS
from lgnn.engines.lagrangian import DTYPES, LagrangianEngine, SimulationConfig, Trajectory
from lgnn.errors import ConfigError
from lgnn.scene import Scene, State


class Engine(Protocol):
    """What every engine answers (module docstring)."""

    name: str
    dtype: str

    def rollout(self, scene: Scene, config: SimulationConfig, states: State) -> Trajectory: ...

    def timed_rollout(self, scene: Scene, config: SimulationConfig, states: State) -> tuple[float, float, np.ndarray]: ...


def form_of(engine, scene: Scene) -> str:
    """The MJCF form `engine` runs `scene` in: a MuJoCo engine's own choice for the
    scene (`form_of`) or its fixed `form`; "" for engines without MJCF."""
    return engine.form_of(scene) if hasattr(engine, "form_of") else getattr(engine, "form", "")


def _lagrangian(dtype: str, progress: bool) -> Engine:
    return LagrangianEngine(dtype=dtype, progress=progress)


def _mujoco(dtype: str, progress: bool) -> Engine:
    from lgnn.engines.mujoco import MujocoEngine

    return MujocoEngine()


def _mjx(dtype: str, progress: bool) -> Engine:
    import sys

    from lgnn.engines.mjx import MjxEngine

    # progress: say before a compile starts (minutes on a CPU), on stderr.
    return MjxEngine(dtype=dtype, log=(lambda line: print(line, file=sys.stderr, flush=True)) if progress else None)


def _mjwarp(dtype: str, progress: bool) -> Engine:
    from lgnn.engines.mjwarp import MjwarpEngine

    return MjwarpEngine()


# Name -> factory(dtype, progress). The MuJoCo factories import their module (and so
# `mujoco`) when called.
ENGINES: dict[str, Callable[[str, bool], Engine]] = {"lagrangian": _lagrangian, "mujoco": _mujoco, "mjx": _mjx, "mjwarp": _mjwarp}


def get_engine(name: str, *, dtype: str = "float64", progress: bool = False, form: str | None = None) -> Engine:
    """The engine `name` (a key of `ENGINES`) computing in `dtype` where it has a choice;
    `progress` shows progress where the engine has it (the Lagrangian engine's bars,
    MJX's compile notice); `form` picks the MJCF form of a MuJoCo engine ("nested",
    "maximal", or "auto": the engine's own choice; None: its default)."""
    if name not in ENGINES:
        raise ConfigError(f"unknown engine {name!r} (choose from {', '.join(ENGINES)})")
    if dtype not in DTYPES:
        raise ConfigError(f"unknown dtype {dtype!r} (choose from {', '.join(DTYPES)})")
    engine = ENGINES[name](dtype, progress)
    if form is None:
        return engine
    if form not in ("auto", *FORMS):
        raise ConfigError(f"unknown MJCF form {form!r} (choose from auto, {', '.join(FORMS)})")
    if not (dataclasses.is_dataclass(engine) and any(field.name == "form" for field in dataclasses.fields(engine))):
        raise ConfigError(f"engine {name!r} has no MJCF form (only the MuJoCo engines take --form)")
    return dataclasses.replace(engine, form=form)


def batch_of_one(state: State) -> State:
    """`state` (N, D) as a batch of one initial state (1, N, D), for `Engine.rollout`."""
    return State(np.asarray(state.q)[None], np.asarray(state.qd)[None])
