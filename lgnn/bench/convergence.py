"""Convergence in dt of the Lagrangian reference: how wrong is the ground truth itself?

`reference_convergence(scene, config, halvings)` integrates the scene from its initial
state at `config.dt`, `dt/2`, ..., `dt/2^halvings` (same frames, same horizon
`config.duration`) with `lgnn.engines.lagrangian.simulate` and returns one tidy row
per step size:

    scene, integrator, horizon, dt, steps, difference, order, error_estimate, verdict,
    energy_drift, energy_change, wall_s, note

- `difference`: the largest distance of a node between this run and the run at half
  its step, over every saved frame (NaN for the last run);
- `order`: the observed order `log2(difference / next difference)` (NaN where the
  next difference does not exist);
- `error_estimate` and `verdict` (`assess`): Richardson's estimate of this run's
  error, `difference / (2^order - 1)`, where the differences shrink at a sane, steady
  order (`asymptotic`: the integrator's order, or `low-order`: slower but steady, at
  least `MIN_ORDER`); the difference itself where it is at round-off (`round-off`:
  both runs agree to round-off) or the next one is (`resolved`); and the raw
  difference, flagged, where they do not shrink at a sane, steady order
  (`not-converged`: the raw difference is then a lower bound on the error) or a run
  diverged (`diverged`);
- `relative_difference`, `relative_estimate`: the same in the benchmark's metric
  (`lgnn.metrics.relative_error` of all node positions, max over frames), the estimate
  scaled from the difference by the same factor, to set beside the models' errors;
- `displacement`: the largest distance of a node from its initial position over the
  run (on a structure whose exact motion is rest, the reference's error itself);
- `energy_drift`: `lgnn.metrics.energy_drift` of the run (max |E - E0| / energy
  scale), `energy_change`: its signed last-frame change (E(T) - E0) / energy scale
  (a loss at every step size is a dissipative scheme, not round-off).

`summary(rows)` gives one line per scene: the estimate and verdict at the step the
benchmark uses. The `lgnn convergence` command writes the rows with `write_table`.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Callable, Sequence

import numpy as np

from lgnn import metrics
from lgnn.engines.base import Integration, SimulationConfig, Trajectory
from lgnn.engines.lagrangian import simulate
from lgnn.errors import SimulationError
from lgnn.scene import Scene, is_pinned_chain

COLUMNS = ("scene", "integrator", "horizon", "dt", "steps", "difference", "order", "error_estimate", "verdict",
           "relative_difference", "relative_estimate", "displacement", "energy_drift", "energy_change", "wall_s", "note")
VERDICTS = ("asymptotic", "low-order", "round-off", "resolved", "unassessed", "not-converged", "diverged")
# Verdicts whose error estimate a reader can trust as an estimate (not a lower bound).
TRUSTED = ("asymptotic", "low-order", "round-off", "resolved")
# Classical orders of the integrators (tests/test_integrate.py::test_convergence_order).
INTEGRATOR_ORDERS = {"rk4": 4, "verlet": 2}
# An observed order within this of the integrator's is "asymptotic".
ORDER_TOLERANCE = 0.6
# Below this observed order, or when successive orders differ by more than
# `ORDER_STEADINESS`, the differences do not behave like a power of dt and Richardson's
# estimate (which sums their geometric series) is not trusted: the raw difference is
# reported, flagged. (At order 0.5 the estimate is 2.4 x the difference.)
MIN_ORDER = 0.5
ORDER_STEADINESS = 0.5
# Differences below this many multiples of (double-precision epsilon x the structure's
# size x sqrt(steps of the finer run)) are round-off: a random walk of one rounding per
# step (measured on chain4 over 1 s: 4e-14 and 7e-14 between dt 1e-4, 5e-5 and 2.5e-5,
# whose floors are 6e-13 and 9e-13; the truncation error between 5e-4 and 2.5e-4,
# 6e-13 at order 3.96, stays above its floor of 4e-13).
ROUNDOFF_FACTOR = 3.0


# Formulations proposed in place of the self-stressed T2 and T3 (catalogue.slackened),
# measured beside the built-ins by default.
PROPOSED_SCENES = ("T2-slack", "T3-slack")
# Simulated seconds: 1 s on small pinned chains; 0.1 s on longer chains and on the
# structures (T1-T3: dense solves), where 8 x the benchmark's steps over 1 s would take
# most of an hour on a CPU.
HORIZON = 1.0
SHORT_HORIZON = 0.1
SMALL_CHAIN_LINKS = 16


def default_horizon(scene: Scene) -> float:
    return HORIZON if is_pinned_chain(scene) and scene.n_links <= SMALL_CHAIN_LINKS else SHORT_HORIZON


@dataclasses.dataclass(frozen=True)
class Assessment:
    order: float
    error_estimate: float
    verdict: str
    note: str = ""


def roundoff_floor(scene: Scene, steps: int) -> float:
    """The node distance two runs of `steps` steps can differ by from rounding alone."""
    return ROUNDOFF_FACTOR * np.finfo(np.float64).eps * metrics.structure_size(scene, scene.nodes) * math.sqrt(steps)


def assess(differences: Sequence[float], floors: Sequence[float], integrator_order: int) -> list[Assessment]:
    """Order, error estimate and verdict of each run but the last from the successive
    `differences` d_k between run k and run k+1 (step halved) and their round-off
    `floors` (module docstring). NaN differences mean a run diverged."""
    out = []
    for k, d in enumerate(differences):
        nxt = differences[k + 1] if k + 1 < len(differences) else math.nan
        order = math.log2(d / nxt) if d > 0 and nxt > 0 else math.nan
        if not math.isfinite(d):
            out.append(Assessment(math.nan, math.nan, "diverged", "a run diverged or is missing"))
        elif d <= floors[k]:
            out.append(Assessment(order, d, "round-off", f"difference at round-off (floor {floors[k]:.1e})"))
        elif math.isfinite(nxt) and nxt <= floors[k + 1]:
            out.append(Assessment(order, d, "resolved", "the next halving is at round-off"))
        elif not math.isfinite(nxt):
            # The last difference: no order of its own; the previous one's, if it was steady.
            previous = out[-1] if out else None
            if previous is not None and previous.verdict in ("asymptotic", "low-order"):
                out.append(Assessment(math.nan, d / (2.0**previous.order - 1.0), previous.verdict, "at the previous halving's order"))
            else:
                out.append(Assessment(math.nan, d, "unassessed", "no order (last halving): raw difference"))
        else:
            following = differences[k + 2] if k + 2 < len(differences) else math.nan
            # The next order, where the difference after next is above round-off.
            next_order = math.log2(nxt / following) if math.isfinite(following) and following > floors[k + 2] else math.nan
            steady = not math.isfinite(next_order) or abs(order - next_order) <= ORDER_STEADINESS
            if order >= MIN_ORDER and steady:
                verdict = "asymptotic" if abs(order - integrator_order) <= ORDER_TOLERANCE else "low-order"
                note = "" if verdict == "asymptotic" else f"order {order:.2f}, the integrator's is {integrator_order}"
                out.append(Assessment(order, d / (2.0**order - 1.0), verdict, note))
            else:
                why = f"order {order:.2f}" + ("" if steady else f" then {next_order:.2f}")
                out.append(Assessment(order, d, "not-converged", f"{why} (integrator: {integrator_order}): raw difference, a lower bound on the error"))
    return out


@dataclasses.dataclass(frozen=True)
class Rigidity:
    """First- and second-order rigidity of a scene at its initial configuration.

    `flexes`: motions of the free nodes that keep every link length to first order
    (the null space of the constraint Jacobian); `self_stresses`: link tensions in
    equilibrium with no load (its left null space), where the inextensible model is
    singular; `unresisted`: flexes that no self-stress resists at second order (`v`
    with `V^T Omega(w) V v = 0` for every self-stress `w`, `Omega` the stress matrix):
    a mechanism that can move. `prestress_stable`: a single self-stress whose stress
    matrix is definite on every flex, which makes the structure rigid (the only motion
    of the inextensible model is rest, whatever the load); None where several
    self-stresses leave it undecided.
    """

    flexes: int
    self_stresses: int
    unresisted: int
    prestress_stable: bool | None

    def describe(self) -> str:
        if self.self_stresses == 0:
            return ""
        text = (f"singular at rest: {self.self_stresses} self-stress(es), {self.flexes} first-order flexes of which "
                f"{self.unresisted} no self-stress resists")
        if self.prestress_stable:
            text += "; prestress-stable, so rigid: the exact motion of the inextensible model is rest and the displacement is the reference's error"
        return text


def rigidity(scene: Scene) -> Rigidity:
    """`Rigidity` of `scene` at its initial configuration (NumPy SVDs; free nodes only,
    links between two pinned nodes left out)."""
    import scipy.linalg

    q, (n, d) = np.asarray(scene.nodes, np.float64), (scene.n_nodes, scene.dim)
    pinned = set(scene.pinned)
    free = np.flatnonzero(np.repeat([k not in pinned for k in range(n)], d))
    links = [(int(i), int(j)) for i, j in scene.edge_index if not (i in pinned and j in pinned)]
    jac = np.zeros((len(links), n * d))
    for row, (i, j) in enumerate(links):
        unit = (q[i] - q[j]) / np.linalg.norm(q[i] - q[j])
        jac[row, i * d:(i + 1) * d] += unit
        jac[row, j * d:(j + 1) * d] -= unit
    jac = jac[:, free]
    flexes = scipy.linalg.null_space(jac)
    stresses = scipy.linalg.null_space(jac.T)

    def stress_matrix(w):
        omega = np.zeros((n, n))
        for wk, (i, j) in zip(w, links):
            coefficient = wk / np.linalg.norm(q[i] - q[j])
            omega[i, i] += coefficient
            omega[j, j] += coefficient
            omega[i, j] -= coefficient
            omega[j, i] -= coefficient
        return flexes.T @ np.kron(omega, np.eye(d))[np.ix_(free, free)] @ flexes

    blocks = [stress_matrix(w) for w in stresses.T]
    if not blocks or flexes.shape[1] == 0:
        return Rigidity(flexes.shape[1], stresses.shape[1], flexes.shape[1] if not blocks else 0, None)
    singular_values = np.linalg.svd(np.vstack(blocks), compute_uv=False)
    unresisted = int(np.sum(singular_values < 1e-9 * singular_values.max()))
    stable = None
    if len(blocks) == 1:
        eigenvalues = np.linalg.eigvalsh(blocks[0])
        scale = np.abs(eigenvalues).max()
        stable = bool(eigenvalues.min() > 1e-9 * scale or eigenvalues.max() < -1e-9 * scale)
    return Rigidity(flexes.shape[1], stresses.shape[1], unresisted, stable)


def _node_distance(a: Trajectory, b: Trajectory) -> float:
    if a is None or b is None:
        return math.nan
    return float(np.max(np.linalg.norm(a.q - b.q, axis=-1)))


def _relative_difference(a: Trajectory, b: Trajectory) -> float:
    if a is None or b is None:
        return math.nan
    return float(np.max(metrics.relative_error(a.q, b.q, 2)[1:]))


def reference_convergence(scene: Scene, config: SimulationConfig, halvings: int = 3,
                          log: Callable[[str], None] = lambda line: None, integration: Integration = Integration()) -> list[dict]:
    """Rows (module docstring) of `halvings + 1` runs from the scene's initial state at
    `config.dt / 2^k`, k = 0..halvings, frames every `config.frame_dt` over
    `config.duration`, integrated by `integration`."""
    if halvings < 1:
        raise ValueError(f"halvings must be at least 1, got {halvings}")
    runs, rows = [], []
    for k in range(halvings + 1):
        run_config = dataclasses.replace(config, dt=config.dt / 2**k)
        start = time.perf_counter()
        note = ""
        try:
            trajectory = simulate(scene, run_config, integration=integration)
        except SimulationError as err:
            trajectory, note = None, str(err)
        wall = time.perf_counter() - start
        runs.append(trajectory)
        steps = round(config.duration / run_config.dt)
        scale = metrics.energy_scale(scene, scene.initial_state)
        drift = metrics.energy_drift(scene, trajectory) if trajectory is not None else math.nan
        change = float(trajectory.energy[-1] - trajectory.energy[0]) / scale if trajectory is not None else math.nan
        displacement = float(np.max(np.linalg.norm(trajectory.q - trajectory.q[0], axis=-1))) if trajectory is not None else math.nan
        rows.append(dict(scene=scene.name, integrator=integration.integrator, horizon=config.duration, dt=run_config.dt, steps=steps,
                         displacement=displacement, energy_drift=drift, energy_change=change, wall_s=wall, note=note))
        log(f"{scene.name} dt {run_config.dt:.4g}: {steps} steps in {wall:.1f} s, energy drift {drift:.2e}{' ' + note if note else ''}")
    rows[0]["note"] = "; ".join(n for n in (rigidity(scene).describe(), rows[0]["note"]) if n)
    differences = [_node_distance(a, b) for a, b in zip(runs, runs[1:])]
    floors = [roundoff_floor(scene, row["steps"]) for row in rows[1:]]
    assessments = assess(differences, floors, INTEGRATOR_ORDERS[integration.integrator])
    relative = [_relative_difference(a, b) for a, b in zip(runs, runs[1:])] + [math.nan]
    for row, d, r, a in zip(rows, differences + [math.nan], relative, assessments + [None]):
        estimate = a.error_estimate if a else math.nan
        row.update(difference=d, order=a.order if a else math.nan, error_estimate=estimate, relative_difference=r,
                   relative_estimate=r * estimate / d if d > 0 else math.nan,
                   verdict=a.verdict if a else "", note="; ".join(n for n in (row["note"], a.note if a else "") if n))
    return rows


def _ranking(row: dict) -> str:
    if "prestress-stable" in row["note"]:
        return (f"; NOT RANKABLE as dynamics: the exact motion is rest, so a model that never moves is exact, and the reference "
                f"itself moves {row['displacement']:.2g} from rest")
    if row["verdict"] == "diverged":
        return "; NOT RANKABLE: a reference run diverged"
    if row["verdict"] not in TRUSTED:
        return "; NOT RANKABLE: the reference's error at the benchmark's step is unknown (only bounded below)"
    return ""


def unrankable(rows: Sequence[dict]) -> dict[str, str]:
    """`{scene: why}` for the scenes whose reference cannot rank models at the
    benchmark's step (the first, coarsest row of each scene; `rows` as `reference_convergence`
    gives them or as read back from the CSV, numbers as text)."""
    found = {}
    for row in rows:
        if row["scene"] not in found:
            found[row["scene"]] = _ranking({**row, "displacement": float(row["displacement"])}).removeprefix("; NOT RANKABLE").lstrip(": ")
    return {scene: why for scene, why in found.items() if why}


def summary(rows: Sequence[dict]) -> list[str]:
    """One line per scene: the estimated error and verdict of its first (coarsest: the
    benchmark's) step."""
    lines, seen = [], set()
    for row in rows:
        if row["scene"] in seen:
            continue
        seen.add(row["scene"])
        bound = "" if row["verdict"] in TRUSTED else " (a lower bound)"
        singular = f" ({row['note'].split(';')[0]})" if row["note"].startswith("singular") else ""
        lines.append(f"{row['scene']}{singular}: error of the reference at dt {row['dt']:g} over {row['horizon']:g} s ~ "
                     f"{row['error_estimate']:.2g}{bound} (relative {row['relative_estimate']:.2g}), observed order {row['order']:.2f}: "
                     f"{row['verdict']}{_ranking(row)}")
    return lines


NOTES = (
    "each scene is integrated from its own initial state with the Lagrangian engine (lgnn.engines.lagrangian.simulate: "
    "the benchmark's integrator, with projection) at dt / 2^k, k = 0 .. halvings; dt is the full benchmark's step for the scene "
    "(EvaluateSettings.simulation); frames every 1e-3 s",
    "difference = max over frames and nodes of the node distance to the run at half the step; order = log2(difference / next "
    "difference); error_estimate = Richardson, difference / (2^order - 1), where the order is sane and steady",
    "verdict: asymptotic = the integrator's order (within 0.6); low-order = a steady order >= 0.5 below it (estimate "
    "still Richardson); round-off = the difference is at round-off (3 eps x size x sqrt(steps)); resolved = the next "
    "difference is; unassessed = no order to judge by; not-converged = the differences do not shrink at a sane, steady "
    "order: error_estimate is the raw difference, a lower bound; diverged = a run stopped (lgnn.metrics divergence rule)",
    "relative_difference, relative_estimate: the same in the benchmark's metric (||a - b|| / (||a|| + ||b||) over all "
    "nodes, max over frames), to compare with the models' rollout errors",
    "displacement = max node distance from the initial state over the run",
    "energy_drift = max |E - E0| / energy scale (lgnn.metrics.energy_drift); energy_change = (E(T) - E0) / energy scale, signed",
)


# The files `lgnn convergence` writes into its output folder, and the report reads
# beside its own (`load_unrankable`).
TABLE_CSV, TABLE_MD = "convergence.csv", "convergence.md"


def load_unrankable(folder) -> dict[str, str]:
    """`unrankable` of the convergence table in `folder` (`TABLE_CSV`, written by `lgnn
    convergence`); `{}` where there is none."""
    from pathlib import Path

    from lgnn.bench.tables import read_table

    path = Path(folder) / TABLE_CSV
    return unrankable(read_table(path)[1]) if path.exists() else {}


def write_report(rows: Sequence[dict], csv_path, md_path, command: str, notes: Sequence[str] = ()) -> None:
    """The rows as CSV + markdown (`lgnn.bench.tables.write_table`) with the command and
    provenance (`lgnn.provenance.environment`), the notes and one summary line per scene."""
    from lgnn.bench.tables import write_table
    from lgnn.provenance import environment

    env = environment()
    header = [f"command: {command}", f"commit: {env['commit']}", f"machine: {env['device']}", f"versions: {env['versions']}",
              "seed: none (each scene's own initial state, deterministic)"]
    write_table(rows, COLUMNS, csv_path, md_path, "Convergence in dt of the Lagrangian reference", header,
                NOTES + tuple(notes) + tuple(summary(rows)))
