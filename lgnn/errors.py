"""Errors a user can cause, each carrying one line that names the problem.

Entry points (the CLI, the benchmark) catch `LgnnError` and print its message
without a traceback; anything else escaping is a bug in lgnn.
"""


class LgnnError(Exception):
    """Base class of every user-facing error: `str(err)` is one complete line."""


class SceneError(LgnnError):
    """A scene (built-in name or JSON file) is missing, malformed or physically invalid."""


class ConfigError(LgnnError):
    """A setting (dt, duration, model name, output path, ...) is invalid."""


class SimulationError(LgnnError):
    """A simulation produced a non-finite or exploding state.

    `time` is the simulated time (s) of the first bad frame when known, and
    `trajectory` the frames before it (a `simulate.Trajectory`), so callers can
    report how far a run got; both are None when unknown.
    """

    def __init__(self, message: str, *, time: float | None = None, trajectory=None):
        super().__init__(message)
        self.time = time
        self.trajectory = trajectory


class CheckpointError(LgnnError):
    """A model checkpoint is missing, corrupt, or does not match what it is used for."""


def check_number(label: str, value, *, above: float = 0.0, whole: bool = False) -> None:
    """`ConfigError` "LABEL must be ..., got VALUE" unless `value` is a real, finite
    number above `above` (`whole`: a whole number >= 1 instead). A bool is not a number
    here: `True` in a settings file is a mistake, not 1."""
    import math

    number = isinstance(value, (int, float)) and not isinstance(value, bool)
    if whole:
        if not (isinstance(value, int) and number and value >= 1):
            raise ConfigError(f"{label} must be a whole number >= 1, got {value!r}")
    elif not (number and math.isfinite(value) and value > above):
        kind = "a positive number" if above == 0 else "a finite number" if above == -math.inf else f"a finite number > {above:g}"
        raise ConfigError(f"{label} must be {kind}, got {value!r}")
