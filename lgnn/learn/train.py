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
(`TrainConfig`, `optimizer`; off by default, see `CLIP_NORM`). A rate or warm-up the
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
from lgnn import records
from lgnn.learn.data import DataConfig, Dataset, draw_scenes
from lgnn.errors import CheckpointError, ConfigError
from lgnn.runtime import in_float64
from lgnn.scene import Scene

# The format `save_checkpoint` writes (`lgnn.learn.checkpoints`).
CHECKPOINT_FORMAT = checkpoints.FORMAT


# The schedule and clipping of `TrainConfig`. The warm-up is ~1.3 epochs of the paper's
# chain4 data (750 steps per epoch); the decay halves the rate every 100 such epochs
# (a choice, not yet tuned by measurement).
WARMUP_STEPS = 1000
DECAY_STEPS = 75_000
DECAY_RATE = 0.5
MIN_LEARNING_RATE = 1e-5
# No clipping by default: measured on the tiny test dataset (tests/test_models.py),
# seed 1, clipping at global norm 1 blew up at epoch 15 (validation 4.1 -> 7.6e4),
# while the same run unclipped fell smoothly to 0.75. The fix is the start (`models`).
CLIP_NORM = None
# The paper's Adam learning rate: the schedule's peak (`scheduled`).
PAPER_LEARNING_RATE = 1e-3
# A budget of fewer Adam steps than this (the quick profile's 30: a check of the
# machinery, not a result) peaks at SHORT_BUDGET_RATE: at the paper's 1e-3 LGNN gained
# only 10 % on the untrained model in 30 steps; at 1e-2 seeds 0 and 1 reach 0.70 and
# 0.53 of it, GNS 0.50 and 0.60, LGN 0.47 and 0.77, CLNN 0.02 and 0.01.
SHORT_BUDGET_STEPS = 1000
SHORT_BUDGET_RATE = 1e-2
# What checkpoints written before these fields existed were trained with: the paper's
# plain Adam (no warm-up, no decay, no clipping), so they load with their own optimiser.
LEGACY_OPTIMISATION = {"warmup_steps": 0, "decay_steps": 1, "decay_rate": 1.0, "min_learning_rate": 0.0, "clip_norm": None}


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    # Paper: Adam, learning rate 1e-3, batch size 10 (the peak of the schedule below).
    # None: by the schedule rule (`scheduled`, which needs the budget in Adam steps).
    learning_rate: float | None = None
    batch_size: int = 10
    # Paper budget: 10 000 epochs with early stopping.
    epochs: int = 10_000
    # Wall-clock budget in minutes (None: no limit); checked between calls of
    # `checkpoint_every` epochs, so a run may overshoot it by one call.
    minutes: float | None = None
    # Early stopping: stop after this many epochs without a better validation loss.
    patience: int = 500
    # Seed of the initial parameters and of every epoch's shuffle.
    seed: int = 0
    # States per vmapped validation chunk (memory vs. speed).
    val_chunk: int = 500
    # Epochs per device call, and a checkpoint after each call (and at the end).
    checkpoint_every: int = 1
    # Deviations from the paper's plain Adam (issue 13: its first epochs swung over
    # orders of magnitude): a linear warm-up from 0 over this many steps, so Adam's
    # moment estimates settle before full-size steps (0: none; None: by the rule).
    warmup_steps: int | None = None
    # Then the learning rate times `decay_rate` every `decay_steps` steps (exponential,
    # per step, so it does not depend on the epoch budget and a resumed run with a
    # longer budget keeps its schedule), never below `min_learning_rate`.
    decay_steps: int = DECAY_STEPS
    decay_rate: float = DECAY_RATE
    min_learning_rate: float = MIN_LEARNING_RATE
    # Gradients rescaled to at most this global norm before Adam (None: no clipping).
    clip_norm: float | None = CLIP_NORM
    # Plateau rule (with `patience`, `plateaued`): stop once the best validation loss is
    # not below (1 - min_improvement) times the best `patience` epochs earlier (0: the
    # patience rule, `patience` epochs after the best). The best parameters are still
    # the best epoch's, however small its gain.
    min_improvement: float = 0.0

    def __post_init__(self):
        if self.learning_rate is not None and not 0 < self.learning_rate < float("inf"):
            raise ConfigError(f"learning rate must be > 0 and finite, got {self.learning_rate}")
        peak = PAPER_LEARNING_RATE if self.learning_rate is None else self.learning_rate
        if (self.warmup_steps or 0) < 0 or self.decay_steps < 1 or not 0 < self.decay_rate <= 1 or not 0 <= self.min_learning_rate <= peak:
            raise ConfigError("warm-up steps must be >= 0, decay steps >= 1, decay rate in (0, 1], 0 <= minimum learning rate <= learning rate")
        if self.clip_norm is not None and not 0 < self.clip_norm < float("inf"):
            raise ConfigError(f"clip norm must be > 0, got {self.clip_norm}")
        if self.batch_size < 1 or self.epochs < 0 or self.patience < 1 or self.checkpoint_every < 1:
            raise ConfigError("batch size, patience and checkpoint interval must be >= 1, epochs >= 0")
        if not 0 <= self.min_improvement < 1:
            raise ConfigError(f"minimum improvement must be in [0, 1), got {self.min_improvement}")
        if self.minutes is not None and not self.minutes > 0:
            raise ConfigError(f"minutes must be > 0, got {self.minutes}")


