"""Seconds of batched RK4 rollouts (with projection, dt 1e-3) of LGNN (the committed
checkpoint lgnn-chain4-s0) and of the ground truth on one scene, twice each after the
compiling call, as one JSON line.

    python results/gpu/sweeps/chain_rollouts.py --unroll 10 --scene chain100 --states 100 --duration 0.1
    python results/gpu/sweeps/chain_rollouts.py --dense ...   # the dense solves instead of the chain's
    python results/gpu/sweeps/chain_rollouts.py --chain-elimination cyclic ...   # cyclic reduction instead of the sweeps
    python results/gpu/sweeps/chain_rollouts.py --checkpoint results/benchmark/checkpoints/lgn-chain4-s0.npz \
        --no-truth --save lgn-s0.npz ...   # another model alone, its positions kept to compare solves

`--unroll` sets `lgnn.physics.solvers.ACCELERATOR_SWEEP_UNROLL` before anything
compiles; `--dense` raises `system.CHAIN_SOLVER_MIN_LINKS` past the chain and gives the
ground truth the Schur solve, so neither takes the chain's block elimination."""
import argparse
import json

from lgnn.runtime import configure

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--unroll", type=int, default=None)
parser.add_argument("--dense", action="store_true")
parser.add_argument("--scene", default="chain100")
parser.add_argument("--states", type=int, default=100)
parser.add_argument("--duration", type=float, default=0.1)
parser.add_argument("--chain-elimination", choices=("sweeps", "cyclic"), default=None,
                    help="how chain_kkt_solve eliminates, on any platform (default: solvers.chain_elimination's choice)")
parser.add_argument("--checkpoint", default="results/benchmark/checkpoints/lgnn-chain4-s0.npz", help="the LGNN (lgnn-chain4-3d-s0 for a 3D chain)")
parser.add_argument("--no-truth", action="store_true", help="time the checkpoint's model only")
parser.add_argument("--save", default=None, help="write the model's positions (states, frames, N, D) to this .npz")
args = parser.parse_args()
configure()

import jax  # noqa: E402
import numpy as np  # noqa: E402

import lgnn.physics.solvers as solvers  # noqa: E402
import lgnn.physics.system as system  # noqa: E402
from lgnn import physics  # noqa: E402
from lgnn.engines.base import Integration, SimulationConfig, State  # noqa: E402
from lgnn.engines.rollouts import Unparametrised, batched_rollouts  # noqa: E402
from lgnn.learn import models  # noqa: E402
from lgnn.learn.checkpoints import load_model  # noqa: E402
from lgnn.physics.dynamics import true_acceleration_fn, vectorised_true_acceleration_fn  # noqa: E402
from lgnn.scene import get_scene  # noqa: E402

if args.unroll is not None:
    solvers.ACCELERATOR_SWEEP_UNROLL = args.unroll
if args.dense:
    system.CHAIN_SOLVER_MIN_LINKS = 10**9
if args.chain_elimination is not None:
    solvers.chain_elimination = lambda: args.chain_elimination


def schur_truth(scene):
    return true_acceleration_fn(scene, "schur")


scene = get_scene(args.scene)
states = State(*(np.asarray(a) for a in physics.benchmark_initial_states(scene, args.states, 1)))
config = SimulationConfig(1e-3, 1e-3, args.duration)
model, params = load_model(args.checkpoint)
truth = Unparametrised(schur_truth if args.dense else vectorised_true_acceleration_fn)
row = dict(scene=args.scene, states=args.states, duration=args.duration, unroll=solvers.sweep_unroll(), dense=args.dense,
           chain_elimination=solvers.chain_elimination(), backend=jax.default_backend())
row["checkpoint"] = args.checkpoint
for label, factory, p in (("lgnn", models.AccelerationFactory(model), params), ("truth", truth, None))[:1 if args.no_truth else 2]:
    runs = [batched_rollouts(scene, config, factory, states, p, integration=Integration("rk4", project=True), chunk=args.states) for _ in range(3)]
    row[f"{label}_compile_s"] = round(runs[0].compile_s, 2)
    row[f"{label}_run_s"] = [round(r.run_s, 3) for r in runs[1:]]
    row[f"{label}_final_abs_sum"] = float(np.abs(runs[-1].q[:, -1]).sum())
    if label == "lgnn" and args.save:
        np.savez(args.save, q=np.asarray(runs[-1].q))
print(json.dumps(row), flush=True)
