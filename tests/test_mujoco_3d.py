"""MuJoCo in 3D: both MJCF forms of spatial scenes (nested ball joints, maximal free
bodies) against the exact Lagrangian engine, the quaternion state maps, the rod's
axial inertia, the planar embedding, and a user's 3D file through the CLI (MJX too).

Tolerances are measured (RK4, dt 1e-4, 0.5 s): chain4-3d nested 2.8e-14, maximal
1.6e-9; net3x3-3d (5 loops) nested 3.6e-9, maximal 2.0e-8 (the `connect` softness of
`mjcf.SOLREF_STEPS` / `MAXIMAL_SOLREF_STEPS`, as in 2D); an unpinned triangle with a
tail (free-3d) nested 5.7e-12, maximal 1.9e-11.
"""

import functools
import json

import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from lgnn import physics
from lgnn.cli import main
from lgnn.engines import get_engine, mjcf
from lgnn.engines import mujoco as lm
from lgnn.engines.base import SimulationConfig, Trajectory
from lgnn.engines.lagrangian import simulate
from lgnn.scene import embedded_in_3d, get_scene, scene_from_dict, scene_to_dict, spatial_chain, spatial_net
from lgnn.scene.catalogue import double_pinned_chain

# 51 frames: the map to node states (a Python loop over frames in MuJoCo C) stays cheap.
HALF_SECOND = SimulationConfig(dt=1e-4, frame_dt=1e-2, duration=0.5)


def free_scene():
    """An unpinned triangle with a tail in 3D, moving rigidly (a free root: a free joint
    at a node in the nested form)."""
    nodes = np.array([[0, 0, 0], [1, 0, 0.3], [0.5, 0.8, -0.2], [1.5, 0.8, 0.4]])
    velocities = np.array([0.3, 0.1, -0.2]) + np.cross([0.3, -0.5, 0.7], nodes)
    links = [{"nodes": list(e), "mass": 1.0, "inertia": 0.1} for e in [(0, 1), (1, 2), (2, 0), (2, 3)]]
    return scene_from_dict({"name": "free-3d", "nodes": nodes.tolist(), "velocities": velocities.tolist(), "pinned": [], "links": links})


# chain4-3d-varied: links of four lengths, masses and inertias (the transfer track's),
# where a unit chain would hide a swapped or misscaled per-link property.
SCENES = {"chain4-3d": lambda: get_scene("chain4-3d"), "chain4-3d-varied": lambda: get_scene("chain4-3d-varied"),
          "net3x3-3d": lambda: spatial_net(3, 3), "free-3d": free_scene}


@functools.cache
def scene(name):
    return SCENES[name]()


@functools.cache
def lagrangian(name):
    return simulate(scene(name), HALF_SECOND)


@pytest.mark.parametrize("form", mjcf.FORMS)
@pytest.mark.parametrize("name", SCENES)
def test_rendered_spatial_model_reproduces_nodes(name, form):
    s = scene(name)
    compiled = lm.compile_scene(s, 1e-4, form)
    data = mujoco.MjData(compiled.model)
    mujoco.mj_kinematics(compiled.model, data)
    np.testing.assert_allclose(data.site_xpos[compiled.node_site], s.nodes, rtol=0, atol=1e-12)


@functools.cache
def spatial_states(name):
    """Node states of scene `name` to map: its own shape and, for the chain, the shape
    turned about its pin by 1.4 rad and every link reversed (the far side of the
    shortest-rotation map), each with the node velocities of a random joint velocity
    of the nested model that keeps its loops closed."""
    s = scene(name)
    shapes = [np.asarray(s.nodes)]
    if s.name.startswith("chain"):
        axis = np.array([0.3, -0.8, 0.5]) / np.linalg.norm([0.3, -0.8, 0.5])
        cross = np.cross(np.eye(3), axis)  # Rodrigues: R = I + sin K + (1 - cos) K^2
        turn = np.eye(3) + np.sin(1.4) * cross + (1 - np.cos(1.4)) * cross @ cross
        shapes.append(s.nodes[0] + (s.nodes - s.nodes[0]) @ turn.T)
        links = np.diff(s.nodes, axis=0)
        shapes.append(np.concatenate([s.nodes[:1], s.nodes[:1] - np.cumsum(links, axis=0)]))
    nested = lm.compile_scene(s, 1e-4, "nested")
    rng, states = np.random.default_rng(5), []
    for q in shapes:
        qpos = np.asarray(lm.state_to_qpos_qvel(nested, jnp.asarray(q), jnp.zeros_like(q))[0])
        qvel = rng.normal(size=nested.model.nv)
        if nested.model.neq:
            eq = lm.equality_jacobian(nested, qpos)
            qvel -= np.linalg.pinv(eq) @ (eq @ qvel)  # test-only: a velocity that keeps loops closed
        states.append((q, (lm.site_jacobian(nested, qpos) @ qvel).reshape(q.shape)))
    return states


