"""Constrained Lagrangian mechanics of a scene in Cartesian node coordinates.

Contract: every function here takes a concrete `Scene` and returns pure functions of
node arrays `q, qd` of shape (N, D) (no batching; `vmap` them). Nothing here calls
`jit`. Use float64 (`jax_enable_x64`) where accuracy matters.

The central piece is `acceleration_fn(scene, lagrangian_fn, force_fn)`, a function
transformer: given *any* Lagrangian `L(q, qd)` (the exact one of `lagrangian_fn`, or
a learned one) it returns `qdd(q, qd)` from the constrained Euler-Lagrange equations
of the paper (Eq. acc)

    M qdd + A^T lam = Pi - C qd + F,      A qdd = -Adot qd,

with `M = d2L/dqd2`, `C = d2L/dqd dq`, `Pi = dL/dq`, `F` non-conservative and external
forces (drag), `A = dPhi/dq` the Jacobian of the link-length constraints.

How the difficult cases are handled (no pseudo-inverse anywhere):
- Pins are exact: pinned nodes are removed from the unknowns (their position is the
  scene's pin position, their velocity and acceleration zero). No pin rows exist, so an
  unpinned scene has none and a pinned one has no slipping pin.
- The rod mass matrix is singular: a rod's kinetic energy does not change when it is
  stretched, so `M` has a null direction per link (and is entirely singular when links
  are collinear). We never invert `M`: we solve the saddle-point (KKT) system
  `[[M, A^T], [A, 0]] [qdd; lam] = [f; -Adot qd]` by LU. It is nonsingular whenever
  `A` has full row rank and `M` is positive definite on the null space of `A` (the
  motions that keep link lengths), which holds for any rod of positive mass: the length
  constraints remove exactly the directions in which `M` is singular.
- Redundant constraints (a link between two pinned nodes, an over-braced truss): rows
  are selected once per scene by a rank-revealing (column-pivoted) QR of the constraint
  Jacobian at a random *generic* configuration, so exactly the structurally redundant
  rows are dropped (links between two pinned nodes always are). The kept rows span the
  same constraint manifold, so accelerations are unique and exact; only the
  multipliers of the dropped rows (which are not unique) are not computed.
- Singular configurations: a structure can also lose rank at particular configurations
  (a self-stressed tensegrity such as T2 or T3 at rest, a rope pulled exactly taut).
  There the KKT matrix is singular, the multipliers are not unique and the
  acceleration-level equations no longer encode the constraints fully (to first order
  a taut rope may move sideways). We solve the regularised system
  `[[M, A^T], [A, -eps I]]` by LU and refine the solution iteratively against the
  exact system: away from singular configurations the refinement converges to the
  exact solution (to round-off, tested against the unregularised solve); at them it
  gives the acceleration with minimum-norm multipliers, and the position projection
  of the integrators (which enforces the exact constraints, second-order terms
  included) keeps the structure on the constraint set. The inextensible model itself
  is singular there (a taut rope under a transverse load needs infinite tension), so
  expect less: T2 is prestress-stable (rigid with inextensible links), its exact motion
  is rest, and this engine keeps it within ~5e-5 of rest over 0.1 s; T3 is partly locked, partly
  free, and its trajectory converges only at first order in dt (measured over 0.1 s:
  1.7e-3 between dt = 1e-4 and 5e-5), with energy lost in the first steps as the
  projection removes the sideways kick. `Constraints.self_stresses` counts the
  self-stresses at the scene's initial configuration so callers can report such scenes.
- Constraint rows are scaled by 1/l (`Phi_e = (|dq|^2 - l^2) / 2l`, Jacobian rows are
  unit vectors) so links of very different lengths are equally well conditioned.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from lgnn.scene import Scene

Array = jax.Array
LagrangianFn = Callable[[Array, Array], Array]
ForceFn = Callable[[Array, Array], Array]
AccelerationFn = Callable[[Array, Array], Array]

# Relative size of a pivot of the constraint Jacobian's QR below which its row is
# redundant (the Jacobian rows are unit vectors, so this is an absolute angle scale).
RANK_TOLERANCE = 1e-9
# Regularisation of the KKT solve relative to the mass scale, and refinement steps.
# With 1e-9, three refinement steps reach round-off on every built-in scene (the
# contraction per step is ~eps / sigma_min(A M^-1 A^T)); at singular configurations
# it bounds the multipliers like a very stiff rod (measured on T2: smaller eps
# makes no difference to the motion, larger lets the structure sag visibly).
KKT_REGULARISATION = 1e-9
KKT_REFINEMENT_STEPS = 3
# Levenberg-Marquardt shift of the projection's Gauss-Newton steps (the Gram matrix of
# unit Jacobian rows has eigenvalues of order 1): bounds the step at singular
# configurations, where an unshifted step along a self-stress diverges.
PROJECTION_SHIFT = 1e-6
VELOCITY_PROJECTION_PASSES = 5


# ---------------------------------------------------------------------------------
# Per-link kinematics
# ---------------------------------------------------------------------------------


def _link_kinematics(scene: Scene, q: Array, qd: Array):
    i, j = scene.edge_index.T
    dq = q[i] - q[j]
    dqd = qd[i] - qd[j]
    v_cm = 0.5 * (qd[i] + qd[j])
    y_cm = 0.5 * (q[i, 1] + q[j, 1])
    return dq, dqd, v_cm, y_cm


def angular_speed_squared(dq: Array, dqd: Array) -> Array:
    """omega^2 of rods with axis `dq` and end-velocity difference `dqd` (..., D).

    `|dq x dqd|^2 / |dq|^4`, written with Lagrange's identity
    `|a x b|^2 = |a|^2 |b|^2 - (a.b)^2` so it holds in 2D and 3D alike.
    """
    dq2 = jnp.sum(dq * dq, -1)
    cross2 = dq2 * jnp.sum(dqd * dqd, -1) - jnp.sum(dq * dqd, -1) ** 2
    return cross2 / dq2**2


def kinetic_energy_per_link(scene: Scene, q: Array, qd: Array) -> Array:
    """(E,) exact rod kinetic energy `1/2 m |v_cm|^2 + 1/2 I omega^2`."""
    dq, dqd, v_cm, _ = _link_kinematics(scene, q, qd)
    m, inertia = jnp.asarray(scene.masses), jnp.asarray(scene.inertias)
    return 0.5 * m * jnp.sum(v_cm * v_cm, -1) + 0.5 * inertia * angular_speed_squared(dq, dqd)


def potential_energy_per_link(scene: Scene, q: Array) -> Array:
    """(E,) gravitational energy `m g y_cm` (gravity along -y)."""
    i, j = scene.edge_index.T
    y_cm = 0.5 * (q[i, 1] + q[j, 1])
    return jnp.asarray(scene.masses) * jnp.asarray(scene.gravity) * y_cm


def lagrangian_fn(scene: Scene) -> LagrangianFn:
    """The exact Lagrangian `L(q, qd) = T - V` of the scene's rods."""

    def lagrangian(q, qd):
        return jnp.sum(kinetic_energy_per_link(scene, q, qd)) - jnp.sum(potential_energy_per_link(scene, q))

    return lagrangian


