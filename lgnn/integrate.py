"""Time integrators and rollouts; they know nothing about scenes or models.

An integrator is built from an acceleration function `accel(q, qd) -> qdd` and a step
`dt`: `init_fn(state) -> carry`, `step_fn(carry) -> carry`, with `carry.state` the
current `State`. Both optionally project `(q, qd)` back onto the constraint manifold
after every step (`project(q, qd, q_low) -> (q, qd, q_low)`, see
`physics.projection_fn`).

Positions are summed with compensation (`compensated_add`): the carry holds, beside
`state.q`, the part `q_low` of each position that its rounding lost, and feeds it back
into the next step. In float32 the rounding of `q + dt * ...` to the positions' own
scale (ulp 1e-6 at 12 m) is otherwise the largest error of a step: chain16, 100 RK4
steps of 1e-3 against float64, 8.1e-6 of the 1.05e-5 total came from rounding the
positions alone (everything else in float64), 1.2e-8 from rounding the velocities
(whose increments are not small against them, so they get no compensation).
In float64 the same rounding is ~1e-16 of the positions, below everything else a step
errs by, so float64 positions are summed plainly and carry no `q_low` (`compensates`):
the compensation cost float64 rollouts ~6% of a step (chain12 on a CPU) for nothing.

`rollout` saves a frame every `steps_per_frame` steps with nested `lax.scan`s, so the
integration step `dt` is decoupled from the saved frame interval.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from lgnn.scene import State

Projection = Callable[[jax.Array, jax.Array, jax.Array], tuple[jax.Array, jax.Array, jax.Array]]


def compensated_add(q: jax.Array, q_low: jax.Array, increment: jax.Array) -> tuple[jax.Array, jax.Array]:
    """`(q + q_low) + increment` as a rounded sum and its exact remainder (Knuth's
    two-sum of `q` and `q_low + increment`): the remainder is what the rounding to `q`'s
    scale lost, exact in any dtype, so adding it into the next increment keeps the
    positions' error at round-off of the increments instead of the positions."""
    addend = q_low + increment
    total = q + addend
    addend_part = total - q
    return total, (q - (total - addend_part)) + (addend - addend_part)


def compensates(dtype) -> bool:
    """Whether positions of `dtype` are summed with compensation (module docstring):
    those narrower than float64."""
    return jnp.finfo(dtype).bits < 64


class Carry(NamedTuple):
    state: State
    # Acceleration at `state`, reused by velocity Verlet (one evaluation per step);
    # None for integrators that do not carry it.
    qdd: jax.Array | None = None
    # What rounding lost of `state.q` (module docstring): the positions are
    # `state.q + q_low`, |q_low| at most half an ulp of `state.q`; None where positions
    # are summed plainly (float64, `compensates`).
    q_low: jax.Array | None = None


class Integrator(NamedTuple):
    init_fn: Callable[[State], Carry]
    step_fn: Callable[[Carry], Carry]
    evaluations_per_step: int


def _next_carry(project: Projection | None, q, q_low, increment, qd, qdd=None) -> Carry:
    """The carry at positions `q + q_low + increment` (summed with compensation; plainly
    where `q_low` is None) and velocities `qd`, projected when `project` is given."""
    if q_low is None:
        q = q + increment
        if project is not None:
            q, qd = project(q, qd)
        return Carry(State(q, qd), qdd, None)
    q, q_low = compensated_add(q, q_low, increment)
    if project is not None:
        q, qd, q_low = project(q, qd, q_low)
    return Carry(State(q, qd), qdd, q_low)


def _initial_carry(state: State, qdd=None) -> Carry:
    q, qd = state
    return Carry(State(q, qd), qdd, jnp.zeros_like(q) if compensates(q.dtype) else None)


# RK4's stages as rows (stage offset c, weight w): stage k evaluates the acceleration
# at `q + c dt kv`, `qd + c dt ka` of the stage before it, and the step adds
# `dt / 6 * sum(w k)`. The offset of the first stage is 0, so it is the state itself.
RK4_OFFSETS = (0.0, 0.5, 0.5, 1.0)
RK4_WEIGHTS = (1.0, 2.0, 2.0, 1.0)


