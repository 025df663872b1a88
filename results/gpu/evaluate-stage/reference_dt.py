"""Why the evaluate stage's MuJoCo C reference steps finer than the ground truth: how
far each is from the Lagrangian engine at a fine step, at several steps.

From the first `--initial-conditions` of the full profile's evaluation initial
conditions of each scene, `--duration` s, float64: the Lagrangian engine (RK4 with
projection) at dt 1e-3 (the ground truth's step) and at `--fine-dt`, and MuJoCo C
(nested form, RK4) at each of `--mujoco-dts`; the largest node distance over all
frames between each pair, and MuJoCo's seconds.

    python results/gpu/evaluate-stage/reference_dt.py      # reference-dt-cpu.txt
    python results/gpu/evaluate-stage/reference_dt.py --scene chain100-3d --initial-conditions 4 --duration 0.2 \\
        --mujoco-dts 1e-4 2.5e-4 5e-4 1e-3                  # reference-dt-chain100-3d-h200.txt
"""

import argparse
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

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--scene", nargs="+", default=["chain16-3d", "chain16"])
parser.add_argument("--initial-conditions", type=int, default=10)
parser.add_argument("--duration", type=float, default=1.0)
parser.add_argument("--fine-dt", type=float, default=1e-4)
parser.add_argument("--mujoco-dts", type=float, nargs="+", default=[1e-4, 1e-3])
args = parser.parse_args()

profile = load_profile("full")
lagrangian, mujoco_c = get_engine("lagrangian"), get_engine("mujoco", form="nested")
for name in args.scene:
    scene = get_scene(name)
    states = evaluation_initial_states(profile, scene)
    states = State(np.asarray(states.q[:args.initial_conditions]), np.asarray(states.qd[:args.initial_conditions]))
    truth = lagrangian.rollout(scene, SimulationConfig(1e-3, 1e-3, args.duration), states)
    fine = lagrangian.rollout(scene, SimulationConfig(args.fine_dt, 1e-3, args.duration), states)
    found = {f"truth dt1e-3 vs truth dt{args.fine_dt:g}": np.abs(truth.q - fine.q).max()}
    for dt in args.mujoco_dts:
        began = time.perf_counter()
        reference = mujoco_c.rollout(scene, SimulationConfig(dt, 1e-3, args.duration), states)
        found[f"mujoco dt{dt:g} vs truth dt1e-3"] = np.abs(reference.q - truth.q).max()
        found[f"mujoco dt{dt:g} vs truth dt{args.fine_dt:g}"] = np.abs(reference.q - fine.q).max()
        found[f"mujoco dt{dt:g} s"] = time.perf_counter() - began
    print(name, {key: f"{value:.3g}" for key, value in found.items()}, flush=True)
print(environment())
