"""Upgrade benchmark records written by earlier versions of the evaluate stage.

Three upgrades, each applied only where it is due, so running the tool twice changes
nothing; a record keeps its key, meta and the environment that made it (the checksum is
recomputed):

- **Curves every `evaluate.CURVE_DT` s.** Records written before the stage kept its
  per-frame statistics (`<metric>/gmean`, `low`, `high`, and `t`) at every frame, 1 ms
  apart; the report draws them every 10 ms (`evaluate.curve_frames`). The tool keeps
  those frames, which are the frames the report read, so tables, curves and figures stay
  as they were; the per-initial-condition statistics (`per_ic_log`) are untouched.
- **Snapshots only where the report draws them.** Records written before kept a
  trajectory snapshot (`snapshot/...`) on every scene; the stage now keeps them on
  `grid.SNAPSHOT_SCENES` alone, the scenes of the report's snapshot figures.
- **Stale MuJoCo references.** Version 1 of MuJoCo C's reference trajectories (array
  records whose meta has no `mujoco_reference`; the stage writes
  `truth_stage.REFERENCE_VERSION`, 2): the last `mujoco.rollout` call of a batch of several
  drag-free trajectories left its frames stale, up to the last 18 % of frames, so every
  array scored against MuJoCo (`MUJOCO_ARRAYS`) of such a record is wrong; the rest of
  the record is not (MuJoCo enters nothing else). A single trajectory's buffer was
  contiguous, and drag scenes stepped in Python, so records of one initial condition or
  of a drag scene are sound. The tool removes those arrays; the report then shows "not
  computed" for them, and `lgnn benchmark --stage evaluate` recomputes the record (it
  lacks arrays the current metrics need). The records under `results/` carry version 2.

    PYTHONPATH=. python tools/upgrade_records.py results             # rewrite what is due
    PYTHONPATH=. python tools/upgrade_records.py results --dry-run   # only say which
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from lgnn import records
from lgnn.bench.stages import evaluate
from lgnn.bench.stages import truth as truth_stage
from lgnn.scene import get_scene

# Array name prefixes made from the MuJoCo reference, in a pair or ground-truth record.
MUJOCO_ARRAYS = ("truth_vs_mujoco", "rollout_error_vs_mujoco", f"{evaluate.REST}/rollout_error_vs_mujoco",
                 f"{evaluate.NO_DRAG}/rollout_error_vs_mujoco", "snapshot/mujoco")


def is_stale(meta: dict) -> bool:
    """Whether a record's MuJoCo-scored arrays came from a stale reference: version 1,
    several initial conditions, a drag-free scene (module docstring)."""
    return (meta.get("mujoco_reference", 1) < truth_stage.REFERENCE_VERSION and meta.get("initial_conditions", 1) > 1
            and "scene" in meta and not get_scene(meta["scene"]).drag)


def without_stale_mujoco(arrays: dict, meta: dict) -> dict:
    """The arrays a record keeps: those not scored against MuJoCo if it is stale
    (`is_stale`), else all of them."""
    return {name: value for name, value in arrays.items() if not (is_stale(meta) and name.startswith(MUJOCO_ARRAYS))}


# The per-frame statistics of a record, at its frames `t`.
CURVE_STATISTICS = ("/gmean", "/low", "/high")


def with_thinned_curves(arrays: dict) -> dict:
    """The arrays with the per-frame statistics and `t` kept at the curves' frames
    (`evaluate.curve_frames` of the record's frame step, `t[1] - t[0]`)."""
    t = arrays.get("t")
    if t is None or len(t) < 2:
        return arrays
    frames = evaluate.curve_frames(float(t[1] - t[0]))
    return {name: value[frames] if name == "t" or name.endswith(CURVE_STATISTICS) and value.shape == t.shape else value
            for name, value in arrays.items()}


def without_undrawn_snapshots(arrays: dict, meta: dict) -> dict:
    """The arrays without trajectory snapshots unless the record's scene keeps them
    (`evaluate.keeps_snapshots`)."""
    drawn = evaluate.keeps_snapshots(meta.get("scene"))
    return {name: value for name, value in arrays.items() if drawn or not name.startswith("snapshot/")}


def upgraded(arrays: dict, meta: dict) -> dict | None:
    """The arrays a record keeps after every upgrade due, or None when none is."""
    kept = with_thinned_curves(without_undrawn_snapshots(without_stale_mujoco(arrays, meta), meta))
    unchanged = kept.keys() == arrays.keys() and all(kept[name].shape == arrays[name].shape for name in kept)
    return None if unchanged else kept


def upgrade(out: Path, dry_run: bool = False) -> list[Path]:
    """Rewrite every array record under `out/benchmark/runs/` that an upgrade is due
    for (`upgraded`); the paths rewritten (or, with `dry_run`, to rewrite)."""
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
    print(f"{len(changed)} record(s) upgraded" + (" (dry run)" if args.dry_run else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
