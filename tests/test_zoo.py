"""The zoo's constrained models, CGNODE (`cgnode`), CHGN (`chgn`) and CHNN (`chnn`):
their formulations are the ground truth's physics when given the true forces or the
true Hamiltonian, their gradients match finite differences, their rollouts keep the
constraints, CHGN and CHNN conserve their learned energy, the graph models transfer to
another size (CHNN refuses one), and training lowers their loss."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lgnn import physics
from lgnn.engines.base import Integration, SimulationConfig
from lgnn.errors import ConfigError
from lgnn.learn import data, models, train
from lgnn.learn.models import cgnode, chgn, chnn
from lgnn.scene import State, get_scene

TINY_DATA = data.DataConfig(n_trajectories=6, duration=0.2, sample_dt=0.01, dt=1e-3)
ZOO = ("cgnode", "chgn", "chnn")
# Test sizes: the code, not the default widths (cgnode's are the strong GNS's 1.6M parameters).
SIZES = {"cgnode": dict(latent=8, hidden=8, message_passing=1), "chgn": dict(message_passing=1), "chnn": dict(hidden=16)}
# The models that learn a Hamiltonian, with their learned energy and momentum.
HAMILTONIAN = {"chgn": chgn, "chnn": chnn}
SHORT = SimulationConfig(dt=1e-3, frame_dt=1e-2, duration=0.2)


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    return data.load_or_generate(TINY_DATA, tmp_path_factory.mktemp("cache"))


def _training_arrays(dataset):
    return tuple(a[dataset.train] for a in (dataset.q, dataset.qd, dataset.qdd))


def _moving_states(scene, count=2, seed=0):
    """States on the constraint manifold with non-zero velocities, (B, N, D) each."""
    q = jnp.broadcast_to(jnp.asarray(scene.nodes), (count, *scene.nodes.shape))
    return jax.jit(jax.vmap(physics.projection_fn(scene)))(q, jax.random.normal(jax.random.PRNGKey(seed), q.shape))


def _model(name, dataset, seed=1):
    """`name` at test size for chain4, with chain4's training statistics, random params."""
    scene = get_scene("chain4")
    config = models.ModelConfig.for_scene(name, scene, **SIZES[name])
    statistics = models.training_statistics(config, scene, *_training_arrays(dataset))
    return config, models.with_statistics(models.init(jax.random.PRNGKey(seed), config), statistics)


def _true_node_mass(scene):
    return cgnode.node_mass(scene, np.asarray(scene.masses, float), np.asarray(scene.inertias, float))


def _true_forces(scene):
    """Gravity and the scene's drag on the free nodes, (N, D)."""
    drag = physics.drag_force_fn(scene)
    free = jnp.asarray(physics.Constraints(scene).free_mask, float)
    gravity = jnp.asarray(physics.prepare(scene).node_gravity)
    return lambda q, qd: gravity if drag is None else gravity + drag(q, qd) * free


# ---------------------------------------------------------------------------------
# The formulations are the physics
# ---------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["chain4-drag", "chain4-3d"])
def test_the_formulations_with_the_true_forces_or_hamiltonian_give_the_ground_truth(name):
    """CGNODE's mass-metric projection of the unconstrained `M^-1 F` and CHGN's
    constrained Hamiltonian equations of the scene's own rods, gravity and drag are the
    ground truth's accelerations; the assembled node mass is the ground truth's
    constant on-manifold mass, and the Hamiltonian is the scene's energy."""
    scene = get_scene(name)
    mass = _true_node_mass(scene)
    np.testing.assert_allclose(np.kron(mass, np.eye(scene.dim)), physics.constant_node_mass(scene), atol=1e-14)
    q, qd = (a[0] for a in _moving_states(scene, 1))
    truth = physics.true_acceleration_fn(scene)(q, qd)
    free = jnp.asarray(scene.free_nodes)
    unconstrained = jnp.zeros_like(q).at[free].set(jnp.linalg.solve(mass[jnp.ix_(free, free)], _true_forces(scene)(q, qd)[free]))
    solve = jax.jit(cgnode.constrained_solve_fn(scene))
    np.testing.assert_allclose(solve(mass, q, qd, mass @ unconstrained), truth, atol=1e-10)
    # A prediction that already satisfies the constraints is kept.
    np.testing.assert_allclose(solve(mass, q, qd, mass @ truth), truth, atol=1e-10)
    potential = lambda x: jnp.sum(physics.potential_energy_per_link(scene, x))  # noqa: E731
    hamiltonian = chgn.separable_hamiltonian_fn(scene, lambda: mass, potential)
    assert float(hamiltonian(q, mass @ qd)) == pytest.approx(float(physics.energy_fn(scene)(q, qd)), rel=1e-12)
    accel = jax.jit(chgn.constrained_hamiltonian_fn(scene, lambda: mass, hamiltonian, physics.drag_force_fn(scene)))
    np.testing.assert_allclose(accel(q, qd), truth, atol=1e-10)


