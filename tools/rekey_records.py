"""Re-key benchmark records made from checkpoints on the checkpoint's content, and deflate them.

The evaluation, mass, speed and scaling records of a profile depend on checkpoints.
Their keys digested each checkpoint file's bytes (`lgnn.records.file_digest`) until the
stages keyed on what the rollouts depend on, the model settings and best parameters
(`lgnn.learn.checkpoints.content_digest`), so that a converted checkpoint
(`tools/convert_checkpoints.py`) keeps its records. This tool recomputes, for each such
record of the profile, the key the file-digest derivation gives it (the stages' key
functions with `file_digest` in place of `content_digest`) and, if the record carries
exactly that key, rewrites it with the content key: arrays, meta and the environment
that made it unchanged, the arrays deflated. A record with the content key already is
left as it is (only deflated); one with neither key is reported and left alone (it is
stale either way). Every other array record (the ground truths) is deflated. Run it while the checkpoints are the files the records were made
from, before converting them.

    PYTHONPATH=. python tools/rekey_records.py --full            # results/
    PYTHONPATH=. python tools/rekey_records.py --full --dry-run  # only say what it would do
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import sys
import zipfile
from pathlib import Path

import lgnn

lgnn.configure()

from lgnn import records  # noqa: E402
from lgnn.bench import profiles, store  # noqa: E402
from lgnn.bench.stages import evaluate, mass, scaling, speed  # noqa: E402
from lgnn.files import write_text_atomic  # noqa: E402

KEYED_STAGES = (evaluate, mass, scaling, speed)


@contextlib.contextmanager
def file_digest_keys():
    """The stages' key functions as they were: checkpoints digested by their bytes."""
    kept = [stage.content_digest for stage in KEYED_STAGES]
    for stage in KEYED_STAGES:
        stage.content_digest = records.file_digest
    try:
        yield
    finally:
        for stage, digest in zip(KEYED_STAGES, kept):
            stage.content_digest = digest


def _rekey_arrays(path: Path, old: str, new: str, dry_run: bool) -> str:
    arrays, meta = records.read(path)
    what = "content key already" if meta.get("key") == new else "rekeyed" if meta.get("key") == old else None
    if what is None:
        return "STALE: neither key (left alone)"
    if not dry_run:
        _rewrite(path, arrays, {**meta, "key": new})
    return what


def _rekey_json(path: Path, old: str, new: str, dry_run: bool) -> str:
    stored = json.loads(path.read_text())
    if stored.get("key") == new:
        return "content key already"
    if stored.get("key") != old:
        return "STALE: neither key (left alone)"
    if not dry_run:
        # Written as `records.save_json` writes, the fields kept in their stored order.
        write_text_atomic(path, json.dumps({**stored, "key": new}, indent=1, default=float))
    return "rekeyed"


def _keys(key_function, *args) -> tuple[str, str]:
    with file_digest_keys():
        old = key_function(*args)
    return old, key_function(*args)


def rekey(profile: profiles.Profile, out: Path, dry_run: bool = False) -> dict[Path, str]:
    """What happened to each checkpoint-keyed record of the profile under `out`."""
    layout = store.layout(profile, out)
    done = {}
    for pair in profiles.evaluation_pairs(profile):
        path, checkpoint = layout.pair_record(pair), layout.found(layout.checkpoint(pair.job))
        if path.exists() and checkpoint.exists():
            done[path] = _rekey_arrays(path, *_keys(evaluate.pair_key, profile, pair, checkpoint), dry_run)
    for scene in profile.speed.scenes:
        path = layout.speed_record(scene)
        if path.exists():
            done[path] = _rekey_json(path, *_keys(speed.speed_key, profile, scene, out), dry_run)
    if layout.scaling_record.exists():
        # The committed scaling record predates the 3D rows: it carries the key of the
        # planar-only settings it was made with (`scaling.scaling_key`).
        planar = dataclasses.replace(profile, scaling=dataclasses.replace(
            profile.scaling, spatial_lengths=(), throughput_scenes=tuple(s for s in profile.scaling.throughput_scenes if not s.endswith("-3d"))))
        old, new = _keys(scaling.scaling_key, profile, out)
        if json.loads(layout.scaling_record.read_text()).get("key") not in (old, new):
            old, new = _keys(scaling.scaling_key, planar, out)
        done[layout.scaling_record] = _rekey_json(layout.scaling_record, old, new, dry_run)
    for scene in profile.mass.scenes:
        path, checkpoint = layout.mass_record(scene), layout.found(layout.checkpoint(profiles.lgnn_job(profile, scene)))
        if path.exists() and checkpoint.exists():
            done[path] = _rekey_arrays(path, *_keys(mass.mass_key, profile, scene, checkpoint), dry_run)
    for path in sorted((layout.bench / "runs").rglob("*.npz")):
        if path not in done:
            done[path] = _deflate(path, dry_run)
    return done


def _deflate(path: Path, dry_run: bool) -> str:
    """Deflate an array record that keys on no checkpoint (a ground truth), its content unchanged."""
    with zipfile.ZipFile(path) as archive:
        if all(entry.compress_type == zipfile.ZIP_DEFLATED for entry in archive.infolist()):
            return "deflated already"
    if not dry_run:
        _rewrite(path, *records.read(path))
    return "deflated"


def _rewrite(path: Path, arrays: dict, meta: dict) -> None:
    """The array record at `path` written again, deflated: `arrays`, `meta` and the
    environment that made it (the checksum recomputed)."""
    environment = meta.pop("environment")
    records.save(path, arrays, meta, environment=environment, compressed=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--full", action="store_true", help="the full profile (default: quick)")
    parser.add_argument("--out", default=None, help="output directory (default: the profile's, results/ for --full)")
    parser.add_argument("--dry-run", action="store_true", help="say what would change, change nothing")
    args = parser.parse_args(argv)
    profile = profiles.get_profile("full" if args.full else "quick")
    out = Path(args.out) if args.out else store.default_out(profile)
    done = rekey(profile, out, args.dry_run)
    for path, what in done.items():
        print(f"{path}: {what}")
    return 1 if any(what.startswith("STALE") for what in done.values()) else 0


if __name__ == "__main__":
    sys.exit(main())
