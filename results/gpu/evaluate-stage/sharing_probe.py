"""Seconds per rollout call of one evaluation part's models (a job's 3 seeds stacked in
one program, as the evaluate stage rolls them out), with the full profile's evaluation
settings, as one JSON line: what `sharing_probe.sh` starts alone and beside others.

    python results/gpu/evaluate-stage/sharing_probe.py --job lgnn-chain4 --scene chain100 --calls 2

Each call is 100 frames (`rollouts.FRAMES_PER_CALL`); the rollouts' duration is cut to
`--calls` of them, so a part's programs are the stage's own. The rollouts run twice: the
first compiles (`compile_s`), the second is timed (`run_s`, `per_call_s`; `--once`: one
run, its compiling apart, as in the stage), with
`process_s` the CPU time the process spent meanwhile (its threads summed): a process
whose calls wait on its own host threads shows `process_s` near `run_s`."""
import argparse
import dataclasses
import json
import os
import time

from lgnn.runtime import configure, enable_compilation_cache

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--job", required=True, help="a training job without its seed, e.g. lgnn-chain4")
parser.add_argument("--scene", required=True)
parser.add_argument("--calls", type=int, default=2)
parser.add_argument("--seeds", default="0,1,2")
parser.add_argument("--tag", default="")
parser.add_argument("--once", action="store_true", help="roll out once: run_s beside the compile_s of the same call (process_s counts both)")
args = parser.parse_args()
configure()
enable_compilation_cache()

import jax  # noqa: E402
import numpy as np  # noqa: E402

from lgnn.bench.profiles import get_profile  # noqa: E402
from lgnn.bench.stages.evaluate import evaluation_initial_states  # noqa: E402
from lgnn.engines.rollouts import FRAMES_PER_CALL, batched_rollouts  # noqa: E402
from lgnn.learn import models  # noqa: E402
from lgnn.learn.checkpoints import load_model  # noqa: E402
from lgnn.scene import get_scene  # noqa: E402

began = time.time()
profile = get_profile("full")
scene = get_scene(args.scene)
config = profile.evaluate.simulation(args.scene)
config = dataclasses.replace(config, duration=args.calls * FRAMES_PER_CALL * config.frame_dt)
loaded = [load_model(f"results/benchmark/checkpoints/{args.job}-s{seed}.npz") for seed in args.seeds.split(",")]
stacked = jax.tree.map(lambda *leaves: np.stack(leaves), *(params for _, params in loaded))
states = evaluation_initial_states(profile, scene)


def rollouts():
    return batched_rollouts(scene, config, models.AccelerationFactory(loaded[0][0]), states, stacked, integration=profile.evaluate.integration,
                            stacked=True, chunk=100)


timed_from, cpu0 = time.time(), time.process_time()
runs = rollouts()
compile_s = runs.compile_s
if not args.once:
    timed_from, cpu0 = time.time(), time.process_time()
    runs = rollouts()
print(json.dumps(dict(tag=args.tag, job=args.job, scene=args.scene, seeds=len(loaded), states=len(states.q), calls=args.calls,
                      steps_per_call=FRAMES_PER_CALL * config.steps_per_frame, compile_s=round(compile_s, 2),
                      run_s=round(runs.run_s, 3), per_call_s=round(runs.run_s / args.calls, 3),
                      process_s=round(time.process_time() - cpu0, 2), started=round(began, 2), timed_from=round(timed_from, 2), ended=round(time.time(), 2),
                      pid=os.getpid(), xla_flags=os.environ.get("XLA_FLAGS", ""), mps="CUDA_MPS_PIPE_DIRECTORY" in os.environ,
                      backend=jax.default_backend(), finite=bool(np.isfinite(runs.q).all()))), flush=True)
