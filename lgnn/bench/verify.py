"""Every row of a results folder re-derived before it is believed (`lgnn leaderboard verify`).

A row of the leaderboard is a model as the tables label it (`Pair.label`: a training
group's seeds, projected or not). `verify(profile, out)` checks each row of the
profile's grid from what the folder holds, and nothing else:

- **Its records belong to its checkpoints.** Each seed's checkpoint is read (its
  checksum and meta checked: `lgnn.learn.checkpoints.read`) and every record of the
  row must carry the key its checkpoint and the profile's settings give
  (`evaluate.pair_key`). A record edited after the fact keeps its old key only if the
  checkpoint is unchanged, and a checkpoint whose parameters changed has another
  content digest: either is named.
- **Its numbers come out again.** The row's seeds are rolled out again, in one program
  as the evaluation rolls them (`evaluate.stacked_rollouts`), from the first
  `conditions` evaluation initial conditions of its checked scenes (the smallest scene
  it is evaluated on, or every one: `scenes="all"`), against a ground truth computed
  again for those initial conditions alone (`truth.first_ground_truth`: the same
  Lagrangian engine, reference engines and settings), and scored by the evaluation's
  own functions (`evaluate.pair_arrays`). Every recorded metric's per-initial-condition
  value (`<metric>/per_ic_log`, the log of a geometric mean over frames, what every
  table's number is made of) must agree with the record's within `TOLERANCE`.
- **A row whose checkpoints lack their parameters** (kept slim: `without_parameters`)
  cannot be rolled out: it is *unverified*, and says so.
- **The summary is its records'.** `benchmark/summary.csv.gz`, what README.md's and
  LEADERBOARD.md's tables print, must equal the statistics computed again from the
  records (`report.summary.tables`) to `SUMMARY_TOLERANCE`.

Predictions made elsewhere (`runs/external/`) are re-scored from their predictions
file where one is given (`predictions`); a record without its file is unverified.

The outcome is a `Verification`: one `Finding` per row (and per folder-level check),
each *verified*, *unverified* or *failed* with one line saying why. It is kept as
`benchmark/verification.json` beside the records, with the command, environment and
settings that made it and, per row, the digest of the record keys it checked
(`row_digest`): `LEADERBOARD.md` marks a row verified only while its records are the
ones verified.
"""

from __future__ import annotations

import dataclasses
import json
import math
import tempfile
from pathlib import Path

import numpy as np

from lgnn import records
from lgnn.bench import store
from lgnn.bench.grid import Pair
from lgnn.bench.profiles import Profile, evaluation_pairs
from lgnn.bench.stages import evaluate, external
from lgnn.bench.stages import truth as truth_stage
from lgnn.bench.store import log
from lgnn.engines.base import Trajectory
from lgnn.errors import CheckpointError, ConfigError
from lgnn.files import write_text_atomic
from lgnn.learn import checkpoints
from lgnn.scene import get_scene

# How far a re-derived per-initial-condition value may be from the record's, as |d ln
# error| (a relative difference): the records were made on GPUs in float64, and rolled
# out again on a 2-core CPU the committed rows agree to 1e-7 and better (round-off in
# another order, grown by the dynamics over 1 s; the largest, 9.9e-8, is CHNN's energy
# error on chain4, whose first frames sit near round-off). 100 times that; an edited
# number or another model differs by orders more.
TOLERANCE = 1e-5
# How far the committed summary's numbers may be from the statistics computed again
# (relative): the CSV keeps 6 significant digits (`tables.write_csv`), so a number is
# within half a unit of its 6th digit, 5e-6 of it; the bootstrap draws its resamples
# with fixed seeds, so the intervals come out as they were, to round-off.
SUMMARY_TOLERANCE = 5e-6 + 1e-12
# Initial conditions rolled out again per checked scene, by default.
CONDITIONS = 2
# The checked scenes of a row: its smallest evaluation scene, or every one.
SCENE_CHOICES = ("smallest", "all")
VERIFIED, UNVERIFIED, FAILED = "verified", "unverified", "failed"
# Where the outcome is kept, under `<out>/benchmark/`.
VERIFICATION = "verification.json"
FORMAT = 1
# The row of a check of the whole folder (the summary), not of one model.
FOLDER_ROW = "(the folder)"


