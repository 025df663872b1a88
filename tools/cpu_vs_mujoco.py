"""The Lagrangian engine against MuJoCo C on one CPU trajectory (issue 33, item 3).

Usage: python tools/cpu_vs_mujoco.py [--links 12] [--seed 0] [--duration 10]
           [--rounds 4] [--stepping-duration 2] [--cache {fresh,off,default}]
           [--scene NAME ...] [--skip {stepping,processes}]

A held-out planar chain (`lgnn.scene.catalogue.chain(links, seed)`, written to a
temporary scene file), or each built-in `--scene` in turn, from its own initial state,
at the default dt (1e-4) and frame interval, both engines in float64:

1. stepping alone, compilation apart, in this process: `Engine.timed_rollout` of the
   Lagrangian engine (its compiled rollout calls) and of MuJoCo C (`mujoco.rollout`),
   over `--stepping-duration` simulated seconds, the two alternated `--rounds` times;
2. whole processes: `lgnn simulate SCENE --duration D --quiet` with `--engine
   lagrangian` and `--engine mujoco`, alternated `--rounds` times (start-up, imports,
   compilation and writing the file included). `--cache fresh` gives the Lagrangian
   processes a new, empty persistent compilation cache (the first run compiles, the
   others read it), `off` none, `default` the user's (`lgnn.runtime`).

It prints medians with [min-max] over the rounds and the per-round ratios, the
machine, the versions and the two trajectories' largest node distance. The machine is
shared and its wall clock noisy: compare ratios from one run of this script. No
timing here is asserted anywhere.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def spread(values) -> str:
    return f"{statistics.median(values):.3g} [{min(values):.3g}-{max(values):.3g}]"


def machine() -> str:
    model = ""
    try:
        model = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    import jax
    import jaxlib
    import mujoco
    import numpy

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    return (f"{platform.node()}: {os.cpu_count()} cores ({model or platform.processor()}), {platform.system()} {platform.release()}; "
            f"python {platform.python_version()}, jax {jax.__version__}, jaxlib {jaxlib.__version__}, mujoco {mujoco.__version__}, "
            f"numpy {numpy.__version__}; lgnn {commit}; XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}")


def stepping(scene, duration: float, rounds: int) -> None:
    import numpy as np

    from lgnn.engines import batch_of_one, get_engine
    from lgnn.engines.base import SimulationConfig

    config = SimulationConfig(duration=duration)
    states = batch_of_one(scene.initial_state)
    engines = {name: get_engine(name) for name in ("lagrangian", "mujoco")}
    steps = round(duration / config.dt)
    run_s = {name: [] for name in engines}
    compile_s, final = {}, {}
    for k in range(rounds):
        for name, engine in engines.items():
            seconds_compiling, seconds, q = engine.timed_rollout(scene, config, states)
            compile_s.setdefault(name, seconds_compiling)
            run_s[name].append(seconds)
            final[name] = q
    print(f"stepping alone ({steps} RK4 steps of {config.dt:g} s, compilation apart, {rounds} rounds alternated):")
    for name in engines:
        per_step = [s / steps * 1e6 for s in run_s[name]]
        print(f"  {name:10s} run {spread(run_s[name])} s = {spread(per_step)} us/step; first compile {compile_s[name]:.3g} s")
    ratios = [a / b for a, b in zip(run_s["lagrangian"], run_s["mujoco"])]
    print(f"  ratio lagrangian / mujoco: {spread(ratios)}")
    distance = np.max(np.linalg.norm(final["lagrangian"] - final["mujoco"], axis=-1))
    print(f"  largest node distance between the two trajectories: {distance:.2e} m")


def whole_processes(scene_file: Path, duration: float, rounds: int, cache: str, out: Path) -> None:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    if cache == "fresh":
        env["LGNN_JAX_CACHE"] = str(out / "jax-cache")
    elif cache == "off":
        env["LGNN_JAX_CACHE"] = "off"
    wall = {"lagrangian": [], "mujoco": []}
    for _ in range(rounds):
        for engine in wall:
            command = [sys.executable, "-m", "lgnn.cli", "simulate", str(scene_file), "--engine", engine, "--duration", f"{duration:g}",
                       "--out", str(out / f"{engine}.npz"), "--quiet"]
            began = time.perf_counter()
            subprocess.run(command, env=env, check=True, stdout=subprocess.DEVNULL)
            wall[engine].append(time.perf_counter() - began)
    print(f"whole processes (lgnn simulate ... --duration {duration:g} --quiet, {rounds} rounds alternated, cache {cache}):")
    for engine, seconds in wall.items():
        print(f"  {engine:10s} {spread(seconds)} s  (in order: {', '.join(f'{s:.2f}' for s in seconds)})")
    ratios = [a / b for a, b in zip(wall["lagrangian"], wall["mujoco"])]
    print(f"  ratio lagrangian / mujoco: {spread(ratios)}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--links", type=int, default=12)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--duration", type=float, default=10.0, help="simulated seconds of the whole-process runs")
    parser.add_argument("--stepping-duration", type=float, default=2.0, help="simulated seconds of the in-process timing")
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--cache", choices=("fresh", "off", "default"), default="fresh")
    parser.add_argument("--skip", choices=("stepping", "processes"), help="leave one part out")
    parser.add_argument("--scene", action="append", help="a built-in scene instead of the held-out chain (repeatable)")
    args = parser.parse_args()

    from lgnn.runtime import configure

    configure()
    from lgnn.scene import get_scene, scene_to_dict
    from lgnn.scene.catalogue import chain

    scenes = [get_scene(name) for name in args.scene] if args.scene else [chain(args.links, seed=args.seed, name=f"chain{args.links}-heldout")]
    print(machine())
    for scene in scenes:
        print(f"== {scene.name} ({scene.n_links} links, {scene.dim}D)")
        with tempfile.TemporaryDirectory() as tmp:
            scene_file = Path(tmp) / f"{scene.name}.json"
            scene_file.write_text(json.dumps(scene_to_dict(scene)))
            if args.skip != "stepping":
                stepping(scene, args.stepping_duration, args.rounds)
            if args.skip != "processes":
                whole_processes(scene_file, args.duration, args.rounds, args.cache, Path(tmp))


if __name__ == "__main__":
    main()
