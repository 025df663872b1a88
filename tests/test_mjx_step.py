"""lgnn's MJX step (`lgnn.engines.mjx.make_step`) against MuJoCo C's `mj_step`, step by
step, on tiny models over 20 steps: a ball-joint chain (C 4.0's RKMK-corrected RK4)
and a maximal-form loop (C's `Jdot v` in connect rows); MJX's own `mjx.step` fails
both bounds (numbers in each test, measured with `mjx.step` swapped in). Each compiles in ~20 s on
a 2-core CPU; `tools/mjx_vs_c.py` prints the same comparison for any MJCF."""

from __future__ import annotations

import jax
import mujoco
import numpy as np
import pytest

from lgnn.engines.mjx import _mjx, make_step
from lgnn.engines.mujoco import compile_scene, state_to_qpos_qvel
from lgnn.errors import ConfigError
from lgnn.scene import spatial_chain
from lgnn.scene.catalogue import double_pinned_chain


# (20 steps: XLA's optimisations would cost more to compile than they save.)

STEPS = 20


def gap_after_steps(scene, form, qvel_noise=0.0):
    """Max |qpos| and |qvel| gap of `make_step` from `mj_step` after `STEPS` steps
    from the scene's initial state (plus `qvel_noise` x N(0, 1): velocities the
    connects must absorb, which exercises their reference acceleration)."""
    mjx = _mjx()
    compiled = compile_scene(scene, 1e-4, form)
    model, state = compiled.model, scene.initial_state
    qpos, qvel = (np.asarray(x) for x in state_to_qpos_qvel(compiled, jax.numpy.asarray(state.q), jax.numpy.asarray(state.qd)))
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:] = qpos, qvel + qvel_noise * np.random.default_rng(0).normal(size=model.nv)
    mx = mjx.put_model(model)
    d = mjx.make_data(mx).replace(qpos=jax.numpy.asarray(data.qpos), qvel=jax.numpy.asarray(data.qvel))
    step = jax.jit(make_step(model))
    for _ in range(STEPS):
        mujoco.mj_step(model, data)
        d = step(mx, d)
    return np.abs(np.asarray(d.qpos) - data.qpos).max(), np.abs(np.asarray(d.qvel) - data.qvel).max()


def test_ball_joints_step_as_in_mujoco_c():
    """Measured: 4e-16 in qpos, 5e-15 in qvel (mjx.step: 1.2e-11, 6e-13)."""
    dq, dv = gap_after_steps(spatial_chain(2), "nested")
    assert dq <= 1e-14 and dv <= 1e-13, (dq, dv)


def test_maximal_loop_connects_step_as_in_mujoco_c():
    """Measured: 9e-16 in qpos, 4e-13 in qvel (mjx.step: 1.5e-9, 2.6e-7)."""
    dq, dv = gap_after_steps(double_pinned_chain(), "maximal", qvel_noise=0.3)
    assert dq <= 1e-14 and dv <= 1e-11, (dq, dv)


def test_equalities_other_than_connect_and_weld_are_refused():
    model = mujoco.MjModel.from_xml_string(
        '<mujoco><option integrator="RK4"/><worldbody><body><joint name="a"/><geom size="0.1"/></body>'
        '<body><joint name="b"/><geom size="0.1"/></body></worldbody><equality><joint joint1="a" joint2="b"/></equality></mujoco>')
    with pytest.raises(ConfigError, match="JOINT"):
        make_step(model)
