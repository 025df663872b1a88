"""Cross-check of the ground-truth engines (Lagrangian, MuJoCo C, MJX) and their speed.

Every engine is an `lgnn.engines.Engine` from `get_engine`, so each stage treats them
alike, and what sets one apart is its registry entry (`lgnn.engines.EngineEntry`),
never its name: `default_engines()` are the entries marked `cpu_ground_truth`; an
engine whose compile grows with tree depth (`compile_grows_with_depth`: MJX) may be
skipped past `mjx_max_depth`; a compiled one (`compiled`) has its wall time noted as
including the compile and its speed runs bounded by link-steps.

`crosscheck(scene, config, engines)` runs every engine from the scene's initial state
(an engine named `NAME` or `NAME:FORM`, e.g. `mujoco:maximal`, so one table holds a
MuJoCo engine in both MJCF forms) and returns tidy rows `scene, engine, form, metric, value, note`: per engine the
relative energy drift and the constraint violation (`lgnn.metrics`: max over frames;
the latter includes loop closure) and the wall time; per pair `a~b` the max node error
over the run. `form` is the MJCF form a MuJoCo engine ran the scene in (each picks
its own, `MujocoEngine.form_of`; "a~b" for pairs, "" for the Lagrangian engine): MJX
runs deep scenes in the maximal form, whose compile time barely grows with the number
of links, so no scene is skipped unless `mjx_max_depth` asks for it (for every engine
whose compile grows with depth).

`speed_error(...)` measures steps per second (compile excluded) and accuracy against
a converged reference (`SPEED_REFERENCE`, MuJoCo C): the speed-against-error table.
`write_crosscheck` and `write_speed_error` write them as CSV + markdown (`lgnn.bench.tables`: `STEM.csv` and
`STEM.md` in a folder, their columns and notes) with `header(command)`: the command,
commit, machine and versions.
"""

from __future__ import annotations

import dataclasses
import itertools
import time
from pathlib import Path

import jax
import numpy as np

from lgnn import metrics, provenance
from lgnn.bench.tables import write_table
from lgnn.engines import ENGINES, batch_of_one, engine_entry, form_of, get_engine
from lgnn.engines.base import Integration, SimulationConfig
from lgnn.engines.mjcf import scene_layout
from lgnn.scene import Scene, State

# The scenes `lgnn crosscheck` runs when given none: issue 14's acceptance, every
# engine on every built-in benchmark scene.
SCENES = ("chain4", "chain8", "chain16", "chain100", "T1", "T2", "T3")
# The scenes of the speed-against-error table when given none.
SPEED_SCENES = ("chain4", "chain16", "chain100", "T1")
# The speed-against-error table's reference engine: MuJoCo C, RK4 at a tenth of the
# smallest dt (converged to round-off there; the table's notes say so).
SPEED_REFERENCE = "mujoco"
# The note of an engine skipped past `mjx_max_depth` (`EngineEntry.title`: "MJX").
SKIP_DEEP = "skipped: {title} compile too slow on CPU (tree depth {depth} > {limit})"
# The tables' file names (`STEM.csv`, `STEM.md`) and columns.
CROSSCHECK_STEM, SPEED_STEM = "crosscheck", "engines_speed_error"
CROSSCHECK_COLUMNS = ("scene", "engine", "form", "metric", "value", "note")
SPEED_COLUMNS = ("scene", "engine", "form", "batch", "dt", "dtype", "steps_per_s", "compile_s", "max_node_error", "note")


def default_engines() -> tuple[str, ...]:
    """The engines `lgnn crosscheck` compares when given none: the CPU ground truths
    (`EngineEntry.cpu_ground_truth`), in registry order."""
    return tuple(name for name, entry in ENGINES.items() if entry.cpu_ground_truth)


def _skipped_past_depth(name: str, depth: int, mjx_max_depth: int | None) -> str:
    # The note of an engine whose compile grows with depth on a scene past the limit, or "".
    entry = engine_entry(name)
    if entry.compile_grows_with_depth and mjx_max_depth is not None and depth > mjx_max_depth:
        return SKIP_DEEP.format(title=entry.title, depth=depth, limit=mjx_max_depth)
    return ""


def engine_spec(spec: str) -> tuple[str, str | None]:
    """`(name, form)` of an engine spec `NAME` (form None: the engine's own) or
    `NAME:FORM` (a MuJoCo engine in the MJCF form FORM)."""
    name, _, form = spec.partition(":")
    return name, form or None


