"""The whole benchmark: train every model of the grid (`lgnn.bench.grid`), evaluate it on
every scene against both ground truths, measure speed against error, cost against
size and the learned mass matrix, and write the report (`lgnn.bench.report`).

Stages are a registry: `STAGES` maps each name to its `Stage` (the settings it reads,
how it runs, how its records load and its section of the report), in the order `run`
runs them; `register_stage` adds one (a researcher's stage is run and reported like a
built-in). Stages are resumable: each output is a record written atomically, reused
when the settings it was made with match, redone otherwise; so stages may run apart,
on several machines, and be assembled by the report. With `workers` > 1 the training
groups and the evaluation (scene, model) parts run in that many child processes at
once (`lgnn.bench.parallel`), or, with the "ray" executor, as tasks of a Ray cluster
(`lgnn.bench.ray_executor`).

With a profile's `base` (a results folder read in place, `lgnn.bench.store.layout`),
`run` runs `BASE_STAGES` unless told otherwise: what puts a model beside the base's
rows; the base's speed, scaling and mass records are read, not remade.

Each call appends what it cost (commit, versions, device, wall seconds per stage) to
`OUT/benchmark/run.json` (`lgnn.bench.run_record`).
"""

from __future__ import annotations

import contextlib
import dataclasses
from pathlib import Path
from typing import Any, Callable

from lgnn.bench import report
from lgnn.bench.grid import Pair, TrainingJob
from lgnn.bench.profiles import Profile, evaluation_pairs, evaluation_scenes, training_jobs
from lgnn.bench import run_record, store
from lgnn.bench.parallel import run_split
from lgnn.runtime import release_compiled_programs, xla_optimisations_off
from lgnn.bench.stages.evaluate import evaluate_group, evaluate_scene, truth_cost, truth_recorded
from lgnn.bench.stages.external import check_predictions, evaluate_external, read_predictions
from lgnn.bench.stages.mass import mass_matrices
from lgnn.bench.stages.scaling import scaling
from lgnn.bench.stages.speed import speed_error
from lgnn.bench.stages.train import prepare_datasets, train_jobs
from lgnn.bench.store import default_out
from lgnn.errors import ConfigError
from lgnn.learn.checkpoints import seconds_per_epoch
from lgnn.scene import get_scene


@dataclasses.dataclass(frozen=True)
class StageRun:
    """What one `run` call asks of every stage: the profile, the output directory, the
    selected training jobs, the selected evaluation scenes (`scenes_given`: whether
    `--scene` narrowed them), and how to run (progress bars, child processes)."""

    profile: Profile
    out: Path
    jobs: list[TrainingJob]
    scenes: list[str]
    scenes_given: bool
    progress: bool
    workers: int
    profile_argv: list[str] | None
    # The command that asked for this run, as the report's header names it (None: a
    # call of `run` from Python).
    command: str | None = None
    # Where split parts run: "local" (child processes, `lgnn.bench.parallel`) or "ray"
    # (Ray tasks, `lgnn.bench.ray_executor`; parts split even with one worker).
    executor: str = "local"
    # The stages this run runs (a stage may do a later one's work early: `_train`).
    stages: tuple[str, ...] = ()

    @property
    def split(self) -> bool:
        """Whether training and evaluation run as parts (child processes or Ray tasks)."""
        return self.workers > 1 or self.executor == "ray"

    def run_split(self, stage: str, parts: dict[str, list[str]], after: tuple[tuple[str, dict[str, list[str]]], ...] = ()) -> None:
        """Run `parts` of `stage`, then `after`'s (`(stage, parts)`), on this run's executor."""
        if self.executor == "ray":
            from lgnn.bench import ray_executor

            ray_executor.run_split(stage, parts, self.profile_argv, self.out, self.workers, after)
        else:
            run_split(stage, parts, self.profile_argv, self.out, self.workers, after)

    def keeps(self, scene: str) -> bool:
        """Whether a stage's scene is selected (every scene unless `--scene` named some)."""
        return not self.scenes_given or scene in self.scenes


@dataclasses.dataclass(frozen=True)
class Stage:
    """One benchmark stage: `run(StageRun)` writes its records under `out`;
    `settings(profile)` is the settings dataclass its records are keyed on (None: it
    reads the others'); `load(profile, out)` its records for the report and
    `section(profile, out, records) -> markdown lines` its part of `README.md` (None:
    the report's own body shows it: the built-in stages' tables and figures)."""

    name: str
    run: Callable[[StageRun], None]
    settings: Callable[[Profile], Any] | None = None
    load: Callable[[Profile, Path], Any] | None = None
    section: Callable[[Profile, Path, Any], list[str]] | None = None


