"""The `lgnn` command line.

Every `LgnnError` becomes one line on stderr (`lgnn: error: ...`) and exit status 2
(`EXIT_BAD_INPUT`), 3 for a diverged simulation (`EXIT_DIVERGED`, frames before it kept),
130 for Ctrl-C (`lgnn.interrupts`); output files are written atomically. Runtime set-up
(`lgnn.runtime.configure`: float64, thread counts, XLA flags) is done here, at the
entry point. The commands parse their arguments and call the library: `simulation`
(scenes, ground-truth engines, MJCF, cross-checks), `learning` (training, checkpoints,
rollouts, evaluation, figures), `benchmark` (the benchmark, its leaderboard, data
export) and `studies` (stability, convergence, GPU ground truth); `options` holds what
they share.
"""

from __future__ import annotations

from lgnn.interrupts import EXIT_INTERRUPTED, HeldWhileLoading, leave, run_interruptibly

# A Ctrl-C while this package loads, before `main` takes SIGINT, is remembered here and
# answered by `main` (one line, exit 130), not raised as a traceback from an import.
_LOADING = HeldWhileLoading()
with _LOADING:
    import argparse
    import os
    import sys

    from lgnn.cli import benchmark, learning, simulation, studies
    from lgnn.cli.learning import train_settings
    from lgnn.cli.options import EXIT_CHECK_FAILED, Parser, one_line
    from lgnn.errors import LgnnError, SimulationError


# Exit statuses (docs/cli.md, "Behaviour common to every command").
EXIT_BAD_INPUT = 2
EXIT_DIVERGED = 3  # a simulation or rollout diverged; the frames before it are kept
__all__ = ["EXIT_BAD_INPUT", "EXIT_CHECK_FAILED", "EXIT_DIVERGED", "EXIT_INTERRUPTED", "build_parser", "entry", "main", "train_settings"]


class _VersionAction(argparse.Action):
    """`--version`: the versions every result records (`lgnn.provenance`), read only
    when asked (package metadata takes tens of milliseconds)."""

    def __init__(self, option_strings, dest, **kwargs):
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        from lgnn import provenance

        print(f"{provenance.versions()}; commit {provenance.commit()}")
        parser.exit()


def build_parser() -> argparse.ArgumentParser:
    """The `lgnn` parser: every command, each run by `args.run(args)`."""
    parser = Parser(prog="lgnn", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action=_VersionAction, help="print lgnn's version, commit and its dependencies' versions, and exit")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for group in (simulation, learning, benchmark, studies):  # `lgnn --help` lists the commands in this order
        for add_parsers in group.PARSERS:
            add_parsers(commands)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command `argv` (default: the process's arguments); its exit status.

    Ctrl-C at any moment, while JAX loads or compiles included, is one line and exit
    130 (`lgnn.interrupts.run_interruptibly`: one during an XLA compilation is held
    until that compilation ends; a second one leaves at once).
    """
    return run_interruptibly(lambda interrupts_after_loading: _run(argv, interrupts_after_loading), _LOADING.take())


def entry() -> None:
    """The `lgnn` console script and `python -m lgnn`: the process ends with `main()`'s
    exit status; a Ctrl-C at any moment after the interpreter has started and lgnn's
    entry point has loaded, the interpreter's own ending included, with the one line and
    130 (`lgnn.interrupts.leave`)."""
    try:
        code = main()
        leave(code)
    except KeyboardInterrupt:  # between main's own handling and `leave`'s
        print("lgnn: interrupted", file=sys.stderr, flush=True)
        leave(EXIT_INTERRUPTED)


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
        # A command returns None, or an exit status of its own (EXIT_CHECK_FAILED).
        code = args.run(args)
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
    return code if isinstance(code, int) else 0
