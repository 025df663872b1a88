"""Why the evaluate stage's MuJoCo C reference steps at 1e-4 while the ground truth
steps at 1e-3: how far each is from the Lagrangian engine at both steps.

From the first 10 of the full profile's evaluation initial conditions of chain16-3d
and chain16, 1 s, float64: the Lagrangian engine (RK4 with projection) at dt 1e-3
(the ground truth's step) and 1e-4, and MuJoCo C (nested form, RK4) at 1e-4 and 1e-3;
the largest node distance over all frames between each pair, and MuJoCo's seconds.

    python results/gpu/evaluate-stage/reference_dt.py
"""

from lgnn.runtime import configure
configure()
import numpy as np, time
from lgnn.bench.grid import load_profile
from lgnn.bench.stages.evaluate import evaluation_initial_states
from lgnn.engines import get_engine
from lgnn.engines.base import SimulationConfig
from lgnn.scene import State, get_scene
profile = load_profile("full")
for name in ("chain16-3d", "chain16"):
    scene = get_scene(name)
    s = evaluation_initial_states(profile, scene)
    s = State(np.asarray(s.q[:10]), np.asarray(s.qd[:10]))
    truth = get_engine("lagrangian").rollout(scene, SimulationConfig(1e-3, 1e-3, 1.0), s)
    fine = get_engine("lagrangian").rollout(scene, SimulationConfig(1e-4, 1e-3, 1.0), s)
    out = {"truth dt1e-3 vs truth dt1e-4": np.abs(truth.q - fine.q).max()}
    for dt in (1e-4, 1e-3):
        t = time.perf_counter()
        m = get_engine("mujoco", form="nested").rollout(scene, SimulationConfig(dt, 1e-3, 1.0), s)
        out[f"mujoco dt{dt:g} vs truth dt1e-3"] = np.abs(m.q - truth.q).max()
        out[f"mujoco dt{dt:g} vs truth dt1e-4"] = np.abs(m.q - fine.q).max()
        out[f"mujoco dt{dt:g} s"] = time.perf_counter() - t
    print(name, {k: f"{v:.3g}" for k, v in out.items()}, flush=True)
