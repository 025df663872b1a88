"""`lgnn gpu-truth` (`lgnn.bench.gpu_truth`) small on the CPU: the table's rows, the
float32 engines really in float32, and non-finite runs said plainly.

The GPU runs themselves are made on a lent machine (results/gpu/truth/README.md has the commands); here
chain4 and chain4-3d, 2 worlds, 10 steps, with the engines this machine has (MJX is left out for its
~35 s CPU compile, tested in test_mujoco.py; MuJoCo Warp only where installed).
"""

import csv
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lgnn import physics
from lgnn.bench import gpu_truth
from lgnn.bench.report import performance as report_performance
from lgnn.bench.profiles import get_profile
from lgnn.bench.tables import write_table
from lgnn.cli import main
from lgnn.engines import mjwarp
from lgnn.engines.base import SimulationConfig
from lgnn.engines.lagrangian import rollout_fn
from lgnn.errors import ConfigError
from lgnn.scene import get_scene


def read_rows(path):
    with open(path) as handle:
        return list(csv.DictReader(line for line in handle if not line.startswith("#")))


def test_float32_lagrangian_program_holds_no_float64():
    """With x64 on (as every entry point runs), a rollout traced from float32 states is
    float32 throughout: the lowered program names no f64 type (it would if a float64
    constant promoted the state)."""
    scene = get_scene("T1")  # loops: the constrained solve and projection are in it
    run = jax.jit(jax.vmap(rollout_fn(scene, SimulationConfig(dt=1e-3, frame_dt=1e-2, duration=1e-2), physics.vectorised_true_acceleration_fn)))
    shape = jax.ShapeDtypeStruct((2, scene.n_nodes, 2), jnp.float32)
    text = run.lower(shape, shape).as_text()
    assert "f32" in text and "f64" not in text


@pytest.mark.parametrize("scene", ["chain4", "chain4-3d"])
def test_small_cpu_run_writes_the_table(tmp_path, scene):
    """chain4 (and the 3D chain: ball joints in MuJoCo Warp), 2 worlds, 10 RK4 steps: a
    row per engine with speed, compile and the error against float64; float32 is ~1e-7
    from it (not 1e-14: it is float32)."""
    engines = ["lagrangian:float32"] + (["mjwarp:float32"] if mjwarp.available() else [])
    code = main(["gpu-truth", "--scenes", scene, "--batches", "2", "--steps", "10", "--repeats", "2",
                 "--engines", *engines, "--out", str(tmp_path), "--quiet"])
    assert code == 0
    rows = read_rows(tmp_path / f"gpu_truth_{scene}.csv")
    assert [(r["engine"], r["dtype"]) for r in rows] == [("lagrangian", "float64")] + [tuple(e.split(":")) for e in engines]
    for row in rows:
        assert float(row["steps_per_s_min"]) <= float(row["steps_per_s"]) <= float(row["steps_per_s_max"])
        assert float(row["compile_s"]) > 0 and row["finite_worlds"] == "2" and row["steps"] == "10"
    assert float(rows[0]["max_node_error"]) == 0 and rows[0]["note"] == "reference"
    for row in rows[1:]:
        assert 1e-9 < float(row["max_node_error"]) < 1e-5, row
    markdown = (tmp_path / f"gpu_truth_{scene}.md").read_text()
    assert "commit: " in markdown and "machine: " in markdown and "mujoco" in markdown


def test_non_finite_worlds_are_said_plainly(monkeypatch):
    """An engine whose world goes non-finite gets NaN error and a note counting the
    worlds, never an error computed from the finite ones."""
    final = np.zeros((3, 5, 2))

    def fake_run(spec, scene, config, states, settings):
        q = final.copy()
        if spec != gpu_truth.reference_spec():
            q[1, 2, 0] = np.nan
        return 0.5, [1.0, 2.0], q

    monkeypatch.setattr(gpu_truth, "_run", fake_run)
    settings = gpu_truth.GpuTruthSettings(scenes=("chain4",), batches=(3,), engines=("mjx:float32",), steps=4)
    reference, row = gpu_truth.measure(get_scene("chain4"), settings, log=lambda line: None)
    assert reference["max_node_error"] == 0 and reference["finite_worlds"] == 3
    assert np.isnan(row["max_node_error"]) and row["finite_worlds"] == 2 and row["note"] == "non-finite in 1 of 3 worlds"
    # Speeds of the runs: 12 and 6 steps/s; the median of two is their mean.
    assert row["steps_per_s"] == pytest.approx(9) and row["steps_per_s_min"] == 6 and row["steps_per_s_max"] == 12


