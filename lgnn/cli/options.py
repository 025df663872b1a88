"""What the commands share: the argument parser, option types and the options common
to several commands, each turned into the library's settings.

`Parser` makes a usage error one line (`lgnn: error: ...`, exit 2); the option types
(`positive_float`, `float_in`, `int_in`, ...) refuse a bad value in argparse's own
words, naming the option; `add_simulation_options` / `simulation_config` /
`integration_of` are the rollout settings (`lgnn.engines.base.SimulationConfig`,
`Integration`) of every command that rolls out; `add_profile_options` chooses a
benchmark profile.
"""

from __future__ import annotations

import argparse
import math
import re

from lgnn.errors import ConfigError

# The exit status of a check that ran and found what it checks wrong (`lgnn leaderboard
# verify`, docs/cli.md): the command returns it, each finding printed in one line.
EXIT_CHECK_FAILED = 1


class Parser(argparse.ArgumentParser):
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


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def float_in(low: float, high: float):
    """An option's type: a number in [low, high] (a rate whose reciprocal must stay finite)."""

    def parse(text: str) -> float:
        value = positive_float(text)
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"must be between {low:g} and {high:g}, got {text}")
        return value

    return parse


def int_in(low: int, high: int | None = None):
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


positive_int = int_in(1)
nonnegative_int = int_in(0)


def file_name_part(text: str) -> str:
    """An option's type: text that goes into a file's name, so no folder in it."""
    if any(mark in text for mark in ("/", "\\", "\0")) or text in (".", ".."):
        raise argparse.ArgumentTypeError(f"goes into file names, so no folder or path separator: {text!r}")
    return text


def model_reference(text: str) -> str:
    """A built-in model name, or a `module:attribute` / `file.py:attribute` reference
    to a model defined outside lgnn (imported when the command runs, so a failing
    import is the command's one-line error, not argparse's)."""
    from lgnn.learn.models import model_names

    if ":" in text or text in model_names():
        return text
    raise argparse.ArgumentTypeError(f"invalid choice: {text!r} (choose from {', '.join(map(repr, model_names()))}, "
                                     "or module:attribute or file.py:attribute of your own ModelSpec)")


def add_model_code_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model-code", metavar="MODULE:ATTR", default=None,
                        help="a checkpoint of your own model: the module:attribute or file.py:attribute it was trained with "
                             "(the checkpoint names it; its code is imported only when you say so)")


def import_model_code(args) -> None:
    """Register the model code `--model-code` names, before a checkpoint of it is read."""
    if args.model_code:
        from lgnn.learn.models import load_spec

        load_spec(args.model_code)


def add_simulation_options(parser: argparse.ArgumentParser) -> None:
    from lgnn.integrate import INTEGRATORS
    from lgnn.engines.base import Integration, SimulationConfig

    default = SimulationConfig()
    # Integration options default to None: given, they are refused by an engine that
    # integrates its own way (the MuJoCo engines), not silently dropped.
    parser.add_argument("--integrator", choices=sorted(INTEGRATORS), default=None,
                        help=f"integrator of the Lagrangian engine and learned models (default {Integration().integrator})")
    parser.add_argument("--dt", type=positive_float, default=default.dt, help="integration step (s)")
    parser.add_argument("--frame-dt", type=positive_float, default=default.frame_dt, help="interval between saved frames (s)")
    parser.add_argument("--duration", type=positive_float, default=default.duration, help="simulated time (s)")
    parser.add_argument("--no-project", dest="project", action="store_const", const=False, default=None,
                        help="do not project onto the constraints after each step (Lagrangian engine and learned models)")


def simulation_config(args):
    from lgnn.engines.base import SimulationConfig

    if args.dt > args.frame_dt:
        raise ConfigError(f"dt {args.dt:g} is longer than the interval between frames (--frame-dt {args.frame_dt:g}): "
                          f"pass --frame-dt too, a whole multiple of dt (e.g. --frame-dt {args.dt:g})")
    return SimulationConfig(args.dt, args.frame_dt, args.duration)


def integration_of(args):
    """The `Integration` that `--integrator` and `--no-project` ask for; None where
    neither is given (each engine's own)."""
    from lgnn.engines.base import Integration

    if args.integrator is None and args.project is None:
        return None
    default = Integration()
    return Integration(args.integrator or default.integrator, default.project if args.project is None else args.project)


def trajectory_out(path: str):
    """`--out` of a trajectory: an `.npz` file (the only trajectory format), checked
    writable before any work."""
    from lgnn.files import check_writable

    checked = check_writable(path)
    if checked.suffix != ".npz":
        raise ConfigError(f"--out: trajectories are written as .npz (t, q, qd, energy; docs/formats.md), got {path!r}")
    return checked


def add_profile_options(parser, full_help: str, set_help: str) -> None:
    """The options that choose a benchmark profile: --full, --profile, --config, --set."""
    from lgnn.bench import profiles

    parser.add_argument("--full", action="store_true", help=full_help)
    parser.add_argument("--profile", choices=profiles.PROFILE_NAMES, help="a shipped profile: quick (default) or full (same as --full)")
    parser.add_argument("--config", help="a benchmark config file (TOML; docs/benchmark.md, 'Configs')")
    parser.add_argument("--set", action="append", metavar="KEY=VALUE", help=set_help)


def profile_source(args) -> str:
    """The profile `add_profile_options`' options choose: a config file, a shipped name, or quick."""
    if sum(map(bool, (args.full, args.profile, args.config))) > 1:
        raise ConfigError("give one of --config, --profile and --full")
    return args.config or args.profile or ("full" if args.full else "quick")
