"""Numerical stability on hard cases: what breaks first, and is it detected.

Every hard case is declared once, as a frozen `Case` (`cases(settings)` lists them);
`run_case(case)` runs one and returns a tidy row:

    case, scene, engine, integrator, dt, duration, status, time_to_failure,
    max_constraint_violation, energy_drift, accel_error, step_s, wall_s, message

`status` is what happened: `ok` (finished and within the case's tolerances),
`detected` (the engine stopped with a `SimulationError` naming the time of the first
non-finite or exploding frame: `time_to_failure`; the other columns then describe the
frames before it), or `silent` (finished without complaint but outside the case's
tolerances: a failure nobody was told about). Two kinds of case:

- rollouts (`kind="rollout"`): integrate `duration` seconds with an engine
  (`lagrangian`, `mujoco`: `lgnn.engines.get_engine`; or a learned model
  `gns-untrained` / `gns-bad` loaded from a checkpoint file, as `lgnn rollout` does).
  `energy_drift` and `max_constraint_violation` are `lgnn.metrics`' (the true energy's
  largest change over an energy scale; the largest link-length or pin error over the
  frames).
- accelerations (`kind="acceleration"`): at the scene's initial state, the exact
  accelerations must be unique and correct: `accel_error` is their largest
  difference from an independent reference (the constant-mass Lagrangian, which
  equals the exact one on the constraint manifold but has a well-conditioned mass
  matrix; or exactly zero where the structure is rigid), and
  `max_constraint_violation` is the acceleration-level residual
  `|d^2/dt^2 (|r_i - r_j|^2 / 2l)|` over *every* link, the dropped redundant ones
  included.

`step_cost(n)` measures the ground truth's seconds per RK4 step on an n-link chain
(compile excluded) and `cost_rows` fits the log-log exponent. `write_report` writes
the markdown and CSV (atomically, with the command, commit, machine and versions).
The library never calls `jit` on its own behalf except through the engines and these
measurement helpers, which are entry points.
"""

from __future__ import annotations

import dataclasses
import math
import tempfile
import time
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from lgnn import metrics, physics
from lgnn.errors import SimulationError
from lgnn.scene import Scene
from lgnn.scene import chain, get_scene
from lgnn.engines import batch_of_one, get_engine
from lgnn.engines.base import Integration, SimulationConfig, Trajectory

STATUSES = ("ok", "detected", "silent")
COLUMNS = (
    "case", "scene", "engine", "integrator", "dt", "duration", "status", "time_to_failure",
    "max_constraint_violation", "energy_drift", "accel_error", "step_s", "wall_s", "message",
)
# The scale of the deliberately bad GNS parameters: every weight of an untrained GNS
# times this (measured on chain4: x1 stays finite and bounded, x3 explodes in 0.03 s).
BAD_MODEL_SCALE = 3.0
SEED = 0


# ---------------------------------------------------------------------------------
# Cases
# ---------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Case:
    # Row label.
    name: str
    # A scene of the catalogue (`lgnn.scene`: built-in or hard case) or a scene file.
    scene: str
    # An engine of `lgnn.engines.ENGINES`, or a learned model: "gns-untrained" or
    # "gns-bad" (BAD_MODEL_SCALE).
    engine: str = "lagrangian"
    # "rollout" or "acceleration" (module docstring).
    kind: str = "rollout"
    # Integration of the Lagrangian engine and models (the MuJoCo engines: RK4 always).
    integrator: str = "rk4"
    # 1e-3 keeps the 10 s runs of chain100 and T1-T3 within minutes on a laptop CPU
    # (RK4 error at 1e-3 over 0.1 s is ~1e-11 on chains, 1e-6 on T1: results/).
    dt: float = 1e-3
    frame_dt: float = 1e-2
    duration: float = 10.0
    project: bool = True
    # A finished run beyond these is a silent failure: relative energy drift, and the
    # link-length/pin error (acceleration cases: the acceleration-level residual).
    max_drift: float = 1e-2
    max_violation: float = 1e-6
    # Acceleration cases: largest allowed difference from the reference accelerations.
    max_accel_error: float = 1e-8
    # Acceleration cases: the reference is exactly zero (a rigid, fully pinned structure).
    expect_rest: bool = False

    @property
    def simulation(self) -> SimulationConfig:
        return SimulationConfig(self.dt, self.frame_dt, self.duration)

    @property
    def integration(self) -> Integration:
        return Integration(self.integrator, self.project)


