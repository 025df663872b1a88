"""The benchmark: train every model of the grid, evaluate it on every scene, against
both ground truths, and measure speed against error. `lgnn.bench.report` turns the records
into `results/`.

The grid and both profiles are declared once, here:

- `GRID`: LGNN, GNS, LGN and CLNN trained on `chain4` (LGNN also on `chain4-varied` and
  `chain4-drag`, as the paper's appendix), each with the scenes it is evaluated on
  (CLNN, tied to its system size, on `chain4` only);
- `PROFILES["quick"]` (minutes on 2 CPU cores, part of CI: tiny data and training
  budgets, 3 initial conditions, 0.1 s rollouts, a subset of scenes) and
  `PROFILES["full"]` (the paper's data, 100 initial conditions per chain scene, 1 s
  rollouts, every scene).

Stages (each resumable: its output is a file written atomically, reused when the
settings it was made with match, redone otherwise):

1. `train_job`: a checkpoint per (model, training scene, seed), `train.train` with
   resume; a finished checkpoint with the same model/data/training settings is reused.
2. `evaluate_scene` / `evaluate_pair`: per evaluation scene, the Lagrangian ground
   truth (RK4 with projection, the same integrator and step as the models), its chaos
   floor (initial positions perturbed by `floor_perturbation`, projected back onto the
   constraints) and MuJoCo C (RK4 at `mujoco_dt`, frames at the same times); per
   (model, scene) the model's rollouts from the same initial conditions. Per frame
   (t > 0) and initial condition: rollout error `||q_hat - q|| / (||q_hat|| + ||q||)`
   over all node coordinates, energy error (the same formula on the scene's true
   Hamiltonian of both trajectories), and the rollout error against MuJoCo's
   trajectory (`lgnn.metrics`). Errors are clipped to [1e-16, 1] (1 is the metric's
   maximum; 1e-16 keeps an exact match from dominating a geometric mean). A rollout
   *diverges* at the first frame the one divergence rule of `lgnn.metrics` flags
   (non-finite, true energy or a node's reach beyond 10 times what the scene allows),
   the rule that stops every engine; from that frame on its errors count as 1 and
   the divergence time is recorded.
3. `speed_error`: wall time per simulated second (single trajectory, compile apart)
   against rollout error for the ground-truth engines at several steps and for each
   learned model, against a MuJoCo C reference at a tenth of the smallest step.
4. `mass_matrices`: the learned LGNN mass matrix `d2L/dqd2` against the true one on
   `chain16` and `T1` (quick: `chain8`) at a state of a ground-truth trajectory.

Records live under `<out>/benchmark/` (`checkpoints/`, `runs/`); datasets under
`<out>/datasets/`. Progress goes to stderr.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
import sys
import time
import zipfile
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from lgnn.learn import data, models, train
from lgnn import metrics, physics, sharding
from lgnn.files import atomic_path
from lgnn.errors import CheckpointError, ConfigError, SceneError, SimulationError
from lgnn.scene import Scene, State, scene_to_dict
from lgnn.scene import get_scene, is_pinned_chain, sample_initial_states
from lgnn.engines.lagrangian import SimulationConfig, rollout_fn

RECORD_FORMAT = 1
TRANSFER_SCENES = ("chain4", "chain8", "chain16", "chain100", "T1", "T2", "T3")
# Metrics recorded per frame and initial condition.
METRICS = ("rollout_error", "energy_error", "rollout_error_vs_mujoco")
# Trajectories kept for figures: initial condition 0, a frame every SNAPSHOT_DT s.
SNAPSHOT_DT = 0.01


@dataclasses.dataclass(frozen=True)
class GridEntry:
    """A model trained on `train_scene`, evaluated on `eval_scenes`."""

    model: str
    train_scene: str
    eval_scenes: tuple[str, ...]


GRID = (
    GridEntry("lgnn", "chain4", TRANSFER_SCENES),
    GridEntry("gns", "chain4", TRANSFER_SCENES),
    GridEntry("lgn", "chain4", TRANSFER_SCENES),
    GridEntry("clnn", "chain4", ("chain4",)),
    GridEntry("lgnn", "chain4-varied", ("chain4-varied",)),
    GridEntry("lgnn", "chain4-drag", ("chain4-drag",)),
)


@dataclasses.dataclass(frozen=True)
class TrainingJob:
    model: str
    scene: str
    seed: int

    @property
    def name(self) -> str:
        return f"{self.model}-{self.scene}-s{self.seed}"

    @property
    def label(self) -> str:
        """The model as tables name it: `lgnn`, or `lgnn (chain4-varied)` off the main training scene."""
        return self.model if self.scene == "chain4" else f"{self.model} ({self.scene})"


@dataclasses.dataclass(frozen=True)
class Pair:
    """One evaluation: a trained job on a scene."""

    job: TrainingJob
    scene: str


@dataclasses.dataclass(frozen=True)
class Profile:
    name: str
    # Training data (the scene is each job's) and optimisation budget.
    data: data.DataConfig
    train: train.TrainConfig
    # Training seeds: the grid's third axis.
    seeds: tuple[int, ...]
    # Evaluation scenes kept from GRID (None: all of them).
    scenes: tuple[str, ...] | None
    # Initial conditions per chain scene (T1-T3 have one: their own rest state).
    initial_conditions: int
    # Rollouts: RK4 with projection at `dt` for models and the Lagrangian ground truth.
    duration: float
    dt: float = 1e-3
    # Scenes that need a smaller step than `dt`, for models and ground truth alike (the
    # same integrator for both, SPEC): T2 and T3 start self-stressed, singular
    # configurations (lgnn/physics.py) where RK4 at 1e-3 and 5e-4 runs to NaN within
    # 0.01 s and 1e-4 converges (results/crosscheck.md).
    scene_dts: tuple[tuple[str, float], ...] = (("T2", 1e-4), ("T3", 1e-4))
    frame_dt: float = 1e-3
    # Seed of the evaluation initial conditions (training data use DataConfig.seed = 0).
    ic_seed: int = 1
    floor_perturbation: float = 1e-4
    # MuJoCo C reference step (RK4) for the learned-vs-MuJoCo comparison.
    mujoco_dt: float = 1e-4
    # Initial conditions per compiled, vmapped rollout call (memory and progress).
    chunk: int = 25
    # Speed against error: scenes, ground-truth steps, horizon, MJX on or off.
    speed_scenes: tuple[str, ...] = ("chain4", "chain16", "chain100", "T1")
    speed_dts: tuple[float, ...] = (1e-3, 1e-4, 1e-5)
    speed_horizon: float = 0.1
    mjx: bool = True
    # Learned models in the speed table (None: every chain4-trained one).
    speed_models: tuple[str, ...] | None = None
    # Training scenes kept from GRID (None: all).
    train_scenes: tuple[str, ...] | None = None
    # Scenes of the learned-mass-matrix comparison (each must be evaluated).
    mass_scenes: tuple[str, ...] = ("chain16", "T1")
    # Lagrangian engine runs longer than this many link-steps are skipped (with a row
    # saying so): dt 1e-5 on chain100 would take most of an hour on a CPU.
    max_link_steps: float = 5e5
    # Cost per step against chain length (the "scaling" stage): chains of these many
    # links, this many RK4 steps at `dt`, single trajectory; and batches of
    # `throughput_batch` initial conditions of each speed scene against MuJoCo C.
    scaling_lengths: tuple[int, ...] = (4, 16, 100, 1000)
    scaling_steps: int = 100
    throughput_batch: int = 100

    def dt_for(self, scene_name: str) -> float:
        return dict(self.scene_dts).get(scene_name, self.dt)

    def simulation(self, scene_name: str) -> SimulationConfig:
        """Rollout settings of models and Lagrangian ground truth on a scene."""
        return SimulationConfig("rk4", self.dt_for(scene_name), self.frame_dt, self.duration, True)

    def eval_key(self, scene_name: str) -> dict:
        """Settings a scene's evaluation records depend on."""
        fields = ("initial_conditions", "duration", "frame_dt", "ic_seed", "floor_perturbation", "mujoco_dt")
        return {**{f: getattr(self, f) for f in fields}, "dt": self.dt_for(scene_name)}


