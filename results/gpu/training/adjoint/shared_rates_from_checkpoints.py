"""Each training job's rate from the checkpoints under a benchmark output folder: one
JSON line per job with its epochs, the seconds of its first call (its history's 10th
epoch, compilation included), of its last checkpoint, and its epochs per second between
the two.

    python results/gpu/training/adjoint/shared_rates_from_checkpoints.py OUT_DIR
"""

import glob
import json
import os
import sys

from lgnn.runtime import configure

configure()

from lgnn.learn.train import load_checkpoint  # noqa: E402

for path in sorted(glob.glob(os.path.join(sys.argv[1], "**", "checkpoints", "*.npz"), recursive=True)):
    state = load_checkpoint(path)[0]
    row = dict(job=os.path.basename(path)[: -len(".npz")], epochs=int(state.epoch))
    if len(state.history) >= 2:
        (e0, _, _, t0), (e1, _, _, t1) = state.history[min(9, len(state.history) - 1)], state.history[-1]
        row.update(first_call_s=round(t0, 1), last_s=round(t1, 1), shared_epochs_per_s=round((e1 - e0) / (t1 - t0), 2) if t1 > t0 else None)
    print(json.dumps(row))
