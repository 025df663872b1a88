"""`OUT/benchmark/run.json`: each invocation of the benchmark appends what it cost and
where it ran, and the top level sums them and says when they disagree."""

import json
import os

import pytest

from lgnn import provenance
from lgnn.bench import run_record
from lgnn.bench.profiles import load_profile
from lgnn.bench.run import run
from lgnn.runtime import BENCHMARK_CHILD


def test_each_run_appends_its_stages_times_and_the_top_level_sums_them(tmp_path, tiny_benchmark_config):
    profile, out = load_profile(str(tiny_benchmark_config("gns", epochs=2))), tmp_path / "out"
    run(profile, out, progress=False, command="first")
    run(profile, out, stages=("evaluate", "report"), progress=False, command="second")  # resumes: reuses the records
    record = json.loads(run_record.path(out).read_text())
    first, second = record["invocations"]
    assert (first["command"], second["command"]) == ("first", "second")
    assert list(first["stages"]) == ["train", "evaluate"] and list(second["stages"]) == ["evaluate", "report"]
    for invocation in record["invocations"]:
        assert invocation["outcome"] == "completed" and invocation["commit"] == provenance.commit()
        # Each time is rounded to the millisecond, so the stages' sum may pass the wall time by half a millisecond each.
        assert 0 < sum(invocation["stages"].values()) <= invocation["wall_s"] + 5e-4 * len(invocation["stages"])
        assert invocation["started"] <= invocation["ended"]
    assert record["wall_s"] == pytest.approx(first["wall_s"] + second["wall_s"], abs=2e-3)
    assert record["stages"]["evaluate"] == pytest.approx(first["stages"]["evaluate"] + second["stages"]["evaluate"], abs=2e-3)
    assert (record["started"], record["ended"]) == (first["started"], second["ended"])
    assert (record["commit"], record["versions"], record["device"]) == (provenance.commit(), provenance.versions(), provenance.device())


def test_an_interrupted_invocation_is_recorded_as_such_and_a_changed_machine_reads_mixed(tmp_path, monkeypatch):
    with pytest.raises(KeyboardInterrupt):
        with run_record.recording(tmp_path, "lgnn benchmark") as timed:
            with timed("train"):
                raise KeyboardInterrupt
    monkeypatch.setattr(provenance, "device", lambda: "another machine")
    with run_record.recording(tmp_path, "lgnn benchmark") as timed:
        with timed("train"):
            pass
    record = run_record.read(tmp_path)
    assert [i["outcome"] for i in record["invocations"]] == ["interrupted", "completed"]
    assert record["device"].startswith("mixed: ") and record["device"].endswith("; another machine")
    assert set(record["stages"]) == {"train"}


def test_a_split_runs_child_processes_write_no_record(tmp_path, monkeypatch):
    monkeypatch.setenv(BENCHMARK_CHILD, "1")
    with run_record.recording(tmp_path, None) as timed:
        with timed("train"):
            pass
    assert not run_record.path(tmp_path).exists() and run_record.read(tmp_path) is None
    assert os.listdir(tmp_path) == []


def test_a_profile_that_disables_xla_optimisations_compiles_its_run_so_and_restores_the_setting(tmp_path, monkeypatch):
    """The quick profile compiles with most of XLA's passes off (its programs run for
    milliseconds); the full profile as the process has it; after the run the process's
    setting is what it was."""
    import dataclasses

    import jax

    from lgnn.bench import profiles
    from lgnn.bench import run as bench_run

    assert profiles.PROFILES["quick"].disable_xla_optimisations and not profiles.PROFILES["full"].disable_xla_optimisations
    seen = []
    monkeypatch.setattr(bench_run, "STAGES", dict(bench_run.STAGES))
    bench_run.register_stage(bench_run.Stage("look", lambda request: seen.append(jax.config.read("jax_disable_most_optimizations"))))
    before = jax.config.read("jax_disable_most_optimizations")
    jax.config.update("jax_disable_most_optimizations", False)
    try:
        for disable in (True, False):
            profile = dataclasses.replace(profiles.PROFILES["quick"], disable_xla_optimisations=disable)
            bench_run.run(profile, tmp_path / str(disable), stages=("look",), progress=False)
            assert jax.config.read("jax_disable_most_optimizations") is False
    finally:
        jax.config.update("jax_disable_most_optimizations", before)
    assert seen == [True, False]