def test_the_linear_time_chain_solve_equals_the_dense_one():
    """From `CHAIN_SOLVER_MIN_LINKS` links a pinned chain takes `chain_kkt_solve`."""
    scene = get_scene("chain100")
    assert physics.prepare(scene).long_chain
    mass = _true_node_mass(scene)
    q, qd = (a[0] for a in _moving_states(scene, 1))
    force = _true_forces(scene)(q, qd) + jax.random.normal(jax.random.PRNGKey(5), q.shape) * jnp.asarray(physics.Constraints(scene).free_mask, float)
    chain, dense = (jax.jit(cgnode.constrained_solve_fn(scene, structured=s))(mass, q, qd, force) for s in (True, False))
    np.testing.assert_allclose(chain, dense, atol=1e-9 * float(jnp.max(jnp.abs(dense))))


def test_chgn_mass_is_positive_definite_and_the_solve_keeps_the_constraints(tiny_dataset):
    """On T1 (ropes, braces, loops): CHGN's learned rod form is positive for any seed (five here),
    so its node mass is positive definite on the free nodes, and the solve both models
    share gives accelerations with `A qdd + Adot qd = 0` on every link for any force
    (the models' own accelerations: the unprojected rollouts below)."""
    scene = get_scene("T1")
    free = np.asarray(scene.free_nodes)
    config, params = _model("chgn", tiny_dataset)
    statistics = params[models.STATISTICS]
    forms = jax.jit(jax.vmap(lambda key: chgn.rod_form(config, models.with_statistics(models.init(key, config), statistics), scene)))
    for masses, inertias in zip(*forms(jax.random.split(jax.random.PRNGKey(0), 5))):
        assert np.all(masses > 0) and np.all(inertias > 0)
        eigenvalues = np.linalg.eigvalsh(np.asarray(cgnode.node_mass(scene, masses, inertias))[np.ix_(free, free)])
        assert eigenvalues[0] > 1e-3 * eigenvalues[-1]
    q, qd = (a[0] for a in _moving_states(scene, 1))
    force = 10.0 * jax.random.normal(jax.random.PRNGKey(6), q.shape)
    qdd = jax.jit(cgnode.constrained_solve_fn(scene))(cgnode.node_mass(scene, masses, inertias), q, qd, force)
    i, j = scene.edge_index.T
    # d2/dt2 |q_i - q_j|^2 / 2 = dq . dqdd + |dqd|^2 on every link.
    rate = jnp.sum((q[i] - q[j]) * (qdd[i] - qdd[j]), -1) + jnp.sum((qd[i] - qd[j]) ** 2, -1)
    assert float(jnp.max(jnp.abs(rate))) < 1e-9 * float(jnp.max(jnp.abs(qdd)))
    assert np.all(np.asarray(qdd)[list(scene.pinned)] == 0)


def test_chnn_mass_is_positive_definite_and_can_be_the_rods_node_mass(tiny_dataset):
    """CHNN's learned constant mass is positive definite for any seed, and its
    parametrisation holds the rods' exact on-manifold node mass (a dense matrix, not a
    diagonal one), so with the true potential its dynamics would be the ground truth's
    (the formulation test above)."""
    scene = get_scene("chain4")
    config, params = _model("chnn", tiny_dataset)
    for key in jax.random.split(jax.random.PRNGKey(0), 5):
        mass = np.asarray(chnn.node_mass_fn(config, {**models.init(key, config), "statistics": params["statistics"]}, scene)())
        assert np.linalg.eigvalsh(mass)[0] > 0
    true = np.asarray(_true_node_mass(scene))
    lower = np.linalg.cholesky(true / float(params["statistics"]["mass_scale"]))
    factor = np.tril(lower, -1) + np.diag(np.log(np.expm1(np.diag(lower))))  # softplus inverse on the diagonal
    np.testing.assert_allclose(chnn.node_mass_fn(config, {**params, "mass_factor": jnp.asarray(factor)}, scene)(), true, rtol=1e-12, atol=1e-14)


