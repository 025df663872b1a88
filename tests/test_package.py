"""lgnn as a package others depend on: `python -m build` makes a wheel and an sdist from
the project's sources alone, and the wheel installed into a clean virtual environment
runs `lgnn scenes` and `lgnn simulate chain4` with its package data and without the
checkout."""

import shutil
import subprocess
import sys
import venv
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
# What the build reads: the package, its metadata and the files the metadata names.
SOURCES = ("lgnn", "pyproject.toml", "README.md", "LICENSE", "CITATION.cff")


@pytest.mark.slow
def test_the_wheel_installs_into_a_clean_environment_and_runs_without_the_checkout(tmp_path):
    pytest.importorskip("build", reason="the test extra's build package")
    source = tmp_path / "source"
    source.mkdir()
    for name in SOURCES:
        copy = shutil.copytree if (ROOT / name).is_dir() else shutil.copy2
        copy(ROOT / name, source / name, **({"ignore": shutil.ignore_patterns("__pycache__")} if (ROOT / name).is_dir() else {}))
    dist = tmp_path / "dist"
    # Without isolation: the build's setuptools is this environment's (the test extra's), no download.
    built = subprocess.run([sys.executable, "-m", "build", "--no-isolation", "--outdir", str(dist), str(source)], capture_output=True, text=True,
                           timeout=300)
    assert built.returncode == 0, built.stdout[-2000:] + built.stderr[-2000:]
    wheels, sdists = sorted(dist.glob("lgnn-*.whl")), sorted(dist.glob("lgnn-*.tar.gz"))
    assert len(wheels) == 1 and len(sdists) == 1, sorted(p.name for p in dist.iterdir())

    # A clean environment holding the wheel alone; its dependencies (jax, MuJoCo, ...)
    # are this environment's, seen through a .pth file rather than installed again.
    clean = tmp_path / "clean"
    venv.EnvBuilder(with_pip=False).create(clean)
    python = clean / "bin" / "python"
    site = Path(subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], capture_output=True, text=True,
                               check=True).stdout.strip())
    installed = subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps", "--no-index", "--quiet", str(wheels[0])],
                               capture_output=True, text=True, timeout=300)
    assert installed.returncode == 0, installed.stderr[-2000:]
    ours = Path(subprocess.run([sys.executable, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], capture_output=True, text=True,
                               check=True).stdout.strip())
    (site / "dependencies.pth").write_text(f"{ours}\n")

    work = tmp_path / "elsewhere"
    work.mkdir()
    env = {"PATH": f"{clean / 'bin'}:/usr/bin:/bin", "HOME": str(tmp_path / "home"), "LGNN_CACHE": str(tmp_path / "cache")}
    where = subprocess.run([str(python), "-c", "import lgnn; print(lgnn.__file__)"], cwd=work, env=env, capture_output=True, text=True, check=True)
    assert Path(where.stdout.strip()).is_relative_to(clean), where.stdout  # the wheel's copy, not the checkout's
    scenes = subprocess.run([str(clean / "bin" / "lgnn"), "scenes"], cwd=work, env=env, capture_output=True, text=True, timeout=300)
    assert scenes.returncode == 0 and "chain4" in scenes.stdout and "T1" in scenes.stdout, scenes.stderr[-2000:]
    simulated = subprocess.run([str(clean / "bin" / "lgnn"), "simulate", "chain4", "--duration", "0.05", "--out", "chain4.npz"], cwd=work, env=env,
                               capture_output=True, text=True, timeout=300)
    assert simulated.returncode == 0, simulated.stderr[-2000:]
    with np.load(work / "chain4.npz") as trajectory:
        assert trajectory["q"].shape[-2:] == (5, 2) and np.isfinite(trajectory["q"]).all()
