"""What the evaluate stage's MuJoCo reference of one scene costs, and whether MJX in
float64 on the GPU could stand in for MuJoCo C there at equal accuracy.

From the full profile's evaluation initial conditions of SCENE (100 for a chain),
`DURATION` s at the reference step (`EvaluateSettings.mujoco_dt`, 1e-4, RK4), the
nested MJCF form: MuJoCo C on every core (`get_engine("mujoco")`, one MjData per core),
then MJX in float64 (compile apart: the program is compiled first on a shorter run
of the same step count per call, then timed). Prints one JSON line: seconds of each,
seconds per simulated second, and the largest node position difference between the
two at the last frame.

    python results/gpu/evaluate-stage/reference_probe.py SCENE [DURATION]
"""

import json
import sys
import time

from lgnn.runtime import configure

configure()

import numpy as np  # noqa: E402

from lgnn.bench.profiles import load_profile  # noqa: E402
from lgnn.bench.stages.evaluate import evaluation_initial_states  # noqa: E402
from lgnn.engines import get_engine  # noqa: E402
from lgnn.engines.base import SimulationConfig  # noqa: E402
from lgnn.provenance import environment  # noqa: E402
from lgnn.scene import State, get_scene  # noqa: E402

scene_name = sys.argv[1]
duration = float(sys.argv[2]) if len(sys.argv) > 2 else 0.01
profile = load_profile("full")
scene = get_scene(scene_name)
states = evaluation_initial_states(profile, scene)
states = State(np.asarray(states.q), np.asarray(states.qd))
config = SimulationConfig(profile.evaluate.mujoco_dt, profile.evaluate.frame_dt, duration)
found = {"scene": scene_name, "initial_conditions": len(states.q), "dt": config.dt, "duration": duration}

began = time.perf_counter()
c = get_engine("mujoco", form="nested").rollout(scene, config, states)
found["mujoco_c_s"] = round(time.perf_counter() - began, 2)
found["mujoco_c_s_per_simulated_s"] = round(found["mujoco_c_s"] / duration, 1)
print(json.dumps({**found, **environment()}), flush=True)

mjx = get_engine("mjx", dtype="float64", form="nested")
compile_s, run_s, q_mjx = mjx.timed_rollout(scene, config, states)
found["mjx_float64_compile_s"] = round(compile_s, 2)
found["mjx_float64_s"] = round(run_s, 3)
found["mjx_float64_s_per_simulated_s"] = round(run_s / duration, 1)
found["max_node_difference"] = float(np.max(np.abs(np.asarray(q_mjx)[:, -1] - np.asarray(c.q)[:, -1])))
print(json.dumps({**found, **environment()}), flush=True)
