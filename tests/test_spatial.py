"""Physics in 3D: a planar scene embedded at z = 0 moves exactly as in 2D; spatial
scenes conserve energy, keep their constraints, converge at RK4's order; accelerations
agree with an independent implementation in maximal coordinates."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lgnn import integrate, physics
from lgnn.engines.base import Integration, SimulationConfig
from lgnn.engines.lagrangian import simulate
from lgnn.scene import embedded_in_3d, get_scene, sample_initial_states, scene_names, spatial_chain, spatial_net
from lgnn.scene.catalogue import SPATIAL_CHAIN_CONE, SPATIAL_CHAIN_SPIN, double_pinned_chain


def random_state(scene, seed=0, speed=1.0):
    """The scene's positions with random velocities projected onto the manifold."""
    q = jnp.asarray(scene.nodes)
    qd = jnp.asarray(speed * np.random.default_rng(seed).normal(size=q.shape))
    return jax.jit(physics.projection_fn(scene))(q, qd)


# ---------------------------------------------------------------------------------
# The planar embedding
# ---------------------------------------------------------------------------------


@pytest.mark.parametrize("solver", ["generic", "schur"])
def test_embedded_planar_chain_has_the_planar_accelerations(solver):
    """The generic solve (learned models' path) and the Schur solve give an embedded
    chain the planar accelerations to round-off and no acceleration out of the plane
    (the z blocks of every matrix are decoupled)."""
    planar = get_scene("chain4-drag")
    spatial = embedded_in_3d(planar)
    assert spatial.dim == 3 and spatial.drag == planar.drag
    q, qd = random_state(planar, seed=1, speed=2.0)
    flat = np.asarray(jax.jit(physics.true_acceleration_fn(planar, solver))(q, qd))
    lift = lambda x: jnp.concatenate([x, jnp.zeros((len(x), 1))], axis=1)  # noqa: E731
    lifted = np.asarray(jax.jit(physics.true_acceleration_fn(spatial, solver))(lift(q), lift(qd)))
    np.testing.assert_allclose(lifted[:, :2], flat, rtol=0, atol=1e-13 * np.abs(flat).max())
    np.testing.assert_array_equal(lifted[:, 2], 0.0)


def test_embedded_planar_scene_reproduces_the_planar_trajectory():
    """0.5 s of RK4 with projection on a chain hanging between two pins (a loop through
    the ground): the embedded scene's trajectory and energy are the planar ones to
    round-off, and it never leaves the plane z = 0."""
    planar = double_pinned_chain()

    def trajectory(scene):
        integrator = integrate.rk4(physics.true_acceleration_fn(scene), 1e-3, physics.projection_fn(scene))
        frames = jax.jit(lambda: integrate.rollout(integrator, scene.initial_state, 50, 10))()
        return frames, jax.vmap(physics.energy_fn(scene))(*frames)

    (flat, flat_energy), (lifted, lifted_energy) = trajectory(planar), trajectory(embedded_in_3d(planar))
    np.testing.assert_allclose(lifted.q[..., :2], flat.q, rtol=0, atol=1e-12)
    np.testing.assert_allclose(lifted.qd[..., :2], flat.qd, rtol=0, atol=1e-11)
    np.testing.assert_array_equal(lifted.q[..., 2], 0.0)
    assert np.max(np.abs(flat.q[-1] - flat.q[0])) > 0.1  # it moves
    np.testing.assert_allclose(lifted_energy, flat_energy, rtol=0, atol=1e-12 * np.abs(flat_energy).max())


# ---------------------------------------------------------------------------------
# Energies and mass matrices in 3D
# ---------------------------------------------------------------------------------