@dataclasses.dataclass(frozen=True)
class StabilitySettings:
    # Horizon of chain100 and T1-T3 (s).
    long_horizon: float = 10.0
    # Horizon of the large-step runs on chain4/chain16 (s).
    large_step_horizon: float = 10.0
    # Horizon of the 1000-link chain (s); its RK4 step costs ~3 s on a 2-core CPU.
    chain1000_horizon: float = 0.1
    # Horizon of the learned-model rollouts (s).
    model_horizon: float = 10.0
    # Horizon of the near-singular rollouts (s).
    singular_horizon: float = 1.0
    # Chains whose cost per step is measured.
    cost_sizes: tuple[int, ...] = (4, 16, 100, 1000)


def cases(settings: StabilitySettings = StabilitySettings()) -> tuple[Case, ...]:
    """Every hard case, in report order."""
    out = []
    for scene in ("chain100", "T1", "T2", "T3"):
        out.append(Case(f"long-{scene}", scene, "lagrangian", duration=settings.long_horizon))
        for dt in (1e-3, 1e-4):
            out.append(Case(f"long-{scene}", scene, "mujoco", dt=dt, duration=settings.long_horizon))
    # 10 RK4 steps of 1e-2 (the chain barely moves in 0.1 s; each step costs seconds).
    out.append(Case("chain1000", "chain1000", "lagrangian", dt=1e-2, frame_dt=1e-2, duration=settings.chain1000_horizon))
    out.append(Case("chain1000", "chain1000", "mujoco", dt=1e-3, frame_dt=1e-2, duration=settings.chain1000_horizon))
    for scene in ("chain4", "chain16"):
        for integrator in ("rk4", "verlet"):
            for dt in (1e-2, 5e-3):
                for project in (True, False):
                    out.append(Case(f"large-step{'' if project else '-noproj'}", scene, "lagrangian", integrator=integrator, dt=dt,
                                    duration=settings.large_step_horizon, project=project, max_drift=5e-2, max_violation=1e-6 if project else 1e-2))
        for dt in (1e-2, 5e-3):
            out.append(Case("large-step", scene, "mujoco", dt=dt, duration=settings.large_step_horizon, max_drift=5e-2))
    for scene in ("taut4-0.999", "taut4-exact", "folded4"):
        out.append(Case("near-singular", scene, kind="acceleration"))
        out.append(Case("near-singular", scene, "lagrangian", dt=1e-4, duration=settings.singular_horizon))
    out.append(Case("redundant", "pinned-triangle", kind="acceleration", expect_rest=True))
    out.append(Case("redundant", "pinned-triangle", "lagrangian", dt=1e-3, duration=settings.singular_horizon))
    out.append(Case("redundant", "T3", kind="acceleration"))
    for engine in ("gns-untrained", "gns-bad"):
        out.append(Case("learned", "chain4", engine, duration=settings.model_horizon))
    return tuple(out)


# ---------------------------------------------------------------------------------
# Running a case
# ---------------------------------------------------------------------------------


def _row(case: Case, **values) -> dict:
    row = dict(case=case.name, scene=case.scene, engine=case.engine, integrator=case.integrator if case.kind == "rollout" else "",
               dt=case.dt if case.kind == "rollout" else math.nan, duration=case.duration if case.kind == "rollout" else math.nan,
               status="ok", time_to_failure=math.nan, max_constraint_violation=math.nan, energy_drift=math.nan,
               accel_error=math.nan, step_s=math.nan, wall_s=math.nan, message="")
    row.update(values)
    return row


def bad_model_checkpoint(path: str | Path, scene: Scene, scale: float) -> Path:
    """Write a GNS checkpoint of untrained parameters times `scale` (the file `lgnn
    rollout --model` reads)."""
    from lgnn.learn import models, protocol, train

    model = models.ModelConfig.for_scene("gns", scene)
    config = protocol.TrainConfig(seed=SEED)
    state = train.initial_state(model, config)
    params = jax.tree.map(lambda x: x * scale, state.params)
    state = state._replace(params=params, best_params=params)
    train.save_checkpoint(path, state, model, config)
    return Path(path)


