"""Training stage: a checkpoint per (model, training scene, seed).

`train_jobs` trains the seeds of each (model, training scene) together, one compiled
program (`lgnn.learn.train.train_seeds`), resuming interrupted runs from their
checkpoints (written every `checkpoint_every` epochs, so a run cut off by a 10-minute
limit goes on where it stopped); a finished checkpoint whose model, optimisation (`protocol.training_key`) and data settings
match the profile's `TrainSettings` is reused, one made with other settings or
unreadable is replaced. Each job is claimed before it trains (`lgnn.bench.claims`), so
processes sharing the output folder train it once. `load_checkpoints` gives the
report the finished ones.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from lgnn.bench.grid import LGNN_VARIANTS, TRAINING_SCENE, TrainingJob
from lgnn.bench.profiles import Profile, training_jobs
from lgnn.bench.profiles import train_config as train_config_of
from lgnn.bench import claims, store
from lgnn.bench.store import Layout, log
from lgnn.errors import CheckpointError
from lgnn.learn import data, models, protocol, train
from lgnn.scene import get_scene


def job_settings(profile: Profile, job: TrainingJob):
    """`(scene, model config, data config, train config)` of a training job: what its
    checkpoint is trained with (and what tools that time its epochs rebuild)."""
    scene = get_scene(job.scene)
    # On varied draws (the transfer track), with each link's mass, inertia and length
    # where the model takes them: without them its links are indistinguishable.
    features = {"link_features": True} if job.varied_draws and models.get_spec(job.model).link_features else {}
    model = models.ModelConfig.for_scene(job.model, scene, **features)
    data_config = dataclasses.replace(profile.training.data_for(job.scene), varied_draws=job.varied_draws)
    train_config = train_config_of(profile, job)
    return scene, model, data_config, train_config


def made_with(meta: dict, settings) -> bool:
    """Whether a checkpoint's meta was trained with a job's `settings` (`job_settings`),
    budgets apart (`protocol.training_key`): a checkpoint missing a setting was not."""
    _, model, data_config, train_config = settings
    return meta["model"] == model.to_dict() and meta.get("train") == protocol.training_key(train_config) and meta.get("data") == data_config.to_dict()


def _resumable(job: TrainingJob, path: Path, settings) -> bool | None:
    """None if the job's checkpoint is finished with its `settings` (`job_settings`:
    reuse it), True if it can be resumed, False if training starts afresh."""
    train_config = settings[3]
    if not path.exists():
        return False
    try:
        state, meta = train.load_checkpoint(path)
    except CheckpointError as err:
        log(f"warning: {err}; retraining {job.name}")
        return False
    same = made_with(meta, settings)
    if same and not protocol.finished(state, train_config) and state.params is None:
        log(f"train {job.name}: its unfinished checkpoint is kept without its optimiser state; retraining")
        return False
    if same and protocol.finished(state, train_config):
        log(f"train {job.name}: reusing finished checkpoint ({state.epoch} epochs, best validation MSE {state.best_val:.3g})")
        return None
    if same:
        log(f"train {job.name}: resuming at epoch {state.epoch}")
        return True
    log(f"train {job.name}: checkpoint was made with other settings; retraining")
    return False


def train_jobs(profile: Profile, jobs: list[TrainingJob], out: Path, progress: bool = True) -> list[Path]:
    """Checkpoints of `jobs` (in order). The seeds of one (model, training scene) are
    trained together, one compiled program (`train.train_seeds`), each resumed from its
    own checkpoint or started afresh; finished checkpoints are reused."""
    layout = store.layout(profile, out)
    groups: dict[tuple[str, str], list[TrainingJob]] = {}
    for job in jobs:
        if layout.in_base(layout.checkpoint(job)) is not None:
            log(f"train {job.name}: the base folder's checkpoint, read in place, never trained")
            continue
        groups.setdefault(job.group, []).append(job)
    for group in groups.values():
        # Each job claimed (`lgnn.bench.claims`): one trained by another process (a second
        # `lgnn benchmark` on this folder) is waited for, then reused or resumed.
        claims.each_once(group, layout.checkpoint, lambda claimed: _train_group(layout, profile, claimed, progress), "train")
    return [layout.found(layout.checkpoint(job)) for job in jobs]


def _train_group(layout: Layout, profile: Profile, group: list[TrainingJob], progress: bool) -> None:
    """Train (or resume) the jobs of one (model, training scene) group that lack a
    finished checkpoint, their seeds together."""
    paths = [layout.checkpoint(job) for job in group]
    for path in paths:
        path.parent.mkdir(parents=True, exist_ok=True)
    settings = [job_settings(profile, job) for job in group]
    plans = [_resumable(job, path, setting) for job, path, setting in zip(group, paths, settings)]
    todo = [(job, path, plan, setting) for job, path, plan, setting in zip(group, paths, plans, settings) if plan is not None]
    if not todo:
        return
    fresh = [job for job, _, plan, _ in todo if not plan]
    for job, path, plan, _ in todo:
        if not plan and path.exists():
            path.unlink()  # replaced: other settings or unreadable
    # The seeds of a group share everything but the seed: the first one's model and
    # data (and the data's scenes) serve them all.
    _, model, data_config, train_config = todo[0][3]
    dataset = data.load_or_generate(data_config, layout.datasets, progress=progress)
    if fresh:
        log(f"train {', '.join(j.name for j in fresh)}: {len(dataset.train)} training states, budget {train_config.epochs} epochs"
            + (f", plateau: no {train_config.min_improvement:.0%} gain in {train_config.patience} epochs" if train_config.min_improvement else "")
            + (f" / {train_config.minutes:g} min" if train_config.minutes else ""))
    configs = [setting[3] for _, _, _, setting in todo]
    states = train.train_seeds(model, configs, dataset, data.draw_scenes(data_config), outs=[path for _, path, _, _ in todo], data_config=data_config,
                               resume=True, progress=progress)
    for (job, _, _, _), state in zip(todo, states):
        log(f"train {job.name}: {state.epoch} epochs in {state.elapsed_s / 60:.1f} min, best validation MSE {state.best_val:.3g} (epoch {state.best_epoch})")


def prepare_datasets(profile: Profile, jobs: list[TrainingJob], out: Path, progress: bool = True) -> None:
    """Generate (or find cached) the training data of every training scene (and varied
    draws) of `jobs`, one at a time, before worker processes start: otherwise each of
    the groups sharing a scene generates the same data at once (on one H100 the 14
    groups of the full grid spent 10 minutes generating the four training scenes' data
    before their first epoch, 2026-11-24)."""
    for config in dict.fromkeys(job_settings(profile, job)[2] for job in jobs):
        with claims.once(data.cache_path(config, Layout(out).datasets)):  # a second driver reads it from the cache
            data.load_or_generate(config, Layout(out).datasets, progress=progress)


@dataclasses.dataclass(frozen=True)
class Trained:
    """A job's checkpoint as the report reads it once: the job, its training state
    (`train.load_checkpoint`) and the checkpoint's meta (environment, parameter count
    of one kept without its parameters)."""

    job: TrainingJob
    state: protocol.TrainState
    meta: dict


def load_checkpoints(profile: Profile, out: Path) -> list[Trained]:
    """`Trained` of every job of the profile with a checkpoint under `out` (or its base)."""
    layout = store.layout(profile, out)
    found = [(job, layout.found(layout.checkpoint(job))) for job in training_jobs(profile)]
    return [Trained(job, *train.load_checkpoint(path)) for job, path in found if path.exists()]


def default_lgnn(profile: Profile, out: Path, training_scene: str = TRAINING_SCENE,
                 checkpoints: list[Trained] | None = None) -> tuple[str | None, dict[str, float]]:
    """The default LGNN of one training scene (chain4; chain4-3d for the spatial grid),
    chosen from the training records: among `LGNN_VARIANTS` trained on `training_scene`
    with a checkpoint for every seed of the profile, the one with the lowest geometric
    mean over seeds of the best validation MSE (ties: the earlier, simpler variant).
    Returns `(name, {variant: that mean})`; name None when no variant has all its seeds.
    `checkpoints`: `load_checkpoints(profile, out)` where the caller has it already."""
    found: dict[str, list[float]] = {}
    for trained in load_checkpoints(profile, out) if checkpoints is None else checkpoints:
        job = trained.job
        if job.model in LGNN_VARIANTS and job.scene == training_scene and not job.varied_draws:
            found.setdefault(job.model, []).append(trained.state.best_val)
    scores = {v: float(np.exp(np.mean(np.log(found[v])))) for v in LGNN_VARIANTS if len(found.get(v, ())) == len(profile.seeds)}
    return (min(scores, key=lambda v: (scores[v], LGNN_VARIANTS.index(v))) if scores else None), scores