def test_mass_matrix_of_a_spatial_rod():
    """A rod of mass m, inertia I about its centre, along the unit vector e: over its two
    ends' velocities `M = m/4 [[1, 1], [1, 1]] (x) 1 + I/l^2 [[1, -1], [-1, 1]] (x)
    (1 - e e^T)`: only the motion perpendicular to the rod turns it (no spin about its
    own axis)."""
    length, mass, inertia = 1.7, 2.3, 0.4
    e = np.array([0.36, -0.8, 0.48])
    scene = spatial_chain(1).replace(
        nodes=np.stack([np.zeros(3), length * e]), velocities=np.zeros((2, 3)),
        lengths=np.array([length]), masses=np.array([mass]), inertias=np.array([inertia]))
    mass_m = np.asarray(jax.jit(physics.mass_matrix_fn(physics.lagrangian_fn(scene)))(jnp.asarray(scene.nodes), jnp.zeros((2, 3))))
    expected = mass / 4 * np.kron(np.ones((2, 2)), np.eye(3)) + inertia / length**2 * np.kron([[1, -1], [-1, 1]], np.eye(3) - np.outer(e, e))
    np.testing.assert_allclose(mass_m, expected, rtol=1e-13, atol=1e-15)


def test_spatial_mass_matrix_is_symmetric_psd_and_gives_the_kinetic_energy():
    scene = get_scene("net4x4-3d")
    q, qd = random_state(scene, seed=2)
    mass = np.asarray(jax.jit(physics.mass_matrix_fn(physics.lagrangian_fn(scene)))(q, qd))
    np.testing.assert_allclose(mass, mass.T, atol=1e-12)
    eigenvalues = np.linalg.eigvalsh(mass)
    assert eigenvalues.min() > -1e-10 * eigenvalues.max()
    kinetic = jnp.sum(physics.kinetic_energy_per_link(scene, q, qd))
    np.testing.assert_allclose(0.5 * qd.ravel() @ mass @ qd.ravel(), kinetic, rtol=1e-12)
    constant_mass = jax.jit(jax.hessian(lambda v: physics.constant_mass_lagrangian_fn(scene)(q, v.reshape(q.shape))))(jnp.zeros(q.size))
    np.testing.assert_allclose(physics.constant_node_mass(scene), constant_mass, atol=1e-14)


def test_spatial_lagrangian_is_invariant_under_rotations_and_translations():
    """Without gravity the Lagrangian is invariant under any 3D rotation; with it, under
    rotations about the y axis, and a translation shifts it by the weight times dy."""
    scene = get_scene("net4x4-3d")
    q, qd = random_state(scene, seed=3)
    lagrangian = physics.lagrangian_fn(scene)
    weightless = physics.lagrangian_fn(scene.replace(gravity=np.asarray(0.0)))
    rotation, _ = np.linalg.qr(np.random.default_rng(4).normal(size=(3, 3)))
    np.testing.assert_allclose(weightless(q @ rotation.T, qd @ rotation.T), weightless(q, qd), rtol=1e-12)
    angle = 0.83
    about_y = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    np.testing.assert_allclose(lagrangian(q @ about_y.T, qd @ about_y.T), lagrangian(q, qd), rtol=1e-12)
    shift = jnp.asarray([0.3, -2.0, 1.1])
    weight = float(np.sum(scene.masses)) * float(scene.gravity)
    np.testing.assert_allclose(lagrangian(q + shift, qd), lagrangian(q, qd) - weight * float(shift[1]), rtol=1e-12)


# ---------------------------------------------------------------------------------
# The solves in 3D
# ---------------------------------------------------------------------------------

SPATIAL_TEST_SCENES = {
    "chain4-3d-drag": lambda: spatial_chain(4, seed=1).replace(drag=0.5),
    "chain90-3d": lambda: spatial_chain(90),
    "net4x4-3d": spatial_net,
}


