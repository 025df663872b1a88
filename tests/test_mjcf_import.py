"""MJCF in (`lgnn.import_mjcf`, `lgnn scene import`): files of this test's own, imported
and simulated by the Lagrangian engine, agree with MuJoCo C running the original file
at a refined step; every built-in scene's rendered MJCF imports back as the same scene;
every feature lgnn does not model is refused in one line."""

import json
import tempfile
from pathlib import Path

import mujoco
import numpy as np
import pytest

import lgnn
from lgnn.engines import SimulationConfig, batch_of_one, get_engine, mjcf
from lgnn.engines.mjcf_import import imported, node_positions
from lgnn.errors import SceneError
from lgnn.scene import CATALOGUE, scene_from_dict, scene_names, scene_to_dict

pytestmark = pytest.mark.usefixtures("x64")

# The acceptance bound: every node within this of MuJoCo C on the original file over 2 s.
AGREEMENT_M = 1e-6
DURATION = 2.0
# MuJoCo's refined step (RK4), whose own error over 2 s is far below the bound.
MUJOCO_DT = 1e-4

# A double pendulum of capsules hinged on the world's y axis, moving in the x-z plane
# under MuJoCo's default gravity (-z), started from a keyframe.
DOUBLE_PENDULUM = """<mujoco model="double">
  <option timestep="0.01" integrator="RK4"><flag contact="disable"/></option>
  <default><geom type="capsule" density="1000"/></default>
  <worldbody>
    <body name="upper" pos="0 0 2">
      <joint name="shoulder" type="hinge" axis="0 1 0"/>
      <geom fromto="0 0 0 0 0 -1" size="0.05"/>
      <body name="lower" pos="0 0 -1">
        <joint name="elbow" type="hinge" axis="0 1 0"/>
        <geom fromto="0 0 0 0 0 -0.7" size="0.04"/>
      </body>
    </body>
  </worldbody>
  <keyframe><key name="swing" qpos="0.8 -0.4" qvel="1.5 -2"/></keyframe>
</mujoco>
"""
# dm_control's acrobot's damping on both hinges.
DAMPED_DOUBLE_PENDULUM = DOUBLE_PENDULUM.replace('<default>', '<default><joint damping="0.05"/>')
# A massless pole with a bob at 0.5 m, as dm_control's pendulum (undamped, unactuated
# but for a motor, which does nothing at zero control).
BOB_PENDULUM = """<mujoco model="bob">
  <option><flag contact="disable"/></option>
  <worldbody>
    <body name="pole" pos="0 0 .6">
      <joint name="hinge" type="hinge" axis="0 1 0"/>
      <geom name="pole" type="capsule" fromto="0 0 0 0 0 0.5" size="0.02" mass="0"/>
      <geom name="mass" type="sphere" pos="0 0 0.5" size="0.05" mass="1"/>
    </body>
  </worldbody>
  <actuator><motor name="torque" joint="hinge" gear="1" ctrlrange="-1 1"/></actuator>
  <keyframe><key name="tilted" qpos="2.5" qvel="0.3"/></keyframe>
</mujoco>
"""
# A rope of three ball-jointed capsules of different radii, the last carrying a welded
# sphere at its end, started turning (no spin about any capsule's axis).
ROPE = """<mujoco model="rope">
  <option><flag contact="disable"/></option>
  <default><geom type="capsule" density="500"/></default>
  <worldbody>
    <body name="a" pos="0 0 3">
      <joint type="ball"/>
      <geom fromto="0 0 0 0 0 -0.4" size="0.03"/>
      <body name="b" pos="0 0 -0.4">
        <joint type="ball"/>
        <geom fromto="0 0 0 0 0 -0.5" size="0.025"/>
        <body name="c" pos="0 0 -0.5">
          <joint type="ball"/>
          <geom fromto="0 0 0 0 0 -0.3" size="0.02"/>
          <body name="weight" pos="0 0 -0.3"><geom type="sphere" size="0.04"/></body>
        </body>
      </body>
    </body>
  </worldbody>
  <keyframe><key name="thrown" qpos="0.9950041652780258 0.09983341664682815 0 0  1 0 0 0  1 0 0 0" qvel="0.5 -0.3 0  1 0.2 0  -0.4 0.7 0"/></keyframe>
</mujoco>
"""
# A parallelogram linkage: two cranks hinged to the world and a coupler, closed by a
# stiff connect equality.
FOUR_BAR = """<mujoco model="four-bar">
  <option timestep="1e-4" integrator="RK4"><flag contact="disable"/></option>
  <default><geom type="capsule" size="0.02" mass="1"/></default>
  <worldbody>
    <body name="left" pos="0 0 0">
      <joint type="hinge" axis="0 1 0"/>
      <geom fromto="0 0 0 0.3 0 -1"/>
      <body name="coupler" pos="0.3 0 -1">
        <joint type="hinge" axis="0 1 0"/>
        <geom fromto="0 0 0 1 0 0"/>
        <site name="coupler_end" pos="1 0 0"/>
      </body>
    </body>
    <body name="right" pos="1 0 0">
      <joint type="hinge" axis="0 1 0"/>
      <geom fromto="0 0 0 0.3 0 -1"/>
      <site name="right_end" pos="0.3 0 -1"/>
    </body>
  </worldbody>
  <equality><connect site1="coupler_end" site2="right_end" solref="2e-4 1" solimp="0.9999 0.9999 0.001 0.5 2"/></equality>
</mujoco>
"""

