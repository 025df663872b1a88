"""Convergence per GPU-second of the training protocol and of rules that would change
its batch size or learning rate: at a batch of the batch rule
(`lgnn.learn.protocol.batch_scaled`), and with schedule settings overridden (`--set`).
Each model's full-profile job, its seeds packed in one program as the benchmark trains
them, from scratch for a wall-clock budget (the first call's compilation included):
one JSON line per model with each seed's running best validation MSE against its
epochs and training seconds.

    # One process per GPU, started together, so both batches are timed in one run:
    M="lgn:200 lgnn-mp2:110 lgnn:80 clnn:40 gns:40"
    CUDA_VISIBLE_DEVICES=0 python tools/batch_rule.py --scene chain4 --batch 100 --models $M > protocol-chain4.jsonl &
    CUDA_VISIBLE_DEVICES=1 python tools/batch_rule.py --scene chain4 --batch 750 --models $M > rule-chain4.jsonl &
    wait
    # The schedule 3x as fast: every rate x3, every duration in Adam steps / 3
    python tools/batch_rule.py --scene chain4 --models $M --label fast3 \
        --set learning_rate=3e-3 warmup_steps=333 decay_steps=25000 min_learning_rate=3e-5 > fast3-chain4.jsonl

    # The table, with the committed checkpoints' plateaus (trained at the protocol's batch)
    python tools/batch_rule.py --summarise results/gpu/training/batch_rule/*.jsonl --reference results/benchmark/checkpoints

A model is named with its budget in seconds (`lgn:200`). Packed seeds share one clock:
the epochs of one device call are spread evenly over it (`train.train_seeds`).
"""
import argparse
import dataclasses
import json
import os
import sys
import tempfile

import numpy as np

from lgnn import runtime


def _positive(text: str) -> int:
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"a whole number >= 1, not {text!r}")
    return int(text)


parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--models", nargs="+", default=["lgnn:60"], metavar="MODEL:SECONDS")
parser.add_argument("--scene", default="chain4", help="training scene of the jobs (the paper track's)")
parser.add_argument("--batch", type=_positive, default=100, help="batch size; the rate and schedule follow the batch rule")
parser.add_argument("--data", default=os.path.join(tempfile.gettempdir(), "lgnn-datasets"), help="dataset cache directory")
parser.add_argument("--set", nargs="+", default=[], metavar="FIELD=VALUE", help="TrainConfig fields to override after the batch rule")
parser.add_argument("--label", help="the variant's name in the table (default: the protocol, or its batch)")
parser.add_argument("--every", type=_positive, default=10, help="epochs per device call, and between the points kept")
parser.add_argument("--summarise", nargs="+", metavar="JSONL", help="print the table of these outputs instead of measuring")
parser.add_argument("--reference", help="--summarise: a folder of the benchmark's checkpoints (MODEL-SCENE-sK.npz), trained at the protocol's batch")
args = parser.parse_args()

# The times at which the table reads each run's validation MSE.
READ_AT_S = (30, 60, 120)
# The columns of a curve's points (`_curve`, `_median_curve`).
EPOCH, MSE, SECONDS = 0, 1, 2


def budgets(specs: list[str]) -> list[tuple[str, float]]:
    out = []
    for spec in specs:
        name, _, seconds = spec.partition(":")
        try:
            budget = float(seconds or 60)
        except ValueError:
            budget = float("nan")
        if not 0 < budget < float("inf"):
            raise SystemExit(f"error: --models {spec!r}: name a model and its seconds (> 0), as lgn:200")
        out.append((name, budget))
    return out