def adam_steps_per_epoch(data: DataConfig, config: TrainConfig) -> int:
    """Adam steps in one epoch of `data` (`lgnn.learn.data`'s split; the remainder of
    a shuffle is dropped)."""
    return round(data.train_fraction * data.n_trajectories * data.states_per_trajectory) // config.batch_size


def scheduled(config: TrainConfig, steps_per_epoch: int) -> TrainConfig:
    """`config` with the one schedule rule for every model (docs/benchmark.md, "Training recipe")
    filling what it leaves None: the peak rate PAPER_LEARNING_RATE (SHORT_BUDGET_RATE
    for a budget under SHORT_BUDGET_STEPS Adam steps), a warm-up over a fifth of the
    budget's steps but at most WARMUP_STEPS (Adam's moments settle; a short budget is
    not spent warming up). A value the config gives is kept."""
    steps = config.epochs * steps_per_epoch
    rate = SHORT_BUDGET_RATE if steps < SHORT_BUDGET_STEPS else PAPER_LEARNING_RATE
    return dataclasses.replace(
        config,
        learning_rate=rate if config.learning_rate is None else config.learning_rate,
        warmup_steps=max(1, min(WARMUP_STEPS, steps // 5)) if config.warmup_steps is None else config.warmup_steps,
    )


def batch_scaled(config: TrainConfig, batch_size: int) -> TrainConfig:
    """`config` (resolved by `scheduled`) at another batch size by the batch rule: a
    batch `k` times as large takes the peak rate times sqrt(k) (the square-root
    scaling rule for Adam) and the warm-up and decay in Adam steps divided by k, so
    the schedule is the same in epochs; the epoch budget, the patience and the plateau
    rule are in epochs and stay. The rate's floor stays, capped at the new peak.
    Measured against the protocol per GPU-second, and not adopted:
    results/gpu/training/batch_rule/README.md."""
    _check_scheduled(config)
    if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
        raise ConfigError(f"batch size must be a whole number >= 1, got {batch_size!r}")
    k = batch_size / config.batch_size
    rate = config.learning_rate * k**0.5
    return dataclasses.replace(
        config, batch_size=batch_size, learning_rate=rate, warmup_steps=round(config.warmup_steps / k),
        decay_steps=max(1, round(config.decay_steps / k)), min_learning_rate=min(config.min_learning_rate, rate),
    )


def _check_scheduled(config: TrainConfig) -> None:
    if config.learning_rate is None or config.warmup_steps is None:
        raise ConfigError("the learning rate or warm-up is left to the schedule rule: resolve it with train.scheduled(config, steps_per_epoch)")


class TrainState(NamedTuple):
    params: dict
    opt_state: tuple
    best_params: dict
    best_val: float
    best_epoch: int
    epoch: int  # epochs completed
    history: list  # [(epoch, train_loss, val_loss, elapsed_s), ...] (older checkpoints: no elapsed_s)
    # Wall-clock seconds spent training, summed over resumed runs (the minutes budget
    # counts all of them, so an interrupted run does not get a fresh budget).
    elapsed_s: float = 0.0


def stop_reason(state: TrainState, config: TrainConfig) -> str | None:
    """Why training has ended (the epoch budget, the plateau or patience rule, the
    minutes cap), or None while it has not."""
    if state.epoch >= config.epochs:
        return "epoch budget"
    if config.min_improvement:
        if plateaued(state, config):
            return f"plateau (best improved by under {config.min_improvement:.0%} in epochs {state.epoch - config.patience}-{state.epoch})"
    elif state.epoch - state.best_epoch > config.patience:
        return f"patience (best at epoch {state.best_epoch})"
    if out_of_minutes(config, state.elapsed_s):
        return "minutes cap"
    return None


def out_of_minutes(config: TrainConfig, elapsed_s: float) -> bool:
    """Whether `elapsed_s` seconds of training have spent `config`'s minutes cap."""
    return config.minutes is not None and elapsed_s >= 60 * config.minutes


def finished(state: TrainState, config: TrainConfig) -> bool:
    """Whether training has ended by one of `config`'s budgets or early stopping."""
    return stop_reason(state, config) is not None


def plateaued(state: TrainState, config: TrainConfig) -> bool:
    """The plateau rule: the best validation loss now is not below `1 - min_improvement`
    times the best `patience` epochs ago. The gain is measured over the whole window,
    not epoch by epoch: a run whose best falls steadily by 0.5 % an epoch is far from a
    plateau although no single epoch gains 1 % (the per-epoch reading stopped every
    full-batch run of the grid at epoch 202 while its loss was falling, 2026-11-24).
    Training applies the same rule on the device (`_chunk_fn`)."""
    start = state.epoch - config.patience
    if not config.min_improvement or start < 1 or not state.history:
        return False
    best = _running_best(state.history, state.epoch)
    return not best[state.epoch] < (1 - config.min_improvement) * best[start]


def learning_rate_schedule(config: TrainConfig) -> optax.Schedule | float:
    """The learning rate per step: warm-up, then exponential decay to the floor (a
    plain number when neither is set, as for the paper's Adam)."""
    _check_scheduled(config)
    if config.warmup_steps == 0 and config.decay_rate == 1:
        return config.learning_rate
    return optax.warmup_exponential_decay_schedule(
        0.0, config.learning_rate, max(config.warmup_steps, 1), config.decay_steps, config.decay_rate, end_value=config.min_learning_rate,
    )


def optimizer(config: TrainConfig, weight_decay: float = 0.0) -> optax.GradientTransformation:
    """Adam on the schedule, after global-norm clipping when `config.clip_norm` is set
    (the paper's `optax.adam(1e-3)` for the legacy settings, state and all); AdamW
    with a model's recipe's `weight_decay` (`ModelSpec.weight_decay`) when above 0."""
    schedule = learning_rate_schedule(config)
    adam = optax.adamw(schedule, weight_decay=weight_decay) if weight_decay else optax.adam(schedule)
    return adam if config.clip_norm is None else optax.chain(optax.clip_by_global_norm(config.clip_norm), adam)


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
        best_upto[k, : state.epoch + 1] = _running_best(state.history, state.epoch)
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


def _running_best(history: list, epochs: int) -> np.ndarray:
    """(epochs + 1,) the lowest validation loss of epochs 1..e for each e (inf before
    any; NaN losses skipped): what the plateau rule compares."""
    val = np.full(epochs + 1, np.inf)
    for entry in history:
        if 1 <= entry[0] <= epochs and not np.isnan(entry[2]):
            val[entry[0]] = min(val[entry[0]], entry[2])
    return np.minimum.accumulate(val)


def _budget(config: TrainConfig) -> tuple:
    return config.epochs, config.minutes, config.patience, config.min_improvement, config.checkpoint_every


# ---------------------------------------------------------------------------------
# Checkpoints
# ---------------------------------------------------------------------------------


def training_key(config: TrainConfig) -> dict:
    # Budgets may change on resume (train longer); the optimisation itself may not.
    return {k: v for k, v in dataclasses.asdict(config).items() if k not in ("epochs", "minutes", "patience", "min_improvement", "checkpoint_every", "val_chunk")}


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


def physics_differences(meta: dict, scene: Scene) -> list[str]:
    """How `scene`'s physical parameters differ from the scene a checkpoint was trained
    on (gravity, drag, the link masses, inertias and lengths: values the model never
    saw; the number of links and how they connect may differ, that is the zero-shot
    generalisation the benchmark measures): one phrase each, empty when they agree or when the
    training scene is unknown or no longer loadable (a moved scene file)."""
    from lgnn.errors import SceneError
    from lgnn.scene import get_scene

    source = (meta.get("data") or {}).get("scene")
    draws = (meta.get("data") or {}).get("varied_draws", 0)
    try:
        trained = get_scene(source) if source else None
        if trained is not None and draws:
            return _outside_the_draws(scene, draw_scenes(DataConfig(scene=source, n_trajectories=draws, varied_draws=draws)))
    except (SceneError, ConfigError):
        return []
    if trained is None:
        return []
    differences = _gravity_and_drag_differences(scene, trained)
    for name in ("masses", "inertias", "lengths"):
        values, trained_values = (np.unique(np.round(getattr(s, name), 12)) for s in (scene, trained))
        if values.shape != trained_values.shape or not np.allclose(values, trained_values):
            differences.append(f"link {name} {_values(values)} (trained on {_values(trained_values)})")
    return differences


def _gravity_and_drag_differences(scene: Scene, trained: Scene) -> list[str]:
    differences = []
    if not np.allclose(trained.gravity, scene.gravity):
        differences.append(f"gravity {np.asarray(scene.gravity).tolist()} (trained on {np.asarray(trained.gravity).tolist()})")
    if not np.isclose(trained.drag, scene.drag):
        differences.append(f"drag {scene.drag:g} (trained on {trained.drag:g})")
    return differences


def _outside_the_draws(scene: Scene, draws: tuple[Scene, ...]) -> list[str]:
    """`physics_differences` of a model trained on varied draws: the gravity and drag of
    the draws, and link values outside the range the draws spanned."""
    differences = _gravity_and_drag_differences(scene, draws[0])
    for name in ("masses", "inertias", "lengths"):
        seen = np.concatenate([getattr(draw, name) for draw in draws])
        values = np.asarray(getattr(scene, name))
        low, high = seen.min() * (1 - 1e-12), seen.max() * (1 + 1e-12)
        if values.min() < low or values.max() > high:
            differences.append(f"link {name} from {values.min():g} to {values.max():g} (trained on {seen.min():g} to {seen.max():g})")
    return differences


def _values(values: np.ndarray) -> str:
    shown = ", ".join(f"{v:g}" for v in values[:4])
    return f"{{{shown}{', ...' if len(values) > 4 else ''}}}"
