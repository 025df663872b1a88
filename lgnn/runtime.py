"""Process-wide runtime settings, applied by an explicit call, never at import.

`configure()` is what the command line, the test configuration and a user's script call
before they compute anything (docs/engines.md, "Precision"):

- float64 (`jax_enable_x64`) unless asked otherwise: accuracy is the point of a ground
  truth (float32 drifts the energy of a 4-link chain by 1e-4 over 1 s, float64 by 1e-13);
- one OpenBLAS thread: the dense systems here are small (at most a few hundred
  unknowns), where OpenBLAS's thread pool (used by numpy, scipy and jaxlib's CPU LAPACK)
  only adds contention: a 300x300 LU took 83 ms with it and 3 ms without on 2 cores.
  OpenBLAS reads the variable when numpy first loads it, so call `configure()` before
  importing numpy (`import lgnn` itself loads nothing heavy);
- XLA's concurrency-optimised CPU scheduler off: it deadlocks (all threads idle,
  forever) on vmapped rollouts whose steps hold several batched LAPACK calls (measured:
  chain16 x 100, one RK4 step with projection, jax 0.10). XLA reads the flag when the
  CPU backend starts, at the first computation;
- XLA's parallel CPU code generation off (`XLA_CODEGEN_FLAG`: see its comment).

A setting the user made in the environment wins over the thread count; the XLA flag is
appended to whatever `XLA_FLAGS` holds.

`enable_compilation_cache()`, called by the command line only (never on import, never
by the tests unless one asks), keeps JAX's compiled programs on disk
(`compilation_cache_dir`: `$LGNN_JAX_CACHE`, else `jax/` in lgnn's cache directory,
`lgnn.files.user_cache_dir`: `$LGNN_CACHE`, else `$XDG_CACHE_HOME/lgnn`, else
`~/.cache/lgnn`; `LGNN_JAX_CACHE=off` for none), so a second `lgnn simulate` of a
scene skips its seconds of compilation. JAX keys an entry on the program, its dtypes and
matmul precision, the XLA flags and the jaxlib version, so another precision or flag
setting compiles its own. A directory that cannot be created or written (a read-only
home) means no cache, said in one debug log line.

Precision is not left to that process-wide switch: `import lgnn` must change nothing
outside the package, yet a script that never calls `configure()` must not get float32
ground truth silently (JAX's default; a 4-link chain then drifts its energy by 7.8e-5
instead of 2.1e-13). So the computing entry points (`simulate`, every engine's
`rollout` and `timed_rollout`, data generation, training) run inside
`precision(dtype)`, JAX's thread-local x64 context, with `dtype` float64 unless the
caller passes `dtype="float32"` (`get_engine(..., dtype=...)`): the result is the same
whatever the global setting, and the global setting is left as it was. A context
rather than a check-and-raise: the safe default needs no set-up at all; a context
rather than a warning: a warning is easy to miss in a long log.
"""

from __future__ import annotations

import contextlib
import functools
import os
import signal
import sys
import threading
from typing import Callable, ContextManager, Iterator

from lgnn.errors import ConfigError

OPENBLAS_THREADS = "1"
# Set in the environment of `lgnn benchmark --workers`' child processes
# (`lgnn.bench.parallel`), which their parent stops with SIGINT.
BENCHMARK_CHILD = "LGNN_BENCHMARK_CHILD"
# The pid of a benchmark child's parent that must not outlive it: set by a Ray task
# (`lgnn.bench.ray_executor`) for its child, so that a task whose worker dies (Ray then
# retries it) leaves no orphan computing on.
STOP_WITH_PARENT = "LGNN_STOP_WITH_PARENT"
# prctl's option that signals a process when its parent dies (Linux).
PR_SET_PDEATHSIG = 1
XLA_SCHEDULER_FLAG = "--xla_cpu_enable_concurrency_optimized_scheduler=false"
# XLA:CPU compiles a program's LLVM module in parallel parts by default. Test workers
# compiling the batched rollout programs (`lgnn.engines.rollouts`) were aborted inside
# XLA's compile, at random and without a message (a different test each time, on 2
# cores, jax 0.10); compiling each module whole is the mitigation taken while the cause
# is not established (a race in the parallel codegen is the suspect).
XLA_CODEGEN_FLAG = "--xla_cpu_parallel_codegen_split_count=1"
XLA_CPU_FLAGS = (XLA_SCHEDULER_FLAG, XLA_CODEGEN_FLAG)


