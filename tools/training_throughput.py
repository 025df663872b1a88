"""Seconds per training epoch of the full profile's jobs: one JSON line per (model,
precision, batch size), 3 seeds vmapped in one program (`lgnn.learn.train.train_seeds`),
the job's training scene's full-profile data (generated into --data on first use),
from the initial parameters, compile apart; issue 13, item 2.

    python tools/training_throughput.py --models lgnn gns --batches 100 7500 --dtype float64
    python tools/training_throughput.py --models lgnn --batches 100 --epochs 100   # x4 at once: contention

    python tools/training_throughput.py --summarise results/gpu/training/*.jsonl   # the table

    # The training loop itself (`train_seeds`: epochs, validation, stopping rule and
    # checkpoints): epochs per second alone (1 seed) and packed (3 seeds in one program),
    # with the device running 1 or 10 epochs per call.
    python tools/training_throughput.py --loop --models lgnn lgn --seed-counts 1 3 --per-call 1 10
    python tools/training_throughput.py --loop --checkpoints ...   # writing checkpoints, as the benchmark does

One precision per process (`--dtype`): jit caches built in one precision are not
reused in the other. Several processes started at once measure how they share a
device; results/gpu/training/README.md has the commands and the numbers.
"""
import argparse
import dataclasses
import json
import os
import tempfile
import time

import jax
import jax.numpy as jnp

from lgnn import runtime

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--models", nargs="+", default=["lgnn"])
parser.add_argument("--scene", default="chain4", help="training scene of the jobs")
parser.add_argument("--batches", nargs="+", type=int, default=[100])
parser.add_argument("--dtype", choices=["float64", "float32"], default="float64")
parser.add_argument("--epochs", type=int, default=3, help="timed epochs after the compiling one")
parser.add_argument("--data", default="/tmp/lgnn-datasets", help="dataset cache directory")
parser.add_argument("--summarise", nargs="+", metavar="JSONL", help="print a markdown table of these outputs instead of measuring")
parser.add_argument("--loop", action="store_true", help="time the training loop (train_seeds), not a bare epoch")
parser.add_argument("--seed-counts", nargs="+", type=int, default=[1, 3], help="--loop: seeds trained in one program")
parser.add_argument("--per-call", nargs="+", type=int, default=[10], help="--loop: epochs per device call (checkpoint_every)")
parser.add_argument("--checkpoints", action="store_true", help="--loop: write each seed's checkpoint after every call, as the benchmark does (to a temporary folder)")
args = parser.parse_args()


def measurements(paths):
    """`(file label, row, "device, commit")` of each measurement line of the outputs at
    `paths` (a file's environment line names the device and commit of the lines after it)."""
    for path in paths:
        env = {}
        for line in open(path):
            row = json.loads(line)
            if "environment" in row:
                env = row["environment"]
                continue
            # An A/B measurement's lines name their variant (and round) of the code.
            variant = " ".join(str(row[k]) for k in ("variant", "round") if k in row)
            label = os.path.basename(path)[:-6] + (f" ({variant})" if variant else "")
            yield label, row, f"{env.get('device', '?').split(';')[0]}, {env.get('commit', '?')}"


def _epoch_cells(row) -> list:
    timing = [str(row["epoch_s_mean"]), f"{row['epoch_s_min']}..{row['epoch_s_max']}", str(row["compile_s"])] if "epoch_s_mean" in row else [row.get("error", "?"), "", ""]
    return [row["model"], row.get("scene", ""), row["dtype"], str(row["batch"]), str(row.get("adam_steps", "")), *timing]


def _loop_cells(row) -> list:
    rate = ([str(row["epochs_per_s"]), str(round(row["epochs_per_s"] * row["seeds"], 1)), str(row["first_call_s"])] if "epochs_per_s" in row
            else [row.get("error", "?"), "", ""])
    return [row["model"], row["scene"], str(row["seeds"]), str(row["per_call"]), "yes" if row.get("checkpoints") else "no", *rate]


# The two tables: a bare epoch's outputs, and `--loop`'s (columns between the file and the device).
EPOCH_TABLE = (("model", "scene", "dtype", "batch", "Adam steps", "epoch s (mean)", "epoch s (min..max)", "compile s"), _epoch_cells)
LOOP_TABLE = (("model", "scene", "seeds", "epochs per call", "checkpoints written", "epochs/s", "seed-epochs/s", "first call s"), _loop_cells)


