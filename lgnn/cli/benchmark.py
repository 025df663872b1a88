"""The commands of the benchmark: `lgnn benchmark`, `leaderboard`, `handoff`, `dataset
export` and `papers` (`PARSERS`); each parses its options and calls the library
(`lgnn.bench.run`, `lgnn.bench.grid`, `lgnn.bench.report`, `lgnn.bench.dataset`,
`lgnn.bench.handoff`, `lgnn.bench.papers`).
"""

from __future__ import annotations

from lgnn.cli.options import EXIT_CHECK_FAILED, add_profile_options, one_line, positive_float, positive_int, profile_source
from lgnn.errors import ConfigError, LgnnError


def _cmd_benchmark(args) -> None:
    from pathlib import Path

    from lgnn.bench.api import benchmark_profile
    from lgnn.bench.run import STAGES, run
    from lgnn.bench.store import default_out
    from lgnn.files import check_out_dir

    source = profile_source(args)
    if args.out_dir:
        check_out_dir(args.out_dir)
    # --chunk is not an evaluation setting (records stay valid): only how many rollouts share a call.
    # The child processes of --workers never score the predictions (the parent does).
    profile = benchmark_profile(source, settings=[*(args.set or ()), *([f"evaluate.chunk={args.chunk}"] if args.chunk is not None else [])],
                                add_models=args.add_model or (), predictions=args.add_predictions or (), with_results=args.with_results)
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