@dataclasses.dataclass(frozen=True)
class Finding:
    """The outcome of one row's checks: `status` (VERIFIED, UNVERIFIED or FAILED) and one
    line saying what was checked or what is wrong (`detail`); `checked`: the
    `(job, scene)` pairs rolled out again; `digest`: the row's `row_digest`."""

    row: str
    status: str
    detail: str
    checked: tuple[tuple[str, str], ...] = ()
    digest: str | None = None
    # What LEADERBOARD.md's column says of the row (`marks`).
    mark: str = ""

    def line(self) -> str:
        return f"{self.row}: {self.status}: {self.detail}"


@dataclasses.dataclass(frozen=True)
class Verification:
    findings: tuple[Finding, ...]
    conditions: int
    scenes: str
    tolerance: float = TOLERANCE
    # Only some rows were checked (`verify(rows=...)`): `save` keeps the others' findings.
    partial: bool = False

    @property
    def failed(self) -> list[Finding]:
        return [f for f in self.findings if f.status == FAILED]

    def counts(self) -> dict[str, int]:
        return {status: sum(f.status == status for f in self.findings) for status in (VERIFIED, UNVERIFIED, FAILED)}


def row_digest(pairs_and_keys: list[tuple[Pair, str | None]]) -> str:
    """The digest of a row's records: each pair's job, scene, projection and record key
    (None for a pair without a record), in a fixed order."""
    return records.digest(sorted([p.job.name, p.scene, p.projected, key] for p, key in pairs_and_keys))


def rows_of(profile: Profile) -> dict[str, list[Pair]]:
    """The grid's pairs by row (`Pair.label`), in grid order."""
    rows: dict[str, list[Pair]] = {}
    for pair in evaluation_pairs(profile):
        rows.setdefault(pair.label, []).append(pair)
    return rows


def checked_scenes(pairs: list[Pair], scenes: str) -> list[str]:
    """The scenes a row is rolled out on again: every scene it is evaluated on (`all`),
    or the smallest (fewest coordinates; the first in grid order of those)."""
    names = list(dict.fromkeys(p.scene for p in pairs))
    if scenes == "all":
        return names
    return [min(names, key=lambda name: (get_scene(name).n_nodes * get_scene(name).dim, names.index(name)))]


def _record_key(layout: store.Layout, pair: Pair) -> str | None:
    """The key a pair's record carries (None: no record), checksum checked."""
    path = layout.found(layout.pair_record(pair))
    if not path.exists():
        return None
    _, meta = records.read(path)
    return meta.get("key")


def verify(profile: Profile, out: Path, conditions: int = CONDITIONS, scenes: str = "smallest", predictions=(),
           progress: bool = False, rows: tuple[str, ...] | None = None) -> Verification:
    """Check every row of the profile's grid under `out` (module docstring); `predictions`:
    predictions files of external rows, re-scored; `rows`: only these rows of the grid
    (labels), without the external rows and the summary (the folder's checks)."""
    grid = rows_of(profile)
    unknown = [row for row in rows or () if row not in grid]
    if unknown:
        raise ConfigError(f"no row {unknown[0]!r} in the {profile.name} profile's grid (rows: {', '.join(grid)})")
    if scenes not in SCENE_CHOICES:
        raise ConfigError(f"scenes must be one of {', '.join(SCENE_CHOICES)}, got {scenes!r}")
    if not (isinstance(conditions, int) and conditions >= 1):
        raise ConfigError(f"initial conditions must be a whole number >= 1, got {conditions!r}")
    out = Path(out)
    layout = store.layout(profile, out)
    truths = {}  # each checked scene's ground truth of its first initial conditions, shared by its rows
    findings = [_verify_row(profile, layout, label, pairs, conditions, scenes, truths, progress) for label, pairs in grid.items()
                if rows is None or label in rows]
    if rows is None:
        findings += _verify_externals(profile, out, predictions)
        findings.append(_verify_summary(profile, out))
    return Verification(tuple(f for f in findings if f is not None), conditions, scenes, partial=rows is not None)


