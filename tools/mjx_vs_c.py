"""MJX against MuJoCo C on one MJCF, step by step (the measurements behind
`lgnn.engines.mjx.make_step`).

Steps MuJoCo C (`mj_step`), MJX's own `mjx.step` and lgnn's `lgnn.engines.mjx.make_step` from the same
state (the model's `qpos0`, velocities `--vel` x N(0, 1), seed 0; unconstrained
velocities are fine, the stiff equalities absorb them) and prints, after each count
in `--steps`, the largest |qpos| and |qvel| difference of each MJX step from C's.
Float64; `--replace OLD=>NEW` edits the MJCF text first (e.g. the integrator).

    PYTHONPATH=. python tools/mjx_vs_c.py mjcf/chain4-3d.xml --steps 1,10,100
    PYTHONPATH=. python -m lgnn.cli mjcf T1 --form maximal --out /tmp/t1.xml
    PYTHONPATH=. python tools/mjx_vs_c.py /tmp/t1.xml --vel 0 --steps 1,100,1000
"""

from __future__ import annotations

import argparse
import contextlib
import io
import time

import jax

jax.config.update("jax_enable_x64", True)

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

with contextlib.redirect_stdout(io.StringIO()):
    from mujoco import mjx  # noqa: E402

from lgnn.engines.mjx import make_step  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("mjcf")
    parser.add_argument("--steps", default="1,10,100", help="comma-separated step counts to report at")
    parser.add_argument("--vel", type=float, default=1.0, help="initial qvel scale (x N(0, 1))")
    parser.add_argument("--replace", action="append", default=[], help="OLD=>NEW text edit of the MJCF")
    parser.add_argument("--only", choices=("mjx", "lgnn"), help="run one MJX step only")
    args = parser.parse_args()
    xml = open(args.mjcf).read()
    for edit in args.replace:
        old, new = edit.split("=>")
        if old not in xml:
            parser.error(f"{old!r} is not in {args.mjcf}")
        xml = xml.replace(old, new)
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    data.qvel[:] = args.vel * np.random.default_rng(0).normal(size=model.nv)
    mx = mjx.put_model(model)
    d0 = mjx.make_data(mx).replace(qpos=jax.numpy.asarray(data.qpos), qvel=jax.numpy.asarray(data.qvel))
    steps = {"mjx": jax.jit(mjx.step), "lgnn": jax.jit(make_step(model))}
    if args.only:
        steps = {args.only: steps[args.only]}
    state = {}
    for name, step in steps.items():
        start = time.perf_counter()
        jax.block_until_ready(step(mx, d0))
        print(f"{name}: compiled in {time.perf_counter() - start:.0f} s")
        state[name] = d0
    print(f"{args.mjcf}: nq {model.nq} nv {model.nv} neq {model.neq}, dt {model.opt.timestep:g}")
    done = 0
    for count in sorted(int(s) for s in args.steps.split(",")):
        for _ in range(count - done):
            mujoco.mj_step(model, data)
            for name, step in steps.items():
                state[name] = step(mx, state[name])
        done = count
        line = [f"step {count:6d}"]
        for name, d in state.items():
            dq, dv = np.abs(np.asarray(d.qpos) - data.qpos).max(), np.abs(np.asarray(d.qvel) - data.qvel).max()
            line.append(f"{name}: qpos {dq:.2e} qvel {dv:.2e}")
        print("  ".join(line))


if __name__ == "__main__":
    main()
