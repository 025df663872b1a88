"""Training: Adam on the mean squared error of accelerations, with resumable checkpoints.

`train(model_config, train_config, dataset, out=CKPT)` fits a model to a `data.Dataset`
(float64 under x64; the caller enables it): each epoch shuffles the training states
with a key derived from `(seed, epoch)` and takes `len(train) // batch_size` Adam steps
(the remainder of a shuffle is dropped) in one `lax.scan` (a dataset of K varied draws:
each batch takes `batch_size / K` states of every draw, each scored with its own
draw's scene); the validation loss is
computed after every epoch; the parameters with the best validation loss are kept;
training stops at the epoch budget (the budget: it means the same on any machine),
after `patience` epochs without an improvement by the fraction `min_improvement` over
that window (the plateau rule), or at the optional minutes cap (a safety net). The
device runs `checkpoint_every` epochs per call, validation, best parameters and the
stopping rule included, with no host round trip between them; the host checks the
minutes cap and writes checkpoints between calls, while the next call runs.
`train_seeds` trains several seeds of one job in one compiled program (vmapped over
params and Adam states, the data shared), each seed's run equal to its own `train` run
to round-off.

The optimiser is the paper's Adam (peak learning rate 1e-3, batch 10) with a linear
warm-up, a per-step exponential decay and optional global-norm gradient clipping
(`lgnn.learn.protocol`: `TrainConfig`, `optimizer`; off by default, see `CLIP_NORM`). A rate or warm-up the
config leaves None follows one rule for the budget (`scheduled`: 1e-2 under 1000 Adam
steps, a warm-up of a fifth of them but at most 1000), filled in by `train_seeds` and
the benchmark's `TrainSettings`, so checkpoints hold the values trained with. Why: plain Adam from the paper's random start swung
the validation loss by orders of magnitude in the first epochs (issue 13). The cause
was the start, a learned mass matrix indefinite on the constraint tangent space (fixed
in `models`: LGNN's kinetic energy starts strictly convex, and the initial validation
MSE falls from 1e4-1e6 to ~20); the warm-up lets Adam's moments settle first. The loss is not normalised:
Adam is invariant to the scale of the loss, and the targets (O(10) with gravity 10)
keep MSE comparable with the paper's. After every `checkpoint_every` epochs the whole training state (params,
best params, Adam state, epoch, losses) is written atomically to `out`, so an
interrupted run resumed from it (`resume=True`) reaches the uninterrupted run's result
to round-off (the same arithmetic, in programs compiled for the two budgets).

A model's spec may carry its own recipe (`models.ModelSpec`): AdamW's weight decay in
place of Adam, Gaussian noise on the training inputs' free-node velocities (a fraction
of the training velocities' std per dimension, a fresh draw every step; the targets
stay the clean accelerations, so the model learns to be robust to the state errors a
rollout accumulates), and statistics of the training states it normalises by:
computed once before the first epoch, kept in the params, never stepped (the
optimiser sees only `models.split_statistics`'s trainable part).

Checkpoints (`lgnn.learn.checkpoints`: leaves by pytree path) hold the
whole training state; `load_checkpoint` rebuilds it from the model config and the
optimiser's template, for resuming, and refuses, with one `CheckpointError` line, a
file that is unreadable, corrupt or of another shape. Inference reads only the best
parameters, without the optimiser (`lgnn.learn.checkpoints.load_model`).
"""

from __future__ import annotations

import dataclasses
import functools
import os
import time
from pathlib import Path
from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optax

from lgnn.learn import checkpoints, models
from lgnn.learn.protocol import (LEGACY_OPTIMISATION, TrainConfig, TrainState, finished, optimizer, out_of_minutes, running_best, scheduled,
                                 training_key)
from lgnn import records
from lgnn.learn.data import DataConfig, Dataset
from lgnn.errors import CheckpointError, ConfigError
from lgnn.runtime import in_float64
from lgnn.scene import Scene

# The format `save_checkpoint` writes (`lgnn.learn.checkpoints`).
CHECKPOINT_FORMAT = checkpoints.FORMAT


def loss_fn(model: models.ModelConfig, scene: Scene):
    """`loss(params, q, qd, qdd)`: mean squared acceleration error over a batch (B, N, D)."""

    accel = jax.vmap(models.trainable_acceleration_fn(model, scene), in_axes=(None, 0, 0))

    def loss(params, q, qd, qdd):
        return jnp.mean((accel(params, q, qd) - qdd) ** 2)

    return loss


