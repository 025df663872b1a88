"""The commands of the studies beside the benchmark: `lgnn stability`, `convergence`
and `gpu-truth` (`PARSERS`), each a call of its `lgnn.bench` module.
"""

from __future__ import annotations

import dataclasses

from lgnn.cli.options import file_name_part, int_in, positive_float, positive_int
from lgnn.errors import ConfigError

# `lgnn convergence --halvings`: dt / 2^20 is a millionth of the coarsest step, already
# more steps than a run finishes in a day.
MAX_HALVINGS = 20


def _cmd_convergence(args) -> None:
    from lgnn.bench import convergence
    from lgnn.bench.profiles import get_profile
    from lgnn.files import check_writable, out_dir
    from lgnn.provenance import environment
    from lgnn.scene import get_scene, scene_names

    args.out_dir = out_dir(args.out_dir)
    check_writable(f"{args.out_dir}/{convergence.TABLE_MD}")
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
    convergence.write_report(rows, f"{args.out_dir}/{convergence.TABLE_CSV}", f"{args.out_dir}/{convergence.TABLE_MD}", command)
    print("\n".join(convergence.summary(rows)))
    print(f"wrote {args.out_dir}/{convergence.TABLE_CSV} and .md")


def _add_convergence_parser(commands) -> None:
    parser = commands.add_parser("convergence", help="measure the Lagrangian reference's convergence in dt on each scene")
    parser.add_argument("scenes", nargs="*", help="built-in names or scene files (default: every built-in scene, then T2-slack and T3-slack)")
    parser.add_argument("--halvings", type=int_in(1, MAX_HALVINGS), default=3, help="runs at dt, dt/2, ..., dt/2^halvings (default 3)")
    parser.add_argument("--dt", type=positive_float, default=None, help="coarsest step (default: the full benchmark's step for the scene)")
    parser.add_argument("--horizon", type=positive_float, default=None,
                        help="simulated seconds (default: 1 s, 0.1 s on chain100 and the self-stressed or large scenes)")
    parser.add_argument("--frame-dt", type=positive_float, default=1e-3, help="frames compared every this many seconds (default 1e-3)")
    parser.add_argument("--out-dir", default=None, help="output directory (default: ./lgnn-out; the committed tables are results/)")
    parser.add_argument("--quiet", action="store_true", help="no per-run lines")
    parser.set_defaults(run=_cmd_convergence)


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
        parser.add_argument(f"--{name.replace('_', '-')}", type=positive_float, default=getattr(default, name),
                            help=f"simulated seconds (default {getattr(default, name):g})")
    parser.add_argument("--cost-sizes", type=positive_int, nargs="*", default=list(default.cost_sizes), help="chain sizes timed per step (none: skip)")
    names = list(dict.fromkeys(case.name for case in cases()))
    parser.add_argument("--case", action="append", choices=names, metavar="CASE", help=f"only this case (repeatable): {', '.join(names)}")
    parser.add_argument("--quiet", action="store_true", help="no per-case lines")
    parser.set_defaults(run=_cmd_stability)


def _cmd_gpu_truth(args) -> None:
    from pathlib import Path

    from lgnn.bench import gpu_truth
    from lgnn.files import check_out_dir, check_writable
    from lgnn.scene import get_scene

    check_out_dir(args.out)
    settings = gpu_truth.GpuTruthSettings(tuple(args.scenes), tuple(args.batches), tuple(args.engines), args.steps, args.dt,
                                          args.repeats, args.form, args.seed)
    scenes = [get_scene(name) for name in settings.scenes]  # every name checked before any run
    Path(args.out).mkdir(parents=True, exist_ok=True)  # an output folder is created (docs/cli.md)
    check_writable(f"{args.out}/gpu_truth_{settings.scenes[0]}{args.suffix}.md")
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
    parser.add_argument("--batches", type=positive_int, nargs="+", default=list(default.batches), help="batch sizes")
    parser.add_argument("--engines", nargs="+", default=list(default.engines),
                        help="name:dtype besides the float64 Lagrangian reference (default: %(default)s)")
    parser.add_argument("--steps", type=positive_int, default=default.steps, help="RK4 steps; the error is after the last")
    parser.add_argument("--dt", type=positive_float, default=default.dt, help="integration step (s)")
    parser.add_argument("--repeats", type=positive_int, default=default.repeats, help="timed runs per engine and batch (the spread)")
    parser.add_argument("--form", choices=FORMS, default=default.form, help=f"MJCF form of the MuJoCo engines (default {default.form})")
    parser.add_argument("--seed", type=int, default=default.seed, help="initial states' seed")
    parser.add_argument("--out", required=True, help="output directory: gpu_truth_<scene><suffix>.csv and .md")
    parser.add_argument("--suffix", type=file_name_part, default="", help="appended to the file names (e.g. _mjx for a call of its own)")
    parser.add_argument("--fresh", action="store_true",
                        help="measure every scene, also one whose table in --out this machine made with these settings at this commit")
    parser.add_argument("--quiet", action="store_true", help="no per-run lines")
    parser.set_defaults(run=_cmd_gpu_truth)


# `lgnn stability`, `convergence` and `gpu-truth`: their parsers' builders, in `lgnn
# --help`'s order.
PARSERS = (_add_stability_parser, _add_convergence_parser, _add_gpu_truth_parser)
