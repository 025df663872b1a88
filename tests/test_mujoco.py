"""MuJoCo (C) and MJX against the exact Lagrangian engine, the maps between them, the
MJCF rendering, and the one engine interface (`lgnn.engines`).

Tolerances are measured (RK4, dt 1e-4, 1 s): open chains agree to ~1e-13, loops to
~9e-8 (loop6, T1; MuJoCo's stiff but soft `connect`), drag to 1.9e-6 (drag held over
a step), MJX float64 to MuJoCo C to ~1e-14 on open chains. The maximal form (every
joint a soft `connect`): 3e-11..5e-7 over 1 s, falling as dt^2. MJX compiles slowly on
CPU (~35 s for chain4 nested, ~30 s of CPU time for chain12 maximal), so one small
scene per form is compiled once per session.
"""

import functools
import json
import subprocess
import sys

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from lgnn import physics
from lgnn.cli import main
from lgnn.engines import ENGINES, batch_of_one, get_engine, mjcf
from lgnn.engines import mujoco as lm
from lgnn.errors import ConfigError, SceneError, SimulationError
from lgnn.scene import State, scene_from_dict, scene_to_dict
from lgnn.scene import chain, get_scene, sample_initial_states, scene_names
from lgnn.engines.base import Integration, SimulationConfig, Trajectory
from lgnn.engines.lagrangian import simulate


pytestmark = pytest.mark.xla_optimised  # MJX programs run thousands of steps (conftest.py)

# The engines' chain4 rollouts (0.25 s: MJX's CPU run of a whole second took most of a
# 2-core CI minute; a quarter already swings every link through large angles).
CHAIN4_ROLLOUT = SimulationConfig(dt=1e-4, frame_dt=1e-3, duration=0.25)


def tree_scene():
    """A branching tree pinned at node 0, with unequal links."""
    nodes = [[0, 0], [0.6, -0.8], [1.6, -0.8], [0.6, -1.8], [0.0, -2.6], [1.6, 0.2]]
    edges = [(0, 1), (1, 2), (1, 3), (3, 4), (2, 5)]
    links = [{"nodes": list(e), "mass": 1.0 + 0.3 * k, "inertia": 0.05 + 0.02 * k} for k, e in enumerate(edges)]
    return scene_from_dict({"name": "tree", "nodes": nodes, "pinned": [0], "links": links})


def loop_scene():
    """A 6-link chain pinned at both ends (one closed loop through the world)."""
    data = scene_to_dict(chain(6, seed=1))
    data.update(name="loop6", pinned=[0, 6])
    return scene_from_dict(data)


def free_scene():
    """An unpinned, moving 3-link chain with a closed triangle (free planar root)."""
    nodes = [[0, 0], [1, 0], [0.5, 0.8], [1.5, 0.8]]
    edges = [(0, 1), (1, 2), (2, 0), (2, 3)]
    links = [{"nodes": list(e), "mass": 1.0, "inertia": 0.1} for e in edges]
    w = 0.7  # rigid rotation about node 0 plus a translation: satisfies every link
    velocities = [[0.3 - w * y, 0.1 + w * x] for x, y in nodes]
    return scene_from_dict({"name": "free", "nodes": nodes, "velocities": velocities, "pinned": [], "links": links})


EXTRA = {"tree": tree_scene, "loop6": loop_scene, "free": free_scene}


@functools.cache
def scene(name):
    return EXTRA[name]() if name in EXTRA else get_scene(name)


@functools.cache
def lagrangian(name, duration=1.0):
    return simulate(scene(name), SimulationConfig(dt=1e-4, duration=duration))


@functools.cache
def mujoco_c(name, duration=1.0):
    return lm.rollout(scene(name), SimulationConfig(dt=1e-4, duration=duration))


def max_violation(s, q):
    return float(np.max(jax.vmap(lambda x: physics.constraint_violation(s, x))(q)))


# --------------------------------------------------------------------- layout and maps


def test_layout_spanning_tree():
    assert [b.closes_loop for b in mjcf.scene_layout(scene("chain4")).bodies] == [False] * 4
    loop = mjcf.scene_layout(scene("loop6"))
    assert sum(b.closes_loop for b in loop.bodies) == 1 and len(loop.bodies) == 6
    free = mjcf.scene_layout(scene("free"))
    assert [b.free_root for b in free.bodies].count(True) == 1 and sum(b.closes_loop for b in free.bodies) == 1
    t3 = get_scene("T3")
    layout = mjcf.scene_layout(t3)
    pinned = set(t3.pinned)
    assert len(layout.bodies) + len(layout.static_links) == t3.n_links
    assert all(set(t3.edges[e]) <= pinned for e in layout.static_links)


