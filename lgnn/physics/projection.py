"""Projection of a state back onto the constraint manifold (after each integration step).

Contract: `projection_fn(scene)` returns a pure `project(q, qd) -> (q, qd)` of node
arrays (N, D): positions satisfy every kept link length and sit exactly at the pins,
velocities keep every link length stationary and are zero at the pins. Its static data
comes from `prepare(scene)`.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from lgnn.integrate import compensated_add
from lgnn.physics.constraints import add_rows, take_rows
from lgnn.physics.energies import Array
from lgnn.physics.solvers import refine
from lgnn.physics.system import prepare
from lgnn.runtime import full_precision_matmuls
from lgnn.scene import Scene

# Levenberg-Marquardt shift of the projection's Gauss-Newton steps (the Gram matrix of
# unit Jacobian rows has eigenvalues of order 1): bounds the step at singular
# configurations, where an unshifted step along a self-stress diverges.
PROJECTION_SHIFT = 1e-6
VELOCITY_PROJECTION_PASSES = 5
# Scenes regular at their initial configuration (chains, T1) use a shift far below
# the smallest Gram eigenvalue of any built-in scene (~2.5e-6 for a 1000-link chain),
# which only keeps the factorisation defined should the motion pass a singular
# configuration; two passes then reach round-off.
REGULAR_PROJECTION_SHIFT = 1e-12
REGULAR_VELOCITY_PROJECTION_PASSES = 2
# Gauss-Newton steps on the positions. Regular scenes converge quadratically, so two
# steps take the drift of one integration step (round-off for the exact accelerations;
# about dt^2 |a| / 2 for a learned model's) to round-off: measured over 1 s at dt 1e-4,
# trajectories with 2 and 4 steps differ by 6e-14 m (chain12), 2e-12 m (chain100) and
# 3e-7 m on T1, below T1's own sensitivity to a 1e-15 change of its initial velocity
# (5.8e-7 m); a chain12 step costs 16.4 us with 4 and 13.7 us with 2 (2 CPU cores,
# medians of 5). Self-stressed scenes, whose shifted steps converge more slowly, keep 4.
# A larger drift (a state from elsewhere: 1e-4 m on T1) is left at ~5e-12 m by two
# steps and at round-off by the next projection; callers that need round-off at once
# (sampling) ask for more.
PROJECTION_ITERATIONS = 4
REGULAR_PROJECTION_ITERATIONS = 2
# What "round-off" means to `adaptive` projection: a link residual (m) or velocity
# defect (m/s) at most this many ulps of the largest position or speed.
ROUND_OFF_ULPS = 8


def projection_fn(scene: Scene, iterations: int | None = None, *, adaptive: bool = False) -> Callable[..., tuple[Array, ...]]:
    """Project `(q, qd)` back onto the constraint manifold: `project(q, qd) -> (q, qd)`,
    or, for positions carried with their rounding remainders `q_low` (the integrators,
    `integrate.compensated_add`), `project(q, qd, q_low) -> (q, qd, q_low)`.

    Positions: `iterations` Gauss-Newton steps `q <- q - A^T (A A^T)^-1 Phi(q)` (the
    minimum-norm correction; quadratic convergence, so a fixed few steps reach round-off
    from the small drift of one integration step, and larger drifts still converge;
    None: `REGULAR_PROJECTION_ITERATIONS` for a scene regular at its initial
    configuration, `PROJECTION_ITERATIONS` for a self-stressed one). Velocities: the
    orthogonal projection onto `A v = 0` at the corrected positions (`passes` of it).
    `adaptive` (a regular scene's two steps and passes only): the second Gauss-Newton
    step and the second velocity pass are taken only where the first leaves more than
    round-off (`ROUND_OFF_ULPS`), a branch (`lax.cond`). The exact dynamics' drift over
    one small step is round-off, so one trajectory of the ground truth on a CPU (where
    a branch is one: `lgnn.engines.rollouts.adaptive_projection`) mostly skips them; a
    large step, or a learned model's drift, takes both as before. Under `vmap` both
    branches run: no saving there. All products with `A` use its per-link blocks
    (`solvers.LinkGram` solves with `A A^T`), so a chain projects in time linear in its
    length; `adaptive` (one system on a CPU) also solves their tridiagonal parts by
    LAPACK's one call instead of two loops. `A A^T` is SPD at regular configurations; a
    Levenberg-Marquardt shift keeps its factorisation defined at singular ones
    (`REGULAR_PROJECTION_SHIFT` for scenes regular at their initial configuration,
    `PROJECTION_SHIFT` for self-stressed ones, where an unshifted step along a
    self-stress diverges). Pins are exact by construction.

    With `q_low` the link vectors include it and the corrections are added to it with
    compensation (without it, plainly: float64 rollouts carry none), so the projection
    works at the accuracy of the links' own lengths: from positions rounded to their
    scale (float32 at 12 m: ulp 1e-6) it would move the structure by that much each step
    (chain16, 100 RK4 steps in float32: 3.3e-6 from float64 with compensated RK4 sums
    alone, 8.3e-7 with this).
    """
    system = prepare(scene)
    constraints, gram = system.constraints, system.gram
    i, j = constraints.edge_index[constraints.links].T
    free_nodes = constraints.free_mask.astype(np.float64)
    singular = constraints.self_stresses > 0
    shift = PROJECTION_SHIFT if singular else REGULAR_PROJECTION_SHIFT
    # The shift leaves a fraction ~shift / sigma^2 of `A v` per pass; repeated passes
    # with the same factor remove it geometrically (iterative refinement).
    passes = VELOCITY_PROJECTION_PASSES if singular else REGULAR_VELOCITY_PROJECTION_PASSES
    if iterations is None:
        iterations = PROJECTION_ITERATIONS if singular else REGULAR_PROJECTION_ITERATIONS
    adaptive_here = adaptive and not singular and iterations == REGULAR_PROJECTION_ITERATIONS

    def transpose_times(u, lam):
        force = u * lam[:, None]
        return add_rows(add_rows(jnp.zeros(constraints.shape, u.dtype), i, force), j, -force) * jnp.asarray(free_nodes, u.dtype)

    def times(u, v):
        return jnp.sum(u * (take_rows(v, i) - take_rows(v, j)), -1)

    def project(q, qd, q_low=None):
        low = None if q_low is None else q_low * jnp.asarray(free_nodes, q.dtype)
        if constraints.n_rows == 0:
            q, qd = constraints.embed(constraints.restrict(q)), constraints.embed_velocity(constraints.restrict(qd))
            return (q, qd) if q_low is None else (q, qd, low)
        # Pinned nodes are put exactly at their pins, at rest.
        q = jnp.where(constraints.free_mask, q, jnp.asarray(constraints.pin_positions, q.dtype))
        qd = qd * jnp.asarray(free_nodes, qd.dtype)

        def gauss_newton(q, low):
            u = constraints.link_directions(q, low)
            correction = -transpose_times(u, gram.solve_fn(u, shift, adaptive)(constraints.link_residual(q, low)))
            return (q + correction, low) if low is None else compensated_add(q, low, correction)

        def round_off(residual, values):
            return jnp.max(jnp.abs(residual)) <= ROUND_OFF_ULPS * jnp.finfo(values.dtype).eps * jnp.max(jnp.abs(values))

        if adaptive_here:
            q, low = gauss_newton(q, low)
            q, low = jax.lax.cond(round_off(constraints.link_residual(q, low), q), lambda q, low: (q, low), gauss_newton, q, low)
        else:
            for _ in range(iterations):
                q, low = gauss_newton(q, low)
        u = constraints.link_directions(q, low)
        solve = gram.solve_fn(u, shift, adaptive)

        # The velocity's defect is `A qd`; its correction the minimum-norm `-A^T G^-1 A qd`.
        def velocity_pass(v):
            return refine(lambda defect: -transpose_times(u, solve(defect)), lambda v: times(u, v), v, 1)

        if adaptive_here:
            qd = velocity_pass(qd)
            qd = jax.lax.cond(round_off(times(u, qd), qd), lambda v: v, velocity_pass, qd)
        else:
            for _ in range(passes):
                qd = velocity_pass(qd)
        return (q, qd) if q_low is None else (q, qd, low)

    # Full-precision products: float32 on a GPU is otherwise TF32's (`lgnn.runtime`).
    return full_precision_matmuls(project)