def _epoch(model, scenes: tuple[Scene, ...], config: TrainConfig):
    """`epoch(params, opt_state, arrays, key) -> (params, opt_state, mean loss)`: one
    shuffle of the training states, Adam steps in one `lax.scan` (unjitted;
    `compiled_epoch_fn` and `_chunk_fn` compile it). `arrays` holds `(q, qd, qdd)` of
    each of `scenes` (the varied draws of `lgnn.learn.data`, or the one scene): every
    step's batch takes `batch_size / len(scenes)` states of each, shuffled within it, so
    each step sees every draw; `min(len(q)) // that` steps (the remainder of a shuffle
    is dropped). With one scene this is the paper's shuffle of all states."""
    losses = [loss_fn(model, scene) for scene in scenes]
    opt = optimizer(config, model.spec.weight_decay)
    n_draws = len(scenes)
    per_draw = config.batch_size // n_draws
    free = np.zeros((scenes[0].n_nodes, 1))
    free[list(scenes[0].free_nodes)] = 1.0

    def step(carry, batch, noise_std):
        (params, opt_state), (draw_batches, key) = carry, batch
        # Only the trainable params are stepped; the statistics are constants.
        trainable, statistics = models.split_statistics(params)

        def loss(p):
            total = 0.0
            for k, (q, qd, qdd) in enumerate(draw_batches):
                if model.spec.velocity_noise:
                    noise_key = key if n_draws == 1 else jax.random.fold_in(key, k)
                    # In the states' precision: a float64 constant beside float32 states is refused.
                    scale = jnp.asarray(noise_std, qd.dtype) * jnp.asarray(free, qd.dtype)
                    qd = qd + scale * jax.random.normal(noise_key, qd.shape, qd.dtype)
                total = total + losses[k](models.join_statistics(p, statistics), q, qd, qdd)
            return total / n_draws

        value, grads = jax.value_and_grad(loss)(trainable)
        updates, opt_state = opt.update(grads, opt_state, trainable)
        return (models.join_statistics(optax.apply_updates(trainable, updates), statistics), opt_state), value

    def epoch(params, opt_state, arrays, key):
        n_batches = min(q.shape[0] for q, _, _ in arrays) // per_draw
        draw_batches = []
        for k, draw_arrays in enumerate(arrays):
            # One scene: the key itself, as every run before draws existed.
            draw_key = key if n_draws == 1 else jax.random.fold_in(key, 2 + k)
            order = jax.random.permutation(draw_key, draw_arrays[0].shape[0])[: n_batches * per_draw]
            draw_batches.append(tuple(a[order].reshape(n_batches, per_draw, *a.shape[1:]) for a in draw_arrays))
        # The recipe's input noise, per dimension a fraction of the training
        # velocities' spread over the free nodes (pinned ones are zero).
        velocities = jnp.concatenate([qd[:, list(scenes[0].free_nodes)] for _, qd, _ in arrays])
        noise_std = model.spec.velocity_noise * jnp.std(velocities, axis=(0, 1))
        keys = jax.random.split(jax.random.fold_in(key, 1), n_batches)
        (params, opt_state), values = jax.lax.scan(lambda c, b: step(c, b, noise_std), (params, opt_state), (tuple(draw_batches), keys))
        return params, opt_state, jnp.mean(values)

    return epoch


@functools.lru_cache(maxsize=16)
def _epoch_fn(model, scene, config: TrainConfig, vmapped: bool = False):
    draws_epoch = _epoch(model, (scene,), config)

    def epoch(params, opt_state, q, qd, qdd, key):
        return draws_epoch(params, opt_state, ((q, qd, qdd),), key)

    return jax.jit(jax.vmap(epoch, in_axes=(0, 0, None, None, None, 0)) if vmapped else epoch)


def compiled_epoch_fn(model: models.ModelConfig, scene: Scene, config: TrainConfig, vmapped: bool = False):
    """`epoch(params, opt_state, q, qd, qdd, key) -> (params, opt_state, mean loss)`,
    jitted and shared by every caller with the same optimisation settings (budgets and
    the seed do not matter): the benchmark's timing of an epoch and tools. `vmapped`:
    params, opt_state and key with a leading seed axis (the loss too). Training itself
    runs `_chunk_fn`, several of these epochs and their validation in one program."""
    return _epoch_fn(model, scene, _optimisation_only(config), vmapped)


