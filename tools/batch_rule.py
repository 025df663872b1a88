"""Convergence per GPU-second at the protocol's batch and at a batch of the batch rule
(`lgnn.learn.train.batch_scaled`): each model's full-profile job, its seeds packed in
one program as the benchmark trains them, from scratch for a wall-clock budget (the
first call's compilation included), one JSON line per model with each seed's running
best validation MSE against its training seconds.

    # One process per GPU, started together, so both batches are timed in one run:
    M="lgn:200 lgnn-mp2:110 lgnn:80 clnn:40 gns:40"
    CUDA_VISIBLE_DEVICES=0 python tools/batch_rule.py --scene chain4 --batch 100 --models $M > protocol-chain4.jsonl &
    CUDA_VISIBLE_DEVICES=1 python tools/batch_rule.py --scene chain4 --batch 750 --models $M > rule-chain4.jsonl &
    wait

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

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--models", nargs="+", default=["lgnn:60"], metavar="MODEL:SECONDS")
parser.add_argument("--scene", default="chain4", help="training scene of the jobs (the paper track's)")
parser.add_argument("--batch", type=int, default=100, help="batch size; the rate and schedule follow the batch rule")
parser.add_argument("--data", default=os.path.join(tempfile.gettempdir(), "lgnn-datasets"), help="dataset cache directory")
parser.add_argument("--every", type=int, default=10, help="epochs per device call, and between the points kept")
parser.add_argument("--summarise", nargs="+", metavar="JSONL", help="print the table of these outputs instead of measuring")
parser.add_argument("--reference", help="--summarise: a folder of the benchmark's checkpoints (MODEL-SCENE-sK.npz), trained at the protocol's batch")
args = parser.parse_args()

# The times at which the table reads each run's validation MSE.
READ_AT_S = (30, 60, 120)


def budgets(specs: list[str]) -> list[tuple[str, float]]:
    out = []
    for spec in specs:
        name, _, seconds = spec.partition(":")
        try:
            out.append((name, float(seconds or 60)))
        except ValueError:
            raise SystemExit(f"error: --models {spec!r}: name a model and its seconds, as lgn:200") from None
    return out


def measure(models: list[tuple[str, float]]):
    runtime.configure()
    from lgnn.bench.grid import get_profile, training_jobs
    from lgnn.bench.stages.train import job_settings
    from lgnn.learn import data, train
    from lgnn.provenance import environment

    profile = get_profile("full")
    print(json.dumps({"environment": environment()}), flush=True)
    for name, seconds in models:
        jobs = [j for j in training_jobs(profile) if j.model == name and j.scene == args.scene and not j.varied_draws]
        if not jobs:
            raise SystemExit(f"error: the full profile trains no {name} on {args.scene}")
        scene, model, data_config, protocol = job_settings(profile, jobs[0])
        dataset = data.load_or_generate(data_config, args.data)
        config = dataclasses.replace(train.batch_scaled(protocol, args.batch), minutes=seconds / 60, checkpoint_every=args.every)
        with runtime.precision("float64"):
            states = train.train_seeds(model, [dataclasses.replace(config, seed=j.seed) for j in jobs], dataset, scene)
        row = dict(model=name, scene=args.scene, batch=config.batch_size, learning_rate=config.learning_rate, warmup_steps=config.warmup_steps,
                   decay_steps=config.decay_steps, protocol_batch=protocol.batch_size, seeds=[j.seed for j in jobs], seconds=seconds,
                   epochs=[s.epoch for s in states], stop=[train.stop_reason(s, config) for s in states],
                   curves=[_curve(s.history) for s in states])
        print(json.dumps(row), flush=True)
        print(f"{name} on {args.scene}, batch {config.batch_size}: {states[0].epoch} epochs in {states[0].elapsed_s:.0f} s, "
              f"best {np.median([s.best_val for s in states]):.3g}", file=sys.stderr, flush=True)


def _curve(history) -> list:
    """`[epoch, best validation MSE so far, seconds]` at every `--every`-th epoch and the last."""
    best = np.minimum.accumulate(np.array([entry[2] for entry in history], dtype=float))
    keep = [i for i, entry in enumerate(history) if entry[0] % args.every == 0 or i == len(history) - 1]
    return [[history[i][0], float(best[i]), round(float(history[i][3]), 3)] for i in keep]


def _median_curve(row) -> np.ndarray:
    """`(epoch, median over seeds of the best MSE so far, seconds)` rows: packed seeds
    share one clock, so the epochs line up while every seed runs."""
    n = min(len(c) for c in row["curves"])
    curves = np.array([c[:n] for c in row["curves"]], dtype=float)
    return np.column_stack([curves[0, :, 0], np.median(curves[:, :, 1], axis=0), curves[0, :, 2]])


def _at(curve: np.ndarray, seconds: float) -> float | None:
    """The median best MSE reached by `seconds` (None before the first point)."""
    index = np.searchsorted(curve[:, 2], seconds, side="right") - 1
    return None if index < 0 else float(curve[index, 1])


def _seconds_to(curve: np.ndarray, target: float) -> float | None:
    reached = np.nonzero(curve[:, 1] <= target)[0]
    return None if not len(reached) else float(curve[reached[0], 2])


def _rate(curve: np.ndarray) -> float:
    """Epochs per second after the first device call (compilation apart)."""
    return (curve[-1, 0] - curve[0, 0]) / (curve[-1, 2] - curve[0, 2]) if len(curve) > 1 else float("nan")


def _reference(model: str, scene: str):
    """(median plateau MSE, median epochs) of the committed checkpoints, or None."""
    if not args.reference:
        return None
    from lgnn.learn import train

    paths = [os.path.join(args.reference, f"{model}-{scene}-s{seed}.npz") for seed in range(3)]
    if not all(os.path.exists(p) for p in paths):
        return None
    states = [train.load_checkpoint(p)[0] for p in paths]
    return float(np.median([s.best_val for s in states])), int(np.median([s.epoch for s in states]))


def _cell(value, digits=3) -> str:
    return "" if value is None else f"{value:.{digits}g}"


def summarise(paths):
    rows = [json.loads(line) for path in paths for line in open(path) if '"curves"' in line]
    pairs = {}
    for row in rows:
        pairs.setdefault((row["scene"], row["model"]), {})[row["batch"] == row["protocol_batch"]] = row
    print("| scene | model | batch | rate | epochs/s | " + " | ".join(f"MSE at {s} s" for s in READ_AT_S)
          + " | budget s | epochs | MSE at the end | s to the protocol's end MSE | stopped by | committed plateau MSE (epochs) |")
    print("|" + "---|" * (11 + len(READ_AT_S)))
    for (scene, model), pair in sorted(pairs.items()):
        protocol = pair.get(True)
        target = _median_curve(protocol)[-1, 1] if protocol else None
        reference = _reference(model, scene)
        for is_protocol in (True, False):
            row = pair.get(is_protocol)
            if row is None:
                continue
            curve = _median_curve(row)
            stops = sorted({s or "budget" for s in row["stop"]})
            cells = [scene, model, str(row["batch"]), f"{row['learning_rate']:.3g}", f"{_rate(curve):.1f}",
                     *(_cell(_at(curve, s)) for s in READ_AT_S), f"{row['seconds']:g}", str(int(np.median(row["epochs"]))),
                     _cell(curve[-1, 1]), _cell(_seconds_to(curve, target) if target is not None and not is_protocol else None),
                     "; ".join(s.split(" (")[0] for s in stops),
                     f"{reference[0]:.3g} ({reference[1]})" if reference else ""]
            print("| " + " | ".join(cells) + " |")


if args.summarise:
    summarise(args.summarise)
else:
    measure(budgets(args.models))
