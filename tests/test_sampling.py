"""`physics.sample_initial_conditions`: random initial states of any scene, on its
constraint manifold, different from each other and reproducible by seed."""

import numpy as np
import pytest

from lgnn import physics
from lgnn.errors import ConfigError
from lgnn.scene import get_scene
from lgnn.scene.catalogue import free_triangle

# A truss with closed loops, a free body (no pins) and a chain of unequal links.
SCENES = {"T1": lambda: get_scene("T1"), "free_triangle": free_triangle, "chain4-varied": lambda: get_scene("chain4-varied")}


@pytest.mark.parametrize("name", sorted(SCENES))
def test_samples_satisfy_every_constraint_and_differ(name):
    scene = SCENES[name]()
    states = physics.sample_initial_conditions(scene, 6, seed=3)
    assert states.q.shape == states.qd.shape == (6, *scene.nodes.shape)
    length = float(np.mean(scene.lengths))
    for q, qd in zip(states.q, states.qd):
        assert float(physics.constraint_violation(scene, q)) < 1e-9 * length
        assert float(physics.velocity_constraint_violation(scene, q, qd)) < 1e-9 * np.sqrt(10 * length)
        np.testing.assert_array_equal(q[list(scene.pinned)], scene.nodes[list(scene.pinned)])
    # Perturbations, not copies: every pair of samples differs in position and velocity,
    # by about the sampler's scale (5 % of a link, 0.1 sqrt(g l)), not by round-off.
    free = list(scene.free_nodes)
    for a in range(6):
        for b in range(a):
            assert np.abs(states.q[a, free] - states.q[b, free]).max() > 1e-3 * length
            assert np.abs(states.qd[a, free] - states.qd[b, free]).max() > 1e-3
    assert np.abs(states.q[:, free] - scene.nodes[free]).max() < 0.5 * length


def test_samples_are_reproducible_by_seed():
    scene = get_scene("T1")
    first, again = physics.sample_initial_conditions(scene, 3, 7), physics.sample_initial_conditions(scene, 3, 7)
    other = physics.sample_initial_conditions(scene, 3, 8)
    np.testing.assert_array_equal(first.q, again.q)
    np.testing.assert_array_equal(first.qd, again.qd)
    assert not np.allclose(first.q, other.q)


def test_zero_scales_give_the_scenes_own_state():
    scene = get_scene("chain4-varied")
    states = physics.sample_initial_conditions(scene, 2, 0, position_scale=0.0, velocity_scale=0.0)
    np.testing.assert_allclose(states.q, np.broadcast_to(scene.nodes, states.q.shape), atol=1e-12)
    np.testing.assert_allclose(states.qd, 0.0, atol=1e-12)


def test_bad_counts_are_one_line_errors():
    with pytest.raises(ConfigError, match="at least one initial condition"):
        physics.sample_initial_conditions(get_scene("chain4"), 0, 0)


def test_the_benchmark_samples_a_users_scene_and_keeps_the_papers_choices(tmp_path):
    """Chains keep the paper's sampler and T1 its own rest state (records stay valid); a
    user's scene file gets sampled initial conditions, not copies of its state."""
    from lgnn.scene import sample_initial_states, scene_to_json

    chain = get_scene("chain4")
    paper = sample_initial_states(chain, __import__("jax").random.PRNGKey(1), 3)
    np.testing.assert_array_equal(physics.benchmark_initial_states(chain, 3, 1).q, paper.q)
    t1 = get_scene("T1")
    np.testing.assert_array_equal(physics.benchmark_initial_states(t1, 2, 1).q, np.broadcast_to(t1.nodes, (2, *t1.nodes.shape)))
    path = tmp_path / "mine.json"
    path.write_text(scene_to_json(t1.replace(name="mine")))
    mine = get_scene(str(path))
    np.testing.assert_array_equal(physics.benchmark_initial_states(mine, 3, 1).q, physics.sample_initial_conditions(mine, 3, 1).q)


def test_the_self_stressed_trusses_are_sampled_within_their_stated_tolerance():
    """T3 (four self-stresses; T2 has one) is singular at its own state: one round of 8
    Gauss-Newton steps left a violation of 1e-4 of a link (the old fixed rule refused
    it); repeated rounds bring it below `SINGULAR_TOLERANCE`, and samples still differ."""
    from lgnn.physics import sampling

    scene = get_scene("T3")
    states = physics.sample_initial_conditions(scene, 4, seed=0)
    length, speed = float(np.mean(scene.lengths)), np.sqrt(abs(float(scene.gravity)) * float(np.mean(scene.lengths)))
    for q, qd in zip(states.q, states.qd):
        assert float(physics.constraint_violation(scene, q)) < sampling.SINGULAR_TOLERANCE * length
        assert float(physics.velocity_constraint_violation(scene, q, qd)) < sampling.SINGULAR_TOLERANCE * speed
    assert np.abs(states.q[0] - states.q[1]).max() > 1e-3 * length
    # The regular scenes keep the strict tolerance (a looser one is only for self-stresses).
    assert sampling.TOLERANCE["float64"] < sampling.SINGULAR_TOLERANCE


def test_a_new_builtin_and_the_same_scene_as_a_file_start_alike(tmp_path, monkeypatch):
    """The initial states follow the catalogue entry's policy, not whether a scene is a
    chain: a new non-chain built-in with projected perturbations gets the profile's
    count of sampled states, and its file (same content) the very same ones; an entry
    that keeps its own state gets one initial condition, its file too."""
    from lgnn.bench.profiles import PROFILES
    from lgnn.bench.stages.evaluate import evaluation_initial_states
    from lgnn.scene import CATALOGUE, OWN_STATE, PROJECTED, CatalogueEntry, scene_to_json
    from lgnn.scene.catalogue import double_pinned_chain

    profile = PROFILES["quick"]
    count = profile.evaluate.initial_conditions
    hammock = lambda: double_pinned_chain().replace(name="hammock")  # noqa: E731
    for policy, expected in ((PROJECTED, count), (OWN_STATE, 1)):
        monkeypatch.setitem(CATALOGUE, "hammock", CatalogueEntry("hammock", "a test scene", hammock, ("planar", "hard"), policy))
        path = tmp_path / f"hammock-{expected}.json"
        path.write_text(scene_to_json(hammock()))
        builtin, from_file = (evaluation_initial_states(profile, get_scene(source)) for source in ("hammock", str(path)))
        assert len(builtin.q) == expected
        # Exact: equal scenes share the sampler's program (cached per scene content).
        np.testing.assert_array_equal(builtin.q, from_file.q)
        np.testing.assert_array_equal(builtin.qd, from_file.qd)
    monkeypatch.delitem(CATALOGUE, "hammock")
    assert len(evaluation_initial_states(profile, hammock()).q) == count  # not in the catalogue: projected perturbations