@pytest.mark.parametrize("name", ["chain90-3d", "net4x4-3d"])
def test_spatial_solvers_agree(name):
    """The chain elimination with 4 x 4 blocks and the local-mass solve (on chain90-3d
    the chain elimination of a general Lagrangian) give the Schur solve's accelerations
    to round-off; the Schur and generic solves are checked against an independent
    implementation below."""
    scene = SPATIAL_TEST_SCENES[name]()
    q, qd = random_state(scene, seed=5, speed=2.0)
    reference = np.asarray(jax.jit(physics.true_acceleration_fn(scene, "schur"))(q, qd))
    tolerance = 1e-11 * (1 + np.abs(reference).max())
    if physics.prepare(scene).is_pinned_chain:
        qdd = np.asarray(jax.jit(physics.true_acceleration_fn(scene, "chain"))(q, qd))
        np.testing.assert_allclose(qdd, reference, atol=tolerance, err_msg="chain")
    lagrangian, drag = physics.lagrangian_fn(scene), physics.drag_force_fn(scene)
    local = np.asarray(jax.jit(physics.acceleration_fn(scene, lagrangian, drag, mass=physics.LOCAL))(q, qd))
    np.testing.assert_allclose(local, reference, atol=10 * tolerance, err_msg="local mass")


def maximal_coordinate_accelerations(scene, q, qd):
    """Node accelerations of `scene` at (q, qd), computed independently of lgnn.physics.

    Each rod k is a rigid body of its own: centre c_k and unit axis e_k (so its ends are
    `c_k +- l_k/2 e_k`), kinetic energy `1/2 m |c_k'|^2 + 1/2 I |e_k'|^2` (a thin rod:
    `|e'| = |omega_perp|`), a constant diagonal mass matrix. Explicit Lagrange
    multipliers enforce `|e_k| = 1`, that all rod ends at a node coincide, and that one
    rod end at each pinned node stays at its pin. Gravity `-m g` and drag `-c c_k'` act
    on the centres. One dense KKT solve in NumPy (float64)."""
    q, qd = np.asarray(q, np.float64), np.asarray(qd, np.float64)
    edges, lengths = scene.edge_index, np.asarray(scene.lengths)
    n_rods = len(edges)
    size = 6 * n_rods  # (c, e) per rod
    i, j = edges.T
    e = (q[i] - q[j]) / lengths[:, None]
    c_dot, e_dot = (qd[i] + qd[j]) / 2, (qd[i] - qd[j]) / lengths[:, None]
    mass = np.diag(np.repeat(np.stack([scene.masses, scene.inertias], 1), 3))  # (rod, c or e, xyz) flattened
    force = np.zeros((n_rods, 2, 3))
    force[:, 0, 1] = -np.asarray(scene.masses) * float(scene.gravity)
    force[:, 0] -= scene.drag * c_dot
    rows, speed_terms = [], []

    def end_row(rod, sign):
        """The row picking the position of rod's end (+1: its first node, -1: second)."""
        row = np.zeros((3, n_rods, 2, 3))
        row[:, rod, 0] = np.eye(3)
        row[:, rod, 1] = sign * lengths[rod] / 2 * np.eye(3)
        return row.reshape(3, size)

    for rod in range(n_rods):
        row = np.zeros((n_rods, 2, 3))
        row[rod, 1] = e[rod]
        rows.append(row.reshape(1, size))
        speed_terms.append([e_dot[rod] @ e_dot[rod]])  # d2/dt2 of (|e|^2 - 1)/2 beyond J x''
    ends = {}
    for rod, (a, b) in enumerate(edges):
        ends.setdefault(int(a), []).append((rod, 1.0))
        ends.setdefault(int(b), []).append((rod, -1.0))
    for node, incident in ends.items():
        first = end_row(*incident[0])
        for other in incident[1:]:
            rows.append(first - end_row(*other))  # linear in (c, e): no speed term
            speed_terms.append(np.zeros(3))
        if node in scene.pinned:
            rows.append(first)
            speed_terms.append(np.zeros(3))
    jac = np.concatenate(rows)
    speed = np.concatenate(speed_terms)
    k = len(jac)
    kkt = np.block([[mass, jac.T], [jac, np.zeros((k, k))]])
    assert np.linalg.matrix_rank(kkt) == size + k  # independent constraints, regular M
    solution = np.linalg.solve(kkt, np.concatenate([force.reshape(-1), -speed]))
    accel = solution[:size].reshape(n_rods, 2, 3)
    node_accel = np.zeros_like(q)
    for node, incident in ends.items():
        rod, sign = incident[0]
        node_accel[node] = accel[rod, 0] + sign * lengths[rod] / 2 * accel[rod, 1]
    return node_accel


