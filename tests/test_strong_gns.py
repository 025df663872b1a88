"""The strong GNS (`gns-10-128`, `lgnn.learn.models.strong_gns`) and the training-set statistics
a model normalises by: physics of its predictions, its statistics from training to
checkpoint, and its recipe (AdamW, input noise). The benchmark trains it through its
stages (`bench/test_benchmark.py::test_training`, which also checks the statistics a
stage's checkpoint carries)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lgnn import physics
from lgnn.errors import ConfigError
from lgnn.learn import checkpoints, data, models, protocol, train
from lgnn.scene import get_scene

TINY_DATA = data.DataConfig(n_trajectories=6, duration=0.2, sample_dt=0.01, dt=1e-3)
# The recipe's network at test size: its code, not its 1.6M parameters.
SMALL = dict(latent=16, hidden=16, message_passing=2)


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    return data.load_or_generate(TINY_DATA, tmp_path_factory.mktemp("cache"))


def _training_arrays(dataset):
    return tuple(a[dataset.train] for a in (dataset.q, dataset.qd, dataset.qdd))


def _moving_states(scene, count=3):
    """States on the constraint manifold with non-zero velocities, (B, N, D) each."""
    q = jnp.broadcast_to(jnp.asarray(scene.nodes), (count, *scene.nodes.shape))
    kicks = jax.random.normal(jax.random.PRNGKey(0), q.shape)
    return jax.jit(jax.vmap(physics.projection_fn(scene)))(q, kicks)


def _trained_statistics_params(scene, dataset, **sizes):
    config = models.ModelConfig.for_scene("gns-10-128", scene, **sizes)
    statistics = models.training_statistics(config, scene, *_training_arrays(dataset))
    return config, models.with_statistics(models.init(jax.random.PRNGKey(1), config), statistics)


def test_the_recipe_sizes_and_statistics_of_the_training_set(tiny_dataset):
    scene = get_scene("chain4")
    config = models.ModelConfig.for_scene("gns-10-128", scene)
    assert (config.latent, config.hidden, config.message_passing) == (128, 128, 10)
    trainable, statistics = models.split_statistics(models.init(jax.random.PRNGKey(0), config))
    # The recipe's size: about 1.2-1.6M parameters (10 steps of two MLPs 3x128/2x128 -> 128 -> 128 -> 128).
    assert 1.2e6 < sum(leaf.size for leaf in jax.tree.leaves(trainable)) < 1.7e6
    q, qd, qdd = _training_arrays(tiny_dataset)
    computed = models.training_statistics(config, scene, q, qd, qdd)
    assert set(computed) == set(statistics)
    np.testing.assert_allclose(computed["velocity_std"], qd[:, 1:].std((0, 1)))
    np.testing.assert_allclose(computed["acceleration_mean"], qdd[:, 1:].mean((0, 1)))
    np.testing.assert_allclose(computed["length_scale"], 1.0)  # chain4's links are all 1 long
    assert models.training_statistics(models.ModelConfig.for_scene("gns", scene), scene, q, qd, qdd) is None


@pytest.mark.parametrize("scene_name", ["chain4", "T1", "chain4-3d"])
def test_zero_at_pinned_nodes_and_invariant_under_translation(tiny_dataset, scene_name):
    # Statistics of chain4 (non-zero mean acceleration): the pins stay at rest anyway.
    config, params = _trained_statistics_params(get_scene("chain4"), tiny_dataset, **SMALL)
    scene = get_scene(scene_name)
    config = dataclasses.replace(config, dim=scene.dim)
    if scene.dim == 3:  # a 3D model: its own sizes, placeholder statistics
        params = models.init(jax.random.PRNGKey(1), config)
    accel = jax.jit(jax.vmap(models.acceleration_fn(config, params, scene)))
    q, qd = _moving_states(scene)
    qdd = accel(q, qd)
    assert np.all(np.isfinite(qdd)) and np.all(qdd[:, list(scene.pinned)] == 0)
    assert np.max(np.abs(qdd[:, list(scene.free_nodes)])) > 0
    shift = jnp.asarray(np.arange(1, scene.dim + 1) * 3.7)
    np.testing.assert_allclose(accel(q + shift, qd), qdd, atol=1e-11)


def test_loss_gradient_matches_finite_differences_and_skips_the_statistics(tiny_dataset):
    scene = get_scene("chain4")
    config, params = _trained_statistics_params(scene, tiny_dataset, **SMALL)
    q, qd = _moving_states(scene, 2)
    qdd = jax.vmap(physics.true_acceleration_fn(scene))(q, qd)
    loss = jax.jit(train.loss_fn(config, scene))
    grads = jax.grad(loss)(params, q, qd, qdd)
    assert all(np.all(leaf == 0) for leaf in jax.tree.leaves(grads[models.STATISTICS]))
    direction = jax.tree.map(lambda x: jax.random.normal(jax.random.PRNGKey(3), x.shape), models.split_statistics(params)[0])
    trainable, statistics = models.split_statistics(params)
    analytic = sum(jnp.vdot(g, d) for g, d in zip(jax.tree.leaves(models.split_statistics(grads)[0]), jax.tree.leaves(direction)))
    eps = 1e-6
    shifted = lambda s: models.join_statistics(jax.tree.map(lambda p, d: p + s * d, trainable, direction), statistics)  # noqa: E731
    numeric = (loss(shifted(eps), q, qd, qdd) - loss(shifted(-eps), q, qd, qdd)) / (2 * eps)
    assert abs(analytic - numeric) <= 1e-6 * max(1.0, abs(analytic))


def test_training_lowers_the_loss_and_keeps_the_statistics_into_the_checkpoint(tiny_dataset, tmp_path):
    scene = get_scene("chain4")
    model = models.ModelConfig.for_scene("gns-10-128", scene, **SMALL)
    config = protocol.TrainConfig(learning_rate=3e-3, epochs=6, warmup_steps=5)  # 6 x 12 AdamW steps
    statistics = models.training_statistics(model, scene, *_training_arrays(tiny_dataset))
    val = tuple(a[tiny_dataset.val] for a in (tiny_dataset.q, tiny_dataset.qd, tiny_dataset.qdd))
    before = train.evaluate_fn(model, scene)(train.initial_state(model, config, statistics).params, *val)
    state = train.train(model, config, tiny_dataset, scene, out=tmp_path / "strong.npz")
    assert state.best_val < before / 2
    # Training filled the statistics in once and never stepped them (AdamW's weight
    # decay included): equal to the training set's, bit for bit, in the latest and best params
    # (the same function of the same states, in this process, then only carried along).
    for params in (state.params, state.best_params):
        for name, value in statistics.items():
            np.testing.assert_array_equal(params[models.STATISTICS][name], value)
    assert not np.all(statistics["velocity_std"] == 1.0)  # not the placeholders
    # Inference from the checkpoint alone has them, and predicts what training had.
    loaded_model, loaded = checkpoints.load_model(tmp_path / "strong.npz")
    for name, value in statistics.items():
        np.testing.assert_array_equal(loaded[models.STATISTICS][name], value)
    assert train.evaluate_fn(loaded_model, scene)(loaded, *val) == pytest.approx(state.best_val, rel=1e-12)
    # A resumed run keeps them too (the optimiser's state is of the trainable part only).
    resumed = train.train(model, dataclasses.replace(config, epochs=7), tiny_dataset, scene, out=tmp_path / "strong.npz", resume=True)
    np.testing.assert_array_equal(resumed.params[models.STATISTICS]["acceleration_std"], statistics["acceleration_std"])


def test_the_recipe_adds_velocity_noise_and_weight_decay(tiny_dataset):
    scene = get_scene("chain4")
    spec = models.get_spec("gns-10-128")
    quiet = models.register(dataclasses.replace(spec, name="gns-10-128-quiet", velocity_noise=0.0))
    config = protocol.TrainConfig(learning_rate=3e-3, epochs=1, warmup_steps=5)
    noisy_run, quiet_run = (train.train(models.ModelConfig.for_scene(s.name, scene, **SMALL), config, tiny_dataset, scene) for s in (spec, quiet))
    # Same seed, same data, same shuffles: only the noise on the inputs differs.
    assert noisy_run.history[0][1] != quiet_run.history[0][1]
    # AdamW: a step with zero gradients still shrinks the weights, by rate x decay.
    adamw = protocol.optimizer(dataclasses.replace(config, warmup_steps=0, decay_rate=1.0), weight_decay=0.5)
    params = {"w": jnp.ones(2)}
    updates, _ = adamw.update({"w": jnp.zeros(2)}, adamw.init(params), params)
    np.testing.assert_allclose(updates["w"], -3e-3 * 0.5)
    with pytest.raises(ConfigError, match="velocity noise must be a finite number >= 0"):
        dataclasses.replace(spec, name="gns-bad", velocity_noise=-1.0)


def test_statistics_of_another_shape_than_inits_placeholders_are_refused():
    config = models.ModelConfig.for_scene("gns-10-128", get_scene("chain4"), **SMALL)
    params = models.init(jax.random.PRNGKey(0), config)
    with pytest.raises(ConfigError, match="placeholders of its statistics"):
        models.with_statistics(params, {"velocity_mean": jnp.zeros(3)})



@pytest.mark.parametrize("name", ["gns-10-128", "cgnode"])
def test_the_message_passing_steps_written_out_are_the_loop_to_round_off(monkeypatch, tiny_dataset, name):
    """On an accelerator the processor's steps are written out (`processor_unroll`), on
    a CPU looped: the same network, so the same accelerations and gradients to round-off
    (both run here, on the CPU, the unrolled one forced)."""
    from lgnn.learn.models import strong_gns

    scene = get_scene("chain4")
    config = models.ModelConfig.for_scene(name, scene, **SMALL)
    params = models.init(jax.random.PRNGKey(3), config)
    q, qd = _moving_states(scene)

    def loss(params):
        return jnp.sum(jax.vmap(models.acceleration_fn(config, params, scene))(q, qd) ** 2)

    def unrolled_steps() -> set[str]:
        # (A function of its own each time: JAX caches the trace of one function object.)
        return {word for word in str(jax.make_jaxpr(lambda p: loss(p))(params)).split() if word.startswith("unroll=")}

    assert not strong_gns.processor_unroll() and unrolled_steps() == {"unroll=1"}  # the CPU loops
    looped = jax.jit(jax.value_and_grad(loss))(params)
    monkeypatch.setattr(strong_gns, "processor_unroll", lambda: True)
    assert unrolled_steps() == {f"unroll={config.message_passing}"}
    unrolled = jax.jit(jax.value_and_grad(loss))(params)
    for a, b in zip(jax.tree.leaves(looped), jax.tree.leaves(unrolled)):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * float(np.max(np.abs(a))))


def test_a_model_with_input_noise_trains_in_float32(tiny_dataset):
    """The recipe's velocity noise is drawn and scaled in the states' precision: in
    float32 (`train_seeds` under `runtime.precision("float32")`) it trains, in float32."""
    from lgnn import runtime

    scene = get_scene("chain4")
    model = models.ModelConfig.for_scene("gns-10-128", scene, **SMALL)
    assert model.spec.velocity_noise > 0
    config = protocol.TrainConfig(learning_rate=3e-3, epochs=2, warmup_steps=2)
    train.train_seeds(model, [config], tiny_dataset, scene)  # float64 first: its program cached, as in a precision study
    with runtime.precision("float32"):
        (state,) = train.train_seeds(model, [config], tiny_dataset, scene)
    assert state.epoch == 2 and np.isfinite(state.best_val)
    assert {leaf.dtype for leaf in jax.tree.leaves(state.params)} == {np.dtype("float32")}