def constant_mass_lagrangian_fn(scene: Scene) -> LagrangianFn:
    """A Lagrangian equal to `lagrangian_fn` on the constraint manifold, with a constant,
    positive definite mass matrix: `1/2 m |v_cm|^2 + 1/2 (I / l^2) |dqd|^2 - V`.

    On the manifold `dq . dqd = 0` and `|dq| = l`, so `omega^2 = |dqd|^2 / l^2`; both give
    the same trajectories (tested). Used to cross-check the singular-`M` handling.
    """
    m, inertia, length = (jnp.asarray(a) for a in (scene.masses, scene.inertias, scene.lengths))

    def lagrangian(q, qd):
        _, dqd, v_cm, _ = _link_kinematics(scene, q, qd)
        kinetic = 0.5 * m * jnp.sum(v_cm * v_cm, -1) + 0.5 * inertia / length**2 * jnp.sum(dqd * dqd, -1)
        return jnp.sum(kinetic) - jnp.sum(potential_energy_per_link(scene, q))

    return lagrangian


def energy_fn(scene: Scene) -> Callable[[Array, Array], Array]:
    """The exact Hamiltonian `H(q, qd) = T + V` of the scene."""

    def energy(q, qd):
        return jnp.sum(kinetic_energy_per_link(scene, q, qd)) + jnp.sum(potential_energy_per_link(scene, q))

    return energy