@pytest.mark.parametrize("form", mjcf.FORMS)
@pytest.mark.parametrize("name", [*scene_names("paper"), *EXTRA])
def test_rendered_model_reproduces_nodes(name, form):
    s = scene(name)
    compiled = lm.compile_scene(s, 1e-4, form)
    data = mujoco.MjData(compiled.model)
    mujoco.mj_kinematics(compiled.model, data)
    np.testing.assert_allclose(data.site_xpos[compiled.node_site, :2], s.nodes, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(data.site_xpos[compiled.node_site, 2], 0.0)  # exact: in-plane offsets, z hinges


@pytest.mark.parametrize(("name", "form"), [(name, "nested") for name in ["chain8", "chain4-varied", "tree", "free", "loop6", "T1"]]
                         + [(name, "maximal") for name in ["chain4-varied", "free", "loop6"]])
def test_state_maps_round_trip(name, form):
    s = scene(name)
    compiled = lm.compile_scene(s, 1e-4, form)
    states = sample_initial_states(s, jax.random.key(1), 3)
    # Rigid-body-consistent velocities: from a random qvel of the sampled shapes.
    for q in np.asarray(states.q):
        qpos, _ = lm.state_to_qpos_qvel(compiled, jnp.asarray(q), jnp.zeros_like(q))
        qvel = np.random.default_rng(0).normal(size=compiled.model.nv)
        if any(b.closes_loop for b in compiled.layout.bodies):
            jac = lm.equality_jacobian(compiled, np.asarray(qpos))
            qvel -= np.linalg.pinv(jac) @ (jac @ qvel)  # test-only: a velocity that keeps loops closed
        nodes = lm.node_states(compiled, np.asarray(qpos), qvel)
        np.testing.assert_allclose(nodes.q[0], q, rtol=0, atol=1e-12)
        qpos2, qvel2 = lm.state_to_qpos_qvel(compiled, jnp.asarray(nodes.q[0]), jnp.asarray(nodes.qd[0]))
        np.testing.assert_allclose(np.asarray(qvel2), qvel, rtol=0, atol=1e-10)
        np.testing.assert_allclose(np.cos(np.asarray(qpos2) - np.asarray(qpos)), 1.0, rtol=0, atol=1e-12)


@pytest.mark.parametrize(("name", "form"), [("tree", "nested"), ("free", "maximal"), ("chain4-3d", "nested"), ("chain4-3d", "maximal")])
def test_node_velocities_are_the_sites_jacobians_times_qvel(name, form):
    """`node_states` takes velocities from the bodies' `cvel`; MuJoCo's definition is
    `mj_jacSite @ qvel`, per site: both at random qpos and qvel, over 3 frames."""
    s = get_scene(name) if name == "chain4-3d" else scene(name)
    compiled, rng = lm.compile_scene(s, 1e-4, form), np.random.default_rng(2)
    model, data = compiled.model, mujoco.MjData(compiled.model)
    qpos = np.stack([model.qpos0 + 0.3 * rng.normal(size=model.nq) for _ in range(3)])
    qvel = rng.normal(size=(3, model.nv))
    nodes, jac = lm.node_states(compiled, qpos, qvel), np.empty((3, model.nv))
    for f in range(3):
        data.qpos[:] = qpos[f]
        mujoco.mj_kinematics(model, data), mujoco.mj_comPos(model, data)
        for k, site in enumerate(compiled.node_site):
            mujoco.mj_jacSite(model, data, jac, None, site)
            np.testing.assert_allclose(nodes.qd[f, k], (jac @ qvel[f])[:s.dim], rtol=0, atol=1e-12)
            np.testing.assert_array_equal(nodes.q[f, k], data.site_xpos[site, :s.dim])


@pytest.mark.parametrize(("name", "form"), [(name, "nested") for name in ["chain4-varied", "tree", "free", "loop6", "T1"]]
                         + [(name, "maximal") for name in ["chain4-varied", "free", "T1"]])
def test_mass_matrix_matches_kinetic_energy(name, form):
    """MuJoCo's M mapped to node velocities gives lgnn's exact rod kinetic energy (in
    the maximal form: on velocities that keep every `connect` joint together)."""
    s = scene(name)
    compiled = lm.compile_scene(s, 1e-4, form)
    qpos, _ = lm.state_to_qpos_qvel(compiled, jnp.asarray(s.nodes), jnp.asarray(s.velocities))
    qpos = np.asarray(qpos)
    mass, jac = lm.mass_matrix(compiled, qpos), lm.site_jacobian(compiled, qpos)
    kinetic = jax.jit(lambda qd: jnp.sum(physics.kinetic_energy_per_link(s, jnp.asarray(s.nodes), qd)))
    rng = np.random.default_rng(2)
    for _ in range(5):
        qvel = rng.normal(size=compiled.model.nv)
        if any(b.closes_loop for b in compiled.layout.bodies):
            eq = lm.equality_jacobian(compiled, qpos)
            qvel -= np.linalg.pinv(eq) @ (eq @ qvel)  # test-only projection onto loop-preserving velocities
        qd = (jac @ qvel).reshape(s.n_nodes, 2)
        ours = float(kinetic(jnp.asarray(qd)))
        # Links between two pins have no body and no velocity: they add nothing.
        np.testing.assert_allclose(0.5 * qvel @ mass @ qvel, ours, rtol=1e-12)


def test_the_files_check_allows_the_last_bits_only():
    text = '<key name="initial" qvel="0.18714713107606384 -1.614022247386884"/>'
    assert mjcf.same_up_to_rounding(text, text.replace("384", "373"))
    assert not mjcf.same_up_to_rounding(text, text.replace("0.1871471310", "0.1871471311"))
    assert not mjcf.same_up_to_rounding(text, text.replace("initial", "start"))


def test_mjcf_files_match_rendering():
    """mjcf/ holds both forms of every built-in and spatial scene (maximal ones under
    mjcf/maximal/)."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "mjcf"
    files = mjcf.builtin_files()
    only_nested = [name for name in scene_names("mjcf") if mjcf.nested_only(get_scene(name))]
    # The planar imported scenes have dampers, rails, point masses or limits; the 3D rope of capsules has none (both forms).
    assert len(files) == len(mjcf.FORMS) * len(scene_names("mjcf")) - len(only_nested) and set(only_nested) >= set(scene_names("planar", "imported"))
    assert "maximal/rope-capsules-3d.xml" in files
    for name, text in files.items():
        path = root / name
        assert path.exists(), f"{path} missing: run `python -m lgnn.cli mjcf`"
        assert mjcf.same_up_to_rounding(path.read_text(), text), f"{path} drifted: run `python -m lgnn.cli mjcf`"
        mujoco.MjModel.from_xml_path(str(path))
    assert files["chain4.xml"] == mjcf.render(get_scene("chain4"), form="nested")


def test_maximal_layout_is_flat():
    """Every moving link is a free body under the world; a node with k links gets k-1
    connects (plus one per link at a pin), so loops need no spanning tree."""
    t1 = get_scene("T1")
    layout = mjcf.scene_layout(t1, "maximal")
    assert layout.depth == 1 and all(b.free_root for b in layout.bodies)
    assert len(layout.bodies) + len(layout.static_links) == t1.n_links
    degree = np.bincount(np.asarray(t1.edges).ravel(), minlength=t1.n_nodes)
    pinned = set(t1.pinned)
    moving = [e for e in range(t1.n_links) if e not in layout.static_links]
    expected = sum(degree[k] - 1 for k in range(t1.n_nodes) if k not in pinned)
    expected += sum(1 for e in moving for k in t1.edges[e] if k in pinned)
    assert len(layout.ties) == expected
    with pytest.raises(ConfigError, match="form"):
        mjcf.render(t1, form="spatial")


# --------------------------------------------------------------------- agreement


@pytest.mark.parametrize("name", ["chain4", "chain8", "chain16", "tree"])
def test_open_chains_agree_with_lagrangian(name):
    err = np.max(np.abs(mujoco_c(name).q[0] - lagrangian(name).q))
    assert err <= 1e-7, f"{name}: MuJoCo RK4 vs Lagrangian RK4 max node error {err:.2e}"


@pytest.mark.parametrize("name", ["loop6", "T1"])
def test_closed_loops_agree_with_lagrangian(name):
    s, ours = scene(name), mujoco_c(name)
    err = np.max(np.abs(ours.q[0] - lagrangian(name).q))
    violation = max_violation(s, ours.q[0])
    print(f"{name}: max node error {err:.2e}, MuJoCo loop-closure violation {violation:.2e}")
    assert err <= 1e-6
    assert violation <= 1e-7


@functools.cache
def maximal_c(name, dt=1e-4, duration=1.0):
    return lm.rollout(scene(name), SimulationConfig(dt=dt, duration=duration), form="maximal")


@pytest.mark.parametrize(("name", "tolerance"), [("chain4", 1e-8), ("tree", 1e-7), ("free", 1e-9), ("loop6", 1e-6)])
def test_maximal_form_agrees_with_nested_and_lagrangian(name, tolerance):
    """The maximal form's joints are soft `connect`s (solref 2 dt): measured over 1 s
    at dt 1e-4, max node error against the Lagrangian engine chain4 2.9e-9, tree
    1.8e-8, free 2.7e-11, loop6 4.8e-7 (nested: 8.9e-8); constraint violation stays
    small."""
    s, ours = scene(name), maximal_c(name).q[0]
    err = np.max(np.abs(ours - lagrangian(name).q))
    assert err <= tolerance, f"{name}: maximal vs Lagrangian {err:.2e}"
    assert np.max(np.abs(ours - mujoco_c(name).q[0])) <= tolerance
    assert max_violation(s, ours) <= tolerance


def test_maximal_form_error_falls_as_dt_squared():
    """Its error is set by the constraint time constant (2 dt) and falls ~dt^2: the tree
    over 0.2 s at dt 1e-3 against 2e-4 (measured ratio ~25, the RK4 part is far smaller)."""
    reference = lagrangian("tree", 0.2).q
    coarse = np.max(np.abs(maximal_c("tree", 1e-3, 0.2).q[0] - reference))
    fine = np.max(np.abs(maximal_c("tree", 2e-4, 0.2).q[0] - reference))
    assert 15 <= coarse / fine <= 40, (coarse, fine)


def test_mujoco_c_runs_past_the_nesting_limit_in_the_maximal_form():
    """A chain deeper than MuJoCo's parser allows runs in the maximal form, chosen by the
    engine's "auto" form; a short run keeps every link length."""
    deep = chain(mjcf.MAX_BODY_DEPTH + 1)
    engine = get_engine("mujoco")
    assert engine.form_of(deep) == "maximal" and engine.form_of(scene("chain4")) == "nested"
    config = SimulationConfig(dt=1e-4, frame_dt=1e-3, duration=3e-3)
    traj = engine.rollout(deep, config, batch_of_one(deep.initial_state))
    assert traj.metadata["engine"]["form"] == "maximal"
    assert max_violation(deep, traj.q[0]) <= 1e-9
    with pytest.raises(SimulationError, match="too deep"):
        get_engine("mujoco", form="nested").rollout(deep, config, batch_of_one(deep.initial_state))


def test_mixed_chain_is_as_accurate_as_mujoco_at_equal_dt():
    """Issue 14, item 6, on a chain of 20x mixed lengths and 1000x mixed masses
    (`chain8-mixed`) over 0.5 s against MuJoCo C at dt 1e-4 (converged: 5e-12 from
    2e-4). Measured (RK4): dt 4e-3, 2e-3, 1e-3: MuJoCo C 6.0e-7, 4.1e-8, 3.0e-9; the
    Lagrangian engine 4.7e-7, 3.2e-8, 2.1e-9 (order 3.9); without the projection
    2.8e-6, 1.8e-7, 1.1e-8. So at equal dt the Lagrangian engine is as accurate as
    MuJoCo C, fourth order, and what it needs for that is the projection after each
    step: RK4 on the acceleration-level equations alone is ~5x less accurate (its
    drift off the constraints feeds back into the motion)."""
    s, duration = get_scene("chain8-mixed"), 0.5

    def config(dt):
        return SimulationConfig(dt=dt, frame_dt=duration, duration=duration)

    def mujoco_error(dt):
        return np.max(np.abs(lm.rollout(s, config(dt)).q[0, -1] - reference))

    reference = lm.rollout(s, config(1e-4)).q[0, -1]
    ours = {dt: np.max(np.abs(simulate(s, config(dt)).q[-1] - reference)) for dt in (4e-3, 2e-3)}
    order = np.log2(ours[4e-3] / ours[2e-3])
    assert 3.6 <= order <= 4.4, ours
    for dt, error in ours.items():
        assert error <= 1.2 * mujoco_error(dt), (dt, error, mujoco_error(dt))
    unprojected = np.max(np.abs(simulate(s, config(2e-3), integration=Integration(project=False)).q[-1] - reference))
    assert unprojected >= 3 * ours[2e-3], (unprojected, ours)


@pytest.mark.parametrize("name", ["T2", "T3"])
def test_mujoco_keeps_singular_loops_closed(name):
    """T2 and T3 start with taut straight ropes between pins (a singular constraint
    Jacobian); MuJoCo keeps every link length to ~1e-6 over 1 s."""
    s = scene(name)
    assert max_violation(s, mujoco_c(name).q[0]) <= 5e-6


@pytest.mark.parametrize(("name", "tolerance"), [("T2", 5e-4), ("T3", 2e-2)])
def test_singular_loops_agree_with_lagrangian_as_far_as_the_model_allows(name, tolerance):
    """T2 and T3 start self-stressed (taut straight ropes between pins: a singular
    constraint Jacobian, lgnn/physics/constraints.py). There the inextensible model is singular: a rope
    that stretches by e sags by ~sqrt(e l), so MuJoCo's soft `connect` (e ~ 4e-7) sags
    ~2e-4 where the exact engine (e ~ 1e-9) sags ~4e-5. T2 is prestress-stable: both
    keep it at rest to that level. T3 is partly free; over 0.1 s both move ~4e-2 and
    differ by ~8e-3 (measured), the exact engine converging only at first order there."""
    s = scene(name)
    ref = lagrangian(name, 0.1)
    ours = mujoco_c(name, 0.1).q[0]
    assert max_violation(s, ref.q) <= 1e-7
    assert np.max(np.abs(ours - ref.q)) <= tolerance
    if name == "T2":
        assert np.max(np.abs(ref.q - ref.q[0])) <= 1e-4 and np.max(np.abs(ours - ours[0])) <= 5e-4


def test_drag_agrees_with_lagrangian():
    """Drag is held over each step (xfrc_applied): an O(dt) error of a small force.
    Measured 1.9e-6 over 1 s at dt 1e-4 (drag-free chain4: 3e-14)."""
    err = np.max(np.abs(mujoco_c("chain4-drag").q[0] - lagrangian("chain4-drag").q))
    assert err <= 5e-6, err


def test_rollout_batch_equals_single():
    s = scene("chain4")
    config = SimulationConfig(dt=1e-4, duration=0.05)
    states = sample_initial_states(s, jax.random.key(3), 3)
    batch = lm.rollout(s, config, State(np.asarray(states.q), np.asarray(states.qd)), threads=2)
    for k in range(3):
        one = lm.rollout(s, config, State(np.asarray(states.q)[k : k + 1], np.asarray(states.qd)[k : k + 1]))
        # Exact: MuJoCo C steps each world by the same `mj_step`, whatever the batch or threads.
        np.testing.assert_array_equal(batch.q[k], one.q[0])


def test_rollout_in_several_calls_equals_one_call(monkeypatch):
    # A long batched rollout runs in calls of a bounded buffer; the last, shorter call
    # once left its frames stale (a non-contiguous buffer, silently copied by MuJoCo):
    # frames 889-1000 of chain4's 100-IC reference were frames 1-112 again.
    s = scene("chain4")
    config = SimulationConfig(dt=1e-4, duration=0.05)
    states = sample_initial_states(s, jax.random.key(3), 3)
    states = State(np.asarray(states.q), np.asarray(states.qd))
    whole = lm.rollout(s, config, states)
    monkeypatch.setattr(lm, "ROLLOUT_BUFFER_VALUES", 3 * 10 * 9 * 7)  # 7 frames a call: 50 = 7 x 7 + 1
    # Exact: MuJoCo C's steps, each call from the full physics state the last one left.
    np.testing.assert_array_equal(lm.rollout(s, config, states).q, whole.q)


# --------------------------------------------------------------------- MJX


def chain4_states():
    states = sample_initial_states(scene("chain4"), jax.random.key(4), 3)
    return State(np.asarray(states.q), np.asarray(states.qd))


@functools.cache
def engine_chain4(name):
    """`name`'s float64 rollout of chain4 from 3 initial states over 0.25 s (MJX compiles
    once: ~35 s)."""
    return get_engine(name).rollout(scene("chain4"), CHAIN4_ROLLOUT, chain4_states())


def test_mjx_float64_agrees_with_mujoco_c():
    states, ours = chain4_states(), engine_chain4("mjx")
    reference = lm.rollout(scene("chain4"), CHAIN4_ROLLOUT, states)
    err = np.max(np.abs(ours.q - reference.q))
    assert err <= 1e-8, err
    assert np.max(np.abs(ours.qd - reference.qd)) <= 1e-7


def test_a_diverging_mjx_run_keeps_the_frames_before_it(monkeypatch):
    """An MJX run whose state turns non-finite (here from frame 3 of the second initial
    state, standing in for a blow-up) raises one `SimulationError` carrying that
    state's frames before it, as every engine does, not an error with no frames."""
    from lgnn.engines import mjx

    states, config = chain4_states(), CHAIN4_ROLLOUT
    reference = lm.rollout(scene("chain4"), config, states)
    q, qd = reference.q.copy(), reference.qd.copy()
    q[1, 3:], qd[1, 3:] = np.nan, np.inf
    monkeypatch.setattr(mjx, "runner", lambda *args, **kwargs: lambda q0, qd0: (jnp.asarray(q), jnp.asarray(qd)))
    with pytest.raises(SimulationError, match="mjx state became non-finite at t = 0.003 s") as raised:
        get_engine("mjx").rollout(scene("chain4"), config, states)
    kept = raised.value.trajectory
    np.testing.assert_array_equal(kept.q, reference.q[1, :3])
    assert raised.value.time == pytest.approx(3 * config.frame_dt)


def test_mjx_default_reproduces_a_12_link_chain_within_its_tolerance():
    """MJX with its default form (maximal past depth 8; the nested form of a 12-link
    chain compiled for over 10 minutes on a 2-core CPU) and settings (dt 1e-4) on a
    12-link chain over 1 s: MuJoCo C's loop in the same form at the same step to
    round-off, and the Lagrangian engine within the accuracy it states
    (`mjcf.form_error` at the step `mjcf.maximal_substeps` chose), which meets the
    ground-truth tolerance (on 24 links: measured 2.0e-7, stated 9.8e-7 at one step per
    dt, with twice the compile time)."""
    s, config = chain(12), SimulationConfig(dt=1e-4, frame_dt=1e-3, duration=1.0)
    engine = get_engine("mjx")
    assert engine.form_of(s) == "maximal"
    traj = engine.rollout(s, config, batch_of_one(s.initial_state))
    accuracy = engine.accuracy(s, config)
    assert traj.metadata["engine"]["form"] == "maximal" and traj.metadata["engine"]["accuracy"] == accuracy
    same_form = lm.rollout(s, lm.stepped_config(s, config, "maximal", mjcf.MAXIMAL_TOLERANCE), form="maximal").q[0]
    assert np.max(np.abs(traj.q[0] - same_form)) <= 1e-9, np.max(np.abs(traj.q[0] - same_form))
    err = np.max(np.abs(traj.q[0] - simulate(s, config).q))
    assert err <= accuracy <= mjcf.MAXIMAL_TOLERANCE, (err, accuracy)


def test_maximal_step_rule_meets_the_tolerance_where_dt_alone_did_not(monkeypatch):
    """A 40-link chain in the maximal form at dt 1e-4 is 1.4e-6 from exact joints over
    1 s (measured); MJX's engine steps it at `dt / mjcf.maximal_substeps` and then meets
    the accuracy it states, within the tolerance. MJX's stepping is MuJoCo C's to
    round-off per step (`tests/test_mjx_step.py`) and a 40-link MJX compile takes CPU
    minutes, so the engine's stepping is MuJoCo C's here. The nested form's stated
    accuracy (RK4's error) bounds its error at dt too. Reference: the nested form at dt / 4."""
    from lgnn.engines import mjx

    s, config = chain(40, seed=1), SimulationConfig(dt=1e-4, frame_dt=1e-3, duration=1.0)
    reference = lm.rollout(s, SimulationConfig(dt=2.5e-5, frame_dt=1e-3, duration=1.0)).q[0]
    alone = np.max(np.abs(lm.rollout(s, config, form="maximal").q[0] - reference))
    assert alone > mjcf.MAXIMAL_TOLERANCE and mjcf.maximal_substeps(s, config.dt) > 1
    monkeypatch.setattr(mjx, "rollout", lambda scene, stepped, states, dtype, form: lm.rollout(scene, stepped, states, form=form))
    engine = get_engine("mjx")
    traj = engine.rollout(s, config, batch_of_one(s.initial_state))
    stepped = lm.stepped_config(s, config, "maximal", mjcf.MAXIMAL_TOLERANCE)
    assert traj.metadata["engine"]["step"] == stepped.dt < config.dt and traj.t.shape == (1001,)
    err = np.max(np.abs(traj.q[0] - reference))
    assert err <= engine.accuracy(s, config) <= mjcf.MAXIMAL_TOLERANCE, (alone, err, engine.accuracy(s, config))
    nested = np.max(np.abs(lm.rollout(s, config).q[0] - reference))
    assert nested <= get_engine("mujoco").accuracy(s, config) <= mjcf.MAXIMAL_TOLERANCE


@pytest.mark.parametrize("tolerance", [1e-6, 2e-8])
def test_the_maximal_forms_step_is_measured_on_a_scene_of_unlike_links(tolerance):
    """Where the error model does not hold (chain8-mixed: links of 0.1-2 m and 0.01-10 kg),
    the maximal form's substeps are measured on the scene (`measured_maximal_substeps`):
    MuJoCo C at the step chosen meets the tolerance against a converged Lagrangian
    reference over 1 s, with the error it states within a factor 2 of the true one, and
    MJX states that error. 2e-8 takes the path that predicts the substeps from the first
    two runs and checks them."""
    from lgnn.engines.mjx import MjxEngine

    s = scene("chain8-mixed")
    assert not mjcf.error_model_holds(s)
    config = SimulationConfig(frame_dt=1e-2, duration=1.0)
    substeps, estimate = lm.measured_maximal_substeps(s, config.dt, config.frame_dt, tolerance)
    assert substeps > 1 and estimate <= tolerance
    stepped = lm.stepped_config(s, config, "maximal", tolerance)
    assert stepped.dt == pytest.approx(config.dt / substeps) and stepped.frame_dt == config.frame_dt
    reference = simulate(s, SimulationConfig(dt=1e-5, frame_dt=1e-2, duration=1.0)).q
    error = float(np.abs(lm.rollout(s, stepped, form="maximal").q[0] - reference).max())
    assert error <= tolerance and 0.5 * error <= estimate <= 2 * error, (error, estimate)
    assert MjxEngine(form="maximal", tolerance=tolerance).accuracy(s, config) == estimate


def test_error_models_hold_only_where_fitted():
    """`mjcf.form_error` is fitted on open chains of alike links under gravity over 1 s;
    elsewhere it states nothing, and the maximal form steps at the caller's dt. Its errors fall as
    h^2 (maximal) and h^4 (nested), and the step rule's count follows."""
    for name in ("tree", "loop6", "chain4-drag", "chain8-mixed", "T1"):
        assert mjcf.form_error(scene(name), "maximal", 1e-4, 1.0) is None
        assert mjcf.maximal_substeps(scene(name), 1e-4) == 1
    chain4 = scene("chain4")
    for changed in (chain4.replace(dampers=((0, -1, 0.1),)), chain4.replace(point_masses=((3, 0.5),))):
        assert mjcf.form_error(changed, "nested", 1e-4, 1.0) is None
    for s in (chain(40), get_scene("chain16-3d")):
        maximal, nested = (mjcf.form_error(s, form, 1e-4, 1.0) for form in ("maximal", "nested"))
        assert mjcf.form_error(s, "maximal", 5e-5, 1.0) == pytest.approx(maximal / 4)
        assert mjcf.form_error(s, "nested", 5e-5, 1.0) == pytest.approx(nested / 16)
        substeps = mjcf.maximal_substeps(s, 1e-4, tolerance=maximal / 10)
        assert substeps == 4 and mjcf.form_error(s, "maximal", 1e-4 / substeps, 1.0) <= maximal / 10
        # Past the fitted 1 s the chains' chaos grows the error faster: nothing is stated.
        assert mjcf.form_error(s, "maximal", 1e-4, 2.0) is None and mjcf.form_error(s, "maximal", 1e-4, 0.5) == maximal
    assert mjcf.maximal_substeps(chain(4), 1e-4) == 1
    with pytest.raises(ConfigError, match="tolerance"):
        mjcf.maximal_substeps(chain(4), 1e-4, tolerance=0.0)


# --------------------------------------------------------------------- user scene, CLI


def test_user_scene_through_all_engines(tmp_path, capsys):
    """A scene file (a hanging triangle with a tail: one loop) through the CLI; MJX says
    it is compiling, and in which form, before it does."""
    nodes = [[0, 0], [0.6, -0.8], [-0.6, -0.8], [0.4, -1.5]]
    links = [{"nodes": [0, 1], "mass": 1.0, "inertia": 0.08}, {"nodes": [1, 2], "mass": 0.5, "inertia": 0.1},
             {"nodes": [2, 0], "mass": 1.0, "inertia": 0.08}, {"nodes": [1, 3], "mass": 0.3, "inertia": 0.02}]
    path = tmp_path / "mine.json"
    path.write_text(json.dumps({"name": "mine", "nodes": nodes, "pinned": [0], "links": links}))
    out = {}
    for engine in ("lagrangian", "mujoco", "mjx"):
        npz = tmp_path / f"{engine}.npz"
        quiet = [] if engine == "mjx" else ["--quiet"]
        capsys.readouterr()
        assert main(["simulate", str(path), "--engine", engine, "--duration", "0.2", "--out", str(npz), *quiet]) == 0
        if engine == "mjx":
            assert "MJX: compiling mine (nested form" in capsys.readouterr().err
        out[engine] = Trajectory.load(npz)
        assert out[engine].q.shape == (201, 4, 2) and out[engine].energy.shape == (201,)
    assert np.max(np.abs(out["mujoco"].q - out["lagrangian"].q)) <= 1e-6
    # MJX steps with MuJoCo C's arithmetic (`lgnn.engines.mjx.make_step`: mjx.step's
    # connect rows lack C's Jdot v term and were 1e-6 off here): the same loop to round-off.
    assert np.max(np.abs(out["mjx"].q - out["mujoco"].q)) <= 1e-12
    assert np.max(np.abs(out["mjx"].q - out["lagrangian"].q)) <= 1e-6
    assert np.max(np.abs(out["mujoco"].energy - out["lagrangian"].energy)) <= 1e-5


def test_cli_renders_a_scene_file_in_either_form(tmp_path, capsys):
    """`lgnn mjcf SCENE.json --form F --out F.xml` writes the file MuJoCo loads; a bad
    form or an engine without forms is one line."""
    path = tmp_path / "loop.json"
    path.write_text(json.dumps(scene_to_dict(scene("loop6"))))
    for form in mjcf.FORMS:
        out = tmp_path / f"{form}.xml"
        assert main(["mjcf", str(path), "--form", form, "--out", str(out)]) == 0
        assert f"--mjcf={out}" in capsys.readouterr().err
        assert out.read_text() == mjcf.render(scene("loop6"), form=form)
        model = mujoco.MjModel.from_xml_path(str(out))
        assert model.nbody - 1 == 6 and model.neq == (7 if form == "maximal" else 1)  # maximal: 5 inner nodes + 2 pins
    assert main(["mjcf", "--out", str(tmp_path / "x.xml")]) == 2 and "needs a SCENE" in capsys.readouterr().err
    code = main(["simulate", "chain4", "--form", "maximal", "--out", str(tmp_path / "x.npz"), "--quiet"])
    assert code == 2 and "no MJCF form" in capsys.readouterr().err


@pytest.mark.parametrize("option", [["--integrator", "verlet"], ["--no-project"]])
def test_cli_refuses_an_integration_for_a_mujoco_engine_in_one_line(tmp_path, capsys, option):
    code = main(["simulate", "chain4", "--engine", "mujoco", *option, "--out", str(tmp_path / "x.npz")])
    err = capsys.readouterr().err
    assert code == 2 and "takes no integrator or projection" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "x.npz").exists()