def rk4(accel, dt: float, project: Projection | None = None) -> Integrator:
    """Classical 4th-order Runge-Kutta on the first-order system (q, qd).

    The four stages are one loop over `RK4_OFFSETS` and `RK4_WEIGHTS`, so a
    compiled step holds one copy of `accel`, not four. A learned model's acceleration
    (its network, derivatives and constrained solve) is most of a rollout program, and
    compiling it four times was most of the evaluate stage's compile time: on a 2-core
    CPU its programs compiled in 0.50-0.66 of the time for the Lagrangian models and
    stepped within 6 % (results/gpu/compile/README.md). Where a step costs
    microseconds the loop costs a fifth of it (one 12-link chain's exact step on a CPU,
    11.4 to 14.1 us, results/cpu_vs_mujoco.md): there the stages are written out
    (`written_out_rk4`, `integrator(..., cheap_steps=True)`). Either way the sums run in
    the written-out formula's order, `k1 + 2 k2 + 2 k3 + k4`: the same step, to the
    round-off by which two compiled programs may fuse it differently (2 ulps,
    tests/test_integrate.py)."""

    def step(carry: Carry) -> Carry:
        (q, qd), _, q_low = carry
        # NumPy constants in the state's dtype: no device array is made where the
        # integrator is built (a program for the host's CPU may be built on a GPU
        # machine), and a float32 program holds no float64 value.
        tableau = tuple(np.asarray(row, qd.dtype) for row in (RK4_OFFSETS, RK4_WEIGHTS))

        def stage(sums, row):
            sum_v, sum_a, kv, ka = sums
            offset, weight = row
            v = qd + offset * dt * ka
            a = accel(q + offset * dt * kv, v)
            return (sum_v + weight * v, sum_a + weight * a, v, a), None

        zero = jnp.zeros_like(qd)
        (sum_v, sum_a, _, _), _ = jax.lax.scan(stage, (zero, zero, zero, zero), tableau)
        return _next_carry(project, q, q_low, dt / 6 * sum_v, qd + dt / 6 * sum_a)

    return Integrator(_initial_carry, step, 4)


def written_out_rk4(accel, dt: float, project: Projection | None = None) -> Integrator:
    """`rk4` with its stages written out (four copies of `accel` in a compiled step)."""

    def step(carry: Carry) -> Carry:
        (q, qd), _, q_low = carry
        k1v, k1a = qd, accel(q, qd)
        k2v = qd + 0.5 * dt * k1a
        k2a = accel(q + 0.5 * dt * k1v, k2v)
        k3v = qd + 0.5 * dt * k2a
        k3a = accel(q + 0.5 * dt * k2v, k3v)
        k4v = qd + dt * k3a
        k4a = accel(q + dt * k3v, k4v)
        qd_next = qd + dt / 6 * (k1a + 2 * k2a + 2 * k3a + k4a)
        return _next_carry(project, q, q_low, dt / 6 * (k1v + 2 * k2v + 2 * k3v + k4v), qd_next)

    return Integrator(_initial_carry, step, 4)


def velocity_verlet(accel, dt: float, project: Projection | None = None) -> Integrator:
    """Velocity Verlet (the paper's integrator), second order, one evaluation per step.

    The acceleration depends on velocity (constraint forces, drag), so the new
    acceleration is evaluated at the new positions and the predicted velocity
    `qd + dt a`, which keeps the scheme second order (a half-step velocity would make
    it first order).
    """

    def init(state: State) -> Carry:
        return _initial_carry(state, accel(*state))

    def step(carry: Carry) -> Carry:
        (q, qd), a, q_low = carry
        increment = dt * qd + 0.5 * dt**2 * a
        a_next = accel(q + increment, qd + dt * a)
        qd_next = qd + 0.5 * dt * (a + a_next)
        return _next_carry(project, q, q_low, increment, qd_next, a_next)

    return Integrator(init, step, 1)


INTEGRATORS = {"rk4": rk4, "verlet": velocity_verlet}
# The form of an integrator for steps that cost microseconds, where its stage loop
# would cost a fifth of a step (`rk4`); an integrator without one steps as it is.
CHEAP_STEP_FORMS = {"rk4": written_out_rk4}


def integrator(name: str, accel, dt: float, project: Projection | None = None, *, cheap_steps: bool = False) -> Integrator:
    """The integrator `name` of `INTEGRATORS` stepping `accel` by `dt`, projecting with
    `project`; where `cheap_steps`, its `CHEAP_STEP_FORMS` form if it has one."""
    factory = CHEAP_STEP_FORMS.get(name) if cheap_steps else None
    return (factory or INTEGRATORS[name])(accel, dt, project)


def advance(integrator: Integrator, carry: Carry, n_frames: int, steps_per_frame: int):
    """Advance `n_frames` frames; returns the final carry and the frames' states
    (each (n_frames, ...)), excluding the starting state."""

    def frame(carry, _):
        carry = jax.lax.fori_loop(0, steps_per_frame, lambda _, c: integrator.step_fn(c), carry)
        return carry, carry.state

    return jax.lax.scan(frame, carry, None, length=n_frames)


def rollout(integrator: Integrator, state: State, n_frames: int, steps_per_frame: int) -> State:
    """Trajectory of `n_frames + 1` frames (frame 0 is `state`): `State` of (F+1, N, D)."""
    _, frames = advance(integrator, integrator.init_fn(state), n_frames, steps_per_frame)
    return jax.tree.map(lambda x0, xs: jnp.concatenate([x0[None], xs]), State(*state), frames)