def _trajectory(case: Case, scene: Scene) -> Trajectory:
    config = case.simulation
    if case.engine in ("gns-untrained", "gns-bad"):
        from lgnn.learn import models
        from lgnn.learn.checkpoints import load_model

        with tempfile.TemporaryDirectory() as tmp:
            path = bad_model_checkpoint(Path(tmp) / "gns.npz", scene, 1.0 if case.engine == "gns-untrained" else BAD_MODEL_SCALE)
            model, params = load_model(path)
        return models.rollout(model, params, scene, config, integration=case.integration)
    # The default integration is every engine's own; another is the Lagrangian engine's
    # (a MuJoCo engine refuses it).
    integration = None if case.integration == Integration() else case.integration
    return get_engine(case.engine, integration=integration).rollout(scene, config, batch_of_one(scene.initial_state)).member(0)


def _run_rollout(case: Case, scene: Scene) -> dict:
    start = time.perf_counter()
    try:
        traj = _trajectory(case, scene)
    except SimulationError as err:
        partial = err.trajectory
        values = dict(status="detected", message=str(err), time_to_failure=err.time if err.time is not None else math.nan)
        if partial is not None:
            values.update(energy_drift=metrics.energy_drift(scene, partial), max_constraint_violation=metrics.max_constraint_violation(scene, partial.q))
        return _row(case, wall_s=time.perf_counter() - start, **values)
    wall = time.perf_counter() - start
    drift, violation = metrics.energy_drift(scene, traj), metrics.max_constraint_violation(scene, traj.q)
    problems = []
    if not drift <= case.max_drift:
        problems.append(f"energy drift {drift:.2g} > {case.max_drift:g}")
    if not violation <= case.max_violation:
        problems.append(f"constraint violation {violation:.2g} > {case.max_violation:g}")
    status = "silent" if problems else "ok"
    message = ("finished without error, but " + " and ".join(problems)) if problems else ""
    return _row(case, status=status, message=message, energy_drift=drift, max_constraint_violation=violation, wall_s=wall)


def acceleration_residual(scene: Scene, q, qd, qdd) -> float:
    """Largest `|d^2/dt^2 (|r_i - r_j|^2) / 2l|` over every link (redundant ones included)
    and `|qdd|` over pinned nodes: zero for accelerations that keep every constraint."""
    q, qd, qdd = (np.asarray(a, np.float64) for a in (q, qd, qdd))
    i, j = scene.edge_index.T
    dq, dqd, dqdd = q[i] - q[j], qd[i] - qd[j], qdd[i] - qdd[j]
    residual = np.abs(np.sum(dq * dqdd, -1) + np.sum(dqd * dqd, -1)) / scene.lengths
    pins = np.abs(qdd[list(scene.pinned)]).max() if scene.pinned else 0.0
    return float(max(residual.max(), pins))


def _run_acceleration(case: Case, scene: Scene) -> dict:
    start = time.perf_counter()
    q, qd = jnp.asarray(scene.nodes), jnp.asarray(scene.velocities)
    qdd = np.asarray(jax.jit(physics.true_acceleration_fn(scene))(q, qd))
    if case.expect_rest:
        reference, what = np.zeros_like(qdd), "zero (rigid structure)"
    else:
        constant_mass = physics.acceleration_fn(scene, physics.constant_mass_lagrangian_fn(scene), physics.dissipative_force_fn(scene))
        reference, what = np.asarray(jax.jit(constant_mass)(q, qd)), "the constant-mass Lagrangian's"
    finite = bool(np.isfinite(qdd).all())
    error = float(np.max(np.abs(qdd - reference))) if finite else math.inf
    residual = acceleration_residual(scene, q, qd, qdd) if finite else math.inf
    problems = []
    if not finite:
        problems.append("non-finite accelerations")
    if not error <= case.max_accel_error:
        problems.append(f"accelerations differ from {what} by {error:.2g} > {case.max_accel_error:g}")
    if not residual <= case.max_violation:
        problems.append(f"acceleration-level constraint residual {residual:.2g} > {case.max_violation:g}")
    message = "; ".join(problems) if problems else f"max |qdd| {np.abs(qdd).max():.3g}, equal to {what} within {error:.1e}"
    return _row(case, status="silent" if problems else "ok", message=message, accel_error=error,
                max_constraint_violation=residual, wall_s=time.perf_counter() - start)


def run_case(case: Case) -> dict:
    """One tidy row (module docstring)."""
    scene = get_scene(case.scene)
    return _run_acceleration(case, scene) if case.kind == "acceleration" else _run_rollout(case, scene)