def overrides(config, settings: list[str]):
    """`config` with `--set FIELD=VALUE`s, each value of its field's type."""
    changes = {}
    for setting in settings:
        field, _, value = setting.partition("=")
        current = getattr(config, field, None)
        if not value or field not in {f.name for f in dataclasses.fields(config)}:
            raise SystemExit(f"error: --set {setting!r}: name a TrainConfig field and its value")
        try:
            changes[field] = int(value) if isinstance(current, int) and not isinstance(current, bool) else float(value)
        except ValueError:
            raise SystemExit(f"error: --set {setting!r}: {value!r} is not a number of {field}'s kind") from None
    return dataclasses.replace(config, **changes)


def measure(models: list[tuple[str, float]]):
    runtime.configure()
    from lgnn.bench.profiles import get_profile, training_jobs
    from lgnn.bench.stages.train import job_settings
    from lgnn.learn import data, protocol, train
    from lgnn.provenance import environment

    profile = get_profile("full")
    overrides(protocol.TrainConfig(), args.set)  # the fields' names, before minutes of data generation
    print(json.dumps({"environment": environment()}), flush=True)
    for name, seconds in models:
        jobs = [j for j in training_jobs(profile) if j.model == name and j.scene == args.scene and not j.varied_draws]
        if not jobs:
            raise SystemExit(f"error: the full profile trains no {name} on {args.scene}")
        scene, model, data_config, recipe = job_settings(profile, jobs[0])
        dataset = data.load_or_generate(data_config, args.data)
        config = overrides(protocol.batch_scaled(recipe, args.batch), args.set)
        is_protocol = config == recipe
        config = dataclasses.replace(config, minutes=seconds / 60, checkpoint_every=args.every)
        with runtime.precision("float64"):
            states = train.train_seeds(model, [dataclasses.replace(config, seed=j.seed) for j in jobs], dataset, scene)
        variant = args.label or ("protocol" if is_protocol else f"batch {config.batch_size}")
        row = dict(model=name, scene=args.scene, variant=variant, protocol=is_protocol, batch=config.batch_size, learning_rate=config.learning_rate,
                   warmup_steps=config.warmup_steps, decay_steps=config.decay_steps, min_learning_rate=config.min_learning_rate,
                   seeds=[j.seed for j in jobs], seconds=seconds, epochs=[s.epoch for s in states],
                   stop=[protocol.stop_reason(s, config) for s in states], curves=[_curve(s.history) for s in states])
        print(json.dumps(row), flush=True)
        print(f"{name} on {args.scene}, {variant}: {states[0].epoch} epochs in {states[0].elapsed_s:.0f} s, "
              f"best {np.median([s.best_val for s in states]):.3g}", file=sys.stderr, flush=True)


def _curve(history) -> list:
    """`[epoch, best validation MSE so far, seconds]` at every `--every`-th epoch and the last."""
    best = np.minimum.accumulate(np.array([entry[2] for entry in history], dtype=float))
    keep = [i for i, entry in enumerate(history) if entry[0] % args.every == 0 or i == len(history) - 1]
    return [[history[i][0], float(best[i]), round(float(history[i][3]), 3)] for i in keep]


def _median_curve(row) -> np.ndarray:
    """`(epoch, median over seeds of the best MSE so far, seconds)` rows on the longest
    seed's points: packed seeds share one clock, and a seed that has stopped keeps its
    best."""
    curves = [np.array(c, dtype=float) for c in row["curves"]]
    longest = max(curves, key=len)
    best = [np.concatenate([c[:, MSE], np.full(len(longest) - len(c), c[-1, MSE])]) for c in curves]
    return np.column_stack([longest[:, EPOCH], np.median(best, axis=0), longest[:, SECONDS]])


def _reached_by(curve: np.ndarray, value: float, column: int) -> float | None:
    """The median best MSE at the last point whose `column` (EPOCH or SECONDS) is at
    most `value` (None before the first point)."""
    index = np.searchsorted(curve[:, column], value, side="right") - 1
    return None if index < 0 else float(curve[index, MSE])


def _first_reaching(curve: np.ndarray, target: float, column: int) -> float | None:
    """The `column` (EPOCH or SECONDS) of the first point whose median best MSE is at
    most `target` (None if none is)."""
    reached = np.nonzero(curve[:, MSE] <= target)[0]
    return None if not len(reached) else float(curve[reached[0], column])