PROFILES = {
    "quick": Profile(
        name="quick",
        data=data.DataConfig(n_trajectories=5, duration=0.5, sample_dt=0.05),
        train=train.TrainConfig(epochs=10, patience=10),
        seeds=(0,),
        # The chain4-trained models on chains only: compiling T1-T3 and the varied/drag
        # models' own pipelines takes minutes on a small CPU (the full profile has them).
        train_scenes=("chain4",),
        scenes=("chain4", "chain8"),
        initial_conditions=3,
        duration=0.1,
        chunk=3,
        speed_scenes=("chain4",),
        speed_dts=(1e-3,),
        speed_horizon=0.02,
        mjx=False,
        speed_models=("lgnn",),
        mass_scenes=("chain8",),
        scaling_lengths=(4, 16),
        scaling_steps=10,
        throughput_batch=4,
    ),
    "full": Profile(
        name="full",
        data=data.DataConfig(),
        # The paper's 10 000 epochs do not fit a session; the minutes budget ends training
        # first (results/README.md states the epochs reached).
        train=train.TrainConfig(epochs=10_000, minutes=6.5),
        seeds=(0,),
        scenes=None,
        initial_conditions=100,
        duration=1.0,
    ),
}


def get_profile(name: str) -> Profile:
    if name not in PROFILES:
        raise ConfigError(f"unknown benchmark profile {name!r} (choose from {', '.join(PROFILES)})")
    return PROFILES[name]


def _grid(profile: Profile) -> list[GridEntry]:
    return [e for e in GRID if profile.train_scenes is None or e.train_scene in profile.train_scenes]


def training_jobs(profile: Profile) -> list[TrainingJob]:
    return [TrainingJob(e.model, e.train_scene, seed) for e in _grid(profile) for seed in profile.seeds]


def evaluation_pairs(profile: Profile) -> list[Pair]:
    pairs = []
    for entry in _grid(profile):
        for seed in profile.seeds:
            for scene in entry.eval_scenes:
                if profile.scenes is None or scene in profile.scenes:
                    pairs.append(Pair(TrainingJob(entry.model, entry.train_scene, seed), scene))
    return pairs


def evaluation_scenes(profile: Profile) -> list[str]:
    return list(dict.fromkeys(p.scene for p in evaluation_pairs(profile)))


def log(message: str) -> None:
    print(f"[benchmark] {message}", file=sys.stderr, flush=True)


@functools.cache
def scene_named(name: str) -> Scene:
    """One Scene object per name per process, so compiled functions cached per scene are reused."""
    return get_scene(name)


# ---------------------------------------------------------------------------------
# Paths and records
# ---------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Layout:
    """Where a profile's outputs live under `out`."""

    out: Path

    @property
    def bench(self) -> Path:
        return self.out / "benchmark"

    def checkpoint(self, job: TrainingJob) -> Path:
        return self.bench / "checkpoints" / f"{job.name}.npz"

    def pair_record(self, pair: Pair) -> Path:
        return self.bench / "runs" / pair.job.name / f"{pair.scene}.npz"

    def truth_record(self, scene: str) -> Path:
        return self.bench / "runs" / "ground-truth" / f"{scene}.npz"

    @property
    def scaling_record(self) -> Path:
        return self.bench / "runs" / "scaling.json"

    def speed_record(self, scene: str) -> Path:
        return self.bench / "runs" / "speed-error" / f"{scene}.json"

    def mass_record(self, scene: str) -> Path:
        return self.bench / "runs" / "mass-matrix" / f"{scene}.npz"

    @property
    def datasets(self) -> Path:
        return self.out / "datasets"


