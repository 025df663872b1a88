"""The transfer track's training data: varied draws of a chain (`DataConfig.varied_draws`),
each state of its own draw's physics, and training on all draws at once."""

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lgnn import physics
from lgnn.errors import ConfigError
from lgnn.learn import checkpoints, data, graphs, models, protocol, train
from lgnn.scene import get_scene

DRAWS = data.DataConfig(n_trajectories=4, duration=0.2, sample_dt=0.01, dt=1e-3, varied_draws=2)


@pytest.fixture(scope="module")
def draws_dataset(tmp_path_factory):
    return data.load_or_generate(DRAWS, tmp_path_factory.mktemp("cache"))


def test_varied_draws_are_chains_of_the_rule_each_state_of_its_own_draw(draws_dataset):
    """Two draws of 4-link chains, two trajectories each: every state keeps its own draw's
    link lengths (not the other's) and its target is its own draw's exact acceleration."""
    scenes = data.draw_scenes(DRAWS)
    assert [s.n_links for s in scenes] == [4, 4] and not np.allclose(scenes[0].lengths, scenes[1].lengths)
    assert [s.name for s in scenes] == ["chain4-draw0", "chain4-draw1"]
    np.testing.assert_array_equal(np.bincount(draws_dataset.draw), [40, 40])
    assert set(draws_dataset.draw[draws_dataset.train]) == {0, 1} and set(draws_dataset.draw[draws_dataset.val]) == {0, 1}
    for k, scene in enumerate(scenes):
        mine = draws_dataset.draw == k
        q, qd, qdd = draws_dataset.q[mine], draws_dataset.qd[mine], draws_dataset.qdd[mine]
        violation = jax.jit(jax.vmap(lambda x, s=scene: physics.constraint_violation(s, x)))
        assert float(violation(q).max()) < 1e-9
        assert float(jax.vmap(lambda x, s=scenes[1 - k]: physics.constraint_violation(s, x))(q[:5]).min()) > 1e-3
        np.testing.assert_allclose(jax.jit(jax.vmap(physics.true_acceleration_fn(scene)))(q, qd), qdd, rtol=1e-9, atol=1e-9)


def test_varied_draws_settings_are_checked_and_keep_the_keys_of_data_without_them():
    assert "varied_draws" not in data.DataConfig().to_dict() and DRAWS.to_dict()["varied_draws"] == 2
    assert data.DataConfig().key(get_scene("chain4"))["settings"] == {
        k: v for k, v in dataclasses.asdict(data.DataConfig()).items() if k not in ("chunk", "varied_draws")}
    with pytest.raises(ConfigError, match="cannot be shared equally among 3 varied draws"):
        data.DataConfig(n_trajectories=4, varied_draws=3)
    with pytest.raises(ConfigError, match="varied draws must be a whole number"):
        data.DataConfig(varied_draws=-1)
    with pytest.raises(ConfigError, match="need a chain pinned at one end; 'T1'"):
        data.draw_scenes(dataclasses.replace(DRAWS, scene="T1"))


def test_varied_draws_of_a_3d_chain_are_3d_chains_of_the_rule():
    """The 3D track's draws: 3D chains of the named chain's length whose links are the
    planar draws' (one rule and seed per draw), each started by the 3D chain sampler."""
    spatial = data.draw_scenes(dataclasses.replace(DRAWS, scene="chain4-3d-varied"))
    flat = data.draw_scenes(DRAWS)
    assert [s.name for s in spatial] == ["chain4-3d-varied-draw0", "chain4-3d-varied-draw1"]
    for s, f in zip(spatial, flat, strict=True):
        assert s.dim == 3 and s.n_links == 4
        np.testing.assert_array_equal(s.lengths, f.lengths)
        np.testing.assert_array_equal(s.masses, f.masses)


