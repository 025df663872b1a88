"""Physics of the constrained Lagrangian: energies, mass matrices, invariances, the solve."""

import functools
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lgnn import integrate, physics
from lgnn.scene import is_pinned_chain, scene_from_dict, scene_to_json
from lgnn.scene import chain, get_scene, sample_initial_states, scene_names
from lgnn.scene.catalogue import double_pinned_chain, free_triangle, pendulum, pinned_triangle, spatial_chain


def _spy_on_branches(monkeypatch, where: str) -> list:
    """The predicates (True: the first branch) of every `jax.lax.cond` traced from here
    on whose first branch is defined in a function named `where`, in the order they
    run: which branch a compiled function took, where both branches give the same
    numbers to round-off and the values cannot tell."""
    taken, cond = [], jax.lax.cond

    def spied(pred, true_fun, *args, **kwargs):
        if where in true_fun.__qualname__:
            jax.debug.callback(lambda p: taken.append(bool(p)), pred)
        return cond(pred, true_fun, *args, **kwargs)

    monkeypatch.setattr(jax.lax, "cond", spied)
    return taken


def random_state(scene, seed=0, speed=1.0):
    """A state on the constraint manifold: the scene's positions with random admissible velocities."""
    rng = np.random.default_rng(seed)
    q = jnp.asarray(scene.nodes)
    qd = jnp.asarray(speed * rng.normal(size=q.shape))
    _, qd = jax.jit(physics.projection_fn(scene))(q, qd)
    return q, qd


@pytest.mark.parametrize("name", ["chain4", "chain4-varied", "T1"])
def test_mass_matrix_symmetric_positive_semidefinite(name):
    scene = get_scene(name)
    q, qd = random_state(scene)
    mass = jax.jit(physics.mass_matrix_fn(physics.lagrangian_fn(scene)))(q, qd)
    np.testing.assert_allclose(mass, mass.T, atol=1e-12)
    eigenvalues = np.linalg.eigvalsh(np.asarray(mass))
    assert eigenvalues.min() > -1e-10 * eigenvalues.max()


def test_mass_matrix_of_a_pendulum_is_the_rods_at_its_angle():
    """A rod of mass m, inertia I = m l^2 / 12 about its centre, at angle a from the
    vertical: over its two ends' velocities `M = m/4 [[1, 1], [1, 1]] (x) 1 + I/l^2
    [[1, -1], [-1, 1]] (x) t t^T`, t the unit normal to the rod (v_cm = mean of the
    ends' velocities, omega = t . (v_1 - v_0) / l)."""
    length, mass, angle = 1.7, 2.3, 0.4
    scene = pendulum(angle, length, mass)
    mass_m = np.asarray(physics.mass_matrix_fn(physics.lagrangian_fn(scene))(jnp.asarray(scene.nodes), jnp.zeros((2, 2))))
    normal = np.array([np.cos(angle), np.sin(angle)])
    expected = mass / 4 * np.kron(np.ones((2, 2)), np.eye(2)) + mass / 12 * np.kron([[1, -1], [-1, 1]], np.outer(normal, normal))
    np.testing.assert_allclose(mass_m, expected, rtol=1e-13, atol=1e-15)


def test_mass_matrix_of_an_l_shaped_double_pendulum():
    """Unit rods (m = 1, I = 1/12): one hanging from the pin, one horizontal from its
    end. The free nodes' blocks, by hand: node 1 sees both rods, `(1/4 + 1/4) 1 + 1/12
    (e_x e_x^T + e_y e_y^T) = 7/12 1`; the pair couples through the second rod only,
    `1/4 1 - 1/12 e_y e_y^T`; node 2, `1/4 1 + 1/12 e_y e_y^T`."""
    scene = scene_from_dict({
        "name": "double-pendulum", "nodes": [[0, 0], [0, -1], [1, -1]], "pinned": [0],
        "links": [{"nodes": [0, 1], "mass": 1.0, "inertia": 1 / 12}, {"nodes": [1, 2], "mass": 1.0, "inertia": 1 / 12}],
    })
    mass_m = np.asarray(physics.mass_matrix_fn(physics.lagrangian_fn(scene))(jnp.asarray(scene.nodes), jnp.zeros((3, 2))))
    expected = np.array([
        [7 / 12, 0, 1 / 4, 0],
        [0, 7 / 12, 0, 1 / 6],
        [1 / 4, 0, 1 / 4, 0],
        [0, 1 / 6, 0, 1 / 3],
    ])
    np.testing.assert_allclose(mass_m[2:, 2:], expected, rtol=1e-13, atol=1e-15)


def test_kinetic_energy_is_quadratic_form_of_mass_matrix():
    scene = get_scene("chain4-varied")
    q, qd = random_state(scene, seed=3)
    mass = jax.jit(physics.mass_matrix_fn(physics.lagrangian_fn(scene)))(q, qd)
    kinetic = jnp.sum(physics.kinetic_energy_per_link(scene, q, qd))
    np.testing.assert_allclose(0.5 * qd.ravel() @ mass @ qd.ravel(), kinetic, rtol=1e-12)


def test_pendulum_energy_is_physical_pendulum_energy():
    """A rod about its end: T = 1/2 (m l^2 / 3) theta_dot^2, V = -m g (l/2) cos(theta)."""
    length, mass, gravity, angle, rate = 1.7, 2.3, 9.81, 0.4, -1.1
    scene = pendulum(angle, length, mass, gravity)
    q = jnp.asarray(scene.nodes)
    qd = jnp.asarray([[0.0, 0.0], [length * rate * np.cos(angle), length * rate * np.sin(angle)]])
    expected = 0.5 * mass * length**2 / 3 * rate**2 - mass * gravity * length / 2 * np.cos(angle)
    np.testing.assert_allclose(physics.energy_fn(scene)(q, qd), expected, rtol=1e-14)
    # and the Hamiltonian built generically from the Lagrangian agrees
    np.testing.assert_allclose(physics.hamiltonian_fn(physics.lagrangian_fn(scene))(q, qd), expected, rtol=1e-14)


def test_pendulum_acceleration_is_physical_pendulum():
    """theta_ddot = -(3 g / 2 l) sin(theta) for a uniform rod about its end."""
    length, gravity, angle = 1.3, 10.0, 0.7
    scene = pendulum(angle, length, 1.0, gravity)
    qdd = jax.jit(physics.true_acceleration_fn(scene))(jnp.asarray(scene.nodes), jnp.zeros((2, 2)))
    theta_ddot = -1.5 * gravity / length * np.sin(angle)
    expected_tip = length * theta_ddot * np.array([np.cos(angle), np.sin(angle)])
    np.testing.assert_allclose(qdd[1], expected_tip, rtol=1e-12)
    np.testing.assert_array_equal(qdd[0], 0.0)