def summarise(paths):
    """A markdown table, one row per measurement: the file it came from (its name says
    which run, e.g. `mps4-2`: the second of 4 processes at once under MPS), its device
    and commit; `--loop` outputs get the loop's columns."""
    loop = any('"epochs_per_s"' in line for path in paths for line in open(path))
    columns, cells = LOOP_TABLE if loop else EPOCH_TABLE
    print("| " + " | ".join(["file", *columns, "device, commit"]) + " |")
    print("|" + "---|" * (len(columns) + 2))
    for label, row, where in measurements(paths):
        print("| " + " | ".join([label, *cells(row), where]) + " |")


def measure_loop(names):
    """Epochs per second of `train.train_seeds` from the initial parameters: the
    first call (compilation included) apart, then `--epochs` more epochs timed from the
    history's clock (no early stopping: patience above the budget)."""
    for name in names:
        job = next(j for j in training_jobs(profile) if j.model == name and j.scene == args.scene and j.seed == 0)
        scene, model, data_config, train_config = job_settings(profile, job)
        dataset = data.load_or_generate(data_config, args.data)
        for seeds in args.seed_counts:
            for per_call in args.per_call:
                timed = max(args.epochs, per_call)
                config = dataclasses.replace(train_config, epochs=per_call + timed, patience=10 * (per_call + timed), min_improvement=0.0, checkpoint_every=per_call)
                row = dict(model=name, scene=args.scene, dtype=args.dtype, seeds=seeds, per_call=per_call, batch=config.batch_size, checkpoints=args.checkpoints)
                try:
                    with runtime.precision(args.dtype), tempfile.TemporaryDirectory() as folder:
                        outs = [os.path.join(folder, f"seed{s}.npz") for s in range(seeds)] if args.checkpoints else None
                        states = train.train_seeds(model, [dataclasses.replace(config, seed=s) for s in range(seeds)], dataset, scene, outs=outs)
                    times = [entry[3] for entry in states[0].history]
                    row.update(first_call_s=round(times[per_call - 1], 2), epochs_per_s=round(timed / (times[-1] - times[per_call - 1]), 2), timed_epochs=timed)
                except Exception as err:  # noqa: BLE001 -- a measurement: report (e.g. out of memory) and go on
                    row["error"] = str(err).splitlines()[0][:200]
                print(json.dumps(row), flush=True)


if args.summarise:
    summarise(args.summarise)
    raise SystemExit

runtime.configure()
from lgnn.bench.profiles import get_profile, training_jobs  # noqa: E402
from lgnn.bench.stages.train import job_settings  # noqa: E402
from lgnn.learn import data, protocol, train  # noqa: E402
from lgnn.provenance import environment  # noqa: E402

profile = get_profile("full")
print(json.dumps({"environment": environment()}), flush=True)
if args.loop:
    measure_loop(args.models)
    raise SystemExit
for name in args.models:
    job = next(j for j in training_jobs(profile) if j.model == name and j.scene == args.scene and j.seed == 0)
    scene, model, data_config, train_config = job_settings(profile, job)
    dataset = data.load_or_generate(data_config, args.data)
    with runtime.precision(args.dtype):
        arrays = tuple(jnp.asarray(a[dataset.train]) for a in (dataset.q, dataset.qd, dataset.qdd))
        for batch in args.batches:
            steps = len(dataset.train) // batch
            config = protocol.scheduled(dataclasses.replace(train_config, batch_size=batch), steps)
            states = [train.initial_state(model, dataclasses.replace(config, seed=s)) for s in profile.seeds]
            stack = lambda trees: jax.tree.map(lambda *leaves: jnp.stack(leaves), *trees)  # noqa: E731
            params, opt = stack([s.params for s in states]), stack([s.opt_state for s in states])
            keys = jnp.stack([jax.random.PRNGKey(s) for s in profile.seeds])
            epoch = train.compiled_epoch_fn(model, scene, config, vmapped=True)
            row = dict(model=name, scene=args.scene, dtype=args.dtype, batch=batch, adam_steps=steps, seeds=len(profile.seeds))
            try:
                start = time.perf_counter()
                params, opt, loss = jax.block_until_ready(epoch(params, opt, *arrays, keys))
                row["compile_s"] = round(time.perf_counter() - start, 2)
                times = []
                for _ in range(args.epochs):
                    start = time.perf_counter()
                    params, opt, loss = jax.block_until_ready(epoch(params, opt, *arrays, keys))
                    times.append(time.perf_counter() - start)
                row.update(epoch_s_min=round(min(times), 4), epoch_s_mean=round(sum(times) / len(times), 4), epoch_s_max=round(max(times), 4), timed_epochs=len(times))
            except Exception as err:  # noqa: BLE001 -- a measurement: report (e.g. out of memory) and go on
                row["error"] = str(err).splitlines()[0][:200]
            print(json.dumps(row), flush=True)