def _add_benchmark_parser(commands) -> None:
    from lgnn.bench.run import EXECUTORS, STAGES

    parser = commands.add_parser("benchmark", help="train and evaluate every model on every scene; write results/")
    add_profile_options(parser, "the full profile (default: the quick one, minutes on a laptop)",
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
    parser.add_argument("--chunk", type=positive_int, default=None, help="initial conditions per compiled rollout call (default 25; a GPU wants 100)")
    parser.add_argument("--workers", type=positive_int, default=1,
                        help="train each model group and evaluate each (scene, model) in this many processes at once (a GPU or a "
                             "many-core CPU; logs under OUT/benchmark/logs/)")
    parser.add_argument("--executor", choices=EXECUTORS, default="local",
                        help="where training groups and evaluation parts run: local (child processes of this machine, with --workers > 1) "
                             "or ray (tasks of a Ray cluster, --workers at once; needs pip install 'lgnn[ray]'; docs/cluster.md)")
    parser.add_argument("--address", default=None,
                        help="with --executor ray: the Ray cluster, auto (this node's) or HOST:PORT (default: start Ray on this machine)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.set_defaults(run=_cmd_benchmark)


def _cmd_leaderboard(args) -> int | None:
    from pathlib import Path

    from lgnn.bench.api import benchmark_profile
    from lgnn.bench.report import leaderboard
    from lgnn.bench.store import default_out, layout

    if args.action == "verify":
        return _verify(args)
    if args.folder is not None:
        raise ConfigError(f"lgnn leaderboard: unexpected {args.folder!r} (a folder is given as --out-dir, or to lgnn leaderboard verify)")
    for option in ("initial_conditions", "scenes", "predictions", "row"):
        if getattr(args, option) is not None:
            raise ConfigError(f"--{option.replace('_', '-')} is an option of lgnn leaderboard verify")
    profile = benchmark_profile(profile_source(args), settings=args.set or (), with_results=args.with_results)
    out = Path(args.out_dir) if args.out_dir else default_out(profile)
    if not out.is_dir():
        raise ConfigError(f"results folder {out} does not exist (lgnn benchmark writes it)")
    layout(profile, out)
    path = leaderboard.write_leaderboard(profile, out, "lgnn " + " ".join(args.argv))
    print(f"wrote {path}")
    return None


def _verify(args) -> int:
    from pathlib import Path


    from lgnn.bench import verify
    from lgnn.bench.api import benchmark_profile
    from lgnn.bench.report import leaderboard
    from lgnn.provenance import environment

    if args.folder is not None and args.out_dir is not None:
        raise ConfigError("give the folder to verify once: as FOLDER or as --out-dir")
    out = Path(args.folder or args.out_dir or "results")
    if not out.is_dir():
        raise ConfigError(f"results folder {out} does not exist")
    # The committed results and the rows submitted beside them are the full profile's.
    source = profile_source(args) if (args.profile or args.config) else "full"
    profile = benchmark_profile(source, settings=args.set or (), with_results=args.with_results)
    command = "lgnn " + " ".join(args.argv)
    env = environment()  # before anything is written: a committed folder would read "+dirty"
    if args.row and args.predictions:
        raise ConfigError("--row checks rows of the grid alone: give --predictions without it")
    outcome = verify.verify(profile, out, args.initial_conditions or verify.CONDITIONS, args.scenes or "smallest", args.predictions or (),
                            progress=not args.quiet, rows=tuple(args.row) if args.row else None)
    for finding in outcome.findings:
        print(finding.line())
    saved = verify.save(outcome, out, command, env)
    counts = outcome.counts()
    summary = f"{counts['verified']} verified, {counts['unverified']} unverified, {counts['failed']} failed; wrote {saved}"
    try:
        written = leaderboard.write_leaderboard(profile, out, env=env)
    except LgnnError as err:  # a checkpoint the failures name: the table cannot be made from it
        print(f"{summary}; LEADERBOARD.md not rewritten: {one_line(str(err))}")
        return EXIT_CHECK_FAILED
    print(f"{summary} and {written}")
    return EXIT_CHECK_FAILED if outcome.failed else 0


def _add_leaderboard_parser(commands) -> None:
    parser = commands.add_parser("leaderboard", help="write LEADERBOARD.md of a results folder from its records (ranks, parameters, training "
                                                     "time), or verify every row (lgnn leaderboard verify FOLDER)")
    parser.add_argument("action", nargs="?", choices=("verify",),
                        help="verify: re-derive every row of FOLDER (default results/, the full profile's) from its checkpoints and "
                             "records, name each disagreement in one line (exit 1 if any), keep the outcome in "
                             "FOLDER/benchmark/verification.json and mark LEADERBOARD.md's rows (docs/benchmark.md, 'Verifying a leaderboard')")
    parser.add_argument("folder", nargs="?", help="with verify: the results folder (default results/)")
    add_profile_options(parser, "the full profile's results (default folder: results/)", "override a config value, as lgnn benchmark's (repeatable)")
    parser.add_argument("--with-results", metavar="DIR", help="also read the records of DIR in place, as lgnn benchmark --with-results")
    parser.add_argument("--out-dir", default=None, help="the results folder, read and written into (default: as lgnn benchmark's)")
    parser.add_argument("--initial-conditions", type=positive_int, default=None, metavar="K",
                        help="with verify: roll each row out again from the first K evaluation initial conditions of each checked scene (default 2)")
    parser.add_argument("--scenes", choices=("smallest", "all"), default=None,
                        help="with verify: the scenes each row is rolled out on again: its smallest (default) or every one")
    parser.add_argument("--predictions", action="append", metavar="FILE.npz",
                        help="with verify: the predictions file of an external row, scored again (repeatable; without, the row is unverified)")
    parser.add_argument("--row", action="append", metavar="LABEL",
                        help="with verify: only this row of the grid, as the tables label it, e.g. 'lgnn' or 'gns (chain4-3d)' "
                             "(repeatable; without the external rows and the summary)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.set_defaults(run=_cmd_leaderboard)


def _cmd_dataset_export(args) -> None:
    from lgnn.bench import profiles
    from lgnn.bench.dataset import export_scene
    from lgnn.files import check_writable
    from lgnn.learn import data

    from lgnn.learn.export import check_path

    check_path(check_writable(args.out))
    profile = profiles.load_profile(args.config or args.profile, args.set or ())
    shapes = export_scene(profile, args.scene, args.out, args.cache_dir or data.default_cache_dir(), progress=not args.quiet)
    print(f"{args.scene}: {shapes['q'][0]} states ({shapes['train'][0]} train, {shapes['val'][0]} validation), "
          f"{shapes['eval_q0'][0]} evaluation initial conditions ({profile.name} profile); wrote {args.out}")


def _add_dataset_parser(commands) -> None:
    from lgnn.bench import profiles

    parser = commands.add_parser("dataset", help="training and evaluation data for other frameworks")
    sub = parser.add_subparsers(dest="dataset_command", required=True, metavar="SUBCOMMAND")
    export = sub.add_parser("export", help="write a scene's training data and evaluation initial conditions (.npz or .h5; docs/formats.md)")
    export.add_argument("--scene", required=True, help="built-in scene name or scene JSON file")
    export.add_argument("--out", required=True, help="output file: .npz, or .h5 (needs h5py: pip install 'lgnn[hdf5]')")
    export.add_argument("--profile", choices=profiles.PROFILE_NAMES, default="full", help="data and evaluation settings (default: full, the paper's)")
    export.add_argument("--config", help="a benchmark config file instead of --profile")
    export.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a setting, e.g. training.data.n_trajectories=10")
    export.add_argument("--cache-dir", default=None, help="training data cache (default: as lgnn train's)")
    export.add_argument("--quiet", action="store_true", help="no progress bar")
    export.set_defaults(run=_cmd_dataset_export)


def _cmd_handoff_pack(args) -> None:
    from pathlib import Path

    from lgnn.bench import handoff
    from lgnn.bench.api import benchmark_profile

    profile = benchmark_profile(profile_source(args), settings=args.set or (), add_models=args.add_model or ())
    limits = handoff.Limits(args.files, int(args.file_mib * handoff.MIB), int(args.total_mib * handoff.MIB))
    manifest = handoff.pack(profile, Path(args.out_dir), Path(args.to), limits)
    roles = {}
    for member in manifest["members"]:
        roles[member["role"]] = roles.get(member["role"], 0) + 1
    print(f"handed back {len(manifest['members'])} files ({', '.join(f'{n} {role}' for role, n in roles.items())}) in "
          f"{len(manifest['parts'])} parts, {manifest['bytes'] / handoff.MIB:.1f} MiB, and {handoff.MANIFEST}; wrote {args.to}/")


def _cmd_handoff_unpack(args) -> None:
    from pathlib import Path

    from lgnn.bench import handoff

    manifest = handoff.unpack(Path(args.source), Path(args.out_dir))
    print(f"unpacked {len(manifest['members'])} files into {args.out_dir}/; lgnn benchmark --out-dir {args.out_dir} resumes the run")


def _add_handoff_parser(commands) -> None:
    parser = commands.add_parser("handoff", help="hand an unfinished benchmark run to the next job in a few files, and take it back")
    sub = parser.add_subparsers(dest="handoff_command", required=True, metavar="SUBCOMMAND")
    pack = sub.add_parser("pack", help="write what a fresh machine needs to resume a benchmark run (docs/benchmark.md, 'Resuming across jobs')")
    pack.add_argument("out_dir", metavar="OUT", help="the run's output folder (lgnn benchmark --out-dir)")
    pack.add_argument("--to", required=True, metavar="DIR", help="where to write the parts and handoff.json")
    add_profile_options(pack, "the full profile's run", "override a config value, as given to lgnn benchmark (repeatable)")
    pack.add_argument("--add-model", action="append", metavar="FILE.py:ATTR", help="a model added to the run, as given to lgnn benchmark")
    pack.add_argument("--files", type=positive_int, default=8, help="at most this many files, handoff.json among them (default 8)")
    pack.add_argument("--file-mib", type=positive_float, default=16.0, help="each at most this many MiB (default 16)")
    pack.add_argument("--total-mib", type=positive_float, default=64.0, help="at most this many MiB in all (default 64)")
    pack.set_defaults(run=_cmd_handoff_pack)
    unpack = sub.add_parser("unpack", help="put a hand-back into an output folder, to resume the run there")
    unpack.add_argument("source", metavar="DIR", help="the folder holding handoff.json and its parts")
    unpack.add_argument("--out-dir", required=True, help="the output folder to resume in (without a run yet)")
    unpack.set_defaults(run=_cmd_handoff_unpack)


def _cmd_papers(args) -> None:
    import dataclasses
    from pathlib import Path

    from lgnn import files
    from lgnn.bench import papers

    if args.protocol == "lgnn2022" and args.seeds:
        raise ConfigError("--seeds: the lgnn2022 table trains nothing (it reads --results)")
    if args.protocol != "lgnn2022" and args.results:
        raise ConfigError(f"--results is read by --protocol lgnn2022 only, not {args.protocol}")
    if args.protocol == "lgnn2022":
        out = Path(args.out_dir or "results/papers")
        files.check_out_dir(out, "lgnn2022.md")
        out.mkdir(parents=True, exist_ok=True)
        files.write_text_atomic(out / "lgnn2022.md", text := papers.lgnn2022_report(args.results or "results"))
        print(text)
        print(f"wrote {out / 'lgnn2022.md'}")
        return
    protocol = papers.PROTOCOLS[args.protocol]
    if args.seeds:
        protocol = dataclasses.replace(protocol, seeds=tuple(args.seeds))
    out_dir = args.out_dir or ("results/papers" if args.protocol == "finzi2020" else f"lgnn-out/papers-{args.protocol}")
    print(f"lgnn papers ({protocol.name}): writing into {out_dir}/", flush=True)
    readme = papers.run(protocol, out_dir, log=(lambda line: None) if args.quiet else (lambda line: print(line, flush=True)))
    print(readme.read_text())
    print(f"wrote {readme.parent}/")


def _add_papers_parser(commands) -> None:
    from lgnn.bench import papers

    parser = commands.add_parser("papers", help="train the zoo's CHNN and CLNN by Finzi et al.'s own protocol and put them beside "
                                                "the published numbers (docs/papers.md)")
    parser.add_argument("--protocol", choices=(*papers.PROTOCOLS, "lgnn2022"), default="finzi2020",
                        help="finzi2020 (default: the paper's data, recipe and metric), quick (seconds, CI's), or lgnn2022 (the "
                             "LGNN paper's stated numbers beside the benchmark's cells in --results; trains nothing)")
    parser.add_argument("--results", default=None, help="lgnn2022: the benchmark results folder to read (default results/)")
    parser.add_argument("--seeds", type=int, nargs="+", help="training seeds (default: the protocol's, 0 1 2 for finzi2020)")
    parser.add_argument("--out-dir", default=None,
                        help="output folder (default results/papers/ for finzi2020, lgnn-out/papers-quick/ for quick); groups "
                             "already recorded there with the same settings are reused")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    parser.set_defaults(run=_cmd_papers)


# `lgnn benchmark`, `leaderboard`, `handoff`, `dataset export` and `papers`: their
# parsers' builders, in `lgnn --help`'s order.
PARSERS = (_add_benchmark_parser, _add_leaderboard_parser, _add_handoff_parser, _add_dataset_parser, _add_papers_parser)
