"""The commands of scenes and ground-truth engines: `lgnn scenes`, `scene export`, `scene import`,
`simulate`, `mjcf` and `crosscheck` (`PARSERS`); each parses its options and
calls the library (`lgnn.scene`, `lgnn.engines`, `lgnn.bench.crosscheck`).
"""

from __future__ import annotations

import sys

from lgnn.cli.options import add_simulation_options, integration_of, nonnegative_int, positive_float, positive_int, simulation_config, trajectory_out
from lgnn.errors import ConfigError


def _cmd_scenes(args) -> None:
    from lgnn.bench.profiles import PROFILES, evaluation_scenes
    from lgnn.scene import CATALOGUE, TAGS

    evaluated_by = {name: [profile for profile, settings in PROFILES.items() if name in evaluation_scenes(settings)] for name in CATALOGUE}
    columns = ("name", "nodes", "links", "tags", "initial states", "benchmark", "description")
    rows = []
    for name, entry in CATALOGUE.items():
        scene = entry.build()
        benchmark = f"evaluated ({', '.join(evaluated_by[name])})" if evaluated_by[name] else "-"
        rows.append((name, str(scene.n_nodes), str(scene.n_links), " ".join(entry.tags), entry.initial_states, benchmark, entry.description))
    widths = [max(len(row[k]) for row in (columns, *rows)) for k in range(len(columns) - 1)]
    print("# every built-in scene (`lgnn scene export NAME` writes one as JSON); benchmark: the profiles whose grid evaluates it")
    for row in (columns, *rows):
        print("  ".join(cell.ljust(width) for cell, width in zip(row, widths)) + "  " + row[-1])
    print("# tags: " + "; ".join(f"{tag}: {meaning}" for tag, meaning in TAGS.items()))


def _cmd_scene_export(args) -> None:
    from lgnn.files import write_text_atomic
    from lgnn.scene import CATALOGUE, get_scene, scene_to_json

    if args.name not in CATALOGUE:
        raise ConfigError(f"unknown built-in scene {args.name!r} (`lgnn scenes` lists them: {', '.join(CATALOGUE)})")
    text = scene_to_json(get_scene(args.name))
    if args.out in (None, "-"):
        sys.stdout.write(text)
    else:
        write_text_atomic(args.out, text)
        print(f"wrote {args.out}", file=sys.stderr)


def _cmd_scene_import(args) -> None:
    from lgnn.engines.mjcf_import import imported
    from lgnn.files import write_text_atomic
    from lgnn.scene import scene_to_json

    result = imported(args.file, args.key)
    for note in result.notes:
        print(f"note: {note}", file=sys.stderr)
    scene = result.scene
    text = scene_to_json(scene)
    if args.out in (None, "-"):
        sys.stdout.write(text)
    else:
        write_text_atomic(args.out, text)
        print(f"wrote {args.out}: {scene.name}, {scene.dim}D, {_count(scene.n_nodes, 'node')}, {_count(scene.n_links, 'link')}, "
              f"pins {list(scene.pinned)}, gravity {_gravity(scene)}", file=sys.stderr)


def _gravity(scene) -> str:
    return f"{[float(f'{g:.6g}') for g in scene.gravity_vector]}" if scene.lateral_gravity else f"{float(scene.gravity):g}"


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}{'' if n == 1 else 's'}"


def _cmd_simulate(args) -> None:
    from lgnn.engines import batch_of_one, get_engine
    from lgnn.engines.base import save_rollout
    from lgnn.metrics import energy_drift
    from lgnn.scene import get_scene

    config = simulation_config(args)
    trajectory_out(args.out)
    engine = get_engine(args.engine, dtype=args.dtype, progress=not args.quiet, form=args.form, integration=integration_of(args))
    scene = get_scene(args.scene)
    trajectory = save_rollout(lambda: engine.rollout(scene, config, batch_of_one(scene.initial_state)).member(0), args.out)
    # A JAX engine's trajectory names its integration; a MuJoCo engine steps by its own RK4.
    integrator = trajectory.metadata["integration"]["integrator"] if "integration" in trajectory.metadata else "MuJoCo's RK4"
    print(
        f"{scene.name}: {len(trajectory.t)} frames over {config.duration:g} s "
        f"({integrator}, dt {config.dt:g}); energy drift {energy_drift(scene, trajectory):.2e}; wrote {args.out}"
    )
    engine_record = trajectory.metadata.get("engine")
    if isinstance(engine_record, dict) and "accuracy" in engine_record:  # a MuJoCo engine's promise, or that there is none
        stated = engine_record["accuracy"]
        print(f"{args.engine}: expected max node error {stated:.1e} m (its stated accuracy)" if stated is not None else
              f"{args.engine}: no accuracy stated for this run (the error models hold for float64 runs of at most 1 s of open chains of alike links; MJX "
              "measures its maximal form's step on the scene itself); compare with a smaller --dt or --engine lagrangian",
              file=sys.stderr)