def default_out(profile: Profile) -> Path:
    return Path("results") if profile.name == "full" else Path("results") / profile.name


def _digest(value) -> str:
    return hashlib.sha256(json.dumps(value, sort_keys=True, default=str).encode()).hexdigest()


def _file_digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def save_record(path: Path, key: str, arrays: dict, meta: dict) -> None:
    """An `.npz` record: arrays, a JSON `meta` (with the settings `key`) and a checksum."""
    from lgnn.provenance import environment

    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {**meta, "key": key, "format": RECORD_FORMAT, "environment": environment()}
    meta_text = json.dumps(meta, sort_keys=True, default=float)
    checksum = _arrays_digest(arrays, meta_text)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as handle:
            np.savez(handle, meta=meta_text, checksum=checksum, **arrays)


def _fresh_json_record(path: Path, key: str) -> bool:
    """Whether the JSON record at `path` exists and was made with the settings `key`
    (an unreadable one is recomputed, with a warning)."""
    if not path.exists():
        return False
    try:
        return json.loads(path.read_text()).get("key") == key
    except (OSError, ValueError):
        log(f"warning: {path}: unreadable; recomputing")
        return False


def _save_json_record(path: Path, key: str, **fields) -> None:
    """A JSON record: the settings `key`, the environment and `fields`, written atomically."""
    from lgnn.provenance import environment

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps({"key": key, **fields, "environment": environment()}, indent=1, default=float))


def _arrays_digest(arrays: dict, meta_text: str) -> str:
    digest = hashlib.sha256(meta_text.encode())
    for name in sorted(arrays):
        value = np.ascontiguousarray(arrays[name])
        digest.update(f"{name}:{value.dtype.str}:{value.shape};".encode())
        digest.update(value.tobytes())
    return digest.hexdigest()


def load_record(path: Path, key: str | None = None) -> tuple[dict, dict] | None:
    """`(arrays, meta)` of a valid record with settings `key` (any key if None); None
    (with a warning for a damaged file) when it is absent, damaged or stale."""
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as stored:
            arrays = {k: np.asarray(stored[k]) for k in stored.files if k not in ("meta", "checksum")}
            meta_text, checksum = str(stored["meta"]), str(stored["checksum"])
        meta = json.loads(meta_text)
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as err:
        log(f"warning: {path}: unreadable record ({type(err).__name__}); recomputing")
        return None
    if _arrays_digest(arrays, meta_text) != checksum:
        log(f"warning: {path}: corrupt record (checksum mismatch); recomputing")
        return None
    if meta.get("format") != RECORD_FORMAT or (key is not None and meta.get("key") != key):
        return None
    return arrays, meta


# ---------------------------------------------------------------------------------
# Training
# ---------------------------------------------------------------------------------


def _job_settings(profile: Profile, job: TrainingJob):
    scene = scene_named(job.scene)
    model = models.ModelConfig.for_scene(job.model, scene)
    data_config = dataclasses.replace(profile.data, scene=job.scene)
    train_config = dataclasses.replace(profile.train, seed=job.seed)
    return scene, model, data_config, train_config


def train_job(profile: Profile, job: TrainingJob, out: Path, progress: bool = True) -> Path:
    """The job's checkpoint, trained (or resumed) unless a finished one with the same
    settings exists. A checkpoint made with other settings, or unreadable, is replaced."""
    scene, model, data_config, train_config = _job_settings(profile, job)
    path = Layout(out).checkpoint(job)
    path.parent.mkdir(parents=True, exist_ok=True)
    resume = False
    if path.exists():
        try:
            state, meta = train.load_checkpoint(path)
        except CheckpointError as err:
            log(f"warning: {err}; retraining {job.name}")
        else:
            same = (
                meta["model"] == model.to_dict()
                and meta["train"] == train.training_key(train_config)
                and meta["data"] == dataclasses.asdict(data_config)
            )
            if same and train.finished(state, train_config):
                log(f"train {job.name}: reusing finished checkpoint ({state.epoch} epochs, best validation MSE {state.best_val:.3g})")
                return path
            if same:
                log(f"train {job.name}: resuming at epoch {state.epoch}")
                resume = True
            else:
                log(f"train {job.name}: checkpoint was made with other settings; retraining")
    dataset = data.load_or_generate(data_config, Layout(out).datasets, progress=progress)
    if not resume:
        log(f"train {job.name}: {len(dataset.train)} training states, budget {train_config.epochs} epochs" + (f" / {train_config.minutes:g} min" if train_config.minutes else ""))
    state = train.train(model, train_config, dataset, scene, out=path, data_config=data_config, resume=resume, progress=progress)
    log(f"train {job.name}: {state.epoch} epochs in {state.elapsed_s / 60:.1f} min, best validation MSE {state.best_val:.3g} (epoch {state.best_epoch})")
    return path


def timed_epoch_fn(profile: Profile, job: TrainingJob, out: Path):
    """`(run, steps)`: a no-argument call running one training epoch of the job (the
    compiled function training used, from the checkpoint's parameters), and the Adam
    steps it takes; for pytest-benchmark."""
    scene, model, data_config, train_config = _job_settings(profile, job)
    state, _ = train.load_checkpoint(Layout(out).checkpoint(job))
    dataset = data.load_or_generate(data_config, Layout(out).datasets)
    arrays = tuple(jnp.asarray(a[dataset.train]) for a in (dataset.q, dataset.qd, dataset.qdd))
    epoch = train.compiled_epoch_fn(model, scene, train_config)
    key = jax.random.PRNGKey(0)
    steps = len(dataset.train) // train_config.batch_size
    return (lambda: jax.block_until_ready(epoch(state.params, state.opt_state, *arrays, key))), steps