@pytest.mark.parametrize("form", mjcf.FORMS)
@pytest.mark.parametrize("name", SCENES)
def test_spatial_state_maps_round_trip_and_keep_the_kinetic_energy(name, form):
    """Node states -> qpos (unit quaternions), qvel -> MuJoCo's kinematics gives the
    node states back, and MuJoCo's `1/2 qvel M qvel` is lgnn's rod kinetic energy (no
    spin about a link's axis is put in)."""
    s = scene(name)
    compiled = lm.compile_scene(s, 1e-4, form)
    for q, qd in spatial_states(name):
        qpos, qvel = (np.asarray(x) for x in lm.state_to_qpos_qvel(compiled, jnp.asarray(q), jnp.asarray(qd)))
        quats = qpos[compiled.rotation_qpos[:, None] + np.arange(4)]
        np.testing.assert_allclose(np.linalg.norm(quats, axis=-1), 1.0, rtol=0, atol=1e-14)
        nodes = lm.node_states(compiled, qpos, qvel)
        np.testing.assert_allclose(nodes.q[0], q, rtol=0, atol=1e-12)
        np.testing.assert_allclose(nodes.qd[0], qd, rtol=0, atol=1e-11)
        mass = lm.mass_matrix(compiled, qpos)
        np.testing.assert_allclose(0.5 * qvel @ mass @ qvel, float(jnp.sum(physics.kinetic_energy_per_link(s, jnp.asarray(q), jnp.asarray(qd)))), rtol=1e-12)


@pytest.mark.parametrize(("name", "form", "tolerance"), [
    ("chain4-3d", "nested", 1e-12), ("chain4-3d", "maximal", 1e-8), ("chain4-3d-varied", "nested", 1e-12),
    ("net3x3-3d", "nested", 2e-8), ("net3x3-3d", "maximal", 1e-7),
    ("free-3d", "nested", 1e-10),
])
def test_spatial_scenes_agree_with_lagrangian(name, form, tolerance):
    ref = lagrangian(name)
    ours = lm.rollout(scene(name), HALF_SECOND, form=form)
    assert np.max(np.abs(ref.q[-1] - ref.q[0])) > 0.2  # it moves
    err = np.max(np.abs(ours.q[0] - ref.q))
    assert err <= tolerance, f"{name} {form}: MuJoCo vs Lagrangian {err:.2e}"


@pytest.mark.parametrize(("form", "tolerance"), [("nested", 1e-8), ("maximal", 1e-6)])
def test_tensegrity_agrees_with_lagrangian(form, tolerance):
    """The loose tensegrity prism (rods and slack rope chains, 9 independent loops
    through its pins and rods) in both forms. Measured (RK4, dt 1e-4, 0.2 s): nested
    1.1e-9, maximal 8.0e-8 (the `connect` softness); over 0.5 s 1.4e-8 and 4.8e-7."""
    s, config = get_scene("tensegrity-3d"), SimulationConfig(dt=1e-4, frame_dt=1e-2, duration=0.2)
    ref = simulate(s, config)
    err = np.max(np.abs(lm.rollout(s, config, form=form).q[0] - ref.q))
    assert np.max(np.abs(ref.q[-1] - ref.q[0])) > 0.1  # it moves
    assert err <= tolerance, f"tensegrity-3d {form}: MuJoCo vs Lagrangian {err:.2e}"


