"""The tables of README.md, from the two jobs' hand-backs unpacked into JOB1 and JOB2
(`lgnn handoff unpack`) and the committed checkpoints in results/benchmark/checkpoints:

    lgnn handoff unpack BACK1 --out-dir /tmp/h1; lgnn handoff unpack BACK2 --out-dir /tmp/h2
    python results/gpu/handoff/compare.py /tmp/h1 /tmp/h2
"""

import os
import sys
from pathlib import Path

import numpy as np

from lgnn.learn import checkpoints

first, second = (Path(a) / "benchmark" / "checkpoints" for a in sys.argv[1:3])
committed = Path(__file__).resolve().parents[2] / "benchmark" / "checkpoints"
print("| checkpoint | epoch after job 1 | epoch after job 2 | job 2 | committed run: epoch, best validation MSE | this run | relative difference |")
print("|---|---|---|---|---|---|---|")
for path in sorted(second.glob("*.npz")):
    meta, arrays = checkpoints.read(path)
    history = np.asarray(arrays["history"])
    before = first / path.name
    if before.exists():
        meta1, arrays1 = checkpoints.read(before)
        kept = len(history) >= len(arrays1["history"]) and np.array_equal(history[: len(arrays1["history"])], arrays1["history"])
        how = ("trained on from job 1's checkpoint (its history kept bit for bit)" if kept and meta["epoch"] > meta1["epoch"]
               else "reused as job 1 finished it" if kept else "trained again")
        epoch1 = str(meta1["epoch"])
    else:
        how, epoch1 = "started in job 2", ""
    finished = checkpoints.FOR_INFERENCE in meta
    row = f"| {path.stem} | {epoch1} | {meta['epoch']} | {how}{'' if finished else ' (unfinished)'} |"
    theirs = committed / path.name
    if finished and theirs.exists():
        ref, _ = checkpoints.read(theirs)
        row += f" {ref['epoch']}, {ref['best_val']:.6e} | {meta['epoch']}, {meta['best_val']:.6e} | {abs(meta['best_val'] / ref['best_val'] - 1):.1e} |"
    else:
        row += " | | |"
    print(row)
