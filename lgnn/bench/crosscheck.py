"""Cross-check of the ground-truth engines (Lagrangian, MuJoCo C, MJX) and their speed.

`crosscheck(scene, config, engines)` runs every engine from the scene's initial state
and returns tidy rows `scene, engine, metric, value, note`: per engine the relative
energy drift and the constraint violation (`lgnn.metrics`: max over frames; the latter
includes loop closure) and the wall time; per
pair `a~b` the max node error over the run. MJX is skipped, with an explicit row,
on scenes whose tree is deeper than `MJX_MAX_DEPTH` (its compile time on CPU grows
steeply with depth: 35 s for chain4, minutes beyond 16 links).

`speed_error(...)` measures steps per second (compile excluded) and accuracy against
a converged reference: the speed-against-error table. The command writes both as CSV +
markdown (`lgnn.bench.tables`) with `header(command)`: the command, machine and versions.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

from lgnn import metrics, physics, sharding
from lgnn.scene import Scene, State
from lgnn.engines.lagrangian import SimulationConfig, rollout_fn

ENGINES = ("lagrangian", "mujoco", "mjx")
# Deepest spanning tree MJX is compiled for by default (chain4 compiles in ~35 s on a
# 2-core CPU; chain16 20-60 s; 100 links kinematics alone 459 s).
MJX_MAX_DEPTH = 8
SKIP_MJX = "skipped: MJX compile too slow on CPU (tree depth {depth} > {limit})"


def _run_engine(scene: Scene, config: SimulationConfig, engine: str, dtype: str = "float64"):
    from lgnn.engines import mujoco as lm
    from lgnn.engines.lagrangian import simulate

    start = time.perf_counter()
    if engine == "lagrangian":
        traj = simulate(scene, config)
    else:
        traj = lm.simulate(scene, config, engine=engine, dtype=dtype)
    return traj, time.perf_counter() - start


def crosscheck(scene: Scene, config: SimulationConfig, engines=ENGINES, mjx_max_depth: int = MJX_MAX_DEPTH) -> list[dict]:
    """Tidy rows (module docstring). Wall time of MJX includes its compile (once per process)."""
    from lgnn.engines import mujoco as lm

    rows, trajectories = [], {}
    for engine in engines:
        depth = lm.scene_layout(scene).depth
        if engine == "mjx" and depth > mjx_max_depth:
            rows.append(dict(scene=scene.name, engine=engine, metric="skipped", value=float("nan"),
                             note=SKIP_MJX.format(depth=depth, limit=mjx_max_depth)))
            continue
        traj, wall = _run_engine(scene, config, engine)
        trajectories[engine] = traj
        rows += [
            dict(scene=scene.name, engine=engine, metric="energy_drift", value=metrics.energy_drift(scene, traj), note="max |E-E0| / energy scale"),
            dict(scene=scene.name, engine=engine, metric="constraint_violation", value=metrics.max_constraint_violation(scene, traj.q), note="max link-length/pin/loop error"),
            dict(scene=scene.name, engine=engine, metric="wall_s", value=wall, note="incl. compile" if engine != "mujoco" else ""),
        ]
    for a, b in itertools.combinations(trajectories, 2):
        err = float(np.max(np.abs(trajectories[a].q - trajectories[b].q)))
        rows.append(dict(scene=scene.name, engine=f"{a}~{b}", metric="max_node_error", value=err, note=f"over {config.duration:g} s"))
    return rows


def header(command: str) -> list[str]:
    """Provenance lines: command, machine, versions."""
    import mujoco

    return [
        f"command: {command}",
        f"machine: {platform.node()} {platform.machine()} {platform.processor() or ''} ({jax.device_count()} {jax.default_backend()} device)".strip(),
        f"versions: python {platform.python_version()}, jax {jax.__version__}, mujoco {mujoco.__version__}, numpy {np.__version__}",
    ]


# ---------------------------------------------------------------------------------
# Speed against error
# ---------------------------------------------------------------------------------


def time_compiled(run, *args):
    """`(compile_s, run_s, out)` of a jitted `run(*args)`: compile apart, then one
    untimed run (its one-off costs, ~0.1 s for LGNN) and one timed run."""
    start = time.perf_counter()
    compiled = run.lower(*args).compile()
    compile_s = time.perf_counter() - start
    jax.block_until_ready(compiled(*args))
    start = time.perf_counter()
    out = jax.block_until_ready(compiled(*args))
    return compile_s, time.perf_counter() - start, out


def timed_rollout(engine: str, scene: Scene, config: SimulationConfig, states: State, dtype="float64"):
    """(compile_s, run_s, q (B, F+1, N, 2)) of one engine on a batch of initial states."""
    from lgnn.engines import mujoco as lm

    if engine == "mujoco":
        # Warm-up: compiles the model, kept apart. Timed: MuJoCo's stepping alone; the
        # map to node states afterwards is a Python loop over frames and nodes that
        # would otherwise dominate small scenes (the JAX engines' timings include it,
        # compiled into their rollout).
        start = time.perf_counter()
        lm.joint_rollout(scene, dataclasses.replace(config, frame_dt=config.dt, duration=config.dt), states, threads=2)
        compile_s = time.perf_counter() - start
        start = time.perf_counter()
        compiled, qpos, qvel = lm.joint_rollout(scene, config, states, threads=2)
        run_s = time.perf_counter() - start
        return compile_s, run_s, lm.node_trajectories(compiled, qpos, qvel).q
    if engine == "mjx":
        run = lm.mjx_runner(scene, config, dtype)
        args = (jnp.asarray(states.q, dtype), jnp.asarray(states.qd, dtype))
    else:
        factory = physics.vectorised_true_acceleration_fn if len(states.q) > 1 else physics.true_acceleration_fn
        rollouts = jax.vmap(rollout_fn(scene, config, factory))
        # A batch is spread over every local device (`sharding`; on one device this
        # is plain `jit`).
        run = sharding.batch_jit(rollouts) if len(states.q) % sharding.device_count() == 0 else jax.jit(rollouts)
        args = (jnp.asarray(states.q, dtype), jnp.asarray(states.qd, dtype))
    with lm.mjx_precision(dtype) if engine == "mjx" else contextlib.nullcontext():
        compile_s, run_s, out = time_compiled(run, *args)
    q = out[0] if isinstance(out, tuple) else jnp.concatenate([args[0][:, None], out], axis=1)
    return compile_s, run_s, np.asarray(q, np.float64)


def speed_error(scenes, engines=ENGINES, dts=(1e-3, 1e-4, 1e-5), batches=(100,), batch_dts=(1e-4,), horizon: float = 0.1,
                mjx_max_depth: int = MJX_MAX_DEPTH, max_steps: int = 25_000, dtype: str = "float64", log=print) -> list[dict]:
    """Rows `scene, engine, batch, dt, dtype, steps_per_s, compile_s, max_node_error, note`.

    Speed: steps per second of simulated trajectories (batch x steps / run time),
    compile excluded, over `horizon` s: a single state at each of `dts`, and each of
    `batches` initial conditions at each of `batch_dts`. Accuracy: max node error over
    `horizon` s at each dt (single state) against the MuJoCo C RK4 solution at dt / 10
    of the smallest dt (RK4 is converged to round-off there). Runs whose link-steps
    (batch x steps x links) exceed `max_steps` x 16 for the JAX engines, or MJX beyond
    `mjx_max_depth`, get a row saying so. `dtype` applies to the JAX engines (MuJoCo C
    is float64).
    """
    from lgnn.engines import mujoco as lm
    from lgnn.scene import get_scene, sample_initial_states

    rows = []
    for name in scenes:
        scene = get_scene(name)
        depth = lm.scene_layout(scene).depth
        single = State(scene.nodes[None], scene.velocities[None])
        batched = []
        for size in batches:
            states = sample_initial_states(scene, jax.random.key(0), size)
            batched.append(State(np.asarray(states.q), np.asarray(states.qd)))
        ref_config = SimulationConfig(dt=min(dts) / 10, frame_dt=horizon, duration=horizon)
        reference = lm.rollout(scene, ref_config, single).q[0, -1]
        for engine in engines:
            if engine == "mjx" and depth > mjx_max_depth:
                rows.append(dict(scene=name, engine=engine, batch=0, dt=float("nan"), dtype=dtype, steps_per_s=float("nan"), compile_s=float("nan"),
                                 max_node_error=float("nan"), note=SKIP_MJX.format(depth=depth, limit=mjx_max_depth)))
                continue
            runs = [(dt, single) for dt in dts] + [(dt, states) for dt in batch_dts for states in batched]
            for dt, states in runs:
                b = len(states.q)
                steps = round(horizon / dt)
                config = SimulationConfig(dt=dt, frame_dt=horizon, duration=horizon)
                row = dict(scene=name, engine=engine, batch=b, dt=dt, dtype="float64" if engine == "mujoco" else dtype,
                           steps_per_s=float("nan"), compile_s=float("nan"), max_node_error=float("nan"), note="")
                if engine != "mujoco" and b * steps * scene.n_links > max_steps * 16:
                    row["note"] = "not run: over the link-step limit (--max-steps)"
                    rows.append(row)
                    continue
                compile_s, run_s, q = timed_rollout(engine, scene, config, states, dtype)
                row.update(steps_per_s=b * steps / run_s, compile_s=compile_s)
                if b == 1:
                    row["max_node_error"] = float(np.max(np.abs(q[0, -1] - reference)))
                rows.append(row)
                log(f"{name} {engine} batch {b} dt {dt:g}: {row['steps_per_s']:.3g} steps/s, compile {compile_s:.1f} s, error {row['max_node_error']:.2e}")
    return rows
