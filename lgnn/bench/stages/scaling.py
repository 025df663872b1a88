"""Scaling stage: cost per step against chain length (planar and 3D chains), and
batched throughput.

The record (JSON) depends on the profile's `ScalingSettings` and `EvaluateSettings` (the
step and the initial conditions' seed) and on the content of the LGNN checkpoints timed
(`scaling_key`: the planar one, and the 3D one where there are 3D lengths);
`load_scaling` gives the report the record if it matches.
"""

from __future__ import annotations

from pathlib import Path

import jax
import numpy as np

from lgnn import physics, records
from lgnn.bench import store
from lgnn.engines import get_engine
from lgnn.bench.grid import TRAINING_SCENES
from lgnn.bench.profiles import Profile, lgnn_job
from lgnn.records import settings_key
from lgnn.bench.store import log
from lgnn.engines.base import Integration, SimulationConfig
from lgnn.engines.rollouts import Unparametrised, timed_rollouts
from lgnn.errors import ConfigError, SceneError, SimulationError
from lgnn.learn import models
from lgnn.learn.checkpoints import content_digest, load_model
from lgnn.scene import State, chain, get_scene, sample_initial_states, spatial_chain

# Chains of n links per dimension: the planar chain and the 3D one (`spatial_chain`).
CHAINS = {2: chain, 3: spatial_chain}


def _checkpoint(profile: Profile, out: Path, dim: int = 2) -> tuple[Path, str | None]:
    layout = store.layout(profile, out)
    checkpoint = layout.found(layout.checkpoint(lgnn_job(profile, TRAINING_SCENES[dim])))
    return checkpoint, content_digest(checkpoint) if checkpoint.exists() else None


def _lengths(profile: Profile) -> dict[int, tuple[int, ...]]:
    """`{dim: chain lengths}` of the size rows."""
    return {2: profile.scaling.lengths, 3: profile.scaling.spatial_lengths}


def scaling_key(profile: Profile, out: Path) -> str:
    """Settings the scaling record depends on (module docstring). Without 3D lengths,
    neither they nor the 3D checkpoint enter it: a planar record keeps its key."""
    settings, parts = settings_key(profile.scaling), {}
    if not settings["spatial_lengths"]:
        del settings["spatial_lengths"]
    else:
        parts["lgnn_3d"] = _checkpoint(profile, out, 3)[1]
    return records.digest({"scaling": settings, "evaluate": settings_key(profile.evaluate), "lgnn": _checkpoint(profile, out)[1], **parts})


def scaling(profile: Profile, out: Path) -> Path:
    """Record (JSON) of rows `kind, scene, dim, n_links, solver, batch, s_per_step, compile_s, note`:
    - kind "size": wall seconds per RK4 step at the evaluation dt against chain length
      (`lengths` planar, `spatial_lengths` 3D), single trajectory from the scene's
      sampler, for the Lagrangian ground truth, MuJoCo C (its stepping alone; the note
      names its MJCF form) and the LGNN of the chain's dimension (`lgnn_job`: trained on
      chain4, chain4-3d), where its checkpoint exists;
    - kind "batch": `throughput_batch` initial conditions of each of `throughput_scenes`
      at once (batches spread over every local device; MuJoCo C on two threads), for the
      Lagrangian ground truth and MuJoCo C.
    Each timing runs `steps` steps after a compile (or warm-up) run kept apart."""
    settings = profile.scaling
    layout = store.layout(profile, out)
    path, key = layout.scaling_record, scaling_key(profile, out)
    if layout.load_json(path, key) is not None:
        return path
    steps, dt, ic_seed = settings.steps, profile.evaluate.dt, profile.evaluate.ic_seed
    config = SimulationConfig(dt, steps * dt, steps * dt)
    rows = []
    for dim, lengths in _lengths(profile).items():
        checkpoint, digest = _checkpoint(profile, out, dim) if lengths else (None, None)
        model_params = load_model(checkpoint) if digest else None
        for n in lengths:
            rows += _size_rows(CHAINS[dim](n), config, profile.evaluate.integration, ic_seed, model_params)
    for name in settings.throughput_scenes:
        scene = get_scene(name)
        states = sample_initial_states(scene, jax.random.PRNGKey(ic_seed), settings.throughput_batch)
        batch = State(np.asarray(states.q), np.asarray(states.qd))
        for solver in ("lagrangian", "mujoco"):
            compile_s, run_s, _ = get_engine(solver).timed_rollout(scene, config, batch)
            rows.append(dict(kind="batch", scene=name, dim=scene.dim, n_links=scene.n_links, solver=solver, batch=settings.throughput_batch,
                             s_per_step=run_s / steps, compile_s=compile_s, note=""))
            log(f"throughput {name} {solver} x{settings.throughput_batch}: {settings.throughput_batch * steps / run_s:.3g} steps/s")
    store.save_json(path, key, rows=rows)
    return path


def _size_rows(scene, config: SimulationConfig, integration: Integration, ic_seed: int, model_params) -> list[dict]:
    """The size rows of one chain (`scaling`): Lagrangian, MuJoCo C and, with
    `model_params`, the LGNN, each `config.duration / config.dt` steps (the JAX ones
    integrated by `integration`)."""
    steps = round(config.duration / config.dt)
    states = sample_initial_states(scene, jax.random.PRNGKey(ic_seed), 1)
    single = State(np.asarray(states.q), np.asarray(states.qd))
    factories = {"lagrangian": (Unparametrised(physics.true_acceleration_fn), None), "mujoco": (None, None)}
    if model_params is not None:
        model, params = model_params
        factories["lgnn"] = (models.AccelerationFactory(model), params)
    rows = []
    for solver, (factory, params) in factories.items():
        row = dict(kind="size", scene=scene.name, dim=scene.dim, n_links=scene.n_links, solver=solver, batch=1,
                   s_per_step=float("nan"), compile_s=float("nan"), note="")
        if factory is None:
            # MuJoCo C picks its MJCF form (nested up to MuJoCo's nesting limit, then
            # maximal: chain1000 runs); the note says which.
            engine = get_engine("mujoco")
            row["note"] = f"{engine.form_of(scene)} MJCF"
            try:
                compile_s, run_s, _ = engine.timed_rollout(scene, config, single)
            except (ConfigError, SceneError, SimulationError) as err:
                row["note"] = f"not run: {err}"
                rows.append(row)
                log(f"scaling {scene.name} mujoco: {row['note']}")
                continue
        else:
            # One trajectory (a batch of one), as the speed stage times learned models.
            compile_s, (run_s,), _ = timed_rollouts(scene, config, factory, single, params, integration=integration)
        rows.append({**row, "s_per_step": run_s / steps, "compile_s": compile_s})
        log(f"scaling {scene.name} {solver}: {run_s / steps:.3g} s per step (compile {compile_s:.1f} s)")
    return rows


def load_scaling(profile: Profile, out: Path) -> dict | None:
    """The scaling record if it matches the profile and checkpoint, else None."""
    layout = store.layout(profile, out)
    return layout.load_json(layout.scaling_record, scaling_key(profile, out))