def _train(request: StageRun) -> None:
    profile, out = request.profile, request.out
    if request.split:
        groups: dict[str, list[str]] = {}
        for job in request.jobs:
            groups.setdefault(job.group, []).append(job.name)
        prepare_datasets(profile, request.jobs, out, request.progress)
        # The evaluation's ground truths need no model: with the truth stage to come, they
        # are queued behind the training groups, so they take the workers the groups
        # leave (a group's GPU program leaves the host's cores idle, and the references
        # are CPU work: chain100-3d's MuJoCo C reference takes 6.6 minutes of 16 cores).
        after = (("truth", _truth_parts(request)),) if "truth" in request.stages else ()
        request.run_split("train", {name: [a for j in names for a in ("--job", j)] for name, names in groups.items()}, after)
    else:
        train_jobs(profile, request.jobs, out, request.progress)


def _truth(request: StageRun) -> None:
    """Each selected scene's ground truth (kept in the dataset cache) and ground-truth
    record, before any model is evaluated there: in split runs one part per scene, the
    costliest reference first (those `_train` did not already finish). In one process
    with the evaluate stage to come, nothing: that stage computes each scene's ground
    truth while the scene's models roll out (`evaluate_group`)."""
    if request.split:
        parts = _truth_parts(request)
        if parts:
            request.run_split("truth", parts)
    elif "evaluate" not in request.stages:
        for scene in _scenes_of_jobs(request):
            evaluate_scene(request.profile, scene, request.out, request.progress)


def _scenes_of_jobs(request: StageRun) -> list[str]:
    """The selected scenes on which a selected training job is evaluated."""
    selected = set(request.jobs)
    evaluated = {pair.scene for pair in evaluation_pairs(request.profile) if pair.job in selected}
    return [scene for scene in request.scenes if scene in evaluated]


def _truth_parts(request: StageRun) -> dict[str, list[str]]:
    """`{scene: ["--scene", scene]}` of the selected jobs' scenes (`_scenes_of_jobs`)
    whose ground-truth record is not yet written, the costliest reference first
    (`truth_cost`)."""
    missing = [scene for scene in _scenes_of_jobs(request) if not truth_recorded(request.profile, scene, request.out)]
    return {scene: ["--scene", scene] for scene in sorted(missing, key=lambda scene: -truth_cost(request.profile, scene))}


def _evaluate(request: StageRun) -> None:
    profile, out = request.profile, request.out
    by_scene = {scene: _seed_groups(profile, scene, request.jobs) for scene in request.scenes}
    if request.split:
        # One part per (scene, model's seeds); scenes interleaved, so the first parts
        # to start compute different scenes' ground truths (`ground_truth`: one
        # process computes a scene's, the others wait and read it). Then the costliest
        # first (`_rollout_cost`; parts of no known cost keep that order, last): on one
        # H200 the last parts to end were LGN's on the 100-link chains, which the
        # interleaving alone had started 1.5-2.5 minutes in.
        parts, costs, layout = {}, {}, store.layout(profile, out)
        for rank in range(max(map(len, by_scene.values()), default=0)):
            for scene, groups in by_scene.items():
                if rank < len(groups):
                    name, pairs = groups[rank]
                    parts[f"{scene}-{name}"] = ["--scene", scene, *(a for j in dict.fromkeys(p.job.name for p in pairs) for a in ("--job", j))]
                    costs[f"{scene}-{name}"] = _rollout_cost(layout, scene, pairs)
        request.run_split("evaluate", {name: parts[name] for name in sorted(parts, key=lambda name: -costs[name])})
    else:
        for scene, groups in by_scene.items():
            # The models first: their rollouts run while the scene's ground truth is
            # computed (`evaluate_group`), which the scene's own record then reuses.
            for _, pairs in groups:
                evaluate_group(profile, pairs, out, request.progress)
            evaluate_scene(profile, scene, out, request.progress)
    # Predictions made outside lgnn (`--add-predictions`), here: no model to roll out, a
    # scoring against the ground truth the scene's parts computed or read.
    for path in profile.predictions:
        if read_predictions(profile, path).scene in request.scenes:
            evaluate_external(profile, path, out, request.progress)


def _rollout_cost(layout: store.Layout, scene: str, pairs: list[Pair]) -> float:
    """An evaluation part's cost in arbitrary units, to start the longest first: its
    model's training seconds per epoch (the slowest seed's checkpoint in `layout`: how
    dear its acceleration is, measured where it trained) times the scene's nodes; 0
    where no checkpoint says."""
    rates = [rate for rate in (seconds_per_epoch(layout.checkpoint(pair.job)) for pair in pairs) if rate is not None]
    return max(rates, default=0.0) * get_scene(scene).n_nodes


def _speed(request: StageRun) -> None:
    for scene in request.profile.speed.scenes:
        if request.keeps(scene):
            speed_error(request.profile, scene, request.out)


def _scaling(request: StageRun) -> None:
    if not request.scenes_given:  # chains of its own lengths, no evaluation scene
        scaling(request.profile, request.out)