# ---------------------------------------------------------------------------------
# Evaluation
# ---------------------------------------------------------------------------------


def initial_states(profile: Profile, scene: Scene) -> State:
    """The evaluation initial conditions (C, N, D): `initial_conditions` samples of the
    paper's chain sampler (seed `ic_seed`), or the scene's own state (C = 1)."""
    count = profile.initial_conditions if is_pinned_chain(scene) else 1
    states = sample_initial_states(scene, jax.random.PRNGKey(profile.ic_seed), count)
    return State(np.asarray(states.q), np.asarray(states.qd))


@functools.lru_cache(maxsize=64)
def _compiled_rollouts(scene: Scene, config: SimulationConfig, accel_factory: Callable, chunk: int, dtype: str):
    """`(compiled, compile_s)`: the jitted, vmapped rollout of `chunk` initial
    conditions (a multiple of the device count: they are sharded over every local
    device), compiled once per (scene object, settings, acceleration factory)."""
    run = sharding.batch_jit(jax.vmap(rollout_fn(scene, config, accel_factory)))
    shape = jax.ShapeDtypeStruct((chunk, scene.n_nodes, scene.dim), jnp.dtype(dtype))
    start = time.perf_counter()
    compiled = run.lower(shape, shape).compile()
    return compiled, time.perf_counter() - start


def _batched_rollouts(scene: Scene, config: SimulationConfig, accel_factory: Callable, states: State, chunk: int, label: str, progress: bool):
    """Trajectories (C, F+1, N, D) of q and qd, in vmapped chunks of `chunk` (the last
    padded, so one compile serves all), with the compile and run times."""
    from tqdm.auto import tqdm

    count = len(states.q)
    chunk = sharding.padded_size(min(chunk, count))
    compiled, compile_s = _compiled_rollouts(scene, config, accel_factory, chunk, str(states.q.dtype))
    pad = lambda a, start: jnp.asarray(sharding.pad_batch(a[start : start + chunk], chunk))  # noqa: E731
    qs, qds = [], []
    run_s = 0.0
    with tqdm(total=count, desc=label, unit="IC", disable=not progress, leave=False, file=sys.stderr) as bar:
        for start in range(0, count, chunk):
            t0 = time.perf_counter()
            out = jax.block_until_ready(compiled(pad(states.q, start), pad(states.qd, start)))
            run_s += time.perf_counter() - t0
            take = min(chunk, count - start)
            qs.append(np.asarray(out.q[:take]))
            qds.append(np.asarray(out.qd[:take]))
            bar.update(take)
    return np.concatenate(qs), np.concatenate(qds), compile_s, run_s


@functools.lru_cache(maxsize=2)
def _ground_truth(profile: Profile, scene_name: str, progress: bool = True) -> dict:
    """In-memory ground truth of a scene's evaluation (not stored: large, cheap to redo)."""
    scene = scene_named(scene_name)
    states = initial_states(profile, scene)
    config = profile.simulation(scene_name)
    log(f"ground truth {scene_name}: {len(states.q)} initial conditions, RK4 dt {config.dt:g}, {config.duration:g} s")
    q, qd, compile_s, run_s = _batched_rollouts(scene, config, physics.vectorised_true_acceleration_fn, states, profile.chunk, f"truth {scene_name}", progress)
    energy = metrics.true_energies(scene, q, qd)
    _check_reference(scene, config, "Lagrangian ground truth", q, qd, energy)
    noise = profile.floor_perturbation * jax.random.normal(jax.random.PRNGKey(profile.ic_seed + 1000), states.q.shape)
    perturbed = State(*map(np.asarray, jax.vmap(physics.projection_fn(scene))(jnp.asarray(states.q) + noise, jnp.asarray(states.qd))))
    # The perturbed runs are not references: one that diverges (T2/T3's perturbed
    # self-stressed states need dt <= 2.5e-5) is recorded as such, like a model's.
    q_floor, qd_floor, _, _ = _batched_rollouts(scene, config, physics.vectorised_true_acceleration_fn, perturbed, profile.chunk, f"floor {scene_name}", progress)
    from lgnn.engines import mujoco as lm

    mj_config = SimulationConfig("rk4", profile.mujoco_dt, profile.frame_dt, profile.duration, True)
    start = time.perf_counter()
    q_mj, qd_mj = lm.rollout(scene, mj_config, states, threads=os.cpu_count() or 1)
    mujoco_s = time.perf_counter() - start
    _check_reference(scene, mj_config, "MuJoCo reference", q_mj, qd_mj, metrics.true_energies(scene, q_mj, qd_mj))
    floor_diverged = _divergence(scene, config, q_floor, qd_floor, metrics.true_energies(scene, q_floor, qd_floor))
    return dict(q=q, qd=qd, energy=energy, q_floor=q_floor, floor_diverged=floor_diverged, q_mujoco=q_mj, states=states,
                compile_s=compile_s, run_s=run_s, mujoco_s=mujoco_s)


def _metric_frames(diverged: np.ndarray) -> np.ndarray:
    """Divergence frame indices (C,) shifted to the metric arrays, which exclude t = 0."""
    return np.where(diverged > 0, diverged - 1, diverged)


def _divergence(scene: Scene, config: SimulationConfig, q: np.ndarray, qd: np.ndarray, energy: np.ndarray) -> np.ndarray:
    """(C,) first diverged frame of each trajectory (`lgnn.metrics`' one rule), or -1."""
    return metrics.divergence_frames(scene, np.arange(q.shape[1]) * config.frame_dt, q, qd, energy)