def _cmd_mjcf(args) -> None:
    from pathlib import Path

    from lgnn.engines import mjcf
    from lgnn.files import write_text_atomic
    from lgnn.scene import get_scene

    if args.scene is not None:
        form = {"form": args.form} if args.form else {}  # none: the renderer's default (nested)
        text = mjcf.render(get_scene(args.scene), args.dt, **form)
        if args.out in (None, "-"):
            sys.stdout.write(text)
        else:
            write_text_atomic(args.out, text)
            print(f"wrote {args.out} (view: python -m mujoco.viewer --mjcf={args.out})", file=sys.stderr)
        return
    if args.out is not None:
        raise ConfigError("--out needs a SCENE (without one, every built-in is written into --dir)")
    out = Path(args.dir)
    if not out.is_dir():
        raise ConfigError(f"MJCF directory does not exist: {out}")
    count, stale = mjcf.write_builtin_files(out, (args.form,) if args.form else mjcf.FORMS, check=args.check)
    if stale:
        raise ConfigError(f"MJCF files differ from what the code renders: {', '.join(stale)} (run: lgnn mjcf)")
    print(f"{'checked' if args.check else 'wrote'} {count} MJCF files in {out}")


def _cmd_crosscheck(args) -> None:
    from lgnn.bench import crosscheck as cc
    from lgnn.engines import ENGINES, get_engine
    from lgnn.files import check_writable, out_dir
    from lgnn.scene import get_scene

    command = "lgnn " + " ".join(args.argv)
    args.out_dir = out_dir(args.out_dir)
    stem = cc.SPEED_STEM if args.speed else cc.CROSSCHECK_STEM
    check_writable(f"{args.out_dir}/{stem}.md")
    engines = tuple(args.engines.split(","))
    parsed = [cc.engine_spec(spec) for spec in engines]
    if {name for name, _ in parsed} - set(ENGINES) or not engines:
        raise ConfigError(f"--engines: choose from {', '.join(ENGINES)} (each optionally NAME:FORM), got {args.engines!r}")
    for name, form in parsed:
        get_engine(name, form=form)  # a bad form fails before any run
    if args.speed and any(form for _, form in parsed):
        raise ConfigError(f"--engines: --speed takes engine names only (each MuJoCo engine in its own form), got {args.engines!r}")
    if args.speed:
        rows = cc.speed_error(args.scenes or list(cc.SPEED_SCENES), engines, dts=tuple(args.speed_dts), batches=tuple(args.batch),
                              batch_dts=tuple(args.batch_dts), mjx_max_depth=args.mjx_max_depth, max_steps=args.max_steps, dtype=args.dtype)
        cc.write_speed_error(rows, args.out_dir, command, args.dtype)
    else:
        config = simulation_config(args)
        rows = []
        for name in args.scenes or cc.SCENES:
            scene = get_scene(name)
            rows += cc.crosscheck(scene, config, engines, args.mjx_max_depth, progress=True, integration=integration_of(args))
            # Rows name the scene, not the argument (a scene file's path).
            print("\n".join(cc.row_line(row) for row in rows if row["scene"] == scene.name))
        cc.write_crosscheck(rows, args.out_dir, command, config)
    print(f"wrote {args.out_dir}/{stem}.csv and .md")


