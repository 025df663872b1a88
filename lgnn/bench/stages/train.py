"""Training stage: a checkpoint per (model, training scene, seed).

`train_job` trains with `lgnn.learn.train.train` (resuming an interrupted run); a
finished checkpoint whose model, optimisation (`train.training_key`) and data settings
match the profile's `TrainSettings` is reused, one made with other settings or
unreadable is replaced. `load_checkpoints` gives the report the finished ones.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp

from lgnn.bench.grid import Profile, TrainingJob, training_jobs
from lgnn.bench.store import Layout, log
from lgnn.errors import CheckpointError
from lgnn.learn import data, models, train
from lgnn.scene import get_scene


def _job_settings(profile: Profile, job: TrainingJob):
    scene = get_scene(job.scene)
    model = models.ModelConfig.for_scene(job.model, scene)
    data_config = dataclasses.replace(profile.training.data, scene=job.scene)
    train_config = dataclasses.replace(profile.training.train, seed=job.seed)
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


def load_checkpoints(profile: Profile, out: Path) -> list[tuple[TrainingJob, train.TrainState]]:
    """`(job, training state)` of every job of the profile with a checkpoint under `out`."""
    layout = Layout(out)
    return [(job, train.load_checkpoint(layout.checkpoint(job))[0]) for job in training_jobs(profile) if layout.checkpoint(job).exists()]


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
