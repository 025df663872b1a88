"""The engine registry is the only place that names an engine (issue 62): an engine
registered here, with no other edit, enters the benchmark's speed stage, `lgnn
crosscheck`'s default engines and `lgnn gpu-truth`, as its `EngineEntry` flags say; the
report titles the built-ins as before.

The engine is a thin wrapper of the Lagrangian engine (so it agrees with the reference
to round-off), with no `timed_batch` of its own: gpu-truth times it through the
`Engine` default built on `timed_rollout`. chain4, a few steps; MJX is left out (its
~35 s CPU compile) by the quick profile's `mjx = false` and `mjx_max_depth=0`.
"""

import dataclasses
import json
from typing import ClassVar

import numpy as np
import pytest

from lgnn.bench import crosscheck, gpu_truth, profiles
from lgnn.bench.report import summary
from lgnn.bench.stages import speed
from lgnn.cli import build_parser
from lgnn.engines import ENGINES, Engine, EngineEntry, register_engine
from lgnn.engines.base import SimulationConfig
from lgnn.engines.lagrangian import LagrangianEngine
from lgnn.errors import ConfigError
from lgnn.scene import get_scene

NAME = "test-engine"


@dataclasses.dataclass(frozen=True)
class WrappedLagrangian(Engine):
    """The Lagrangian engine behind another name: rollout and timing are its."""

    name: ClassVar[str] = NAME
    dtype: str = "float64"

    def rollout(self, scene, config, states):
        return LagrangianEngine(dtype=self.dtype).rollout(scene, config, states)

    def timed_rollout(self, scene, config, states):
        return LagrangianEngine(dtype=self.dtype).timed_rollout(scene, config, states)


ENTRY = EngineEntry(NAME, lambda dtype, progress, form, integration: WrappedLagrangian(dtype), ("float64", "float32"),
                    title="the test engine", cpu_ground_truth=True, compiled=True, in_speed_table=True, gpu_truth_role="timed")


@pytest.fixture
def test_engine():
    register_engine(ENTRY)
    try:
        yield ENTRY
    finally:
        ENGINES.pop(NAME, None)


def test_the_speed_stage_times_a_registered_engine_and_remeasures_a_record_without_it(test_engine, tmp_path):
    """Its rows follow the built-ins' (registry order); a record made before it was
    registered (same key) lacks its rows and is measured again."""
    quick = profiles.PROFILES["quick"]
    profile = dataclasses.replace(quick, speed=dataclasses.replace(quick.speed, scenes=("chain4",), models=(), repeats=2))

    def engine_rows():
        return [r for r in json.loads(speed.speed_error(profile, "chain4", tmp_path).read_text())["rows"] if r["kind"] == "engine"]

    ENGINES.pop(NAME)
    before = engine_rows()
    register_engine(test_engine)
    after = engine_rows()
    assert [r["solver"] for r in before] == ["lagrangian", "mujoco", "mjx"]
    assert [r["solver"] for r in after] == ["lagrangian", "mujoco", "mjx", NAME]
    ours = after[-1]
    assert ours["runs"] == 2 and ours["note"] == "" and ours["form"] == ""
    assert ours["rollout_error"] == pytest.approx(after[0]["rollout_error"], rel=1e-6)
    assert after[2]["note"] == "not run in this profile"  # the quick profile's mjx = false


def test_crosscheck_compares_a_registered_cpu_ground_truth_by_default(test_engine, capsys):
    assert crosscheck.default_engines() == ("lagrangian", "mujoco", "mjx", NAME)
    assert build_parser().parse_args(["crosscheck"]).engines == f"lagrangian,mujoco,mjx,{NAME}"
    config = SimulationConfig(dt=1e-3, frame_dt=1e-2, duration=0.02)
    rows = crosscheck.crosscheck(get_scene("chain4"), config, crosscheck.default_engines(), mjx_max_depth=0)
    ours = {r["metric"]: r for r in rows if r["engine"] == NAME}
    assert set(ours) == {"energy_drift", "constraint_violation", "wall_s"} and ours["wall_s"]["note"] == "incl. compile"
    (mjx,) = [r for r in rows if r["engine"] == "mjx"]
    assert mjx["metric"] == "skipped" and mjx["note"].startswith("skipped: MJX compile too slow on CPU (tree depth ")
    pair = next(r for r in rows if r["engine"] == f"lagrangian~{NAME}")
    assert pair["form"] == "-~-" and pair["value"] < 1e-12
    assert [r["engine"] for r in rows if r["metric"] == "max_node_error"] == ["lagrangian~mujoco", f"lagrangian~{NAME}", f"mujoco~{NAME}"]


def test_gpu_truth_runs_a_registered_engine_through_the_default_timed_batch(test_engine):
    assert f"{NAME}:float32" in gpu_truth.GpuTruthSettings().engines
    assert gpu_truth.GpuTruthSettings().engines[:3] == ("lagrangian:float32", "mjx:float32", "mjwarp:float32")
    settings = gpu_truth.GpuTruthSettings(scenes=("chain4",), batches=(2,), engines=(f"{NAME}:float32",), steps=5, repeats=2)
    reference, ours = gpu_truth.measure(get_scene("chain4"), settings, log=lambda line: None)
    assert (reference["engine"], reference["dtype"], reference["note"]) == ("lagrangian", "float64", "reference")
    assert (ours["engine"], ours["dtype"], ours["form"], ours["finite_worlds"]) == (NAME, "float32", "", 2)
    assert 1e-9 < ours["max_node_error"] < 1e-5 and ours["steps_per_s_min"] <= ours["steps_per_s"] <= ours["steps_per_s_max"]
    # The checks of an engine spec read the registry, with the messages they had.
    with pytest.raises(ConfigError, match=r"^--engines: MuJoCo Warp computes in float32 only \(mjwarp:float32\)$"):
        gpu_truth.GpuTruthSettings(engines=("mjwarp:float64",))
    with pytest.raises(ConfigError, match=f"with name in lagrangian, mjx, mjwarp, {NAME} and dtype float32 or float64$"):
        gpu_truth.GpuTruthSettings(engines=("bullet:float32",))


def test_the_default_timed_batch_is_repeated_timed_rollouts(test_engine):
    scene = get_scene("chain4")
    states = gpu_truth.physics.benchmark_initial_states(scene, 2, 0)
    config = SimulationConfig(dt=1e-3, frame_dt=5e-3, duration=5e-3)
    compile_s, run_s, q = WrappedLagrangian().timed_batch(scene, config, states, repeats=3)
    assert compile_s > 0 and len(run_s) == 3 and q.shape == (2, scene.n_nodes, scene.dim)
    np.testing.assert_allclose(q, LagrangianEngine().rollout(scene, config, states).q[:, -1], atol=1e-12)


def test_the_report_titles_engines_from_the_registry(test_engine):
    assert [summary.engine_title(name) for name in ("lagrangian", "mujoco", "mjx", "mjwarp", NAME, "unregistered")] == [
        "the Lagrangian engine", "MuJoCo", "MJX", "MuJoCo Warp", "the test engine", "unregistered"]
    with pytest.raises(ConfigError, match="gpu_truth_role"):
        dataclasses.replace(test_engine, gpu_truth_role="judge")
