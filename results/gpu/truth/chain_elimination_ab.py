"""The GPU ground truth's chain elimination at large batches: float32 Lagrangian steps/s
(the `lgnn gpu-truth` settings: RK4 at dt 1e-3, 100 steps, repeats 3) by scene, batch and
`solvers.chain_elimination` ("sweeps" unrolled, or "cyclic" reduction), the two
alternated twice in one process, one JSON line per run appended to `$OUT/elimination.jsonl`.

    PYTHONPATH=. python3 results/gpu/truth/chain_elimination_ab.py chain100,chain100-3d,chain16,chain4 1024,8192,65536 [seconds]

Stops, between runs, once `seconds` (default 480) have passed."""
import json
import os
import sys
import time

from lgnn.runtime import configure

configure()

import numpy as np  # noqa: E402

import lgnn.physics.solvers as solvers  # noqa: E402
from lgnn import physics  # noqa: E402
from lgnn.engines import rollouts  # noqa: E402
from lgnn.engines.base import Integration, SimulationConfig  # noqa: E402
from lgnn.engines.rollouts import Unparametrised, timed_rollouts  # noqa: E402
from lgnn.scene import get_scene  # noqa: E402

START = time.perf_counter()
BUDGET = float(sys.argv[3]) if len(sys.argv) > 3 else 480.0
config = SimulationConfig(dt=1e-3, frame_dt=0.1, duration=0.1)
out = open(os.path.join(os.environ.get("OUT", "/tmp"), "elimination.jsonl"), "a")
for name in sys.argv[1].split(","):
    scene = get_scene(name)
    for batch in [int(b) for b in sys.argv[2].split(",")]:
        states = physics.benchmark_initial_states(scene, batch, 0)
        for elimination in ("sweeps", "cyclic") * 2:
            if time.perf_counter() - START > BUDGET:
                sys.exit(f"stopped after {BUDGET:.0f} s")
            solvers.chain_elimination = lambda e=elimination: e
            rollouts.compiled_programs.cache_clear()
            compile_s, runs, last = timed_rollouts(scene, config, Unparametrised(physics.vectorised_true_acceleration_fn), states,
                                                   integration=Integration(), repeats=3, dtype="float32")
            steps = [batch * 100 / s for s in runs]
            row = dict(scene=name, batch=batch, elimination=elimination, steps_per_s=float(np.median(steps)), lo=min(steps), hi=max(steps),
                       compile_s=compile_s, qsum=float(np.abs(np.asarray(last.q[:, -1], np.float64)).sum()))
            print(json.dumps(row), flush=True)
            out.write(json.dumps(row) + "\n")
            out.flush()