def test_an_mjx_that_cannot_be_imported_is_a_row_note(monkeypatch, tmp_path):
    """MJX installed without its own dependencies (on a lent GPU, wheels without
    `trimesh`) raised an ImportError out of `lgnn gpu-truth`: it is the row's note, and
    the other engines' rows are still written."""
    import sys

    from lgnn.engines import mjx

    import mujoco

    mjx._mjx.cache_clear()
    # `from mujoco import mjx` raises ImportError, also where MJX was imported before in
    # this process (the package then holds it as an attribute).
    monkeypatch.setitem(sys.modules, "mujoco.mjx", None)
    monkeypatch.delattr(mujoco, "mjx", raising=False)
    try:
        code = main(["gpu-truth", "--scenes", "chain4", "--batches", "2", "--steps", "2", "--repeats", "1",
                     "--engines", "lagrangian:float32", "mjx:float32", "--out", str(tmp_path), "--quiet"])
    finally:
        mjx._mjx.cache_clear()
    assert code == 0
    rows = read_rows(tmp_path / "gpu_truth_chain4.csv")
    assert [r["engine"] for r in rows] == ["lagrangian", "lagrangian", "mjx"]
    assert rows[2]["note"].startswith("not run: the mjx engine cannot import MuJoCo MJX") and rows[1]["note"] == ""