# dm_control's cart-pole (its cart, rail and pole; its slider's limit left out) with a
# second pole, as Gymnasium's inverted double pendulum.
CART_DOUBLE_POLE = """<mujoco model="cart-double-pole">
  <option timestep="0.01" integrator="RK4"><flag contact="disable"/></option>
  <default><default class="pole">
    <joint type="hinge" axis="0 1 0" damping="2e-3"/>
    <geom type="capsule" fromto="0 0 0 0 0 1" size="0.045" mass=".1"/>
  </default></default>
  <worldbody>
    <geom name="floor" pos="0 0 -.05" size="4 4 .2" type="plane"/>
    <body name="cart" pos="0 0 1">
      <joint name="slider" type="slide" axis="1 0 0" damping="5e-2"/>
      <geom name="cart" type="box" size="0.2 0.15 0.1" mass="1"/>
      <body name="pole_1" childclass="pole">
        <joint name="hinge_1"/>
        <geom name="pole_1"/>
        <body name="pole_2" childclass="pole" pos="0 0 1">
          <joint name="hinge_2"/>
          <geom name="pole_2"/>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator><motor name="slide" joint="slider" gear="10" ctrlrange="-1 1"/></actuator>
  <keyframe><key name="falling" qpos="0.1 0.3 -0.2" qvel="0.5 1 -1.5"/></keyframe>
</mujoco>
"""
# Gymnasium's inverted double pendulum's gravity, which leans along the rail.
TILTED_CART_DOUBLE_POLE = CART_DOUBLE_POLE.replace('integrator="RK4"', 'integrator="RK4" gravity="1e-5 0 -9.81"')
# A cart on a rail along the world's y axis with a ball-jointed pole: in 3D the rail
# is one of the scene's axes (z).
CART_BALL_POLE = """<mujoco model="cart-ball-pole">
  <option><flag contact="disable"/></option>
  <worldbody>
    <body name="cart" pos="0 0 1">
      <joint type="slide" axis="0 1 0"/>
      <geom type="box" size="0.2 0.15 0.1" mass="2"/>
      <body name="pole" pos="0 0 0.05">
        <joint type="ball"/>
        <geom type="capsule" fromto="0 0 0 0 0 -1" size="0.03" mass="0.5"/>
      </body>
    </body>
  </worldbody>
  <keyframe><key name="swing" qpos="0 0.9950041652780258 0.09983341664682815 0 0" qvel="0.4 1 -0.5 0"/></keyframe>
</mujoco>
"""


def _write(tmp_path, text: str, name: str = "model.xml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def _mujoco_nodes(path, scene, key: str | None, frame_dt: float, duration: float) -> np.ndarray:
    """(F+1, N, D) the scene's nodes (through its `source`) as MuJoCo C moves the
    original file, RK4 at `MUJOCO_DT`."""
    model = mujoco.MjModel.from_xml_path(str(path))
    model.opt.timestep, model.opt.integrator = MUJOCO_DT, mujoco.mjtIntegrator.mjINT_RK4
    data = mujoco.MjData(model)
    if key is not None:
        mujoco.mj_resetDataKeyframe(model, data, mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, key))
    mujoco.mj_forward(model, data)
    steps = round(frame_dt / MUJOCO_DT)
    frames = [node_positions(scene, model, data)]
    for _ in range(round(duration / frame_dt)):
        for _ in range(steps):
            mujoco.mj_step(model, data)
        frames.append(node_positions(scene, model, data))
    return np.asarray(frames)


