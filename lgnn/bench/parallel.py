"""Stages split over worker processes (`lgnn benchmark --workers N`).

The training grid's (model, training scene) groups and the evaluation's (scene, model)
parts are independent records (`lgnn.bench.store`), so they can run at once, and on a
multi-core CPU each process takes its own cores. `run_split` runs one `lgnn benchmark`
child per part (the same profile arguments, `--stage`, and `--job`s and `--scene`
naming the part),
at most `workers` at a time, each writing its log to
`<out>/benchmark/logs/<stage>-<part>.log`; children do not preallocate GPU memory, so
they share the device. A part that fails fails the stage with one line naming its log
(the others run to the end, their records kept).

On a GPU, processes of their own take turns on the device (time slices), however small
their programs: measured on one H100 (2026-11-24, LGNN on chain4, 3 seeds, batch 100,
float64), an epoch took 0.076 s alone and 0.30-0.32 s each with 4 processes at once, the
throughput of one. So `gpu_sharing` runs the children under a private MPS daemon
(NVIDIA's Multi-Process Service, `nvidia-cuda-mps-control`) wherever one can be started:
their kernels then run side by side, 0.12 s per epoch each with 4 processes (2.5x the
throughput of one) and 0.15 s with 8 (4x). Without it (no NVIDIA driver tools, a CPU,
`LGNN_MPS=0`) the children run as before.

On a host of several GPUs each child is given one (`CUDA_VISIBLE_DEVICES`), the one
running the fewest children when it starts, so the parts spread over every GPU instead
of all landing on the first (JAX's default device), each GPU's children sharing it
through the same daemon.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from lgnn.bench.store import Layout, file_name, log
from lgnn.errors import LgnnError
from lgnn.runtime import BENCHMARK_CHILD

# How long stopping children (the parent interrupted) may take, all of them together,
# before the ones still running are killed: a training child saves its checkpoint.
STOP_GRACE_S = 60.0


def run_split(stage: str, parts: dict[str, list[str]], profile_argv: list[str], out: Path, workers: int,
              after: tuple[tuple[str, dict[str, list[str]]], ...] = ()) -> None:
    """Run `lgnn benchmark PROFILE_ARGV --stage STAGE --out-dir OUT ARGS` for each part
    (`{name: ARGS}`, e.g. `["--job", "gns-chain4-s0", ...]`), `workers` at a time.
    `after`: `(stage, parts)` of other stages, queued behind these in the same pool (the
    evaluation's ground truths behind the training groups, `lgnn.bench.run`)."""
    queue = split_queue(stage, parts, after)
    logs = logs_folder(out)
    with gpu_sharing(child_environment(os.environ), enabled=workers > 1 and len(queue) > 1) as env:
        _run_parts(queue, profile_argv, out, workers, env, logs)


def split_queue(stage: str, parts: dict[str, list[str]], after=()) -> list[tuple[str, str, list[str]]]:
    """`(stage, part, args)` in the order the parts start: `parts`, then each of `after`'s."""
    return [(name_of_stage, name, args) for name_of_stage, named in ((stage, parts), *after) for name, args in named.items()]


def stages_named(queue: list[tuple[str, str, list[str]]]) -> str:
    """The stages of a queue, as a failure names them ("train" or "train, truth")."""
    return ", ".join(dict.fromkeys(stage for stage, _, _ in queue))


def logs_folder(out: Path) -> Path:
    """Where the parts' logs go (`<stage>-<part>.log`), created."""
    logs = Layout(out).bench / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    return logs


def child_arguments(stage: str, profile_argv: list[str], out: Path, args: list[str]) -> list[str]:
    """The arguments of `python -m lgnn.cli` that run one part of `stage` (`args`:
    its `--job`s and `--scene`)."""
    return ["benchmark", *profile_argv, "--stage", stage, "--out-dir", str(out), "--quiet", *args]


def child_environment(environ) -> dict:
    """A part's process environment: `environ`, marked a benchmark child, without
    preallocating GPU memory (parts share the device)."""
    env = {**environ, "XLA_PYTHON_CLIENT_PREALLOCATE": environ.get("XLA_PYTHON_CLIENT_PREALLOCATE", "false"), BENCHMARK_CHILD: "1"}
    env.pop("XLA_PYTHON_CLIENT_MEM_FRACTION", None)  # a fraction each would over-commit the device
    return env


def _run_parts(queue: list[tuple[str, str, list[str]]], profile_argv: list[str], out: Path, workers: int, env: dict, logs: Path) -> None:
    waiting, running, failed = list(queue), {}, []
    try:
        _supervise(len(queue), profile_argv, out, workers, env, logs, waiting, running, failed)
    finally:
        # The parent unwinding (Ctrl-C, SIGTERM): its children stop too, each as on
        # Ctrl-C (a training child saves its checkpoint first; `runtime.
        # accept_interrupts_if_child`), those still running after STOP_GRACE_S killed.
        for process, _, _ in running.values():
            process.send_signal(signal.SIGINT)
        deadline = time.monotonic() + STOP_GRACE_S
        for process, handle, _ in running.values():
            try:
                process.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
            handle.close()
    if failed:
        raise LgnnError(f"benchmark {stages_named(queue)}: {len(failed)} of {len(queue)} parts failed; see {failed[0][1]}")


def _supervise(total, profile_argv, out, workers, env, logs, waiting, running, failed) -> None:
    """Start the `waiting` parts, `workers` at a time, until every one has ended."""
    started = time.monotonic()
    gpus, on_gpu = visible_gpus(env), {}
    while waiting or running:
        while waiting and len(running) < workers:
            stage, part, args = waiting.pop(0)
            name = f"{stage} {part}"
            command = [sys.executable, "-m", "lgnn", *child_arguments(stage, profile_argv, out, args)]
            path = logs / f"{stage}-{file_name(part)}.log"
            handle = path.open("w")
            child_env, where = env, ""
            if len(gpus) > 1:
                gpu = least_loaded(gpus, [on_gpu[n] for n in running])
                on_gpu[name], child_env, where = gpu, {**env, "CUDA_VISIBLE_DEVICES": gpu}, f", GPU {gpu}"
            running[name] = (subprocess.Popen(command, stdout=handle, stderr=subprocess.STDOUT, env=child_env), handle, path)
            log(f"{name}: started (log {path}{where})")
        time.sleep(1.0)
        for name, (process, handle, path) in list(running.items()):
            if process.poll() is None:
                continue
            handle.close()
            del running[name]
            if process.returncode:
                failed.append((name, path))
            log(f"{name}: {'failed' if process.returncode else 'done'} after {(time.monotonic() - started) / 60:.1f} min"
                f" ({total - len(waiting) - len(running)} of {total} parts ended)")


def visible_gpus(env: dict) -> list[str]:
    """The GPUs a child may be given: `CUDA_VISIBLE_DEVICES`'s entries where it is set,
    else every GPU `nvidia-smi` lists (none without it: a CPU host)."""
    named = env.get("CUDA_VISIBLE_DEVICES")
    if named is not None:
        return [gpu.strip() for gpu in named.split(",") if gpu.strip()]
    if shutil.which("nvidia-smi") is None:
        return []
    listed = subprocess.run(["nvidia-smi", "--query-gpu=index", "--format=csv,noheader"], capture_output=True, text=True)
    return [line.strip() for line in listed.stdout.splitlines() if line.strip()] if listed.returncode == 0 else []


def least_loaded(gpus: list[str], taken: list[str]) -> str:
    """The first of `gpus` given to the fewest running children (`taken`: one entry per child)."""
    return min(gpus, key=lambda gpu: (taken.count(gpu), gpus.index(gpu)))


MPS_CONTROL = "nvidia-cuda-mps-control"


@contextlib.contextmanager
def gpu_sharing(env: dict, enabled: bool = True):
    """`env` for child processes that share one GPU side by side: with a private MPS
    daemon started for them (its pipe and log directories in a temporary directory,
    named in the returned environment; only processes given them connect) and stopped
    on exit, where `nvidia-cuda-mps-control` is on the PATH and `LGNN_MPS` is not "0".
    Otherwise (not `enabled`: one child at a time; `env` already names an MPS pipe
    directory: the caller's daemon serves), or if the daemon does not start (one line
    says so), `env` unchanged. A parent killed by a signal leaves the daemon running:
    `echo quit | CUDA_MPS_PIPE_DIRECTORY=/tmp/lgnn-mps-*/pipe nvidia-cuda-mps-control`
    stops it."""
    control = shutil.which(MPS_CONTROL)
    if not enabled or control is None or env.get("LGNN_MPS") == "0" or "CUDA_MPS_PIPE_DIRECTORY" in env:
        yield env
        return
    with tempfile.TemporaryDirectory(prefix="lgnn-mps-") as root:
        shared = {**env, "CUDA_MPS_PIPE_DIRECTORY": os.path.join(root, "pipe"), "CUDA_MPS_LOG_DIRECTORY": os.path.join(root, "log")}
        os.makedirs(shared["CUDA_MPS_PIPE_DIRECTORY"]), os.makedirs(shared["CUDA_MPS_LOG_DIRECTORY"])
        started = subprocess.run([control, "-d"], env=shared, capture_output=True, text=True)
        if started.returncode:
            log(f"warning: no MPS daemon ({MPS_CONTROL} -d: {(started.stderr or started.stdout).strip() or started.returncode}); the workers take turns on the GPU")
            yield env
            return
        log("workers share the GPU through a private MPS daemon")
        # A SIGTERM (a job scheduler's stop, `timeout`) unwinds like Ctrl-C, so the daemon
        # still gets its quit; only a SIGKILL leaves it (the docstring says how to stop it).
        main = threading.current_thread() is threading.main_thread()
        previous = signal.signal(signal.SIGTERM, _exit_on_sigterm) if main else None
        try:
            yield shared
        finally:
            subprocess.run([control], input="quit\n", env=shared, capture_output=True, text=True)
            if main:
                signal.signal(signal.SIGTERM, previous)


def _exit_on_sigterm(signum, frame):
    raise SystemExit(128 + signum)