# --------------------------------------------------------------------- the engine interface


# MuJoCo Warp is float32 only and an optional extra: tests/test_mjwarp.py checks it.
@pytest.mark.parametrize("name", [name for name in ENGINES if name != "mjwarp"])
def test_every_engine_agrees_with_the_lagrangian_engine(name):
    """One interface: every registered engine's batched rollout of chain4 (float64, RK4,
    dt 1e-4, 0.25 s) has the same shape and the same motion and energy as the Lagrangian
    engine.s (measured: MuJoCo C within 4e-14 in positions, 5e-13 in energy)."""
    ours, reference = engine_chain4(name), engine_chain4("lagrangian")
    assert get_engine(name).name == name
    assert ours.q.shape == ours.qd.shape == (3, 251, 5, 2) and ours.energy.shape == (3, 251) and ours.t.shape == (251,)
    np.testing.assert_array_equal(ours.t, reference.t)  # both `np.arange(frames) * frame_dt`
    assert np.max(np.abs(ours.q - reference.q)) <= 1e-10
    assert np.max(np.abs(ours.energy - reference.energy)) <= 1e-10
    member = ours.member(1)
    np.testing.assert_array_equal(member.q, ours.q[1])
    assert member.energy.shape == (251,)


def test_mujoco_engine_is_the_c_rollout_with_energies():
    """The engine adds energies and checks to `mujoco.rollout`, and changes no number."""
    s, config = scene("T1"), SimulationConfig(dt=1e-4, duration=0.05)
    states = batch_of_one(s.initial_state)
    traj = get_engine("mujoco").rollout(s, config, states)
    nodes = lm.rollout(s, config, states)
    # Exact: the same MuJoCo C run twice in this process (no compiled program of ours).
    np.testing.assert_array_equal(traj.q, nodes.q)
    np.testing.assert_array_equal(traj.qd, nodes.qd)
    assert traj.metadata["engine"]["name"] == "mujoco" and traj.metadata["engine"]["dtype"] == "float64"