def crosscheck(scene: Scene, config: SimulationConfig, engines=None, mjx_max_depth: int | None = None,
               progress: bool = False, integration: Integration | None = None) -> list[dict]:
    """Tidy rows (module docstring) of the engine specs `engines` (`engine_spec`; None:
    every registered engine), each engine that takes an integration (the Lagrangian one)
    integrating by `integration` (None: its own), the MuJoCo engines by their RK4; an
    engine whose compile grows with depth (MJX) is skipped on trees deeper than
    `mjx_max_depth` (None: on none). Wall time of a compiled engine includes its
    compile (once per process); `progress` lets those whose compile grows with depth
    say so before compiling."""
    rows, trajectories, forms, names = [], {}, {}, {}
    for spec in tuple(ENGINES) if engines is None else engines:
        name, chosen = engine_spec(spec)
        names[spec] = name
        entry = engine_entry(name)
        engine = get_engine(name, progress=progress and entry.compile_grows_with_depth, form=chosen,
                            integration=integration if entry.integrates else None)
        form = forms[spec] = form_of(engine, scene)
        skipped = _skipped_past_depth(name, scene_layout(scene).depth, mjx_max_depth)
        if skipped:
            rows.append(dict(scene=scene.name, engine=name, form=form, metric="skipped", value=float("nan"), note=skipped))
            continue
        start = time.perf_counter()
        traj = trajectories[spec] = engine.rollout(scene, config, batch_of_one(scene.initial_state)).member(0)
        wall = time.perf_counter() - start
        rows += [
            dict(scene=scene.name, engine=name, form=form, metric="energy_drift", value=metrics.energy_drift(scene, traj), note="max |E-E0| / energy scale" + ("; with what the scene's damping takes out" if scene.dissipates else "")),
            dict(scene=scene.name, engine=name, form=form, metric="constraint_violation", value=metrics.max_constraint_violation(scene, traj.q), note="max link-length/pin/loop error"),
            dict(scene=scene.name, engine=name, form=form, metric="wall_s", value=wall, note="incl. compile" if entry.compiled else ""),
        ]
    for a, b in itertools.combinations(trajectories, 2):
        err = float(np.max(np.abs(trajectories[a].q - trajectories[b].q)))
        rows.append(dict(scene=scene.name, engine=f"{names[a]}~{names[b]}", form=f"{forms[a] or '-'}~{forms[b] or '-'}", metric="max_node_error", value=err,
                         note=f"over {config.duration:g} s"))
    return rows


def row_line(row: dict) -> str:
    """One crosscheck row as the line the command prints."""
    return f"{row['scene']:8s} {row['engine']:18s} {row['form']:16s} {row['metric']:22s} {row['value']:.3e} {row['note']}"


def write_crosscheck(rows: list[dict], out_dir, command: str, config: SimulationConfig) -> None:
    """`crosscheck`'s rows of every scene as `out_dir/crosscheck.csv` and `.md`."""
    notes = [f"RK4, dt {config.dt:g}, {config.duration:g} s, float64; MuJoCo loops: connect, solref 2 dt, solimp 0.9999",
             "form: the MJCF form each MuJoCo engine ran (nested: joint coordinates; maximal: a body per link, connect joints)"]
    write_table(rows, list(CROSSCHECK_COLUMNS), f"{out_dir}/{CROSSCHECK_STEM}.csv", f"{out_dir}/{CROSSCHECK_STEM}.md",
                "Cross-check of the ground-truth engines", header(command), notes)


def write_speed_error(rows: list[dict], out_dir, command: str, dtype: str) -> None:
    """`speed_error`'s rows (its JAX engines in `dtype`) as `out_dir/engines_speed_error.csv` and `.md`."""
    notes = [f"speed: steps/s = batch x steps / run time (compile apart), RK4, horizon 0.1 s, JAX engines in {dtype}",
             "error: max node error after 0.1 s (single state) vs MuJoCo C RK4 at dt 1e-6"]
    write_table(rows, list(SPEED_COLUMNS), f"{out_dir}/{SPEED_STEM}.csv", f"{out_dir}/{SPEED_STEM}.md",
                "Engines: speed against error", header(command), notes)


@dataclasses.dataclass(frozen=True)
class BatchedRate:
    """One engine's steps per second on a batch of more than one, as a speed table
    (`write_speed_error`) holds it: the table's file name without its suffix, the scene,
    the batch, the engine, its dtype and the rate."""

    table: str
    scene: str
    batch: int
    engine: str
    dtype: str
    steps_per_s: float


