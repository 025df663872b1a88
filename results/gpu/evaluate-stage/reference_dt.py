"""Why the evaluate stage's MuJoCo C reference steps at 1e-4 while the ground truth
steps at 1e-3: how far each is from the Lagrangian engine at both steps.

From the first 10 of the full profile's evaluation initial conditions of chain16-3d
and chain16, 1 s, float64: the Lagrangian engine (RK4 with projection) at dt 1e-3
(the ground truth's step) and 1e-4, and MuJoCo C (nested form, RK4) at 1e-4 and 1e-3;
the largest node distance over all frames between each pair, and MuJoCo's seconds.

    python results/gpu/evaluate-stage/reference_dt.py
"""

import time

from lgnn.runtime import configure

configure()

import numpy as np  # noqa: E402

from lgnn.bench.grid import load_profile  # noqa: E402
from lgnn.bench.stages.evaluate import evaluation_initial_states  # noqa: E402
from lgnn.engines import get_engine  # noqa: E402
from lgnn.engines.base import SimulationConfig  # noqa: E402
from lgnn.provenance import environment  # noqa: E402
from lgnn.scene import State, get_scene  # noqa: E402

profile = load_profile("full")
lagrangian, mujoco_c = get_engine("lagrangian"), get_engine("mujoco", form="nested")
for name in ("chain16-3d", "chain16"):
    scene = get_scene(name)
    states = evaluation_initial_states(profile, scene)
    states = State(np.asarray(states.q[:10]), np.asarray(states.qd[:10]))
    truth = lagrangian.rollout(scene, SimulationConfig(1e-3, 1e-3, 1.0), states)
    fine = lagrangian.rollout(scene, SimulationConfig(1e-4, 1e-3, 1.0), states)
    found = {"truth dt1e-3 vs truth dt1e-4": np.abs(truth.q - fine.q).max()}
    for dt in (1e-4, 1e-3):
        began = time.perf_counter()
        reference = mujoco_c.rollout(scene, SimulationConfig(dt, 1e-3, 1.0), states)
        found[f"mujoco dt{dt:g} vs truth dt1e-3"] = np.abs(reference.q - truth.q).max()
        found[f"mujoco dt{dt:g} vs truth dt1e-4"] = np.abs(reference.q - fine.q).max()
        found[f"mujoco dt{dt:g} s"] = time.perf_counter() - began
    print(name, {key: f"{value:.3g}" for key, value in found.items()}, flush=True)
print(environment())
