"""One-off (issue 12): give committed benchmark records the keys of the new derivation.

Until issue 12 each stage's record key listed `Profile` fields by hand; now it is the
digest of every settings group the stage reads (`lgnn.bench.grid.settings_key`,
`lgnn.bench.stages`). The records under `<out>/benchmark/runs/` were made with the
same settings, so recomputing them would give the same numbers at the cost of hours.
This tool recomputes, for each record of the profile, the key the old code gave it
(`old_*_key` below, a copy of the old derivation) and, if the record carries exactly
that key, rewrites it with the new key: arrays, meta fields and the environment that
made it unchanged (an array record's checksum is recomputed, as the key is part of its
meta). A record carrying the new key already is left alone; one carrying neither is
reported and left alone (it is stale either way). Checkpoints have no key and are not
touched.

    PYTHONPATH=. python tools/rekey_records.py --full            # results/
    PYTHONPATH=. python tools/rekey_records.py --full --dry-run  # only say what it would do
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import lgnn

lgnn.configure()

from lgnn import records  # noqa: E402
from lgnn.bench import grid  # noqa: E402
from lgnn.bench.stages import evaluate, mass, scaling, speed  # noqa: E402
from lgnn.bench.store import Layout  # noqa: E402
from lgnn.files import write_text_atomic  # noqa: E402
from lgnn.scene import get_scene, scene_to_dict  # noqa: E402

# ---------------------------------------------------------------------------------
# The old key derivation (lgnn/bench/benchmark.py before issue 12), from the new settings
# ---------------------------------------------------------------------------------


def old_truth_key(profile: grid.Profile, scene: str) -> str:
    e = profile.evaluate
    fields = dict(initial_conditions=e.initial_conditions, duration=e.duration, frame_dt=e.frame_dt, ic_seed=e.ic_seed,
                  floor_perturbation=e.floor_perturbation, mujoco_dt=e.mujoco_dt, dt=e.dt_for(scene))
    return records.digest({"eval": fields, "scene": scene_to_dict(get_scene(scene))})


def old_pair_key(profile: grid.Profile, pair: grid.Pair, checkpoint: Path) -> str:
    return records.digest({"truth": old_truth_key(profile, pair.scene), "checkpoint": records.file_digest(checkpoint)})


def old_speed_key(profile: grid.Profile, scene: str, out: Path) -> str:
    e, s = profile.evaluate, profile.speed
    layout = Layout(out)
    checkpoints = {j.name: records.file_digest(layout.checkpoint(j)) for j in speed.timed_jobs(profile, scene) if layout.checkpoint(j).exists()}
    settings = dict(speed_scenes=s.scenes, speed_dts=s.dts, speed_horizon=s.horizon, mjx=s.mjx, speed_models=s.models, frame_dt=e.frame_dt,
                    ic_seed=e.ic_seed, max_link_steps=s.max_link_steps, dt=e.dt_for(scene))
    return records.digest({"settings": settings, "scene": scene_to_dict(get_scene(scene)), "checkpoints": checkpoints})


def old_scaling_key(profile: grid.Profile, out: Path) -> str:
    e, s = profile.evaluate, profile.scaling
    checkpoint = Layout(out).checkpoint(grid.lgnn_job(profile))
    digest = records.file_digest(checkpoint) if checkpoint.exists() else None
    # The old profile's throughput scenes were its speed scenes.
    settings = dict(scaling_lengths=s.lengths, scaling_steps=s.steps, throughput_batch=s.throughput_batch, speed_scenes=profile.speed.scenes,
                    dt=e.dt, ic_seed=e.ic_seed)
    return records.digest({"settings": settings, "lgnn": digest})


def old_mass_key(profile: grid.Profile, scene: str, checkpoint: Path) -> str:
    return records.digest({"truth": old_truth_key(profile, scene), "checkpoint": records.file_digest(checkpoint), "analysis": 2})


# ---------------------------------------------------------------------------------
# Rewriting
# ---------------------------------------------------------------------------------


def _rekey_arrays(path: Path, old: str, new: str, dry_run: bool) -> str:
    arrays, meta = records.read(path)
    if meta.get("key") == new:
        return "new key already"
    if meta.get("key") != old:
        return "STALE: neither key (left alone)"
    if not dry_run:
        environment = meta.pop("environment")
        records.save(path, arrays, {**meta, "key": new}, environment=environment)
    return "rekeyed"


def _rekey_json(path: Path, old: str, new: str, dry_run: bool) -> str:
    stored = json.loads(path.read_text())
    if stored.get("key") == new:
        return "new key already"
    if stored.get("key") != old:
        return "STALE: neither key (left alone)"
    if not dry_run:
        # Written as `records.save_json` writes, the fields kept in their stored order.
        write_text_atomic(path, json.dumps({**stored, "key": new}, indent=1, default=float))
    return "rekeyed"


def rekey(profile: grid.Profile, out: Path, dry_run: bool = False) -> dict[Path, str]:
    """What happened to each record of the profile under `out` (module docstring)."""
    layout = Layout(out)
    done = {}
    for scene in grid.evaluation_scenes(profile):
        path = layout.truth_record(scene)
        if path.exists():
            done[path] = _rekey_arrays(path, old_truth_key(profile, scene), evaluate.truth_key(profile, scene), dry_run)
    for pair in grid.evaluation_pairs(profile):
        path, checkpoint = layout.pair_record(pair), layout.checkpoint(pair.job)
        if path.exists() and checkpoint.exists():
            done[path] = _rekey_arrays(path, old_pair_key(profile, pair, checkpoint), evaluate.pair_key(profile, pair, checkpoint), dry_run)
    for scene in profile.speed.scenes:
        path = layout.speed_record(scene)
        if path.exists():
            done[path] = _rekey_json(path, old_speed_key(profile, scene, out), speed.speed_key(profile, scene, out), dry_run)
    if layout.scaling_record.exists():
        done[layout.scaling_record] = _rekey_json(layout.scaling_record, old_scaling_key(profile, out), scaling.scaling_key(profile, out), dry_run)
    for scene in profile.mass.scenes:
        path, checkpoint = layout.mass_record(scene), layout.checkpoint(grid.lgnn_job(profile, scene))
        if path.exists() and checkpoint.exists():
            done[path] = _rekey_arrays(path, old_mass_key(profile, scene, checkpoint), mass.mass_key(profile, scene, checkpoint), dry_run)
    return done


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--full", action="store_true", help="the full profile (default: quick)")
    parser.add_argument("--out", default=None, help="output directory (default: the profile's, results/ for --full)")
    parser.add_argument("--dry-run", action="store_true", help="say what would change, change nothing")
    args = parser.parse_args(argv)
    from lgnn.bench.store import default_out

    profile = grid.get_profile("full" if args.full else "quick")
    out = Path(args.out) if args.out else default_out(profile)
    done = rekey(profile, out, args.dry_run)
    for path, what in done.items():
        print(f"{path}: {what}")
    return 1 if any(what.startswith("STALE") for what in done.values()) else 0


if __name__ == "__main__":
    sys.exit(main())
