"""MuJoCo Warp as an engine (`lgnn.engines.mjwarp`): batched, float32, against MuJoCo C.

MuJoCo Warp is an optional extra that CI does not install: the tests that run it are
skipped when `mujoco_warp` cannot be imported; the one-line error for its absence is
tested everywhere. On Warp's CPU backend a chain4 step of 3 worlds takes ~0.1 s (kernel
launches), and a first run compiles its kernels for minutes (cached on disk by Warp),
so the runs are short.
"""

import functools
import sys

import jax
import numpy as np
import pytest

from lgnn.cli import main
from lgnn.engines import get_engine, mjwarp
from lgnn.engines import mujoco as lm
from lgnn.engines.base import SimulationConfig
from lgnn.errors import ConfigError
from lgnn.scene import State, get_scene, sample_initial_states

needs_mjwarp = pytest.mark.skipif(not mjwarp.available(), reason="MuJoCo Warp not installed (pip install 'lgnn[mjwarp]')")
# 20 RK4 steps of 1e-3 s, a frame every 10.
SHORT = SimulationConfig(dt=1e-3, frame_dt=1e-2, duration=2e-2)


@functools.cache
def chain4_states():
    states = sample_initial_states(get_scene("chain4"), jax.random.key(4), 3)
    return State(np.asarray(states.q), np.asarray(states.qd))


def test_missing_mjwarp_is_one_line(monkeypatch, tmp_path, capsys):
    """Without the extra, the engine is a one-line error naming the fix, also from the CLI."""
    monkeypatch.setitem(sys.modules, "mujoco_warp", None)  # makes `import mujoco_warp` fail
    mjwarp.runner.cache_clear()
    with pytest.raises(ConfigError, match=r"not installed.*lgnn\[mjwarp\]") as info:
        get_engine("mjwarp").rollout(get_scene("chain4"), SHORT, chain4_states())
    assert "\n" not in str(info.value) and not mjwarp.available()
    code = main(["simulate", "chain4", "--engine", "mjwarp", "--duration", "0.01", "--out", str(tmp_path / "x.npz"), "--quiet"])
    assert code == 2 and "not installed" in capsys.readouterr().err
    assert not (tmp_path / "x.npz").exists()


def test_drag_is_refused_in_one_line():
    if not mjwarp.available():
        pytest.skip("MuJoCo Warp not installed")
    with pytest.raises(ConfigError, match="drag"):
        mjwarp.runner(get_scene("chain4-drag"), SHORT, 1)


@needs_mjwarp
def test_batched_chain4_agrees_with_mujoco_c():
    """Three worlds of chain4 (nested form) in one MuJoCo Warp data against MuJoCo C
    float64 from the same states: float32 round-off only (measured 7.6e-7 in positions
    after 100 steps). The node map (Warp's site positions and `cvel` velocities)
    reproduces the initial states, and the engine returns the checked `Trajectory`."""
    scene, states = get_scene("chain4"), chain4_states()
    traj = get_engine("mjwarp").rollout(scene, SHORT, states)
    reference = lm.rollout(scene, SHORT, states)
    assert traj.q.shape == traj.qd.shape == (3, 3, 5, 2) and traj.energy.shape == (3, 3)
    assert traj.metadata["engine"]["dtype"] == "float32" and traj.metadata["engine"]["form"] == "nested"
    np.testing.assert_allclose(traj.q[:, 0], states.q, atol=1e-6)
    np.testing.assert_allclose(traj.qd[:, 0], states.qd, atol=1e-5)
    assert np.max(np.abs(traj.q - reference.q)) <= 5e-6
    assert np.max(np.abs(traj.qd - reference.qd)) <= 5e-5
    # A world's motion is its own: the three differ, as their initial states do.
    assert np.min(np.abs(traj.q[0, -1] - traj.q[1, -1]).max()) > 1e-3