def configure(*, x64: bool = True) -> None:
    """Set the process up for lgnn: thread counts and XLA flags (see the module
    docstring), then JAX's float64 mode (`x64=False` for float32 work)."""
    os.environ.setdefault("OPENBLAS_NUM_THREADS", OPENBLAS_THREADS)
    flags = os.environ.get("XLA_FLAGS", "")
    for flag in XLA_CPU_FLAGS:
        if flag.split("=")[0] not in flags:
            flags = f"{flags} {flag}".strip()
    os.environ["XLA_FLAGS"] = flags
    import jax

    jax.config.update("jax_enable_x64", x64)


COMPILATION_CACHE_ENV = "LGNN_JAX_CACHE"
# Programs that compile faster than this are not written to the cache (JAX's default,
# 1 s, would leave out a small scene's start program).
CACHE_MIN_COMPILE_S = 0.2


def compilation_cache_dir() -> str | None:
    """Where `enable_compilation_cache` keeps compiled programs (module docstring), or
    None where `LGNN_JAX_CACHE` turns it off ("off", "0", "none" or empty)."""
    value = os.environ.get(COMPILATION_CACHE_ENV)
    if value is not None:
        return None if value.strip().lower() in ("", "0", "off", "none") else os.path.expanduser(value)
    from lgnn.files import user_cache_dir

    return os.path.join(user_cache_dir(), "jax")


def enable_compilation_cache() -> str | None:
    """Turn JAX's persistent compilation cache on at `compilation_cache_dir()`; returns
    the directory, or None where it is off or cannot be written (then silently off)."""
    import logging

    directory = compilation_cache_dir()
    if directory is None:
        return None
    try:
        os.makedirs(directory, exist_ok=True)
        writable = os.access(directory, os.W_OK | os.X_OK)
    except OSError:
        writable = False
    if not writable:
        logging.getLogger(__name__).debug("no compilation cache: %s cannot be written", directory)
        return None
    import jax

    jax.config.update("jax_compilation_cache_dir", directory)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", CACHE_MIN_COMPILE_S)
    return directory


# Every compiled XLA:CPU program holds a few memory mappings until JAX's caches let it
# go, and a process may hold at most `vm.max_map_count` of them (65530 by default on
# Linux). Past that, LLVM fails ("Cannot allocate memory") and the process dies inside
# XLA's compile (SIGSEGV or SIGABRT): seen in test workers at 65 386 mappings, after
# thousands of compiles. Long runs release their compiled programs between parts of
# their work once above this many (`release_compiled_programs`).
MAPPINGS_KEPT = 20_000


def memory_mappings() -> int:
    """The process's memory mappings (0 where /proc is not there to say)."""
    try:
        with open("/proc/self/maps", "rb") as maps:
            return maps.read().count(b"\n")
    except OSError:
        return 0


def release_compiled_programs(above: int = MAPPINGS_KEPT) -> bool:
    """Drop every compiled JAX program (`jax.clear_caches`: 300 small programs, 970
    mappings, all returned) if the process holds more than `above` memory mappings;
    whether it did. What is needed again compiles again."""
    if memory_mappings() <= above:
        return False
    import jax

    jax.clear_caches()
    return True


