"""The MuJoCo engines' error on open chains, in each MJCF form (the measurements behind
`lgnn.engines.mjcf.MAXIMAL_ERROR_COEFFICIENT` and `NESTED_ERROR_COEFFICIENT`).

For each chain (`chain(N, seed)`, or `spatial_chain(N, seed)` with `--dim 3`: unit
links, released from their own initial state), the reference is MuJoCo C in the
nested form (exact joints) at `dt / 4`. Prints the max node position error over the
run of

- the nested form at `dt` (RK4's error) and its coefficient
  `error * l / (depth^5 g^2 dt^4)` ("-" where the error is round-off, below `ROUND_OFF`);
- the maximal form at MuJoCo steps `h = dt / s`, `s` in `--substeps` (the soft
  `connect` joints' error) and its coefficient `error / (depth^3 g h^2)`,

`depth` the chain's links, `l` the link length, `g` gravity (the models'
dimensionless forms, `lgnn.engines.mjcf`). MJX steps with MuJoCo C's arithmetic
(`lgnn.engines.mjx.make_step`, round-off per step) and MuJoCo Warp the same model, so
the numbers are theirs too.

    PYTHONPATH=. python tools/maximal_error.py --links 4,8,16,24,40,64 --seeds 0,1,2,3,5 --substeps 1,2
    PYTHONPATH=. python tools/maximal_error.py --dim 3 --links 4,8,16,32,64 --seeds 0,1 --substeps 1
"""

from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from lgnn.engines import mujoco as lm  # noqa: E402
from lgnn.engines.base import SimulationConfig  # noqa: E402
from lgnn.engines.mjcf import scene_layout  # noqa: E402
from lgnn.scene import chain, spatial_chain  # noqa: E402

# Node position differences (m) this small are round-off over 1 s of unit links (chain4's
# nested form is 3e-14 from the reference at any dt): no coefficient is fitted on them.
ROUND_OFF = 1e-12


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dim", type=int, choices=(2, 3), default=2)
    parser.add_argument("--links", default="4,8,16,24,40")
    parser.add_argument("--seeds", default="0,1")
    parser.add_argument("--substeps", default="1,2")
    parser.add_argument("--dt", type=float, default=1e-4)
    parser.add_argument("--duration", type=float, default=1.0)
    args = parser.parse_args()
    build = chain if args.dim == 2 else spatial_chain

    def config(dt: float) -> SimulationConfig:
        return SimulationConfig(dt=dt, frame_dt=1e-3, duration=args.duration)

    print("dim links seed form h error coefficient seconds")
    for n in map(int, args.links.split(",")):
        for seed in map(int, args.seeds.split(",")):
            scene = build(n, seed=seed)
            depth, g, length = scene_layout(scene).depth, float(scene.gravity), float(np.max(scene.lengths))
            reference = lm.rollout(scene, config(args.dt / 4)).q[0]
            runs = [("nested", args.dt, lambda e, h: e * length / (depth**5 * g**2 * h**4))]
            runs += [("maximal", args.dt / s, lambda e, h: e / (depth**3 * g * h**2)) for s in map(int, args.substeps.split(","))]
            for form, h, coefficient in runs:
                start = time.perf_counter()
                q = lm.rollout(scene, config(h), form=form).q[0]
                seconds = time.perf_counter() - start
                error = float(np.max(np.abs(q - reference)))
                # Below ROUND_OFF the difference is float64 round-off, not the model's error.
                fitted = f"{coefficient(error, h):.3g}" if error >= ROUND_OFF else "-"
                print(f"{args.dim} {n} {seed} {form} {h:.3g} {error:.3g} {fitted} {seconds:.2f}", flush=True)


if __name__ == "__main__":
    main()