@pytest.mark.parametrize("name", ["chain4-3d-drag", "net4x4-3d"])
def test_accelerations_match_an_independent_maximal_coordinate_solve(name):
    """Both ground-truth solves (the Schur solve of the constant on-manifold mass, the
    generic KKT solve of the exact Lagrangian by AD) against maximal coordinates, and
    their power: dH/dt = qd . F_drag (zero without drag; constraint forces do no work)."""
    scene = SPATIAL_TEST_SCENES[name]()
    q, qd = random_state(scene, seed=6, speed=2.0)
    expected = maximal_coordinate_accelerations(scene, q, qd)
    energy = physics.energy_fn(scene)
    drag = physics.drag_force_fn(scene)
    drag_power = 0.0 if drag is None else float(jnp.sum(qd * drag(q, qd)))
    gravity_power = float(jnp.sum(jnp.abs(qd * jax.grad(energy)(q, qd))))
    for solver in ("auto", "generic"):
        qdd = np.asarray(jax.jit(physics.true_acceleration_fn(scene, solver))(q, qd))
        np.testing.assert_allclose(qdd, expected, rtol=0, atol=1e-10 * np.abs(expected).max(), err_msg=solver)
        _, power = jax.jvp(energy, (q, qd), (qd, jnp.asarray(qdd)))
        assert abs(float(power) - drag_power) < 1e-12 * gravity_power, solver
    assert (drag is None) == (scene.drag == 0) and (drag is None or drag_power < -1e-3)


def test_spatial_projection_restores_constraints():
    scene = get_scene("net4x4-3d")
    rng = np.random.default_rng(9)
    q = jnp.asarray(scene.nodes + 1e-4 * rng.normal(size=scene.nodes.shape))
    q, qd = jax.jit(physics.projection_fn(scene))(q, jnp.asarray(rng.normal(size=scene.nodes.shape)))
    assert physics.constraint_violation(scene, q) < 1e-12
    assert physics.velocity_constraint_violation(scene, q, qd) < 1e-12


# ---------------------------------------------------------------------------------
# Integration in 3D
# ---------------------------------------------------------------------------------


def relative_energy_drift(trajectory):
    return float(np.max(np.abs(trajectory.energy - trajectory.energy[0])) / np.max(np.abs(trajectory.energy)))


@pytest.mark.parametrize(("name", "dt", "duration"), [
    ("chain4-3d", 1e-3, 1.0), ("net4x4-3d", 1e-3, 1.0), ("tensegrity-3d", 1e-3, 0.5),
    # The rope's 0.1 links swing fast once its helix falls: over 0.5 s its energy drifts
    # 4.6e-6 at dt 1e-3, 1.4e-7 at 5e-4 (RK4's fifth order in energy), so a finer step.
    ("rope-3d", 2.5e-4, 0.5),
])
def test_spatial_rk4_conserves_energy_and_constraints(name, dt, duration):
    scene = get_scene(name)
    trajectory = simulate(scene, SimulationConfig(dt=dt, frame_dt=1e-2, duration=duration))
    assert np.all(np.isfinite(trajectory.q))
    assert relative_energy_drift(trajectory) < 1e-8
    assert max(float(physics.constraint_violation(scene, q)) for q in trajectory.q) < 1e-10
    assert np.max(np.abs(trajectory.q[:, list(scene.pinned)] - scene.pin_positions)) == 0.0
    assert np.max(np.abs(trajectory.q[-1] - trajectory.q[0])) > 0.1  # it moves


def test_spatial_constraint_drift_without_projection_is_the_truncation_error():
    scene = get_scene("net4x4-3d")
    trajectory = simulate(scene, SimulationConfig(dt=1e-3, frame_dt=1e-2, duration=0.5), integration=Integration(project=False))
    violation = max(float(physics.constraint_violation(scene, q)) for q in trajectory.q)
    assert 1e-14 < violation < 1e-4