def _add_mujoco_commands(commands) -> None:
    from lgnn.bench.crosscheck import SCENES, default_engines
    from lgnn.engines.base import DTYPES
    from lgnn.engines.mjcf import FORMS

    mjcf = commands.add_parser("mjcf", help="render a scene's MJCF, or every built-in's into mjcf/")
    mjcf.add_argument("scene", nargs="?", help="built-in name or scene file to render (default: every built-in, both forms, into --dir)")
    mjcf.add_argument("--form", choices=FORMS, help="nested (joint coordinates) or maximal (a body per link, connect joints)")
    mjcf.add_argument("--dt", type=positive_float, default=1e-4, help="SCENE: time step written into the model (default 1e-4)")
    mjcf.add_argument("--out", help="SCENE: output .xml file (default: standard output)")
    mjcf.add_argument("--dir", default="mjcf", help="output directory (default: mjcf)")
    mjcf.add_argument("--check", action="store_true", help="fail if a file differs from the rendered text (numbers beyond 1e-12 relative: machines round the last bit differently)")
    mjcf.set_defaults(run=_cmd_mjcf)
    check = commands.add_parser("crosscheck", help="run every engine on the same scenes and compare them")
    check.add_argument("scenes", nargs="*", help=f"built-in names or scene files (default: {' '.join(SCENES)})")
    check.add_argument("--engines", default=",".join(default_engines()),
                       help="comma-separated engines, each NAME or NAME:FORM (e.g. mujoco:nested,mujoco:maximal: both MJCF forms in one table)")
    check.add_argument("--mjx-max-depth", type=nonnegative_int, help="skip MJX on deeper trees (default: skip none)")
    check.add_argument("--speed", action="store_true", help="write the speed-against-error table instead")
    check.add_argument("--speed-dts", type=positive_float, nargs="+", default=[1e-3, 1e-4, 1e-5], help="--speed: steps of the single-state runs")
    check.add_argument("--batch", type=positive_int, nargs="+", default=[100], help="--speed: batch sizes of the batched runs (default 100)")
    check.add_argument("--batch-dts", type=positive_float, nargs="+", default=[1e-4], help="--speed: steps of the batched runs (default 1e-4)")
    check.add_argument("--max-steps", type=positive_int, default=25_000, help="--speed: skip JAX runs over 16x this many link-steps")
    check.add_argument("--dtype", choices=DTYPES, default=DTYPES[0], help="--speed: precision of the JAX engines")
    check.add_argument("--out-dir", default=None, help="output directory (default: ./lgnn-out; the committed tables are results/)")
    add_simulation_options(check)
    check.set_defaults(run=_cmd_crosscheck)


def _of_engines(field: str) -> list[str]:
    """Every value of the registered engines' `field` (`EngineEntry.dtypes`, `.forms`), in order."""
    from lgnn.engines import ENGINES

    return list(dict.fromkeys(value for entry in ENGINES.values() for value in getattr(entry, field)))


def _add_scene_parsers(commands) -> None:
    from lgnn.engines import ENGINES

    scenes = commands.add_parser("scenes", help="list the built-in scenes, their tags, initial states and whether the benchmark evaluates them")
    scenes.set_defaults(run=_cmd_scenes)

    scene = commands.add_parser("scene", help="scene utilities")
    scene_commands = scene.add_subparsers(dest="scene_command", required=True, metavar="SUBCOMMAND")
    export = scene_commands.add_parser("export", help="write a built-in scene as JSON")
    export.add_argument("name")
    export.add_argument("--out", help="output file (default: standard output)")
    export.set_defaults(run=_cmd_scene_export)
    mjcf_in = scene_commands.add_parser("import", help="import an MJCF file (MuJoCo's model format) as a scene, or say in one line why not")
    mjcf_in.add_argument("file", help="MJCF (.xml) file; MuJoCo compiles it, includes and defaults as MuJoCo reads them")
    mjcf_in.add_argument("--key", help="keyframe whose qpos and qvel are the initial state (default: qpos0, at rest)")
    mjcf_in.add_argument("--out", help="output scene JSON file (default: standard output)")
    mjcf_in.set_defaults(run=_cmd_scene_import)

    simulate = commands.add_parser("simulate", help="simulate a scene with a ground-truth engine")
    simulate.add_argument("scene", help="built-in scene name or scene JSON file")
    simulate.add_argument("--engine", default="lagrangian", choices=list(ENGINES), help="ground-truth engine (default: lagrangian)")
    simulate.add_argument("--dtype", choices=_of_engines("dtypes"), default=None,
                          help="precision of the engine (default: its own, float64 but MuJoCo Warp's float32); one it lacks is refused")
    simulate.add_argument("--form", choices=_of_engines("forms"), help="MuJoCo engines: MJCF form (default auto: the engine's choice)")
    add_simulation_options(simulate)
    simulate.add_argument("--out", required=True, help="output .npz file")
    simulate.add_argument("--quiet", action="store_true", help="no progress bar")
    simulate.set_defaults(run=_cmd_simulate)


# `lgnn scenes`, `scene export`, `simulate`, `mjcf` and `crosscheck`: their parsers'
# builders, in `lgnn --help`'s order.
PARSERS = (_add_scene_parsers, _add_mujoco_commands)