def _verify_row(profile: Profile, layout: store.Layout, label: str, pairs: list[Pair], conditions: int, scenes: str, truths: dict,
                progress: bool) -> Finding:
    jobs = list(dict.fromkeys(p.job for p in pairs))
    found = {job: layout.found(layout.checkpoint(job)) for job in jobs}
    if not any(path.exists() for path in found.values()):
        return Finding(label, UNVERIFIED, "not trained here (no checkpoint of any seed): no number to verify", mark="no: not trained")
    metas = {}
    for job, path in found.items():
        if not path.exists():
            return Finding(label, FAILED, f"{job.name}: no checkpoint at {path}, while other seeds of the row have one", mark=FAILED)
        try:
            metas[job] = checkpoints.read(path)[0]
            checkpoints.model_config(path, metas[job])  # a model defined outside lgnn is named, never imported
        except CheckpointError as err:
            return Finding(label, FAILED, str(err), mark=FAILED)
    keys = []
    for pair in pairs:
        try:
            key = _record_key(layout, pair)
        except records.RecordError as err:
            return Finding(label, FAILED, str(err), mark=FAILED)
        expected = evaluate.pair_key(profile, pair, found[pair.job])
        if key is not None and key != expected:
            return Finding(label, FAILED, f"{pair.job.name} on {pair.scene}: its record {layout.found(layout.pair_record(pair))} was not made "
                                          "from this checkpoint with these settings (its key differs): an edited checkpoint or record, or a stale one",
                           mark=FAILED)
        keys.append((pair, key))
    digest = row_digest(keys)
    recorded = [pair for pair, key in keys if key is not None]
    if not recorded:
        return Finding(label, UNVERIFIED, "no evaluation record yet: no number to verify", digest=digest, mark="no: not evaluated")
    slim = [job.name for job, meta in metas.items() if not checkpoints.has_parameters(meta)]
    if slim:
        return Finding(label, UNVERIFIED, f"the checkpoints of {', '.join(slim)} are kept without their parameters: its numbers cannot be "
                                          "rolled out again from this folder", digest=digest, mark="no: parameters not kept")
    checked, largest = [], 0.0
    for scene_name in checked_scenes(recorded, scenes):
        for projected in dict.fromkeys(p.projected for p in recorded if p.scene == scene_name):
            group = [p for p in recorded if p.scene == scene_name and p.projected == projected]
            gap, problem = _rolled_out_again(profile, layout, group, found, conditions, truths, progress)
            if problem:
                return Finding(label, FAILED, problem, digest=digest, mark=FAILED)
            largest = max(largest, gap)
            checked += [(p.job.name, p.scene) for p in group]
    seeds = len({job for job, _ in checked})
    scenes_text = ", ".join(dict.fromkeys(scene for _, scene in checked))
    return Finding(label, VERIFIED, f"{len(recorded)} records keyed on their checkpoints; {seeds} seed(s) rolled out again on {scenes_text} "
                                    f"from {conditions} initial condition(s), every metric within {TOLERANCE:g} of the records "
                                    f"(the largest difference {largest:.1e})",
                   tuple(checked), digest, mark=f"yes ({scenes_text})")


