"""One trajectory on the GPU: the batch-of-one program (`rollouts._over_batch`, not
vmapped) against the same trajectory vmapped as a batch of one, for the ground truth
(`physics.true_acceleration_fn`, as `lgnn simulate` runs it, and the vectorised
solver) and `lgnn-notebook` (the committed chain4 seed 0), on chain16, RK4 with
projection at dt 1e-3 for `--duration` s, compiled and run once, then timed once. One
JSON line per case:

    python results/gpu/host-rollouts/batch_of_one.py > batch-of-one.jsonl
"""

import argparse
import json
import time

from lgnn.runtime import configure

configure()

import jax  # noqa: E402

from lgnn import physics, provenance  # noqa: E402
from lgnn.engines import rollouts  # noqa: E402
from lgnn.engines.base import Integration, SimulationConfig  # noqa: E402
from lgnn.learn import models  # noqa: E402
from lgnn.learn.checkpoints import load_model  # noqa: E402
from lgnn.scene import get_scene  # noqa: E402

UNVMAPPED = rollouts._over_batch


def vmapped(fn, in_axes, batch):
    return jax.vmap(fn, in_axes=in_axes)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--duration", type=float, default=0.02)
    args = parser.parse_args()
    scene = get_scene("chain16")
    config = SimulationConfig(1e-3, 1e-3, args.duration)
    model, params = load_model("results/benchmark/checkpoints/lgnn-notebook-chain4-s0.npz")
    state = physics.benchmark_initial_states(scene, 1, 1)
    cases = {"truth (simulate's solver)": (rollouts.Unparametrised(physics.true_acceleration_fn), None),
             "truth (vectorised solver)": (rollouts.Unparametrised(physics.vectorised_true_acceleration_fn), None),
             "lgnn-notebook": (models.AccelerationFactory(model), params)}
    for name, (factory, p) in cases.items():
        for form, over_batch in (("batch-of-one program", UNVMAPPED), ("vmapped", vmapped)):
            rollouts._over_batch = over_batch
            rollouts.compiled_programs.cache_clear()
            run = lambda: rollouts.batched_rollouts(scene, config, factory, state, p, integration=Integration())  # noqa: E731
            first = run()
            timed = run()
            print(json.dumps(dict(case=name, form=form, platform=timed.platform, steps=config.n_frames, compile_s=round(first.compile_s, 3),
                                  run_s=round(timed.run_s, 4), ms_per_step=round(1e3 * timed.run_s / config.n_frames, 4),
                                  device=provenance.device(), commit=provenance.commit())), flush=True)


if __name__ == "__main__":
    main()