def hamiltonian_fn(lagrangian: LagrangianFn) -> Callable[[Array, Array], Array]:
    """`H = qd . dL/dqd - L` of any Lagrangian (for learned models)."""

    def hamiltonian(q, qd):
        value, momentum_dot_qd = jax.jvp(lambda v: lagrangian(q, v), (qd,), (qd,))
        return momentum_dot_qd - value

    return hamiltonian


def drag_force_fn(scene: Scene) -> ForceFn | None:
    """Linear drag: each link feels `-drag * v_cm`, split equally between its two nodes.

    `None` when the scene has no drag, so no drag term is built at all.
    """
    if scene.drag == 0:
        return None
    i, j = scene.edge_index.T
    drag = scene.drag

    def force(q, qd):
        half = -0.5 * drag * 0.5 * (qd[i] + qd[j])
        return jnp.zeros_like(qd).at[i].add(half).at[j].add(half)

    return force


# ---------------------------------------------------------------------------------
# Constraints
# ---------------------------------------------------------------------------------


class Constraints:
    """The scene's independent link-length constraints over the free coordinates.

    Attributes (all static NumPy): `free` indices into the flattened (N*D) coordinates
    of the free (unpinned) nodes; `links` the link indices kept as constraint rows.
    `embed(x)` maps free coordinates to full (N, D) positions (pins at their place).
    """

    def __init__(self, scene: Scene):
        n, d = scene.n_nodes, scene.dim
        free_mask = np.ones((n, d), bool)
        free_mask[list(scene.pinned)] = False
        self.shape = (n, d)
        self.free = np.flatnonzero(free_mask.ravel())
        self.pin_positions = np.asarray(scene.nodes, np.float64).copy()
        pinned = set(scene.pinned)
        candidate = np.asarray(
            [k for k, (a, b) in enumerate(scene.edges) if not (a in pinned and b in pinned)], dtype=np.int64
        )
        self.lengths_all = np.asarray(scene.lengths, np.float64)
        self.edge_index = scene.edge_index
        self.links = self._independent_rows(candidate)
        self.redundant = np.setdiff1d(np.arange(scene.n_links), self.links)

    def _independent_rows(self, candidate: np.ndarray) -> np.ndarray:
        """Rows independent at a random generic configuration (structural rank)."""
        if len(candidate) == 0:
            return candidate
        generic = np.random.default_rng(0).normal(size=self.pin_positions.shape)
        jac = self._jacobian_np(candidate, generic)
        _, r, pivots = scipy.linalg.qr(jac.T, mode="economic", pivoting=True)
        diag = np.abs(np.diag(r))
        rank = int(np.sum(diag > RANK_TOLERANCE * max(diag[0], 1.0)))
        return np.sort(candidate[pivots[:rank]])

    @property
    def self_stresses(self) -> int:
        """Dependencies among the kept rows at the scene's initial configuration: 0 for a
        regular configuration, > 0 for a self-stressed (singular) one such as T2 at rest."""
        if self.n_rows == 0:
            return 0
        singular_values = np.linalg.svd(self._jacobian_np(self.links, self.pin_positions), compute_uv=False)
        return int(np.sum(singular_values < RANK_TOLERANCE * singular_values[0]))

    def _jacobian_np(self, links: np.ndarray, q: np.ndarray) -> np.ndarray:
        i, j = self.edge_index[links].T
        rows = np.zeros((len(links), *self.shape))
        unit = (q[i] - q[j]) / self.lengths_all[links, None]
        rows[np.arange(len(links)), i] = unit
        rows[np.arange(len(links)), j] = -unit
        return rows.reshape(len(links), -1)[:, self.free]

    @property
    def n_rows(self) -> int:
        return len(self.links)

    def embed(self, x: Array) -> Array:
        """Free coordinates (F,) -> positions (N, D) with pinned nodes at their pins."""
        full = jnp.asarray(self.pin_positions, x.dtype).ravel().at[self.free].set(x)
        return full.reshape(self.shape)

    def embed_velocity(self, v: Array) -> Array:
        return jnp.zeros(self.shape[0] * self.shape[1], v.dtype).at[self.free].set(v).reshape(self.shape)

    def restrict(self, full: Array) -> Array:
        """(N, D) -> free coordinates (F,)."""
        return full.reshape(-1)[self.free]

    def residual(self, x: Array) -> Array:
        """Phi(x) (K,): `(|dq|^2 - l^2) / 2l` per kept link; zero on the manifold."""
        q = self.embed(x)
        i, j = self.edge_index[self.links].T
        length = jnp.asarray(self.lengths_all[self.links], x.dtype)
        dq = q[i] - q[j]
        return (jnp.sum(dq * dq, -1) - length**2) / (2 * length)

    def jacobian(self, x: Array) -> Array:
        """A(x) = dPhi/dx (K, F)."""
        return jax.jacfwd(self.residual)(x)

    def jacobian_dot_v(self, x: Array, v: Array) -> Array:
        """`Adot v` (K,): the second directional derivative of Phi along v."""
        return jax.jvp(lambda y: jax.jvp(self.residual, (y,), (v,))[1], (x,), (v,))[1]