def run(selected: tuple[Case, ...], log: Callable[[str], None] = lambda line: None) -> list[dict]:
    rows = []
    for case in selected:
        row = run_case(case)
        log(f"{row['case']:20s} {row['scene']:16s} {row['engine']:14s} {row['integrator']:6s} dt {row['dt']:<8.3g} "
            f"{row['status']:8s} {row['wall_s']:6.1f} s {row['message']}")
        rows.append(row)
    return rows


# ---------------------------------------------------------------------------------
# Cost per step
# ---------------------------------------------------------------------------------


def step_cost(n_links: int, steps: int = 3) -> float:
    """Seconds per RK4 step (with projection) of the ground truth on an n-link chain,
    compile excluded: the second of two runs of `steps` steps."""
    scene = chain(n_links, SEED)
    config = SimulationConfig(1e-3, 1e-3, steps * 1e-3)
    _, run_s, _ = get_engine("lagrangian").timed_rollout(scene, config, batch_of_one(scene.initial_state))
    return run_s / steps


def cost_rows(sizes=(4, 16, 100, 1000), log: Callable[[str], None] = lambda line: None) -> tuple[list[dict], float]:
    """Rows of seconds per step for each chain size, and the fitted exponent `p` of
    `cost ~ n^p` (least squares of log cost on log n)."""
    rows = []
    for n in sizes:
        start = time.perf_counter()
        cost = step_cost(n, steps=2 if n >= 500 else 20)
        case = Case("cost-per-step", f"chain{n}", dt=1e-3, duration=math.nan)
        rows.append(_row(case, step_s=cost, wall_s=time.perf_counter() - start, duration=math.nan))
        log(f"cost chain{n}: {cost:.3g} s/step")
    exponent = fit_exponent(dict(zip(sizes, (r["step_s"] for r in rows)))) if len(sizes) > 1 else math.nan
    return rows, exponent


def fit_exponent(costs: dict[int, float]) -> float:
    """`p` of `cost ~ n^p` from `{n: cost}`: least squares of log cost on log n."""
    sizes = sorted(costs)
    return float(np.polyfit(np.log(sizes), np.log([costs[n] for n in sizes]), 1)[0])


# ---------------------------------------------------------------------------------
# Report
# ---------------------------------------------------------------------------------


def _cell(value) -> str:
    if isinstance(value, float):
        return "" if math.isnan(value) else f"{value:.3g}"
    return str(value).replace("|", "/")


def _csv_cell(value):
    return repr(value) if isinstance(value, float) else value


def write_report(rows: list[dict], md_path: str | Path, command: str, exponent: float, notes=()) -> Path:
    """`md_path` and the CSV beside it (same stem), atomically, with provenance."""
    from lgnn.bench.tables import write_table
    from lgnn.files import check_writable
    from lgnn.provenance import environment

    md_path = check_writable(md_path)
    csv_path = md_path.with_suffix(".csv")
    env = environment()
    header = [f"command: {command}", f"commit: {env['commit']}", f"machine: {env['device']}", f"versions: {env['versions']}",
              f"seed: {SEED} (chain shapes, model parameters)"]
    counts = {s: sum(r["status"] == s for r in rows if r["case"] != "cost-per-step") for s in STATUSES}
    outcome = (f"outcome: {counts['ok']} ok, {counts['detected']} detected failures, {counts['silent']} silent failures",
               f"cost per RK4 step of the ground truth grows like n^{exponent:.2f} over n = "
               + ", ".join(r["scene"].removeprefix("chain") for r in rows if r["case"] == "cost-per-step") + " links")
    write_table(rows, COLUMNS, csv_path, md_path, "Stability on hard cases", header, tuple(notes) + outcome, csv_cell=_csv_cell, markdown_cell=_cell)
    return csv_path


NOTES = (
    "status: ok = finished within the case's tolerances; detected = stopped with a one-line SimulationError at the first "
    "non-finite or exploding frame (time_to_failure; columns describe the frames before it); silent = finished without "
    "complaint but outside the tolerances",
    "energy_drift = max |E - E0| / energy scale of the true energy (lgnn.metrics: mass x (g size + v0^2 + size^2)); max_constraint_violation = largest link-length/pin error over "
    "the frames (acceleration cases: acceleration-level residual over every link, redundant ones included); accel_error = "
    "largest difference from the reference accelerations; step_s = seconds per RK4 step with projection, compile excluded",
    "tolerances: drift 1e-2 (large steps 5e-2), violation 1e-6 (without projection 1e-2), accelerations 1e-8",
)
