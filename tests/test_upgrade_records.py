"""`tools/upgrade_records.py`: records made before MuJoCo C's stale-frame fix lose their
MuJoCo-scored arrays (then recomputed by the evaluate stage), everything else of them
and every sound record is kept as it was."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from lgnn import records
from lgnn.bench import grid
from lgnn.bench.stages import evaluate

ROOT = Path(__file__).resolve().parents[1]


def _tool():
    spec = importlib.util.spec_from_file_location("upgrade_records", ROOT / "tools" / "upgrade_records.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("scene, initial_conditions, version, stale", [
    ("chain4", 100, None, True), ("chain4", 100, evaluate.REFERENCE_VERSION, False),
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
    assert tool.upgrade(tmp_path, dry_run=True) == ([path] if stale else [])
    assert set(records.read(path)[0]) == set(arrays), "a dry run writes nothing"
    assert tool.upgrade(tmp_path) == ([path] if stale else [])
    kept, kept_meta = records.read(path)
    expected = {"rollout_error/per_ic_log", "snapshot/truth", "node_rms_error/per_ic_log"} if stale else set(arrays)
    assert set(kept) == expected and kept_meta == {**meta, "environment": environment}
    assert tool.upgrade(tmp_path) == [], "a second run changes nothing"
    # The stage recomputes what was removed: the record lacks an array the metrics need.
    assert "rollout_error_vs_mujoco" in {m.name for m in evaluate.recorded_metrics(grid.PROFILES["quick"].evaluate.references)}
