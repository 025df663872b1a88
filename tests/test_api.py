"""The Python API: safe by default (float64 without any set-up), every public name
resolves, and the README's Python example runs as written."""

import re
import subprocess
import sys
from pathlib import Path

import lgnn

README = Path(__file__).resolve().parents[1] / "README.md"


def readme_python_example() -> str:
    section = README.read_text().split("## From Python", 1)[1]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_public_names_resolve():
    for name in lgnn.__all__:
        assert getattr(lgnn, name) is not None, name


def test_readme_example_is_float64_without_configure():
    """In a fresh process that never calls `lgnn.configure()` (JAX's default float32),
    the README example's ground truth is float64 and conserves energy to round-off
    (float32 drifted it by 7.8e-5 over 1 s), and JAX's global setting is untouched."""
    script = readme_python_example() + "\nimport jax\nprint('global-x64', jax.config.jax_enable_x64)\n"
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert "float64" in lines[0]
    drift = float(re.search(r"energy drift (\S+)", out.stdout).group(1))
    distance = float(re.search(r"distance to MuJoCo (\S+)", out.stdout).group(1))
    assert drift < 1e-10 and distance < 1e-9, out.stdout
    assert lines[-1] == "global-x64 False"



def test_caches_go_to_the_user_cache_not_the_working_directory(monkeypatch, tmp_path):
    from lgnn.files import user_cache_dir
    from lgnn.learn.data import default_cache_dir

    monkeypatch.delenv("LGNN_CACHE", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert default_cache_dir() == tmp_path / "xdg" / "lgnn" / "datasets"
    monkeypatch.setenv("LGNN_CACHE", str(tmp_path / "mine"))
    assert user_cache_dir() == tmp_path / "mine"
    monkeypatch.delenv("LGNN_CACHE")
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert user_cache_dir() == Path.home() / ".cache" / "lgnn"


def test_the_notebook_api_reads_results_as_frames_and_runs_the_benchmark(tmp_path):
    """`lgnn.load_results` gives the committed summary as a DataFrame (the README's
    headline cell in it), `lgnn.benchmark` runs a stage as `lgnn benchmark` does, and
    bad input is one `ConfigError`."""
    import pytest

    summary = lgnn.load_results(README.parent / "results")
    cell = summary[(summary.scene == "chain4") & (summary.model == "lgnn-notebook") & (summary.seed == -1)
                   & (summary.metric == "rollout_error") & (summary.statistic == "gmean")]
    assert f"{cell.value.item():.2e}" in README.read_text()
    with pytest.raises(lgnn.ConfigError, match="no such results table"):
        lgnn.load_results(tmp_path)
    with pytest.raises(lgnn.ConfigError, match="unknown results table"):
        lgnn.load_results(tmp_path, "everything")
    out = lgnn.benchmark("quick", tmp_path / "quick", stages=["report"], settings=["seeds=[0]"])
    assert (out / "README.md").exists() and (out / "LEADERBOARD.md").exists()
    assert lgnn.load_results(out).empty
