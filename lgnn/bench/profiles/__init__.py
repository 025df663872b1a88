"""The benchmark's profiles: a `Profile` is the grid's selection (seeds, training and
evaluation scenes, models, tracks) and one frozen settings dataclass per stage
(`TrainSettings`, `EvaluateSettings`, `SpeedSettings`, `ScalingSettings`,
`MassSettings`).

- `PROFILES["quick"]` (minutes on 2 CPU cores, part of CI: tiny data and training
  budgets, 3 initial conditions, 0.1 s rollouts, a subset of scenes) and
  `PROFILES["full"]` (the paper's data, 100 initial conditions per chain scene, 1 s
  rollouts, every scene): the TOML files beside this module (`quick.toml`,
  `full.toml`), read by `load_profile`, which reads a user's config file the same way.

A stage's record key is the digest of `settings_key(...)` of every settings group the
stage reads (`lgnn.bench.stages`): every field enters it, except those declared
`NOT_IN_KEY` (how the work is split or which records exist, never what a record holds),
so no field can be forgotten. The grid itself (`GridEntry`, jobs, pairs, tracks,
figure groups) is `lgnn.bench.grid`'s.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import tomllib
from importlib import resources
from pathlib import Path

from lgnn.errors import ConfigError, SceneError
from lgnn.records import KEY_UNLESS_DEFAULT, NOT_IN_KEY
from lgnn.engines import ENGINES
from lgnn.engines.base import Integration, SimulationConfig
from lgnn.learn.data import DataConfig
from lgnn.learn.models import load_spec
from lgnn.learn.protocol import TrainConfig, adam_steps_per_epoch, scheduled
from lgnn.scene import check_scene_name, get_scene

from lgnn.bench.grid import ERROR_FIGURES, GRID, MEASURED_MODEL, SPATIAL_TRAINING_SCENE, SPATIAL_TRANSFER_SCENES, TRACKS, TRAINING_SCENE, TRAINING_SCENES, TRANSFER_SCENES, FigureGroup, GridEntry, Pair, TrainingJob, check_numbers

@dataclasses.dataclass(frozen=True)
class TrainSettings:
    """Training data (the scene is each job's) and the optimisation budget. A checkpoint
    is reused when its model, `protocol.training_key` and data settings match. A learning
    rate or warm-up `train` leaves None follows the schedule rule for this budget
    (`lgnn.learn.protocol.scheduled`), filled in here so that records and the report see
    the values trained with; one the config gives is kept."""

    data: DataConfig
    train: TrainConfig

    def __post_init__(self):
        object.__setattr__(self, "train", scheduled(self.train, adam_steps_per_epoch(self.data, self.train)))

    def data_for(self, scene_name: str) -> DataConfig:
        """The training data of one scene (`data` is every training scene's but for its name)."""
        return dataclasses.replace(self.data, scene=scene_name)


# Initial conditions per compiled rollout call by default: `EvaluateSettings.chunk`, and
# `lgnn evaluate` on a CPU.
ROLLOUTS_PER_CALL = 25


@dataclasses.dataclass(frozen=True)
class EvaluateSettings:
    """Rollouts of models and ground truths from the evaluation initial conditions."""

    # Initial conditions per chain scene (T1-T3 have one: their own rest state).
    initial_conditions: int
    # Rollouts: RK4 with projection at `dt` for models and the Lagrangian ground truth.
    duration: float
    dt: float = 1e-3
    # Scenes that need a smaller step than `dt`, for models and ground truth alike (the
    # same integrator for both, SPEC): T2 and T3 start self-stressed, singular
    # configurations (lgnn.physics) where RK4 at 1e-3 and 5e-4 runs to NaN within
    # 0.01 s and 1e-4 converges (results/crosscheck.md).
    scene_dts: tuple[tuple[str, float], ...] = (("T2", 1e-4), ("T3", 1e-4))
    frame_dt: float = 1e-3
    # Seed of the evaluation initial conditions (training data use DataConfig.seed = 0).
    ic_seed: int = 1
    # Chaos floor: initial positions perturbed by this much.
    floor_perturbation: float = 1e-4
    # Step (RK4) of the reference engines (`references`; the name is MuJoCo C's, the default).
    mujoco_dt: float = 1e-4
    # Initial conditions per compiled, vmapped rollout call (memory and progress).
    chunk: int = dataclasses.field(default=ROLLOUTS_PER_CALL, metadata=NOT_IN_KEY)
    # Reference engines (names in `lgnn.engines.ENGINES`) run from the same initial
    # conditions beside the Lagrangian ground truth: the ground truth and every model
    # are also scored against each (`rollout_error_vs_<engine>`). MuJoCo C, the
    # independent implementation of the same physics, by default.
    references: tuple[str, ...] = dataclasses.field(default=("mujoco",), metadata=KEY_UNLESS_DEFAULT)

    def __post_init__(self):
        unknown = [name for name in self.references if name not in ENGINES]
        if unknown:
            raise ConfigError(f"evaluate.references: unknown engine {unknown[0]!r} (choose from {', '.join(ENGINES)})")
        check_numbers("evaluate", self, initial_conditions=True, chunk=True, duration=False, dt=False, frame_dt=False, mujoco_dt=False)
        check_numbers("evaluate", self, -math.inf, floor_perturbation=False)
        if self.floor_perturbation < 0:
            raise ConfigError(f"setting 'evaluate.floor_perturbation' must be >= 0, got {self.floor_perturbation!r}")
        for scene_name, dt in self.scene_dts:
            if not (isinstance(dt, float) and math.isfinite(dt) and dt > 0):
                raise ConfigError(f"setting 'evaluate.scene_dts' of {scene_name}: dt must be a finite number > 0, got {dt!r}")
        for dt in {self.dt, *dict(self.scene_dts).values()}:
            try:  # whole multiples and bounded counts, before any stage starts
                SimulationConfig(dt, self.frame_dt, self.duration)
            except ConfigError as err:
                raise ConfigError(f"settings 'evaluate': {err}") from None

    def dt_for(self, scene_name: str) -> float:
        return dict(self.scene_dts).get(scene_name, self.dt)

    def simulation(self, scene_name: str) -> SimulationConfig:
        """Rollout settings of models and Lagrangian ground truth on a scene."""
        return SimulationConfig(self.dt_for(scene_name), self.frame_dt, self.duration)

    @property
    def integration(self) -> Integration:
        """How models and the Lagrangian ground truth integrate: RK4 with projection (a
        property, not a field: no record key holds it)."""
        return Integration("rk4", project=True)

    def for_scene(self, scene_name: str) -> EvaluateSettings:
        """The settings a scene's evaluation uses: its own step as `dt`, no other scene's."""
        return dataclasses.replace(self, dt=self.dt_for(scene_name), scene_dts=())


@dataclasses.dataclass(frozen=True)
class SpeedSettings:
    """Speed against error: ground-truth engines at several steps and the learned
    models, single trajectory, against a MuJoCo C reference."""

    # Scenes with a speed record (which records exist, not what each holds).
    scenes: tuple[str, ...] = dataclasses.field(default=("chain4", "chain16", "chain100", "T1", "chain4-3d", "chain16-3d", "chain100-3d"),
                                                metadata=NOT_IN_KEY)
    # Ground-truth engine steps; the reference runs at a tenth of the smallest.
    dts: tuple[float, ...] = (1e-3, 1e-4, 1e-5)
    horizon: float = 0.1
    # MJX on or off (its CPU compile takes minutes beyond small trees; `runs`).
    mjx: bool = True
    # Learned models timed (None: every one `speed.timed_jobs` names: those the grid
    # evaluates on the scene, trained on its dimension's training scene). Not in the key
    # as such: the key names each timed checkpoint (`speed.speed_key`).
    models: tuple[str, ...] | None = dataclasses.field(default=None, metadata=NOT_IN_KEY)
    # Runs of a compiled engine (the Lagrangian engine, MJX: `EngineEntry.compiled`)
    # longer than this many link-steps are skipped (with a row saying so): the
    # Lagrangian engine at dt 1e-5 on chain100 would take most of an hour on a CPU.
    max_link_steps: float = 5e5
    # Timed runs per row: the table gives their median and spread (min..max). In the key
    # (a record of 3 runs holds other numbers than one of 1), but left out of it at 1,
    # so the single-run records made before this field keep theirs (`speed.speed_key`).
    # A JAX engine's repeat is a whole `timed_rollout`, compile included (reported apart).
    repeats: int = 1

    def __post_init__(self):
        if self.repeats < 1:
            raise ConfigError(f"speed.repeats must be >= 1, got {self.repeats}")
        check_numbers("speed", self, dts=False, horizon=False, max_link_steps=False)

    def runs(self, engine: str) -> bool:
        """Whether this profile runs engine `engine` of the speed table
        (`lgnn.engines.EngineEntry.in_speed_table`): every one unless turned off here
        (`mjx` false: MJX)."""
        return self.mjx or engine != "mjx"


@dataclasses.dataclass(frozen=True)
class ScalingSettings:
    """Cost per step against chain length, and batched throughput."""

    # Chains of these many links, single trajectory, `steps` RK4 steps at the evaluation dt.
    lengths: tuple[int, ...] = (4, 16, 100, 1000)
    # 3D chains (`lgnn.scene.spatial_chain`) of these many links, timed as `lengths`
    # with the LGNN of the 3D grid. MuJoCo C runs chain100-3d nested (6.7 ms a step on
    # 2 cores, 22x planar chain100: a serial chain's joint-space mass matrix is dense,
    # O(nv^3) in its 300 ball-joint DOF) and chain1000-3d maximal. Empty: no 3D rows, and out of the key (records
    # made before this field keep theirs, `scaling.scaling_key`).
    spatial_lengths: tuple[int, ...] = (4, 16, 100, 1000)
    steps: int = 100
    # Batches of `throughput_batch` initial conditions of each of these scenes against MuJoCo C.
    throughput_scenes: tuple[str, ...] = ("chain4", "chain16", "chain100", "T1", "chain4-3d", "chain16-3d")
    throughput_batch: int = 100

    def __post_init__(self):
        check_numbers("scaling", self, lengths=True, spatial_lengths=True, steps=True, throughput_batch=True)


@dataclasses.dataclass(frozen=True)
class MassSettings:
    """The learned LGNN mass matrix against the true one."""

    # Scenes analysed (each must be evaluated: the state comes from its ground truth),
    # each with the LGNN of its dimension's grid (`lgnn_job`).
    scenes: tuple[str, ...] = dataclasses.field(default=("chain16", "T1", "chain16-3d"), metadata=NOT_IN_KEY)
    # Version of what is derived from the matrices (2: the scale-fitted errors).
    analysis: int = 2


@dataclasses.dataclass(frozen=True)
class Profile:
    name: str
    training: TrainSettings
    evaluate: EvaluateSettings
    speed: SpeedSettings = SpeedSettings()
    scaling: ScalingSettings = ScalingSettings()
    mass: MassSettings = MassSettings()
    # Training seeds: the grid's third axis.
    seeds: tuple[int, ...] = (0,)
    # Training scenes kept from GRID (None: all).
    train_scenes: tuple[str, ...] | None = None
    # Evaluation scenes kept from GRID (None: all of them).
    scenes: tuple[str, ...] | None = None
    # The grid: which model is trained on which scene and evaluated on which (config files may give their own).
    grid: tuple[GridEntry, ...] = GRID
    # Stages `lgnn benchmark` runs (None: all of `lgnn.bench.run.STAGES`; `--stage` overrides).
    stages: tuple[str, ...] | None = None
    # Models kept from the grid (None: all of them).
    models: tuple[str, ...] | None = None
    # Tracks kept from the grid (`TRACKS`; None: all of them).
    tracks: tuple[str, ...] | None = None
    # Files of predictions made outside lgnn (docs/formats.md, "Predictions"), each
    # scored by the evaluate stage against its scene's ground truth and reported as
    # `MODEL (external)` (`lgnn.bench.stages.external`). Not in any record key.
    predictions: tuple[str, ...] = ()
    # A results folder (e.g. the committed `results/`) read in place beside this run's
    # output folder, never written: its checkpoints are never retrained, its records are
    # reused where their settings key matches, the report merges both
    # (`lgnn.bench.store.Layout`). None: the output folder alone.
    base: str | None = None
    # Compile with most of XLA's optimisation passes off (JAX's
    # `jax_disable_most_optimizations`) for the whole run: where every program runs for
    # milliseconds (the quick profile), the passes cost more than they save. They change
    # no result beyond round-off (the quick profile's tables agree to every printed
    # digit either way, docs/benchmark.md). Not in any record key.
    disable_xla_optimisations: bool = False


# The shipped profiles: TOML files beside this module (`load_profile`).
PROFILE_NAMES = ("quick", "full")


def load_profile(source: str | os.PathLike, overrides=(), add: tuple[str, ...] = ()) -> Profile:
    """A profile from a shipped name (`quick`, `full`) or a TOML config file, with
    `KEY=VALUE` overrides (`lgnn.bench.settings`; an unknown key is a one-line
    `ConfigError` naming it). A config file starts from the shipped profile its
    `profile` key names (default `quick`) and sets `Profile`'s fields over it: `name`
    (default: the file's stem), `seeds`, `train_scenes`, `scenes`, `stages`, `base`,
    `[[grid]]` entries (replacing `GRID`), `[[add]]` entries (added to the grid, `GRID`
    or the config's), and one table per settings group (`[training.data]`,
    `[training.train]`, `[evaluate]`, `[speed]`, `[scaling]`, `[mass]`). Scene files,
    `base` and `file.py:attribute` model references are relative to the config's
    directory; a `module:attribute` or `file.py:attribute` model is imported and
    registered (`lgnn.learn.models.load_spec`) and the grid names it by its spec's name.

    `add` names more models to add, as `[[add]]` entries of their model alone. An added
    entry's `train_scene` defaults to `TRAINING_SCENE`, its `eval_scenes` to its
    training scene's grid (`added_entry`); it passes a profile's `models` selection;
    an override `add.KEY=VALUE` sets `KEY` of every added entry (e.g. `add.epochs=20`)."""
    from lgnn.bench import settings

    def shipped(name: str) -> dict:
        return tomllib.loads(resources.files("lgnn.bench.profiles").joinpath(f"{name}.toml").read_text())

    if str(source) in PROFILE_NAMES:
        data, base = shipped(str(source)), None
    else:
        path = Path(source)
        data, base = settings.read_toml(path), path.resolve().parent
        profile = data.pop("profile", "quick")
        if profile not in PROFILE_NAMES:
            raise ConfigError(f"{path}: profile {profile!r} is not a shipped profile (choose from {', '.join(PROFILE_NAMES)})")
        base_profile = {**shipped(profile), "name": path.stem}
        if "grid" in data and "models" not in data:
            base_profile.pop("models", None)  # a grid of one's own is kept whole, not filtered by the shipped profile's models
        data = settings.merged(base_profile, data)
    added = data.pop("add", [])
    if not isinstance(added, list) or not all(isinstance(entry, dict) for entry in added):
        raise ConfigError("setting 'add' must be a list of tables ([[add]] entries)")
    added = [*added, *({"model": model} for model in add)]
    entry_overrides = [text.partition(".")[2] for text in overrides if text.strip().startswith("add.")]
    data = settings.apply_overrides(data, [text for text in overrides if not text.strip().startswith("add.")])
    added = [settings.build(GridEntry, added_entry(settings.apply_overrides(entry, entry_overrides)), f"add[{k}].") for k, entry in enumerate(added)]
    profile = settings.build(Profile, data)
    if added:
        profile = dataclasses.replace(profile, grid=(*profile.grid, *added),
                                      models=None if profile.models is None else (*profile.models, *(e.model for e in added)))
    profile = _resolved(profile, base)
    _check_names(profile)
    return profile


def added_entry(entry: dict) -> dict:
    """An `[[add]]` table with its defaults filled in: trained on `TRAINING_SCENE`,
    evaluated on its training scene's transfer scenes (`TRANSFER_SCENES`,
    `SPATIAL_TRANSFER_SCENES`; another training scene: itself alone)."""
    train_scene = entry.get("train_scene", TRAINING_SCENE)
    grids = {TRAINING_SCENE: TRANSFER_SCENES, SPATIAL_TRAINING_SCENE: SPATIAL_TRANSFER_SCENES}
    return {"train_scene": train_scene, "eval_scenes": list(grids.get(train_scene, (train_scene,))), **entry}


def _check_names(profile: Profile) -> None:
    """`ConfigError` for a name that no stage could use, before any stage starts: a
    grid entry's unknown model or missing scene, a selection (`scenes`, `train_scenes`,
    `models`) that keeps nothing the grid has, a stage's unknown scene, no seeds."""
    from lgnn.learn.models import model_names

    if not profile.seeds:
        raise ConfigError("setting 'seeds' must name at least one training seed")
    for k, entry in enumerate(profile.grid):
        if entry.model not in model_names():
            raise ConfigError(f"grid[{k}]: unknown model {entry.model!r} (choose from {', '.join(model_names())}, or module:attribute)")
        for name in (entry.train_scene, *entry.eval_scenes):
            try:
                check_scene_name(name)
            except SceneError as err:
                raise ConfigError(f"grid[{k}]: {err}") from None
    unknown_tracks = sorted(set(profile.tracks or ()) - set(TRACKS))
    if unknown_tracks:
        raise ConfigError(f"setting 'tracks': unknown track {unknown_tracks[0]!r} (choose from {', '.join(TRACKS)})")
    unknown_models = sorted(set(profile.models or ()) - set(model_names()))
    if unknown_models:
        raise ConfigError(f"setting 'models': unknown model {unknown_models[0]!r} (choose from {', '.join(model_names())})")
    # A selection filters the grid (a shipped profile's may name scenes a user's grid lacks), but must keep something.
    in_grid = {"scenes": {n for e in profile.grid for n in e.eval_scenes}, "train_scenes": {e.train_scene for e in profile.grid},
               "models": {e.model for e in profile.grid}, "tracks": {e.track for e in profile.grid}}
    for key, known in in_grid.items():
        selected = getattr(profile, key)
        if selected is not None and not set(selected) & known:
            raise ConfigError(f"setting {key!r}: {', '.join(selected) or 'none'} keeps nothing of the grid (which has {', '.join(sorted(known))})")
    for key, names in (("scenes", profile.scenes or ()), ("train_scenes", profile.train_scenes or ()), ("speed.scenes", profile.speed.scenes),
                       ("scaling.throughput_scenes", profile.scaling.throughput_scenes), ("mass.scenes", profile.mass.scenes)):
        for name in names:
            try:
                check_scene_name(name)
            except SceneError as err:
                raise ConfigError(f"setting {key!r}: {err}") from None


def _resolved(profile: Profile, base: Path | None) -> Profile:
    """The profile with scene files as paths from here and model references registered."""

    def scene(name: str) -> str:
        if base is None or not name.endswith(".json"):
            return name
        path = (base / name).resolve()
        relative = os.path.relpath(path)
        return path.as_posix() if relative.startswith("..") else Path(relative).as_posix()

    def scenes(names):
        return None if names is None else tuple(scene(n) for n in names)

    def model(name: str) -> str:
        return load_spec(name, base).name if ":" in name else name

    entries = tuple(dataclasses.replace(e, model=model(e.model), train_scene=scene(e.train_scene), eval_scenes=scenes(e.eval_scenes)) for e in profile.grid)
    models = None if profile.models is None else tuple(dict.fromkeys(map(model, profile.models)))
    results = None if profile.base is None else str(Path(base or ".", profile.base))
    predictions = tuple(str(Path(base or ".", path)) for path in profile.predictions)
    return dataclasses.replace(profile, grid=entries, train_scenes=scenes(profile.train_scenes), scenes=scenes(profile.scenes), models=models,
                               base=results, predictions=predictions)


PROFILES = {name: load_profile(name) for name in PROFILE_NAMES}


def get_profile(name: str) -> Profile:
    if name not in PROFILES:
        raise ConfigError(f"unknown benchmark profile {name!r} (choose from {', '.join(PROFILES)})")
    return PROFILES[name]


def _entries(profile: Profile) -> list[GridEntry]:
    return [e for e in profile.grid if (profile.train_scenes is None or e.train_scene in profile.train_scenes)
            and (profile.models is None or e.model in profile.models) and (profile.tracks is None or e.track in profile.tracks)]


def _job(entry: GridEntry, seed: int) -> TrainingJob:
    return TrainingJob(entry.model, entry.train_scene, seed, entry.varied_draws)


def entry_seeds(profile: Profile, entry: GridEntry) -> tuple[int, ...]:
    """The training seeds of a grid entry: its own, else the profile's."""
    return profile.seeds if entry.seeds is None else entry.seeds


def training_jobs(profile: Profile) -> list[TrainingJob]:
    return list(dict.fromkeys(_job(e, seed) for e in _entries(profile) for seed in entry_seeds(profile, e)))


def train_config(profile: Profile, job: TrainingJob) -> TrainConfig:
    """The training settings of a job: the profile's `training.train` with the job's seed
    and the budget (epochs, minutes) of the first grid entry that trains it, where it
    gives one."""
    entry = next((e for e in _entries(profile) if _job(e, job.seed) == job), None)
    budget = {} if entry is None else {name: getattr(entry, name) for name in ("epochs", "minutes") if getattr(entry, name) is not None}
    return dataclasses.replace(profile.training.train, seed=job.seed, **budget)


def evaluation_pairs(profile: Profile) -> list[Pair]:
    pairs = []
    for entry in _entries(profile):
        for seed in entry_seeds(profile, entry):
            for scene in entry.eval_scenes:
                if profile.scenes is None or scene in profile.scenes:
                    pairs.append(Pair(_job(entry, seed), scene))
                    if entry.unprojected:
                        pairs.append(Pair(_job(entry, seed), scene, projected=False))
    return pairs


def evaluation_scenes(profile: Profile) -> list[str]:
    return list(dict.fromkeys(p.scene for p in evaluation_pairs(profile)))


def evaluated_jobs(profile: Profile, scene_name: str) -> list[TrainingJob]:
    """The jobs the grid evaluates on `scene_name` (the entries whose `eval_scenes` name
    it: the spatial entries on 3D scenes, CLNN on its own training scene only), whether
    or not the profile's `scenes` keep it, in `training_jobs` order."""
    return [_job(e, seed) for e in _entries(profile) if scene_name in e.eval_scenes for seed in entry_seeds(profile, e)]


def lgnn_job(profile: Profile, scene_name: str | None = None) -> TrainingJob:
    """The model whose learned mass matrix (on `scene_name`) and cost against size are
    measured: LGNN trained on the main training scene of the scene's dimension
    (`TRAINING_SCENES`: chain4, chain4-3d in 3D; chain4 without a scene), first seed."""
    dim = 2 if scene_name is None else get_scene(scene_name).dim
    return TrainingJob(MEASURED_MODEL, TRAINING_SCENES[dim], profile.seeds[0])


def model_order(profile: Profile) -> tuple[str, ...]:
    """Every model of the built-in grid and of the profile's, each once, in the order
    their grids first name them: the order of the report's columns and legends."""
    return tuple(dict.fromkeys(entry.model for entry in (*GRID, *profile.grid)))


def error_figures(profile: Profile) -> list[FigureGroup]:
    """The report's error-against-time figures: `ERROR_FIGURES`, then for the profile's
    evaluation scenes none of them draws, one figure per set of training scenes their
    models come from (a new scene is drawn, not only tabled)."""
    drawn = {scene for group in ERROR_FIGURES for scene in group.scenes}
    trained_on: dict[str, list[str]] = {}
    for pair in evaluation_pairs(profile):
        if pair.scene not in drawn:
            trained_on.setdefault(pair.scene, [])
            if pair.job.scene not in trained_on[pair.scene]:
                trained_on[pair.scene].append(pair.job.scene)
    groups: dict[tuple[str, ...], list[str]] = {}
    for scene, sources in trained_on.items():
        groups.setdefault(tuple(sources), []).append(scene)
    stem = lambda scene: re.sub(r"[^A-Za-z0-9]+", "", Path(scene).stem if scene.endswith(".json") else scene)  # noqa: E731
    extra = [FigureGroup(f"error_vs_time_{'_'.join(map(stem, scenes))}.png", tuple(scenes), sources[0] if len(sources) == 1 else "each")
             for sources, scenes in groups.items()]
    return [*ERROR_FIGURES, *extra]
