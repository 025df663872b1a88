"""The commands of learned models: `lgnn train`, `checkpoint`, `rollout`, `evaluate`,
`compare`, `animate` and `plot` (`PARSERS`); each parses its options and calls
the library (`lgnn.learn`, `lgnn.bench.evaluation`, `lgnn.bench.viz`).
"""

from __future__ import annotations

import dataclasses
import sys

from lgnn.cli.options import (add_model_code_option, add_simulation_options, float_in, import_model_code, int_in, integration_of, model_reference,
                              nonnegative_int, positive_float, positive_int, simulation_config, trajectory_out)
from lgnn import metrics
from lgnn.errors import ConfigError

# `lgnn animate`: frames per second and simulated seconds per second of animation; out
# of these, a frame lasts longer than a GIF can say or the stride overflows.
FPS_RANGE = (0.1, 1000.0)
SPEED_RANGE = (1e-6, 1e6)
# `lgnn evaluate --initial-conditions`: the paper's 100 a thousand times over; more
# would be refused only after sampling them all (their rollouts are kept in memory).
MAX_INITIAL_CONDITIONS = 100_000


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
    from lgnn.learn import checkpoints, models
    from lgnn.scene import get_scene
    from lgnn.metrics import energy_drift

    config = simulation_config(args)
    trajectory_out(args.out)
    import_model_code(args)
    model, params = checkpoints.load_model(args.model)  # inference: no optimiser
    scene = get_scene(args.scene)
    meta, _ = checkpoints.read(args.model)
    differences = checkpoints.physics_differences(meta, scene)
    if differences:
        print(f"lgnn: warning: {scene.name} differs from the scene {model.name} was trained on: {'; '.join(differences)}", file=sys.stderr)
    integration = integration_of(args) or Integration()
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
    parser.add_argument("--model", required=True, type=model_reference, metavar="{" + ",".join(model_names()) + "}|MODULE:ATTR",
                        help=f"a built-in model ({', '.join(model_names())}) or your own ModelSpec as module:attribute "
                             "or file.py:attribute (docs/models.md)")
    parser.add_argument("--scene", default="chain4", help="training scene (built-in name or JSON file)")
    parser.add_argument("--epochs", type=positive_int, default=default.epochs, help=f"epoch budget (default {default.epochs}, the full profile's and the paper's)")
    parser.add_argument("--minutes", type=positive_float, default=None, help="optional wall-clock cap (checked every 10 epochs); the budget is --epochs")
    parser.add_argument("--patience", type=positive_int, default=default.patience,
                        help=f"plateau rule: stop when the best validation MSE has not improved by {default.min_improvement:.0%}% "
                             f"in this many epochs (default {default.patience}, the full profile's)")
    # The full profile's recipe whatever the budget, as the benchmark's `[[add]]` entries
    # with a budget of their own (`profiles.train_config`): a checkpoint comparable with its.
    parser.add_argument("--lr", type=positive_float, default=default.learning_rate, help=f"peak learning rate (default {default.learning_rate:g}, the full profile's)")
    parser.add_argument("--batch-size", type=positive_int, default=default.batch_size, help=f"default {default.batch_size}, the full profile's")
    parser.add_argument("--message-passing", type=nonnegative_int, default=None, help="message-passing layers (default: the model's)")
    parser.add_argument("--trajectories", type=positive_int, default=recipe.data.n_trajectories,
                        help=f"training trajectories (default {recipe.data.n_trajectories}, the full profile's and the paper's)")
    parser.add_argument("--link-features", action="store_true",
                        help="edges also carry each link's mass, inertia ratio and length (for models that read them; with --varied-draws)")
    parser.add_argument("--varied-draws", type=nonnegative_int, default=0,
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
    add_model_code_option(inspect)
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
    add_model_code_option(rollout)
    add_simulation_options(rollout)
    rollout.add_argument("--out", required=True, help="output .npz file (same layout as lgnn simulate)")
    rollout.add_argument("--quiet", action="store_true", help="no progress bar")
    rollout.set_defaults(run=_cmd_rollout)


def _cmd_evaluate(args) -> None:
    from lgnn.bench import evaluation
    from lgnn.engines.base import Integration
    from lgnn.files import DEFAULT_OUT, check_out_dir
    from lgnn.learn.checkpoints import load_model
    from lgnn.scene import get_scene

    config = simulation_config(args)
    integration = integration_of(args) or Integration()
    out = check_out_dir(args.out_dir or DEFAULT_OUT, "evaluate_summary.md")  # created once every scene has run
    import_model_code(args)
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

    viz.plot(args.files, args.out, args.metric)
    print(f"wrote {args.out}")


def _add_evaluation_parsers(commands) -> None:
    evaluate = commands.add_parser("evaluate", help="score a checkpoint against the Lagrangian engine and MuJoCo on any scenes")
    evaluate.add_argument("scenes", nargs="+", metavar="SCENE", help="built-in scene names or scene JSON files")
    evaluate.add_argument("--model", required=True, help="checkpoint written by lgnn train or lgnn benchmark")
    add_model_code_option(evaluate)
    evaluate.add_argument("--initial-conditions", type=int_in(1, MAX_INITIAL_CONDITIONS), default=1,
                          help="1: the scene's own state (default); N: N sampled ones (the paper's chain sampler, else projected perturbations)")
    evaluate.add_argument("--seed", type=int, default=0, help="seed of the sampled initial conditions")
    add_simulation_options(evaluate)
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
    animate.add_argument("--fps", type=float_in(*FPS_RANGE), default=30.0, help="animation frames per second (default 30)")
    animate.add_argument("--speed", type=float_in(*SPEED_RANGE), default=1.0, help="simulated seconds per second of animation (default 1)")
    animate.set_defaults(run=_cmd_animate)

    plot = commands.add_parser("plot", help="an error against the first file (default per-node RMS position) and energy, against time")
    plot.add_argument("files", nargs="+", metavar="FILE", help="trajectory .npz files of one scene, the reference first")
    plot.add_argument("--out", required=True, help="output figure (.png, .pdf, .svg)")
    plot.add_argument("--metric", choices=tuple(metrics.METRICS), default="node_rms_error",
                      help="the error drawn (a registered metric; default node_rms_error, in lengths)")
    plot.set_defaults(run=_cmd_plot)


def _cmd_checkpoint(args) -> None:
    from pathlib import Path

    from lgnn.files import check_writable
    from lgnn.learn import checkpoints, train

    import_model_code(args)
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


# `lgnn train`, `checkpoint`, `rollout`, `evaluate`, `compare`, `animate` and `plot`:
# their parsers' builders, in `lgnn --help`'s order.
PARSERS = (_add_train_parser, _add_evaluation_parsers)
