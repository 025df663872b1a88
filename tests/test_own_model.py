"""Bring your own model: a `ModelSpec` written here, outside the package, named in a
benchmark config as `module:attribute`, trains and evaluates through the benchmark's
own stages and appears in its tables beside the built-in models."""

import functools
import os

import jax.numpy as jnp

from lgnn import physics
from lgnn.bench import profiles, report
from lgnn.bench.report import summary as report_summary
from lgnn.bench.run import run
from lgnn.bench.stages import evaluate
from lgnn.cli import main
from lgnn.learn import data, train
from lgnn.learn.models import ModelSpec

# The smallest Lagrangian model: the true kinetic and potential energies, each scaled
# by a learned factor exp(s); it starts wrong (s = +-0.5) and the truth is s = 0.
SCALED_TRUTH = ModelSpec(
    "scaled-truth",
    init=lambda key, config: {"log_scale": jnp.array([0.5, -0.5])},
    lagrangian=lambda config, params, scene: (
        lambda q, qd: jnp.exp(params["log_scale"][0]) * jnp.sum(physics.kinetic_energy_per_link(scene, q, qd))
        - jnp.exp(params["log_scale"][1]) * jnp.sum(physics.potential_energy_per_link(scene, q))
    ),
)


def test_a_model_defined_outside_the_package_runs_through_the_benchmark(tmp_path, tiny_benchmark_config):
    config = tiny_benchmark_config(f"{__name__}:SCALED_TRUTH", epochs=15, data_duration=0.2,
                                   train_settings="learning_rate = 0.05\nwarmup_steps = 1\n")
    profile = profiles.load_profile(config)
    out = run(profile, tmp_path / "out", progress=False)
    (job,) = profiles.training_jobs(profile)
    state, meta = train.load_checkpoint(out / "benchmark" / "checkpoints" / f"{job.name}.npz")
    assert meta["model"]["name"] == "scaled-truth" and meta["model_source"].endswith(":SCALED_TRUTH")
    assert state.best_val < 0.1 * state.history[0][2]  # it learns towards the truth
    ((pair, record),) = evaluate.load_pairs(profile, out)
    assert pair.job.model == "scaled-truth" and pair.scene == "chain4"
    # The report's tables and error figure carry it like a built-in model.
    readme = report.write(profile, out).read_text()
    header = next(line for line in readme.splitlines() if line.startswith("| scene |"))
    assert "scaled-truth" in header.split("|")[2] and "| chain4 | " in readme
    assert "scaled-truth" in set(report_summary.tables(evaluate.load_truths(profile, out), [(pair, record)])[0]["model"])
    assert (out / "figures" / "error_vs_time_chain4_8_16.png").exists()


def test_lgnn_train_takes_a_model_reference(capsys, tmp_path, monkeypatch):
    """`lgnn train --model module:attribute` trains a model defined outside the package;
    the checkpoint names it and where its code is, and `--help` still lists the built-ins."""
    # A tenth of a second of data (the CLI's is 1 s a trajectory): the reference is the point here.
    monkeypatch.setattr(data, "DataConfig", functools.partial(data.DataConfig, duration=0.1, sample_dt=0.01))
    out = tmp_path / "own.npz"
    argv = ["train", "--model", f"{__name__}:SCALED_TRUTH", "--trajectories", "1", "--epochs", "2", "--batch-size", "4", "--quiet",
            "--cache-dir", str(tmp_path / "cache"), "--out", str(out)]
    assert main(argv) == 0
    assert capsys.readouterr().out.startswith("scaled-truth on chain4: 2 epochs")
    _, meta = train.load_checkpoint(out)
    assert meta["model"]["name"] == "scaled-truth" and meta["model_source"] == f"{__name__}:SCALED_TRUTH"
    assert main(["train", "--model", "no_such_module:SPEC", "--out", str(tmp_path / "x.npz")]) == 2
    assert "cannot import 'no_such_module'" in capsys.readouterr().err
    try:
        main(["train", "--help"])
    except SystemExit:
        pass
    usage = capsys.readouterr().out
    assert all(name in usage for name in ("lgnn", "lgnn-mp1", "gns", "lgn", "clnn")) and "module:attr" in usage


def test_commands_reading_a_checkpoint_load_its_model_code_when_told(capsys, tmp_path, monkeypatch):
    """`lgnn rollout`, `lgnn evaluate` and `lgnn checkpoint` on a checkpoint of one's own
    model: without its code one line naming the option, with `--model-code` they run."""
    from lgnn.learn import models, protocol
    from lgnn.scene import get_scene

    reference = f"{__name__}:SCALED_TRUTH"
    models.load_spec(reference)
    model = models.ModelConfig.for_scene("scaled-truth", get_scene("chain4"))
    config = protocol.TrainConfig(learning_rate=protocol.PAPER_LEARNING_RATE, warmup_steps=1)
    checkpoint = tmp_path / "own.npz"
    train.save_checkpoint(checkpoint, train.initial_state(model, config), model, config)
    short = ["--duration", "0.01", "--quiet"]
    commands = {
        "rollout": ["rollout", "chain4", "--model", checkpoint, "--out", tmp_path / "own_traj.npz", *short],
        "evaluate": ["evaluate", "chain4", "--model", checkpoint, "--out-dir", tmp_path, *short],
        "checkpoint": ["checkpoint", checkpoint],
    }
    for name, argv in commands.items():
        monkeypatch.delitem(models.registry._REGISTRY, "scaled-truth")  # a fresh process: the checkpoint's code not imported
        assert main(argv) == 2, name
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"--model-code {reference}" in err, err
        assert main([*argv, "--model-code", reference]) == 0, name
        assert "scaled-truth" in capsys.readouterr().out


def test_a_model_file_added_to_the_models_folder_needs_no_other_edit(tmp_path):
    """ARCHITECTURE.md's claim for a model: one file under `lgnn/learn/models/` registers
    itself after the built-ins (the tables' column order kept), and the benchmark's grid
    takes it by its name. Checked on a copy of the package, never the checkout's."""
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    import lgnn

    copy = tmp_path / "lgnn"
    shutil.copytree(Path(lgnn.__file__).parent, copy, ignore=shutil.ignore_patterns("__pycache__"))
    (copy / "learn" / "models" / "mine.py").write_text(
        "import dataclasses\n\nfrom lgnn.learn.models.registry import get_spec, register\n\n"
        "MINE = register(dataclasses.replace(get_spec('gns'), name='mine'))\n")
    check = ("import lgnn, jax, numpy as np\n"
             f"assert lgnn.__file__.startswith({str(tmp_path)!r}), lgnn.__file__\n"
             "from lgnn.learn import models\n"
             "from lgnn.bench import profiles\n"
             "from lgnn.scene import get_scene\n"
             "names = models.model_names()\n"
             "assert names[-1] == 'mine' and names[:-1] == tuple(n for n in names if n != 'mine'), names\n"
             "profile = profiles.load_profile('quick', add=('mine',))\n"
             "assert 'mine-chain4-s0' in [job.name for job in profiles.training_jobs(profile)]\n"
             "scene = get_scene('chain4')\n"
             "config = models.ModelConfig.for_scene('mine', scene)\n"
             "params = models.init(jax.random.PRNGKey(0), config)\n"
             "qdd = models.acceleration_fn(config, params, scene)(scene.initial_state.q, scene.initial_state.qd)\n"
             "assert np.isfinite(np.asarray(qdd)).all()\n")
    result = subprocess.run([sys.executable, "-c", check], cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(tmp_path)},
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
