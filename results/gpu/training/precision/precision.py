"""Float32 against float64 training of the large graph networks: the same job's 3 seeds
packed (`train.train_seeds`), the full profile's chain4 data and recipe, from the same
initial parameters, for a fixed number of epochs (no early stopping); prints per seed the
best validation MSE (computed in the training precision) at each reading, and the rate.

    python results/gpu/training/precision/precision.py --models gns-10-128 cgnode --epochs 200 --data /tmp/ds

A measurement towards a precision rule (float32 where the validation MSE and the
rollout errors stay within their intervals), not the rule itself: a short budget, no
rollouts.
"""
import argparse
import dataclasses
import json

from lgnn import runtime

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--models", nargs="+", default=["gns-10-128", "cgnode"])
parser.add_argument("--epochs", type=int, default=200)
parser.add_argument("--readings", nargs="+", type=int, default=[50, 100, 150, 200])
parser.add_argument("--data", default="/tmp/lgnn-datasets")
args = parser.parse_args()

runtime.configure()
from lgnn.bench.profiles import get_profile, training_jobs  # noqa: E402
from lgnn.bench.stages.train import job_settings  # noqa: E402
from lgnn.learn import data, train  # noqa: E402
from lgnn.provenance import environment  # noqa: E402

import numpy as np  # noqa: E402

profile = get_profile("full")
print(json.dumps({"environment": environment()}), flush=True)
for name in args.models:
    job = next(j for j in training_jobs(profile) if j.model == name and j.scene == "chain4" and j.seed == 0)
    scene, model, data_config, train_config = job_settings(profile, job)
    dataset = data.load_or_generate(data_config, args.data)
    config = dataclasses.replace(train_config, epochs=args.epochs, patience=10 * args.epochs, min_improvement=0.0, checkpoint_every=50, minutes=None)
    for dtype in ("float64", "float32"):
        with runtime.precision(dtype):
            states = train.train_seeds(model, [dataclasses.replace(config, seed=s) for s in profile.seeds], dataset, scene)
        row = {"model": name, "dtype": dtype, "epochs": args.epochs}
        for state, seed in zip(states, profile.seeds):
            val = np.array([entry[2] for entry in state.history])
            row[f"seed{seed}_best_val"] = {str(r): float(np.nanmin(val[:r])) for r in args.readings if r <= len(val)}
        times = [entry[3] for entry in states[0].history]
        row["epochs_per_s_after_first_call"] = round((len(times) - 50) / (times[-1] - times[49]), 2)
        print(json.dumps(row), flush=True)