def test_get_engine_unknown_name_is_one_line():
    with pytest.raises(ConfigError) as info:
        get_engine("bullet")
    message = str(info.value)
    assert "\n" not in message and "'bullet'" in message and all(name in message for name in ENGINES)
    with pytest.raises(ConfigError, match="float16"):
        get_engine("mjx", dtype="float16")


def test_importing_the_engines_does_not_import_mujoco():
    script = "import sys, lgnn.engines; print(sorted(m for m in ('mujoco', 'mujoco.mjx') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_nesting_limit_is_measured_and_refused_in_one_line(monkeypatch):
    """MuJoCo's XML parser takes `MAX_BODY_DEPTH` nested bodies and not one more; deeper
    trees are refused before rendering (a `SceneError`), and the MuJoCo engine reports
    them as a run it cannot make (a `SimulationError`, a row of the stability report)."""
    mujoco.MjModel.from_xml_string(mjcf.scene_to_mjcf(chain(mjcf.MAX_BODY_DEPTH)))
    deep = chain(mjcf.MAX_BODY_DEPTH + 1)
    with monkeypatch.context() as patch:
        patch.setattr(mjcf, "MAX_BODY_DEPTH", 10**6)
        with pytest.raises(ValueError, match="XML parse error"):
            mujoco.MjModel.from_xml_string(mjcf.scene_to_mjcf(deep))
    with pytest.raises(SceneError, match="too deep"):
        mjcf.scene_to_mjcf(deep)
    with pytest.raises(SimulationError, match="too deep") as info:
        lm.compile_scene(deep)
    assert "\n" not in str(info.value)


def test_only_the_mujoco_engines_import_mujoco():
    """MuJoCo stays behind the engine interface: no other module of lgnn imports it
    (deferred imports included)."""
    import ast
    from pathlib import Path

    package = Path(__file__).resolve().parents[1] / "lgnn"
    importers = set()
    for path in package.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""] if isinstance(node, ast.ImportFrom) and node.level == 0 else []
            if any(name == "mujoco" or name.startswith("mujoco.") for name in names):
                importers.add(path.relative_to(package).as_posix())
    assert importers == {"engines/mujoco.py", "engines/mjx.py", "engines/mjwarp.py", "engines/mjcf_import.py"}
