"""The `lgnn` command line.

Every `LgnnError` becomes one line on stderr (`lgnn: error: ...`) and exit status 2
(`EXIT_BAD_INPUT`), 3 for a diverged simulation (`EXIT_DIVERGED`, frames before it kept);
output files are written atomically. Runtime set-up (`lgnn.runtime.configure`: float64,
thread counts, XLA flags) is done here, at the entry point.
"""

from __future__ import annotations

from lgnn.interrupts import EXIT_INTERRUPTED, HeldWhileLoading, run_interruptibly

# A Ctrl-C while this module loads, before `main` takes SIGINT, is remembered here and
# answered by `main` (one line, exit 130), not raised as a traceback from an import.
_LOADING = HeldWhileLoading()
with _LOADING:
    import argparse
    import dataclasses
    import math
    import os
    import re
    import sys

    from lgnn.errors import ConfigError, LgnnError, SimulationError


# Exit statuses (docs/cli.md, "Behaviour common to every command").
EXIT_BAD_INPUT = 2
EXIT_DIVERGED = 3  # a simulation or rollout diverged; the frames before it are kept
# EXIT_INTERRUPTED (130, Ctrl-C) is `lgnn.interrupts`'.
# `lgnn convergence --halvings`: dt / 2^20 is a millionth of the coarsest step, already
# more steps than a run finishes in a day.
MAX_HALVINGS = 20
# `lgnn animate`: frames per second and simulated seconds per second of animation; out
# of these, a frame lasts longer than a GIF can say or the stride overflows.
FPS_RANGE = (0.1, 1000.0)
SPEED_RANGE = (1e-6, 1e6)
# `lgnn evaluate --initial-conditions`: the paper's 100 a thousand times over; more
# would be refused only after sampling them all (their rollouts are kept in memory).
MAX_INITIAL_CONDITIONS = 100_000


class _Parser(argparse.ArgumentParser):
    """argparse, but a usage error is one line `lgnn: error: ...` (exit 2) like every
    other bad input; `--help` still shows the usage. A negative number in scientific
    notation (`--dt -1e-4`) is a value, not an option, so it reaches the value's own
    check ("must be a positive number") instead of "expected one argument"."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$")

    def error(self, message: str):
        self.exit(2, f"lgnn: error: {one_line(message)} (see: {self.prog} --help)\n")


# Characters that would break the one error line (a newline in a file name) or the
# terminal's encoding (a lone surrogate from an undecodable name): shown escaped.
_UNPRINTABLE = re.compile(r"[\x00-\x1f\x7f\ud800-\udfff]")


def one_line(message: str) -> str:
    """`message` with control characters and lone surrogates escaped (`\\n`, `\\udcff`)."""
    return _UNPRINTABLE.sub(lambda match: repr(match.group())[1:-1], message)


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def _float_in(low: float, high: float):
    """An option's type: a number in [low, high] (a rate whose reciprocal must stay finite)."""

    def parse(text: str) -> float:
        value = _positive_float(text)
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"must be between {low:g} and {high:g}, got {text}")
        return value

    return parse