def _check_reference(scene: Scene, config: SimulationConfig, what: str, q: np.ndarray, qd: np.ndarray, energy: np.ndarray) -> None:
    """A reference trajectory that diverged would turn every error into 1 for every
    model: stop with one line instead of recording meaningless numbers."""
    diverged = _divergence(scene, config, q, qd, energy)
    if (diverged >= 0).any():
        first = int(np.argmax(diverged >= 0))
        raise SimulationError(
            f"{scene.name}: the {what} diverged at t = {diverged[first] * config.frame_dt:g} s (initial condition {first}, "
            f"RK4 dt {config.dt:g}): give the scene a smaller step (Profile.scene_dts)"
        )


def _snapshot(profile: Profile, trajectory: np.ndarray) -> np.ndarray:
    """IC 0 of a trajectory at every SNAPSHOT_DT s (figures), float32."""
    stride = max(1, round(SNAPSHOT_DT / profile.frame_dt))
    return np.asarray(trajectory[0, ::stride], np.float32)


def _metric_arrays(prefix: str, errors: np.ndarray) -> dict:
    stats = metrics.error_statistics(errors)
    return {f"{prefix}/{k}": v for k, v in stats.items()}


def _truth_key(profile: Profile, scene: Scene) -> str:
    return _digest({"eval": profile.eval_key(scene.name), "scene": scene_to_dict(scene)})