def _rolled_out_again(profile: Profile, layout: store.Layout, group: list[Pair], found: dict, conditions: int, truths: dict,
                      progress: bool) -> tuple[float, str | None]:
    """`(largest difference, None)` if the pairs of `group` (one row's seeds on one scene,
    one projection) roll out again to their records' numbers (the largest |d ln| of any
    metric and initial condition), else `(nan, the one line that says where not)`."""
    scene_name = group[0].scene
    scene = get_scene(scene_name)
    count = min(conditions, truth_stage.evaluation_count(profile, scene))
    if scene_name not in truths:
        truths[scene_name] = truth_stage.first_ground_truth(profile, scene_name, count)
    truth = truths[scene_name]
    loaded = [checkpoints.load_model(found[pair.job]) for pair in group]
    model = loaded[0][0]
    runs = evaluate.stacked_rollouts(profile, model, [params for _, params in loaded], scene_name, group[0].projected, truth.states,
                                     f"verify {group[0].label} on {scene_name}", progress)
    largest = 0.0
    for pair, q, qd, energy in zip(group, runs.q, runs.qd, runs.energy):
        again = evaluate.pair_arrays(profile, scene_name, Trajectory(truth.truth.t, q, qd, energy), truth)
        arrays, _ = records.read(layout.found(layout.pair_record(pair)))
        for name in evaluate.pair_needs(profile):
            if name not in arrays:
                return math.nan, f"{pair.job.name} on {scene_name}: its record lacks {name}"
            recorded, derived = np.asarray(arrays[name])[:count], again[name]
            gap = np.abs(recorded - derived)
            if not (recorded.shape == derived.shape and np.all(gap <= TOLERANCE)):
                k = int(np.argmax(np.where(np.isnan(gap), np.inf, gap))) if recorded.shape == derived.shape else 0
                return math.nan, (f"{pair.job.name} on {scene_name}: {name.removesuffix('/per_ic_log')} of initial condition {k} is "
                                  f"{math.exp(recorded[k]):.6g} in the record, {math.exp(derived[k]):.6g} rolled out again")
            largest = max(largest, float(np.max(gap, initial=0.0)))
        log(f"verify {pair.label} s{pair.job.seed} on {scene_name}: {count} initial condition(s) agree")
    return largest, None


def _verify_externals(profile: Profile, out: Path, predictions) -> list[Finding]:
    """One finding per external row: re-scored from its predictions file where given,
    else unverified."""
    given = {}
    for path in predictions:
        read = external.read_predictions(profile, path)
        given[(read.model, read.scene)] = path
    rows: dict[str, list[Finding]] = {}
    keys: dict[str, list] = {}
    for pair, (arrays, meta) in external.load_externals(profile, out):
        keys.setdefault(pair.label, []).append((pair, meta.get("key")))
        model, scene_name = pair.job.model, pair.scene
        path = given.pop((model, scene_name), None)
        if path is None:
            problem, status = f"on {scene_name}: no predictions file given (--predictions) to score again", UNVERIFIED
        else:
            with tempfile.TemporaryDirectory() as scratch:
                again, _ = records.read(external.evaluate_external(profile, path, Path(scratch), progress=False))
            differs = [name for name in evaluate.pair_needs(profile)
                       if name in arrays and not np.allclose(arrays[name], again[name], rtol=0, atol=TOLERANCE, equal_nan=True)]
            problem, status = ((f"on {scene_name}: {differs[0]} differs from {path} scored again", FAILED) if differs
                               else (f"on {scene_name}: {path} scored again to the record", VERIFIED))
        rows.setdefault(pair.label, []).append(Finding(pair.label, status, problem))
    unused = [f"{model} on {scene}" for model, scene in given]
    if unused:
        raise ConfigError(f"predictions of {', '.join(unused)} answer no external record of this folder")
    findings = []
    for label, items in rows.items():
        worst = next((f for status in (FAILED, UNVERIFIED) for f in items if f.status == status), items[0])
        mark = {VERIFIED: "yes (scored again)", UNVERIFIED: "no: predictions not given", FAILED: FAILED}[worst.status]
        findings.append(Finding(label, worst.status, "; ".join(f.detail for f in items), digest=row_digest(keys[label]), mark=mark))
    return findings