@needs_mjwarp
@pytest.mark.parametrize(("name", "tolerance"), [("chain4-3d", 1e-5), ("chain16-3d", 1e-4)])
def test_spatial_chains_agree_with_mujoco_c(name, tolerance):
    """Ball joints in float32: two worlds of a 3D chain (nested form) against MuJoCo C
    from the same states, as on planar chains. The joint-space mass matrix must be
    well conditioned for float32 (`mjcf.AXIAL_INERTIA_FRACTION`): with rods of 1e-3
    axial inertia chain16-3d's was 2.2e8 and MuJoCo Warp ended 14 m away (NaN
    velocities) after these 20 steps. Measured now: 1.6e-6 and 7.7e-6 in positions."""
    scene = get_scene(name)
    states = sample_initial_states(scene, jax.random.key(16), 2)
    states = State(np.asarray(states.q), np.asarray(states.qd))
    nodes = mjwarp.rollout(scene, SHORT, states)
    reference = lm.rollout(scene, SHORT, states)
    assert np.max(np.abs(nodes.q - reference.q)) <= tolerance
    assert np.max(np.abs(nodes.qd - reference.qd)) <= 10 * tolerance


@needs_mjwarp
def test_timed_rollout_is_the_rollout():
    """The timed run steps the same worlds as `rollout` (same runner, reset between
    runs): identical positions, a positive run time."""
    scene, states = get_scene("chain4"), chain4_states()
    engine = get_engine("mjwarp")
    compile_s, run_s, q = engine.timed_rollout(scene, SHORT, states)
    nodes = mjwarp.rollout(scene, SHORT, states)
    assert compile_s >= 0 and run_s > 0
    np.testing.assert_array_equal(q, nodes.q)  # exact: the one cached runner (same kernels) rerun on the same worlds


def test_unknown_form_is_one_line():
    if not mjwarp.available():
        pytest.skip("MuJoCo Warp not installed")
    with pytest.raises(ConfigError, match="form"):
        mjwarp.runner(get_scene("chain4"), SHORT, 1, "spaghetti")


def test_auto_form_is_mjx_choice_without_running_warp(tmp_path, capsys):
    """`--engine mjwarp --form auto` resolves as MJX's "auto" does (nested to
    `mjx.NESTED_MAX_DEPTH`, maximal beyond) and reaches MuJoCo Warp (here, where it is
    not installed, its one-line absence, not an unknown form); the maximal form steps
    at the MJX rule's step."""
    from lgnn.engines import mjcf, mjx

    engine = get_engine("mjwarp", form="auto")
    deep, config = get_scene("chain16"), SimulationConfig(dt=1e-3, frame_dt=1e-2, duration=1.0)
    assert engine.form_of(get_scene("chain4")) == "nested" == mjx.best_form(get_scene("chain4"))
    assert engine.form_of(deep) == "maximal" == mjx.best_form(deep)
    form, stepped = engine.stepped(deep, config)
    assert stepped.dt == config.dt / mjcf.maximal_substeps(deep, config.dt) < config.dt
    assert stepped.frame_dt == config.frame_dt and stepped.duration == config.duration
    if not mjwarp.available():
        code = main(["simulate", "chain16", "--engine", "mjwarp", "--form", "auto", "--duration", "0.01",
                     "--out", str(tmp_path / "x.npz"), "--quiet"])
        assert code == 2 and "not installed" in capsys.readouterr().err


@needs_mjwarp
def test_maximal_form_sizes_its_constraint_rows():
    """A loop in the maximal form has 3 rows per `connect` equality (here more than the
    default 64 MuJoCo Warp allocates would hold for T1): the engine sizes them from the
    model, and one world agrees with MuJoCo C on the same MJCF to float32 round-off."""
    scene = get_scene("double-pinned")
    states = State(np.asarray(scene.nodes)[None], np.asarray(scene.velocities)[None])
    traj = get_engine("mjwarp", form="maximal").rollout(scene, SHORT, states)
    reference = lm.rollout(scene, SHORT, states, form="maximal")
    assert traj.metadata["engine"]["form"] == "maximal" and np.all(np.isfinite(traj.q))
    assert np.max(np.abs(traj.q - reference.q)) <= 5e-5
