"""Stages split over worker processes (`lgnn benchmark --workers N`).

The training grid's (model, training scene) groups and the evaluation's scenes are
independent records (`lgnn.bench.store`), so they can run at once: one small training
program does not fill a GPU (on one H100, 9 groups x 3 seeds at the paper's batch 10
took 4.3 s per epoch together, against 0.45 s for one LGNN seed alone: 2.8x the
throughput), and on a multi-core CPU each process takes its own cores. `run_split` runs one `lgnn benchmark`
child per part (the same profile arguments, `--stage`, and `--job` or `--scene` naming
the part), at most `workers` at a time, each writing its log to
`<out>/benchmark/logs/<stage>-<part>.log`; children do not preallocate GPU memory, so
they share the device. A part that fails fails the stage with one line naming its log
(the others run to the end, their records kept).
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

from lgnn.bench.store import Layout, file_name, log
from lgnn.errors import LgnnError


def run_split(stage: str, parts: dict[str, list[str]], flag: str, profile_argv: list[str], out: Path, workers: int) -> None:
    """Run `lgnn benchmark PROFILE_ARGV --stage STAGE --out-dir OUT FLAG x ...` for each
    part (`{name: [values of FLAG]}`), `workers` at a time."""
    logs = Layout(out).bench / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "XLA_PYTHON_CLIENT_PREALLOCATE": os.environ.get("XLA_PYTHON_CLIENT_PREALLOCATE", "false")}
    env.pop("XLA_PYTHON_CLIENT_MEM_FRACTION", None)  # a fraction each would over-commit the device
    waiting, running, failed = list(parts.items()), {}, []
    started = time.monotonic()
    while waiting or running:
        while waiting and len(running) < workers:
            name, values = waiting.pop(0)
            command = [sys.executable, "-m", "lgnn.cli", "benchmark", *profile_argv, "--stage", stage, "--out-dir", str(out), "--quiet"]
            command += [arg for value in values for arg in (flag, value)]
            path = logs / f"{stage}-{file_name(name)}.log"
            handle = path.open("w")
            running[name] = (subprocess.Popen(command, stdout=handle, stderr=subprocess.STDOUT, env=env), handle, path)
            log(f"{stage} {name}: started (log {path})")
        time.sleep(1.0)
        for name, (process, handle, path) in list(running.items()):
            if process.poll() is None:
                continue
            handle.close()
            del running[name]
            if process.returncode:
                failed.append((name, path))
            log(f"{stage} {name}: {'failed' if process.returncode else 'done'} after {(time.monotonic() - started) / 60:.1f} min"
                f" ({len(parts) - len(waiting) - len(running)} of {len(parts)} parts ended)")
    if failed:
        raise LgnnError(f"benchmark {stage}: {len(failed)} of {len(parts)} parts failed; see {failed[0][1]}")
