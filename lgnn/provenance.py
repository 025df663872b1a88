"""Where a result came from: commit, versions, machine.

Every results file records these next to its numbers. The commit is lgnn's own, read
from git in the directory of the `lgnn` package (whatever the working directory: a
researcher runs the benchmark from a project of their own), or from `LGNN_COMMIT`
where the tree is a copy without `.git` (the lent GPU machine); a dirty tree is marked
`+dirty`; "unknown" where neither gives it (an install without git).
"""

from __future__ import annotations

import functools
import importlib.metadata
import os
import platform
import subprocess
from pathlib import Path


def _git(*args: str) -> str | None:
    try:
        out = subprocess.run(["git", *args], capture_output=True, text=True, timeout=10, check=True, cwd=Path(__file__).parent)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip()


@functools.cache
def commit() -> str:
    if os.environ.get("LGNN_COMMIT"):
        return os.environ["LGNN_COMMIT"]
    head = _git("rev-parse", "--short=10", "HEAD")
    if head is None:
        return "unknown"
    dirty = _git("status", "--porcelain", "--untracked-files=no")
    return head + ("+dirty" if dirty else "")


def _version(package: str) -> str:
    try:
        return importlib.metadata.version(package)
    except importlib.metadata.PackageNotFoundError:
        return "absent"


# Installed versions do not change within a process, and reading package metadata takes
# tens of milliseconds: every record (a checkpoint each epoch) states them.
@functools.cache
def versions() -> str:
    """`python 3.12.3, jax 0.10.2, ...` of the packages a result depends on."""
    from lgnn import __version__

    packages = ("jax", "jaxlib", "jraph", "optax", "mujoco", "mujoco-mjx", "numpy")
    return ", ".join([f"python {platform.python_version()}", f"lgnn {__version__}"] + [f"{p} {_version(p)}" for p in packages])


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as handle:
            for line in handle:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def device() -> str:
    """The JAX backend's device(s) and the CPU, e.g. `1x NVIDIA H100 (gpu); CPU: ... x16`."""
    import jax

    devices = jax.devices()
    return f"{len(devices)}x {devices[0].device_kind} ({jax.default_backend()}); CPU: {_cpu_model()} x{os.cpu_count()}"


def environment() -> dict[str, str]:
    """`commit, versions, device` columns for tidy tables."""
    return {"commit": commit(), "versions": versions(), "device": device()}