@pytest.mark.parametrize(
    "text, key, dim, nodes, pins",
    [(DOUBLE_PENDULUM, "swing", 2, 3, 1), (DAMPED_DOUBLE_PENDULUM, "swing", 2, 3, 1), (BOB_PENDULUM, "tilted", 2, 2, 1),
     (BOB_PENDULUM.replace('axis="0 1 0"', 'axis="0 1 0" damping="0.1"'), "tilted", 2, 2, 1), (ROPE, "thrown", 3, 4, 1), (FOUR_BAR, None, 2, 4, 2),
     (CART_DOUBLE_POLE, "falling", 2, 3, 0), (CART_BALL_POLE, "swing", 3, 2, 0), (TILTED_CART_DOUBLE_POLE, "falling", 2, 3, 0),
     (TILTED_CART_DOUBLE_POLE.replace("1e-5 0 -9.81", "2 0 -9.81"), "falling", 2, 3, 0)],
    ids=["double-pendulum", "damped-double-pendulum", "bob-pendulum", "damped-bob-pendulum", "rope-3d", "four-bar", "cart-double-pole",
         "cart-ball-pole-3d", "gymnasium-gravity", "gravity-along-the-rail"],
)
def test_an_imported_file_moves_as_mujoco_moves_the_original(tmp_path, text, key, dim, nodes, pins):
    path = _write(tmp_path, text)
    scene = lgnn.import_mjcf(path, key=key)
    assert (scene.dim, scene.n_nodes, len(scene.pinned)) == (dim, nodes, pins)
    config = SimulationConfig(duration=DURATION)  # the default step and frames, as `lgnn simulate`
    ours = get_engine("lagrangian").rollout(scene, config, batch_of_one(scene.initial_state)).member(0)
    theirs = _mujoco_nodes(path, scene, key, config.frame_dt, DURATION)
    assert np.abs(theirs[0] - scene.nodes).max() < 1e-12  # the source mapping places every node
    assert ours.q.shape == theirs.shape
    assert np.abs(ours.q - theirs).max() < AGREEMENT_M


def test_a_cart_becomes_a_point_mass_on_a_rail(tmp_path):
    """dm_control's cart (1 kg, a slide along the world's x with damping 5e-2) is node 0:
    a point mass sliding along scene x, where its pole's hinge is; the hinges' damping
    is on the pole (which the cart does not turn) and between the poles."""
    result = imported(_write(tmp_path, CART_DOUBLE_POLE), "falling")
    scene = result.scene
    assert scene.pinned == () and scene.rails == ((0, 0, 0.05),) and scene.point_masses == ((0, pytest.approx(1.0)),)
    assert scene.edges == ((0, 1), (1, 2)) and scene.dampers == ((0, -1, 2e-3), (1, 0, 2e-3))
    np.testing.assert_allclose(scene.masses, 0.1)
    assert scene.source.nodes[0].body == "cart"
    np.testing.assert_allclose(scene.velocities[0], [0.5, 0.0])
    assert result.notes == ("left out: actuator 'slide' (no force at zero control; a scene is the passive system)",)
    # The learned models' graphs know no rails, and the maximal MJCF form has no joints
    # to put a cart on: each says so.
    from lgnn.errors import ConfigError
    from lgnn.learn import models

    with pytest.raises(ConfigError, match="has rails"):
        models.check_compatible(models.ModelConfig.for_scene("lgnn", scene), scene)
    with pytest.raises(SceneError, match="nested form only"):
        mjcf.render(scene, form="maximal")


def _carts():
    """(scene, what it has) of the imported carts, each with a point mass added at its
    last node, which the renderer welds to that node's link as a body of its own."""
    limited = TILTED_CART_DOUBLE_POLE.replace('damping="5e-2"', 'damping="5e-2" range="-0.3 0.45"')
    limited = limited.replace('<joint name="hinge_2"/>', '<joint name="hinge_2" range="-60 45"/>')
    for text, key, what in ((limited, "falling", "planar, damped, tilted gravity, a rail's and a hinge's range"),
                            (CART_BALL_POLE, "swing", "3D, a ball-jointed pole")):
        with tempfile.TemporaryDirectory() as folder:
            scene = lgnn.import_mjcf(_write(Path(folder), text), key)
        yield scene.replace(point_masses=scene.point_masses + ((scene.n_nodes - 1, 0.3),)), what


@pytest.mark.parametrize("engine", ["mujoco", "mjx"])
def test_a_rendered_cart_runs_in_the_mujoco_engines_as_in_the_lagrangian_engine(engine):
    """Rails (a body on a slide, with the slide's damping), point masses (the cart's own
    mass; elsewhere a body welded at the node) and joint ranges (kept in the file, run
    free of, and stopped at as the Lagrangian engine stops) rendered to MJCF: MuJoCo C
    and MJX (float64) move every node as the Lagrangian engine does and stop at the
    same frame."""
    from lgnn.errors import SimulationError

    def run(name, scene, config):
        try:
            return get_engine(name).rollout(scene, config, batch_of_one(scene.initial_state)).member(0), ""
        except SimulationError as err:
            return err.trajectory, str(err)

    stops = []
    for scene, what in _carts():
        config = SimulationConfig(duration=0.7)
        (ours, stopped), (theirs, their_stop) = run("lagrangian", scene, config), run(engine, scene, config)
        assert len(theirs.t) == len(ours.t), what
        assert stopped.partition(": state ")[2] == their_stop.partition(f": {engine} state ")[2], (what, stopped, their_stop)
        assert np.abs(theirs.q - ours.q).max() < 1e-9 and np.abs(theirs.qd - ours.qd).max() < 1e-8, what
        stops.append(stopped)
    assert "left the range of the joint of links [1, 0]" in stops[0] and not stops[1]


