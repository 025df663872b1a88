"""Rollouts on the GPU against the host's CPU of the same machine, by batch size.

The ground truth (`physics.vectorised_true_acceleration_fn`) and `lgnn-notebook` (the
three committed chain4 seeds stacked, as the evaluate stage rolls them out) on chain16
and T1, from the evaluation's initial conditions (T1's own state repeated), RK4 with
projection at dt 1e-3 for `--duration` s, in one process of the GPU machine: each case
compiled and run once, then timed `--repeats` times, on the GPU (`platform=None`) and on
the host (`platform="cpu"`). One JSON line per case:

    python results/gpu/host-rollouts/by_batch.py > by_batch.jsonl
"""

import argparse
import json
import time

from lgnn.runtime import configure

configure()

import jax  # noqa: E402
import numpy as np  # noqa: E402

from lgnn import physics, provenance  # noqa: E402
from lgnn.engines.base import Integration, SimulationConfig  # noqa: E402
from lgnn.engines.rollouts import Unparametrised, batched_rollouts  # noqa: E402
from lgnn.learn import models  # noqa: E402
from lgnn.learn.checkpoints import load_model  # noqa: E402
from lgnn.scene import State, get_scene  # noqa: E402

CHECKPOINTS = [f"results/benchmark/checkpoints/lgnn-notebook-chain4-s{seed}.npz" for seed in range(3)]
# (scene, what, initial conditions)
CASES = [("chain16", "truth", 1), ("chain16", "truth", 16), ("chain16", "truth", 256),
         ("chain16", "lgnn-notebook", 1), ("chain16", "lgnn-notebook", 4), ("chain16", "lgnn-notebook", 32),
         ("T1", "truth", 1), ("T1", "lgnn-notebook", 1)]


def states_of(scene, count):
    sampled = physics.benchmark_initial_states(scene, count, 1)
    reps = -(-count // len(sampled.q))
    return State(np.concatenate([sampled.q] * reps)[:count], np.concatenate([sampled.qd] * reps)[:count])


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--duration", type=float, default=0.2)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--platforms", nargs="+", default=["gpu", "cpu"])
    parser.add_argument("--cases", nargs="+", help="SCENE:WHAT:COUNT (default: every case of CASES)")
    args = parser.parse_args()
    cases = CASES if not args.cases else [(c.split(":")[0], c.split(":")[1], int(c.split(":")[2])) for c in args.cases]
    loaded = [load_model(path) for path in CHECKPOINTS]
    model = loaded[0][0]
    stacked = jax.tree.map(lambda *leaves: np.stack(leaves), *(params for _, params in loaded))
    config = SimulationConfig(1e-3, 1e-3, args.duration)
    for scene_name, what, count in cases:
        scene = get_scene(scene_name)
        states = states_of(scene, count)
        for where in args.platforms:
            platform = None if where == "gpu" else where
            if what == "truth":
                run = lambda: batched_rollouts(scene, config, Unparametrised(physics.vectorised_true_acceleration_fn), states,  # noqa: E731
                                               integration=Integration(), platform=platform)
            else:
                run = lambda: batched_rollouts(scene, config, models.AccelerationFactory(model), states, stacked,  # noqa: E731
                                               integration=Integration(), stacked=True, platform=platform)
            began = time.perf_counter()
            first = run()
            first_s = time.perf_counter() - began
            runs = [run().run_s for _ in range(args.repeats)]
            rollouts = count * (3 if what != "truth" else 1)
            print(json.dumps(dict(scene=scene_name, what=what, initial_conditions=count, rollouts=rollouts, platform=first.platform,
                                  steps=config.n_frames, compile_s=round(first.compile_s, 3), first_call_s=round(first_s, 3),
                                  run_s=[round(r, 4) for r in runs], ms_per_step=round(1e3 * min(runs) / config.n_frames, 4),
                                  device=provenance.device(), commit=provenance.commit())), flush=True)


if __name__ == "__main__":
    main()
