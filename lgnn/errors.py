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
    """A simulation produced a non-finite or exploding state."""


class CheckpointError(LgnnError):
    """A model checkpoint is missing, corrupt, or does not match what it is used for."""
