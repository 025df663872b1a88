"""Projection of a state back onto the constraint manifold (after each integration step).

Contract: `projection_fn(scene)` returns a pure `project(q, qd) -> (q, qd)` of node
arrays (N, D): positions satisfy every kept link length and sit exactly at the pins,
velocities keep every link length stationary and are zero at the pins. Its static data
comes from `prepare(scene)`.
"""

from __future__ import annotations

from typing import Callable

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


def projection_fn(scene: Scene, iterations: int = 4) -> Callable[..., tuple[Array, ...]]:
    """Project `(q, qd)` back onto the constraint manifold: `project(q, qd) -> (q, qd)`,
    or, for positions carried with their rounding remainders `q_low` (the integrators,
    `integrate.compensated_add`), `project(q, qd, q_low) -> (q, qd, q_low)`.

    Positions: `iterations` Gauss-Newton steps `q <- q - A^T (A A^T)^-1 Phi(q)` (the
    minimum-norm correction; quadratic convergence, so a fixed few steps reach
    round-off from the small drift of one integration step, and larger drifts still
    converge). Velocities: the orthogonal projection onto `A v = 0` at the corrected
    positions. All products with `A` use its per-link blocks (`solvers.LinkGram` solves
    with `A A^T`), so a chain projects in time linear in its length. `A A^T` is SPD at
    regular configurations; a Levenberg-Marquardt shift keeps its factorisation defined
    at singular ones (`REGULAR_PROJECTION_SHIFT` for scenes regular at their initial
    configuration, `PROJECTION_SHIFT` for self-stressed ones, where an unshifted step
    along a self-stress diverges). Pins are exact by construction.

    With `q_low` the link vectors include it and the corrections are added to it with
    compensation (without it, plainly: float64 rollouts carry none), so the projection works at the accuracy of the links' own lengths:
    from positions rounded to their scale (float32 at 12 m: ulp 1e-6) it would move
    the structure by that much each step (chain16, 100 RK4 steps in float32: 3.3e-6
    from float64 with compensated RK4 sums alone, 8.3e-7 with this).
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
        for _ in range(iterations):
            u = constraints.link_directions(q, low)
            correction = -transpose_times(u, gram.solve_fn(u, shift)(constraints.link_residual(q, low)))
            if low is None:
                q = q + correction
            else:
                q, low = compensated_add(q, low, correction)
        u = constraints.link_directions(q, low)
        solve = gram.solve_fn(u, shift)
        # The velocity's defect is `A qd`; its correction the minimum-norm `-A^T G^-1 A qd`.
        qd = refine(lambda defect: -transpose_times(u, solve(defect)), lambda v: times(u, v), qd, passes)
        return (q, qd) if q_low is None else (q, qd, low)

    # Full-precision products: float32 on a GPU is otherwise TF32's (`lgnn.runtime`).
    return full_precision_matmuls(project)