# ---------------------------------------------------------------------------------
# Learning and rollouts
# ---------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ZOO)
def test_loss_gradient_matches_finite_differences(tiny_dataset, name):
    scene = get_scene("chain4")
    config, params = _model(name, tiny_dataset)
    q, qd = _moving_states(scene)
    qdd = jax.vmap(physics.true_acceleration_fn(scene))(q, qd)
    # One compiled program for the gradient and the losses of the differences.
    value_and_grad = jax.jit(jax.value_and_grad(train.loss_fn(config, scene)))
    loss = lambda p, *batch: value_and_grad(p, *batch)[0]  # noqa: E731
    trainable, statistics = models.split_statistics(params)
    grads = models.split_statistics(value_and_grad(params, q, qd, qdd)[1])[0]
    direction = jax.tree.map(lambda x: jax.random.normal(jax.random.PRNGKey(3), x.shape), trainable)
    analytic = sum(jnp.vdot(g, d) for g, d in zip(jax.tree.leaves(grads), jax.tree.leaves(direction)))
    eps = 1e-6
    shifted = lambda s: models.join_statistics(jax.tree.map(lambda p, d: p + s * d, trainable, direction), statistics)  # noqa: E731
    numeric = (loss(shifted(eps), q, qd, qdd) - loss(shifted(-eps), q, qd, qdd)) / (2 * eps)
    assert abs(analytic) > 1e-3
    assert abs(analytic - numeric) <= 1e-6 * max(1.0, abs(analytic))


@pytest.fixture(scope="module")
def unprojected_rollouts(tiny_dataset):
    """Each model's untrained rollout of chain4 without the per-step projection, from a
    moving state (an untrained potential alone moves the chain little)."""
    scene = get_scene("chain4")
    start = State(*(a[0] for a in _moving_states(scene, 1, seed=4)))
    return {name: models.rollout(*_model(name, tiny_dataset), scene, SHORT, start, integration=Integration(project=False)) for name in ZOO}


@pytest.mark.parametrize("name", ZOO)
def test_untrained_rollouts_keep_the_constraints_and_transfer_to_a_larger_chain(tiny_dataset, unprojected_rollouts, name):
    """Without projection the drift of link lengths is the integrator's truncation
    error only (the accelerations satisfy the constraints); chain4's params roll out on
    chain8 with the engine's projection, which holds link lengths to its 1e-10."""
    scene = get_scene("chain4")
    trajectory = unprojected_rollouts[name]
    assert max(float(physics.constraint_violation(scene, q)) for q in trajectory.q) < 1e-6
    assert np.max(np.abs(trajectory.q[-1] - trajectory.q[0])) > 1e-2  # it moved
    larger = get_scene("chain8")
    if models.get_spec(name).fixed_size:
        with pytest.raises(ConfigError, match="tied to its training system size"):
            models.rollout(*_model(name, tiny_dataset), larger, SHORT)
        return
    trajectory = models.rollout(*_model(name, tiny_dataset), larger, SimulationConfig(dt=1e-3, frame_dt=1e-2, duration=0.1))
    assert trajectory.q.shape[1:] == (9, 2) and np.all(np.isfinite(trajectory.q))
    assert max(float(physics.constraint_violation(larger, q)) for q in trajectory.q) < 1e-10


@pytest.mark.parametrize("name", HAMILTONIAN)
def test_hamiltonian_models_conserve_their_learned_hamiltonian(tiny_dataset, unprojected_rollouts, name):
    """On a conservative scene (chain4, no drag) the untrained model's rollout keeps its
    own Hamiltonian `H(q, M qd)`, not the scene's true energy."""
    config, params = _model(name, tiny_dataset)
    scene = get_scene("chain4")
    trajectory = unprojected_rollouts[name]
    q, qd = jnp.asarray(trajectory.q), jnp.asarray(trajectory.qd)
    energy = jax.jit(jax.vmap(HAMILTONIAN[name].energy_fn(config, params, scene)))(q, qd)
    momentum = HAMILTONIAN[name].momentum_fn(config, params, scene)
    kinetic = jnp.max(jax.vmap(lambda v: 0.5 * jnp.vdot(v, momentum(None, v)))(qd))
    drift = float(jnp.max(jnp.abs(energy - energy[0])) / kinetic)
    assert float(kinetic) > 1e-2 and drift < 1e-8, drift
    assert np.max(np.abs(trajectory.energy - trajectory.energy[0])) / float(kinetic) > 1e3 * drift