def _verify_summary(profile: Profile, out: Path) -> Finding | None:
    """The committed summary against the statistics computed again from the records."""
    import pandas as pd

    from lgnn.bench.report.summary import SUMMARY, tables

    path = out / "benchmark" / SUMMARY
    if not path.exists():
        return None
    summary, _ = tables(evaluate.load_truths(profile, out), evaluate.load_pairs(profile, out) + external.load_externals(profile, out),
                        profile.evaluate.references)
    committed = pd.read_csv(path)
    index = ["scene", "model", "seed", "metric", "statistic"]
    if summary.empty:
        return Finding(FOLDER_ROW, FAILED, f"{path}: the folder has no records that match the profile, so nothing made its summary")
    again = summary.set_index(index)["value"]
    written = committed.set_index(index)["value"]
    missing, extra = again.index.difference(written.index), written.index.difference(again.index)
    if len(missing) or len(extra):
        where = (missing if len(missing) else extra)[0]
        return Finding(FOLDER_ROW, FAILED, f"{path}: row {_where(index, where)} is {'missing' if len(missing) else 'not made by any record'}")
    both = pd.concat([again.rename("again"), written.rename("written")], axis=1)
    gap = (both.again - both.written).abs() > SUMMARY_TOLERANCE * np.maximum(both.again.abs(), both.written.abs())
    gap &= ~(both.again.isna() & both.written.isna())
    if gap.any():
        where = both.index[gap.to_numpy()][0]
        row = both.loc[where]
        return Finding(FOLDER_ROW, FAILED, f"{path}: {_where(index, where)} is {float(row.written):.6g}, its records give {float(row.again):.6g}")
    return Finding(FOLDER_ROW, VERIFIED, f"{path}: its {len(both)} numbers are those its records give, to the 6 digits it keeps")


def _where(index: list[str], values: tuple) -> str:
    return ", ".join(f"{name} {value.item() if isinstance(value, np.generic) else value}" for name, value in zip(index, values))


def save(verification: Verification, out: Path, command: str | None = None, env: dict | None = None) -> Path:
    """Keep a verification as `<out>/benchmark/verification.json` (written whole), with
    the environment that made it (`env`, default this process's: take it before writing
    into a committed folder, or it names the commit dirty); one of some rows alone
    (`partial`) keeps the kept file's other rows. The command, environment and settings
    are the latest verification's."""
    from lgnn.provenance import environment

    path = Path(out) / "benchmark" / VERIFICATION
    rows = [dataclasses.asdict(f) for f in verification.findings]
    kept = load(out) if verification.partial else None
    if kept is not None:  # the rows not checked now keep their findings (their digests say whether they still hold)
        checked = {f.row for f in verification.findings}
        rows = [row for row in kept["rows"] if isinstance(row, dict) and row.get("row") not in checked] + rows
    text = json.dumps({"format": FORMAT, "command": command, "environment": env or environment(), "conditions": verification.conditions,
                       "scenes": verification.scenes, "tolerance": verification.tolerance, "rows": rows}, indent=1, default=list)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, text + "\n")
    return path


def current_digests(profile: Profile, out: Path) -> dict[str, str]:
    """Each row's `row_digest` of the records `out` holds now: the grid's rows and the
    external ones. A record that cannot be read gives its row no digest (no mark)."""
    layout = store.layout(profile, out)
    digests = {}
    for label, pairs in rows_of(profile).items():
        try:
            digests[label] = row_digest([(pair, _record_key(layout, pair)) for pair in pairs])
        except records.RecordError:
            continue
    keys: dict[str, list] = {}
    for pair, (_, meta) in external.load_externals(profile, out):
        keys.setdefault(pair.label, []).append((pair, meta.get("key")))
    return {**digests, **{label: row_digest(items) for label, items in keys.items()}}


def marks(profile: Profile, out: Path) -> tuple[dict | None, dict[str, str]]:
    """The kept verification of `out` (`load`) and LEADERBOARD.md's mark of each row it
    holds: its `Finding.mark` while the row's records are those it verified, else
    "no: records changed since"."""
    kept = load(out)
    if kept is None:
        return None, {}
    now = current_digests(profile, out)
    found = {}
    for row in kept["rows"]:
        if isinstance(row, dict) and isinstance(row.get("row"), str) and row["row"] in now:
            found[row["row"]] = str(row.get("mark", "")) if row.get("digest") == now[row["row"]] else "no: records changed since"
    return kept, found


def load(out: Path) -> dict | None:
    """The kept verification of `out` (`save`), or None where there is none or it cannot
    be read (the leaderboard then marks no row verified)."""
    path = Path(out) / "benchmark" / VERIFICATION
    try:
        kept = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if not (isinstance(kept, dict) and kept.get("format") == FORMAT and isinstance(kept.get("rows"), list)):
        return None
    return kept
