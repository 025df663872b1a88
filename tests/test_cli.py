"""The command line: outputs, and one clear line for every bad input."""

import json

import numpy as np
import pytest

from lgnn.cli import main
from lgnn.scene import BUILTIN_SCENES
from lgnn.engines.lagrangian import Trajectory


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_scenes_lists_every_builtin(capsys):
    code, out, _ = run(capsys, "scenes")
    assert code == 0
    for name in BUILTIN_SCENES:
        assert name in out


def test_closed_output_pipe_is_quiet():
    """`lgnn scenes | head -0`: the reader is gone before lgnn writes; no traceback."""
    import os
    import subprocess
    import sys

    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        result = subprocess.run([sys.executable, "-m", "lgnn.cli", "scenes"], stdout=write_end, stderr=subprocess.PIPE, timeout=120)
    finally:
        os.close(write_end)
    stderr = result.stderr.decode()
    assert result.returncode == 141 and "Traceback" not in stderr, stderr


def test_scene_export_round_trips_through_simulate(capsys, tmp_path):
    path = tmp_path / "chain4.json"
    code, _, _ = run(capsys, "scene", "export", "chain4", "--out", str(path))
    assert code == 0
    assert json.loads(path.read_text())["name"] == "chain4"
    out = tmp_path / "traj.npz"
    code, stdout, _ = run(capsys, "simulate", str(path), "--duration", "0.05", "--dt", "1e-3", "--frame-dt", "1e-2", "--out", str(out), "--quiet")
    assert code == 0 and "wrote" in stdout
    trajectory = Trajectory.load(out)
    assert trajectory.t.shape == (6,) and trajectory.q.shape == (6, 5, 2) and trajectory.qd.shape == (6, 5, 2)
    assert trajectory.energy.shape == (6,)
    np.testing.assert_allclose(trajectory.t, np.arange(6) * 1e-2)
    with np.load(out) as data:
        assert {"t", "q", "qd", "energy"} <= set(data.files)


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["simulate", "chain5", "--out", "{tmp}/x.npz"], "unknown scene 'chain5'"),
        (["simulate", "chain4", "--dt", "3e-4", "--out", "{tmp}/x.npz"], "not a whole multiple of dt"),
        (["simulate", "chain4", "--duration", "0.0015", "--out", "{tmp}/x.npz"], "duration"),
        (["simulate", "chain4", "--out", "{tmp}/missing/x.npz"], "output directory does not exist"),
        (["simulate", "chain4", "--out", "{tmp}"], "is a directory"),
        (["simulate", "{tmp}/nope.json", "--out", "{tmp}/x.npz"], "no such scene file"),
        (["scene", "export", "nope"], "unknown built-in scene"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(capsys, tmp_path, argv, words):
    code, _, err = run(capsys, *[a.format(tmp=tmp_path) for a in argv])
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("lgnn: error:") and words in lines[0], err
    assert not (tmp_path / "x.npz").exists()


@pytest.mark.parametrize("value", ["-1", "0", "nan", "abc"])
def test_invalid_numbers_are_rejected_by_the_parser(capsys, value):
    with pytest.raises(SystemExit) as info:
        main(["simulate", "chain4", "--dt", value, "--out", "x.npz"])
    assert info.value.code == 2
    assert "--dt" in capsys.readouterr().err


def test_simulation_failure_leaves_no_file(capsys, tmp_path):
    """A diverging run (chain4 with a huge step) reports when it diverged and writes nothing."""
    out = tmp_path / "x.npz"
    code, _, err = run(capsys, "simulate", "chain16", "--dt", "0.1", "--frame-dt", "0.1", "--duration", "20", "--no-project", "--out", str(out), "--quiet")
    if code == 0:  # it may survive; then the file must be complete
        assert Trajectory.load(out).q.shape[0] == 201
    else:
        assert code == 2 and ("non-finite" in err or "exploded" in err) and "t =" in err
        assert not out.exists() and not list(tmp_path.iterdir())


def test_crosscheck_of_a_scene_file_writes_beside_the_user_and_summarises(capsys, tmp_path, monkeypatch):
    """Not told where to write, a report goes to ./lgnn-out (never the repository's
    results/), the console shows each engine's lines for a scene file too (they are
    filtered on the scene's name, not the path) and says where it wrote; a `|` inside a
    markdown cell is escaped, so every table row keeps its columns."""
    import re

    from lgnn.scene import get_scene, scene_to_json

    monkeypatch.chdir(tmp_path)
    scene_file = tmp_path / "mine.json"
    scene_file.write_text(scene_to_json(get_scene("chain4")).replace('"chain4"', '"mine"'))
    code, out, err = run(capsys, "crosscheck", str(scene_file), "--engines", "lagrangian,mujoco", "--dt", "1e-3", "--frame-dt", "1e-2", "--duration", "0.02")
    assert code == 0, err
    assert "mine     lagrangian" in out and "lagrangian~mujoco" in out
    assert "wrote lgnn-out/crosscheck.csv" in out
    table = [line for line in (tmp_path / "lgnn-out" / "crosscheck.md").read_text().splitlines() if line.startswith("| ")]
    assert len(table) > 2 and any("\\|E-E0\\|" in line for line in table)
    assert {len(re.findall(r"(?<!\\)\|", line)) for line in table} == {6}  # 5 columns