def test_a_rendered_cart_imports_back_as_itself(tmp_path):
    """A cart's rail, damping, mass and range, and the hinges' dampers and ranges, go out
    to MJCF and come back the same (the limits as the same quantity and range, though a
    limit may come back as the same joint's links in the other order)."""
    from lgnn.metrics import limit_values

    scene, _ = next(_carts())
    scene = scene.replace(point_masses=scene.point_masses[:1])  # a welded point mass imports as part of its link
    back = lgnn.import_mjcf(_write(tmp_path, mjcf.render(scene)), key=mjcf.INITIAL_KEY)
    np.testing.assert_allclose(back.nodes, scene.nodes, rtol=0, atol=1e-14)
    np.testing.assert_allclose(back.velocities, scene.velocities, rtol=0, atol=1e-12)
    assert (back.edges, back.pinned, back.rails, back.lateral_gravity) == (scene.edges, scene.pinned, scene.rails, scene.lateral_gravity)
    assert back.point_masses[0][0] == 0 and back.point_masses[0][1] == pytest.approx(scene.point_masses[0][1], rel=1e-12)
    assert [(e, p) for e, p, _ in back.dampers] == [(e, p) for e, p, _ in scene.dampers]
    np.testing.assert_allclose([b for *_, b in back.dampers], [b for *_, b in scene.dampers], rtol=1e-12)
    assert len(back.limits) == len(scene.limits) == 2
    free = scene.replace(limits=())
    moved = get_engine("lagrangian").rollout(free, SimulationConfig(duration=1.0), batch_of_one(free.initial_state)).member(0).q
    for ours, theirs in zip(scene.limits, back.limits):
        sign = 1.0 if theirs.links == ours.links else -1.0
        assert theirs.links in (ours.links, ours.links[::-1])
        np.testing.assert_allclose(sorted(sign * np.array([theirs.low, theirs.high])), [ours.low, ours.high], rtol=0, atol=1e-12)
        np.testing.assert_allclose(sign * limit_values(back.replace(limits=(theirs,)), moved), limit_values(scene.replace(limits=(ours,)), moved),
                                   rtol=0, atol=1e-9)


def test_gravity_along_a_rail_is_kept_as_a_vector(tmp_path):
    """The rail is the scene's x axis exactly; Gymnasium's gravity (1e-5, 0, -9.81)
    keeps its 1e-5 along it (the scene's gravity is a vector there), written and read
    back as one."""
    scene = lgnn.import_mjcf(_write(tmp_path, TILTED_CART_DOUBLE_POLE), key="falling")
    np.testing.assert_allclose(scene.gravity_vector, [1e-5, -9.81], rtol=1e-12)
    np.testing.assert_allclose(scene.source.axes[0], [1, 0, 0], atol=1e-15)
    data = scene_to_dict(scene)
    assert isinstance(data["gravity"], list) and scene_from_dict(json.loads(json.dumps(data))) == scene


def test_a_bob_becomes_a_rod_whose_middle_is_the_bobs_centre(tmp_path):
    result = imported(_write(tmp_path, BOB_PENDULUM), "tilted")
    scene = result.scene
    (mass,), (inertia,) = scene.masses, scene.inertias
    assert mass == pytest.approx(1.0)
    assert inertia == pytest.approx(0.4 * 0.05**2, rel=1e-12)  # a solid sphere about its centre
    assert scene.lengths[0] == pytest.approx(1.0, rel=1e-12)
    assert result.notes == ("left out: actuator 'torque' (no force at zero control; a scene is the passive system)",)


def test_the_axes_put_gravity_along_minus_y_and_keep_the_frame_right_handed(tmp_path):
    scene = lgnn.import_mjcf(_write(tmp_path, DOUBLE_PENDULUM), key="swing")
    axes = np.asarray(scene.source.axes)
    assert axes @ np.array([0, 0, -9.81]) == pytest.approx([0, -9.81])
    assert float(scene.gravity) == pytest.approx(9.81)
    # x cross y is the hinge axis (either sign is the same hinge): a rotation, no mirror.
    assert abs(np.cross(axes[0], axes[1]) @ np.array([0, 1, 0])) == pytest.approx(1.0)
    rope = lgnn.import_mjcf(_write(tmp_path, ROPE), key="thrown")
    assert np.linalg.det(np.asarray(rope.source.axes)) == pytest.approx(1.0)


def test_an_imported_scene_keeps_its_source_through_json(tmp_path):
    scene = lgnn.import_mjcf(_write(tmp_path, ROPE), key="thrown")
    again = scene_from_dict(json.loads(json.dumps(scene_to_dict(scene))))
    assert again == scene and again.source == scene.source
    assert scene.source.mjcf == "model.xml"
    assert [node.body for node in scene.source.nodes] == ["world", "a", "b", "c"]