def constraint_violation(scene: Scene, q: Array) -> Array:
    """Max absolute error of link lengths and pin positions at positions `q` (N, D)."""
    i, j = scene.edge_index.T
    stretch = jnp.abs(jnp.linalg.norm(q[i] - q[j], axis=-1) - jnp.asarray(scene.lengths))
    worst = jnp.max(stretch)
    if scene.pinned:
        pins = np.asarray(scene.pinned)
        worst = jnp.maximum(worst, jnp.max(jnp.abs(q[pins] - jnp.asarray(scene.nodes[pins]))))
    return worst


def velocity_constraint_violation(scene: Scene, q: Array, qd: Array) -> Array:
    """Max absolute rate of change of link lengths (and pin velocity) at (q, qd)."""
    i, j = scene.edge_index.T
    dq = q[i] - q[j]
    rate = jnp.abs(jnp.sum(dq * (qd[i] - qd[j]), -1)) / jnp.linalg.norm(dq, axis=-1)
    worst = jnp.max(rate)
    if scene.pinned:
        worst = jnp.maximum(worst, jnp.max(jnp.abs(qd[np.asarray(scene.pinned)])))
    return worst


# ---------------------------------------------------------------------------------
# The constrained Euler-Lagrange solve
# ---------------------------------------------------------------------------------


def acceleration_fn(scene: Scene, lagrangian: LagrangianFn, force_fn: ForceFn | None = None) -> AccelerationFn:
    """Constrained Euler-Lagrange accelerations of *any* Lagrangian under the scene's
    constraints (module docstring). Returns `accel(q, qd) -> qdd`, all (N, D), with zero
    acceleration at pinned nodes. `force_fn(q, qd) -> (N, D)` adds generalised forces
    (drag, external); pass `None` for none."""
    constraints = Constraints(scene)

    def reduced_lagrangian(x, v):
        return lagrangian(constraints.embed(x), constraints.embed_velocity(v))

    grad_v = jax.grad(reduced_lagrangian, argnums=1)

    def accel(q, qd):
        x, v = constraints.restrict(q), constraints.restrict(qd)
        pi = jax.grad(reduced_lagrangian, argnums=0)(x, v)
        mass = jax.jacfwd(grad_v, argnums=1)(x, v)
        coriolis_v = jax.jvp(lambda y: grad_v(y, v), (x,), (v,))[1]
        rhs = pi - coriolis_v
        if force_fn is not None:
            rhs = rhs + constraints.restrict(force_fn(q, qd))
        xdd = _solve_kkt(mass, constraints.jacobian(x), rhs, -constraints.jacobian_dot_v(x, v))
        return constraints.embed_velocity(xdd)

    return accel


