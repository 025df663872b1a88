"""Engines: one interface from a scene and a batch of initial states to a `Trajectory`.

The contract (`base`): an `Engine` has a `name`, the precision it computes in
(`dtype`), `rollout(scene, config, states) -> Trajectory` batched over initial states
(B, N, D) -> q, qd (B, F+1, N, D), `timed_rollout` (the same run with compile apart),
`timed_batch` (repeated timed runs of a batch and its final positions),
`form_of(scene)` (its MJCF form, "" without one) and `accuracy(scene, config)` (the
error it expects against the exact solution, None where it states none);
`SimulationConfig`, `Integration` and `Trajectory` are the shared types. The JAX engines roll out
through one batched path (`rollouts.batched_rollouts`: vmapped, sharded over the local
devices, one compiled program per scene and settings with the parameters an
argument, frames in calls of about 100, stopped at divergence for a reference).

`get_engine(name, dtype=..., progress=..., form=..., integration=...)` returns one
from the registry `ENGINES` (name -> `EngineEntry`: its factory, the precisions it
computes in, the MJCF forms it takes, whether it takes an `Integration`, and what the
benchmark's commands read of it: its title, whether it is one of the CPU ground truths
`lgnn crosscheck` compares by default, whether it runs a compiled program, whether its
compile grows with tree depth, whether the speed stage times it, its role in
`lgnn gpu-truth`); `engine_entry(name)` is an engine's entry, `register_engine` adds
one, and `lgnn crosscheck`, `lgnn gpu-truth` and the benchmark's speed stage take
their engines from these fields, not from names:

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


# An engine's role in `lgnn gpu-truth` (`EngineEntry.gpu_truth_role`).
GPU_TRUTH_ROLES = {
    "": "not run by gpu-truth",
    "reference": "lgnn's own engine: its float64 run is every batch's reference, and its float32 run is set against the MuJoCo GPU engines",
    "mujoco-gpu": "a MuJoCo GPU engine, timed against the reference; the fastest that agrees is set beside lgnn's float32 run",
    "timed": "timed against the reference, and set beside nothing",
}


@dataclasses.dataclass(frozen=True)
class EngineEntry:
    """One registered engine: `factory(dtype, progress, form, integration) -> Engine`
    (`form` None for an engine without MJCF forms, else one of `forms`; `integration`
    None for the engine's default or one that takes none), the precisions it computes
    in (`dtypes`, the first its default), the MJCF forms it takes (empty: none) and
    whether it takes an `Integration` (`integrates`).

    The rest is what the benchmark's commands read of an engine, so that none of them
    names one: `title`, the engine as the report's headings and notes name it (default:
    its name); `cpu_ground_truth`, one of the CPU ground truths `lgnn crosscheck`
    compares when given no `--engines`; `compiled`, it runs a compiled program (JAX,
    Warp) rather than MuJoCo C's step loop: its first rollout's wall time includes the
    compile, and the speed tables bound its runs by link-steps; `compile_grows_with_depth`,
    its compile can grow with the scene's tree depth (MJX's nested form: minutes on a
    CPU), so `lgnn crosscheck` may skip it past a depth (`--mjx-max-depth`) and has it
    say so before it compiles; `in_speed_table`, the
    benchmark's speed stage times it (unless the profile turns it off:
    `SpeedSettings.runs`); `gpu_truth_role`, its role in `lgnn gpu-truth`
    (`GPU_TRUTH_ROLES`)."""

    name: str
    factory: Callable[[str, bool, str | None, Integration | None], Engine]
    dtypes: tuple[str, ...]
    forms: tuple[str, ...] = ()
    integrates: bool = False
    title: str = ""
    cpu_ground_truth: bool = False
    compiled: bool = False
    compile_grows_with_depth: bool = False
    in_speed_table: bool = False
    gpu_truth_role: str = ""

    def __post_init__(self):
        unknown = [dtype for dtype in self.dtypes if dtype not in DTYPES]
        if not self.dtypes or unknown:
            raise ConfigError(f"engine {self.name!r}: precisions must be some of {', '.join(DTYPES)}, got {self.dtypes}")
        if self.gpu_truth_role not in GPU_TRUTH_ROLES:
            raise ConfigError(f"engine {self.name!r}: gpu_truth_role must be one of {', '.join(map(repr, GPU_TRUTH_ROLES))}, got {self.gpu_truth_role!r}")
        if not self.title:
            object.__setattr__(self, "title", self.name)


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


register_engine(EngineEntry("lagrangian", _lagrangian, ("float64", "float32"), integrates=True, title="the Lagrangian engine",
                            cpu_ground_truth=True, compiled=True, in_speed_table=True, gpu_truth_role="reference"))
register_engine(EngineEntry("mujoco", _mujoco, ("float64",), MJCF_FORMS, title="MuJoCo", cpu_ground_truth=True, in_speed_table=True))
# MJX's nested form compiles in minutes on a CPU past a few links (the maximal form in
# seconds to a minute: `lgnn.engines.mjcf`).
register_engine(EngineEntry("mjx", _mjx, ("float64", "float32"), MJCF_FORMS, title="MJX", cpu_ground_truth=True, compiled=True,
                            compile_grows_with_depth=True, in_speed_table=True, gpu_truth_role="mujoco-gpu"))
register_engine(EngineEntry("mjwarp", _mjwarp, ("float32",), MJCF_FORMS, title="MuJoCo Warp", compiled=True, gpu_truth_role="mujoco-gpu"))


def engine_entry(name: str) -> EngineEntry:
    """The registry entry of engine `name`; an unknown name is a `ConfigError` naming the choices."""
    entry = ENGINES.get(name)
    if entry is None:
        raise ConfigError(f"unknown engine {name!r} (choose from {', '.join(ENGINES)})")
    return entry


def get_engine(name: str, *, dtype: str | None = None, progress: bool = False, form: str | None = None,
               integration: Integration | None = None) -> Engine:
    """The engine `name` (a key of `ENGINES`) computing in `dtype` (None: its default;
    one it lacks is a `ConfigError`); `progress` shows progress where the engine has it
    (the Lagrangian engine's bars, MJX's compile notice); `form` picks the MJCF form of
    a MuJoCo engine ("nested", "maximal", or "auto": the engine's own choice; None: its
    default); `integration` how an engine that integrates itself does (None: its
    default; for one that does not, a `ConfigError`)."""
    entry = engine_entry(name)
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


__all__ = ["DTYPES", "ENGINES", "GPU_TRUTH_ROLES", "Engine", "EngineEntry", "Integration", "SimulationConfig", "Trajectory", "batch_of_one", "engine_entry", "form_of",
           "get_engine", "register_engine"]