@pytest.mark.parametrize("spec", ["mjwarp:float64", "bullet:float32", "lagrangian"])
def test_bad_engine_is_one_line(spec, tmp_path, capsys):
    assert main(["gpu-truth", "--scenes", "chain4", "--engines", spec, "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lgnn: error: ") and err.count("\n") == 1 and not list(tmp_path.iterdir())


@pytest.mark.parametrize("option, value, named", [("--form", "weird", "--form"), ("--suffix", "/../x", "--suffix"),
                                                  ("--suffix", "a/b", "--suffix")])
def test_bad_form_or_suffix_is_refused_before_any_run(option, value, named, tmp_path, capsys):
    """A bad `--form` was found by the first MuJoCo engine, after the Lagrangian runs of
    the first batch (minutes on a CPU at the default batches); a suffix with a folder in
    it wrote outside `--out`. Both are one line before anything runs."""
    try:
        code = main(["gpu-truth", "--scenes", "chain4", option, value, "--out", str(tmp_path)])
    except SystemExit as exit:  # argparse's own checks end the parse
        code = exit.code
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("lgnn: error: ") and named in err and err.count("\n") == 1 and not list(tmp_path.iterdir())


def test_a_cut_run_resumes_with_the_scenes_it_had_not_written(tmp_path, monkeypatch, capsys):
    """A command cut by a time limit after chain4's table, run again, keeps that table and
    measures chain8; other settings, other engines or `--fresh` measure chain4 again."""
    def argv(*extra, scenes=("chain4",), steps="2", engines=("lagrangian:float32",)):
        return ["gpu-truth", "--scenes", *scenes, "--batches", "2", "--steps", steps, "--repeats", "1", "--engines", *engines,
                "--out", str(tmp_path), "--quiet", *extra]

    assert main(argv()) == 0
    table = (tmp_path / "gpu_truth_chain4.csv").read_text()
    measured = []
    real = gpu_truth.measure
    monkeypatch.setattr(gpu_truth, "measure", lambda scene, *args, **kwargs: measured.append(scene.name) or real(scene, *args, **kwargs))
    capsys.readouterr()
    assert main(argv(scenes=("chain4", "chain8"))) == 0
    assert measured == ["chain8"] and (tmp_path / "gpu_truth_chain4.csv").read_text() == table
    assert "kept " in capsys.readouterr().out
    for changed in (argv("--fresh"), argv(steps="3")):
        measured.clear()
        assert main(changed) == 0 and measured == ["chain4"], changed
    # The table now holds 3 steps of lagrangian:float32 at batch 2: only that run is kept.
    same = gpu_truth.GpuTruthSettings(scenes=("chain4",), batches=(2,), engines=("lagrangian:float32",), steps=3, repeats=1)
    assert gpu_truth.measured_before(tmp_path, "chain4", same)
    for other in (dict(engines=("lagrangian:float32", "mjx:float32")), dict(batches=(2, 4)), dict(repeats=2), dict(form="maximal")):
        assert not gpu_truth.measured_before(tmp_path, "chain4", dataclasses.replace(same, **other)), other
    # A table that does not parse (or lacks its markdown twin) is measured again.
    (tmp_path / "gpu_truth_chain4.csv").write_text("scene\nnot a table")
    assert not gpu_truth.measured_before(tmp_path, "chain4", gpu_truth.GpuTruthSettings(scenes=("chain4",), batches=(2,)))
    (tmp_path / "gpu_truth_chain8.md").unlink()
    measured.clear()
    assert main(argv(scenes=("chain8",))) == 0 and measured == ["chain8"]


def test_settings_refuse_an_unknown_form():
    with pytest.raises(ConfigError, match="unknown MJCF form 'weird'"):
        gpu_truth.GpuTruthSettings(form="weird")


def write_gpu_table(directory, name, rows, machine="1x Test GPU (gpu); CPU: test x2"):
    """A gpu-truth table as `gpu_truth.write` lays it out (header lines, then COLUMNS)."""
    defaults = dict(scene="chain4", dtype="float32", form="", steps=100, steps_per_s_min=0.0, steps_per_s_max=0.0, compile_s=1.0, note="")
    full = [{**defaults, **row} for row in rows]
    for row in full:
        row.setdefault("finite_worlds", row["batch"])
    write_table(full, gpu_truth.COLUMNS, directory / f"gpu_truth_{name}.csv", directory / f"gpu_truth_{name}.md", name,
                ["command: test", f"machine: {machine}"])


def test_performance_reads_the_gpu_truth_tables(tmp_path):
    """The report's GPU-truth section: per scene and batch the float32 Lagrangian against
    the fastest MuJoCo GPU engine that is finite in every world and agrees with the
    reference, the Lagrangian row taken from that engine's own run where it has one, and
    no ratio where MuJoCo has no such run."""
    truth = tmp_path / "gpu" / "truth"
    truth.mkdir(parents=True)
    nan = float("nan")
    write_gpu_table(truth, "chain4", [
        dict(engine="lagrangian", dtype="float64", batch=8, steps_per_s=1e6, max_node_error=0.0, note="reference"),
        dict(engine="lagrangian", batch=8, steps_per_s=9e6, max_node_error=2e-6),
        dict(engine="lagrangian", batch=64, steps_per_s=5e7, max_node_error=3e-6),
    ], machine="1x Older GPU (gpu); CPU: test x2")
    write_gpu_table(truth, "chain4_mujoco", [
        dict(engine="lagrangian", batch=8, steps_per_s=3e6, max_node_error=2e-6),
        dict(engine="mjx", form="maximal", batch=8, steps_per_s=1e6, max_node_error=1e-5),
        # Faster but non-finite in one world: never the comparison.
        dict(engine="mjwarp", form="nested", batch=8, steps_per_s=9e9, max_node_error=nan, finite_worlds=7, note="non-finite in 1 of 8 worlds"),
        dict(engine="mjwarp", form="maximal", batch=64, steps_per_s=nan, max_node_error=nan, finite_worlds=0, note="not run: out of device memory"),
        # Faster and finite, but 15 m off (MuJoCo Warp on an ill-conditioned chain): not a ground truth.
        dict(engine="mjwarp", form="maximal", batch=8, steps_per_s=8e9, max_node_error=15.0),
    ])
    rows = gpu_truth.against_mujoco(gpu_truth.load(truth))
    assert [(r["scene"], r["batch"]) for r in rows] == [("chain4", 8), ("chain4", 64)]
    small, large = rows
    # The Lagrangian's 3e6 of the MJX run's own table, not the 9e6 of another run.
    assert small["mujoco_engine"] == "mjx float32 maximal" and small["ratio"] == pytest.approx(3.0) and small["meets_goal"]
    assert small["tables"] == "gpu_truth_chain4_mujoco" and "mjwarp nested: non-finite in 1 of 8 worlds" in small["note"]
    assert "mjwarp maximal: 15 from the reference" in small["note"]
    assert np.isnan(large["ratio"]) and not large["meets_goal"] and "out of device memory" in large["note"]
    # Each comparison names the GPU of the run(s) it is made of, read from the tables' headers.
    assert small["machine"] == "1x Test GPU (gpu)" and large["machine"] == "1x Older GPU (gpu)"
    text = report_performance.performance_markdown(get_profile("full"), [], None, tmp_path)
    section = text.split("## Ground truth on GPUs against MuJoCo's GPU engines")[1]
    assert "| chain4 | 8 | 3.00e+06 | 2.00e-06 | mjx float32 maximal | 1.00e+06 | 1.00e-05 | 3 | yes |" in section
    assert "| chain4 | 64 | 5.00e+07 |" in section and "| — | — |" in section
    assert "| gpu_truth_chain4_mujoco | 1x Test GPU (gpu) |" in section


def test_gpu_truth_reader_refuses_other_tables(tmp_path):
    (tmp_path / "gpu_truth_x.csv").write_text("scene,engine\nchain4,mjx\n")
    with pytest.raises(ConfigError, match="not a gpu-truth table"):
        gpu_truth.load(tmp_path)


@pytest.mark.parametrize("scene_name", ["chain16", "T1", "T2"])
def test_float32_ground_truth_has_full_precision_matrix_products(scene_name):
    """Every matrix product of the ground truth's accelerations (the chain, Schur and
    generic solvers) is lowered at precision HIGHEST, so a GPU does not compute it in
    TF32 (T1 on an H100: 7.4e-5 from float64 with TF32, 5.9e-7 without)."""
    import re

    import jax
    import jax.numpy as jnp

    from lgnn import physics
    from lgnn.scene import get_scene

    scene = get_scene(scene_name)
    q, qd = (jnp.asarray(a, jnp.float32) for a in scene.initial_state)
    text = jax.jit(physics.true_acceleration_fn(scene)).lower(q, qd).as_text()
    products = re.findall(r"stablehlo\.dot_general[^\n]*", text)
    assert products and all("HIGHEST" in p for p in products)
    plain = jax.jit(lambda a: a @ a).lower(jnp.ones((3, 3), jnp.float32)).as_text()
    assert "HIGHEST" not in plain  # the default, which the solvers must not keep
