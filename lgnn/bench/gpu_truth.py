"""GPU ground truth: every engine on the same batches of initial states, one run per scene.

`measure(scene, settings)` runs, for each batch size, lgnn's Lagrangian engine in
float64 (the reference: `reference_spec()`, the registered engine whose
`EngineEntry.gpu_truth_role` is "reference") and the engines of `settings.engines`
(name:dtype, each an engine of `lgnn.engines.ENGINES` with a GPU-truth role; by
default every one in float32: the Lagrangian engine, MJX, MuJoCo Warp) from the same
`batch` initial states (`lgnn.physics.benchmark_initial_states`, seed
`settings.seed`: the paper's chain sampler, T1's own state) for `settings.steps` RK4
steps of `settings.dt`, each through its `Engine.timed_batch`, and returns tidy rows:

`scene, engine, dtype, form, batch, steps, steps_per_s, steps_per_s_min,
steps_per_s_max, compile_s, max_node_error, finite_worlds, note`

- speed: batch x steps / run time, the median of `repeats` timed runs after an untimed
  one (`Engine.timed_batch`; the Lagrangian engine, MJX and MuJoCo Warp:
  `lgnn.engines.timing.time_runs`), with their min and max; compile apart (JAX:
  the executable; MuJoCo Warp: its kernels and the CUDA graph of the steps);
  `form` is `settings.form` for an engine with MJCF forms, else "";
- error: max node position error after the last step against the float64 Lagrangian
  reference of the same batch; NaN when any world is non-finite, and `finite_worlds`
  says how many are finite (never a number made of the finite ones only).

A run that cannot be made (an engine not installed, a model an engine rejects, out of
device memory) is a row whose note says why, so one scene's table is never lost to one
engine. `write(rows, out_dir, scene, command)` writes `gpu_truth_<scene>.csv` and `.md`
(`lgnn.bench.tables`) with the command, machine, versions and commit
(`lgnn.provenance`).

`load(directory)` reads the tables back, and `against_mujoco(rows)` sets the float32
Lagrangian beside the fastest MuJoCo GPU engine (role "mujoco-gpu": MJX, MuJoCo Warp)
that is finite and agrees with the reference (`AGREEMENT_MAX`), per scene and batch,
with the ratio against issue 14's goal (`GOAL_RATIO`): the report's `performance.md`
section.

Precision (issue 14: "float32 on a GPU: chosen how?"): the process runs with JAX's
float64 on (`lgnn.configure()`), and an engine's precision is that of its inputs: a
float32 Lagrangian run is traced from float32 states, and its compiled program holds
no float64 operation (tests/test_gpu_truth.py checks the lowered text). Turning x64
off for it instead fails (the cached int64 index arrays meet int32 ones). MJX float32
traces under x64 off (`lgnn.engines.mjx.precision`, its own constants); MuJoCo Warp is
float32 only.
"""

from __future__ import annotations

import csv
import dataclasses
import statistics
from pathlib import Path

import numpy as np

from lgnn import physics, provenance
from lgnn.bench.tables import read_table, write_table
from lgnn.engines import DTYPES, ENGINES, get_engine, mjcf
from lgnn.engines.base import SimulationConfig
from lgnn.errors import ConfigError, LgnnError
from lgnn.scene import Scene, State

COLUMNS = ("scene", "engine", "dtype", "form", "batch", "steps", "steps_per_s", "steps_per_s_min", "steps_per_s_max",
           "compile_s", "max_node_error", "finite_worlds", "note")


def engine_names() -> list[str]:
    """The engines `lgnn gpu-truth` runs: every registered one with a GPU-truth role, in
    registry order."""
    return [name for name, entry in ENGINES.items() if entry.gpu_truth_role]


def reference_spec() -> str:
    """The reference, as name:dtype: the first registered engine whose role is
    "reference" (lgnn's Lagrangian engine), in float64."""
    return next(f"{name}:float64" for name, entry in ENGINES.items() if entry.gpu_truth_role == "reference")


def mujoco_gpu_engines() -> list[str]:
    """The engines `against_mujoco` sets beside lgnn's (role "mujoco-gpu": MJX, MuJoCo Warp)."""
    return [name for name, entry in ENGINES.items() if entry.gpu_truth_role == "mujoco-gpu"]


def _float32_engines() -> tuple[str, ...]:
    return tuple(spec for spec in (f"{name}:float32" for name in engine_names() if "float32" in ENGINES[name].dtypes) if spec != reference_spec())