def _int_in(low: int, high: int | None = None):
    """An option's type: a whole number >= low (and <= high when given)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"must be a {'positive' if low == 1 else f'>= {low}'} whole number, got {text}")
        if high is not None and value > high:
            raise argparse.ArgumentTypeError(f"must be at most {high}, got {text}")
        return value

    return parse


_positive_int = _int_in(1)
_nonnegative_int = _int_in(0)


def _file_name_part(text: str) -> str:
    """An option's type: text that goes into a file's name, so no folder in it."""
    if any(mark in text for mark in ("/", "\\", "\0")) or text in (".", ".."):
        raise argparse.ArgumentTypeError(f"goes into file names, so no folder or path separator: {text!r}")
    return text


def _model_reference(text: str) -> str:
    """A built-in model name, or a `module:attribute` / `file.py:attribute` reference
    to a model defined outside lgnn (imported when the command runs, so a failing
    import is the command's one-line error, not argparse's)."""
    from lgnn.learn.models import model_names

    if ":" in text or text in model_names():
        return text
    raise argparse.ArgumentTypeError(f"invalid choice: {text!r} (choose from {', '.join(map(repr, model_names()))}, "
                                     "or module:attribute or file.py:attribute of your own ModelSpec)")


def _add_model_code_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model-code", metavar="MODULE:ATTR", default=None,
                        help="a checkpoint of your own model: the module:attribute or file.py:attribute it was trained with "
                             "(the checkpoint names it; its code is imported only when you say so)")


def _import_model_code(args) -> None:
    """Register the model code `--model-code` names, before a checkpoint of it is read."""
    if args.model_code:
        from lgnn.learn.models import load_spec

        load_spec(args.model_code)


def _cmd_scenes(args) -> None:
    from lgnn.bench.grid import PROFILES, evaluation_scenes
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


def _add_simulation_options(parser: argparse.ArgumentParser) -> None:
    from lgnn.integrate import INTEGRATORS
    from lgnn.engines.base import Integration, SimulationConfig

    default = SimulationConfig()
    # Integration options default to None: given, they are refused by an engine that
    # integrates its own way (the MuJoCo engines), not silently dropped.
    parser.add_argument("--integrator", choices=sorted(INTEGRATORS), default=None,
                        help=f"integrator of the Lagrangian engine and learned models (default {Integration().integrator})")
    parser.add_argument("--dt", type=_positive_float, default=default.dt, help="integration step (s)")
    parser.add_argument("--frame-dt", type=_positive_float, default=default.frame_dt, help="interval between saved frames (s)")
    parser.add_argument("--duration", type=_positive_float, default=default.duration, help="simulated time (s)")
    parser.add_argument("--no-project", dest="project", action="store_const", const=False, default=None,
                        help="do not project onto the constraints after each step (Lagrangian engine and learned models)")


def _simulation_config(args):
    from lgnn.engines.base import SimulationConfig

    if args.dt > args.frame_dt:
        raise ConfigError(f"dt {args.dt:g} is longer than the interval between frames (--frame-dt {args.frame_dt:g}): "
                          f"pass --frame-dt too, a whole multiple of dt (e.g. --frame-dt {args.dt:g})")
    return SimulationConfig(args.dt, args.frame_dt, args.duration)


def _integration(args):
    """The `Integration` that `--integrator` and `--no-project` ask for; None where
    neither is given (each engine's own)."""
    from lgnn.engines.base import Integration

    if args.integrator is None and args.project is None:
        return None
    default = Integration()
    return Integration(args.integrator or default.integrator, default.project if args.project is None else args.project)


def _trajectory_out(path: str):
    """`--out` of a trajectory: an `.npz` file (the only trajectory format), checked
    writable before any work."""
    from lgnn.files import check_writable

    checked = check_writable(path)
    if checked.suffix != ".npz":
        raise ConfigError(f"--out: trajectories are written as .npz (t, q, qd, energy; docs/formats.md), got {path!r}")
    return checked


def _cmd_simulate(args) -> None:
    from lgnn.engines import batch_of_one, get_engine
    from lgnn.engines.base import save_rollout
    from lgnn.metrics import energy_drift
    from lgnn.scene import get_scene

    config = _simulation_config(args)
    _trajectory_out(args.out)
    engine = get_engine(args.engine, dtype=args.dtype, progress=not args.quiet, form=args.form, integration=_integration(args))
    scene = get_scene(args.scene)
    trajectory = save_rollout(lambda: engine.rollout(scene, config, batch_of_one(scene.initial_state)).member(0), args.out)
    # A JAX engine's trajectory names its integration; a MuJoCo engine steps by its own RK4.
    integrator = trajectory.metadata["integration"]["integrator"] if "integration" in trajectory.metadata else "MuJoCo's RK4"
    print(
        f"{scene.name}: {len(trajectory.t)} frames over {config.duration:g} s "
        f"({integrator}, dt {config.dt:g}); energy drift {energy_drift(scene, trajectory):.2e}; wrote {args.out}"
    )


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
        config = _simulation_config(args)
        rows = []
        for name in args.scenes or cc.SCENES:
            scene = get_scene(name)
            rows += cc.crosscheck(scene, config, engines, args.mjx_max_depth, progress=True, integration=_integration(args))
            # Rows name the scene, not the argument (a scene file's path).
            print("\n".join(cc.row_line(row) for row in rows if row["scene"] == scene.name))
        cc.write_crosscheck(rows, args.out_dir, command, config)
    print(f"wrote {args.out_dir}/{stem}.csv and .md")


def _add_mujoco_commands(commands) -> None:
    from lgnn.bench.crosscheck import DEFAULT_ENGINES, SCENES
    from lgnn.engines.base import DTYPES
    from lgnn.engines.mjcf import FORMS

    mjcf = commands.add_parser("mjcf", help="render a scene's MJCF, or every built-in's into mjcf/")
    mjcf.add_argument("scene", nargs="?", help="built-in name or scene file to render (default: every built-in, both forms, into --dir)")
    mjcf.add_argument("--form", choices=FORMS, help="nested (joint coordinates) or maximal (a body per link, connect joints)")
    mjcf.add_argument("--dt", type=_positive_float, default=1e-4, help="SCENE: time step written into the model (default 1e-4)")
    mjcf.add_argument("--out", help="SCENE: output .xml file (default: standard output)")
    mjcf.add_argument("--dir", default="mjcf", help="output directory (default: mjcf)")
    mjcf.add_argument("--check", action="store_true", help="fail if a file differs from the rendered text")
    mjcf.set_defaults(run=_cmd_mjcf)
    check = commands.add_parser("crosscheck", help="run every engine on the same scenes and compare them")
    check.add_argument("scenes", nargs="*", help=f"built-in names or scene files (default: {' '.join(SCENES)})")
    check.add_argument("--engines", default=",".join(DEFAULT_ENGINES),
                       help="comma-separated engines, each NAME or NAME:FORM (e.g. mujoco:nested,mujoco:maximal: both MJCF forms in one table)")
    check.add_argument("--mjx-max-depth", type=_nonnegative_int, help="skip MJX on deeper trees (default: skip none)")
    check.add_argument("--speed", action="store_true", help="write the speed-against-error table instead")
    check.add_argument("--speed-dts", type=_positive_float, nargs="+", default=[1e-3, 1e-4, 1e-5], help="--speed: steps of the single-state runs")
    check.add_argument("--batch", type=_positive_int, nargs="+", default=[100], help="--speed: batch sizes of the batched runs (default 100)")
    check.add_argument("--batch-dts", type=_positive_float, nargs="+", default=[1e-4], help="--speed: steps of the batched runs (default 1e-4)")
    check.add_argument("--max-steps", type=_positive_int, default=25_000, help="--speed: skip JAX runs over 16x this many link-steps")
    check.add_argument("--dtype", choices=DTYPES, default=DTYPES[0], help="--speed: precision of the JAX engines")
    check.add_argument("--out-dir", default=None, help="output directory (default: ./lgnn-out; the committed tables are results/)")
    _add_simulation_options(check)
    check.set_defaults(run=_cmd_crosscheck)


def _cmd_convergence(args) -> None:
    from lgnn.bench import convergence
    from lgnn.bench.grid import get_profile
    from lgnn.files import check_writable, out_dir
    from lgnn.provenance import environment
    from lgnn.scene import get_scene, scene_names

    args.out_dir = out_dir(args.out_dir)
    check_writable(f"{args.out_dir}/convergence.md")
    environment()  # the commit the run starts at, before any edit during a long run
    evaluate = get_profile("full").evaluate
    log = (lambda line: None) if args.quiet else (lambda line: print(line, flush=True))
    rows = []
    for name in args.scenes or list(scene_names("paper")) + list(convergence.PROPOSED_SCENES):
        scene = get_scene(name)
        config = evaluate.simulation(scene.name)
        horizon = args.horizon or convergence.default_horizon(scene)
        config = dataclasses.replace(config, dt=args.dt or config.dt, frame_dt=args.frame_dt, duration=horizon)
        rows += convergence.reference_convergence(scene, config, args.halvings, log=log, integration=evaluate.integration)
    command = "lgnn " + " ".join(args.argv)
    convergence.write_report(rows, f"{args.out_dir}/convergence.csv", f"{args.out_dir}/convergence.md", command)
    print("\n".join(convergence.summary(rows)))
    print(f"wrote {args.out_dir}/convergence.csv and .md")


def _add_convergence_parser(commands) -> None:
    parser = commands.add_parser("convergence", help="measure the Lagrangian reference's convergence in dt on each scene")
    parser.add_argument("scenes", nargs="*", help="built-in names or scene files (default: every built-in scene, then T2-slack and T3-slack)")
    parser.add_argument("--halvings", type=_int_in(1, MAX_HALVINGS), default=3, help="runs at dt, dt/2, ..., dt/2^halvings (default 3)")
    parser.add_argument("--dt", type=_positive_float, default=None, help="coarsest step (default: the full benchmark's step for the scene)")
    parser.add_argument("--horizon", type=_positive_float, default=None,
                        help="simulated seconds (default: 1 s, 0.1 s on chain100 and the self-stressed or large scenes)")
    parser.add_argument("--frame-dt", type=_positive_float, default=1e-3, help="frames compared every this many seconds (default 1e-3)")
    parser.add_argument("--out-dir", default=None, help="output directory (default: ./lgnn-out; the committed tables are results/)")
    parser.add_argument("--quiet", action="store_true", help="no per-run lines")
    parser.set_defaults(run=_cmd_convergence)


def train_settings(args):
    """`(DataConfig, TrainConfig)` of `lgnn train`'s arguments: the full profile's
    recipe (`lgnn.bench.api.train_recipe`) with the options given. The data are the
    profile's for the scene (seed 0 whatever `--seed`, as the benchmark's); `--seed`
    seeds the parameters and shuffles; the checkpoint is written every
    `checkpoint_every` epochs, the recipe's."""
    from lgnn.bench.api import train_recipe

    recipe = train_recipe()
    data_config = dataclasses.replace(recipe.data_for(args.scene), n_trajectories=args.trajectories, varied_draws=args.varied_draws)
    config = dataclasses.replace(recipe.train, learning_rate=args.lr, batch_size=args.batch_size, epochs=args.epochs, minutes=args.minutes,
                                 patience=args.patience, seed=args.seed)
    return data_config, config


def _cmd_train(args) -> None:
    from pathlib import Path

    from lgnn.learn import data, models, train
    from lgnn.files import check_writable
    from lgnn.scene import get_scene

    check_writable(args.out)
    if Path(args.out).exists() and not (args.resume or args.overwrite):
        raise ConfigError(f"{args.out} exists: --resume to continue training it, --overwrite to start over, or choose another --out")
    data_config, config = train_settings(args)
    scene = get_scene(args.scene)
    name = models.load_spec(args.model).name if ":" in args.model else args.model
    model = models.ModelConfig.for_scene(name, scene, message_passing=args.message_passing, link_features=args.link_features)
    if args.resume and Path(args.out).exists():
        train.check_resumable(args.out, model, config)  # before minutes of data generation
    cache = args.cache_dir or data.default_cache_dir()
    dataset = data.load_or_generate(data_config, cache, progress=not args.quiet)
    state = train.train(model, config, dataset, data.draw_scenes(data_config), out=args.out, data_config=data_config, resume=args.resume,
                        progress=not args.quiet)
    draws = f" ({args.varied_draws} varied draws)" if args.varied_draws else ""
    print(f"{name} on {scene.name}{draws}: {state.epoch} epochs, best validation MSE {state.best_val:.4g} (epoch {state.best_epoch}); wrote {args.out} (data cached in {cache})")


def _cmd_rollout(args) -> None:
    from lgnn.engines.base import Integration, save_rollout
    from lgnn.learn import checkpoints, models, train
    from lgnn.scene import get_scene
    from lgnn.metrics import energy_drift

    config = _simulation_config(args)
    _trajectory_out(args.out)
    _import_model_code(args)
    model, params = checkpoints.load_model(args.model)  # inference: no optimiser
    scene = get_scene(args.scene)
    meta, _ = checkpoints.read(args.model)
    differences = train.physics_differences(meta, scene)
    if differences:
        print(f"lgnn: warning: {scene.name} differs from the scene {model.name} was trained on: {'; '.join(differences)}", file=sys.stderr)
    integration = _integration(args) or Integration()
    trajectory = save_rollout(lambda: models.rollout(model, params, scene, config, integration=integration, progress=not args.quiet),
                               args.out)
    print(f"{model.name} on {scene.name}: {len(trajectory.t)} frames over {config.duration:g} s; "
          f"true energy drift {energy_drift(scene, trajectory):.2e}; wrote {args.out}")


def _add_train_parser(commands) -> None:
    from lgnn.bench.api import train_recipe
    from lgnn.learn.models import model_names

    recipe = train_recipe()
    default = recipe.train
    parser = commands.add_parser("train", help="train a learned model on ground-truth data")
    parser.add_argument("--model", required=True, type=_model_reference, metavar="{" + ",".join(model_names()) + "}|MODULE:ATTR",
                        help=f"a built-in model ({', '.join(model_names())}) or your own ModelSpec as module:attribute "
                             "or file.py:attribute (docs/models.md)")
    parser.add_argument("--scene", default="chain4", help="training scene (built-in name or JSON file)")
    parser.add_argument("--epochs", type=_positive_int, default=default.epochs, help=f"epoch budget (default {default.epochs}, the full profile's and the paper's)")
    parser.add_argument("--minutes", type=_positive_float, default=None, help="optional wall-clock cap (checked every 10 epochs); the budget is --epochs")
    parser.add_argument("--patience", type=_positive_int, default=default.patience,
                        help=f"plateau rule: stop when the best validation MSE has not improved by {default.min_improvement:.0%}% "
                             f"in this many epochs (default {default.patience}, the full profile's)")
    # The full profile's recipe whatever the budget, as the benchmark's `[[add]]` entries
    # with a budget of their own (`grid.train_config`): a checkpoint comparable with its.
    parser.add_argument("--lr", type=_positive_float, default=default.learning_rate, help=f"peak learning rate (default {default.learning_rate:g}, the full profile's)")
    parser.add_argument("--batch-size", type=_positive_int, default=default.batch_size, help=f"default {default.batch_size}, the full profile's")
    parser.add_argument("--message-passing", type=_nonnegative_int, default=None, help="message-passing layers (default: the model's)")
    parser.add_argument("--trajectories", type=_positive_int, default=recipe.data.n_trajectories,
                        help=f"training trajectories (default {recipe.data.n_trajectories}, the full profile's and the paper's)")
    parser.add_argument("--link-features", action="store_true",
                        help="edges also carry each link's mass, inertia ratio and length (for models that read them; with --varied-draws)")
    parser.add_argument("--varied-draws", type=_nonnegative_int, default=0,
                        help="train on K chains as long as the scene (of its dimension), each link's length, mass and inertia drawn by the varied-chain rule, "
                             "the trajectories shared among them (the transfer track; default 0: the scene itself)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the initial parameters and shuffles (the data are the full profile's, as the benchmark's)")
    parser.add_argument("--cache-dir", default=None, help="training data cache (default: datasets/ in $LGNN_CACHE, else $XDG_CACHE_HOME/lgnn, else ~/.cache/lgnn)")
    parser.add_argument("--resume", action="store_true", help="continue from the checkpoint at --out")
    parser.add_argument("--overwrite", action="store_true", help="start over even if --out exists (default: refuse)")
    parser.add_argument("--out", required=True, help="checkpoint file (.npz), written every 10 epochs and at the end")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.set_defaults(run=_cmd_train)

    inspect = commands.add_parser("checkpoint", help="summarise a checkpoint: epochs, losses, training time")
    inspect.add_argument("path", help="checkpoint written by lgnn train or lgnn benchmark")
    _add_model_code_option(inspect)
    inspect.add_argument("--reference", help="another checkpoint: also print when this one reached its best validation loss")
    inspect.add_argument("--without-parameters", metavar="OUT",
                         help="also write the checkpoint to OUT without its parameters and optimiser state: its records and training "
                              "history stay readable (how the repository keeps large models)")
    inspect.add_argument("--for-inference", metavar="OUT",
                         help="also write the checkpoint to OUT with its best parameters only, without the latest ones and the "
                              "optimiser state: it rolls out, scores and times as this one, but cannot be resumed (how the repository "
                              "keeps finished models)")
    inspect.set_defaults(run=_cmd_checkpoint)

    rollout = commands.add_parser("rollout", help="roll a trained model out on a scene")
    rollout.add_argument("scene", help="built-in scene name or scene JSON file")
    rollout.add_argument("--model", required=True, help="checkpoint written by lgnn train")
    _add_model_code_option(rollout)
    _add_simulation_options(rollout)
    rollout.add_argument("--out", required=True, help="output .npz file (same layout as lgnn simulate)")
    rollout.add_argument("--quiet", action="store_true", help="no progress bar")
    rollout.set_defaults(run=_cmd_rollout)


def _cmd_evaluate(args) -> None:
    from lgnn.bench import evaluation
    from lgnn.engines.base import Integration
    from lgnn.files import DEFAULT_OUT, check_out_dir
    from lgnn.learn.checkpoints import load_model
    from lgnn.scene import get_scene

    config = _simulation_config(args)
    integration = _integration(args) or Integration()
    out = check_out_dir(args.out_dir or DEFAULT_OUT, "evaluate_summary.md")  # created once every scene has run
    _import_model_code(args)
    model, params = load_model(args.model)
    scored, trajectories = evaluation.evaluate_on_scenes(model, params, [get_scene(name) for name in args.scenes], config, args.initial_conditions,
                                                         args.seed, integration, progress=not args.quiet)
    kept = {out / f"{scene}_{engine}.npz": trajectory for (scene, engine), trajectory in trajectories.items()}
    # Written together once every scene has run: a failed command leaves nothing.
    out.mkdir(parents=True, exist_ok=True)
    for path, trajectory in kept.items():
        trajectory.save(path)
    written = list(kept)
    command = "lgnn " + " ".join(args.argv)
    header = (command, f"model {model.name} ({args.model}); {integration.integrator} dt {config.dt:g}, frames every {config.frame_dt:g} s, "
              f"{config.duration:g} s; initial conditions: " + ("the scene's own" if args.initial_conditions == 1 else
              f"{args.initial_conditions} sampled (seed {args.seed})"))
    written = evaluation.write_outputs(scored, out, "evaluate", f"Evaluation of {args.model}", header) + written
    print(evaluation.format_summary(evaluation.summary_rows(scored)))
    print(f"wrote {', '.join(map(str, written))} (trajectories: initial condition 0)")


def _cmd_compare(args) -> None:
    from pathlib import Path

    from lgnn.bench import evaluation
    from lgnn.files import check_out_dir

    if args.out_dir:
        check_out_dir(args.out_dir, "compare_summary.md")  # created once the files are scored
    scored, notes = evaluation.compare_trajectories([args.reference, args.other])
    for note in notes:
        print(f"note: {note}")
    print(evaluation.format_summary(evaluation.summary_rows([scored])))
    if args.out_dir:
        Path(args.out_dir).mkdir(parents=True, exist_ok=True)
        written = evaluation.write_outputs([scored], args.out_dir, "compare", f"{args.other} against {args.reference}",
                                           ["lgnn " + " ".join(args.argv)], notes)
        print(f"wrote {', '.join(map(str, written))}")


def _cmd_animate(args) -> None:
    from lgnn.bench import viz

    frames = viz.animate(args.files, args.out, fps=args.fps, speed=args.speed)
    print(f"wrote {args.out} ({frames} frames at {args.fps:g} per second)")


def _cmd_plot(args) -> None:
    from lgnn.bench import viz

    viz.plot(args.files, args.out)
    print(f"wrote {args.out}")


def _add_evaluation_parsers(commands) -> None:
    evaluate = commands.add_parser("evaluate", help="score a checkpoint against the Lagrangian engine and MuJoCo on any scenes")
    evaluate.add_argument("scenes", nargs="+", metavar="SCENE", help="built-in scene names or scene JSON files")
    evaluate.add_argument("--model", required=True, help="checkpoint written by lgnn train or lgnn benchmark")
    _add_model_code_option(evaluate)
    evaluate.add_argument("--initial-conditions", type=_int_in(1, MAX_INITIAL_CONDITIONS), default=1,
                          help="1: the scene's own state (default); N: N sampled ones (the paper's chain sampler, else projected perturbations)")
    evaluate.add_argument("--seed", type=int, default=0, help="seed of the sampled initial conditions")
    _add_simulation_options(evaluate)
    evaluate.add_argument("--out-dir", default=None, help="writes evaluate_frames.csv, evaluate_summary.csv/.md and SCENE_{model,lagrangian,mujoco}.npz "
                          "here, created if absent (default: ./lgnn-out)")
    evaluate.add_argument("--quiet", action="store_true", help="no progress bars")
    evaluate.set_defaults(run=_cmd_evaluate)

    compare = commands.add_parser("compare", help="the benchmark's metrics of one trajectory file against another")
    compare.add_argument("reference", help="reference trajectory .npz (lgnn simulate / rollout / evaluate)")
    compare.add_argument("other", help="trajectory .npz scored against the reference")
    compare.add_argument("--out-dir", help="also write compare_frames.csv and compare_summary.csv/.md here (created if absent)")
    compare.set_defaults(run=_cmd_compare)

    animate = commands.add_parser("animate", help="animate trajectory files over each other (the first underneath)")
    animate.add_argument("files", nargs="+", metavar="FILE", help="trajectory .npz files of one scene, the reference (ground truth) first")
    animate.add_argument("--out", required=True, help="output .gif (Pillow) or .mp4 (needs ffmpeg)")
    animate.add_argument("--fps", type=_float_in(*FPS_RANGE), default=30.0, help="animation frames per second (default 30)")
    animate.add_argument("--speed", type=_float_in(*SPEED_RANGE), default=1.0, help="simulated seconds per second of animation (default 1)")
    animate.set_defaults(run=_cmd_animate)

    plot = commands.add_parser("plot", help="per-node error against the first file and energy, against time")
    plot.add_argument("files", nargs="+", metavar="FILE", help="trajectory .npz files of one scene, the reference first")
    plot.add_argument("--out", required=True, help="output figure (.png, .pdf, .svg)")
    plot.set_defaults(run=_cmd_plot)


def _cmd_checkpoint(args) -> None:
    from pathlib import Path

    from lgnn.files import check_writable
    from lgnn.learn import checkpoints, train

    _import_model_code(args)
    copies = {"--without-parameters": args.without_parameters, "--for-inference": args.for_inference}
    if all(copies.values()):
        raise ConfigError("give one of --without-parameters and --for-inference")
    for option, target in copies.items():
        if target:
            check_writable(target)
            if Path(target).resolve() == Path(args.path).resolve():
                raise ConfigError(f"{option} must name another file than the checkpoint")
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
    if args.without_parameters:
        checkpoints.without_parameters(args.path, args.without_parameters)
        print(f"wrote {args.without_parameters} (without parameters)")
    if args.for_inference:
        checkpoints.for_inference(args.path, args.for_inference)
        print(f"wrote {args.for_inference} (for inference)")


def _cmd_benchmark(args) -> None:
    import json
    from pathlib import Path

    from lgnn.bench import grid
    from lgnn.bench.run import STAGES, run
    from lgnn.bench.store import default_out
    from lgnn.files import check_out_dir

    if sum(map(bool, (args.full, args.profile, args.config))) > 1:
        raise ConfigError("give one of --config, --profile and --full")
    if args.out_dir:
        check_out_dir(args.out_dir)
    overrides = list(args.set or ()) + ([f"evaluate.chunk={args.chunk}"] if args.chunk is not None else [])
    # --chunk is not an evaluation setting (records stay valid): only how many rollouts share a call.
    # --with-results as an absolute path: a config's own `base` is relative to the config, this one to here.
    overrides += [f"base={json.dumps(str(Path(args.with_results).resolve()))}"] if args.with_results else []
    # An --add-model file likewise: relative to here, not to a config's directory.
    added = tuple(f"{Path(code).resolve()}:{name}" if code.endswith(".py") else model
                  for model in args.add_model or () for code, _, name in (model.rpartition(":"),))
    profile = grid.load_profile(args.config or args.profile or ("full" if args.full else "quick"), overrides, added)
    # Predictions files relative to here; the child processes of --workers never score them (the parent does).
    profile = dataclasses.replace(profile, predictions=(*profile.predictions, *(str(Path(p).resolve()) for p in args.add_predictions or ())))
    stages = None if args.stage is None else tuple(STAGES) if args.stage == "all" else (args.stage,)
    print(f"lgnn benchmark ({profile.name} profile): writing into {Path(args.out_dir) if args.out_dir else default_out(profile)}/", flush=True)
    # What selects this profile, for the child processes of --workers.
    profile_argv = ((["--config", args.config] if args.config else []) + (["--profile", args.profile] if args.profile else [])
                    + (["--full"] if args.full else []) + [arg for value in args.set or () for arg in ("--set", value)]
                    + (["--chunk", str(args.chunk)] if args.chunk is not None else [])
                    + [arg for value in args.add_model or () for arg in ("--add-model", value)]
                    + (["--with-results", args.with_results] if args.with_results else []))
    out = run(profile, Path(args.out_dir) if args.out_dir else None, stages, args.job, args.scene, progress=not args.quiet,
              workers=args.workers, profile_argv=profile_argv, command="lgnn " + " ".join(args.argv), executor=args.executor, address=args.address)
    if "report" in (stages or profile.stages or STAGES):
        print((out / "README.md").read_text())
    print(f"wrote {out}/")


def _add_profile_options(parser, full_help: str, set_help: str) -> None:
    """The options that choose a benchmark profile: --full, --profile, --config, --set."""
    from lgnn.bench import grid

    parser.add_argument("--full", action="store_true", help=full_help)
    parser.add_argument("--profile", choices=grid.PROFILE_NAMES, help="a shipped profile: quick (default) or full (same as --full)")
    parser.add_argument("--config", help="a benchmark config file (TOML; docs/benchmark.md, 'Configs')")
    parser.add_argument("--set", action="append", metavar="KEY=VALUE", help=set_help)


def _add_benchmark_parser(commands) -> None:
    from lgnn.bench.run import EXECUTORS, STAGES

    parser = commands.add_parser("benchmark", help="train and evaluate every model on every scene; write results/")
    _add_profile_options(parser, "the full profile (default: the quick one, minutes on a laptop)",
                         "override a config value, e.g. training.train.epochs=50 or seeds=[0,1,2]; add.KEY=VALUE sets KEY of every "
                         "added model's grid entry, e.g. add.epochs=20, add.seeds=[0], add.eval_scenes=[chain4,chain8] (repeatable)")
    parser.add_argument("--add-model", action="append", metavar="FILE.py:ATTR",
                        help="add a model to the grid (its spec as file.py:attribute or module:attribute, or a registered name), trained "
                             "on chain4 and evaluated on the planar transfer scenes as the built-in models are (repeatable)")
    parser.add_argument("--add-predictions", action="append", metavar="FILE.npz",
                        help="score predictions made outside lgnn from the exported initial conditions (lgnn dataset export) against the "
                             "same ground truth, as a row 'MODEL (external)' (file format: docs/formats.md, 'Predictions'; repeatable)")
    parser.add_argument("--with-results", metavar="DIR",
                        help="rank beside the results in DIR (e.g. the committed results/), read in place, never copied or written: "
                             "its checkpoints are not retrained, its records are reused where their settings match; runs the train, "
                             "evaluate and report stages into --out-dir (default ./lgnn-out/PROFILE/). One command from a model file "
                             "to its leaderboard row: lgnn benchmark --full --add-model my_model.py:SPEC --with-results results")
    parser.add_argument("--stage", default=None, choices=("all", *STAGES),
                        help="run one stage (default: the config's stages, else all, resuming finished work)")
    parser.add_argument("--job", action="append", help="only this training job, e.g. lgnn-chain4-s0 (repeatable)")
    parser.add_argument("--scene", action="append", help="only this evaluation scene (repeatable)")
    parser.add_argument("--out-dir", default=None, help="output directory (default: results/ for --full, the committed run it resumes and updates; ./lgnn-out/quick/ otherwise)")
    parser.add_argument("--chunk", type=_positive_int, default=None, help="initial conditions per compiled rollout call (default 25; a GPU wants 100)")
    parser.add_argument("--workers", type=_positive_int, default=1,
                        help="train each model group and evaluate each (scene, model) in this many processes at once (a GPU or a "
                             "many-core CPU; logs under OUT/benchmark/logs/)")
    parser.add_argument("--executor", choices=EXECUTORS, default="local",
                        help="where training groups and evaluation parts run: local (child processes of this machine, with --workers > 1) "
                             "or ray (tasks of a Ray cluster, --workers at once; needs pip install 'lgnn[ray]'; docs/cluster.md)")
    parser.add_argument("--address", default=None,
                        help="with --executor ray: the Ray cluster, auto (this node's) or HOST:PORT (default: start Ray on this machine)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.set_defaults(run=_cmd_benchmark)


def _cmd_leaderboard(args) -> None:
    import json
    from pathlib import Path

    from lgnn.bench import grid, report
    from lgnn.bench.store import default_out, layout

    if sum(map(bool, (args.full, args.profile, args.config))) > 1:
        raise ConfigError("give one of --config, --profile and --full")
    overrides = list(args.set or ()) + ([f"base={json.dumps(str(Path(args.with_results).resolve()))}"] if args.with_results else [])
    profile = grid.load_profile(args.config or args.profile or ("full" if args.full else "quick"), overrides)
    out = Path(args.out_dir) if args.out_dir else default_out(profile)
    if not out.is_dir():
        raise ConfigError(f"results folder {out} does not exist (lgnn benchmark writes it)")
    layout(profile, out)
    path = report.write_leaderboard(profile, out, "lgnn " + " ".join(args.argv))
    print(f"wrote {path}")


def _add_leaderboard_parser(commands) -> None:
    parser = commands.add_parser("leaderboard", help="write LEADERBOARD.md of a results folder from its records (ranks, parameters, training time)")
    _add_profile_options(parser, "the full profile's results (default folder: results/)", "override a config value, as lgnn benchmark's (repeatable)")
    parser.add_argument("--with-results", metavar="DIR", help="also read the records of DIR in place, as lgnn benchmark --with-results")
    parser.add_argument("--out-dir", default=None, help="the results folder, read and written into (default: as lgnn benchmark's)")
    parser.set_defaults(run=_cmd_leaderboard)


def _cmd_dataset_export(args) -> None:
    from lgnn.bench import grid
    from lgnn.bench.dataset import export_scene
    from lgnn.files import check_writable
    from lgnn.learn import data

    from lgnn.learn.export import check_path

    check_path(check_writable(args.out))
    profile = grid.load_profile(args.config or args.profile, args.set or ())
    shapes = export_scene(profile, args.scene, args.out, args.cache_dir or data.default_cache_dir(), progress=not args.quiet)
    print(f"{args.scene}: {shapes['q'][0]} states ({shapes['train'][0]} train, {shapes['val'][0]} validation), "
          f"{shapes['eval_q0'][0]} evaluation initial conditions ({profile.name} profile); wrote {args.out}")


def _add_dataset_parser(commands) -> None:
    from lgnn.bench import grid

    parser = commands.add_parser("dataset", help="training and evaluation data for other frameworks")
    sub = parser.add_subparsers(dest="dataset_command", required=True, metavar="SUBCOMMAND")
    export = sub.add_parser("export", help="write a scene's training data and evaluation initial conditions (.npz or .h5; docs/formats.md)")
    export.add_argument("--scene", required=True, help="built-in scene name or scene JSON file")
    export.add_argument("--out", required=True, help="output file: .npz, or .h5 (needs h5py: pip install 'lgnn[hdf5]')")
    export.add_argument("--profile", choices=grid.PROFILE_NAMES, default="full", help="data and evaluation settings (default: full, the paper's)")
    export.add_argument("--config", help="a benchmark config file instead of --profile")
    export.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a setting, e.g. training.data.n_trajectories=10")
    export.add_argument("--cache-dir", default=None, help="training data cache (default: as lgnn train's)")
    export.add_argument("--quiet", action="store_true", help="no progress bar")
    export.set_defaults(run=_cmd_dataset_export)


def _cmd_stability(args) -> None:
    from lgnn.bench import stability
    from lgnn.files import check_writable, out_dir

    out = check_writable(args.out or out_dir(None) / "stability.md")
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
    from lgnn.bench.stability import StabilitySettings, cases

    default = StabilitySettings()
    parser = commands.add_parser("stability", help="run the hard cases (long, large, near-singular, learned) and write a report")
    parser.add_argument("--out", default=None, help="markdown report; the CSV goes beside it (default: ./lgnn-out/stability.md; the committed one is results/stability.md)")
    for name in ("long_horizon", "large_step_horizon", "chain1000_horizon", "model_horizon", "singular_horizon"):
        parser.add_argument(f"--{name.replace('_', '-')}", type=_positive_float, default=getattr(default, name),
                            help=f"simulated seconds (default {getattr(default, name):g})")
    parser.add_argument("--cost-sizes", type=_positive_int, nargs="*", default=list(default.cost_sizes), help="chain sizes timed per step (none: skip)")
    names = list(dict.fromkeys(case.name for case in cases()))
    parser.add_argument("--case", action="append", choices=names, metavar="CASE", help=f"only this case (repeatable): {', '.join(names)}")
    parser.add_argument("--quiet", action="store_true", help="no per-case lines")
    parser.set_defaults(run=_cmd_stability)


def _cmd_gpu_truth(args) -> None:
    from lgnn.bench import gpu_truth
    from lgnn.files import check_writable
    from lgnn.scene import get_scene

    settings = gpu_truth.GpuTruthSettings(tuple(args.scenes), tuple(args.batches), tuple(args.engines), args.steps, args.dt,
                                          args.repeats, args.form, args.seed)
    check_writable(f"{args.out}/gpu_truth_{settings.scenes[0]}{args.suffix}.md")
    scenes = [get_scene(name) for name in settings.scenes]  # every name checked before any run
    log = (lambda line: None) if args.quiet else (lambda line: print(line, flush=True))
    for scene in scenes:
        if not args.fresh and gpu_truth.measured_before(args.out, scene.name + args.suffix, settings):
            print(f"kept {args.out}/gpu_truth_{scene.name}{args.suffix}.md: measured with these settings on this machine at this "
                  "commit (--fresh measures it again)")
            continue
        rows = gpu_truth.measure(scene, settings, log=log)
        print(f"wrote {gpu_truth.write(rows, args.out, scene.name + args.suffix, 'lgnn ' + ' '.join(args.argv), settings)} and .csv")


def _add_gpu_truth_parser(commands) -> None:
    from lgnn.bench.gpu_truth import GpuTruthSettings
    from lgnn.engines.mjcf import FORMS

    default = GpuTruthSettings()
    parser = commands.add_parser("gpu-truth", help="time every ground-truth engine on batches of one scene and its error against float64")
    parser.add_argument("--scenes", nargs="+", default=list(default.scenes), help="built-in names or scene files (a table each)")
    parser.add_argument("--batches", type=_positive_int, nargs="+", default=list(default.batches), help="batch sizes")
    parser.add_argument("--engines", nargs="+", default=list(default.engines),
                        help="name:dtype besides the float64 Lagrangian reference (default: %(default)s)")
    parser.add_argument("--steps", type=_positive_int, default=default.steps, help="RK4 steps; the error is after the last")
    parser.add_argument("--dt", type=_positive_float, default=default.dt, help="integration step (s)")
    parser.add_argument("--repeats", type=_positive_int, default=default.repeats, help="timed runs per engine and batch (the spread)")
    parser.add_argument("--form", choices=FORMS, default=default.form, help=f"MJCF form of the MuJoCo engines (default {default.form})")
    parser.add_argument("--seed", type=int, default=default.seed, help="initial states' seed")
    parser.add_argument("--out", required=True, help="output directory: gpu_truth_<scene><suffix>.csv and .md")
    parser.add_argument("--suffix", type=_file_name_part, default="", help="appended to the file names (e.g. _mjx for a call of its own)")
    parser.add_argument("--fresh", action="store_true",
                        help="measure every scene, also one whose table in --out this machine made with these settings at this commit")
    parser.add_argument("--quiet", action="store_true", help="no per-run lines")
    parser.set_defaults(run=_cmd_gpu_truth)


class _VersionAction(argparse.Action):
    """`--version`: the versions every result records (`lgnn.provenance`), read only
    when asked (package metadata takes tens of milliseconds)."""

    def __init__(self, option_strings, dest, **kwargs):
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        from lgnn import provenance

        print(f"{provenance.versions()}; commit {provenance.commit()}")
        parser.exit()


def _of_engines(field: str) -> list[str]:
    """Every value of the registered engines' `field` (`EngineEntry.dtypes`, `.forms`), in order."""
    from lgnn.engines import ENGINES

    return list(dict.fromkeys(value for entry in ENGINES.values() for value in getattr(entry, field)))


def build_parser() -> argparse.ArgumentParser:
    from lgnn.engines import ENGINES

    parser = _Parser(prog="lgnn", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action=_VersionAction, help="print lgnn's version, commit and its dependencies' versions, and exit")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    scenes = commands.add_parser("scenes", help="list the built-in scenes, their tags, initial states and whether the benchmark evaluates them")
    scenes.set_defaults(run=_cmd_scenes)

    scene = commands.add_parser("scene", help="scene utilities")
    scene_commands = scene.add_subparsers(dest="scene_command", required=True, metavar="SUBCOMMAND")
    export = scene_commands.add_parser("export", help="write a built-in scene as JSON")
    export.add_argument("name")
    export.add_argument("--out", help="output file (default: standard output)")
    export.set_defaults(run=_cmd_scene_export)

    simulate = commands.add_parser("simulate", help="simulate a scene with a ground-truth engine")
    simulate.add_argument("scene", help="built-in scene name or scene JSON file")
    simulate.add_argument("--engine", default="lagrangian", choices=list(ENGINES), help="ground-truth engine (default: lagrangian)")
    simulate.add_argument("--dtype", choices=_of_engines("dtypes"), default=None,
                          help="precision of the engine (default: its own, float64 but MuJoCo Warp's float32); one it lacks is refused")
    simulate.add_argument("--form", choices=_of_engines("forms"), help="MuJoCo engines: MJCF form (default auto: the engine's choice)")
    _add_simulation_options(simulate)
    simulate.add_argument("--out", required=True, help="output .npz file")
    simulate.add_argument("--quiet", action="store_true", help="no progress bar")
    simulate.set_defaults(run=_cmd_simulate)
    _add_mujoco_commands(commands)
    _add_train_parser(commands)
    _add_evaluation_parsers(commands)
    _add_benchmark_parser(commands)
    _add_leaderboard_parser(commands)
    _add_dataset_parser(commands)
    _add_stability_parser(commands)
    _add_convergence_parser(commands)
    _add_gpu_truth_parser(commands)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command `argv` (default: the process's arguments); its exit status.

    Ctrl-C at any moment, while JAX loads or compiles included, is one line and exit
    130 (`lgnn.interrupts.run_interruptibly`: one during an XLA compilation is held
    until that compilation ends; a second one leaves at once).
    """
    return run_interruptibly(lambda interrupts_after_loading: _run(argv, interrupts_after_loading), _LOADING.take())


def _run(argv: list[str] | None, interrupts_after_loading) -> int:
    from lgnn.runtime import accept_interrupts_if_child, configure, enable_compilation_cache

    with interrupts_after_loading():
        configure()  # first: before numpy and JAX load (thread counts, XLA flags, float64)
    if argv is None:
        # The process's own command (not a caller's `main([...])`, e.g. a test): compiled
        # programs kept on disk (`lgnn.runtime.compilation_cache_dir`).
        enable_compilation_cache()
    accept_interrupts_if_child()
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else [str(a) for a in argv]
    args = parser.parse_args(argv)
    args.argv = argv  # reports name the exact command
    try:
        args.run(args)
    except SimulationError as err:
        print(f"lgnn: error: {one_line(str(err))}", file=sys.stderr)
        return EXIT_DIVERGED
    except LgnnError as err:
        print(f"lgnn: error: {one_line(str(err))}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except BrokenPipeError:
        # The reader went away (`lgnn scenes | head`): stop quietly, as Unix tools do.
        # stdout is pointed at devnull so the interpreter's final flush cannot fail again.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    return 0


if __name__ == "__main__":
    sys.exit(main())