def _canonical(scene):
    """The scene's nodes, velocities, pins and links keyed by node position (an import
    numbers nodes in MuJoCo's body order)."""
    order = np.lexsort(np.round(scene.nodes, 9).T[::-1])
    rank = np.argsort(order)
    links = sorted((tuple(sorted((int(rank[i]), int(rank[j])))), m, inertia, length)
                   for (i, j), m, inertia, length in zip(scene.edges, scene.masses, scene.inertias, scene.lengths))
    return scene.nodes[order], scene.velocities[order], sorted(int(rank[p]) for p in scene.pinned), links


@pytest.mark.parametrize("name", scene_names("mjcf"))
def test_a_built_in_scene_rendered_as_mjcf_imports_back_as_itself(tmp_path, name):
    scene = CATALOGUE[name].build()
    path = _write(tmp_path, mjcf.render(scene), f"{name}.xml")
    back = lgnn.import_mjcf(path, key=mjcf.INITIAL_KEY if np.any(scene.velocities) else None)
    assert (back.name, back.dim, float(back.gravity), back.drag) == (scene.name, scene.dim, float(scene.gravity), scene.drag)
    nodes, velocities, pins, links = _canonical(scene)
    nodes_back, velocities_back, pins_back, links_back = _canonical(back)
    scale = float(np.abs(scene.nodes).max())
    np.testing.assert_allclose(nodes_back, nodes, rtol=0, atol=1e-14 * scale)
    np.testing.assert_allclose(velocities_back, velocities, rtol=0, atol=1e-12 * max(1.0, float(np.abs(scene.velocities).max())))
    assert pins_back == pins
    assert [link[0] for link in links_back] == [link[0] for link in links]
    np.testing.assert_allclose(np.array([link[1:] for link in links_back]), np.array([link[1:] for link in links]), rtol=1e-12, atol=0)


def _spun(scene, rate: float = 1.3):
    """`scene` turning rigidly about its first pin (a state every joint allows)."""
    arm = scene.nodes - scene.nodes[scene.pinned[0]]
    return scene.replace(velocities=rate * np.stack([-arm[:, 1], arm[:, 0]], -1))


def _branching_tree():
    """A pinned tree whose breadth-first link order (0-1, 1-2, 1-3, 2-4) is not MuJoCo's
    depth-first one (0-1, 1-2, 2-4, 1-3), each link turning at its own rate."""
    return scene_from_dict({"name": "tree", "nodes": [[0, 0], [1, 0], [2, 0.5], [2, -0.5], [3, 0.5]], "pinned": [0],
                            "velocities": [[0, 0], [0, 1], [-1, 3], [-0.5, 0], [-1, 6]],
                            "links": [{"nodes": pair, "mass": 1.0, "inertia": 0.1} for pair in ([0, 1], [1, 2], [1, 3], [2, 4])]})


def test_a_rendered_keyframe_holds_the_velocities_mujocos_engine_starts_from():
    """The keyframe's `qvel` is in MuJoCo's joint order (the file's, depth first) and
    is what the engines' state map gives; on a branching tree MuJoCo's own kinematics
    then move every node at the scene's velocity."""
    from lgnn.engines import mujoco as mujoco_engine
    from lgnn.scene import free_triangle

    tree = _branching_tree()
    model = mujoco.MjModel.from_xml_string(mjcf.render(tree))
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, mjcf.INITIAL_KEY))
    mujoco.mj_forward(model, data)
    velocity = np.zeros(6)
    for k in range(tree.n_nodes):
        mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_SITE, model.site(f"node{k}").id, velocity, 0)
        np.testing.assert_allclose(velocity[3:5], tree.velocities[k], rtol=0, atol=1e-12)
    for scene in (CATALOGUE["chain4-3d"].build(), CATALOGUE["chain8-3d"].build(), _spun(CATALOGUE["chain4-varied"].build()), free_triangle(), tree):
        assert np.any(scene.velocities)
        for form in mjcf.FORMS:
            compiled = mujoco_engine.compile_scene(scene, form=form)
            _, qvel = mujoco_engine.state_to_qpos_qvel(compiled, scene.nodes, scene.velocities)
            np.testing.assert_allclose(mjcf.initial_qvel(scene, mjcf.scene_layout(scene, form)), np.asarray(qvel), rtol=0, atol=1e-12)


_BODY = '<body name="arm" pos="0 0 1">{joint}<geom type="capsule" fromto="0 0 0 0 0 -1" size="0.05"/>{child}</body>'


def _model(body: str, option: str = '<flag contact="disable"/>', extra: str = "", attributes: str = "") -> str:
    return f"<mujoco><option{attributes}>{option}</option><worldbody>{body}</worldbody>{extra}</mujoco>"


