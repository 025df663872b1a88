"""A researcher's model beside committed results: `[[add]]` entries and `--add-model`
extend the grid, each entry may carry its own seeds and budget, and a `base` results
folder (`--with-results`) is read in place, never written, while the researcher's
outputs go to their own folder and the merged report ranks both and tells the truth
about what it holds. Tiny: chain4, two initial conditions, 0.02 s rollouts."""

import jax.numpy as jnp
import pytest

from lgnn import physics
from lgnn.bench import grid, profiles
from lgnn.bench.report import leaderboard, readme as report_readme
from lgnn.bench.run import run
from lgnn.bench.stages import evaluate
from lgnn.cli import main
from lgnn.errors import ConfigError
from lgnn.learn import models

# The "committed" model: the true accelerations (LagrangeBench's cheating model), with a
# parameter it does not use (the evaluate stage stacks a model's seeds' parameters).
COMMITTED = models.ModelSpec("cheat-leaderboard", lambda key, config: {"unused": jnp.zeros(1)},
                             acceleration=lambda config, params, scene: physics.true_acceleration_fn(scene))
# The researcher's model: the true accelerations times a learned factor exp(s), which
# starts at s = 0.3 (the truth is s = 0).
OWN = models.ModelSpec("scaled-leaderboard", lambda key, config: {"log_scale": jnp.array(0.3)},
                       acceleration=lambda config, params, scene: (
                           lambda q, qd, fn=physics.true_acceleration_fn(scene): jnp.exp(params["log_scale"]) * fn(q, qd)))

# Settings both runs share (their evaluation settings must match for records to be reused).
SETTINGS = ("[training.data]\nn_trajectories = 3\nduration = 0.2\nsample_dt = 0.02\n"
            "[evaluate]\ninitial_conditions = 2\nduration = 0.02\nmujoco_dt = 1e-3\n")


def _files(folder):
    return {path.relative_to(folder).as_posix(): path.read_bytes() for path in sorted(folder.rglob("*")) if path.is_file()}


def _committed(tmp_path, untrained_checkpoint):
    """A committed-like results folder: the cheating model's checkpoint, its evaluation
    and ground-truth records on chain4, and its report; `(config text, folder)`."""
    text = f'[[grid]]\nmodel = "{__name__}:COMMITTED"\ntrain_scene = "chain4"\neval_scenes = ["chain4"]\n' + SETTINGS
    (tmp_path / "committed.toml").write_text(text)
    profile = profiles.load_profile(tmp_path / "committed.toml")
    base = tmp_path / "results"
    untrained_checkpoint(profile, base, COMMITTED.name)
    run(profile, base, stages=("evaluate", "report"), progress=False)
    return text, base


def test_a_researchers_model_is_ranked_beside_committed_results_read_in_place(tmp_path, capsys, untrained_checkpoint):
    text, base = _committed(tmp_path, untrained_checkpoint)
    before = _files(base)
    config = tmp_path / "mine.toml"
    config.write_text(text)
    out = tmp_path / "mine"
    argv = ["benchmark", "--config", config, "--add-model", f"{__name__}:OWN", "--set", "add.epochs=2", "--set", "add.eval_scenes=[chain4]",
            "--with-results", base, "--out-dir", out, "--quiet"]
    assert main(argv) == 0, capsys.readouterr().err
    # The base is read, never written: byte for byte as it was, nothing added.
    assert _files(base) == before
    # The researcher's outputs only in their folder: their checkpoint and pair record; the
    # committed checkpoint, pair record and ground-truth record (same key) reused in place.
    mine = _files(out)  # no claim left (`lgnn.bench.claims`: removed as their blocks end)
    assert "benchmark/checkpoints/scaled-leaderboard-chain4-s0.npz" in mine
    assert "benchmark/runs/scaled-leaderboard-chain4-s0/chain4.npz" in mine
    assert not any(name.startswith(("benchmark/checkpoints/cheat", "benchmark/runs/cheat", "benchmark/runs/ground-truth")) for name in mine)
    readme = (out / "README.md").read_text()
    row = next(line for line in readme.splitlines() if line.startswith("| chain4 | "))
    header = next(line for line in readme.splitlines() if line.startswith("| scene | "))
    assert "cheat-leaderboard" in header and "scaled-leaderboard" in header
    # Both models' cells hold numbers with their seed counts; the cheat reproduces the truth.
    cells = dict(zip(header.strip("|").split("|"), row.strip("|").split("|")))
    assert all("(1 seed)" in cells[f" {name} "] for name in ("cheat-leaderboard", "scaled-leaderboard")), row
    # The added entry's own budget: stopped by it, not "cut off" by the profile's 10 epochs.
    training = next(line for line in readme.splitlines() if line.startswith("| scaled-leaderboard | chain4 | 0 | 2 |"))
    assert "epoch budget" in training
    # The header names the command and the base; the provenance names each record's folder.
    assert f"Written by `lgnn benchmark --config {config}" in readme and f"`{base}` are read in place" in readme
    assert f"| `{base}` |" in readme and f"| `{out}` |" in readme
    assert "performance.md" not in readme  # no speed records, so not written, not listed


