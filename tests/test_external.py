"""Predictions made outside lgnn (`lgnn benchmark --add-predictions`): a researcher exports
the evaluation's initial conditions, rolls them out elsewhere and scores the saved states
against the same ground truth as the benchmark's models. Here the "other framework" is
lgnn's own Lagrangian engine (the exact physics: error at round-off) and the same engine
under 5 % more gravity, in float32, with one rollout blowing up (scored by the divergence
rule, not refused). Tiny: chain4, two initial conditions, 0.02 s."""

import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

from lgnn import physics
from lgnn.bench import profiles, store
from lgnn.bench.report import summary as report_summary
from lgnn.bench.stages import evaluate, external
from lgnn.bench.stages import truth as truth_stage
from lgnn.cli import main
from lgnn.engines import get_engine
from lgnn.learn import models
from lgnn.learn.export import load_exported
from lgnn.scene import State, get_scene

# A trained model beside the external rows: the true accelerations (the cheating model).
CHEAT = models.ModelSpec("cheat-external", lambda key, config: {"unused": jnp.zeros(1)},
                         acceleration=lambda config, params, scene: physics.true_acceleration_fn(scene))
CONFIG = (f'stages = ["evaluate", "report"]\n[[grid]]\nmodel = "{__name__}:CHEAT"\ntrain_scene = "chain4"\neval_scenes = ["chain4"]\n'
          "[training.data]\nn_trajectories = 2\nduration = 0.1\nsample_dt = 0.02\n"
          "[evaluate]\ninitial_conditions = 2\nduration = 0.02\nmujoco_dt = 1e-3\n")


def _setup(tmp_path, untrained_checkpoint):
    """`(config path, profile, output folder)`: the cheating model's checkpoint in place, untrained."""
    config = tmp_path / "tiny.toml"
    config.write_text(CONFIG)
    profile = profiles.load_profile(config)
    out = tmp_path / "out"
    untrained_checkpoint(profile, out, CHEAT.name)
    return config, profile, out


def _save(path, q, qd, evaluation, model, **extra):
    np.savez(path, q=q, qd=qd, scene=evaluation["scene"], key=evaluation["key"], model=model, **extra)
    return path


