"""Benchmark configs (`lgnn.bench.profiles.load_profile`, `lgnn.bench.settings`): the shipped
profiles are TOML files, any value can be overridden, bad keys and values are one-line
errors naming them, and a user's config brings its own scenes and models."""

import dataclasses

import pytest

from lgnn import cli
from lgnn.bench import profiles, settings
from lgnn.errors import ConfigError
from lgnn.learn import models
from lgnn.scene import get_scene, scene_to_json


def test_overrides_reach_any_value_and_nothing_else():
    quick = profiles.load_profile("quick")
    changed = profiles.load_profile("quick", ["training.train.epochs=50", "seeds=[0,1,2]", "scenes=[chain4,chain8]", "speed.models=none"])
    assert changed.training.train.epochs == 50 and changed.seeds == (0, 1, 2) and changed.speed.models is None
    assert changed == dataclasses.replace(quick, seeds=(0, 1, 2), speed=dataclasses.replace(quick.speed, models=None),
                                          # the schedule rule follows the new budget (a warm-up of a fifth of its steps)
                                          training=profiles.TrainSettings(quick.training.data, dataclasses.replace(
                                              quick.training.train, epochs=50, learning_rate=None, warmup_steps=None)))
    assert profiles.load_profile("full") == profiles.PROFILES["full"]



def test_the_schedule_rule_fills_only_what_a_config_leaves_unset():
    """`learning_rate` and `warmup_steps` left None follow the budget (30 Adam steps:
    the short-budget rate, a warm-up of a fifth); a value given is kept, the other
    still follows the rule; an unresolved config cannot make an optimiser."""
    from lgnn.learn import protocol

    quick = profiles.load_profile("quick").training.train
    assert (quick.learning_rate, quick.warmup_steps) == (protocol.SHORT_BUDGET_RATE, 6)
    given = profiles.load_profile("quick", ["training.train.learning_rate=0.05"]).training.train
    assert (given.learning_rate, given.warmup_steps) == (0.05, 6)
    long = protocol.scheduled(protocol.TrainConfig(warmup_steps=7), 750)  # the paper's data and budget
    assert (long.learning_rate, long.warmup_steps) == (protocol.PAPER_LEARNING_RATE, 7)
    with pytest.raises(ConfigError, match="schedule rule"):
        protocol.optimizer(protocol.TrainConfig())

@pytest.mark.parametrize("override, message", [
    ("training.train.epoch=5", "unknown setting 'training.train.epoch'"),
    ("evaluate.duration=fast", "setting 'evaluate.duration' must be float, got 'fast'"),
    ("seeds=3", "setting 'seeds' must be a list"),
    ("seeds.first=3", "'seeds' is not a table"),
    ("epochs", "--set expects KEY=VALUE"),
    ("training.train.learning_rate=-1", "learning rate must be > 0"),
])
def test_bad_overrides_are_one_line_errors_naming_the_key(override, message):
    with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace(".", r"\.")):
        profiles.load_profile("quick", [override])


def test_the_command_line_reports_an_unknown_key_in_one_line(tmp_path, capsys):
    config = tmp_path / "mine.toml"
    config.write_text('seeds = [0]\n[evaluate]\ninitial_condition = 3\n')
    assert cli.main(["benchmark", "--config", str(config), "--out-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unknown setting 'evaluate.initial_condition'" in err
    assert cli.main(["benchmark", "--profile", "quick", "--set", "training.data.n_trajectorie=3", "--out-dir", str(tmp_path)]) == 2
    assert "unknown setting 'training.data.n_trajectorie'" in capsys.readouterr().err
    assert not list(tmp_path.glob("benchmark"))  # nothing written


def test_a_users_config_brings_scene_files_and_models(tmp_path, monkeypatch):
    (tmp_path / "scenes").mkdir()
    (tmp_path / "scenes" / "hammock.json").write_text(scene_to_json(get_scene("double-pinned").replace(name="hammock")))
    (tmp_path / "my_model.py").write_text(
        "from lgnn.learn.models import ModelSpec, get_spec\n"
        "clnn = get_spec('clnn')\n"
        "SPEC = ModelSpec('my-clnn', clnn.init, lagrangian=clnn.lagrangian, hidden=16, fixed_size=True)\n"
    )
    config = tmp_path / "mine.toml"
    config.write_text(
        'seeds = [0, 1]\nstages = ["train", "evaluate"]\n'
        '[[grid]]\nmodel = "my_model.py:SPEC"\ntrain_scene = "chain4"\neval_scenes = ["chain4", "scenes/hammock.json"]\n'
    )
    monkeypatch.chdir(tmp_path / "scenes")  # scene paths are relative to the config, not to here
    profile = profiles.load_profile(config)
    assert profile.name == "mine" and profile.stages == ("train", "evaluate")
    assert [e.model for e in profile.grid] == ["my-clnn"] and models.get_spec("my-clnn").hidden == 16
    assert get_scene(profile.grid[0].eval_scenes[1]).name == "hammock"
    assert [j.name for j in profiles.training_jobs(profile)] == ["my-clnn-chain4-s0", "my-clnn-chain4-s1"]
    assert profiles.load_profile(config) == profile  # loading twice registers the same spec


def test_bad_model_references_are_one_line_errors(tmp_path):
    for reference, message in [("nope", "expected module:attribute"), ("no_such_module_x:SPEC", "cannot import 'no_such_module_x'"),
                               ("lgnn.learn.models:register", "is not a lgnn.learn.models.ModelSpec"), ("missing.py:SPEC", "no file")]:
        with pytest.raises(ConfigError, match=message):
            models.load_spec(reference, tmp_path)


def test_toml_values_are_typed():
    assert settings.parse_override("a.b=1e-3") == ("a.b", 1e-3)
    assert settings.parse_override('x=["T1", "T2"]') == ("x", ["T1", "T2"])
    assert settings.parse_override("x=[chain4, T1]") == ("x", ["chain4", "T1"])
    assert settings.parse_override("flag=true") == ("flag", True)
