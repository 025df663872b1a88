"""The whole benchmark: train every model of the grid (`lgnn.bench.grid`), evaluate it on
every scene against both ground truths, measure speed against error, cost against
size and the learned mass matrix, and write the report (`lgnn.bench.report`).

Stages (`STAGES`, one module each under `lgnn.bench.stages`) are resumable: each
output is a record written atomically, reused when the settings it was made with
match, redone otherwise; so stages may run apart, on several machines, and be
assembled by the report. With `workers` > 1 the training groups and the evaluation
(scene, model) parts run in that many child processes at once (`lgnn.bench.parallel`).
"""

from __future__ import annotations

from pathlib import Path

from lgnn.bench import report
from lgnn.bench.grid import Pair, Profile, TrainingJob, evaluation_pairs, evaluation_scenes, training_jobs
from lgnn.bench.parallel import run_split
from lgnn.bench.stages.evaluate import evaluate_group, evaluate_scene
from lgnn.bench.stages.mass import mass_matrices
from lgnn.bench.stages.scaling import scaling
from lgnn.bench.stages.speed import speed_error
from lgnn.bench.stages.train import prepare_datasets, train_jobs
from lgnn.bench.store import default_out
from lgnn.errors import ConfigError

STAGES = ("train", "evaluate", "speed", "scaling", "mass", "report")


def run(profile: Profile, out: Path | None = None, stages=None, jobs: list[str] | None = None, scenes: list[str] | None = None,
        progress: bool = True, workers: int = 1, profile_argv: list[str] | None = None) -> Path:
    """Run the chosen stages of the benchmark (default: the profile's `stages`, or all),
    restricted to the named training jobs and evaluation scenes when given; returns
    the output directory. With `workers` > 1, training (one part per model and
    training scene) and evaluation (one part per scene and model's seeds) run in child `lgnn benchmark`
    processes given `profile_argv`, the arguments that select this profile."""
    if workers > 1 and profile_argv is None:
        raise ConfigError("parallel workers need the profile's command-line arguments (profile_argv)")
    stages = stages or profile.stages or STAGES
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
    if "train" in stages and workers > 1:
        groups: dict[str, list[str]] = {}
        for job in selected_jobs:
            groups.setdefault(f"{job.model}-{job.scene}", []).append(job.name)
        prepare_datasets(profile, selected_jobs, out, progress)
        run_split("train", {name: [a for j in names for a in ("--job", j)] for name, names in groups.items()}, profile_argv, out, workers)
    elif "train" in stages:
        train_jobs(profile, selected_jobs, out, progress)
    if "evaluate" in stages:
        by_scene = {scene: _seed_groups(profile, scene, selected_jobs) for scene in selected_scenes}
        if workers > 1:
            # One part per (scene, model's seeds); scenes interleaved, so the first parts
            # to start compute different scenes' ground truths (`ground_truth`: one
            # process computes a scene's, the others wait and read it).
            parts = {}
            for rank in range(max(map(len, by_scene.values()), default=0)):
                for scene, groups in by_scene.items():
                    if rank < len(groups):
                        name, pairs = groups[rank]
                        parts[f"{scene}-{name}"] = ["--scene", scene, *(a for j in dict.fromkeys(p.job.name for p in pairs) for a in ("--job", j))]
            run_split("evaluate", parts, profile_argv, out, workers)
        else:
            for scene, groups in by_scene.items():
                # The models first: their rollouts run while the scene's ground truth is
                # computed (`evaluate_group`), which the scene's own record then reuses.
                for _, pairs in groups:
                    evaluate_group(profile, pairs, out, progress)
                evaluate_scene(profile, scene, out, progress)
    if "speed" in stages:
        for scene in profile.speed.scenes:
            if not scenes or scene in scenes:
                speed_error(profile, scene, out)
    if "scaling" in stages and not scenes:
        scaling(profile, out)
    if "mass" in stages:
        for scene in profile.mass.scenes:
            if not scenes or scene in scenes:
                mass_matrices(profile, scene, out)
    if "report" in stages:
        report.write(profile, out)
    return out


def _seed_groups(profile: Profile, scene: str, jobs: list[TrainingJob]) -> list[tuple[str, list[Pair]]]:
    """`(model-training scene, [pairs])` of the selected jobs' pairs on `scene`, one
    entry per model and training scene (its seeds, evaluated together)."""
    selected = set(jobs)
    groups: dict[str, list[Pair]] = {}
    for pair in evaluation_pairs(profile):
        if pair.scene == scene and pair.job in selected:
            groups.setdefault(f"{pair.job.model}-{pair.job.scene}", []).append(pair)
    return list(groups.items())