HINGE = '<joint name="j" type="hinge" axis="0 1 0"{}/>'
REFUSALS = {
    "only a slide": (_model(_BODY.format(joint='<joint name="j" type="slide" axis="1 0 0"/>', child="")), "only slide joints"),
    "slide on a moving body": (_model(_BODY.format(joint=HINGE.format(""), child='<body pos="0 0 -1"><joint name="s" type="slide" axis="0 0 1"/>'
                                                  '<geom type="sphere" size="0.1"/></body>')), "joint 's' slides a body that moves"),
    "slide out of the plane": (CART_DOUBLE_POLE.replace('axis="1 0 0" damping', 'axis="1 0.1 0" damping'),
                               "a slide joint's axis leaves the plane"),
    "free": (_model(_BODY.format(joint="<freejoint name=\"j\"/>", child="")), "joint 'j' is a free joint"),
    "ball damping": (_model(_BODY.format(joint='<joint name="j" type="ball" damping="0.1"/>', child="")), "joint 'j' is a ball joint with damping"),
    "stiffness": (_model(_BODY.format(joint=HINGE.format(' stiffness="2"'), child="")), "joint 'j' has stiffness 2"),
    "armature": (_model(_BODY.format(joint=HINGE.format(' armature="0.1"'), child="")), "joint 'j' has armature"),
    "ball range": (_model(_BODY.format(joint='<joint name="j" type="ball" range="0 30"/>', child="")), "joint 'j' is a ball joint with a range"),
    "limit margin": (_model(_BODY.format(joint=HINGE.format(' range="-10 10" margin="0.2"'), child="")), "its limit margin 0.2 leaves no range"),
    "friction loss": (_model(_BODY.format(joint=HINGE.format(' frictionloss="0.1"'), child="")), "joint 'j' has friction loss"),
    "contact": (_model('<geom name="floor" type="plane" size="3 3 .1"/>' + _BODY.format(joint=HINGE.format(""), child=""), option=""),
                "geoms 'floor' and #1 can collide"),
    "fluid": (_model(_BODY.format(joint=HINGE.format(""), child=""), attributes=' density="1.2"'),
              "fluid forces"),
    "two hinge axes": (_model(_BODY.format(joint=HINGE.format(""), child='<body pos="0 0 -1"><joint name="k" type="hinge" axis="1 0 0"/>'
                                           '<geom type="capsule" fromto="0 0 0 0 0 -1" size="0.05"/></body>')),
                       "joint 'k': its hinge axis differs"),
    "hinge and ball": (_model(_BODY.format(joint=HINGE.format(""), child='<body pos="0 0 -1"><joint type="ball"/>'
                                           '<geom type="capsule" fromto="0 0 0 0 0 -1" size="0.05"/></body>')),
                       "hinge and ball joints together"),
    "off-centre mass": (_model(_BODY.format(joint=HINGE.format(""), child='<geom type="sphere" pos="0 0 -0.2" size="0.2"/>'
                                            '<body pos="0 0 -1"><joint type="hinge" axis="0 1 0"/><geom type="capsule" fromto="0 0 0 0 0 -1" size="0.05"/></body>')),
                        "body 'arm': its centre of mass is not midway"),
    "weld": (_model(_BODY.format(joint=HINGE.format(""), child=""), extra='<equality><weld body1="arm"/></equality>'), "is a weld"),
    "biased actuator": (_model(_BODY.format(joint=HINGE.format(""), child=""), extra='<actuator><position name="servo" joint="j" kp="10"/></actuator>'),
                        "actuator 'servo' pushes at zero control"),
    "no joint": (_model('<body><geom size="0.1"/></body>'), "no body has a joint"),
    "tendon": (_model('<body name="arm" pos="0 0 1"><joint name="j" type="hinge" axis="0 1 0"/><geom type="capsule" fromto="0 0 0 0 0 -1" size="0.05"/>'
                      '<site name="s1"/><site name="s2" pos="0 0 -1"/></body>',
                      extra='<tendon><spatial><site site="s1"/><site site="s2"/></spatial></tendon>'), "1 tendon"),
}


@pytest.mark.parametrize("case", REFUSALS)
def test_what_lgnn_does_not_model_is_refused_in_one_line_naming_it(tmp_path, case):
    text, expected = REFUSALS[case]
    path = _write(tmp_path, text)
    with pytest.raises(SceneError) as raised:
        lgnn.import_mjcf(path)
    message = str(raised.value)
    assert expected in message and "\n" not in message and message.startswith(str(path))


def test_a_missing_keyframe_and_a_broken_file_are_refused_in_one_line(tmp_path):
    with pytest.raises(SceneError, match="no keyframe 'nope' \\(the file has 'swing'\\)"):
        lgnn.import_mjcf(_write(tmp_path, DOUBLE_PENDULUM), key="nope")
    with pytest.raises(SceneError, match="MuJoCo cannot compile it"):
        lgnn.import_mjcf(_write(tmp_path, "<mujoco><worldbody><body><joint type='hinge'/></body>"))
    with pytest.raises(SceneError, match="no such MJCF file"):
        lgnn.import_mjcf(tmp_path / "absent.xml")