def load_batched_rates(folder) -> list[BatchedRate]:
    """The batched rows of every speed table in `folder` (`*.csv` written by `lgnn
    crosscheck --speed`, on GPU machines: the report's `gpu/`), tables in name order,
    rows in each table's; `[]` where there is no such folder."""
    import pandas as pd

    folder = Path(folder)
    rates = []
    for path in sorted(folder.glob("*.csv")) if folder.is_dir() else ():
        frame = pd.read_csv(path, comment="#")
        for row in frame[frame["batch"] > 1].itertuples(index=False):
            rates.append(BatchedRate(path.stem, row.scene, int(row.batch), row.engine, str(row.dtype), float(row.steps_per_s)))
    return rates


def header(command: str) -> list[str]:
    """Provenance lines: command, commit, machine, versions (`lgnn.provenance`)."""
    env = provenance.environment()
    return [f"command: {command}", f"commit: {env['commit']}", f"machine: {env['device']}", f"versions: {env['versions']}"]


# ---------------------------------------------------------------------------------
# Speed against error
# ---------------------------------------------------------------------------------


def speed_error(scenes, engines=None, dts=(1e-3, 1e-4, 1e-5), batches=(100,), batch_dts=(1e-4,), horizon: float = 0.1,
                mjx_max_depth: int | None = None, max_steps: int = 25_000, dtype: str = "float64", log=print) -> list[dict]:
    """Rows `scene, engine, form, batch, dt, dtype, steps_per_s, compile_s, max_node_error, note`.

    Speed: steps per second of simulated trajectories (batch x steps / run time),
    compile excluded, over `horizon` s: a single state at each of `dts`, and each of
    `batches` initial conditions at each of `batch_dts`. Accuracy: max node error over
    `horizon` s at each dt (single state) against the MuJoCo C RK4 solution
    (`SPEED_REFERENCE`) at dt / 10 of the smallest dt (RK4 is converged to round-off
    there). `engines`: names (None: every registered engine). Runs whose link-steps
    (batch x steps x links) exceed `max_steps` x 16 for the compiled engines
    (`EngineEntry.compiled`: the JAX ones), or an engine whose compile grows with depth
    (MJX) beyond `mjx_max_depth` (None: none), get a row saying so. `dtype` applies to
    the engines that compute in it (MuJoCo C is float64).
    """
    from lgnn.scene import get_scene, sample_initial_states

    rows = []
    for name in scenes:
        scene = get_scene(name)
        depth = scene_layout(scene).depth
        single = State(scene.nodes[None], scene.velocities[None])
        batched = []
        for size in batches:
            states = sample_initial_states(scene, jax.random.key(0), size)
            batched.append(State(np.asarray(states.q), np.asarray(states.qd)))
        ref_config = SimulationConfig(dt=min(dts) / 10, frame_dt=horizon, duration=horizon)
        reference = get_engine(SPEED_REFERENCE).rollout(scene, ref_config, single).q[0, -1]
        for engine in tuple(ENGINES) if engines is None else engines:
            # `dtype` is for the JAX engines; MuJoCo C computes in float64 only.
            entry = engine_entry(engine)
            timed = get_engine(engine, dtype=dtype if dtype in entry.dtypes else None)
            form = form_of(timed, scene)
            skipped = _skipped_past_depth(engine, depth, mjx_max_depth)
            if skipped:
                rows.append(dict(scene=name, engine=engine, form=form, batch=0, dt=float("nan"), dtype=dtype, steps_per_s=float("nan"), compile_s=float("nan"),
                                 max_node_error=float("nan"), note=skipped))
                continue
            runs = [(dt, single) for dt in dts] + [(dt, states) for dt in batch_dts for states in batched]
            for dt, states in runs:
                b = len(states.q)
                steps = round(horizon / dt)
                config = SimulationConfig(dt=dt, frame_dt=horizon, duration=horizon)
                row = dict(scene=name, engine=engine, form=form, batch=b, dt=dt, dtype=timed.dtype,
                           steps_per_s=float("nan"), compile_s=float("nan"), max_node_error=float("nan"), note="")
                if entry.compiled and b * steps * scene.n_links > max_steps * 16:
                    row["note"] = "not run: over the link-step limit (--max-steps)"
                    rows.append(row)
                    continue
                compile_s, run_s, q = timed.timed_rollout(scene, config, states)
                row.update(steps_per_s=b * steps / run_s, compile_s=compile_s)
                if b == 1:
                    row["max_node_error"] = float(np.max(np.abs(q[0, -1] - reference)))
                rows.append(row)
                log(f"{name} {engine} batch {b} dt {dt:g}: {row['steps_per_s']:.3g} steps/s, compile {compile_s:.1f} s, error {row['max_node_error']:.2e}")
    return rows
