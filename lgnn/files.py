"""Where outputs go, and atomic file output.

A crash or a kill never leaves a half-written result: files are written to a temporary
file beside the target, then renamed, so readers see the old file or the new one,
nothing in between.

Inputs are read only from regular files (`check_regular_input`): a FIFO with no writer
would block forever, a device would never end. Outputs never replace anything but a
regular file (`check_writable`): a device, FIFO or socket at an output path is refused.
A symbolic link is followed to read; at an output path it is replaced by the new file,
its target left as it was (the rename replaces the name, as every atomic writer does).

No command writes into a repository's committed `results/` unless told to: reports go
to `DEFAULT_OUT` (`./lgnn-out`, created on demand) unless an output is named; caches
(training data) go to `user_cache_dir()` (`$LGNN_CACHE`, else `$XDG_CACHE_HOME/lgnn`,
else `~/.cache/lgnn`), not beside wherever the user stands.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

from lgnn.errors import ConfigError

# Reports of commands not told where to write (`out_dir(None)`).
DEFAULT_OUT = Path("lgnn-out")


def out_dir(path: str | os.PathLike | None) -> Path:
    """The output directory a command writes into, created with its parents if missing:
    `path` (checked first: `check_out_dir`), or `DEFAULT_OUT` when none is named. The
    one rule of every command (docs/cli.md): an output *folder* is created, an output
    *file*'s folder must exist (`check_writable`)."""
    path = DEFAULT_OUT if path is None else check_out_dir(path)
    path.mkdir(parents=True, exist_ok=True)
    return path


def user_cache_dir() -> Path:
    """lgnn's cache directory: `$LGNN_CACHE`, else `$XDG_CACHE_HOME/lgnn`, else
    `~/.cache/lgnn` (not created here)."""
    if os.environ.get("LGNN_CACHE"):
        return Path(os.environ["LGNN_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "lgnn"


def check_writable(path: str | os.PathLike) -> Path:
    """Fail early, with one line, if `path` cannot be written (before any long work)."""
    path = Path(path)
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise ConfigError(f"output directory does not exist: {parent}")
    if not os.access(parent, os.W_OK):
        raise ConfigError(f"output directory is not writable: {parent}")
    if path.is_dir():
        raise ConfigError(f"output path is a directory: {path}")
    if path.exists() and not path.is_file():
        raise ConfigError(f"output path is not a regular file (a device, FIFO or socket is never replaced): {path}")
    return path


def check_out_dir(path: str | os.PathLike, writes: str | None = None) -> Path:
    """An output directory a command creates on demand: `path` itself, if it exists, and
    else its nearest existing parent must be a writable directory (one line otherwise);
    `writes`: a file the command will write in it, checked too if the folder exists."""
    path = Path(path)
    if writes is not None and path.is_dir():
        check_writable(path / writes)
    for folder in (path, *path.parents):
        if folder.exists() or folder.is_symlink():
            if not folder.is_dir():
                raise ConfigError(f"output directory {path}: {folder} is not a directory")
            if not os.access(folder, os.W_OK):
                raise ConfigError(f"output directory {path}: {folder} is not writable")
            return path
    return path


def check_regular_input(path: str | os.PathLike, what: str) -> Path:
    """`path` if it is an existing regular file (symbolic links followed); else one line
    naming `what` it should have been (a FIFO would block the read forever)."""
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"{path}: no such {what}")
    if not path.is_file():
        raise ConfigError(f"{path}: not a regular file (a {what} is read from a file)")
    return path


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path in the target's directory; rename it over `path` on success.
    The temporary file is removed however the body ends: everything after its creation
    runs under the cleanup, so a Ctrl-C (a KeyboardInterrupt at any bytecode) leaves it
    only if it lands inside `mkstemp` between the file's creation and its return."""
    path = check_writable(path)
    tmp = None
    try:
        try:
            fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix, dir=path.parent)
        except OSError as err:
            # os.access says yes to root on read-only or special file systems
            raise ConfigError(f"cannot write in {path.parent}: {err.strerror}") from None
        os.close(fd)
        # mkstemp creates 0600; give the result the permissions of an ordinary new file
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        yield Path(tmp)
        os.replace(tmp, path)
    except OSError as err:
        # a full disk, a quota, a vanished directory: one line, and no partial file
        raise ConfigError(f"cannot write {path}: {err.strerror or err}") from None
    finally:
        if tmp is not None:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)