def accept_interrupts_if_child() -> None:
    """In a benchmark child (`BENCHMARK_CHILD` set), take SIGINT as Ctrl-C even where it
    was inherited ignored: a parent started in the background of a non-interactive shell
    (`lgnn benchmark --workers 8 &`, `nohup`) ignores SIGINT, its children inherit that,
    and Python then installs no handler, so the SIGINT the parent stops them with
    (`parallel.run_split`) would do nothing and a training child would be killed a
    minute later without saving its checkpoint."""
    if os.environ.get(BENCHMARK_CHILD) == "1":
        signal.signal(signal.SIGINT, signal.default_int_handler)
        parent = os.environ.get(STOP_WITH_PARENT)
        if parent and sys.platform.startswith("linux"):
            # Stopped as by its parent (SIGINT: a training child saves its checkpoint and
            # releases its claims) when the parent dies; already orphaned: stopped now.
            import ctypes

            ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGINT)
            if os.getppid() != int(parent):
                raise KeyboardInterrupt


def precision(dtype: str = "float64") -> ContextManager:
    """Context in which JAX computes in `dtype` ("float64": x64 on; "float32": x64
    off), whatever `jax_enable_x64` says outside it (thread-local; jit caches key on it,
    so one function compiled in both precisions keeps both)."""
    import jax

    if dtype not in ("float64", "float32"):
        raise ConfigError(f"unknown dtype {dtype!r} (choose from float64, float32)")
    return jax.enable_x64(dtype == "float64")


@contextlib.contextmanager
def xla_optimisations_off(off: bool = True) -> Iterator[None]:
    """Within: programs compiled with most of XLA's optimisation passes off (JAX's
    `jax_disable_most_optimizations`) where `off`, else as the process had it; the
    process's setting is restored after. Compiling is then faster and running slower:
    for programs that run for milliseconds. The arithmetic is IEEE either way; fusing
    or not may round a reduction differently, to round-off."""
    import jax

    before = jax.config.read("jax_disable_most_optimizations")
    if off:
        jax.config.update("jax_disable_most_optimizations", True)
    try:
        yield
    finally:
        jax.config.update("jax_disable_most_optimizations", before)


def full_precision_matmuls(fn: Callable) -> Callable:
    """`fn` traced with JAX's default matmul precision "highest": its matrix products
    (dot_general) carry full-precision operands wherever the caller traces it. XLA's
    default on recent NVIDIA GPUs computes float32 products in TF32 (10-bit mantissa);
    for the physics solves that cost accuracy at no speed gain: T1's float32 rollout on
    an H100 (100 RK4 steps of 1e-3, batch 1024 and 8192) ended 7.4e-5 from float64 at
    the default and 5.9e-7 at "highest", at the same steps/s (results/gpu/truth/earlier/README.md).
    No effect in float64 or on CPUs."""
    import jax

    @functools.wraps(fn)
    def full_precision_fn(*args, **kwargs):
        with jax.default_matmul_precision("highest"):
            return fn(*args, **kwargs)

    return full_precision_fn


def in_float64(fn: Callable) -> Callable:
    """`fn` run inside `precision("float64")` (a computing entry point's decorator)."""

    @functools.wraps(fn)
    def float64_fn(*args, **kwargs):
        with precision("float64"):
            return fn(*args, **kwargs)

    return float64_fn


def in_background(call: Callable[[], object]) -> Callable[[], object]:
    """Start `call()` in a daemon thread; returns a function that waits for it and gives
    its value (or raises its exception). A daemon, so that an error or Ctrl-C in the
    caller does not wait out a long computation (a ground truth's MuJoCo reference)."""
    outcome: dict[str, object] = {}

    def run() -> None:
        try:
            outcome["value"] = call()
        except BaseException as error:  # handed to the caller, whatever it was
            outcome["error"] = error

    thread = threading.Thread(target=run, daemon=True)
    thread.start()

    def result() -> object:
        thread.join()
        if "error" in outcome:
            raise outcome["error"]
        return outcome["value"]

    return result
