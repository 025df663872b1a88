"""The training rate of one zoo model's 3 seeds, packed as the benchmark trains them
(full profile: chain4's data, batch 100, a checkpoint of each seed every 10 epochs),
with training's checkpoints deflated (as before commit 4536c52) or stored (since):
epochs per second from the checkpoint's history over epochs 20 to EPOCHS, so the first
call's compile and data generation are left out. Run from the repository root, as the
round-robin that made `checkpoint-write-h200.jsonl` ran it:

    for round in 1 2; do for mode in deflated stored; do rm -rf /tmp/ck-$mode
        python -c 'import sys; exec(open("results/gpu/training/checkpoint_rate.py").read())' $mode gns-10-128 40 /tmp/ck-$mode
    done; done
"""
import functools
import json
import sys
import time
from pathlib import Path

from lgnn.runtime import configure

configure()
from lgnn.cli import main  # noqa: E402
from lgnn.learn import checkpoints, train  # noqa: E402

mode, model, epochs, out = sys.argv[1], sys.argv[2], int(sys.argv[3]), Path(sys.argv[4])
if mode == "deflated":
    checkpoints.write = functools.partial(checkpoints.write, compressed=True)
jobs = [a for s in range(3) for a in ("--job", f"{model}-chain4-s{s}")]
start = time.time()
code = main(["benchmark", "--full", "--stage", "train", *jobs, "--set", f"training.train.epochs={epochs}", "--out-dir", str(out), "--quiet"])
wall = time.time() - start
state, _ = train.load_checkpoint(out / "benchmark" / "checkpoints" / f"{model}-chain4-s0.npz")
history = state.history
rate = (len(history) - 20) / (history[-1][3] - history[19][3])
print(json.dumps({"mode": mode, "model": model, "epochs": len(history), "wall_s": round(wall, 1), "epochs_per_s_after_20": round(rate, 2), "code": code}), flush=True)