def _optimisation_only(config: TrainConfig) -> TrainConfig:
    return dataclasses.replace(config, epochs=0, minutes=None, patience=1, min_improvement=0.0, checkpoint_every=1, seed=0)


def _validation_sse(model: models.ModelConfig, scene: Scene, chunk: int):
    """`sse(params, q, qd, qdd)`: the summed squared acceleration error over all states,
    `chunk` states vmapped at a time (memory against speed)."""

    def sse(params, q, qd, qdd):
        accel = models.acceleration_fn(model, params, scene)
        per_state = jax.lax.map(lambda s: jnp.sum((accel(s[0], s[1]) - s[2]) ** 2), (q, qd, qdd), batch_size=chunk)
        return jnp.sum(per_state)

    return sse


@functools.lru_cache(maxsize=16)
def evaluate_fn(model: models.ModelConfig, scene: Scene, chunk: int = 500):
    """`evaluate(params, q, qd, qdd) -> float` mean squared error over all states, one
    jitted program (`chunk` states vmapped at a time)."""
    sse = jax.jit(_validation_sse(model, scene, chunk))
    return lambda params, q, qd, qdd: float(sse(params, q, qd, qdd)) / q.size


class _Seeds(NamedTuple):
    """What a chunk of epochs carries per seed, on the device (leading seed axis)."""

    params: dict
    opt_state: tuple
    best_params: dict
    best_val: jax.Array
    best_epoch: jax.Array
    epoch: jax.Array
    # Training has ended for this seed (budget, early stopping, or the host's minutes
    # cap): the chunk leaves its state as it is.
    done: jax.Array
    # best_upto[e]: the lowest validation loss of epochs 1..e (inf before any), what the
    # plateau rule compares (`plateaued`); as long as the epoch budget.
    best_upto: jax.Array


class _Budget(NamedTuple):
    """The stopping rule's settings, as arguments (a changed budget does not recompile)."""

    epochs: jax.Array
    patience: jax.Array
    min_improvement: jax.Array


@functools.lru_cache(maxsize=16)
def _chunk_fn(model, scenes: tuple[Scene, ...], config: TrainConfig, epochs_per_call: int):
    """`chunk(seeds, budget, base_keys, train_arrays, val_arrays) -> (seeds, train_loss,
    val_loss, ran)`, the arrays `(q, qd, qdd)` of each of `scenes` (`_epoch`):
    `epochs_per_call` epochs of every seed in one compiled program,
    each with its validation loss, best parameters and the stopping rule, so the host
    is not consulted between epochs. A seed that stops mid-call (or was done) keeps its
    state; `ran` (S, K) says which epochs each seed ran; the losses are (S, K).
    The stopping rule is `stop_reason`'s (the minutes cap aside, which the host
    checks between calls)."""
    epoch = _epoch(model, scenes, config)
    sses = [_validation_sse(model, scene, config.val_chunk) for scene in scenes]

    def one_seed(seed: _Seeds, budget: _Budget, base_key, train_arrays, val_arrays):
        def one_epoch(seed: _Seeds):
            params, opt_state, train_loss = epoch(seed.params, seed.opt_state, train_arrays, jax.random.fold_in(base_key, seed.epoch))
            val = sum(sse(params, *arrays) for sse, arrays in zip(sses, val_arrays)) / sum(arrays[0].size for arrays in val_arrays)
            number = seed.epoch + 1
            improved = val < seed.best_val
            best_val = jnp.where(improved, val, seed.best_val)
            best_epoch = jnp.where(improved, number, seed.best_epoch)
            # NaN losses never count as a best (as `min` of the host's history skips them).
            best_so_far = jnp.fmin(seed.best_upto[seed.epoch], val)
            best_upto = seed.best_upto.at[number].set(best_so_far)
            start = number - budget.patience
            plateau = (start >= 1) & ~(best_so_far < (1 - budget.min_improvement) * best_upto[jnp.maximum(start, 0)])
            patience = number - best_epoch > budget.patience
            ended = (number >= budget.epochs) | jnp.where(budget.min_improvement > 0, plateau, patience)
            best_params = jax.tree.map(lambda new, old: jnp.where(improved, new, old), params, seed.best_params)
            return _Seeds(params, opt_state, best_params, best_val, best_epoch, number, ended, best_upto), train_loss, val

        def running(carry):
            i, seed, _ = carry
            return (i < epochs_per_call) & ~seed.done

        def step(carry):
            i, seed, (train_losses, val_losses, ran) = carry
            seed, train_loss, val = one_epoch(seed)
            return i + 1, seed, (train_losses.at[i].set(train_loss), val_losses.at[i].set(val), ran.at[i].set(True))

        # A while loop, not a scan: vmapped over seeds it runs while any seed runs and
        # keeps a stopped seed's state, and a call whose seeds all stop returns early.
        dtype = seed.best_val.dtype
        losses = (jnp.full(epochs_per_call, jnp.nan, dtype), jnp.full(epochs_per_call, jnp.nan, dtype), jnp.zeros(epochs_per_call, bool))
        _, seed, (train_loss, val, ran) = jax.lax.while_loop(running, step, (0, seed, losses))
        return seed, train_loss, val, ran

    return jax.jit(jax.vmap(one_seed, in_axes=(0, None, 0, None, None)))