def _mass(request: StageRun) -> None:
    for scene in request.profile.mass.scenes:
        if request.keeps(scene):
            mass_matrices(request.profile, scene, request.out)


def _report(request: StageRun) -> None:
    sections = [(stage.name, stage.settings, stage.load, stage.section) for stage in STAGES.values() if stage.section is not None]
    report.write(request.profile, request.out, sections, request.command)


STAGES: dict[str, Stage] = {
    stage.name: stage
    for stage in (
        Stage("train", _train, lambda profile: profile.training),
        Stage("truth", _truth, lambda profile: profile.evaluate),
        Stage("evaluate", _evaluate, lambda profile: profile.evaluate),
        Stage("speed", _speed, lambda profile: profile.speed),
        Stage("scaling", _scaling, lambda profile: profile.scaling),
        Stage("mass", _mass, lambda profile: profile.mass),
        Stage("report", _report),
    )
}


# Where split parts run (`lgnn benchmark --executor`): child processes of this machine, or Ray tasks.
EXECUTORS = ("local", "ray")

# The stages a run with a `base` folder runs unless told otherwise.
BASE_STAGES = ("train", "truth", "evaluate", "report")


def register_stage(stage: Stage) -> None:
    """Add `stage` to `STAGES`, before the report (which reads every other stage's
    records); a name already registered is a `ConfigError`."""
    if stage.name in STAGES:
        raise ConfigError(f"benchmark stage {stage.name!r} is already registered")
    report_stage = STAGES.pop("report")
    STAGES[stage.name] = stage
    STAGES["report"] = report_stage


def run(profile: Profile, out: Path | None = None, stages=None, jobs: list[str] | None = None, scenes: list[str] | None = None,
        progress: bool = True, workers: int = 1, profile_argv: list[str] | None = None, command: str | None = None,
        executor: str = "local", address: str | None = None) -> Path:
    """Run the chosen stages of the benchmark (default: the profile's `stages`, else
    `BASE_STAGES` with a `base` folder, else all of `STAGES`), in registry order,
    restricted to the named training jobs and evaluation scenes when given; returns the
    output directory. With `workers` > 1, training (one part per model and training
    scene) and evaluation (one part per scene and model's seeds) run in child `lgnn
    benchmark` processes given `profile_argv`, the arguments that select this profile.
    `executor` "ray": those processes run as Ray tasks (`lgnn.bench.ray_executor`; on
    the cluster at `address`, else a Ray started for the run), whatever `workers`.
    `command`: what the report's header says wrote it."""
    if executor not in EXECUTORS:
        raise ConfigError(f"unknown executor {executor!r} (choose from {', '.join(EXECUTORS)})")
    if address is not None and executor != "ray":
        raise ConfigError("--address names a Ray cluster: give it with --executor ray")
    if (workers > 1 or executor == "ray") and profile_argv is None:
        raise ConfigError("parallel workers need the profile's command-line arguments (profile_argv)")
    stages = stages or profile.stages or (BASE_STAGES if profile.base is not None else tuple(STAGES))
    out = Path(out) if out is not None else default_out(profile)
    store.layout(profile, out)  # a base that is no folder, or is `out`, fails before any stage
    check_predictions(profile)  # likewise a predictions file that answers another evaluation
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
    request = StageRun(profile, out, [j for j in all_jobs if not jobs or j.name in jobs],
                       [s for s in evaluation_scenes(profile) if not scenes or s in scenes], bool(scenes), progress, workers, profile_argv, command,
                       executor, tuple(stages))
    out.mkdir(parents=True, exist_ok=True)
    with xla_optimisations_off(profile.disable_xla_optimisations), run_record.recording(out, command) as timed, \
            _executor_session(executor, address):
        for stage in list(STAGES.values()):
            if stage.name in stages:
                with timed(stage.name):
                    stage.run(request)
                    release_compiled_programs()  # a long run's compiles (`lgnn.runtime.MAPPINGS_KEPT`)
    return out


def _executor_session(executor: str, address: str | None):
    """For the whole run: connected to Ray (`ray_executor.connected`) with "ray"."""
    if executor == "ray":
        from lgnn.bench import ray_executor

        return ray_executor.connected(address)
    return contextlib.nullcontext()


def _seed_groups(profile: Profile, scene: str, jobs: list[TrainingJob]) -> list[tuple[str, list[Pair]]]:
    """`(model-training scene, [pairs])` of the selected jobs' pairs on `scene`, one
    entry per model and training scene (its seeds, evaluated together)."""
    selected = set(jobs)
    groups: dict[str, list[Pair]] = {}
    for pair in evaluation_pairs(profile):
        if pair.scene == scene and pair.job in selected:
            groups.setdefault(pair.job.group, []).append(pair)
    return list(groups.items())
