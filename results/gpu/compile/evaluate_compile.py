"""Compile and run seconds of the evaluate stage's rollout programs, one (model, scene)
pair per process, under the XLA flags this process was started with.

Each argument `JOB@SCENE` takes the committed checkpoint `JOB` (its parameters stacked
three times, as a training job's seeds are), the full profile's evaluation settings of
`SCENE` and its 100 initial conditions (1 for T1-T3), and compiles the program pair
`lgnn.engines.rollouts.compiled_programs` makes for `_evaluate_stacked` (`--chunk 100`,
as the committed runs, 100 frames per call), then runs the start program and one step call (100 frames) twice,
timing the second. One JSON line per pair: compile_s, step_call_s, the XLA flags.

    XLA_FLAGS=... python results/gpu/compile/evaluate_compile.py lgnn-chain4-s0@chain4 ...
"""

import json
import os
import sys
import time

from lgnn.runtime import configure

configure()

import jax  # noqa: E402
import numpy as np  # noqa: E402

from lgnn.bench.profiles import load_profile  # noqa: E402
from lgnn.bench.stages.evaluate import evaluation_initial_states  # noqa: E402
from lgnn.engines.rollouts import compiled_programs, params_signature  # noqa: E402
from lgnn.learn import models  # noqa: E402
from lgnn.learn.checkpoints import load_model  # noqa: E402
from lgnn.provenance import environment  # noqa: E402
from lgnn.scene import get_scene  # noqa: E402
from lgnn import sharding  # noqa: E402

profile = load_profile("full")
# Initial conditions per program, as the committed evaluate runs' `--chunk 100`.
CHUNK = 100
for pair in sys.argv[1:]:
    job, scene_name = pair.split("@")
    model, params = load_model(f"results/benchmark/checkpoints/{job}.npz")
    stacked = jax.tree.map(lambda *leaves: np.stack(leaves), params, params, params)
    scene = get_scene(scene_name)
    config = profile.evaluate.simulation(scene_name)
    states = evaluation_initial_states(profile, scene)
    batch = sharding.padded_size(min(CHUNK, len(states.q)))
    programs = compiled_programs(scene, config, profile.evaluate.integration, models.AccelerationFactory(model), batch, "float64", 100, True,
                                 params_signature(stacked), False, sharding.platform())
    q0, qd0 = (jax.numpy.asarray(sharding.pad_batch(np.asarray(a[:batch]), batch)) for a in states)
    carry, _ = jax.block_until_ready(programs.start(stacked, q0, qd0))
    jax.block_until_ready(programs.step(stacked, carry))
    began = time.perf_counter()
    jax.block_until_ready(programs.step(stacked, carry))
    step_s = time.perf_counter() - began
    print(json.dumps({"pair": pair, "batch": batch, "seeds": 3, "compile_s": round(programs.compile_s, 2), "step_call_s": round(step_s, 4),
                      "frames_per_call": 100, "xla_flags": os.environ.get("XLA_FLAGS", ""), **environment()}), flush=True)