def test_add_entries_extend_the_grid_with_their_own_seeds_and_budget(tmp_path):
    config = tmp_path / "mine.toml"
    config.write_text(f'profile = "full"\nbase = "results"\n[[add]]\nmodel = "{__name__}:OWN"\nseeds = [0]\nepochs = 20\n')
    profile = profiles.load_profile(config)
    # The built-in grid kept whole, the added entry after it with the training scene's transfer scenes.
    assert profile.grid[: len(grid.GRID)] == grid.GRID and profile.grid[-1].eval_scenes == grid.TRANSFER_SCENES
    assert profile.base == str(tmp_path / "results")  # relative to the config
    jobs = [job for job in profiles.training_jobs(profile) if job.model == OWN.name]
    assert [job.seed for job in jobs] == [0] and len(profiles.training_jobs(profile)) == len(profiles.training_jobs(profiles.PROFILES["full"])) + 1
    assert profiles.train_config(profile, jobs[0]).epochs == 20 and profiles.train_config(profile, profiles.training_jobs(profile)[0]).epochs == 10_000
    # A shipped profile's model selection keeps the added model.
    quick = profiles.load_profile("quick", ["add.epochs=3"], add=(f"{__name__}:OWN",))
    assert OWN.name in quick.models and profiles.train_config(quick, grid.TrainingJob(OWN.name, "chain4", 0)).epochs == 3
    with pytest.raises(ConfigError, match="OWN.epochs. must be a whole number"):
        profiles.load_profile("quick", ["add.epochs=0"], add=(f"{__name__}:OWN",))


def test_the_banner_says_what_was_run_not_the_profiles_name(tmp_path):
    quick = profiles.load_profile("quick")
    assert report_readme.banner(quick) == [report_readme.QUICK_WARNING, ""]
    # The full grid trains every entry by the one protocol (epochs and the plateau rule,
    # no wall clock): no entry on a smaller budget.
    assert report_readme.banner(profiles.PROFILES["full"]) == []
    assert all(entry.epochs is None and entry.minutes is None for entry in grid.GRID)
    # Full evaluation settings under another name (the paper's track), one model on a
    # short budget: named, no "Not results".
    short = profiles.load_profile("full", ["name=mine", 'tracks=["paper"]', "add.epochs=20", "add.seeds=[0]"], add=(f"{__name__}:OWN",))
    (text, _) = report_readme.banner(short)
    assert "smaller budget" in text and "scaled-leaderboard (20 epochs; chain4; seed 0)" in text and report_readme.QUICK_WARNING not in text
    assert "lgnn (" not in text and "lgn (" not in text  # the paper's models keep the full recipe