@pytest.mark.parametrize("name", ["chain4", "T2"])
def test_lagrangian_invariant_under_translation_and_rotation(name):
    scene = get_scene(name)
    q, qd = random_state(scene, seed=1)
    lagrangian = physics.lagrangian_fn(scene)
    flat = physics.lagrangian_fn(scene.replace(gravity=np.asarray(0.0)))
    shift = jnp.asarray([0.3, -2.0])
    # translation: T unchanged, V shifts by the constant total m g dy
    total_mass = float(np.sum(scene.masses))
    np.testing.assert_allclose(
        lagrangian(q + shift, qd), lagrangian(q, qd) - total_mass * float(scene.gravity) * float(shift[1]), rtol=1e-12
    )
    angle = 0.83
    rotation = jnp.asarray([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    np.testing.assert_allclose(flat(q @ rotation.T, qd @ rotation.T), flat(q, qd), rtol=1e-12)


@pytest.mark.parametrize("scene_fn", [lambda: get_scene("chain4"), lambda: get_scene("chain4-varied"), lambda: get_scene("T1"), double_pinned_chain])
def test_constant_mass_lagrangian_gives_same_accelerations(scene_fn):
    """The singular rod mass matrix and its regular on-manifold equivalent give the same
    constrained accelerations: the KKT solve is insensitive to M's null directions.
    (Regular configurations only: at T2/T3's self-stressed rest state the acceleration-
    level equations are not unique, see lgnn/physics/dynamics.py.)"""
    scene = scene_fn()
    q, qd = random_state(scene, seed=2)
    exact = jax.jit(physics.acceleration_fn(scene, physics.lagrangian_fn(scene)))(q, qd)
    regular = jax.jit(physics.acceleration_fn(scene, physics.constant_mass_lagrangian_fn(scene)))(q, qd)
    np.testing.assert_allclose(exact, regular, atol=1e-10 * (1 + np.abs(regular).max()))


def test_kkt_solve_matches_papers_formula_when_mass_matrix_is_invertible():
    """With an invertible M, Eq. (acc) of the paper (M^-1 and (A M^-1 A^T)^-1) gives the same."""
    scene = get_scene("chain4-drag")
    q, qd = random_state(scene, seed=4)
    lagrangian = physics.constant_mass_lagrangian_fn(scene)
    ours = jax.jit(physics.acceleration_fn(scene, lagrangian, physics.drag_force_fn(scene)))(q, qd)

    constraints = physics.Constraints(scene)
    reduced = lambda x, v: lagrangian(constraints.embed(x), constraints.embed_velocity(v))  # noqa: E731

    @jax.jit
    def papers_equation(x, v):
        mass = jax.hessian(reduced, argnums=1)(x, v)
        coriolis = jax.jacfwd(jax.grad(reduced, argnums=1), argnums=0)(x, v)
        pi = jax.grad(reduced, argnums=0)(x, v)
        drag = constraints.restrict(physics.drag_force_fn(scene)(constraints.embed(x), constraints.embed_velocity(v)))
        jac, jdot_v = constraints.jacobian(x), constraints.jacobian_dot_v(x, v)
        m_inv = jnp.linalg.inv(mass)
        force = pi - coriolis @ v + drag
        lam = jnp.linalg.solve(jac @ m_inv @ jac.T, jac @ m_inv @ force + jdot_v)
        return m_inv @ (force - jac.T @ lam)

    paper = papers_equation(constraints.restrict(q), constraints.restrict(qd))
    np.testing.assert_allclose(constraints.restrict(ours), paper, rtol=1e-9, atol=1e-11)


def test_accelerations_keep_link_lengths_to_second_order():
    """A qdd + Adot qd = 0: the acceleration keeps every link length stationary."""
    scene = get_scene("T1")
    q, qd = random_state(scene, seed=5)
    qdd = jax.jit(physics.true_acceleration_fn(scene))(q, qd)
    i, j = scene.edge_index.T
    dq, dqd, dqdd = q[i] - q[j], qd[i] - qd[j], qdd[i] - qdd[j]
    second_derivative_of_length_squared = 2 * (jnp.sum(dqd * dqd, -1) + jnp.sum(dq * dqdd, -1))
    np.testing.assert_allclose(second_derivative_of_length_squared, 0.0, atol=1e-9)
    np.testing.assert_array_equal(qdd[np.asarray(scene.pinned)], 0.0)


def test_collinear_chain_has_finite_exact_accelerations():
    """A straight chain makes the rod mass matrix exactly singular (every link's stretch
    direction lines up); the KKT solve still gives finite accelerations equal to those
    of the regular on-manifold Lagrangian."""
    scene = get_scene("chain4")
    angle = 0.5
    q = jnp.asarray([[k * np.sin(angle), -k * np.cos(angle)] for k in range(5)])
    qd = jnp.zeros_like(q)
    mass = jax.jit(physics.mass_matrix_fn(physics.lagrangian_fn(scene)))(q, qd)
    eigenvalues = np.linalg.eigvalsh(np.asarray(mass))
    assert abs(eigenvalues[0]) < 1e-12 * eigenvalues[-1]  # singular: M^-1 of Eq. (acc) would fail
    exact = jax.jit(physics.acceleration_fn(scene, physics.lagrangian_fn(scene)))(q, qd)
    regular = jax.jit(physics.acceleration_fn(scene, physics.constant_mass_lagrangian_fn(scene)))(q, qd)
    assert np.all(np.isfinite(exact))
    np.testing.assert_allclose(exact, regular, atol=1e-10)


def test_redundant_constraints_rigid_triangle_stays_at_rest():
    """A rigid triangle pinned at two corners cannot move: the acceleration is exactly
    zero although the constraints are redundant (3 links, 2 pins, 3 nodes)."""
    scene = pinned_triangle()
    constraints = physics.Constraints(scene)
    assert constraints.n_rows == 2 and list(constraints.redundant) == [0]
    qdd = jax.jit(physics.true_acceleration_fn(scene))(jnp.asarray(scene.nodes), jnp.zeros((3, 2)))
    np.testing.assert_allclose(qdd, 0.0, atol=1e-14)


def test_structural_redundancy_is_dropped_but_singular_configurations_are_not():
    """An over-braced square (K4: 6 links on 4 nodes) has one structurally redundant row,
    at every configuration. T2 and T3 are only singular at rest (self-stressed taut
    ropes): no row may be dropped there, or the dropped link would stretch."""
    braced = scene_from_dict(
        {
            "name": "braced-square",
            "nodes": [[0.0, 0.0], [1.0, 0.0], [1.0, -1.0], [0.0, -1.0]],
            "pinned": [],
            "links": [{"nodes": pair, "mass": 1.0, "inertia": 0.1} for pair in ([0, 1], [1, 2], [2, 3], [3, 0], [0, 2], [1, 3])],
        }
    )
    assert len(physics.Constraints(braced).redundant) == 1
    for name, self_stresses in (("T1", 0), ("T2", 1), ("T3", 4)):
        constraints = physics.Constraints(get_scene(name))
        assert len(constraints.redundant) == 0, name
        assert constraints.self_stresses == self_stresses, name


def test_free_body_falls_with_gravity_and_keeps_spinning():
    """No pins: the centre of mass accelerates at exactly -g and no pin rows exist."""
    scene = free_triangle()
    q, qd = jnp.asarray(scene.nodes), jnp.asarray(scene.velocities)
    qdd = jax.jit(physics.true_acceleration_fn(scene))(q, qd)
    masses = jnp.asarray(scene.masses)
    i, j = scene.edge_index.T
    com_acc = jnp.sum(masses[:, None] * 0.5 * (qdd[i] + qdd[j]), 0) / masses.sum()
    np.testing.assert_allclose(com_acc, [0.0, -float(scene.gravity)], atol=1e-12)


def test_drag_dissipates_energy_at_the_expected_rate():
    """dH/dt = qd . F_drag (constraint forces do no work)."""
    scene = get_scene("chain4-drag")
    q, qd = random_state(scene, seed=6)
    accel = physics.true_acceleration_fn(scene)
    qdd = accel(q, qd)
    energy = physics.energy_fn(scene)
    _, power = jax.jvp(energy, (q, qd), (qd, qdd))
    expected = jnp.sum(qd * physics.drag_force_fn(scene)(q, qd))
    assert expected < 0
    np.testing.assert_allclose(power, expected, rtol=1e-9)
    assert physics.drag_force_fn(get_scene("chain4")) is None  # no drag term when there is no drag


@pytest.mark.parametrize("solver", ["generic", "auto"])
def test_joint_damping_dissipates_twice_its_dissipation_function(solver):
    """dH/dt = qd . F = -2 D with D = 1/2 sum b (omega_e - omega_p)^2 (D is quadratic in
    qd), on every solve path; with drag too, each term adds its own power."""
    import dataclasses

    from lgnn.physics.energies import link_angular_velocity

    drag = get_scene("chain4-drag")
    scene = dataclasses.replace(drag, dampers=((0, -1, 0.3), (1, 0, 0.05), (2, 1, 0.2), (3, 2, 0.1)))
    q, qd = random_state(scene, seed=6)
    qdd = physics.true_acceleration_fn(scene, solver)(q, qd)
    _, power = jax.jvp(physics.energy_fn(scene), (q, qd), (qd, qdd))
    i, j = scene.edge_index.T
    omega = link_angular_velocity(q[j] - q[i], qd[j] - qd[i])
    relative = jnp.array([omega[e] - (omega[p] if p >= 0 else 0.0) for e, p, _ in scene.dampers])
    dissipation = 0.5 * jnp.sum(jnp.array([b for _, _, b in scene.dampers]) * relative**2)
    expected = -2 * dissipation + jnp.sum(qd * physics.drag_force_fn(scene)(q, qd))
    assert dissipation > 0
    np.testing.assert_allclose(power, expected, rtol=1e-9)
    assert physics.damping_force_fn(drag) is None


def _cart_double_pole(rail_damping: float = 0.0):
    """A 1 kg cart on a rail along x with two hinged 0.1 kg poles and a 0.3 kg bob at
    the top, moving."""
    return scene_from_dict({
        "name": "cart-double-pole", "gravity": 9.81, "nodes": [[0.0, 1.0], [0.6, 1.8], [1.4, 2.4]],
        "velocities": [[0.5, 0.0], [0.5 - 0.8 * 1.2, 0.6 * 1.2], [0.5 - 0.8 * 1.2 - 0.6 * 0.7, 0.6 * 1.2 + 0.8 * 0.7]],
        "pinned": [], "links": [{"nodes": [0, 1], "mass": 0.1, "inertia": 0.1 / 12}, {"nodes": [1, 2], "mass": 0.1, "inertia": 0.1 / 12}],
        "point_masses": [{"node": 0, "mass": 1.0}, {"node": 2, "mass": 0.3}], "rails": [{"node": 0, "axis": 0, "damping": rail_damping}],
        "dampers": [{"links": [0], "damping": 0.02}, {"links": [1, 0], "damping": 0.01}]})


@pytest.mark.parametrize("solver", ["generic", "schur"])
def test_a_cart_on_a_rail_keeps_to_it_and_conserves_horizontal_momentum(solver):
    """No horizontal force acts on a cart-pole but the rail's damping: total x momentum
    (rods' centres and point masses) changes at `-b v_cart`; the cart never leaves its
    rail; dH/dt is the dampers' power."""
    from lgnn.physics.energies import damping_force_fn

    for b in (0.0, 0.3):
        scene = _cart_double_pole(b)
        q, qd = jnp.asarray(scene.nodes), jnp.asarray(scene.velocities)
        qdd = physics.true_acceleration_fn(scene, solver)(q, qd)
        assert float(qdd[0, 1]) == 0.0
        i, j = scene.edge_index.T
        momentum_rate = jnp.sum(jnp.asarray(scene.masses) * 0.5 * (qdd[i, 0] + qdd[j, 0])) + jnp.sum(jnp.asarray(scene.node_mass_array) * qdd[:, 0])
        np.testing.assert_allclose(momentum_rate, -b * qd[0, 0], atol=1e-12)
        _, power = jax.jvp(physics.energy_fn(scene), (q, qd), (qd, qdd))
        expected = jnp.sum(qd * damping_force_fn(scene)(q, qd)) - b * qd[0, 0] ** 2
        np.testing.assert_allclose(power, expected, rtol=1e-9)
    assert float(physics.constraint_violation(scene, q.at[0, 1].add(1e-3))) == pytest.approx(1e-3)


def test_sampled_states_of_a_cart_are_on_its_rail_and_its_links():
    """Projected perturbations keep the cart on its rail and the rods' lengths, to
    round-off (the projection's Gram matrix counts a rail's free coordinate only)."""
    scene = _cart_double_pole(0.1)
    states = physics.sample_initial_conditions(scene, 4, seed=0)
    np.testing.assert_array_equal(np.asarray(states.q)[:, 0, 1], scene.nodes[0, 1])
    np.testing.assert_array_equal(np.asarray(states.qd)[:, 0, 1], 0.0)
    for q, qd in zip(states.q, states.qd):
        assert float(physics.constraint_violation(scene, q)) < 1e-14
        assert float(physics.velocity_constraint_violation(scene, q, qd)) < 1e-14


@pytest.mark.parametrize("name", ["chain4", "chain4-drag", "chain4-3d"])
def test_gravity_as_a_vector_turns_the_motion_with_it(name):
    """A scene turned by a rotation R, its gravity turned with it (now with lateral
    components), accelerates as R times the original, on every solver that applies;
    its energy is the original's."""
    from lgnn.scene import scene_to_dict

    scene = get_scene(name)
    angle = 0.4
    c, s_ = np.cos(angle), np.sin(angle)
    rotation = np.array([[c, -s_], [s_, c]]) if scene.dim == 2 else np.array([[c, -s_, 0], [s_, c, 0], [0, 0, 1]]) @ np.array(
        [[1, 0, 0], [0, np.cos(0.3), -np.sin(0.3)], [0, np.sin(0.3), np.cos(0.3)]])
    data = scene_to_dict(scene)
    data["name"] = f"{name}-turned"
    data["nodes"] = (scene.nodes @ rotation.T).tolist()
    data["velocities"] = (scene.velocities @ rotation.T).tolist()
    data["gravity"] = (rotation @ scene.gravity_vector).tolist()
    turned = scene_from_dict(data)
    assert turned.lateral_gravity
    q, qd = random_state(scene, seed=3)
    q_turned, qd_turned = q @ rotation.T, qd @ rotation.T
    for solver in ("generic", "schur", "chain"):
        expected = physics.true_acceleration_fn(scene, solver)(q, qd) @ rotation.T
        np.testing.assert_allclose(physics.true_acceleration_fn(turned, solver)(q_turned, qd_turned), expected, atol=1e-11, err_msg=solver)
    np.testing.assert_allclose(physics.energy_fn(turned)(q_turned, qd_turned), physics.energy_fn(scene)(q, qd), rtol=1e-12)


def test_conservative_power_is_zero():
    for scene in (get_scene("T1"), double_pinned_chain(6)):  # regular configurations (not T2/T3 at rest)
        q, qd = random_state(scene, seed=7)
        qdd = jax.jit(physics.true_acceleration_fn(scene))(q, qd)
        _, power = jax.jvp(physics.energy_fn(scene), (q, qd), (qd, qdd))
        # scale: the power of gravity alone, which the kinetic-energy change must cancel
        gravity_power = jnp.sum(jnp.abs(qd * jax.grad(physics.energy_fn(scene))(q, qd)))
        assert abs(float(power)) < 1e-12 * float(gravity_power)


def test_jit_equals_eager():
    scene = get_scene("chain4-drag")
    q, qd = random_state(scene, seed=8)
    accel = physics.true_acceleration_fn(scene)
    eager = accel(q, qd)
    # Round-off differs between fused and eager kernels: bound it relative to the
    # accelerations' scale (~g), not per element (a near-zero component has none).
    np.testing.assert_allclose(jax.jit(accel)(q, qd), eager, rtol=1e-13, atol=1e-13 * float(jnp.max(jnp.abs(eager))))


def test_vmap_equals_map():
    scene = get_scene("chain8")
    states = sample_initial_states(scene, jax.random.PRNGKey(0), 5)
    qd = jax.random.normal(jax.random.PRNGKey(1), states.q.shape)
    project = physics.projection_fn(scene)
    q, qd = jax.vmap(project)(states.q, qd)
    accel = physics.true_acceleration_fn(scene)
    batched = jax.jit(jax.vmap(accel))(q, qd)
    single_fn = jax.jit(accel)
    single = np.stack([single_fn(q[k], qd[k]) for k in range(5)])
    np.testing.assert_allclose(batched, single, rtol=1e-12, atol=1e-13)


@pytest.mark.parametrize("drift, iterations", [(1e-8, None), (1e-4, 4)])
def test_projection_restores_constraints(drift, iterations):
    """The integrators' default (two Gauss-Newton steps on a regular scene) takes a
    step-sized drift to round-off; four steps take a large one there too."""
    scene = get_scene("T1")
    rng = np.random.default_rng(9)
    q = jnp.asarray(scene.nodes + drift * rng.normal(size=scene.nodes.shape))
    qd = jnp.asarray(rng.normal(size=scene.nodes.shape))
    q, qd = jax.jit(physics.projection_fn(scene, iterations))(q, qd)
    assert physics.constraint_violation(scene, q) < 1e-13
    assert physics.velocity_constraint_violation(scene, q, qd) < 1e-12


@pytest.mark.parametrize("scene_name", ["chain16", "T1"])
def test_adaptive_projection_takes_its_second_step_and_pass_only_where_the_first_leaves_more_than_round_off(scene_name, monkeypatch):
    """`adaptive`: from a drift of 1e-4 the second Gauss-Newton step and velocity pass
    are taken (the result is the two-step one, not the one-step one); from a state
    already projected the second step is skipped (its branch says so; the positions
    are the one-step projection's to round-off)."""
    skipped = _spy_on_branches(monkeypatch, "projection_fn")  # per adaptive step or pass: skipped?
    scene = get_scene(scene_name)
    rng = np.random.default_rng(3)
    q = jnp.asarray(scene.nodes + 1e-4 * rng.normal(size=scene.nodes.shape))
    qd = jnp.asarray(rng.normal(size=scene.nodes.shape))
    adaptive, two, one = (jax.jit(physics.projection_fn(scene, iterations, adaptive=flag))
                          for iterations, flag in ((None, True), (None, False), (1, False)))
    drifted = adaptive(q, qd)
    np.testing.assert_allclose(drifted[0], two(q, qd)[0], rtol=0, atol=1e-14)
    np.testing.assert_allclose(drifted[1], two(q, qd)[1], rtol=0, atol=1e-13)
    assert np.max(np.abs(one(q, qd)[0] - two(q, qd)[0])) > 1e-10  # one step alone would not do
    jax.effects_barrier()
    assert skipped == [False, False], skipped  # the second step and pass taken
    on_manifold = two(q, qd)
    skipped.clear()
    projected = adaptive(*on_manifold)
    jax.effects_barrier()
    assert skipped[0], "the second Gauss-Newton step was taken from a projected state"
    # Two compiled programs (the adaptive one solves by LAPACK's tridiagonal call): the
    # one-step positions to round-off, as the drifted state's above.
    np.testing.assert_allclose(projected[0], one(*on_manifold)[0], rtol=0, atol=1e-14)
    assert physics.velocity_constraint_violation(scene, *projected) < 1e-12


def test_one_trajectory_on_a_cpu_projects_adaptively_to_the_same_motion(monkeypatch):
    """`lgnn simulate`'s programs (one trajectory on a CPU) project adaptively, batches
    do not; forcing the usual two steps changes the ground truth's motion by round-off only."""
    from lgnn.engines import lagrangian, rollouts
    from lgnn.engines.base import SimulationConfig

    scene, config = get_scene("chain16"), SimulationConfig(dt=1e-4, frame_dt=1e-2, duration=0.5)
    assert rollouts.adaptive_projection(1, stacked=False)
    assert not rollouts.adaptive_projection(2, stacked=False) and not rollouts.adaptive_projection(1, stacked=True)
    adaptive = lagrangian.simulate(scene, config)
    try:
        monkeypatch.setattr(rollouts, "adaptive_projection", lambda batch, stacked: False)
        rollouts.compiled_programs.cache_clear()
        usual = lagrangian.simulate(scene, config)
    finally:
        rollouts.compiled_programs.cache_clear()
    difference = np.max(np.abs(adaptive.q - usual.q))
    assert 0 < difference < 1e-12, difference  # other programs, the same motion


def test_gradient_of_acceleration_matches_finite_differences():
    """The solve is differentiable (learned models train through it)."""
    scene = get_scene("chain4")
    q, qd = random_state(scene, seed=10)
    accel = physics.true_acceleration_fn(scene)
    loss = lambda qd: jnp.sum(jnp.sin(accel(q, qd)))  # noqa: E731
    direction = jnp.asarray(np.random.default_rng(11).normal(size=qd.shape))
    eps = 1e-6
    numeric = (loss(qd + eps * direction) - loss(qd - eps * direction)) / (2 * eps)
    analytic = jnp.vdot(jax.grad(loss)(qd), direction)
    np.testing.assert_allclose(analytic, numeric, rtol=1e-6)


def test_kkt_solve_derivatives_are_those_of_the_exact_solution():
    """`solvers.solve_kkt` differentiates by the implicit function theorem: its first
    and second derivatives in the mass matrix, Jacobian and right-hand sides are those
    of the exact saddle-point solution (a dense solve of the unregularised system)."""
    from lgnn.physics import solvers

    rng = np.random.default_rng(12)
    n, k = 8, 4
    root = rng.normal(size=(n, n))
    mass, jac = jnp.asarray(root @ root.T + n * np.eye(n)), jnp.asarray(rng.normal(size=(k, n)))
    force, rhs = jnp.asarray(rng.normal(size=n)), jnp.asarray(rng.normal(size=k))

    def exact(mass, jac, force, rhs):
        kkt = jnp.block([[mass, jac.T], [jac, jnp.zeros((k, k))]])
        return jnp.linalg.solve(kkt, jnp.concatenate([force, rhs]))[:n]

    def scalar(solve):
        return lambda *args: jnp.sum(jnp.sin(solve(*args)))

    args = (mass, jac, force, rhs)
    for ours, theirs in zip(jax.grad(scalar(solvers.solve_kkt), argnums=(0, 1, 2, 3))(*args),
                            jax.grad(scalar(exact), argnums=(0, 1, 2, 3))(*args)):
        np.testing.assert_allclose(ours, theirs, rtol=1e-8, atol=1e-12)
    tangent = tuple(jnp.asarray(rng.normal(size=np.shape(a))) for a in args)
    second = lambda solve: jax.jvp(jax.grad(scalar(solve), argnums=2), args, tangent)[1]  # noqa: E731
    np.testing.assert_allclose(second(solvers.solve_kkt), second(exact), rtol=1e-8, atol=1e-12)


def test_tangent_basis_is_a_complete_qr_of_the_jacobians_transpose():
    """`solvers.tangent_basis`: orthonormal range and null bases with `A N = 0` and
    `A^T = Y R`, R upper triangular to round-off, on a random full-rank Jacobian."""
    from lgnn.physics import solvers

    jac = jnp.asarray(np.random.default_rng(3).normal(size=(4, 9)))
    range_basis, upper, null_basis = solvers.tangent_basis(jac)
    basis = np.concatenate([range_basis, null_basis], 1)
    np.testing.assert_allclose(basis.T @ basis, np.eye(9), atol=1e-14)
    np.testing.assert_allclose(jac @ null_basis, 0, atol=1e-14)
    np.testing.assert_allclose(range_basis @ upper, jac.T, atol=1e-14)
    np.testing.assert_allclose(np.tril(upper, -1), 0, atol=1e-14)  # (solve_triangular reads only the upper part)


def test_constraint_rows_independent_everywhere_only_without_cycles():
    """`Constraints.always_independent`: the kept links with the pins taken as one
    ground node form a forest (chains, a pendulum, a rope pinned at one end), never a
    structure with a cycle through links or the ground (a rope pinned at both ends, a
    triangle pinned at two corners, a free triangle, the tensegrities)."""
    independent = {name: physics.prepare(get_scene(name)).constraints.always_independent
                   for name in ("chain4", "chain4-3d", "chain8-mixed", "pendulum", "rope-3d", "double-pinned",
                                "pinned-triangle", "free-triangle", "T1", "net4x4-3d")}
    assert independent == {"chain4": True, "chain4-3d": True, "chain8-mixed": True, "pendulum": True, "rope-3d": True,
                           "double-pinned": False, "pinned-triangle": False, "free-triangle": False, "T1": False, "net4x4-3d": False}


# The tangent-space solve (a chain) and the KKT solve (a cycle); both are written for any
# dimension, and a 3D case doubled this test's compile time.
@pytest.mark.parametrize("scene_name", ["chain4", "T1"])
def test_parametrised_accelerations_differentiate_as_the_ordinary_route(scene_name):
    """`physics.parametrised_acceleration_fn` takes the derivative by the parameters
    from the adjoint of the constrained equations: the same accelerations and the same
    derivatives by the parameters, positions and velocities as differentiating
    `acceleration_fn` itself, for a Lagrangian whose mass matrix depends on positions
    and velocities and a force that depends on the parameters. On the chains its
    forward solve is in the constraints' tangent space, on T1 (a cycle) the KKT solve."""
    scene = get_scene(scene_name)
    assert physics.uses_tangent_solve(scene, physics.LOCAL) == (scene_name != "T1")
    exact = physics.lagrangian_fn(scene)

    def build(params):
        def lagrangian(q, qd):
            # Exact rods, scaled, plus a coupling of velocities and positions (reach 1).
            i, j = scene.edge_index.T
            dq, dqd = q[i] - q[j], qd[i] - qd[j]
            return params["scale"] * exact(q, qd) + params["coupling"] * jnp.sum(jnp.tanh(jnp.sum(dqd * dqd, -1)) * jnp.cos(jnp.sum(dq, -1)))

        return lagrangian, lambda q, qd: -params["drag"] * qd * jnp.abs(q), physics.LOCAL

    params = {"scale": jnp.asarray(0.7), "coupling": jnp.asarray(0.05), "drag": jnp.asarray(1.3)}
    q, qd = (jnp.asarray(a) for a in physics.sample_initial_conditions(scene, 2, seed=4))
    target = jnp.asarray(np.random.default_rng(5).normal(size=q.shape))
    ours = jax.vmap(physics.parametrised_acceleration_fn(scene, build), in_axes=(None, 0, 0))

    def ordinary(params, q, qd):
        return jax.vmap(lambda a, b: physics.acceleration_fn(scene, *build(params)[:2], mass=physics.LOCAL)(a, b))(q, qd)

    def loss(accel):
        return lambda params, q, qd: jnp.sum(jnp.sin(accel(params, q, qd) * target))

    np.testing.assert_allclose(ours(params, q, qd), ordinary(params, q, qd), rtol=1e-12, atol=1e-12)
    theirs_grads = jax.jit(jax.grad(loss(ordinary), argnums=(0, 1, 2)))(params, q, qd)
    for got, want in zip(jax.tree.leaves(jax.jit(jax.grad(loss(ours), argnums=(0, 1, 2)))(params, q, qd)), jax.tree.leaves(theirs_grads)):
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12 * max(1.0, float(jnp.max(jnp.abs(want)))))


# ---------------------------------------------------------------------------------
# The structured ground-truth solvers and the structured projection
# ---------------------------------------------------------------------------------

STRUCTURED_SCENES = {
    "chain4": lambda: get_scene("chain4"),
    "chain4-drag": lambda: get_scene("chain4-drag"),
    "chain4-varied": lambda: get_scene("chain4-varied"),
    "chain90": lambda: chain(90),
    "T1": lambda: get_scene("T1"),
    "double-pinned": double_pinned_chain,
    "free-triangle": free_triangle,
    "pinned-triangle": pinned_triangle,
    "braced-chain": lambda: braced_chain(),
}


def braced_chain():
    """A chain of 7 links hanging between two pins, with braces between nodes 2 and 5 and
    nodes 1 and 6: three closed loops, regular at rest, like a small T1 (its Gram matrix
    is tridiagonal with a border of the two braces)."""
    data = json.loads(scene_to_json(double_pinned_chain(7)))
    data["name"] = "braced-chain"
    data["links"] += [{"nodes": [a, b], "mass": 0.5, "inertia": 0.02} for a, b in ((2, 5), (1, 6))]
    return scene_from_dict(data)


@pytest.mark.parametrize("name", sorted(STRUCTURED_SCENES))
def test_structured_solvers_match_the_generic_solve(name):
    """Every solver that applies gives the generic (AD mass matrix, KKT) accelerations
    to round-off at a random state on the manifold, drag included."""
    scene = STRUCTURED_SCENES[name]()
    q, qd = random_state(scene, seed=5, speed=2.0)
    reference = np.asarray(jax.jit(physics.true_acceleration_fn(scene, "generic"))(q, qd))
    solvers = ["auto", "schur"] + (["chain"] if is_pinned_chain(scene) else [])
    for solver in solvers:
        for vectorised in (False, True):  # one trajectory's guarded solve, a batch's refined one
            qdd = np.asarray(jax.jit(physics.true_acceleration_fn(scene, solver, vectorised=vectorised))(q, qd))
            np.testing.assert_allclose(qdd, reference, atol=1e-11 * (1 + np.abs(reference).max()), err_msg=f"{solver}, vectorised {vectorised}")


def test_guarded_spd_solve_is_plain_where_safe_and_refined_where_not(monkeypatch):
    """A well-conditioned SPD matrix is solved by one plain Cholesky solve; a singular
    one (rank 2 short, as rows that became dependent) by the regularised, refined solve,
    whose bounded answer the plain one does not give. (Where safe both solves agree to
    an ulp: the branch itself says which one ran.)"""
    from lgnn.physics.solvers import guarded_spd_solve, regularised_spd_solve, spd_solve

    plain_taken = _spy_on_branches(monkeypatch, "guarded_spd_solve")
    rng = np.random.default_rng(3)
    basis = rng.normal(size=(12, 12))
    safe = jnp.asarray(basis @ basis.T + 12 * np.eye(12))
    singular = jnp.asarray(basis[:, :10] @ basis[:, :10].T)
    rhs = jnp.asarray(rng.normal(size=12))
    guarded, plain, refined = (jax.jit(f) for f in (guarded_spd_solve, spd_solve, regularised_spd_solve))
    # Each solve inside the guarded program and alone are two compiled programs: to
    # round-off, of a well-conditioned system for the safe matrix; for the singular
    # one, 30x what a 1-ulp change of the matrix or right-hand side moves it (3e-7 of
    # its size).
    np.testing.assert_allclose(guarded(safe, rhs), plain(safe, rhs), rtol=0, atol=1e-13 * np.abs(plain(safe, rhs)).max())
    np.testing.assert_allclose(guarded(singular, rhs), refined(singular, rhs), rtol=0, atol=1e-5 * np.abs(refined(singular, rhs)).max())
    jax.effects_barrier()
    assert plain_taken == [True, False], plain_taken
    assert np.all(np.isfinite(guarded(singular, rhs))) and not np.allclose(plain(singular, rhs), refined(singular, rhs))


def test_auto_solver_keeps_the_generic_solve_for_self_stressed_scenes():
    """T2's accelerations at rest are defined by the regularised KKT solve of the exact
    mass matrix (lgnn/physics/dynamics.py), which "auto" must keep; the constant-mass Schur solve
    gives different (equally admissible) ones there."""
    scene = get_scene("T2")
    q, qd = jnp.asarray(scene.nodes), jnp.asarray(scene.velocities)
    generic = jax.jit(physics.true_acceleration_fn(scene, "generic"))(q, qd)
    assert physics.prepare(scene).solver("auto") == "generic"
    # Two compilations of one function: round-off apart, which T2's singular KKT system
    # amplifies (a 1-ulp change of q moves these accelerations by 6e-13 of 10). The
    # Schur solve differs from the generic one by about as much here, so the choice
    # above, not the values, tells them apart.
    np.testing.assert_allclose(jax.jit(physics.true_acceleration_fn(scene))(q, qd), generic, rtol=0, atol=1e-11)


def test_constant_node_mass_is_the_hessian_of_the_constant_mass_lagrangian():
    scene = get_scene("chain4-varied")
    n = scene.n_nodes * scene.dim
    lagrangian = physics.constant_mass_lagrangian_fn(scene)
    hessian = jax.hessian(lambda v: lagrangian(jnp.asarray(scene.nodes), v.reshape(scene.nodes.shape)))(jnp.zeros(n))
    np.testing.assert_allclose(physics.constant_node_mass(scene), hessian, atol=1e-14)


def test_singular_constant_mass_falls_back_to_the_generic_solve():
    """A free link of zero inertia has a singular constant mass (its ends can move
    oppositely at no cost): "auto" uses the generic solve, asking for "schur" is an error."""
    data = {"name": "zero-inertia", "nodes": [[0.0, 0.0], [1.0, 0.0]], "pinned": [],
            "links": [{"nodes": [0, 1], "mass": 1.0, "inertia": 0.0}]}
    scene = scene_from_dict(data)
    q, qd = random_state(scene)
    np.testing.assert_allclose(physics.true_acceleration_fn(scene)(q, qd), physics.true_acceleration_fn(scene, "generic")(q, qd))
    with pytest.raises(ValueError, match="singular"):
        physics.true_acceleration_fn(scene, "schur")


@pytest.mark.parametrize("name", ["chain4", "T1", "double-pinned"])
def test_constraint_jacobian_and_its_derivative_match_autodiff(name):
    scene = STRUCTURED_SCENES[name]()
    constraints = physics.Constraints(scene)
    q, qd = random_state(scene, seed=6)
    x, v = constraints.restrict(q), constraints.restrict(qd) + 0.3
    residual = lambda y: constraints.link_residual(constraints.embed(y))  # noqa: E731
    np.testing.assert_allclose(constraints.jacobian(x), jax.jacfwd(residual)(x), atol=1e-14)
    second = jax.jvp(lambda y: jax.jvp(residual, (y,), (v,))[1], (x,), (v,))[1]
    np.testing.assert_allclose(constraints.jacobian_dot_v(x, v), second, atol=1e-13)


@pytest.mark.parametrize("name, tridiagonal, border", [("chain90", True, None), ("T1", False, [43, 44, 45]), ("braced-chain", False, [7, 8]),
                                                      ("double-pinned", True, None), ("pinned-triangle", True, None)])
def test_link_gram_solve_matches_dense_normal_equations(name, tridiagonal, border):
    """`A A^T` from the link pairs (tridiagonal for chains, bordered on braced chains)
    solves like the dense product, by the sweeps and by LAPACK's tridiagonal solve (one
    system on a CPU)."""
    scene = STRUCTURED_SCENES[name]()
    system = physics.prepare(scene)
    constraints, gram = system.constraints, system.gram
    assert gram.tridiagonal == tridiagonal
    assert (gram.border is None and border is None) or gram.border.tolist() == border
    q, _ = random_state(scene, seed=7)
    jac = constraints.jacobian(constraints.restrict(q))
    rhs = jnp.asarray(np.random.default_rng(0).normal(size=constraints.n_rows))
    expected = np.linalg.solve(np.asarray(jac @ jac.T), np.asarray(rhs))
    for one_system in (False, True):
        solved = jax.jit(lambda u, r: gram.solve_fn(u, 0.0, one_system)(r))(constraints.link_directions(q), rhs)
        np.testing.assert_allclose(solved, expected, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("size", [1, 2, 4, 45])
def test_spd_tridiagonal_solve_matches_the_dense_solve(size):
    """The LDL^T sweep of the Gram solves against a dense solve, several right-hand sides,
    on an SPD tridiagonal matrix whose off-diagonals are as large as a chain's."""
    from lgnn.physics.solvers import spd_tridiagonal_solve

    rng = np.random.default_rng(size)
    off = rng.uniform(-1, 1, size - 1)
    diag = 2.0 + rng.uniform(0, 0.1, size)
    dense = np.diag(diag) + np.diag(off, 1) + np.diag(off, -1)
    rhs = rng.normal(size=(size, 3))
    lower, upper = np.concatenate([[0.0], off]), np.concatenate([off, [0.0]])
    solved = jax.jit(spd_tridiagonal_solve)(*(jnp.asarray(a) for a in (lower, diag, upper, rhs)))
    np.testing.assert_allclose(solved, np.linalg.solve(dense, rhs), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("size", [1, 3, 4, 5, 12])
def test_cholesky_solves_written_out_match_lapacks(size):
    """`cholesky_solve_fn` on either side of `UNROLLED_MAX` (written out, then LAPACK):
    the solution of an ill-conditioned SPD system (cond ~1e8) for one and several
    right-hand sides, and the factor's diagonal, against NumPy; an indefinite matrix
    gives NaN pivots, which the guarded solve reads as unsafe, under `vmap` too."""
    from lgnn.physics.solvers import UNROLLED_MAX, cholesky_solve_fn

    assert 3 <= UNROLLED_MAX < 12  # the sizes cover both ways
    rng = np.random.default_rng(size)
    basis, _ = np.linalg.qr(rng.normal(size=(size, size)))
    matrix = basis @ np.diag(np.logspace(0, 8, size)) @ basis.T
    rhs = rng.normal(size=(size, 3))
    solve_pivots = jax.jit(lambda m, r: (cholesky_solve_fn(m)[0](r), cholesky_solve_fn(m)[0](r[:, 0]), cholesky_solve_fn(m)[1]))
    many, one, pivots = solve_pivots(jnp.asarray(matrix), jnp.asarray(rhs))
    expected = np.linalg.solve(matrix, rhs)
    scale = np.abs(expected).max()
    np.testing.assert_allclose(many, expected, atol=1e-7 * scale)
    np.testing.assert_allclose(one, expected[:, 0], atol=1e-7 * scale)
    np.testing.assert_allclose(pivots, np.diag(np.linalg.cholesky(matrix)), rtol=1e-9)
    indefinite = np.stack([np.eye(size), -np.eye(size)])
    assert not np.isnan(jax.vmap(lambda m: cholesky_solve_fn(m)[1])(indefinite)[0]).any()
    assert np.isnan(jax.vmap(lambda m: cholesky_solve_fn(m)[1])(indefinite)[1]).any()


@pytest.mark.parametrize("size", [1, 2, 4, 8, 9, 12])
def test_spd_solves_eliminated_match_numpys(size):
    """`spd_solve` on either side of `ELIMINATED_MAX` (Gauss-Jordan elimination, then
    Cholesky): an ill-conditioned SPD system (cond ~1e8) for one and several right-hand
    sides, plainly and under `vmap`, against NumPy."""
    from lgnn.physics.solvers import ELIMINATED_MAX, spd_solve

    assert 2 <= ELIMINATED_MAX < 9  # the sizes cover both ways
    rng = np.random.default_rng(size)
    basis, _ = np.linalg.qr(rng.normal(size=(size, size)))
    matrix = basis @ np.diag(np.logspace(0, 8, size)) @ basis.T
    rhs = rng.normal(size=(size, 3))
    expected = np.linalg.solve(matrix, rhs)
    scale = np.abs(expected).max()
    many, one = jax.jit(lambda m, r: (spd_solve(m, r), spd_solve(m, r[:, 0])))(jnp.asarray(matrix), jnp.asarray(rhs))
    np.testing.assert_allclose(many, expected, atol=1e-7 * scale)
    np.testing.assert_allclose(one, expected[:, 0], atol=1e-7 * scale)
    batched = jax.vmap(spd_solve)(jnp.stack([matrix, 2 * matrix]), jnp.stack([rhs, rhs]))
    np.testing.assert_allclose(batched[1], expected / 2, atol=1e-7 * scale)


@pytest.mark.parametrize("rows, inner, columns", [(3, 3, 3), (4, 4, 4), (4, 4, None), (2, 5, 3)])
def test_block_products_match_matmul(rows, inner, columns):
    """`block_product`, the chain elimination's dot-free product, against `@` for
    blocks and vectors, plainly and under `vmap`."""
    from lgnn.physics.solvers import block_product

    rng = np.random.default_rng(rows * inner)
    a = rng.normal(size=(2, rows, inner))
    b = rng.normal(size=(2, inner) + (() if columns is None else (columns,)))
    np.testing.assert_allclose(block_product(jnp.asarray(a[0]), jnp.asarray(b[0])), a[0] @ b[0], rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(jax.vmap(block_product)(jnp.asarray(a), jnp.asarray(b)), np.einsum("bij,bj...->bi...", a, b), rtol=1e-14, atol=1e-14)


@pytest.mark.parametrize("dim", [2, 3])
def test_cyclic_reduction_solves_the_chains_kkt_system_as_the_sweeps_do(dim):
    """`chain_kkt_solve` by cyclic reduction against the sweeps, both exact and
    regularised-and-refined, on random chains whose lengths need padding to a power of
    two, with a positive definite block-tridiagonal mass; and under `vmap`."""
    from lgnn.physics.solvers import chain_kkt_solve

    solve = jax.jit(chain_kkt_solve, static_argnames=("regularised", "cyclic"))
    rng = np.random.default_rng(dim)
    # Padded to 1, 4 and 8 blocks; the 300-link test below takes 9 levels.
    for n, regularised in ((1, True), (3, False), (5, True)):
        factors = rng.normal(size=(n, dim, dim)) * 0.3
        diagonal = 2 * np.eye(dim) + factors @ np.swapaxes(factors, 1, 2)
        upper = rng.normal(size=(n - 1, dim, dim)) * 0.3
        u = rng.normal(size=(n, dim))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        args = (diagonal, upper, u, rng.normal(size=(n, dim)), rng.normal(size=n))
        sweeps = np.asarray(solve(*args, regularised=regularised, cyclic=False))
        cyclic = np.asarray(solve(*args, regularised=regularised, cyclic=True))
        np.testing.assert_allclose(cyclic, sweeps, atol=1e-13 * np.abs(sweeps).max(), err_msg=f"{n} links, regularised {regularised}")
    batched = jax.jit(jax.vmap(lambda *a: chain_kkt_solve(*a, regularised=True, cyclic=True)))(*(np.stack([a, a]) for a in args))
    np.testing.assert_allclose(batched[1], sweeps, atol=1e-13 * np.abs(sweeps).max())


def _banded_chain_system(n: int, dim: int, reach: int, seed: int, rank: int = 0):
    """A pinned chain's KKT system whose random positive definite mass couples nodes up
    to `reach` links apart: `(band, u, node_rhs, link_rhs)` for `banded_chain_kkt_solve`
    and the dense solve's node accelerations. With `rank`, the mass also has a dense
    term `factor core factor^T` of that rank, `core` symmetric and indefinite, and the
    system's first item is `(band, u, node_rhs, link_rhs, (factor (n, D, P), core))`."""
    rng = np.random.default_rng(seed)
    node = np.arange(n * dim) // dim
    mass = rng.normal(size=(n * dim, n * dim))
    mass = np.where(np.abs(node[:, None] - node[None, :]) <= reach, mass @ mass.T + 5 * np.eye(n * dim), 0.0)
    band = np.zeros((n, reach + 1, dim, dim))
    for b in range(n):
        for k in range(min(reach + 1, n - b)):
            band[b, k] = mass[dim * b:dim * (b + 1), dim * (b + k):dim * (b + k + 1)]
    if rank:
        factor, core = rng.normal(size=(n * dim, rank)), rng.normal(size=(rank, rank))
        core = core + core.T
        mass = mass + factor @ core @ factor.T
    u = rng.normal(size=(n, dim))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    jac = np.zeros((n, n * dim))
    for b in range(n):
        jac[b, dim * b:dim * (b + 1)] = -u[b]
        if b:
            jac[b, dim * (b - 1):dim * b] = u[b]
    node_rhs, link_rhs = rng.normal(size=(n, dim)), rng.normal(size=n)
    kkt = np.block([[mass, jac.T], [jac, np.zeros((n, n))]])
    expected = np.linalg.solve(kkt, np.concatenate([node_rhs.ravel(), link_rhs]))[:n * dim].reshape(n, dim)
    if rank:
        return (band, u, node_rhs, link_rhs, (factor.reshape(n, dim, rank), core)), expected
    return (band, u, node_rhs, link_rhs), expected


@pytest.mark.parametrize("dim", [2, 3])
def test_banded_chain_kkt_solve_is_the_dense_solve(dim):
    """A chain's KKT system with a mass of reach 1 to 3, grouped into block-tridiagonal
    form (one group; three groups, the last padded), refined, by the sweeps and by
    cyclic reduction, and exact by the sweeps, against the dense solve; at reach 1 it
    is `chain_kkt_solve`'s system."""
    from lgnn.physics import solvers

    cases = [(1, 4, False, True), (2, 1, True, True), (3, 7, False, True), (3, 7, True, True), (3, 7, False, False)]
    # The solves are written for any block size D: the planar run keeps one case of each
    # elimination (compiles are most of this test's time).
    for reach, n, cyclic, regularised in cases if dim == 3 else cases[:2]:
        system, expected = _banded_chain_system(n, dim, reach, seed=10 * n + reach)
        got = jax.jit(functools.partial(solvers.banded_chain_kkt_solve, regularised=regularised, cyclic=cyclic))(*system)
        np.testing.assert_allclose(got, expected, atol=1e-11 * np.abs(expected).max(), err_msg=f"{reach=} {n=} {cyclic=}")
        if reach == 1:
            band, *rest = system
            np.testing.assert_allclose(solvers.chain_kkt_solve(band[:, 0], band[:-1, 1], *rest, regularised=True), expected,
                                       atol=1e-11 * np.abs(expected).max())


@pytest.mark.parametrize("dim", [2, 3])
def test_banded_chain_kkt_solve_with_a_low_rank_term_is_the_dense_solve(dim):
    """The banded solve with an indefinite dense low-rank term added to the mass (LGN's
    pooled read-out), by the Woodbury identity: exact, and regularised and refined by
    both eliminations, against the dense solve; with one group and with several."""
    from lgnn.physics import solvers

    cases = [(3, 7, 4, False, False), (3, 7, 4, False, True), (3, 7, 4, True, True), (2, 1, 3, False, True), (1, 9, 2, True, True)]
    for reach, n, rank, cyclic, regularised in cases if dim == 3 else cases[1:3]:  # (as above)
        (*system, low_rank), expected = _banded_chain_system(n, dim, reach, seed=10 * n + reach + rank, rank=rank)
        solve = functools.partial(solvers.banded_chain_kkt_solve, regularised=regularised, cyclic=cyclic, low_rank=low_rank)
        got = jax.jit(solve)(*system)
        np.testing.assert_allclose(got, expected, atol=1e-10 * np.abs(expected).max(), err_msg=f"{reach=} {n=} {cyclic=} {regularised=}")


def test_an_accelerator_eliminates_a_chain_by_cyclic_reduction_unless_it_solves_many_at_once(monkeypatch):
    """`chain_elimination`: the sweeps on a CPU; where the trace computes on an
    accelerator `ACCELERATOR_CHAIN_ELIMINATION`, and the sweeps past
    `CYCLIC_MAX_SYSTEMS` systems at once."""
    from lgnn import sharding
    from lgnn.physics import solvers

    assert solvers.chain_elimination() == "sweeps"
    monkeypatch.setattr(sharding, "platform", lambda: "gpu")
    assert solvers.chain_elimination() == solvers.ACCELERATOR_CHAIN_ELIMINATION == "cyclic"
    with solvers.systems_at_once(solvers.CYCLIC_MAX_SYSTEMS):
        assert solvers.chain_elimination() == "cyclic"
        with solvers.systems_at_once(solvers.CYCLIC_MAX_SYSTEMS + 1):
            assert solvers.chain_elimination() == "sweeps"
        assert solvers.chain_elimination() == "cyclic"
    assert solvers.chain_elimination() == "cyclic"


@pytest.mark.parametrize("per_device, stacked, elimination", [(8, False, "cyclic"), (16384, False, "cyclic"), (16392, False, "sweeps"),
                                                              (8200, True, "sweeps")])
def test_a_rollout_program_chooses_the_chain_elimination_for_its_batch(per_device, stacked, elimination, monkeypatch):
    """`compiled_programs` traces its solves as the systems it solves at once on each
    device (initial conditions times stacked parameter sets, over the devices), which
    a `vmap`ped solve cannot see."""
    from types import SimpleNamespace

    from lgnn import sharding
    from lgnn.engines import rollouts
    from lgnn.engines.base import Integration, SimulationConfig
    from lgnn.physics import solvers

    monkeypatch.setattr(solvers, "sharding", SimpleNamespace(platform=lambda: "gpu"))
    chosen = set()

    def factory(scene, params):
        chosen.add(solvers.chain_elimination())
        return lambda q, qd: params * jnp.zeros_like(q)

    params = jnp.ones(2) if stacked else jnp.ones(())
    batch = per_device * sharding.device_count()
    rollouts.compiled_programs(chain(1), SimulationConfig(1e-3, 1e-3, 1e-3), Integration(), factory, batch, "float64", 1, stacked,
                               rollouts.params_signature(params), False)
    assert chosen == {elimination}


@pytest.mark.parametrize("elimination", ["sweeps", "cyclic"])
def test_chain_solver_is_accurate_on_a_long_chain(elimination, monkeypatch):
    """The linear-time chain elimination, by sweeps (a CPU's) and by cyclic reduction (an
    accelerator's), against the Schur solve on 300 links, at a random configuration
    with fast motion (round-off relative to the scale)."""
    from lgnn.physics import solvers

    monkeypatch.setattr(solvers, "chain_elimination", lambda: elimination)
    scene = chain(300)
    q = sample_initial_states(scene, jax.random.PRNGKey(3), 1).q[0]
    q, qd = jax.jit(physics.projection_fn(scene))(q, jax.random.normal(jax.random.PRNGKey(4), q.shape))
    fast = np.asarray(jax.jit(physics.true_acceleration_fn(scene, "chain"))(q, qd))
    schur = np.asarray(jax.jit(physics.true_acceleration_fn(scene, "schur"))(q, qd))
    np.testing.assert_allclose(fast, schur, atol=1e-10 * np.abs(schur).max())


@pytest.mark.parametrize("name", ["chain4", "chain4-drag", "chain90", "T1", "double-pinned", "free-triangle"])
def test_local_mass_solve_matches_the_dense_solve(name):
    """Coloured Hessian-vector products (and, for chains, the block elimination with
    regularisation and refinement) give the dense solve's accelerations for the exact
    Lagrangian, whose mass matrix couples only linked nodes."""
    scene = STRUCTURED_SCENES[name]()
    q, qd = random_state(scene, seed=8, speed=2.0)
    lagrangian, drag = physics.lagrangian_fn(scene), physics.drag_force_fn(scene)
    dense = np.asarray(jax.jit(physics.acceleration_fn(scene, lagrangian, drag))(q, qd))
    local = np.asarray(jax.jit(physics.acceleration_fn(scene, lagrangian, drag, mass=physics.LOCAL))(q, qd))
    np.testing.assert_allclose(local, dense, atol=1e-10 * (1 + np.abs(dense).max()))


@pytest.mark.parametrize("name", ["chain4", "chain90", "T1"])
def test_euler_lagranges_structured_mass_matrix_is_the_dense_one(name):
    """`euler_lagrange`'s pieces with the local structure declared: its mass matrix is
    the one forward differentiation gives, its products are what the matrix is made
    of, and a long chain goes to the block elimination (`chain_solve`)."""
    scene = STRUCTURED_SCENES[name]()
    q, qd = random_state(scene, seed=9, speed=2.0)
    constraints = physics.prepare(scene).constraints
    x, v = constraints.restrict(q), constraints.restrict(qd)
    lagrangian = physics.lagrangian_fn(scene)
    dense, local = physics.euler_lagrange(scene, lagrangian), physics.euler_lagrange(scene, lagrangian, physics.LOCAL)
    assert not dense.structured and dense.mass_products is None and local.structured
    assert local.chain_solve == (name == "chain90")
    expected = np.asarray(jax.jit(dense.mass_matrix)(x, v))
    np.testing.assert_allclose(jax.jit(local.mass_matrix)(x, v), expected, atol=1e-12 * np.abs(expected).max())
    products, low_rank = jax.jit(local.mass_products)(x, v)
    assert low_rank is None
    np.testing.assert_allclose(local.local.dense(products), expected, atol=1e-12 * np.abs(expected).max())
    np.testing.assert_allclose(local.right_hand_side(x, v), dense.right_hand_side(x, v), rtol=1e-12, atol=1e-12)


def test_local_mass_colouring_needs_2_reach_plus_1_colours_for_any_chain_and_reach_plus_1_for_a_long_one():
    for n in (4, 40, 400):
        scene = chain(n)
        long = physics.prepare(scene).long_chain
        assert long == (n == 400)
        for reach in (1, 2, 3):
            assert physics.prepare(scene).local_mass(reach).n_colours == (reach + 1 if long else min(2 * reach + 1, n))


@pytest.mark.parametrize(("links", "dim", "reach"), [(300, 2, 1), (300, 2, 3), (100, 3, 2), (81, 3, 3)])
def test_a_long_chains_mass_is_recovered_from_reach_plus_1_colours(links, dim, reach):
    """`ChainBandMass`: a random symmetric mass matrix of `reach` on a long pinned
    chain, from its products with the reach + 1 colours' seeds, as its band blocks and
    dense, to round-off, however long the residue classes' sums."""
    from lgnn.physics.local_mass import ChainBandMass

    scene = chain(links) if dim == 2 else spatial_chain(links)
    local = physics.prepare(scene).local_mass(reach)
    assert isinstance(local, ChainBandMass) and local.n_colours == reach + 1
    free = len(physics.prepare(scene).constraints.free)
    node = np.arange(free) // dim
    rng = np.random.default_rng(links + reach)
    a = rng.normal(size=(free, free))
    mass = np.where(np.abs(node[:, None] - node[None, :]) <= reach, a + a.T, 0.0)
    products = jax.jit(lambda m: local.products(lambda seed: m @ seed, m.dtype))(mass)
    np.testing.assert_allclose(jax.jit(local.dense)(products), mass, rtol=0, atol=1e-13 * np.abs(mass).max())
    blocks = np.asarray(jax.jit(local.band_blocks)(products))
    for b, k in [(0, 0), (links // 2, reach), (links - 1 - reach, reach), (links - 1, 0)]:
        np.testing.assert_allclose(blocks[b, k], mass[dim * b:dim * (b + 1), dim * (b + k):dim * (b + k + 1)], atol=1e-13 * np.abs(mass).max())
    assert not blocks[links - 1, 1:].any()


# ---------------------------------------------------------------------------------
# The static System and the one refinement routine
# ---------------------------------------------------------------------------------


def test_prepare_is_cached_by_scene_content():
    """Equal scenes built separately share one System; any change of content gives
    another. Static parts are built on first use only."""
    first, second = chain(7), chain(7)
    assert first is not second
    system = physics.prepare(first)
    assert physics.prepare(second) is system
    assert physics.prepare(scene_from_dict(json.loads(scene_to_json(first)))) is system
    assert physics.prepare(chain(8)) is not system
    assert physics.prepare(first.replace(masses=2 * first.masses)) is not system
    fresh = physics.prepare(chain(7).replace(gravity=np.asarray(3.25)))
    assert not {"constraints", "gram", "_local_masses", "_pooled_jacobians", "regular_mass", "schur_inverse"} & set(vars(fresh))
    assert fresh.constraints is physics.prepare(chain(7).replace(gravity=np.asarray(3.25))).constraints


def test_factories_build_the_static_data_once(monkeypatch):
    """Every factory takes its constraints from `prepare`: building accelerations and
    projections of one scene again and again makes one `Constraints`."""
    built = []
    original = physics.system.Constraints
    monkeypatch.setattr(physics.system, "Constraints", lambda scene: built.append(scene) or original(scene))
    scene = chain(5).replace(gravity=np.asarray(4.75))
    for solver in ("auto", "generic", "schur", "chain"):
        physics.true_acceleration_fn(scene, solver)
    physics.acceleration_fn(chain(5).replace(gravity=np.asarray(4.75)), physics.lagrangian_fn(scene), mass=physics.LOCAL)
    physics.projection_fn(scene)
    assert len(built) == 1


def test_refine_improves_a_badly_conditioned_solve():
    """A Cholesky factor of `S + eps I` (eps = 1e-9, about the solvers' regularisation) solves
    `S x = r` badly when S has eigenvalues near eps (here down to 1e-6): each `refine`
    step divides the residual by ~sigma_min / eps = 1e3, and three steps reach
    round-off. Zero steps leave the solution as it is."""
    rng = np.random.default_rng(12)
    basis, _ = np.linalg.qr(rng.normal(size=(8, 8)))
    matrix = jnp.asarray(basis @ np.diag(np.logspace(0, -6, 8)) @ basis.T)
    rhs = jnp.asarray(rng.normal(size=8))
    factor = jax.scipy.linalg.cho_factor(matrix + 1e-9 * jnp.eye(8))
    solve = lambda r: jax.scipy.linalg.cho_solve(factor, r)  # noqa: E731
    residual = lambda x: rhs - matrix @ x  # noqa: E731
    start = solve(rhs)
    np.testing.assert_array_equal(physics.refine(solve, residual, start, 0), start)
    norms = [float(jnp.linalg.norm(residual(physics.refine(solve, residual, start, steps)))) for steps in range(4)]
    assert norms[0] > 1e-4
    assert norms[1] < 2e-3 * norms[0] and norms[2] < 2e-3 * norms[1]
    assert norms[3] < 1e-7 * norms[0]
    exact = np.linalg.solve(np.asarray(matrix), np.asarray(rhs))
    np.testing.assert_allclose(physics.refine(solve, residual, start, 3), exact, atol=1e-10 * np.abs(exact).max())


# ---------------------------------------------------------------------------------
# Scale-free solves: a Lagrangian is defined only up to a factor
# ---------------------------------------------------------------------------------

LAGRANGIAN_SCALES = (1e-2, 1e-1, 10.0, 100.0)


def scaled_acceleration_fn(scene, scale, *, local_mass):
    """`acceleration_fn` of `scale * L` (and `scale *` its drag, whose dissipation
    scales with L), the exact Lagrangian of `scene`; `scale` may be traced."""
    lagrangian, drag = physics.lagrangian_fn(scene), physics.drag_force_fn(scene)
    scaled_drag = None if drag is None else (lambda q, qd: scale * drag(q, qd))
    return physics.acceleration_fn(scene, lambda q, qd: scale * lagrangian(q, qd), scaled_drag, mass=physics.LOCAL if local_mass else None)


# Every built-in on both solve paths, except chain100's generic (dense KKT) path and the
# local mass of the self-stressed T2 and T3: each is the same code as on the other
# scenes (the regularised solve's scaling is the KKT solve's, whichever path assembled
# the mass matrix) and together they cost two minutes of CI.
SKIPPED_SCALING_CASES = {("chain100", False), ("T2", True), ("T3", True)}
SCALING_CASES = [pytest.param(name, local_mass, id=f"{name}-{'local-mass' if local_mass else 'generic'}")
                 for name in sorted(scene_names("paper")) for local_mass in (False, True) if (name, local_mass) not in SKIPPED_SCALING_CASES]
# The cases that also roll out 250 steps: the projection takes no Lagrangian, so a
# rollout adds to the accelerations' check only their accumulation over steps, the
# same on every scene of a solve path: chain4 on both paths, the trusses' generic path
# (T2 self-stressed) and chain100's chain elimination cover each.
SCALING_ROLLOUT_CASES = {("chain4", False), ("chain4", True), ("T1", False), ("T2", False), ("chain100", True)}


@pytest.mark.xla_optimised  # 250 steps of each: the optimised program pays for itself
@pytest.mark.parametrize(("name", "local_mass"), SCALING_CASES)
def test_accelerations_and_rollouts_are_invariant_under_scaling_the_lagrangian(name, local_mass):
    """`c L` has the dynamics of `L` (c in `LAGRANGIAN_SCALES`): no regularisation or
    refinement of the solves may depend on the Lagrangian's scale. Accelerations at the
    scene's own state (T2 and T3 are self-stressed there, their KKT matrix singular) and
    at a random moving state agree to 1e-9 of their size, the states after a 0.025 s
    rollout (RK4, dt = 1e-4, projected) to 1e-8. At a singular configuration the
    accelerations are as sensitive to round-off as to the scale (T2 and T3 moving: a
    change of L by one ulp moves them by ~1e-6 of their size, as c does), so the bound
    adds 10 times what that change does; scaling by 2 is exact in floating point and
    must change nothing at all. The local mass (`physics.LOCAL`) on chain100 is the chain
    elimination. The rollout runs on `SCALING_ROLLOUT_CASES`."""
    scene = get_scene(name)
    one_ulp = 1.0 + np.finfo(np.float64).eps
    scales = jnp.asarray((1.0, one_ulp, 2.0) + LAGRANGIAN_SCALES)
    batch = lambda x: jnp.broadcast_to(x, (len(scales),) + x.shape)  # noqa: E731
    accel = jax.jit(jax.vmap(lambda c, q, qd: scaled_acceleration_fn(scene, c, local_mass=local_mass)(q, qd)))

    def check(results, tolerance, what):
        reference, perturbed, doubled = results[:3]
        np.testing.assert_array_equal(doubled, reference, err_msg=f"{what}, c = 2")
        bound = tolerance + 10 * np.abs(perturbed - reference).max()
        for c, result in zip(LAGRANGIAN_SCALES, results[3:]):
            np.testing.assert_allclose(result, reference, rtol=0, atol=bound, err_msg=f"{what}, c = {c}")

    own = (jnp.asarray(scene.nodes), jnp.asarray(scene.velocities))
    for label, (q, qd) in (("own state", own), ("random state", random_state(scene, seed=9, speed=2.0))):
        qdd = np.asarray(accel(scales, batch(q), batch(qd)))
        check(qdd, 1e-9 * np.abs(qdd[0]).max(), f"accelerations at the {label}")
    if (name, local_mass) not in SCALING_ROLLOUT_CASES:
        return
    # One compiled step (RK4's stages are a loop around one copy of the accelerations).
    integrator = integrate.rk4(lambda q, qd: accel(scales, q, qd), 1e-4, jax.vmap(physics.projection_fn(scene)))
    step = jax.jit(integrator.step_fn)
    carry = integrator.init_fn(tuple(map(batch, own)))
    for _ in range(250):
        carry = step(carry)
    q, qd = (np.asarray(part) for part in carry.state)
    assert np.isfinite(q).all() and np.isfinite(qd).all()
    size = np.abs(q[0]).max() + np.abs(qd[0]).max()
    check(q, 1e-8 * size, "q after 0.025 s")
    check(qd, 1e-8 * size, "qd after 0.025 s")


def test_sweeps_unrolled_as_on_an_accelerator_give_the_same_motion(monkeypatch):
    """On an accelerator the sweeps along a chain are unrolled (`solvers.sweep_unroll`).
    Forced here on the CPU, by a factor that does not divide the chain's 16 links, the
    block elimination's accelerations and the projection's tridiagonal Gram solves give
    what the loops give, to round-off."""
    from lgnn.physics import solvers

    scene = get_scene("chain16")
    q0, qd0 = (np.asarray(a) for a in physics.benchmark_initial_states(scene, 2, 0))
    kick = 1e-3 * np.random.default_rng(0).normal(size=q0.shape)

    def motion():
        accel = jax.jit(jax.vmap(physics.vectorised_true_acceleration_fn(scene)))(q0, qd0)
        projected = jax.jit(jax.vmap(physics.projection_fn(scene)))(q0 + kick, qd0)
        return np.asarray(accel), *(np.asarray(a) for a in projected)

    looped = motion()
    monkeypatch.setattr(solvers, "sweep_unroll", lambda: 7)
    unrolled = motion()
    assert np.abs(looped[0]).max() > 1.0 and np.abs(looped[1] - q0).max() > 1e-5
    for a, b in zip(looped, unrolled):
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-12 * np.abs(a).max())