def test_spatial_rk4_convergence_order():
    """The slope of log(error) against log(dt) is 4 on the 3D 4-link chain (errors
    after 0.4 s against a run at dt / 16 of the finest, without projection as in 2D;
    dt and the step count are arguments, so one compiled run serves every dt)."""
    scene = get_scene("chain4-3d")
    duration, dts = 0.4, (4e-3, 2e-3, 1e-3)
    accel, state = physics.true_acceleration_fn(scene), scene.initial_state
    final = jax.jit(lambda dt, steps: integrate.rollout(integrate.rk4(accel, dt), state, 1, steps).q[-1])
    run = lambda dt: np.asarray(final(dt, round(duration / dt)))  # noqa: E731
    reference = run(dts[-1] / 16)
    errors = [float(np.max(np.linalg.norm(run(dt) - reference, axis=-1))) for dt in dts]
    slope = np.polyfit(np.log(dts), np.log(errors), 1)[0]
    assert abs(slope - 4) < 0.3, (errors, slope)


# ---------------------------------------------------------------------------------
# The spatial catalogue
# ---------------------------------------------------------------------------------


def test_spatial_chain_sampler():
    """Links in a cone of 45 degrees about -y with azimuths all round, unit lengths, the
    pin at its place, velocities that keep every link length (turning perpendicular to
    the links), different draws for different keys."""
    scene = get_scene("chain16-3d")
    states = sample_initial_states(scene, jax.random.PRNGKey(0), 100)
    dq = np.diff(np.asarray(states.q), axis=1)
    dqd = np.diff(np.asarray(states.qd), axis=1)
    np.testing.assert_allclose(np.linalg.norm(dq, axis=-1), 1.0, rtol=1e-12)
    polar = np.arccos(-dq[..., 1])
    assert polar.max() <= SPATIAL_CHAIN_CONE + 1e-9 and polar.max() > SPATIAL_CHAIN_CONE - 0.02
    azimuth = np.arctan2(dq[..., 2], dq[..., 0])
    assert np.histogram(azimuth, bins=8, range=(-np.pi, np.pi))[0].min() > 0
    np.testing.assert_allclose(np.sum(dq * dqd, -1), 0.0, atol=1e-12)
    # With dq . dqd = 0, the link's angular velocity is dq x dqd / l^2, perpendicular
    # to it; its rate spans [0, SPATIAL_CHAIN_SPIN] and its axis every direction.
    omega = np.cross(dq, dqd)
    rate = np.linalg.norm(omega, axis=-1)
    assert rate.max() <= SPATIAL_CHAIN_SPIN + 1e-12 and rate.max() > 0.95 * SPATIAL_CHAIN_SPIN and rate.min() < 0.05 * SPATIAL_CHAIN_SPIN
    assert np.all(np.abs(np.sum(omega * dq, -1)) <= 1e-12)
    np.testing.assert_allclose(np.abs(np.mean(omega / rate[..., None], axis=(0, 1))), 0.0, atol=0.05)
    np.testing.assert_array_equal(states.q[:, 0], 0.0)
    np.testing.assert_array_equal(states.qd[:, 0], 0.0)
    assert not np.allclose(states.q, sample_initial_states(scene, jax.random.PRNGKey(1), 100).q)


@pytest.mark.parametrize("name", list(scene_names("3d")))
def test_spatial_scenes_are_regular_3d_scenes(name):
    """Every spatial scene is 3D, regular at its start (no self-stress: no straight rope
    run between pins), and its constant mass is regular, so the fast solvers apply."""
    scene = get_scene(name)
    system = physics.prepare(scene)
    assert scene.dim == 3
    assert system.constraints.self_stresses == 0 and len(system.constraints.redundant) == 0
    assert system.regular_mass and system.solver() in ("schur", "chain")
    assert np.ptp(scene.nodes[:, 2]) > 0.1  # truly spatial
