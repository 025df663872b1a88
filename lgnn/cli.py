"""The `lgnn` command line.

Every `LgnnError` becomes one line on stderr (`lgnn: error: ...`) and exit status 2;
output files are written atomically. x64 is enabled here, at the entry point.
"""

from __future__ import annotations

import argparse
import math
import sys

from lgnn.errors import ConfigError, LgnnError


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def _cmd_scenes(args) -> None:
    from lgnn.scenes import BUILTIN_SCENES

    width = max(map(len, BUILTIN_SCENES))
    for entry in BUILTIN_SCENES.values():
        scene = entry.build()
        print(f"{entry.name:<{width}}  {scene.n_nodes:4d} nodes {scene.n_links:4d} links  {entry.description}")


def _cmd_scene_export(args) -> None:
    from lgnn._io import write_text_atomic
    from lgnn.scene import scene_to_json
    from lgnn.scenes import BUILTIN_SCENES, get_scene

    if args.name not in BUILTIN_SCENES:
        raise ConfigError(f"unknown built-in scene {args.name!r} (choose from {', '.join(BUILTIN_SCENES)})")
    text = scene_to_json(get_scene(args.name))
    if args.out in (None, "-"):
        sys.stdout.write(text)
    else:
        write_text_atomic(args.out, text)
        print(f"wrote {args.out}", file=sys.stderr)


def _add_simulation_options(parser: argparse.ArgumentParser) -> None:
    from lgnn.integrate import INTEGRATORS
    from lgnn.simulate import SimulationConfig

    default = SimulationConfig()
    parser.add_argument("--integrator", choices=sorted(INTEGRATORS), default=default.integrator)
    parser.add_argument("--dt", type=_positive_float, default=default.dt, help="integration step (s)")
    parser.add_argument("--frame-dt", type=_positive_float, default=default.frame_dt, help="interval between saved frames (s)")
    parser.add_argument("--duration", type=_positive_float, default=default.duration, help="simulated time (s)")
    parser.add_argument("--no-project", dest="project", action="store_false", help="do not project onto the constraints after each step")


def _simulation_config(args):
    from lgnn.simulate import SimulationConfig

    return SimulationConfig(args.integrator, args.dt, args.frame_dt, args.duration, args.project)


def _cmd_simulate(args) -> None:
    from lgnn._io import check_writable
    from lgnn.scenes import get_scene
    from lgnn.simulate import simulate

    config = _simulation_config(args)
    check_writable(args.out)
    scene = get_scene(args.scene)
    if args.engine != "lagrangian":
        raise ConfigError(f"engine {args.engine!r} is not available yet (choose from: lagrangian)")
    trajectory = simulate(scene, config, progress=not args.quiet)
    trajectory.save(args.out)
    drift = abs(trajectory.energy[-1] - trajectory.energy[0]) / max(abs(trajectory.energy[0]), 1e-300)
    print(
        f"{scene.name}: {len(trajectory.t)} frames over {config.duration:g} s "
        f"({config.integrator}, dt {config.dt:g}); relative energy drift {drift:.2e}; wrote {args.out}"
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="lgnn", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    scenes = commands.add_parser("scenes", help="list the built-in scenes")
    scenes.set_defaults(run=_cmd_scenes)

    scene = commands.add_parser("scene", help="scene utilities")
    scene_commands = scene.add_subparsers(dest="scene_command", required=True, metavar="SUBCOMMAND")
    export = scene_commands.add_parser("export", help="write a built-in scene as JSON")
    export.add_argument("name")
    export.add_argument("--out", help="output file (default: standard output)")
    export.set_defaults(run=_cmd_scene_export)

    simulate = commands.add_parser("simulate", help="simulate a scene with a ground-truth engine")
    simulate.add_argument("scene", help="built-in scene name or scene JSON file")
    simulate.add_argument("--engine", default="lagrangian", help="ground-truth engine (default: lagrangian)")
    _add_simulation_options(simulate)
    simulate.add_argument("--out", required=True, help="output .npz file")
    simulate.add_argument("--quiet", action="store_true", help="no progress bar")
    simulate.set_defaults(run=_cmd_simulate)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    try:
        args.run(args)
    except LgnnError as err:
        print(f"lgnn: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("lgnn: interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