def test_lgnn_scene_import_writes_the_scene_and_simulate_runs_it(tmp_path, capsys):
    from lgnn.cli import main

    path = _write(tmp_path, BOB_PENDULUM)
    out = tmp_path / "bob.json"
    assert main(["scene", "import", str(path), "--key", "tilted", "--out", str(out)]) in (0, None)
    err = capsys.readouterr().err
    assert "note: left out: actuator 'torque'" in err and "wrote" in err
    scene = lgnn.load_scene_file(out)
    assert scene == lgnn.import_mjcf(path, key="tilted")
    assert main(["simulate", str(out), "--duration", "0.01", "--out", str(tmp_path / "bob.npz"), "--quiet"]) in (0, None)
    assert main(["scene", "import", str(_write(tmp_path, REFUSALS["free"][0], "free.xml")), "--out", str(tmp_path / "no.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "free joint" in err[0] and not (tmp_path / "no.json").exists()


def test_a_source_that_does_not_describe_its_nodes_is_refused(tmp_path):
    data = scene_to_dict(lgnn.import_mjcf(_write(tmp_path, DOUBLE_PENDULUM), key="swing"))
    data["source"]["nodes"] = data["source"]["nodes"][:-1]
    with pytest.raises(SceneError, match="source.nodes: expected 3 entries"):
        scene_from_dict(data)
    data = scene_to_dict(lgnn.import_mjcf(_write(tmp_path, DOUBLE_PENDULUM), key="swing"))
    data["source"]["axes"][0] = [1, 1, 0]
    with pytest.raises(SceneError, match="source.axes: rows must be orthonormal"):
        scene_from_dict(data)


def test_engines_agree_on_an_imported_damped_scene(tmp_path):
    """The damped double pendulum read back: the Lagrangian engine, MuJoCo C and MJX on
    lgnn's own rendering (hinge `damping=`, the keyframe's velocities) agree, and lose
    the same energy; MJX's own choice of form keeps the damping's joints."""
    from lgnn.engines import batch_of_one, get_engine
    from lgnn.engines.base import SimulationConfig
    from lgnn.engines.mjx import best_form

    scene = lgnn.import_mjcf(_write(tmp_path, DAMPED_DOUBLE_PENDULUM), key="swing")
    assert best_form(scene) == "nested"
    config = SimulationConfig(dt=1e-3, frame_dt=1e-2, duration=1.0)
    runs = {name: get_engine(name).rollout(scene, config, batch_of_one(scene.initial_state)) for name in ("lagrangian", "mujoco", "mjx")}
    truth = runs.pop("lagrangian")
    lost = truth.energy[0, 0] - truth.energy[0, -1]
    assert lost > 0.1  # the damping is felt
    for name, run in runs.items():
        assert np.abs(np.asarray(run.q) - np.asarray(truth.q)).max() < 1e-8, name
        np.testing.assert_allclose(run.energy[0, 0] - run.energy[0, -1], lost, rtol=1e-8, err_msg=name)


def _first_outside(path, key: str | None, joint: str, frame_dt: float, duration: float) -> int:
    """The first frame (of `frame_dt`) at which MuJoCo C, moving the original file with
    its limits switched off, has `joint`'s qpos outside its range; -1 if none."""
    model = mujoco.MjModel.from_xml_path(str(path))
    model.opt.timestep, model.opt.integrator = MUJOCO_DT, mujoco.mjtIntegrator.mjINT_RK4
    model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_LIMIT)
    data = mujoco.MjData(model)
    if key is not None:
        mujoco.mj_resetDataKeyframe(model, data, mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, key))
    j = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, joint)
    low, high = model.jnt_range[j] + np.array([1, -1]) * model.jnt_margin[j]  # where MuJoCo's limit would act
    for frame in range(round(duration / frame_dt) + 1):
        if not low <= data.qpos[model.jnt_qposadr[j]] <= high:
            return frame
        for _ in range(round(frame_dt / MUJOCO_DT)):
            mujoco.mj_step(model, data)
    return -1


