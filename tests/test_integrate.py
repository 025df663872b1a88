"""Integrators and the ground-truth engine: conservation, constraints, order, accuracy."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lgnn import physics
from lgnn.integrate import rk4, rollout, velocity_verlet, written_out_rk4
from lgnn.scene import get_scene, sample_initial_states, scene_names
from lgnn.engines.base import Integration, SimulationConfig
from lgnn.engines.lagrangian import rollout_fn, simulate
from lgnn.scene.catalogue import double_pinned_chain, free_triangle, pendulum


def max_node_error(a, b):
    return float(np.max(np.linalg.norm(a.q - b.q, axis=-1)))


def relative_energy_drift(trajectory):
    return float(np.max(np.abs(trajectory.energy - trajectory.energy[0])) / abs(trajectory.energy[0]))


def test_rk4_conserves_energy_on_chain4():
    trajectory = simulate(get_scene("chain4"), SimulationConfig(dt=1e-4, duration=1.0))
    assert relative_energy_drift(trajectory) < 1e-8


def test_verlet_energy_error_is_bounded_and_second_order():
    scene = get_scene("chain4")
    drifts = {}
    for dt in (1e-3, 5e-4):
        trajectory = simulate(scene, SimulationConfig(dt=dt, frame_dt=1e-2, duration=2.0), integration=Integration("verlet"))
        error = np.abs(trajectory.energy - trajectory.energy[0]) / abs(trajectory.energy[0])
        # bounded: no secular growth (second half of the run no worse than 3x the first)
        half = len(error) // 2
        assert error[half:].max() < 3 * error[:half].max()
        drifts[dt] = error.max()
    order = np.log2(drifts[1e-3] / drifts[5e-4])
    assert 1.7 < order < 2.3, drifts


@pytest.mark.parametrize("project", [True, False])
def test_constraint_drift_with_and_without_projection(project, record_property):
    scene = get_scene("T1")
    trajectory = simulate(scene, SimulationConfig(dt=1e-3, frame_dt=1e-2, duration=1.0), integration=Integration(project=project))
    violation = max(float(physics.constraint_violation(scene, q)) for q in trajectory.q)
    record_property("max_constraint_violation", violation)
    if project:
        assert violation < 1e-10
    else:
        # without projection the drift is the integrator's truncation error: small but visible
        assert 1e-14 < violation < 1e-4
    assert np.max(np.abs(trajectory.q[:, list(scene.pinned)] - scene.pin_positions)) == 0.0  # pins are exact


@pytest.mark.parametrize(("name", "dts", "expected_order"), [("rk4", (4e-3, 2e-3, 1e-3), 4), ("verlet", (2e-3, 1e-3, 5e-4), 2)])
def test_convergence_order(name, dts, expected_order):
    scene = get_scene("chain4")
    duration = 0.4
    reference = simulate(scene, SimulationConfig(dt=5e-5, frame_dt=duration, duration=duration), integration=Integration(project=False))
    errors = [
        max_node_error(simulate(scene, SimulationConfig(dt=dt, frame_dt=duration, duration=duration), integration=Integration(name, project=False)), reference)
        for dt in dts
    ]
    slope = np.polyfit(np.log(dts), np.log(errors), 1)[0]
    assert abs(slope - expected_order) < 0.3, (errors, slope)


def test_pendulum_small_angle_period():
    """Period of a uniform rod about its end: 2 pi sqrt(2 l / 3 g) (small angles)."""
    length, gravity, amplitude = 1.0, 10.0, 1e-3
    scene = pendulum(amplitude, length, 1.0, gravity)
    period = 2 * np.pi * np.sqrt(2 * length / (3 * gravity))
    trajectory = simulate(scene, SimulationConfig(dt=1e-4, frame_dt=1e-3, duration=2.0))
    x = trajectory.q[:, 1, 0]
    crossings = np.flatnonzero((x[:-1] > 0) & (x[1:] <= 0))  # downward zero crossings of the tip
    times = trajectory.t[crossings] + x[crossings] / (x[crossings] - x[crossings + 1]) * (trajectory.t[1] - trajectory.t[0])
    assert len(times) >= 1
    # released at +amplitude: first downward crossing at a quarter period
    np.testing.assert_allclose(times[0], period / 4, rtol=1e-5)
    energy_drift = relative_energy_drift(trajectory)
    assert energy_drift < 1e-10


@pytest.mark.parametrize("name", list(scene_names("paper")))
def test_every_builtin_scene_runs(name):
    scene = get_scene(name)
    trajectory = simulate(scene, SimulationConfig(dt=1e-4, frame_dt=1e-2, duration=0.1))
    assert np.all(np.isfinite(trajectory.q)) and np.all(np.isfinite(trajectory.energy))
    # singular (self-stressed) starts are held less tightly: the projection's shift
    # trades exactness along the self-stress for stability (lgnn/physics/projection.py)
    tolerance = 1e-8 if physics.Constraints(scene).self_stresses else 1e-10
    assert float(physics.constraint_violation(scene, trajectory.q[-1])) < tolerance
    displacement = np.max(np.abs(trajectory.q[-1] - trajectory.q[0]))
    if name == "T2":
        # T2 is prestress-stable (its taut ropes and rod lock it, tests/test_physics.py):
        # with inextensible links its exact motion is rest.
        assert displacement < 1e-4  # measured 3.4e-5: the projection's shift lets it sag slightly
    else:
        assert displacement > 1e-3  # falls from rest


@pytest.mark.parametrize(("scene_fn", "duration"), [(lambda: get_scene("chain4"), 1.0), (double_pinned_chain, 1.0), (lambda: get_scene("T1"), 0.1)])
def test_default_settings_are_accurate(scene_fn, duration):
    """Default settings: max node error <= 1e-6 against a converged reference (over 1 s;
    T1 over 0.1 s to keep CI short, its 1 s check is in the MuJoCo cross-check)."""
    scene = scene_fn()
    default = simulate(scene, SimulationConfig(duration=duration))
    reference = simulate(scene, SimulationConfig(dt=2.5e-5, duration=duration))
    assert max_node_error(default, reference) < 1e-6


def test_drag_dissipates_and_no_drag_conserves():
    with_drag = simulate(get_scene("chain4-drag"), SimulationConfig(dt=1e-3, frame_dt=1e-2))
    assert np.all(np.diff(with_drag.energy) < 1e-12)
    assert with_drag.energy[-1] < with_drag.energy[0] - 1e-4


def test_free_body_momentum():
    """No pins: the centre of mass moves on a parabola, whatever the spin."""
    scene = free_triangle()
    trajectory = simulate(scene, SimulationConfig(dt=1e-3, frame_dt=1e-2, duration=1.0))
    masses = scene.masses
    i, j = scene.edge_index.T
    com = np.einsum("e,fed->fd", masses, 0.5 * (trajectory.q[:, i] + trajectory.q[:, j])) / masses.sum()
    com_velocity0 = np.einsum("e,ed->d", masses, 0.5 * (scene.velocities[i] + scene.velocities[j])) / masses.sum()
    t = trajectory.t[:, None]
    expected = com[0] + com_velocity0 * t + 0.5 * np.array([0.0, -float(scene.gravity)]) * t**2
    np.testing.assert_allclose(com, expected, atol=1e-10)


def test_rollout_vmap_equals_map():
    scene = get_scene("chain4")
    states = sample_initial_states(scene, jax.random.PRNGKey(3), 3)
    integrator = rk4(physics.true_acceleration_fn(scene), 1e-3, physics.projection_fn(scene))
    run = jax.jit(lambda state: rollout(integrator, state, 20, 5))
    batched = jax.jit(jax.vmap(lambda q, qd: rollout(integrator, (q, qd), 20, 5)))(states.q, states.qd)
    for k in range(3):
        single = run((states.q[k], states.qd[k]))
        np.testing.assert_allclose(batched.q[k], single.q, rtol=1e-12, atol=1e-13)
    assert batched.q.shape == (3, 21, 5, 2)
    np.testing.assert_array_equal(batched.q[:, 0], states.q)  # frame 0 is the initial state, copied


def test_verlet_carries_one_evaluation_per_step():
    scene = get_scene("chain4")
    calls = []

    def counting_accel(q, qd):
        calls.append(1)
        return physics.true_acceleration_fn(scene)(q, qd)

    integrator = velocity_verlet(counting_accel, 1e-3)
    carry = integrator.init_fn((jnp.asarray(scene.nodes), jnp.zeros((5, 2))))
    calls.clear()
    integrator.step_fn(carry)
    assert len(calls) == 1 == integrator.evaluations_per_step


@pytest.mark.parametrize(("cheap_steps", "copies"), [(False, 1), (True, 4)])
def test_rk4_compiles_one_copy_of_the_acceleration_unless_steps_are_cheap(cheap_steps, copies):
    """RK4's four stages are one loop: tracing a step traces the acceleration once (a
    rollout program then holds one copy of a learned model's derivatives and solve,
    not four); where steps are cheap (one trajectory on a CPU) they are written out.
    A step evaluates the acceleration four times either way."""
    calls = []

    def counting_accel(q, qd):
        calls.append(1)
        return -jnp.sin(q) - 0.1 * qd

    integrator = Integration("rk4", project=False).integrator_for(counting_accel, 1e-2, cheap_steps=cheap_steps)
    carry = integrator.init_fn((jnp.ones((3, 2)), jnp.zeros((3, 2))))
    jax.jit(integrator.step_fn).lower(carry)
    assert len(calls) == copies and integrator.evaluations_per_step == 4


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_rk4_looped_and_written_out_stages_give_the_classical_step(dtype):
    """The looped stages give the written-out step to within 2 ulps (their sums run in
    the same order, float32 through the compensated position sum too: the same bits
    today, but they are two compiled programs, which may contract or fuse differently),
    and both are the classical RK4 step, here a generic explicit Runge-Kutta step over
    its Butcher tableau, to round-off: on a damped pendulum whose acceleration depends
    on q and qd."""

    def accel(q, qd):
        return -jnp.sin(q) - 0.3 * qd * jnp.cos(q)

    dt = 0.05
    q = jnp.asarray(np.random.default_rng(0).normal(size=(4, 2)), dtype)
    qd = jnp.asarray(np.random.default_rng(1).normal(size=(4, 2)), dtype)
    steps = []
    for form in (rk4, written_out_rk4):
        integrator = form(accel, dt)
        steps.append(jax.jit(integrator.step_fn)(integrator.init_fn((q, qd))).state)
    for a, b in zip(*steps):
        assert a.dtype == jnp.dtype(dtype)
        # Two compiled programs: within 2 ulps of the largest value, 5x tighter than the
        # check against the tableau's step below.
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=2 * np.finfo(dtype).eps * np.abs(np.asarray(b)).max())

    # The first-order system y = (q, qd), y' = (qd, accel(q, qd)), in float64.
    def derivative(y):
        return np.stack([y[1], np.asarray(accel(jnp.asarray(y[0]), jnp.asarray(y[1])))])

    tableau, weights = [[], [0.5], [0.0, 0.5], [0.0, 0.0, 1.0]], [1 / 6, 1 / 3, 1 / 3, 1 / 6]
    y = np.stack([np.asarray(q, np.float64), np.asarray(qd, np.float64)])
    slopes = []
    for row in tableau:
        slopes.append(derivative(y + dt * sum((a * k for a, k in zip(row, slopes)), np.zeros_like(y))))
    expected = y + dt * sum(w * k for w, k in zip(weights, slopes))
    tolerance = 10 * np.finfo(dtype).eps * np.abs(expected).max()
    np.testing.assert_allclose(np.asarray(steps[0].q, np.float64), expected[0], rtol=0, atol=tolerance)
    np.testing.assert_allclose(np.asarray(steps[0].qd, np.float64), expected[1], rtol=0, atol=tolerance)


def test_chain_sampler_matches_paper():
    """Link angles within 45 +- 15 degrees of straight down, released from rest, pin at origin."""
    scene = get_scene("chain16")
    states = sample_initial_states(scene, jax.random.PRNGKey(0), 200)
    dq = np.diff(np.asarray(states.q), axis=1)
    angles = np.degrees(np.arctan2(dq[..., 0], -dq[..., 1]))
    assert angles.min() >= 30 - 1e-9 and angles.max() <= 60 + 1e-9
    assert angles.min() < 31 and angles.max() > 59
    np.testing.assert_allclose(np.linalg.norm(dq, axis=-1), 1.0, rtol=1e-12)
    np.testing.assert_array_equal(states.q[:, 0], 0.0)
    np.testing.assert_array_equal(states.qd, 0.0)
    other = sample_initial_states(scene, jax.random.PRNGKey(1), 200)
    assert not np.allclose(states.q, other.q)


@pytest.mark.parametrize("name, bound", [("chain16", 3e-6), ("T1", 1e-6)])
def test_float32_rollout_error_is_that_of_the_links_not_of_the_positions(name, bound):
    """100 RK4 steps of 1e-3 in float32 against float64 from the same states (as `lgnn
    gpu-truth` measures): positions summed with compensation and projected through their
    link vectors (`integrate.compensated_add`) keep chain16 at 8e-7 and T1 at 5e-7
    (measured, 16 worlds); rounding the positions to their own scale (up to 12 m:
    ulp 1e-6) after every step gave 1.05e-5 and 1.5e-6."""
    scene = get_scene(name)
    states = physics.benchmark_initial_states(scene, 4, 0)
    config = SimulationConfig(dt=1e-3, frame_dt=0.1, duration=0.1)
    run = jax.jit(jax.vmap(rollout_fn(scene, config, physics.vectorised_true_acceleration_fn)))
    final = {dtype: np.asarray(run(jnp.asarray(states.q, dtype), jnp.asarray(states.qd, dtype)).q[:, -1], np.float64)
             for dtype in ("float32", "float64")}
    assert np.max(np.abs(final["float32"] - final["float64"])) < bound