def _solve_kkt(mass: Array, jac: Array, force: Array, accel_rhs: Array) -> Array:
    """Solve `[[M, A^T], [A, 0]] [a; lam] = [force; accel_rhs]` for `a`: LU of the
    regularised matrix (`-eps I` in the lower block), refined against the exact one."""
    n, k = mass.shape[0], jac.shape[0]
    if k == 0:
        return jnp.linalg.solve(mass, force)
    eps = KKT_REGULARISATION * jnp.trace(mass) / n
    zeros = jnp.zeros((k, k), mass.dtype)
    kkt = jnp.block([[mass, jac.T], [jac, zeros]])
    factor = jax.scipy.linalg.lu_factor(kkt.at[n:, n:].set(-eps * jnp.eye(k, dtype=mass.dtype)))
    rhs = jnp.concatenate([force, accel_rhs])
    solution = jax.scipy.linalg.lu_solve(factor, rhs)
    for _ in range(KKT_REFINEMENT_STEPS):
        solution = solution + jax.scipy.linalg.lu_solve(factor, rhs - kkt @ solution)
    return solution[:n]


def mass_matrix_fn(lagrangian: LagrangianFn) -> Callable[[Array, Array], Array]:
    """`M(q, qd) = d2L/dqd2` over all node coordinates, shape (N*D, N*D)."""

    def mass_matrix(q, qd):
        flat = lambda v: lagrangian(q, v.reshape(qd.shape))  # noqa: E731
        return jax.hessian(flat)(qd.reshape(-1))

    return mass_matrix


def true_acceleration_fn(scene: Scene) -> AccelerationFn:
    """Ground-truth accelerations: the exact rod Lagrangian, plus drag if the scene has it."""
    return acceleration_fn(scene, lagrangian_fn(scene), drag_force_fn(scene))


def projection_fn(scene: Scene, iterations: int = 4) -> Callable[[Array, Array], tuple[Array, Array]]:
    """Project `(q, qd)` back onto the constraint manifold.

    Positions: Gauss-Newton steps `x <- x - A^T (A A^T)^-1 Phi(x)` (the minimum-norm
    correction; quadratic convergence, so a fixed few steps reach round-off from the
    small drift of one integration step). Velocities: the orthogonal projection onto
    `A v = 0` at the corrected positions. `A A^T` is SPD at regular configurations
    (the kept rows are independent); a tiny Levenberg-Marquardt shift keeps the
    Cholesky factorisation defined at singular (self-stressed) ones. Pins are exact by
    construction.
    """
    constraints = Constraints(scene)

    def shifted_gram_factor(jac):
        gram = jac @ jac.T + PROJECTION_SHIFT * jnp.eye(jac.shape[0], dtype=jac.dtype)
        return jax.scipy.linalg.cho_factor(gram)

    def project(q, qd):
        if constraints.n_rows == 0:
            return q, qd
        x, v = constraints.restrict(q), constraints.restrict(qd)
        for _ in range(iterations):
            jac = constraints.jacobian(x)
            x = x - jac.T @ jax.scipy.linalg.cho_solve(shifted_gram_factor(jac), constraints.residual(x))
        jac = constraints.jacobian(x)
        factor = shifted_gram_factor(jac)
        # The shift leaves a fraction ~shift / sigma^2 of `A v` per pass; repeated passes
        # with the same factor remove it geometrically (iterative refinement).
        for _ in range(VELOCITY_PROJECTION_PASSES):
            v = v - jac.T @ jax.scipy.linalg.cho_solve(factor, jac @ v)
        return constraints.embed(x), constraints.embed_velocity(v)

    return project