@pytest.mark.parametrize(
    "text, key, joint",
    # (MuJoCo reads hinge ranges in degrees by default.)
    [(CART_DOUBLE_POLE.replace('damping="5e-2"', 'damping="5e-2" range="-0.3 0.45"'), "falling", "slider"),
     # Gymnasium's inverted double pendulum's slider has a margin.
     (TILTED_CART_DOUBLE_POLE.replace('damping="5e-2"', 'damping="5e-2" range="-0.3 0.45" margin="0.05"'), "falling", "slider"),
     (CART_DOUBLE_POLE.replace('<joint name="hinge_2"/>', '<joint name="hinge_2" range="-35 6"/>'), "falling", "hinge_2"),
     (DOUBLE_PENDULUM.replace('<joint name="elbow" type="hinge" axis="0 1 0"/>', '<joint name="elbow" type="hinge" axis="0 1 0" range="-70 50"/>'),
      "swing", "elbow"),
     (DOUBLE_PENDULUM.replace('<joint name="shoulder" type="hinge" axis="0 1 0"/>', '<joint name="shoulder" type="hinge" axis="0 -1 0" range="-40 86"/>'),
      "swing", "shoulder")],
    ids=["slider", "slider-with-margin", "pole-on-pole", "elbow", "shoulder-reversed-axis"],
)
def test_a_joint_range_is_kept_as_a_limit_and_the_engine_stops_where_mujocos_joint_leaves_it(tmp_path, text, key, joint):
    """A limited slide or hinge becomes a limit in the scene's coordinates (its sign and
    offset from the joint's qpos at the keyframe); the Lagrangian engine stops at the
    frame where MuJoCo C's qpos (its limits off) first leaves the range, flagged, with
    the motion up to there MuJoCo's."""
    from lgnn.errors import SimulationError

    path = _write(tmp_path, text)
    result = imported(path, key)
    scene = result.scene
    assert len(scene.limits) == 1 and any("limits" in note for note in result.notes)
    config = SimulationConfig(duration=DURATION)
    expected = _first_outside(path, key, joint, config.frame_dt, DURATION)
    assert expected > 10  # the joint starts inside its range and leaves it within the run
    with pytest.raises(SimulationError, match="left the range of") as raised:
        get_engine("lagrangian").rollout(scene, config, batch_of_one(scene.initial_state))
    partial = raised.value.trajectory
    assert abs(len(partial.t) - expected) <= 1, (len(partial.t), expected)
    theirs = _mujoco_nodes(path, scene, key, config.frame_dt, DURATION)[: len(partial.t)]
    assert np.abs(partial.q - theirs).max() < AGREEMENT_M


# ---------------------------------------------------------------------- built-in imports
IMPORTED_SOURCES = Path(lgnn.__file__).parent / "assets" / "mjcf"


def _only_key(path) -> str:
    model = mujoco.MjModel.from_xml_path(str(path))
    assert model.nkey == 1, path
    return model.key(0).name


def _numbers_close(a, b, path="") -> None:
    """Two JSON values equal, their numbers to 1e-12 relative (MuJoCo's compile on
    another machine may round a last bit otherwise)."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), path
        for key in a:
            _numbers_close(a[key], b[key], f"{path}.{key}")
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), path
        for k, (x, y) in enumerate(zip(a, b)):
            _numbers_close(x, y, f"{path}[{k}]")
    elif isinstance(a, float) or isinstance(b, float):
        assert a == pytest.approx(b, rel=1e-12, abs=1e-15), path
    else:
        assert a == b, path


@pytest.mark.parametrize("name", scene_names("imported"))
def test_a_built_in_imported_scene_is_its_source_file_imported_and_moves_as_mujoco_moves_it(name):
    """Each built-in imported scene (lgnn/assets/imported/) is the import of its source
    file (lgnn/assets/mjcf/, at its one keyframe), and the Lagrangian engine moves it as
    MuJoCo C moves that file (RK4 at 1e-4) over 2 s, every node within 1e-6 m, up to
    where a joint leaves its range (where lgnn stops)."""
    from lgnn.errors import SimulationError

    path = IMPORTED_SOURCES / f"{name}.xml"
    key = _only_key(path)
    scene = CATALOGUE[name].build()
    _numbers_close(scene_to_dict(scene), scene_to_dict(imported(path, key).scene))
    config = SimulationConfig(duration=DURATION)
    try:
        ours = get_engine("lagrangian").rollout(scene, config, batch_of_one(scene.initial_state)).member(0).q
    except SimulationError as err:
        assert "left the range" in str(err)
        ours = err.trajectory.q
    theirs = _mujoco_nodes(path, scene, key, config.frame_dt, DURATION)[: len(ours)]
    assert len(ours) > 50 and np.abs(ours[-1] - ours[0]).max() > 0.05  # it moves
    assert np.abs(ours - theirs).max() < AGREEMENT_M


def test_the_built_in_imported_scenes_run_in_mujoco_c_as_in_the_lagrangian_engine():
    """MuJoCo C on every built-in imported scene's rendered MJCF (mjcf/) agrees with the
    Lagrangian engine to 1e-9 m over 1 s and stops where it stops. (MJX on rendered carts,
    planar and 3D: `test_a_rendered_cart_runs_in_the_mujoco_engines_as_in_the_lagrangian_engine`.)"""
    engine = "mujoco"
    from lgnn.errors import SimulationError

    def run(which, scene, config):
        try:
            return get_engine(which).rollout(scene, config, batch_of_one(scene.initial_state)).member(0), ""
        except SimulationError as err:
            return err.trajectory, str(err).split(" state ", 1)[-1]

    for name in scene_names("imported"):
        scene, config = CATALOGUE[name].build(), SimulationConfig(duration=1.0)
        (ours, stopped), (theirs, their_stop) = run("lagrangian", scene, config), run(engine, scene, config)
        assert (len(theirs.t), their_stop) == (len(ours.t), stopped), name
        assert np.abs(theirs.q - ours.q).max() < 1e-9 and np.abs(theirs.qd - ours.qd).max() < 1e-8, name
