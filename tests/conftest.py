"""Shared test setup: float64 everywhere (accuracy is the point of these tests); the
process settings are the root conftest's."""

import jax
import pytest


@pytest.fixture(scope="session")
def x64():
    assert jax.config.jax_enable_x64


@pytest.fixture
def tiny_benchmark_config(tmp_path):
    """`tiny_benchmark_config(model, epochs, data_duration=0.1, train_settings="")`: the
    path of a benchmark config (in `tmp_path`) that trains `model` (a registered name or
    `module:SPEC`) on a few short chain4 trajectories for `epochs` epochs and evaluates it
    on chain4 from 2 initial conditions over 0.02 s: a whole benchmark in seconds."""

    def write(model: str, epochs: int, data_duration: float = 0.1, train_settings: str = ""):
        path = tmp_path / "tiny.toml"
        path.write_text(
            'stages = ["train", "evaluate"]\n'
            f'[[grid]]\nmodel = "{model}"\ntrain_scene = "chain4"\neval_scenes = ["chain4"]\n'
            f"[training.data]\nn_trajectories = 3\nduration = {data_duration}\nsample_dt = 0.02\n"
            f"[training.train]\nepochs = {epochs}\n{train_settings}"
            "[evaluate]\ninitial_conditions = 2\nduration = 0.02\n"
        )
        return path

    return write


@pytest.fixture
def untrained_checkpoint():
    """`untrained_checkpoint(profile, folder, model_name)`: the initial state of the
    profile's one training job, saved where the benchmark keeps its checkpoint under
    `folder` (a model whose parameters need no training, e.g. the true physics)."""
    from lgnn.bench import profiles, store
    from lgnn.learn import models, protocol, train

    def save(profile, folder, model_name: str):
        (job,) = profiles.training_jobs(profile)
        model, config = models.ModelConfig(model_name), protocol.TrainConfig(learning_rate=1e-3, warmup_steps=1)
        path = store.Layout(folder).checkpoint(job)
        path.parent.mkdir(parents=True)
        train.save_checkpoint(path, train.initial_state(model, config), model, config)
        return path

    return save