def initial_state(model: models.ModelConfig, config: TrainConfig, statistics: dict | None = None) -> TrainState:
    """The untrained state: fresh params (with the training set's `statistics`, from
    `models.training_statistics`, where the model has any) and the optimiser's state
    of their trainable part."""
    params = models.with_statistics(models.init(jax.random.fold_in(jax.random.PRNGKey(config.seed), 0), model), statistics)
    return TrainState(params, fresh_optimiser_state(model, config, params), params, float("inf"), -1, 0, [], 0.0)


def fresh_optimiser_state(model: models.ModelConfig, config: TrainConfig, params: dict):
    """The optimiser's state before its first step on `params`' trainable part."""
    # Adam's initial state holds no rate or warm-up, only whether there is a schedule
    # (always, by the rule), so a config that leaves them to the rule has one too.
    return optimizer(scheduled(config, 1), model.spec.weight_decay).init(models.split_statistics(params)[0])


@in_float64
def train(
    model: models.ModelConfig,
    config: TrainConfig,
    dataset: Dataset,
    scene: Scene | Sequence[Scene],
    *,
    out: str | os.PathLike | None = None,
    data_config: DataConfig | None = None,
    resume: bool = False,
    progress: bool = False,
) -> TrainState:
    """Train (or resume training of) `model` on `dataset` of `scene` (or of its varied
    draws' scenes, `lgnn.learn.data.draw_scenes`); module docstring."""
    return train_seeds(model, [config], dataset, scene, outs=None if out is None else [out], data_config=data_config, resume=resume, progress=progress)[0]