@dataclasses.dataclass(frozen=True)
class GpuTruthSettings:
    # The scenes and batches (issue 14, item 5).
    scenes: tuple[str, ...] = ("chain4", "chain16", "chain100", "T1")
    batches: tuple[int, ...] = (1024, 8192, 65536)
    # Engines besides the float64 reference, as name:dtype (MuJoCo Warp: float32 only);
    # default: every engine with a GPU-truth role, in float32 (`engine_names`).
    engines: tuple[str, ...] = dataclasses.field(default_factory=_float32_engines)
    # The measured table: RK4 at dt 1e-3; 100 steps is 0.1 s of motion, enough
    # for float32 and soft loop closures to show their error.
    steps: int = 100
    dt: float = 1e-3
    # Timed runs per engine and batch (the spread); one untimed run comes before them.
    repeats: int = 3
    # MJCF form of the MuJoCo engines (`lgnn.engines.mjcf`).
    form: str = "nested"
    seed: int = 0

    def __post_init__(self):
        names = engine_names()
        for spec in self.engines:
            name, _, dtype = spec.partition(":")
            if name not in names or dtype not in DTYPES:
                raise ConfigError(f"--engines: {spec!r} is not name:dtype with name in {', '.join(names)} and dtype {' or '.join(sorted(DTYPES))}")
            entry = ENGINES[name]
            if dtype not in entry.dtypes:
                raise ConfigError(f"--engines: {entry.title} computes in {' and '.join(entry.dtypes)} only ({name}:{entry.dtypes[0]})")
        if min(self.batches, default=0) < 1 or self.steps < 1 or self.repeats < 1 or not self.dt > 0:
            raise ConfigError("batches, steps and repeats must be positive whole numbers and dt positive")
        # Checked here, not when the first MuJoCo engine renders its MJCF, after the
        # Lagrangian runs of the first batch.
        mjcf.check_form(self.form)

    @property
    def config(self) -> SimulationConfig:
        """One frame after `steps` steps: only the final state is compared."""
        duration = self.steps * self.dt
        return SimulationConfig(dt=self.dt, frame_dt=duration, duration=duration)


def _run(spec: str, scene: Scene, config: SimulationConfig, states: State, settings: GpuTruthSettings):
    """`(compile_s, run_s list, final q (B, N, dim))` of engine `spec` (name:dtype):
    its `Engine.timed_batch`, a MuJoCo engine in `settings.form`."""
    name, _, dtype = spec.partition(":")
    engine = get_engine(name, dtype=dtype, form=settings.form if ENGINES[name].forms else None)
    return engine.timed_batch(scene, config, states, settings.repeats)


def _out_of_memory(err: Exception) -> bool:
    # XLA's and CUDA's allocation failures are runtime errors of their own types; they
    # are told apart by their messages.
    text = str(err)
    return any(mark in text for mark in ("RESOURCE_EXHAUSTED", "out of memory", "Failed to allocate"))


def measure(scene: Scene, settings: GpuTruthSettings, log=print) -> list[dict]:
    """Tidy rows of every engine and batch on `scene` (module docstring)."""
    config = settings.config
    all_states = physics.benchmark_initial_states(scene, max(settings.batches), settings.seed)
    rows, reference_run = [], reference_spec()
    for batch in settings.batches:
        states = State(all_states.q[:batch], all_states.qd[:batch])
        reference = None
        for spec in (reference_run,) + tuple(s for s in settings.engines if s != reference_run):
            name, _, dtype = spec.partition(":")
            row = dict(scene=scene.name, engine=name, dtype=dtype, form=settings.form if ENGINES[name].forms else "",
                       batch=batch, steps=settings.steps, steps_per_s=float("nan"), steps_per_s_min=float("nan"),
                       steps_per_s_max=float("nan"), compile_s=float("nan"), max_node_error=float("nan"), finite_worlds=0, note="")
            try:
                compile_s, run_s, q = _run(spec, scene, config, states, settings)
            except LgnnError as err:
                row["note"] = f"not run: {err}"
            except Exception as err:  # noqa: BLE001 (only allocation failures are a row)
                if not _out_of_memory(err):
                    raise
                row["note"] = "not run: out of device memory"
            else:
                speeds = [batch * settings.steps / s for s in run_s]
                finite = np.isfinite(q).all(axis=(1, 2))
                row.update(steps_per_s=statistics.median(speeds), steps_per_s_min=min(speeds), steps_per_s_max=max(speeds),
                           compile_s=compile_s, finite_worlds=int(finite.sum()))
                if spec == reference_run:
                    reference = q if finite.all() else None
                    row["max_node_error"] = 0.0 if finite.all() else float("nan")
                    row["note"] = "reference" if finite.all() else "reference non-finite: no errors for this batch"
                elif not finite.all():
                    row["note"] = f"non-finite in {batch - int(finite.sum())} of {batch} worlds"
                elif reference is None:
                    row["note"] = "no float64 reference for this batch"
                else:
                    row["max_node_error"] = float(np.max(np.abs(q - reference)))
            rows.append(row)
            log(f"{scene.name} {spec} batch {batch}: {row['steps_per_s']:.3g} steps/s ({row['steps_per_s_min']:.3g}..{row['steps_per_s_max']:.3g}), "
                f"compile {row['compile_s']:.1f} s, error {row['max_node_error']:.2e} {row['note']}".rstrip())
    return rows