def evaluate_scene(profile: Profile, scene_name: str, out: Path, progress: bool = True) -> Path:
    """The ground-truth record of a scene: chaos floor and Lagrangian-vs-MuJoCo errors."""
    scene = scene_named(scene_name)
    path, key = Layout(out).truth_record(scene_name), _truth_key(profile, scene)
    if load_record(path, key) is not None:
        return path
    truth = _ground_truth(profile, scene_name, progress)
    none = np.full(len(truth["q"]), -1)
    floor_diverged = truth["floor_diverged"]
    arrays = {
        "t": np.arange(1, truth["q"].shape[1]) * profile.frame_dt,
        **_metric_arrays("chaos_floor", metrics.clean_errors(metrics.relative_error(truth["q_floor"], truth["q"], 2)[:, 1:], _metric_frames(floor_diverged))),
        "chaos_floor/diverged_at": np.where(floor_diverged >= 0, floor_diverged * profile.frame_dt, np.nan),
        **_metric_arrays("truth_vs_mujoco", metrics.clean_errors(metrics.relative_error(truth["q"], truth["q_mujoco"], 2)[:, 1:], none)),
        "snapshot/truth": _snapshot(profile, truth["q"]),
        "snapshot/mujoco": _snapshot(profile, truth["q_mujoco"]),
        "mid_state": np.stack([truth["q"][0, truth["q"].shape[1] // 2], truth["qd"][0, truth["qd"].shape[1] // 2]]),
    }
    meta = dict(scene=scene_name, initial_conditions=len(truth["q"]), compile_s=truth["compile_s"], run_s=truth["run_s"], mujoco_s=truth["mujoco_s"])
    save_record(path, key, arrays, meta)
    return path


def _pair_key(profile: Profile, pair: Pair, checkpoint: Path) -> str:
    return _digest({"truth": _truth_key(profile, scene_named(pair.scene)), "checkpoint": _file_digest(checkpoint)})


def evaluate_pair(profile: Profile, pair: Pair, out: Path, progress: bool = True) -> Path:
    """The evaluation record of a trained model on a scene (module docstring)."""
    layout = Layout(out)
    checkpoint = layout.checkpoint(pair.job)
    if not checkpoint.exists():
        raise ConfigError(f"no checkpoint for {pair.job.name} at {checkpoint}: run the training stage first")
    path, key = layout.pair_record(pair), _pair_key(profile, pair, checkpoint)
    if load_record(path, key) is not None:
        return path
    scene = scene_named(pair.scene)
    truth = _ground_truth(profile, pair.scene, progress)
    log(f"evaluate {pair.job.label} on {pair.scene}: {len(truth['q'])} initial conditions")
    q, qd, compile_s, run_s = _batched_rollouts(
        scene, profile.simulation(pair.scene), _model_accel_factory(checkpoint, _file_digest(checkpoint)), truth["states"], profile.chunk,
        f"{pair.job.label} on {pair.scene}", progress
    )
    energy = metrics.true_energies(scene, q, qd)
    diverged = _divergence(scene, profile.simulation(pair.scene), q, qd, energy)
    after_t0 = _metric_frames(diverged)
    arrays = {
        "t": np.arange(1, q.shape[1]) * profile.frame_dt,
        **_metric_arrays("rollout_error", metrics.clean_errors(metrics.relative_error(q, truth["q"], 2)[:, 1:], after_t0)),
        **_metric_arrays("energy_error", metrics.clean_errors(metrics.relative_error(energy, truth["energy"], 0)[:, 1:], after_t0)),
        **_metric_arrays("rollout_error_vs_mujoco", metrics.clean_errors(metrics.relative_error(q, truth["q_mujoco"], 2)[:, 1:], after_t0)),
        "diverged_at": np.where(diverged >= 0, diverged * profile.frame_dt, np.nan),
        "snapshot/model": _snapshot(profile, q),
    }
    config = profile.simulation(pair.scene)
    steps = len(q) * config.n_frames * config.steps_per_frame
    meta = dict(job=pair.job.name, model=pair.job.model, label=pair.job.label, train_scene=pair.job.scene, seed=pair.job.seed,
                scene=pair.scene, initial_conditions=len(q), compile_s=compile_s, run_s=run_s, steps_per_s=steps / run_s)
    save_record(path, key, arrays, meta)
    n_div = int(np.sum(diverged >= 0))
    log(f"evaluate {pair.job.label} on {pair.scene}: rollout error {metrics.summarise(arrays['rollout_error/per_ic_log'])[0]:.3g}"
        + (f", {n_div} diverged" if n_div else "") + f" ({run_s:.1f} s + compile {compile_s:.1f} s)")
    return path


@functools.lru_cache(maxsize=16)
def _model_accel_factory(checkpoint: Path, digest: str) -> Callable[[Scene], physics.AccelerationFn]:
    """`scene -> accel` of a checkpoint's best parameters: one object per checkpoint
    content (`digest`), so compiled rollouts cached per factory are shared by
    evaluation and timing."""
    model, params = train.load_model(checkpoint)
    return lambda scene: models.acceleration_fn(model, params, scene)


def timed_rollout_fn(profile: Profile, pair: Pair, out: Path):
    """`(run, steps)`: a no-argument call running the pair's compiled evaluation rollout
    on its first chunk of initial conditions (the function `evaluate_pair` used), and
    the RK4 steps it takes; for pytest-benchmark."""
    scene = scene_named(pair.scene)
    states = initial_states(profile, scene)
    chunk = sharding.padded_size(min(profile.chunk, len(states.q)))
    checkpoint = Layout(out).checkpoint(pair.job)
    accel_factory = _model_accel_factory(checkpoint, _file_digest(checkpoint))
    config = profile.simulation(pair.scene)
    compiled, _ = _compiled_rollouts(scene, config, accel_factory, chunk, str(states.q.dtype))
    q, qd = (jnp.asarray(sharding.pad_batch(a[:chunk], chunk)) for a in states)
    steps = chunk * config.n_frames * config.steps_per_frame
    return (lambda: jax.block_until_ready(compiled(q, qd))), steps


# ---------------------------------------------------------------------------------
# Speed against error
# ---------------------------------------------------------------------------------


def _speed_settings(profile: Profile, scene_name: str, out: Path, jobs: list[TrainingJob] | None = None):
    """`(jobs, checkpoint digests, key)` of a scene's speed-against-error record: the
    chain4-trained models timed on it (CLNN on chain4 only) and what the record depends on."""
    layout = Layout(out)
    jobs = [j for j in (jobs or training_jobs(profile)) if j.scene == "chain4" and (j.model != "clnn" or scene_name == "chain4")
            and (profile.speed_models is None or j.model in profile.speed_models)]
    checkpoints = {j.name: _file_digest(layout.checkpoint(j)) for j in jobs if layout.checkpoint(j).exists()}
    fields = ("speed_scenes", "speed_dts", "speed_horizon", "mjx", "speed_models", "frame_dt", "ic_seed", "max_link_steps")
    settings = {**{f: getattr(profile, f) for f in fields}, "dt": profile.dt_for(scene_name)}
    return jobs, checkpoints, _digest({"settings": settings, "scene": scene_to_dict(scene_named(scene_name)), "checkpoints": checkpoints})


def speed_key(profile: Profile, scene_name: str, out: Path) -> str:
    return _speed_settings(profile, scene_name, out)[2]


def speed_error(profile: Profile, scene_name: str, out: Path, jobs: list[TrainingJob] | None = None) -> Path:
    """Rows `scene, solver, kind, dt, wall_s_per_sim_s, evaluations_per_sim_s,
    compile_s, rollout_error, note` (JSON record): every ground-truth engine at each of
    `speed_dts` and every chain4-trained model at the profile's dt, single trajectory
    from the scene's first initial condition over `speed_horizon` s, frames every
    `frame_dt`; error: geometric mean of the rollout error against MuJoCo C at a tenth
    of the smallest step."""
    from lgnn.engines import mujoco as lm
    from lgnn.bench.crosscheck import MJX_MAX_DEPTH, SKIP_MJX, timed_rollout, time_compiled

    scene = scene_named(scene_name)
    layout = Layout(out)
    jobs, checkpoints, key = _speed_settings(profile, scene_name, out, jobs)
    path = layout.speed_record(scene_name)
    if _fresh_json_record(path, key):
        return path
    states = initial_states(profile, scene)
    single = State(states.q[:1], states.qd[:1])
    horizon, frame_dt = profile.speed_horizon, profile.frame_dt
    reference_config = SimulationConfig("rk4", min(profile.speed_dts) / 10, frame_dt, horizon, True)
    log(f"speed/error {scene_name}: MuJoCo C reference at dt {reference_config.dt:g}")
    reference = lm.rollout(scene, reference_config, single).q[0]
    depth = lm.scene_layout(scene).depth
    rows = []

    def row(solver, kind, dt, **values):
        base = dict(scene=scene_name, solver=solver, kind=kind, dt=dt, wall_s_per_sim_s=float("nan"), evaluations_per_sim_s=4 / dt,
                    compile_s=float("nan"), rollout_error=float("nan"), note="")
        rows.append({**base, **values})

    for engine in ("lagrangian", "mujoco", "mjx"):
        for dt in profile.speed_dts:
            if engine == "mjx" and not profile.mjx:
                row(engine, "engine", dt, note="not run in this profile")
                continue
            if engine == "mjx" and depth > MJX_MAX_DEPTH:
                row(engine, "engine", dt, note=SKIP_MJX.format(depth=depth, limit=MJX_MAX_DEPTH))
                continue
            if engine != "mujoco" and horizon / dt * scene.n_links > profile.max_link_steps:
                row(engine, "engine", dt, note=f"not run: over {profile.max_link_steps:g} link-steps")
                continue
            config = SimulationConfig("rk4", dt, frame_dt, horizon, True)
            compile_s, run_s, q = timed_rollout(engine, scene, config, single)
            row(engine, "engine", dt, wall_s_per_sim_s=run_s / horizon, compile_s=compile_s, rollout_error=metrics.gmean_error(q[0], reference))
            log(f"speed/error {scene_name} {engine} dt {dt:g}: {run_s / horizon:.3g} s per simulated s, error {rows[-1]['rollout_error']:.2e}")
    config = SimulationConfig("rk4", profile.dt_for(scene_name), frame_dt, horizon, True)
    for job in jobs:
        if job.name not in checkpoints:
            row(job.label, "learned", config.dt, note="no checkpoint")
            continue
        model, params = train.load_model(layout.checkpoint(job))
        run = jax.jit(rollout_fn(scene, config, lambda s: models.acceleration_fn(model, params, s)))
        compile_s, run_s, out = time_compiled(run, jnp.asarray(single.q[0]), jnp.asarray(single.qd[0]))
        q = np.asarray(out.q)
        row(job.label, "learned", config.dt, wall_s_per_sim_s=run_s / horizon, compile_s=compile_s, rollout_error=metrics.gmean_error(q, reference))
        log(f"speed/error {scene_name} {job.label}: {run_s / horizon:.3g} s per simulated s, error {rows[-1]['rollout_error']:.2e}")
    _save_json_record(path, key, horizon=horizon, rows=rows)
    return path


# ---------------------------------------------------------------------------------
# Cost against size, and batched throughput
# ---------------------------------------------------------------------------------


def _scaling_settings(profile: Profile, out: Path):
    job = TrainingJob("lgnn", "chain4", profile.seeds[0])
    checkpoint = Layout(out).checkpoint(job)
    digest = _file_digest(checkpoint) if checkpoint.exists() else None
    fields = ("scaling_lengths", "scaling_steps", "throughput_batch", "speed_scenes", "dt", "ic_seed")
    return checkpoint, digest, _digest({"settings": {f: getattr(profile, f) for f in fields}, "lgnn": digest})


def scaling_key(profile: Profile, out: Path) -> str:
    return _scaling_settings(profile, out)[2]


def scaling(profile: Profile, out: Path) -> Path:
    """Record (JSON) of rows `kind, scene, n_links, solver, batch, s_per_step, compile_s, note`:
    - kind "size": wall seconds per RK4 step at the profile's dt against chain length
      (`scaling_lengths`), single trajectory from the paper's sampler, for the
      Lagrangian ground truth, MuJoCo C (its stepping alone) and LGNN trained on chain4;
    - kind "batch": `throughput_batch` initial conditions of each speed scene at once
      (batches spread over every local device; MuJoCo C on two threads), for the
      Lagrangian ground truth and MuJoCo C.
    Each timing runs `scaling_steps` steps after a compile (or warm-up) run kept apart."""
    from lgnn.bench.crosscheck import timed_rollout, time_compiled
    from lgnn.scene import chain

    layout = Layout(out)
    checkpoint, digest, key = _scaling_settings(profile, out)
    path = layout.scaling_record
    if _fresh_json_record(path, key):
        return path
    steps, dt = profile.scaling_steps, profile.dt
    config = SimulationConfig("rk4", dt, steps * dt, steps * dt, True)
    model_params = train.load_model(checkpoint) if digest else None
    rows = []
    for n in profile.scaling_lengths:
        scene = chain(n)
        states = sample_initial_states(scene, jax.random.PRNGKey(profile.ic_seed), 1)
        single = State(np.asarray(states.q), np.asarray(states.qd))
        factories = {"lagrangian": physics.true_acceleration_fn, "mujoco": None}
        if model_params is not None:
            model, params = model_params
            factories["lgnn"] = lambda s, model=model, params=params: models.acceleration_fn(model, params, s)
        for solver, factory in factories.items():
            row = dict(kind="size", scene=scene.name, n_links=n, solver=solver, batch=1, s_per_step=float("nan"), compile_s=float("nan"), note="")
            if factory is None:
                try:
                    compile_s, run_s, _ = timed_rollout("mujoco", scene, config, single)
                except (ConfigError, SceneError, SimulationError) as err:
                    row["note"] = f"not run: {err}"
                    rows.append(row)
                    log(f"scaling {scene.name} mujoco: {row['note']}")
                    continue
            else:
                # One trajectory, not vmapped (as the speed stage times learned models).
                run = jax.jit(rollout_fn(scene, config, factory))
                compile_s, run_s, _ = time_compiled(run, jnp.asarray(single.q[0]), jnp.asarray(single.qd[0]))
            rows.append({**row, "s_per_step": run_s / steps, "compile_s": compile_s})
            log(f"scaling {scene.name} {solver}: {run_s / steps:.3g} s per step (compile {compile_s:.1f} s)")
    for name in profile.speed_scenes:
        scene = scene_named(name)
        states = sample_initial_states(scene, jax.random.PRNGKey(profile.ic_seed), profile.throughput_batch)
        batch = State(np.asarray(states.q), np.asarray(states.qd))
        for solver in ("lagrangian", "mujoco"):
            compile_s, run_s, _ = timed_rollout(solver, scene, config, batch)
            rows.append(dict(kind="batch", scene=name, n_links=scene.n_links, solver=solver, batch=profile.throughput_batch,
                             s_per_step=run_s / steps, compile_s=compile_s, note=""))
            log(f"throughput {name} {solver} x{profile.throughput_batch}: {profile.throughput_batch * steps / run_s:.3g} steps/s")
    _save_json_record(path, key, rows=rows)
    return path


# ---------------------------------------------------------------------------------
# Learned mass matrix
# ---------------------------------------------------------------------------------


def mass_job(profile: Profile) -> TrainingJob:
    """The model whose learned mass matrix is analysed: LGNN trained on chain4."""
    return TrainingJob("lgnn", "chain4", profile.seeds[0])


def mass_key(profile: Profile, scene_name: str, checkpoint: Path) -> str:
    """Settings a mass-matrix record depends on; "analysis" versions what is derived
    from the matrices (2: the scale-fitted errors)."""
    return _digest({"truth": _truth_key(profile, scene_named(scene_name)), "checkpoint": _file_digest(checkpoint), "analysis": 2})


def mass_matrices(profile: Profile, scene_name: str, out: Path, job: TrainingJob | None = None) -> Path:
    """The true and learned (LGNN trained on chain4) mass matrices over the free node
    coordinates at a ground-truth state (IC 0 at half the rollout, from the scene's
    evaluation record), and their percentage errors `100 ||M_hat - M||_F / ||M||_F`:
    over all free coordinates, and on the constraint tangent space (`P M P`, P the
    orthogonal projector onto `A v = 0`: the part of M the dynamics see). Accelerations
    determine a Lagrangian only up to an overall factor (`c L` has the same
    Euler-Lagrange equations), so both are also given for `c M_hat`, `c` the
    least-squares factor on the tangent space (recorded as `scale`)."""
    job = job or mass_job(profile)
    layout = Layout(out)
    checkpoint = layout.checkpoint(job)
    scene = scene_named(scene_name)
    path, key = layout.mass_record(scene_name), mass_key(profile, scene_name, checkpoint)
    if load_record(path, key) is not None:
        return path
    truth = load_record(layout.truth_record(scene_name), _truth_key(profile, scene))
    if truth is None:
        raise ConfigError(f"mass matrix on {scene_name}: run its evaluation stage first (the state comes from its ground truth)")
    q, qd = (jnp.asarray(a) for a in truth[0]["mid_state"])
    model, params = train.load_model(checkpoint)
    free = np.setdiff1d(np.arange(scene.n_nodes), scene.pinned)
    coords = (free[:, None] * scene.dim + np.arange(scene.dim)).reshape(-1)
    true_m = np.asarray(physics.mass_matrix_fn(physics.lagrangian_fn(scene))(q, qd))[np.ix_(coords, coords)]
    learned_m = np.asarray(jax.jit(models.mass_matrix_fn(model, params, scene))(q, qd))[np.ix_(coords, coords)]
    constraints = physics.Constraints(scene)
    jac = np.asarray(constraints.jacobian(constraints.restrict(q)))
    projector = np.eye(len(coords)) - jac.T @ np.linalg.pinv(jac @ jac.T) @ jac  # analysis only, not dynamics
    tangent_true, tangent_learned = projector @ true_m @ projector, projector @ learned_m @ projector
    scale = float(np.sum(tangent_learned * tangent_true) / np.sum(tangent_learned**2))
    percent = lambda a, b: float(100 * np.linalg.norm(a - b) / np.linalg.norm(b))  # noqa: E731
    meta = dict(scene=scene_name, job=job.name, percent_error=percent(learned_m, true_m),
                tangent_percent_error=percent(tangent_learned, tangent_true), scale=scale,
                scaled_percent_error=percent(scale * learned_m, true_m),
                scaled_tangent_percent_error=percent(scale * tangent_learned, tangent_true))
    save_record(path, key, {"true": true_m, "learned": learned_m}, meta)
    log(f"mass matrix {scene_name}: learned within {meta['percent_error']:.2g}% (tangent space {meta['tangent_percent_error']:.2g}%); "
        f"times {scale:.3g}: {meta['scaled_percent_error']:.2g}% (tangent {meta['scaled_tangent_percent_error']:.2g}%)")
    return path


# ---------------------------------------------------------------------------------
# The whole run
# ---------------------------------------------------------------------------------

STAGES = ("train", "evaluate", "speed", "scaling", "mass", "report")


def run(profile: Profile, out: Path | None = None, stages=STAGES, jobs: list[str] | None = None, scenes: list[str] | None = None,
        progress: bool = True) -> Path:
    """Run the chosen stages of the benchmark (all by default), restricted to the named
    training jobs and evaluation scenes when given; returns the output directory."""
    out = Path(out) if out is not None else default_out(profile)
    unknown = sorted(set(stages) - set(STAGES))
    if unknown:
        raise ConfigError(f"unknown benchmark stage {unknown[0]!r} (choose from {', '.join(STAGES)})")
    all_jobs = training_jobs(profile)
    known = {j.name for j in all_jobs}
    for name in jobs or ():
        if name not in known:
            raise ConfigError(f"unknown training job {name!r} (choose from {', '.join(sorted(known))})")
    for name in scenes or ():
        if name not in evaluation_scenes(profile):
            raise ConfigError(f"scene {name!r} is not evaluated in the {profile.name} profile (choose from {', '.join(evaluation_scenes(profile))})")
    selected_jobs = [j for j in all_jobs if not jobs or j.name in jobs]
    selected_scenes = [s for s in evaluation_scenes(profile) if not scenes or s in scenes]
    out.mkdir(parents=True, exist_ok=True)
    if "train" in stages:
        for job in selected_jobs:
            train_job(profile, job, out, progress)
    if "evaluate" in stages:
        for scene in selected_scenes:
            evaluate_scene(profile, scene, out, progress)
            for pair in evaluation_pairs(profile):
                if pair.scene == scene and pair.job in selected_jobs:
                    evaluate_pair(profile, pair, out, progress)
    if "speed" in stages:
        for scene in profile.speed_scenes:
            if not scenes or scene in scenes:
                speed_error(profile, scene, out)
    if "scaling" in stages and not scenes:
        scaling(profile, out)
    if "mass" in stages:
        for scene in profile.mass_scenes:
            if not scenes or scene in scenes:
                mass_matrices(profile, scene, out)
    if "report" in stages:
        from lgnn.bench import report

        report.write(profile, out)
    return out
