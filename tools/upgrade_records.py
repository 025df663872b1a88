"""Upgrade benchmark records made before MuJoCo C's stale-frame fix (c0eb960).

Version 1 of MuJoCo C's reference trajectories (array records whose meta has no
`mujoco_reference`; the evaluate stage writes `evaluate.REFERENCE_VERSION`, 2): the
last `mujoco.rollout` call of a batch of several drag-free trajectories left its frames
stale, up to the last 18 % of frames, so every array scored against MuJoCo
(`MUJOCO_ARRAYS`) of such a record is wrong; the rest of the record is not (MuJoCo
enters nothing else). A single trajectory's buffer was contiguous, and drag scenes
stepped in Python, so records of one initial condition or of a drag scene are sound.

This tool removes the MuJoCo-scored arrays from each stale record under
`<out>/benchmark/runs/`, keeping its key, meta and the environment that made it (the
checksum is recomputed). The report then shows "not computed" for them, and
`lgnn benchmark --stage evaluate` recomputes the record (it lacks arrays the current
metrics need). Every other record is left alone; running it twice changes nothing.
The records committed under `results/` carry version 2 (none needs it).

    PYTHONPATH=. python tools/upgrade_records.py results             # rewrite stale records
    PYTHONPATH=. python tools/upgrade_records.py results --dry-run   # only say which
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from lgnn import records
from lgnn.bench.stages import evaluate
from lgnn.scene import get_scene

# Array name prefixes made from the MuJoCo reference, in a pair or ground-truth record.
MUJOCO_ARRAYS = ("truth_vs_mujoco", "rollout_error_vs_mujoco", f"{evaluate.REST}/rollout_error_vs_mujoco",
                 f"{evaluate.NO_DRAG}/rollout_error_vs_mujoco", "snapshot/mujoco")


def is_stale(meta: dict) -> bool:
    """Whether a record's MuJoCo-scored arrays came from a stale reference: version 1,
    several initial conditions, a drag-free scene (module docstring)."""
    return (meta.get("mujoco_reference", 1) < evaluate.REFERENCE_VERSION and meta.get("initial_conditions", 1) > 1
            and "scene" in meta and not get_scene(meta["scene"]).drag)


def upgraded(arrays: dict, meta: dict) -> dict | None:
    """The arrays a stale record keeps (those not scored against MuJoCo), or None when
    the record is sound or holds no MuJoCo-scored array."""
    if not is_stale(meta):
        return None
    kept = {name: value for name, value in arrays.items() if not name.startswith(MUJOCO_ARRAYS)}
    return kept if len(kept) < len(arrays) else None


def upgrade(out: Path, dry_run: bool = False) -> list[Path]:
    """Rewrite every stale array record under `out/benchmark/runs/` without its
    MuJoCo-scored arrays; the paths rewritten (or, with `dry_run`, to rewrite)."""
    changed = []
    for path in sorted((out / "benchmark" / "runs").rglob("*.npz")):
        arrays, meta = records.read(path)
        kept = upgraded(arrays, meta)
        if kept is None:
            continue
        changed.append(path)
        if not dry_run:
            environment = meta.pop("environment", None)
            records.save(path, kept, meta, environment=environment)
    return changed


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="the benchmark's output directory (results/ for the full profile)")
    parser.add_argument("--dry-run", action="store_true", help="only list the records that would be rewritten")
    args = parser.parse_args(argv)
    if not (args.out / "benchmark" / "runs").is_dir():
        print(f"error: {args.out}: no benchmark/runs/ folder", file=sys.stderr)
        return 2
    try:
        changed = upgrade(args.out, args.dry_run)
    except records.RecordError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    for path in changed:
        print(f"{'would rewrite' if args.dry_run else 'rewrote'} {path}")
    print(f"{len(changed)} stale record(s)" + (" (dry run)" if args.dry_run else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