def _rate(curve: np.ndarray) -> float:
    """Epochs per second after the first device call (compilation apart)."""
    return (curve[-1, EPOCH] - curve[0, EPOCH]) / (curve[-1, SECONDS] - curve[0, SECONDS]) if len(curve) > 1 else float("nan")


def _reference(model: str, scene: str):
    """(median plateau MSE, median epochs, median curve) of the committed checkpoints
    (trained by the protocol; their clock is not this run's), or None."""
    if not args.reference:
        return None
    from lgnn.learn import train

    paths = [os.path.join(args.reference, f"{model}-{scene}-s{seed}.npz") for seed in range(3)]
    if not all(os.path.exists(p) for p in paths):
        return None
    states = [train.load_checkpoint(p)[0] for p in paths]
    curve = _median_curve({"curves": [_curve([(*e[:3], 0.0) for e in s.history]) for s in states]})
    return float(np.median([s.best_val for s in states])), int(np.median([s.epoch for s in states])), curve


def _cell(value, digits=3) -> str:
    return "" if value is None else f"{value:.{digits}g}"


def summarise(paths):
    """One row per run: its rate, its median MSE at READ_AT_S seconds and at its end,
    the seconds it took to the protocol run's end MSE (where one ran), and, against the
    committed checkpoints (`--reference`), their median MSE at the run's last epoch (the
    protocol's at equal cost where the batch is the protocol's) and the epochs the run
    took to their plateau MSE."""
    rows = [json.loads(line) for path in paths for line in open(path) if '"curves"' in line]
    groups = {}
    for row in rows:
        groups.setdefault((row["scene"], row["model"]), []).append(row)
    print("| scene | model | variant | batch | peak rate | epochs/s | " + " | ".join(f"MSE at {s} s" for s in READ_AT_S)
          + " | budget s | epochs | MSE at the end | stopped by | s to the protocol run's end MSE | committed MSE at that epoch"
          + " | epochs to the committed plateau MSE | committed plateau MSE (epochs) |")
    print("|" + "---|" * (15 + len(READ_AT_S)))
    for (scene, model), group in sorted(groups.items()):
        protocol = next((r for r in group if r.get("protocol", r["batch"] == r.get("protocol_batch"))), None)
        target = _median_curve(protocol)[-1, MSE] if protocol else None
        reference = _reference(model, scene)
        for row in sorted(group, key=lambda r: r is not protocol):
            curve = _median_curve(row)
            stops = sorted({(s or "budget").split(" (")[0] for s in row["stop"]})
            to_target = _first_reaching(curve, target, SECONDS) if target is not None and row is not protocol else None
            to_plateau = at_epoch = None
            if reference is not None:
                at_epoch = _reached_by(reference[2], curve[-1, EPOCH], EPOCH)
                to_plateau = _first_reaching(curve, reference[0], EPOCH)
            cells = [scene, model, row.get("variant", "protocol" if row is protocol else f"batch {row['batch']}"), str(row["batch"]), f"{row['learning_rate']:.3g}", f"{_rate(curve):.1f}",
                     *(_cell(_reached_by(curve, s, SECONDS)) for s in READ_AT_S), f"{row['seconds']:g}", str(int(np.median(row["epochs"]))),
                     _cell(curve[-1, MSE]), "; ".join(stops), _cell(to_target), _cell(at_epoch), "" if to_plateau is None else str(int(to_plateau)),
                     f"{reference[0]:.3g} ({reference[1]})" if reference else ""]
            print("| " + " | ".join(cells) + " |")


if args.summarise:
    summarise(args.summarise)
else:
    from lgnn.errors import ConfigError

    try:
        measure(budgets(args.models))
    except ConfigError as err:
        raise SystemExit(f"error: {err}") from None
