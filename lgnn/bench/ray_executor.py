"""Stages split over a Ray cluster (`lgnn benchmark --executor ray`).

The parts `lgnn.bench.parallel.run_split` runs as local child processes (a training
group, an evaluation (scene, model) part) become Ray tasks here, at most `workers` in
flight. A task runs the very child command the local executor runs (`parallel.
child_arguments`), with the Python of the node it lands on, in the driver's working
directory, appending its output to the same log, `<out>/benchmark/logs/<stage>-<part>.log`;
so its records are the local executor's, byte for byte but for timings and the
environment they name. The output folder (and the working directory, for relative
paths in the profile's arguments) must be the same path on every node: a shared
filesystem. The record store stays the source of truth: each child claims the records
it computes (`lgnn.bench.claims`), so a part is computed once even when a task is
retried or a second driver works on the same folder (its task waits for the claim,
then reads the record).

Each task declares its resources: a share of a GPU where the cluster has GPUs (the
cluster's GPUs over `workers`, at most one, so small parts pack several to a GPU),
else CPUs (the cluster's over `workers`, at most one node's). `MAX_RETRIES`: a task
whose worker process or node dies is run again (Ray's retry on system failures); its
child, stopped with it (`runtime.STOP_WITH_PARENT`), saved its checkpoint, and the
retry resumes from it. A child that exits with an error fails its part, not retried:
the stage fails with one line naming its log, the others run to the end.

Ray is imported only here, and only when a run asks for it (`connected`): without
it, one line says how to install it.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from lgnn.bench.parallel import STOP_GRACE_S, child_arguments, child_environment, logs_folder, split_queue, stages_named
from lgnn.bench.store import file_name, log
from lgnn.errors import ConfigError, LgnnError
from lgnn.files import user_cache_dir
from lgnn.runtime import STOP_WITH_PARENT

# Retries of a task whose worker process or node died (not of a child that failed).
MAX_RETRIES = 3
# How often the driver reports its stage's progress while nothing ends (seconds).
PROGRESS_EVERY_S = 60.0
INSTALL = "pip install 'lgnn[ray]'"


def _ray():
    try:
        import ray
    except ImportError:
        raise ConfigError(f"--executor ray needs Ray, which is not installed: {INSTALL}") from None
    return ray


@contextlib.contextmanager
def connected(address: str | None):
    """Connected to a Ray cluster for the block: the one this process is connected to
    already (left connected), else the one at `address` ("auto": the local node's
    cluster; HOST:PORT), else a Ray started here for the block (this machine's cores
    and GPUs). Ray missing or no cluster there: one line."""
    ray = _ray()
    if ray.is_initialized():
        yield
        return
    try:
        ray.init(address=address, include_dashboard=False, log_to_driver=False, logging_level="WARNING")
    except (ConnectionError, RuntimeError, ValueError) as err:
        raise ConfigError(f"no Ray cluster at {address}: {str(err).splitlines()[0] if str(err) else type(err).__name__}") from None
    try:
        resources = ray.cluster_resources()
        log(f"Ray cluster: {len(ray.nodes())} node(s), {resources.get('CPU', 0):g} CPUs, {resources.get('GPU', 0):g} GPUs")
        yield
    finally:
        ray.shutdown()


def task_resources(workers: int) -> dict:
    """The Ray resources of one part (module docstring), from the cluster's."""
    ray = _ray()
    gpus = ray.cluster_resources().get("GPU", 0)
    if gpus:
        # Ray takes fractions of a GPU to four decimals.
        return {"num_gpus": min(1.0, int(gpus / workers * 1e4) / 1e4), "num_cpus": 1}
    per_node = max((node["Resources"].get("CPU", 0) for node in ray.nodes() if node["Alive"]), default=1)
    return {"num_cpus": max(1, min(int(per_node), int(ray.cluster_resources().get("CPU", 1) // workers)))}


def run_split(stage: str, parts: dict[str, list[str]], profile_argv: list[str], out: Path, workers: int,
              after: tuple[tuple[str, dict[str, list[str]]], ...] = ()) -> None:
    """`parallel.run_split` on the connected Ray cluster (`connected`): one task per part
    (`after`'s queued behind `parts`), `workers` in flight; progress (parts done,
    running, failed) on stderr."""
    ray = _ray()
    logs = logs_folder(out)
    out, cwd = Path(out).resolve(), os.getcwd()
    cache = str(user_cache_dir().resolve())  # every task uses the driver's dataset cache
    task = ray.remote(max_retries=MAX_RETRIES, retry_exceptions=False)(run_part).options(**task_resources(workers))
    queue = split_queue(stage, parts, after)
    stages = stages_named(queue)
    waiting, running, failed, done = list(queue), {}, [], 0
    started = last = time.monotonic()
    try:
        while waiting or running:
            while waiting and len(running) < workers:
                part_stage, part, args = waiting.pop(0)
                path = logs / f"{part_stage}-{file_name(part)}.log"
                running[task.remote(child_arguments(part_stage, profile_argv, out, args), cwd, str(path), cache)] = (f"{part_stage} {part}", path)
                log(f"{part_stage} {part}: submitted (log {path})")
            ended, _ = ray.wait(list(running), num_returns=1, timeout=PROGRESS_EVERY_S)
            for ref in ended:
                name, path = running.pop(ref)
                try:
                    code, where = ray.get(ref)
                except ray.exceptions.RayError as err:  # its worker died more than MAX_RETRIES times
                    code, where = 1, f"Ray: {str(err).splitlines()[0]}"
                if code:
                    failed.append((name, path))
                else:
                    done += 1
                log(f"{name}: {'failed' if code else 'done'} on {where}")
            if ended or time.monotonic() - last >= PROGRESS_EVERY_S:
                last = time.monotonic()
                log(f"{stages}: {done} done, {len(running)} running, {len(failed)} failed, {len(waiting)} waiting of {len(queue)} parts"
                    f" ({(last - started) / 60:.1f} min)")
    finally:
        for ref in running:  # the driver interrupted: each running child stops as on Ctrl-C
            ray.cancel(ref)
    if failed:
        raise LgnnError(f"benchmark {stages}: {len(failed)} of {len(queue)} parts failed; see {failed[0][1]}")


def run_part(arguments: list[str], cwd: str, log_path: str, cache: str) -> tuple[int, str]:
    """A Ray task: `python -m lgnn.cli ARGUMENTS` in `cwd`, with this node's Python and
    lgnn's cache at `cache` (`$LGNN_CACHE`), its output appended to `log_path`; `(exit
    status, "host pid N")`. Cancelled (the driver stopping), the child is stopped as on
    Ctrl-C, killed after `STOP_GRACE_S`."""
    where = f"{socket.gethostname()} pid {os.getpid()}"
    env = {**child_environment(os.environ), STOP_WITH_PARENT: str(os.getpid()), "LGNN_CACHE": cache}
    with open(log_path, "a") as handle:
        handle.write(f"# lgnn {' '.join(arguments)} ({where}, {time.strftime('%Y-%m-%d %H:%M:%S')})\n")
        handle.flush()
        process = subprocess.Popen([sys.executable, "-m", "lgnn", *arguments], stdout=handle, stderr=subprocess.STDOUT, env=env, cwd=cwd)
        try:
            return process.wait(), where
        except BaseException:
            process.send_signal(signal.SIGINT)
            try:
                process.wait(timeout=STOP_GRACE_S)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
            raise
