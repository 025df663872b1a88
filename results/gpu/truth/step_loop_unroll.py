"""Step-loop unrolling for the GPU ground truth: float32 Lagrangian steps/s by scene,
batch and unroll of the RK4 step loop (lgnn.integrate.advance's fori_loop)."""
import json, os, sys, time
import jax, numpy as np
import lgnn
from lgnn.runtime import configure; configure()
from lgnn import physics, integrate
from lgnn.engines import rollouts
from lgnn.engines.base import Integration, SimulationConfig
from lgnn.engines.rollouts import Unparametrised, timed_rollouts
from lgnn.scene import get_scene as builtin_scene

UNROLL = {"u": 1}
def advance(integrator, carry, n_frames, steps_per_frame):
    def frame(carry, _):
        carry = jax.lax.fori_loop(0, steps_per_frame, lambda _, c: integrator.step_fn(c), carry, unroll=UNROLL["u"])
        return carry, carry.state
    return jax.lax.scan(frame, carry, None, length=n_frames)
rollouts.advance = advance

config = SimulationConfig(dt=1e-3, frame_dt=0.1, duration=0.1)
out = open(os.path.join(os.environ.get("OUT", "/tmp"), "unroll.jsonl"), "a")
for name in sys.argv[1].split(","):
    scene = builtin_scene(name)
    for batch in [int(b) for b in sys.argv[2].split(",")]:
        states = physics.benchmark_initial_states(scene, batch, 0)
        for u in [int(x) for x in sys.argv[3].split(",")] * 2:
            UNROLL["u"] = u
            rollouts.compiled_programs.cache_clear()
            c, runs, r = timed_rollouts(scene, config, Unparametrised(physics.vectorised_true_acceleration_fn), states,
                                        integration=Integration(), repeats=3, dtype="float32")
            sps = [batch * 100 / s for s in runs]
            row = dict(scene=name, batch=batch, unroll=u, steps_per_s=float(np.median(sps)), lo=min(sps), hi=max(sps), compile_s=c,
                       qsum=float(np.abs(r.q[:, -1]).sum()))
            print(json.dumps(row), flush=True); out.write(json.dumps(row) + "\n"); out.flush()