def header(command: str) -> list[str]:
    """Provenance lines: command, machine, versions (MuJoCo Warp's when installed), commit."""
    from lgnn.engines import mjwarp

    versions = provenance.versions() + (f", {mjwarp.versions()}" if mjwarp.available() else ", mujoco-warp absent")
    return [f"command: {command}", f"machine: {provenance.device()}", f"versions: {versions}", f"commit: {provenance.commit()}"]


NOTES = (
    "steps/s: batch x steps / run time, median of the timed runs (min..max beside it), compile apart; RK4",
    "error: max node position error after the last step against lgnn's Lagrangian engine in float64 from the same initial "
    "states; NaN where any world is non-finite (finite_worlds counts the finite ones)",
    "precision: JAX engines run in the dtype of their inputs with x64 on (no float64 operation in a float32 program); "
    "MuJoCo Warp is float32 only",
)


def _settings_line(settings: GpuTruthSettings) -> str:
    return f"settings: steps {settings.steps}, dt {settings.dt:g}, repeats {settings.repeats}, form {settings.form}, seed {settings.seed}"


def write(rows: list[dict], out_dir, name: str, command: str, settings: GpuTruthSettings) -> str:
    """`gpu_truth_<name>.csv` and `.md` in `out_dir` (`name`: the scene's, and a suffix
    where one scene's engines are split over calls); returns the markdown path. The
    CSV's header holds the settings too, for `measured_before`."""
    stem = f"{out_dir}/gpu_truth_{name}"
    write_table(rows, COLUMNS, f"{stem}.csv", f"{stem}.md", f"GPU ground truth: {name}", header(command) + [_settings_line(settings)], NOTES)
    return f"{stem}.md"


def measured_before(out_dir, name: str, settings: GpuTruthSettings) -> bool:
    """Whether `out_dir` already holds `name`'s table (`write`, both files) made by a run
    like this one: the same settings, engines and batches, on this machine with these
    versions at this commit. A command cut short by a time limit then resumes with the
    scenes it had not written; anything else (an older table, another machine, a file
    that does not parse) is measured again."""
    stem = Path(out_dir) / f"gpu_truth_{name}"
    if not (stem.with_suffix(".csv").is_file() and stem.with_suffix(".md").is_file()):
        return False
    wanted = header("")[1:] + [_settings_line(settings)]  # every provenance line but the command
    try:
        found, table = read_table(stem.with_suffix(".csv"))
        runs = {(row["engine"] + ":" + row["dtype"], int(row["batch"])) for row in table}
    except (OSError, UnicodeDecodeError, csv.Error, KeyError, TypeError, ValueError):
        return False
    expected = {(spec, batch) for spec in (reference_spec(),) + settings.engines for batch in settings.batches}
    return all(line in found for line in wanted) and runs == expected and len(table) == len(expected)


# ---------------------------------------------------------------------------------
# Reading the tables back: lgnn's float32 Lagrangian against the MuJoCo GPU engines
# ---------------------------------------------------------------------------------

# Issue 14's goal: lgnn's Lagrangian engine in float32 at least this many times the
# steps/s of the fastest MuJoCo GPU engine that stays finite (and agrees, below) on
# the same batch.
GOAL_RATIO = 1.5
# A MuJoCo GPU run counts as a ground truth only within this max node error (length
# units) of the float64 reference after the table's steps: finite is not enough (before
# a4de0f6, MuJoCo Warp's float32 chain16-3d ended 15 m off, finite). The float32 runs
# that work are within 6e-4 over 0.1 s (the tables in results/gpu/truth/).
AGREEMENT_MAX = 1e-3