def test_the_base_folder_is_never_the_output_folder(tmp_path):
    (tmp_path / "results").mkdir()
    profile = profiles.load_profile("quick", [f'base="{tmp_path / "results"}"'])
    with pytest.raises(ConfigError, match="read, never written"):
        run(profile, tmp_path / "results", stages=("report",), progress=False)
    with pytest.raises(ConfigError, match="is not a folder"):
        run(profiles.load_profile("quick", [f'base="{tmp_path / "absent"}"']), tmp_path / "out", stages=("report",), progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results"]  # nothing written


def test_records_read_from_the_base_say_so(tmp_path, untrained_checkpoint):
    _, base = _committed(tmp_path, untrained_checkpoint)
    profile = profiles.load_profile(tmp_path / "committed.toml", [f'base="{base}"'])
    ((pair, (_, meta)),) = evaluate.load_pairs(profile, tmp_path / "elsewhere")
    assert meta["folder"] == str(base) and pair.job.model == COMMITTED.name
    assert evaluate.unmatched_base_pairs(profile, tmp_path / "elsewhere") == []


def test_base_results_made_with_other_evaluation_settings_are_named_never_mixed_or_recomputed(tmp_path, untrained_checkpoint):
    _, base = _committed(tmp_path, untrained_checkpoint)
    longer = profiles.load_profile(tmp_path / "committed.toml", [f'base="{base}"', "evaluate.duration=0.03"])
    out = tmp_path / "mine"
    assert evaluate.unmatched_base_pairs(longer, out) == profiles.evaluation_pairs(longer)
    evaluate.evaluate_group(longer, profiles.evaluation_pairs(longer), out, progress=False)
    assert not out.exists() and evaluate.load_pairs(longer, out) == []  # nothing rolled out, nothing written
    (line,) = report_readme._unmatched_lines(longer, out)
    assert line.startswith("**Not compared:** 1 evaluation(s)") and "cheat-leaderboard" in line


@pytest.mark.parametrize("argv, words", [
    (["--add-model", "no_such_module:SPEC"], "cannot import 'no_such_module'"),
    (["--add-model", f"{__name__}:OWN", "--set", "add.epochs=0"], "must be a whole number >= 1"),
    (["--add-model", f"{__name__}:OWN", "--set", "add.seeds=[]"], "at least one training seed"),
    (["--add-model", f"{__name__}:OWN", "--set", "add.colour=red"], "unknown setting 'add[0].colour'"),
    (["--with-results", "{tmp}/absent"], "is not a folder"),
    (["--config", "{tmp}/c.toml"], "'add' must be a list of tables"),
])
def test_bad_leaderboard_input_is_one_line(argv, words, tmp_path, capsys):
    (tmp_path / "c.toml").write_text("add = 3\n")
    argv = [arg.replace("{tmp}", str(tmp_path)) for arg in argv]
    assert main(["benchmark", *argv, "--out-dir", str(tmp_path / "out"), "--stage", "report", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and words in err, err


def test_an_added_model_file_is_relative_to_the_working_directory_not_the_config(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "own.py").write_text("import jax.numpy as jnp\nfrom lgnn import physics\nfrom lgnn.learn.models import ModelSpec\n"
                                     "SPEC = ModelSpec('file-leaderboard', lambda key, config: {'s': jnp.zeros(1)},\n"
                                     "                 acceleration=lambda config, params, scene: physics.true_acceleration_fn(scene))\n")
    (tmp_path / "configs").mkdir()
    (tmp_path / "configs" / "c.toml").write_text(SETTINGS)
    assert main(["benchmark", "--config", "configs/c.toml", "--add-model", "own.py:SPEC", "--stage", "report", "--out-dir", "out", "--quiet"]) == 0
    assert "file-leaderboard" in models.model_names() and (tmp_path / "out" / "README.md").exists()


def test_a_cell_without_a_record_says_why():
    """A grid pair with no record is "not evaluated"; a fixed-size model (CLNN, CHNN) on a
    scene the grid does not run it on is "fixed size"; any other pair outside the grid
    is "—". The committed leaderboard has every pair of its grid."""
    from pathlib import Path

    board = next(b for heading, _, b in leaderboard.leaderboards(profiles.evaluation_pairs(profiles.PROFILES["full"])) if heading.startswith("planar: "))
    clnn = next(p for p in board if p.job.model == "clnn")
    lgnn = next(p for p in board if p.job.model == "lgnn" and p.scene == "chain8")
    assert leaderboard._missing_cell(lgnn.label, "chain8", board) == leaderboard.NOT_EVALUATED
    assert leaderboard._missing_cell(clnn.label, "chain8", board) == leaderboard.FIXED_SIZE_CELL
    assert leaderboard._missing_cell("mine (external)", "chain8", board) == "—"
    committed = (Path(__file__).resolve().parents[1] / "results" / "LEADERBOARD.md").read_text()
    rows = [line for line in committed.splitlines() if line.startswith("| ")]
    assert not any(f"| {leaderboard.NOT_EVALUATED} |" in row for row in rows)
    assert all(row.count(leaderboard.FIXED_SIZE_CELL) == 6 for row in rows if row.split(" | ")[1] in ("clnn", "chnn"))