def test_training_on_draws_scores_each_state_against_its_own_draw(draws_dataset):
    """An epoch's batches take half their states from each draw; the validation loss
    training reports is the mean over both draws' validation states, each scored with its
    own scene, and training lowers it. The wrong scenes, or a batch the draws cannot
    share, are refused in one line."""
    scenes = data.draw_scenes(DRAWS)
    # GNS: the training machinery is the model's business no more than the loss is (and
    # compiles in a fraction of LGNN's time); with link features, as the track trains.
    model = models.ModelConfig.for_scene("gns", scenes[0], link_features=True)
    config = protocol.TrainConfig(learning_rate=3e-3, batch_size=10, epochs=3, warmup_steps=5)
    state = train.train(model, config, draws_dataset, scenes)
    val = [draws_dataset.val[draws_dataset.draw[draws_dataset.val] == k] for k in range(2)]
    per_draw = [train.evaluate_fn(model, scene)(state.best_params, *(a[index] for a in (draws_dataset.q, draws_dataset.qd, draws_dataset.qdd)))
                for scene, index in zip(scenes, val)]
    expected = sum(loss * len(index) for loss, index in zip(per_draw, val)) / sum(len(index) for index in val)
    assert state.best_val == pytest.approx(expected, rel=1e-9)
    initial = train.initial_state(model, config).params
    assert state.best_val < min(train.evaluate_fn(model, scene)(initial, *(a[index] for a in (draws_dataset.q, draws_dataset.qd, draws_dataset.qdd)))
                                for scene, index in zip(scenes, val))
    with pytest.raises(ConfigError, match="holds 2 varied draws but 1 scenes"):
        train.train(model, config, draws_dataset, scenes[0])
    with pytest.raises(ConfigError, match="cannot take the same number of states from each of 2 varied draws"):
        train.train(model, dataclasses.replace(config, batch_size=9), draws_dataset, scenes)


def test_a_model_trained_on_draws_is_warned_only_outside_the_ranges_its_draws_spanned():
    meta = {"data": {**DRAWS.to_dict()}}
    scenes = data.draw_scenes(DRAWS)
    assert checkpoints.physics_differences(meta, scenes[1]) == []
    assert any(d.startswith("link masses from 1 to 1 (trained on ") for d in checkpoints.physics_differences(meta, get_scene("chain4")))


def _moving_state(scene, seed=0):
    q = jnp.asarray(scene.nodes)
    return jax.jit(physics.projection_fn(scene))(q, jax.random.normal(jax.random.PRNGKey(seed), q.shape))