def load(directory) -> list[dict]:
    """Every row of the `gpu_truth_*.csv` tables in `directory` (sorted by file name),
    numbers as numbers, each with `table`: its file's stem, and `machine`: its header's
    GPU (a folder can hold runs of several machines). [] when there are none."""
    import pandas as pd

    rows = []
    for path in sorted(Path(directory).glob("gpu_truth_*.csv")):
        frame = pd.read_csv(path, comment="#", keep_default_na=False, na_values=["nan"])
        missing = set(COLUMNS) - set(frame.columns)
        if missing:
            raise ConfigError(f"{path}: not a gpu-truth table (no column {', '.join(sorted(missing))})")
        machine = _header_machine(path)
        rows += [dict(row, table=path.stem, form=str(row["form"]), machine=machine) for row in frame.to_dict("records")]
    return rows


def _header_machine(path: Path) -> str:
    """The accelerator of a table's `machine: ...` header line (the part before `;`), "" without one."""
    machines = [line.removeprefix("machine:").split(";")[0].strip() for line in read_table(path)[0] if line.startswith("machine:")]
    return machines[0] if machines else ""


def _finite(row: dict) -> bool:
    return row["finite_worlds"] == row["batch"] and np.isfinite(row["steps_per_s"]) and np.isfinite(row["max_node_error"])


def _why_left_out(row: dict) -> str:
    if not _finite(row):
        return row["note"] or "non-finite"
    return f"{row['max_node_error']:.2g} from the reference (over {AGREEMENT_MAX:g})"


def against_mujoco(rows: list[dict]) -> list[dict]:
    """Per scene and batch (in the order met): the float32 Lagrangian against the fastest
    MuJoCo GPU engine finite in every world and within `AGREEMENT_MAX` of the reference.
    Rows `scene, batch, lagrangian_steps_per_s, lagrangian_error, mujoco_engine,
    mujoco_steps_per_s, mujoco_error, ratio, meets_goal, tables, machine, note`.

    Timings swing between sessions, so the Lagrangian row is taken from the MuJoCo
    row's own table (the same run) when that has one, else from another table of the
    scene (`tables` names both). `ratio` is NaN, and `note` says why, where either
    side has no such run; the MuJoCo runs left out (non-finite, not run, too far off) are named."""
    keys = dict.fromkeys((r["scene"], r["batch"]) for r in rows)
    lgnn_engine, mujoco_engines = reference_spec().partition(":")[0], mujoco_gpu_engines()
    out = []
    for scene, batch in keys:
        here = [r for r in rows if r["scene"] == scene and r["batch"] == batch]
        ours = [r for r in here if r["engine"] == lgnn_engine and r["dtype"] == "float32" and _finite(r)]
        theirs = [r for r in here if r["engine"] in mujoco_engines]
        agreeing = [r for r in theirs if _finite(r) and r["max_node_error"] <= AGREEMENT_MAX]
        best = max(agreeing, key=lambda r: r["steps_per_s"]) if agreeing else None
        if best is not None and any(r["table"] == best["table"] for r in ours):
            ours = [r for r in ours if r["table"] == best["table"]]
        own = ours[0] if ours else None
        left_out = [f"{r['engine']} {r['form']}: {_why_left_out(r)}" for r in theirs if r not in agreeing]
        notes = ([] if own else ["no finite float32 Lagrangian run"]) + ([] if best else ["no agreeing MuJoCo GPU run"]) + left_out
        ratio = own["steps_per_s"] / best["steps_per_s"] if own and best else float("nan")
        out.append(dict(
            scene=scene, batch=batch,
            lagrangian_steps_per_s=own["steps_per_s"] if own else float("nan"),
            lagrangian_error=own["max_node_error"] if own else float("nan"),
            mujoco_engine=f"{best['engine']} {best['dtype']} {best['form']}" if best else "",
            mujoco_steps_per_s=best["steps_per_s"] if best else float("nan"),
            mujoco_error=best["max_node_error"] if best else float("nan"),
            ratio=ratio, meets_goal=bool(ratio >= GOAL_RATIO),
            tables=", ".join(dict.fromkeys(r["table"] for r in (own, best) if r is not None)),
            machine=", ".join(dict.fromkeys(r["machine"] for r in (own, best) if r is not None and r["machine"])),
            note="; ".join(notes)))
    return out
