"""The `lgnn` command line.

Every `LgnnError` becomes one line on stderr (`lgnn: error: ...`) and exit status 2;
output files are written atomically. Runtime set-up (`lgnn.runtime.configure`: float64,
thread counts, XLA flags) is done here, at the entry point.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import sys

from lgnn.errors import ConfigError, LgnnError


class _Parser(argparse.ArgumentParser):
    """argparse, but a usage error is one line `lgnn: error: ...` (exit 2) like every
    other bad input; `--help` still shows the usage."""

    def error(self, message: str):
        self.exit(2, f"lgnn: error: {message} (see: {self.prog} --help)\n")


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive whole number, got {text}")
    return value


def _cmd_scenes(args) -> None:
    from lgnn.scene import BUILTIN_SCENES, HARD_SCENES

    width = max(map(len, {**BUILTIN_SCENES, **HARD_SCENES}))
    for title, catalogue in (("built-in scenes", BUILTIN_SCENES), ("hard cases (lgnn stability, tests)", HARD_SCENES)):
        print(f"# {title}")
        for entry in catalogue.values():
            scene = entry.build()
            print(f"{entry.name:<{width}}  {scene.n_nodes:4d} nodes {scene.n_links:4d} links  {entry.description}")


def _cmd_scene_export(args) -> None:
    from lgnn.files import write_text_atomic
    from lgnn.scene import scene_to_json
    from lgnn.scene import BUILTIN_SCENES, get_scene

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
    from lgnn.engines.lagrangian import SimulationConfig

    default = SimulationConfig()
    parser.add_argument("--integrator", choices=sorted(INTEGRATORS), default=default.integrator)
    parser.add_argument("--dt", type=_positive_float, default=default.dt, help="integration step (s)")
    parser.add_argument("--frame-dt", type=_positive_float, default=default.frame_dt, help="interval between saved frames (s)")
    parser.add_argument("--duration", type=_positive_float, default=default.duration, help="simulated time (s)")
    parser.add_argument("--no-project", dest="project", action="store_false", help="do not project onto the constraints after each step")


def _simulation_config(args):
    from lgnn.engines.lagrangian import SimulationConfig

    return SimulationConfig(args.integrator, args.dt, args.frame_dt, args.duration, args.project)


def _cmd_simulate(args) -> None:
    from lgnn.engines import batch_of_one, get_engine
    from lgnn.files import check_writable
    from lgnn.metrics import energy_drift
    from lgnn.scene import get_scene

    config = _simulation_config(args)
    check_writable(args.out)
    engine = get_engine(args.engine, dtype=args.dtype, progress=not args.quiet, form=args.form)
    scene = get_scene(args.scene)
    trajectory = engine.rollout(scene, config, batch_of_one(scene.initial_state)).member(0)
    trajectory.save(args.out)
    print(
        f"{scene.name}: {len(trajectory.t)} frames over {config.duration:g} s "
        f"({config.integrator}, dt {config.dt:g}); energy drift {energy_drift(scene, trajectory):.2e}; wrote {args.out}"
    )


def _cmd_mjcf(args) -> None:
    from pathlib import Path

    from lgnn.engines import mjcf
    from lgnn.files import write_text_atomic
    from lgnn.scene import get_scene

    if args.scene is not None:
        text = mjcf.render(get_scene(args.scene), args.dt, args.form or "nested")
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
    files = mjcf.builtin_files((args.form,) if args.form else mjcf.FORMS)
    stale = []
    for name, text in files.items():
        path = out / name
        if args.check:
            if not path.exists() or path.read_text() != text:
                stale.append(str(path))
        else:
            path.parent.mkdir(exist_ok=True)
            write_text_atomic(path, text)
    if stale:
        raise ConfigError(f"MJCF files differ from what the code renders: {', '.join(stale)} (run: lgnn mjcf)")
    print(f"{'checked' if args.check else 'wrote'} {len(files)} MJCF files in {out}")


def _cmd_crosscheck(args) -> None:
    from lgnn.bench import crosscheck as cc
    from lgnn.bench.tables import write_table
    from lgnn.engines import ENGINES
    from lgnn.files import check_writable
    from lgnn.scene import get_scene

    command = "lgnn " + " ".join(args.argv)
    check_writable(f"{args.out_dir}/engines_speed_error.md" if args.speed else f"{args.out_dir}/crosscheck.md")
    engines = tuple(args.engines.split(","))
    if set(engines) - set(ENGINES) or not engines:
        raise ConfigError(f"--engines: choose from {', '.join(ENGINES)}, got {args.engines!r}")
    if args.speed:
        rows = cc.speed_error(args.scenes or ["chain4", "chain16", "chain100", "T1"], engines, dts=tuple(args.speed_dts), batches=tuple(args.batch),
                              batch_dts=tuple(args.batch_dts), mjx_max_depth=args.mjx_max_depth, max_steps=args.max_steps, dtype=args.dtype)
        columns = ["scene", "engine", "form", "batch", "dt", "dtype", "steps_per_s", "compile_s", "max_node_error", "note"]
        notes = [f"speed: steps/s = batch x steps / run time (compile apart), RK4, horizon 0.1 s, JAX engines in {args.dtype}",
                 "error: max node error after 0.1 s (single state) vs MuJoCo C RK4 at dt 1e-6"]
        stem, title = "engines_speed_error", "Engines: speed against error"
    else:
        config = _simulation_config(args)
        rows = []
        for name in args.scenes or ["chain4", "chain8", "chain16", "T1", "T2", "T3"]:
            rows += cc.crosscheck(get_scene(name), config, engines, args.mjx_max_depth, progress=True)
            print("\n".join(f"{r['scene']:8s} {r['engine']:18s} {r['form']:16s} {r['metric']:22s} {r['value']:.3e} {r['note']}" for r in rows if r["scene"] == name))
        columns = ["scene", "engine", "form", "metric", "value", "note"]
        notes = [f"RK4, dt {config.dt:g}, {config.duration:g} s, float64; MuJoCo loops: connect, solref 2 dt, solimp 0.9999",
                 "form: the MJCF form each MuJoCo engine ran (nested: joint coordinates; maximal: a body per link, connect joints)"]
        stem, title = "crosscheck", "Cross-check of the ground-truth engines"
    write_table(rows, columns, f"{args.out_dir}/{stem}.csv", f"{args.out_dir}/{stem}.md", title, cc.header(command), notes)
    print(f"wrote {args.out_dir}/{stem}.csv and .md")


def _add_mujoco_commands(commands) -> None:
    mjcf = commands.add_parser("mjcf", help="render a scene's MJCF, or every built-in's into mjcf/")
    mjcf.add_argument("scene", nargs="?", help="built-in name or scene file to render (default: every built-in, both forms, into --dir)")
    mjcf.add_argument("--form", choices=("nested", "maximal"), help="nested (joint coordinates) or maximal (a body per link, connect joints)")
    mjcf.add_argument("--dt", type=_positive_float, default=1e-4, help="SCENE: time step written into the model (default 1e-4)")
    mjcf.add_argument("--out", help="SCENE: output .xml file (default: standard output)")
    mjcf.add_argument("--dir", default="mjcf", help="output directory (default: mjcf)")
    mjcf.add_argument("--check", action="store_true", help="fail if a file differs from the rendered text")
    mjcf.set_defaults(run=_cmd_mjcf)
    check = commands.add_parser("crosscheck", help="run every engine on the same scenes and compare them")
    check.add_argument("scenes", nargs="*", help="built-in names or scene files (default: chain4 chain8 chain16 T1 T2 T3)")
    check.add_argument("--engines", default="lagrangian,mujoco,mjx", help="comma-separated engines")
    check.add_argument("--mjx-max-depth", type=int, help="skip MJX on deeper trees (default: skip none)")
    check.add_argument("--speed", action="store_true", help="write the speed-against-error table instead")
    check.add_argument("--speed-dts", type=float, nargs="+", default=[1e-3, 1e-4, 1e-5], help="--speed: steps of the single-state runs")
    check.add_argument("--batch", type=int, nargs="+", default=[100], help="--speed: batch sizes of the batched runs (default 100)")
    check.add_argument("--batch-dts", type=float, nargs="+", default=[1e-4], help="--speed: steps of the batched runs (default 1e-4)")
    check.add_argument("--max-steps", type=int, default=25_000, help="--speed: skip JAX runs over 16x this many link-steps")
    check.add_argument("--dtype", choices=("float64", "float32"), default="float64", help="--speed: precision of the JAX engines")
    check.add_argument("--out-dir", default="results", help="output directory (default: results)")
    _add_simulation_options(check)
    check.set_defaults(run=_cmd_crosscheck)


def _cmd_convergence(args) -> None:
    from lgnn.bench import convergence
    from lgnn.bench.grid import get_profile
    from lgnn.files import check_writable
    from lgnn.provenance import environment
    from lgnn.scene import BUILTIN_SCENES, get_scene

    check_writable(f"{args.out_dir}/convergence.md")
    environment()  # the commit the run starts at, before any edit during a long run
    evaluate = get_profile("full").evaluate
    log = (lambda line: None) if args.quiet else (lambda line: print(line, flush=True))
    rows = []
    for name in args.scenes or list(BUILTIN_SCENES) + list(convergence.PROPOSED_SCENES):
        scene = get_scene(name)
        config = evaluate.simulation(scene.name)
        horizon = args.horizon or convergence.default_horizon(scene)
        config = dataclasses.replace(config, dt=args.dt or config.dt, frame_dt=args.frame_dt, duration=horizon)
        rows += convergence.reference_convergence(scene, config, args.halvings, log=log)
    command = "lgnn " + " ".join(args.argv)
    convergence.write_report(rows, f"{args.out_dir}/convergence.csv", f"{args.out_dir}/convergence.md", command)
    print("\n".join(convergence.summary(rows)))
    print(f"wrote {args.out_dir}/convergence.csv and .md")


def _add_convergence_parser(commands) -> None:
    parser = commands.add_parser("convergence", help="measure the Lagrangian reference's convergence in dt on each scene")
    parser.add_argument("scenes", nargs="*", help="built-in names or scene files (default: every built-in scene, then T2-slack and T3-slack)")
    parser.add_argument("--halvings", type=_positive_int, default=3, help="runs at dt, dt/2, ..., dt/2^halvings (default 3)")
    parser.add_argument("--dt", type=_positive_float, default=None, help="coarsest step (default: the full benchmark's step for the scene)")
    parser.add_argument("--horizon", type=_positive_float, default=None,
                        help="simulated seconds (default: 1 s, 0.1 s on chain100 and the self-stressed or large scenes)")
    parser.add_argument("--frame-dt", type=_positive_float, default=1e-3, help="frames compared every this many seconds (default 1e-3)")
    parser.add_argument("--out-dir", default="results", help="output directory (default: results)")
    parser.add_argument("--quiet", action="store_true", help="no per-run lines")
    parser.set_defaults(run=_cmd_convergence)


def _cmd_train(args) -> None:
    from pathlib import Path

    from lgnn.learn import data, models, train
    from lgnn.files import check_writable
    from lgnn.scene import get_scene

    check_writable(args.out)
    data_config = data.DataConfig(args.scene, n_trajectories=args.trajectories, seed=args.seed)
    scene = get_scene(args.scene)
    model = models.ModelConfig.for_scene(args.model, scene, message_passing=args.message_passing)
    config = train.TrainConfig(args.lr, args.batch_size, args.epochs, args.minutes, args.patience, args.seed)
    if args.resume and Path(args.out).exists():
        train.check_resumable(args.out, model, config)  # before minutes of data generation
    dataset = data.load_or_generate(data_config, args.cache_dir, progress=not args.quiet)
    state = train.train(model, config, dataset, scene, out=args.out, data_config=data_config, resume=args.resume, progress=not args.quiet)
    print(f"{args.model} on {scene.name}: {state.epoch} epochs, best validation MSE {state.best_val:.4g} (epoch {state.best_epoch}); wrote {args.out}")


def _cmd_rollout(args) -> None:
    from lgnn.learn import models
    from lgnn.files import check_writable
    from lgnn.scene import get_scene
    from lgnn.learn.train import load_model
    from lgnn.metrics import energy_drift

    config = _simulation_config(args)
    check_writable(args.out)
    model, params = load_model(args.model)
    scene = get_scene(args.scene)
    trajectory = models.rollout(model, params, scene, config, progress=not args.quiet)
    trajectory.save(args.out)
    print(f"{model.name} on {scene.name}: {len(trajectory.t)} frames over {config.duration:g} s; "
          f"true energy drift {energy_drift(scene, trajectory):.2e}; wrote {args.out}")


def _add_train_parser(commands) -> None:
    from lgnn.learn.models import model_names
    from lgnn.learn.train import TrainConfig

    default = TrainConfig()
    parser = commands.add_parser("train", help="train a learned model on ground-truth data")
    parser.add_argument("--model", required=True, choices=model_names())
    parser.add_argument("--scene", default="chain4", help="training scene (built-in name or JSON file)")
    parser.add_argument("--epochs", type=int, default=default.epochs, help="epoch budget (paper: 10000)")
    parser.add_argument("--minutes", type=_positive_float, default=None, help="optional wall-clock cap (checked after each epoch); the budget is --epochs")
    parser.add_argument("--patience", type=int, default=default.patience, help="early stopping: epochs without improvement")
    parser.add_argument("--lr", type=_positive_float, default=default.learning_rate)
    parser.add_argument("--batch-size", type=int, default=default.batch_size)
    parser.add_argument("--message-passing", type=int, default=None, help="message-passing layers (default: the model's)")
    parser.add_argument("--trajectories", type=int, default=100, help="training trajectories (paper: 100)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cache-dir", default="results/datasets", help="training data cache")
    parser.add_argument("--resume", action="store_true", help="continue from the checkpoint at --out")
    parser.add_argument("--out", required=True, help="checkpoint file (.npz), written after every epoch")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.set_defaults(run=_cmd_train)

    inspect = commands.add_parser("checkpoint", help="summarise a checkpoint: epochs, losses, training time")
    inspect.add_argument("path", help="checkpoint written by lgnn train or lgnn benchmark")
    inspect.add_argument("--reference", help="another checkpoint: also print when this one reached its best validation loss")
    inspect.set_defaults(run=_cmd_checkpoint)

    rollout = commands.add_parser("rollout", help="roll a trained model out on a scene")
    rollout.add_argument("scene", help="built-in scene name or scene JSON file")
    rollout.add_argument("--model", required=True, help="checkpoint written by lgnn train")
    _add_simulation_options(rollout)
    rollout.add_argument("--out", required=True, help="output .npz file (same layout as lgnn simulate)")
    rollout.add_argument("--quiet", action="store_true", help="no progress bar")
    rollout.set_defaults(run=_cmd_rollout)


def _cmd_checkpoint(args) -> None:
    from lgnn.learn import train

    state, meta = train.load_checkpoint(args.path)
    print(f"{args.path}: {meta['model']['name']}, epoch {state.epoch}, best validation loss {state.best_val:.4g} at epoch {state.best_epoch}, "
          f"{state.elapsed_s:.1f} s of training")
    if args.reference:
        reference, _ = train.load_checkpoint(args.reference)
        seconds = train.seconds_to_reach(state, reference.best_val)
        if seconds is not None:
            reached = f"reached after {seconds:.1f} s"
        elif state.history and len(state.history[0]) < 4:
            reached = "unknown (this checkpoint predates per-epoch times)"
        else:
            reached = "not reached"
        print(f"reference {args.reference}: best validation loss {reference.best_val:.4g} ({reference.elapsed_s:.1f} s of training): {reached}")


def _cmd_benchmark(args) -> None:
    from pathlib import Path

    from lgnn.bench import grid
    from lgnn.bench.run import STAGES, run

    profile = grid.get_profile("full" if args.full else "quick")
    if args.chunk is not None:
        # Not an evaluation setting (records stay valid): only how many rollouts share a call.
        profile = dataclasses.replace(profile, evaluate=dataclasses.replace(profile.evaluate, chunk=args.chunk))
    stages = STAGES if args.stage == "all" else (args.stage,)
    out = run(profile, Path(args.out_dir) if args.out_dir else None, stages, args.job, args.scene, progress=not args.quiet)
    if "report" in stages:
        print((out / "README.md").read_text())


def _add_benchmark_parser(commands) -> None:
    from lgnn.bench.run import STAGES

    parser = commands.add_parser("benchmark", help="train and evaluate every model on every scene; write results/")
    parser.add_argument("--full", action="store_true", help="the full profile (default: the quick one, minutes on a laptop)")
    parser.add_argument("--stage", default="all", choices=("all",) + STAGES, help="run one stage (default: all, resuming finished work)")
    parser.add_argument("--job", action="append", help="only this training job, e.g. lgnn-chain4-s0 (repeatable)")
    parser.add_argument("--scene", action="append", help="only this evaluation scene (repeatable)")
    parser.add_argument("--out-dir", default=None, help="output directory (default: results/ for --full, results/quick/ otherwise)")
    parser.add_argument("--chunk", type=_positive_int, default=None, help="initial conditions per compiled rollout call (default 25; a GPU wants 100)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.set_defaults(run=_cmd_benchmark)


def _cmd_stability(args) -> None:
    from lgnn.bench import stability
    from lgnn.files import check_writable

    out = check_writable(args.out)
    if out.suffix != ".md":
        raise ConfigError(f"--out must be a .md file (the CSV is written beside it), got {out}")
    settings = stability.StabilitySettings(
        **{k: getattr(args, k) for k in ("long_horizon", "large_step_horizon", "chain1000_horizon", "model_horizon", "singular_horizon")},
        cost_sizes=tuple(args.cost_sizes),
    )
    selected = stability.cases(settings)
    if args.case:
        known = sorted({c.name for c in selected})
        unknown = sorted(set(args.case) - set(known))
        if unknown:
            raise ConfigError(f"unknown stability case {unknown[0]!r} (choose from {', '.join(known)})")
        selected = tuple(c for c in selected if c.name in args.case)
    log = (lambda line: None) if args.quiet else (lambda line: print(line, flush=True))
    rows = stability.run(selected, log=log)
    cost, exponent = stability.cost_rows(settings.cost_sizes, log=log) if settings.cost_sizes else ([], float("nan"))
    command = "lgnn " + " ".join(args.argv)
    csv_path = stability.write_report(rows + cost, out, command, exponent, stability.NOTES + (f"settings: {dataclasses.asdict(settings)}",))
    print(f"wrote {out} and {csv_path}")


def _add_stability_parser(commands) -> None:
    from lgnn.bench.stability import StabilitySettings

    default = StabilitySettings()
    parser = commands.add_parser("stability", help="run the hard cases (long, large, near-singular, learned) and write a report")
    parser.add_argument("--out", default="results/stability.md", help="markdown report; the CSV goes beside it (default: results/stability.md)")
    for name in ("long_horizon", "large_step_horizon", "chain1000_horizon", "model_horizon", "singular_horizon"):
        parser.add_argument(f"--{name.replace('_', '-')}", type=_positive_float, default=getattr(default, name),
                            help=f"simulated seconds (default {getattr(default, name):g})")
    parser.add_argument("--cost-sizes", type=int, nargs="*", default=list(default.cost_sizes), help="chain sizes timed per step (none: skip)")
    parser.add_argument("--case", action="append", help="only this case (repeatable), e.g. large-step")
    parser.add_argument("--quiet", action="store_true", help="no per-case lines")
    parser.set_defaults(run=_cmd_stability)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="lgnn", description=__doc__.splitlines()[0])
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
    simulate.add_argument("--engine", default="lagrangian", help="ground-truth engine: lagrangian (default), mujoco, mjx (lgnn.engines.ENGINES)")
    simulate.add_argument("--dtype", choices=["float64", "float32"], default="float64", help="MJX precision (default float64)")
    simulate.add_argument("--form", choices=["auto", "nested", "maximal"], help="MuJoCo engines: MJCF form (default auto: the engine's choice)")
    _add_simulation_options(simulate)
    simulate.add_argument("--out", required=True, help="output .npz file")
    simulate.add_argument("--quiet", action="store_true", help="no progress bar")
    simulate.set_defaults(run=_cmd_simulate)
    _add_mujoco_commands(commands)
    _add_train_parser(commands)
    _add_benchmark_parser(commands)
    _add_stability_parser(commands)
    _add_convergence_parser(commands)
    return parser


def main(argv: list[str] | None = None) -> int:
    from lgnn.runtime import configure

    configure()  # first: before numpy and JAX load (thread counts, XLA flags, float64)
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else [str(a) for a in argv]
    args = parser.parse_args(argv)
    args.argv = argv  # reports name the exact command
    try:
        args.run(args)
    except LgnnError as err:
        print(f"lgnn: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("lgnn: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # The reader went away (`lgnn scenes | head`): stop quietly, as Unix tools do.
        # stdout is pointed at devnull so the interpreter's final flush cannot fail again.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    return 0


if __name__ == "__main__":
    sys.exit(main())