def test_link_features_carry_each_links_mass_inertia_and_length():
    """LGNN's machinery with the exact per-link energies written on the link attributes
    alone (mass, inertia ratio, length from `edges["link"]`, nothing from the scene)
    gives the ground truth's accelerations on two varied chains it was not written for:
    the attributes are the physics' own, in the graph's edge order."""

    def energies(graph):
        s, r = graph.senders, graph.receivers
        mass, ratio, length = (graph.edges["link"][:, k] for k in range(graphs.LINK_FEATURES))
        v_cm = 0.5 * (graph.nodes["qd"][s] + graph.nodes["qd"][r])
        dq2 = jnp.sum(graph.edges["dq"] ** 2, -1)
        inertia = ratio * mass * length**2
        kinetic = 0.5 * mass * jnp.sum(v_cm**2, -1) + 0.5 * inertia * jnp.sum(graph.edges["w"] ** 2, -1) / dq2**2
        return kinetic, mass * 10.0 * 0.5 * (graph.nodes["q"][s, 1] + graph.nodes["q"][r, 1])

    for name in ("chain8-varied", "chain16-varied"):
        scene = get_scene(name)
        q, qd = _moving_state(scene, seed=2)
        lagrangian = models.lgnn_lagrangian_fn(scene, ("link",), energies, link_features=True)
        ours = jax.jit(physics.acceleration_fn(scene, lagrangian, mass=physics.LOCAL))(q, qd)
        np.testing.assert_allclose(ours, physics.true_acceleration_fn(scene)(q, qd), rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("name", ["lgnn", "lgnn-notebook", "gns", "lgn"])
def test_graph_models_see_link_masses_only_with_link_features(name):
    """Two chains of the same shape whose links differ in mass only: the paper's features
    cannot tell them apart (the same accelerations, whatever the parameters), the link
    features can."""
    light = get_scene("chain4-varied")
    heavy = light.replace(masses=light.masses * np.asarray([1.0, 3.0, 0.5, 2.0]))
    q, qd = _moving_state(light, seed=3)
    for link_features in (False, True):
        config = models.ModelConfig.for_scene(name, light, link_features=link_features)
        params = models.init(jax.random.PRNGKey(4), config)
        a, b = (np.asarray(jax.jit(models.acceleration_fn(config, params, scene))(q, qd)) for scene in (light, heavy))
        assert np.all(np.isfinite(a)) and np.all(np.isfinite(b))
        assert (np.max(np.abs(a - b)) > 1e-6 * np.max(np.abs(a))) == link_features, (name, link_features)


def test_link_features_are_a_setting_of_the_models_that_read_them():
    config = models.ModelConfig.for_scene("lgnn", get_scene("chain4"), link_features=True)
    assert models.ModelConfig.from_dict(config.to_dict()) == config
    assert "link_features" not in models.ModelConfig("lgnn").to_dict()  # checkpoints made before it compare equal
    with pytest.raises(ConfigError, match="clnn does not read link features"):
        models.ModelConfig("clnn", link_features=True)
    with pytest.raises(ConfigError, match="link-features must be true or false"):
        models.ModelConfig("lgnn", link_features=1)


def test_the_transfer_track_is_a_grid_track_of_its_own(tmp_path):
    """The grid's transfer entries train every graph model on varied draws of chain4
    (data with `varied_draws`, link features where the model takes them) under names
    and labels of their own; the full profile has both tracks, the paper's alone on
    request; a leaderboard and tables of their own rank them, their scenes in the
    track's order; an unknown track is one line."""
    from lgnn.bench import grid, profiles
    from lgnn.bench.report import leaderboard, summary as report_summary
    from lgnn.bench.stages.train import job_settings

    paper = profiles.load_profile("full", ['tracks=["paper"]'])
    assert all(job.track == grid.PAPER_TRACK for job in profiles.training_jobs(paper))
    both = profiles.PROFILES["full"]
    assert both.tracks == grid.TRACKS
    transfer = [job for job in profiles.training_jobs(both) if job.track == grid.TRANSFER_TRACK]
    assert {job.model for job in transfer} == {*grid.LGNN_VARIANTS, "gns", "lgn", "gns-10-128", "cgnode", "chgn"}
    lgnn = next(job for job in transfer if job.model == "lgnn" and job.seed == 0)
    assert (lgnn.name, lgnn.label) == ("lgnn-chain4-varied-draws5-s0", "lgnn (chain4-varied, 5 draws)")
    _, model, data_config, _ = job_settings(both, lgnn)
    assert model.link_features and data_config.varied_draws == grid.TRANSFER_DRAWS and data_config.scene == "chain4-varied"
    # A model whose rod features are its own inputs needs no flag (and has none).
    assert not job_settings(both, next(job for job in transfer if job.model == "chgn"))[1].link_features
    # The paper's appendix LGNN on the one varied chain stays its own job.
    assert grid.TrainingJob("lgnn", "chain4-varied", 0) in profiles.training_jobs(both)
    pairs = profiles.evaluation_pairs(both)
    assert {p.scene for p in pairs if p.job.track == grid.TRANSFER_TRACK} == {*grid.TRANSFER_TRACK_SCENES, *grid.SPATIAL_TRANSFER_TRACK_SCENES}
    boards = {heading: board for heading, _, board in leaderboard.leaderboards(pairs)}
    transfer_heading = "planar, transfer track: trained on chain4-varied, 5 draws"
    spatial_heading = "3D, transfer track: trained on chain4-3d-varied, 5 draws"
    assert set(boards) == {"planar: trained on chain4", "3D: trained on chain4-3d", transfer_heading, spatial_heading}
    assert all(p.job.varied_draws for p in boards[transfer_heading])
    assert {p.scene for p in boards[spatial_heading]} == set(grid.SPATIAL_TRANSFER_TRACK_SCENES)
    assert {p.job.model for p in boards[spatial_heading]} == {"lgnn", "lgnn-notebook", "gns", "lgn", *grid.TRANSFER_ZOO}
    assert not any(p.job.varied_draws for p in boards["planar: trained on chain4"])
    # The track's tables list its scenes as its entries declare them (its training chain
    # first), the paper's tables theirs.
    assert report_summary.scene_groups(["T1", "chain8-varied", "chain4-varied", "chain4"], grid.TRANSFER_TRACK)[2] == [
        "chain4-varied", "chain8-varied", "T1", "chain4"]
    assert report_summary.scene_groups(["chain4-varied", "T1", "chain4"])[2] == ["chain4", "T1", "chain4-varied"]
    # A table's rows (summary, curves) by track: an external prediction stays with the paper's.
    import pandas as pd

    table = pd.DataFrame({"model": ["lgnn", "lgnn (chain4-varied, 5 draws)", "mine (external)", "rest"]})
    assert list(report_summary.track_rows(table, pairs, grid.PAPER_TRACK)["model"]) == ["lgnn", "mine (external)", "rest"]
    assert list(report_summary.track_rows(table, pairs, grid.TRANSFER_TRACK)["model"]) == ["lgnn (chain4-varied, 5 draws)", "mine (external)", "rest"]
    # The committed report: each track's tables apart, no transfer model among the paper's.
    sections = (Path(__file__).resolve().parents[1] / "results" / "README.md").read_text().split("\n## ")
    paper_table = next(s for s in sections if s.startswith("Rollout error against the Lagrangian ground truth (planar: trained on chain4"))
    transfer_table = next(s for s in sections if s.startswith(f"Rollout error against the Lagrangian ground truth ({transfer_heading})"))
    assert "draws)" not in paper_table.splitlines()[2] and "| lgnn-notebook |" in transfer_table.splitlines()[2]
    assert [row.split(" | ")[0].strip("| ") for row in transfer_table.splitlines()[4:11]] == list(grid.TRANSFER_TRACK_SCENES)
    spatial_table = next(s for s in sections if s.startswith(f"Rollout error against the Lagrangian ground truth ({spatial_heading})"))
    assert [row.split(" | ")[0].strip("| ") for row in spatial_table.splitlines()[4:11]] == list(grid.SPATIAL_TRANSFER_TRACK_SCENES)
    assert "not evaluated" not in spatial_table and "| cgnode |" in spatial_table.splitlines()[2]
    with pytest.raises(ConfigError, match="setting 'tracks': unknown track 'mine'"):
        profiles.load_profile("full", ['tracks=["mine"]'])
    with pytest.raises(ConfigError, match="'varied_draws' must be a whole number"):
        grid.GridEntry("lgnn", "chain4", ("chain4",), varied_draws=-1)


def test_a_transfer_entry_trains_on_its_draws_and_is_evaluated_on_other_chains(tmp_path):
    """A profile's transfer entry (GNS, 2 draws) through the benchmark's train and
    evaluate stages: the checkpoint's data are the draws', and the record of a varied
    8-link chain is scored."""
    from lgnn.bench import profiles
    from lgnn.bench.run import run
    from lgnn.bench.stages import evaluate
    from lgnn.learn import checkpoints

    config = tmp_path / "transfer.toml"
    config.write_text('seeds = [0]\ntrain_scenes = ["chain4-varied"]\nscenes = ["chain8-varied"]\nmodels = ["gns"]\n'
                      '[[grid]]\nmodel = "gns"\ntrain_scene = "chain4-varied"\neval_scenes = ["chain8-varied"]\nvaried_draws = 2\n'
                      '[training.data]\nn_trajectories = 4\nduration = 0.3\nsample_dt = 0.05\n'
                      '[training.train]\nepochs = 2\npatience = 2\nbatch_size = 4\n'
                      '[evaluate]\ninitial_conditions = 2\nduration = 0.05\nchunk = 2\n')
    profile = profiles.load_profile(config)
    run(profile, tmp_path / "out", stages=("train", "evaluate"), progress=False)
    (job,) = profiles.training_jobs(profile)
    meta, _ = checkpoints.read(tmp_path / "out" / "benchmark" / "checkpoints" / f"{job.name}.npz")
    assert meta["data"]["varied_draws"] == 2 and meta["model"]["link_features"]
    ((pair, (arrays, _)),) = evaluate.load_pairs(profile, tmp_path / "out")
    assert pair.scene == "chain8-varied" and np.isfinite(arrays["rollout_error/per_ic_log"]).all()