def train_seeds(
    model: models.ModelConfig,
    configs: Sequence[TrainConfig],
    dataset: Dataset,
    scene: Scene | Sequence[Scene],
    *,
    outs: Sequence[str | os.PathLike] | None = None,
    data_config: DataConfig | None = None,
    resume: bool = False,
    progress: bool = False,
) -> list[TrainState]:
    """Train several seeds of one job in one compiled program: `configs` differ in
    their seed only; each seed's run (shuffles, schedule, early stopping, checkpoint
    `outs[k]`) is the run `train` would make alone, to round-off. Params and Adam states
    are stacked on a leading axis (the data shared) and stepped `checkpoint_every`
    epochs per call of one program (`_chunk_fn`: validation, best parameters and early
    stopping on the device); a seed that has finished keeps its state while the others
    go on, and seeds may resume from different epochs. The next call is queued before
    the host writes the last one's checkpoints, so the device does not wait for the
    disk. Each seed's `elapsed_s` counts the group's wall-clock time; the times of the
    epochs inside one call are spread evenly over it. A dataset of varied draws trains
    on the draws' scenes (`scene`, one per draw, in order): each step's batch takes
    `batch_size / draws` states of every draw (`_epoch`), and the validation loss is the
    mean over all validation states, each against its own draw's scene."""
    from tqdm.auto import tqdm

    scenes = (scene,) if isinstance(scene, Scene) else tuple(scene)
    n_draws = int(dataset.draw.max()) + 1 if len(dataset.draw) else 1
    if len(scenes) != n_draws:
        raise ConfigError(f"the dataset holds {n_draws} varied draws but {len(scenes)} scenes were given (lgnn.learn.data.draw_scenes)")

    # The schedule rule needs the budget, known from here on (the benchmark's profiles
    # arrive resolved: `lgnn.bench.profiles.TrainSettings`).
    configs = [scheduled(c, len(dataset.train) // c.batch_size) for c in configs]
    if not configs or any(_optimisation_only(c) != _optimisation_only(configs[0]) or _budget(c) != _budget(configs[0]) for c in configs):
        raise ConfigError("seeds trained together must share every training setting but the seed")
    if outs is not None and len(outs) != len(configs):
        raise ConfigError(f"{len(configs)} seeds but {len(outs)} checkpoint paths")
    for draw_scene in scenes:
        models.check_compatible(model, draw_scene)
    if configs[0].batch_size % n_draws:
        raise ConfigError(f"a batch of {configs[0].batch_size} cannot take the same number of states from each of {n_draws} varied draws")
    train_draws = [dataset.train[dataset.draw[dataset.train] == k] for k in range(n_draws)]
    val_draws = [dataset.val[dataset.draw[dataset.val] == k] for k in range(n_draws)]
    if min(len(t) for t in train_draws) < configs[0].batch_size // n_draws:
        raise ConfigError(f"{len(dataset.train)} training states is fewer than one batch of {configs[0].batch_size}")
    config = configs[0]
    outs = [None] * len(configs) if outs is None else list(outs)
    statistics = _training_statistics(model, scenes, dataset, train_draws)
    states = [
        check_resumable(out, model, c)[0] if resume and out is not None and Path(out).exists() else initial_state(model, c, statistics)
        for c, out in zip(configs, outs)
    ]
    train_arrays = tuple(tuple(jnp.asarray(a[index]) for a in (dataset.q, dataset.qd, dataset.qdd)) for index in train_draws)
    val_arrays = tuple(tuple(jnp.asarray(a[index]) for a in (dataset.q, dataset.qd, dataset.qdd)) for index in val_draws)
    base_keys = jnp.stack([jax.random.fold_in(jax.random.PRNGKey(c.seed), 1) for c in configs])
    budget = _Budget(*(jnp.asarray(v) for v in (config.epochs, config.patience, config.min_improvement)))
    chunk = _chunk_fn(model, scenes, _optimisation_only(config), config.checkpoint_every)
    start, elapsed_before = time.monotonic(), [state.elapsed_s for state in states]
    done = [finished(state, config) for state in states]
    seeds = _to_device(states, done, config.epochs)
    name = model.name + (f" x{len(configs)} seeds" if len(configs) > 1 else "")
    bar = tqdm(total=config.epochs, initial=min(s.epoch for s in states), desc=f"train {name}", unit="epoch", disable=not progress, leave=False)
    try:
        called = time.monotonic()
        queued = None if all(done) else chunk(seeds, budget, base_keys, train_arrays, val_arrays)
        while queued is not None:
            seeds = queued[0]
            # The call's results come to the host in one transfer (which waits for the
            # call) before the next call is queued: read from the device afterwards,
            # each would wait behind the next call, and the device would idle while the
            # host writes checkpoints.
            host_seeds, train_loss, val_loss, ran = jax.device_get(queued)
            now = time.monotonic()
            elapsed = [before + now - start for before in elapsed_before]
            ended = host_seeds.done | np.array([out_of_minutes(c, e) for c, e in zip(configs, elapsed)])
            # The next call goes to the device before this one's results are written.
            queued = None if ended.all() else chunk(seeds._replace(done=jnp.asarray(ended)), budget, base_keys, train_arrays, val_arrays)
            states = _from_device(states, host_seeds, train_loss, val_loss, ran, called - start, now - start, elapsed_before)
            called = now
            for k, (state, out) in enumerate(zip(states, outs)):
                if out is not None and ran[k].any():
                    save_checkpoint(out, state, model, configs[k], data_config)
            bar.n = min(s.epoch for s in states)
            bar.set_postfix(best=" ".join(f"{s.best_val:.3e}" for s in states))
            bar.refresh()
    finally:
        bar.close()
    for state, c, out in zip(states, configs, outs):
        if out is not None:
            save_checkpoint(out, state, model, c, data_config)
    return states


def _training_statistics(model: models.ModelConfig, scenes: tuple[Scene, ...], dataset: Dataset, train_draws: list) -> dict | None:
    """The statistics the model normalises by (`models.training_statistics`): of the one
    scene's training states, or each draw's of its own, averaged weighted by their
    numbers of training states."""
    per_draw = [models.training_statistics(model, scene, *(a[index] for a in (dataset.q, dataset.qd, dataset.qdd)))
                for scene, index in zip(scenes, train_draws)]
    if per_draw[0] is None or len(per_draw) == 1:
        return per_draw[0]
    weights = np.asarray([len(index) for index in train_draws], np.float64) / len(dataset.train)
    return {name: sum(w * np.asarray(draw[name]) for w, draw in zip(weights, per_draw)) for name in per_draw[0]}


def _to_device(states: list[TrainState], done: list[bool], epochs: int) -> _Seeds:
    stack = lambda trees: jax.tree.map(lambda *leaves: jnp.stack(leaves), *trees)  # noqa: E731
    best_upto = np.full((len(states), max(epochs, max(s.epoch for s in states)) + 1), np.inf)
    for k, state in enumerate(states):
        best_upto[k, : state.epoch + 1] = running_best(state.history, state.epoch)
    return _Seeds(
        stack([s.params for s in states]), stack([s.opt_state for s in states]), stack([s.best_params for s in states]),
        jnp.asarray([s.best_val for s in states]), jnp.asarray([s.best_epoch for s in states]), jnp.asarray([s.epoch for s in states]),
        jnp.asarray(done), jnp.asarray(best_upto),
    )


def _from_device(states: list[TrainState], seeds: _Seeds, train_loss, val_loss, ran, called_s: float, returned_s: float, elapsed_before: list[float]) -> list[TrainState]:
    """The host's `TrainState`s after a call: each seed's new history entries (epochs it
    ran, times spread evenly over the call) and its state (`seeds` copied to the host)."""
    updated = []
    for k, state in enumerate(states):
        if not ran[k].any():
            updated.append(state)
            continue
        epochs = np.flatnonzero(ran[k])
        times = [elapsed_before[k] + called_s + (returned_s - called_s) * (j + 1) / len(epochs) for j in range(len(epochs))]
        history = state.history + [(state.epoch + j + 1, float(train_loss[k, i]), float(val_loss[k, i]), t) for j, (i, t) in enumerate(zip(epochs, times))]
        pick = lambda tree, k=k: jax.tree.map(lambda a: a[k], tree)  # noqa: E731
        updated.append(TrainState(pick(seeds.params), pick(seeds.opt_state), pick(seeds.best_params), float(seeds.best_val[k]),
                                  int(seeds.best_epoch[k]), int(seeds.epoch[k]), history, times[-1]))
    return updated


def _budget(config: TrainConfig) -> tuple:
    return config.epochs, config.minutes, config.patience, config.min_improvement, config.checkpoint_every


# ---------------------------------------------------------------------------------
# Checkpoints
# ---------------------------------------------------------------------------------


def _state_arrays(state: TrainState) -> dict:
    return {
        **checkpoints.leaves_by_path("params", state.params),
        **checkpoints.leaves_by_path("best", state.best_params),
        **checkpoints.leaves_by_path("opt", state.opt_state),
    }


def save_checkpoint(path, state: TrainState, model: models.ModelConfig, config: TrainConfig, data_config: DataConfig | None = None) -> None:
    """Write the training state atomically as a checkpoint (`lgnn.learn.checkpoints`)."""
    from lgnn import __version__

    meta = {
        "lgnn": __version__,
        "model": model.to_dict(),
        "train": training_key(config),
        "train_config": dataclasses.asdict(config),
        "data": data_config.to_dict() if data_config else None,
        "epoch": state.epoch,
        "best_epoch": state.best_epoch,
        "best_val": state.best_val if np.isfinite(state.best_val) else None,
        "elapsed_s": state.elapsed_s,
    }
    if models.model_source(model.name):
        # A model defined outside lgnn: where its code is, for the error that asks for it.
        meta["model_source"] = models.model_source(model.name)
    checkpoints.write(path, _state_arrays(state), meta, state.history)


@in_float64  # parameters restored in the precision they were trained in
def load_checkpoint(path) -> tuple[TrainState, dict]:
    """The training state and metadata of a checkpoint of any readable format, for
    resuming (inference needs only `load_model`); `CheckpointError` if unusable. One
    kept without its parameters (`checkpoints.without_parameters`) gives its training
    alone: parameters and optimiser state None; one kept for inference
    (`checkpoints.for_inference`) its best parameters too."""
    meta, arrays = checkpoints.read(path)
    model = checkpoints.model_config(path, meta)
    try:
        config = TrainConfig(**{**LEGACY_OPTIMISATION, **meta["train_config"]})
    except (ConfigError, TypeError, KeyError) as err:
        raise CheckpointError(f"{path}: checkpoint settings are invalid ({err})") from None
    best_val = meta["best_val"] if meta["best_val"] is not None else float("inf")
    history = checkpoints.history(meta, arrays)
    elapsed = float(meta.get("elapsed_s", 0.0))
    if not checkpoints.has_parameters(meta):  # its training only: no parameters or optimiser state
        return TrainState(None, None, None, best_val, meta["best_epoch"], meta["epoch"], history, elapsed), meta
    if not checkpoints.resumable(meta):
        best = checkpoints.restore(path, checkpoints.params_template(model), arrays, "best")
        return TrainState(None, None, best, best_val, meta["best_epoch"], meta["epoch"], history, elapsed), meta
    template = initial_state(model, config)
    arrays = checkpoints.arrays_by_path(path, meta, arrays, {"params": template.params, "best": template.params, "opt": template.opt_state})
    params = checkpoints.restore(path, template.params, arrays, "params")
    best = checkpoints.restore(path, template.params, arrays, "best")
    opt_state = checkpoints.restore(path, template.opt_state, arrays, "opt")
    return TrainState(params, opt_state, best, best_val, meta["best_epoch"], meta["epoch"], history, elapsed), meta


def convert_checkpoint(source, target) -> None:
    """Write the checkpoint at `source` (any readable format) to `target` in the current
    format: the same parameters, optimiser state, history, settings and the environment
    that trained it, plus `converted_from` (the source's format and the sha256 of its
    bytes, which records keyed on the old file can be re-keyed by; a file converted
    before keeps its first source). `source` is only read."""
    state, meta = load_checkpoint(source)
    kept = {key: value for key, value in meta.items() if key not in ("format", "history", "environment", "converted_from")}
    converted_from = {"format": meta["format"], "sha256": records.file_digest(source)}
    checkpoints.write(target, _state_arrays(state), {**kept, "converted_from": meta.get("converted_from", converted_from)}, state.history, meta.get("environment"))


def check_resumable(path, model: models.ModelConfig, config: TrainConfig) -> tuple[TrainState, dict]:
    """The checkpoint at `path` if training `model` with `config` can resume from it;
    `CheckpointError` (one line) if it is unusable or was written with other settings.
    Entry points call it before generating data, so a wrong `--resume` fails at once."""
    state, saved = load_checkpoint(path)
    checkpoints.refuse_unresumable(path, saved)
    differences = settings_differences(saved["model"], model.to_dict(), "model") + settings_differences(saved["train"], training_key(config), "train")
    if differences:
        raise CheckpointError(f"{path}: cannot resume: it was written with other settings ({'; '.join(differences)})")
    return state, saved


def settings_differences(saved: dict, wanted: dict, prefix: str) -> list[str]:
    """`"prefix.key: saved X, now Y"` for each setting that differs between two flat-ish
    settings dicts (nested dicts are compared by key too), in key order."""
    lines = []
    for key in sorted(set(saved) | set(wanted)):
        old, new = saved.get(key), wanted.get(key)
        if isinstance(old, dict) and isinstance(new, dict):
            lines += settings_differences(old, new, f"{prefix}.{key}")
        elif old != new:
            lines.append(f"{prefix}.{key}: checkpoint {old!r}, now {new!r}")
    return lines


def seconds_to_reach(state: TrainState, target: float) -> float | None:
    """Training seconds until the validation loss first reached `target` (None if it
    never did, or if the checkpoint predates per-epoch times)."""
    for entry in state.history:
        if len(entry) >= 4 and entry[2] <= target:
            return float(entry[3])
    return None
