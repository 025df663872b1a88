"""`tools/upgrade_records.py`: records made before MuJoCo C's stale-frame fix lose their
MuJoCo-scored arrays (then recomputed by the evaluate stage); records of every frame
keep the curves' frames, and snapshots only where the report draws them; everything
else of a record is kept as it was."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from lgnn import records
from lgnn.bench import grid, profiles
from lgnn.bench.stages import evaluate
from lgnn.bench.stages import truth as truth_stage

ROOT = Path(__file__).resolve().parents[1]


def _tool():
    spec = importlib.util.spec_from_file_location("upgrade_records", ROOT / "tools" / "upgrade_records.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("scene, initial_conditions, version, stale", [
    ("chain4", 100, None, True), ("chain4", 100, truth_stage.REFERENCE_VERSION, False),
    ("chain4", 1, None, False), ("chain4-drag", 100, None, False),
])
def test_only_arrays_scored_against_a_stale_mujoco_reference_are_removed(tmp_path, scene, initial_conditions, version, stale):
    tool = _tool()
    arrays = {name: np.array([k], float) for k, name in enumerate(
        ("rollout_error/per_ic_log", "rollout_error_vs_mujoco/per_ic_log", "rest/rollout_error_vs_mujoco/gmean",
         "truth_vs_mujoco/per_ic_log", "snapshot/mujoco", "snapshot/truth", "node_rms_error/per_ic_log"))}
    meta = dict(scene=scene, initial_conditions=initial_conditions, key="k", **({} if version is None else {"mujoco_reference": version}))
    path = tmp_path / "benchmark" / "runs" / "lgnn-chain4-s0" / f"{scene}.npz"
    path.parent.mkdir(parents=True)
    environment = {"commit": "abc", "versions": "old", "device": "cpu"}
    records.save(path, arrays, meta, environment=environment)
    assert tool.upgrade(tmp_path, dry_run=True) == [path]
    assert set(records.read(path)[0]) == set(arrays), "a dry run writes nothing"
    assert tool.upgrade(tmp_path) == [path]
    kept, kept_meta = records.read(path)
    expected = {"rollout_error/per_ic_log", "snapshot/truth", "node_rms_error/per_ic_log"} if stale else set(arrays)
    # (chain4's snapshots go too: the report draws none of it.)
    assert set(kept) == expected - {"snapshot/mujoco", "snapshot/truth"} and kept_meta == {**meta, "environment": environment}
    assert tool.upgrade(tmp_path) == [], "a second run changes nothing"
    # The stage recomputes what was removed: the record lacks an array the metrics need.
    assert "rollout_error_vs_mujoco" in {m.name for m in evaluate.recorded_metrics(profiles.PROFILES["quick"].evaluate.references)}


@pytest.mark.parametrize("scene", ["chain8", "chain4"])
def test_records_keep_the_curves_and_snapshots_the_report_draws_and_nothing_else_changes(tmp_path, scene):
    from lgnn.bench.report import summary as report_summary

    tool = _tool()
    frame_dt, frames = 1e-3, 1000
    t = np.arange(1, frames + 1) * frame_dt
    rng = np.random.default_rng(0)
    arrays = {"t": t, "rollout_error/per_ic_log": rng.normal(size=100), "diverged_at": np.full(100, np.nan),
              "snapshot/model": rng.normal(size=(101, 5, 2)).astype(np.float32),
              **{f"rollout_error/{k}": rng.uniform(size=frames) for k in ("gmean", "low", "high")}}
    meta = dict(scene=scene, initial_conditions=100, key="k", mujoco_reference=truth_stage.REFERENCE_VERSION)
    path = tmp_path / "benchmark" / "runs" / "lgnn-chain4-s0" / f"{scene}.npz"
    path.parent.mkdir(parents=True)
    environment = {"commit": "abc", "versions": "old", "device": "cpu"}
    records.save(path, arrays, meta, environment=environment)
    drawn_before = report_summary._curve_rows("chain4", "lgnn", 0, "rollout_error", arrays, "rollout_error")
    assert tool.upgrade(tmp_path) == [path]
    kept, kept_meta = records.read(path)
    assert kept_meta == {**meta, "environment": environment}
    np.testing.assert_allclose(kept["t"], np.arange(1, 101) * evaluate.CURVE_DT, rtol=1e-12)
    np.testing.assert_array_equal(kept["rollout_error/gmean"], arrays["rollout_error/gmean"][9::10])
    for name in ("rollout_error/per_ic_log", "diverged_at"):
        np.testing.assert_array_equal(kept[name], arrays[name])
    # The report draws chain8's snapshots (grid.SNAPSHOT_SCENES), none of chain4.
    assert scene in grid.SNAPSHOT_SCENES and np.array_equal(kept["snapshot/model"], arrays["snapshot/model"]) or (
        scene not in grid.SNAPSHOT_SCENES and "snapshot/model" not in kept)
    assert report_summary._curve_rows("chain4", "lgnn", 0, "rollout_error", kept, "rollout_error") == drawn_before
    assert tool.upgrade(tmp_path) == [], "a second run changes nothing"