def test_exported_initial_conditions_rolled_out_elsewhere_are_scored_against_the_same_ground_truth(tmp_path, capsys, untrained_checkpoint):
    config, profile, out = _setup(tmp_path, untrained_checkpoint)
    exported = tmp_path / "chain4-ic.npz"
    assert main(["dataset", "export", "--scene", "chain4", "--config", config, "--out", exported, "--cache-dir", tmp_path, "--quiet"]) == 0
    arrays, meta = load_exported(exported)
    evaluation = meta["evaluation"]
    states = State(arrays["eval_q0"], arrays["eval_qd0"])
    # The other framework: the settings the export names, from the exported states.
    settings = profile.evaluate.simulation(evaluation["scene"])
    assert (evaluation["dt"], evaluation["frame_dt"], evaluation["frames"]) == (settings.dt, settings.frame_dt, settings.n_frames + 1)
    engine = get_engine("lagrangian", integration=profile.evaluate.integration)
    exact = engine.rollout(get_scene("chain4"), settings, states)
    heavier = get_scene("chain4").replace(gravity=1.05 * get_scene("chain4").gravity)
    other = engine.rollout(heavier, settings, states)
    q, qd = np.asarray(other.q, np.float32), np.asarray(other.qd, np.float32)
    q[1, 10:] = np.nan  # one rollout blew up at frame 10: scored as diverged there
    files = [_save(tmp_path / "exact.npz", exact.q, exact.qd, evaluation, "exact-sim", about="lgnn's Lagrangian engine"),
             _save(tmp_path / "heavier.npz", q, qd, evaluation, "heavier-sim")]
    argv = ["benchmark", "--config", config, "--out-dir", out, "--quiet", *(a for f in files for a in ("--add-predictions", f))]
    assert main(argv) == 0, capsys.readouterr().err

    # Records: one per file, the same arrays as a trained model's pair record.
    for name in ("exact-sim", "heavier-sim"):
        record = store.Layout(out).external_record(name, "chain4")
        assert evaluate.has_arrays(store.load(record), evaluate.pair_needs(profile))
    assert [pair.label for pair, _ in external.load_externals(profile, out)] == ["exact-sim (external)", "heavier-sim (external)"]
    summary = pd.read_csv(out / "benchmark" / report_summary.SUMMARY, comment="#")
    cell = lambda model, statistic, metric="rollout_error": summary[(summary.model == model) & (summary.metric == metric)  # noqa: E731
                                                                   & (summary.statistic == statistic)].value.item()
    assert cell("exact-sim (external)", "gmean") < 1e-9 and cell("exact-sim (external)", "diverged") == 0
    assert cell("heavier-sim (external)", "gmean") > 1e-6 and cell("heavier-sim (external)", "diverged") == 1
    assert cell("heavier-sim (external)", "first_divergence_s") == pytest.approx(0.01)
    # Against MuJoCo too, as every model; energies the scene's, never the file's.
    assert cell("exact-sim (external)", "gmean", "rollout_error_vs_mujoco") < 1e-3
    assert cell("exact-sim (external)", "gmean", "energy_error") < 1e-9
    # The report: a column each, marked external, no seed count; no training row; what each is.
    readme = (out / "README.md").read_text()
    header = next(line for line in readme.splitlines() if line.startswith("| scene | "))
    row = next(line for line in readme.splitlines() if line.startswith("| chain4 | "))
    cells = dict(zip(header.strip("|").split("|"), row.strip("|").split("|")))
    assert "seed" not in cells[" exact-sim (external) "] and "(1 seed)" in cells[" cheat-external "], row
    training = readme.split("## Training", 1)[1].split("## External predictions", 1)
    assert len(training) == 2 and "exact-sim" not in training[0]
    assert "| exact-sim (external) | chain4 | `exact.npz` | lgnn's Lagrangian engine |" in training[1]
    assert "no checkpoint, parameters or training time" in training[1]
    # The leaderboard: README.md's cells (the same records), a rank on each scene and overall.
    board = (out / "LEADERBOARD.md").read_text()
    for model in ("cheat-external", "exact-sim (external)", "heavier-sim (external)"):
        line = next(line for line in board.splitlines() if line.startswith("| ") and f" | {model} | " in line)
        assert f"| {cells[f' {model} '].strip()} (rank " in line, (line, cells)
    ranked = [line.split(" | ")[1] for line in board.splitlines() if line[:4] in ("| 1 ", "| 2 ", "| 3 ")]
    assert ranked[2] == "heavier-sim (external)" and set(ranked[:2]) == {"cheat-external", "exact-sim (external)"}, board
    external_row = next(line for line in board.splitlines() if " | exact-sim (external) | " in line)
    assert " | — | — (external) | " in external_row
    cheat_row = next(line for line in board.splitlines() if " | cheat-external | " in line)
    assert " | 1 | not recorded | " in cheat_row  # one parameter; an untrained checkpoint holds no training time
    # A later report keeps the submitted rows without the files (they are records), and
    # the leaderboard command alone writes the same file from them.
    (out / "LEADERBOARD.md").unlink()
    assert main(["leaderboard", "--config", config, "--out-dir", out]) == 0
    assert (out / "LEADERBOARD.md").read_text().split("\n", 3)[3] == board.split("\n", 3)[3]
    assert "Written by `lgnn leaderboard --config" in (out / "LEADERBOARD.md").read_text()
    # Verified: the model's row rolled out again, each external row scored again from its
    # file where given, unverified without it, failed for a file that is not the one scored.
    verify = ["leaderboard", "verify", out, "--config", config, "--quiet"]
    assert main(verify) == 0
    printed = capsys.readouterr().out
    assert "cheat-external: verified: " in printed and "exact-sim (external): unverified: on chain4: no predictions file given" in printed
    assert main([*verify, "--predictions", files[0], "--predictions", files[1]]) == 0
    printed = capsys.readouterr().out
    assert f"exact-sim (external): verified: on chain4: {files[0]} scored again to the record" in printed, printed
    assert "heavier-sim (external): verified: " in printed and "| yes (scored again) |" in (out / "LEADERBOARD.md").read_text()
    edited = q.copy()
    edited[:, 1:] *= 1.001  # every frame after the initial conditions moved
    _save(files[1], edited, qd, evaluation, "heavier-sim")
    assert main([*verify, "--predictions", files[1]]) == 1
    assert "heavier-sim (external): failed: on chain4: " in capsys.readouterr().out


@pytest.mark.parametrize("change, words", [
    ({"q": lambda q: q[:, :-1]}, "has 20 frames, expected 21"),
    ({"q": lambda q: q[:1]}, "has shape (1, 21, 5, 2), expected (2, 21, 5, 2)"),
    ({"q": lambda q: q + 0.1}, "frame 0 of 'q' is not the exported initial conditions"),
    ({"key": "0123"}, "is not this profile's evaluation of chain4"),
    ({"scene": "chain8"}, "scene 'chain8' is not evaluated"),
    ({"model": "my sim"}, "'model' must be 1-64 letters"),
    ({"model": None}, "missing model"),
])
def test_bad_predictions_are_one_line_before_any_stage(change, words, tmp_path, capsys, untrained_checkpoint):
    config, profile, out = _setup(tmp_path, untrained_checkpoint)
    states = truth_stage.evaluation_initial_states(profile, get_scene("chain4"))
    frames = profile.evaluate.simulation("chain4").n_frames + 1
    arrays = dict(q=np.repeat(states.q[:, None], frames, 1), qd=np.repeat(states.qd[:, None], frames, 1), scene="chain4",
                  key=truth_stage.truth_key(profile, "chain4"), model="my-sim")
    for name, value in change.items():
        if value is None:
            del arrays[name]
        else:
            arrays[name] = value(arrays[name]) if callable(value) else value
    np.savez(tmp_path / "p.npz", **arrays)
    assert main(["benchmark", "--config", config, "--out-dir", out, "--add-predictions", tmp_path / "p.npz", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and words in err and "p.npz" in err, err
    assert not (out / "benchmark" / "runs").exists()  # nothing scored or written