def test_axial_inertia_is_never_excited_and_does_not_matter(monkeypatch):
    """A rod's spin about its own axis stays zero (gravity and joint forces act on the
    axis): measured at most 4e-10 rad/s over 0.2 s (the loops' soft `connect`s; open
    chains 1e-12), against link angular speeds of order 1. So its axial inertia, 10x
    or 100x down (up is beyond MuJoCo's triangle inequality), changes nothing but
    round-off (measured 6e-14)."""
    s, config = scene("net3x3-3d"), SimulationConfig(dt=1e-4, frame_dt=1e-2, duration=0.2)
    compiled, qpos, qvel = lm.joint_rollout(s, config)
    data, velocity = mujoco.MjData(compiled.model), np.empty(6)
    data.qpos[:], data.qvel[:] = qpos[0, -1], qvel[0, -1]
    mujoco.mj_forward(compiled.model, data)
    direction = data.site_xpos[compiled.node_site[compiled.tip]] - data.site_xpos[compiled.node_site[compiled.base]]
    for body, d in zip(compiled.body_id, direction):
        mujoco.mj_objectVelocity(compiled.model, data, mujoco.mjtObj.mjOBJ_BODY, body, velocity, 0)
        assert abs(velocity[:3] @ d) / np.linalg.norm(d) <= 1e-9 and np.linalg.norm(velocity[:3]) > 0.1
    reference = lm.node_trajectories(compiled, qpos, qvel).q
    try:
        for factor in (0.1, 0.01):
            monkeypatch.setattr(mjcf, "AXIAL_INERTIA_FRACTION", mjcf.AXIAL_INERTIA_FRACTION * factor)
            lm.compile_scene.cache_clear()
            assert np.max(np.abs(lm.rollout(s, config).q - reference)) <= 1e-12
    finally:
        monkeypatch.undo()
        lm.compile_scene.cache_clear()


@pytest.mark.parametrize(("planar", "form", "tolerance"), [("chain4", "nested", 1e-13), ("double-pinned", "maximal", 1e-8)])
def test_planar_scene_embedded_in_3d_moves_as_in_2d(planar, form, tolerance):
    """An embedded planar scene stays at z = 0 and has the planar MuJoCo trajectory: to
    round-off with exact joints; with `connect`s within their softness (measured over
    0.5 s: chain4 maximal 2.3e-10, double-pinned nested 2.1e-10, maximal 1.1e-9), which
    differs a little between hinges and balls (MuJoCo scales it by body weights)."""
    flat = get_scene("chain4") if planar == "chain4" else double_pinned_chain()
    ours = lm.rollout(embedded_in_3d(flat), HALF_SECOND, form=form)
    reference = lm.rollout(flat, HALF_SECOND, form=form)
    np.testing.assert_array_equal(ours.q[..., 2], 0.0)  # exact: every out-of-plane term MuJoCo adds is zero
    assert np.max(np.abs(ours.q[..., :2] - reference.q)) <= tolerance


def test_user_3d_file_through_every_engine_and_mjcf(tmp_path, capsys):
    """A user's 3D chain file through `lgnn simulate` (Lagrangian, MuJoCo C, MJX
    float64, each engine's automatic form: nested) and `lgnn mjcf` in both forms.
    Measured over 0.05 s: MuJoCo C to Lagrangian 2e-15; MJX to either at round-off
    since it steps with MuJoCo C 4.0's RK4 for ball joints (`lgnn.engines.mjx.make_step`;
    mjx.step's uncorrected RK4 was 1.7e-10 off here, growing about linearly)."""
    s = spatial_chain(2, name="mine")
    path = tmp_path / "mine.json"
    path.write_text(json.dumps(scene_to_dict(s)))
    out = {}
    for engine in ("lagrangian", "mujoco", "mjx"):
        npz = tmp_path / f"{engine}.npz"
        capsys.readouterr()
        assert main(["simulate", str(path), "--engine", engine, "--duration", "0.05", "--out", str(npz)]) == 0
        if engine == "mjx":
            assert "MJX: compiling mine (nested form" in capsys.readouterr().err
        out[engine] = Trajectory.load(npz)
        assert out[engine].q.shape == (51, 3, 3)
    assert get_engine("mujoco").form_of(s) == "nested"
    assert np.max(np.abs(out["mujoco"].q - out["lagrangian"].q)) <= 1e-12
    assert np.max(np.abs(out["mjx"].q - out["mujoco"].q)) <= 1e-12
    assert np.max(np.abs(out["mjx"].qd - out["mujoco"].qd)) <= 1e-11
    for form in mjcf.FORMS:
        xml = tmp_path / f"{form}.xml"
        assert main(["mjcf", str(path), "--form", form, "--out", str(xml)]) == 0
        model = mujoco.MjModel.from_xml_path(str(xml))
        # nested: two ball joints; maximal: two free joints and a connect at node 1 and the pin
        assert (model.nq, model.nv, model.neq) == ((8, 6, 0) if form == "nested" else (14, 12, 2))
