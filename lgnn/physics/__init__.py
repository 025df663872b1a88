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

Speed comes from structure, never from a different model: `true_acceleration_fn`
solves the exact rods through a constant mass matrix (Schur complement, or a
linear-time block elimination on chains), `acceleration_fn(..., local_mass=True)`
builds a graph-local learned mass matrix from coloured Hessian-vector products, and
`projection_fn` works on per-link blocks (tridiagonal solves on chains). Each is
tested against the general path.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from lgnn.scene import Scene, is_pinned_chain

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
# Scenes regular at their initial configuration (chains, T1) use a shift far below
# the smallest Gram eigenvalue of any built-in scene (~2.5e-6 for a 1000-link chain),
# which only keeps the factorisation defined should the motion pass a singular
# configuration; two passes then reach round-off.
REGULAR_PROJECTION_SHIFT = 1e-12
REGULAR_VELOCITY_PROJECTION_PASSES = 2
# Chains of at least this many links use the linear-time block elimination; shorter
# ones the dense solves, whose fixed cost is lower. Measured per RK4 step on one core
# (schur / chain): 16 links 23 / 41 us, 64 links 123 / 156 us, 100 links 289 / 237 us.
CHAIN_SOLVER_MIN_LINKS = 80


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
    of the free (unpinned) nodes, `free_mask` (N, D) the same as a mask; `links` the
    link indices kept as constraint rows. `embed(x)` maps free coordinates to full
    (N, D) positions (pins at their place). The `link_*` methods work on node arrays
    (N, D), the others on free coordinates.
    """

    def __init__(self, scene: Scene):
        n, d = scene.n_nodes, scene.dim
        free_mask = np.ones((n, d), bool)
        free_mask[list(scene.pinned)] = False
        self.shape = (n, d)
        self.free_mask = free_mask
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
        return self.link_residual(self.embed(x))

    def link_residual(self, q: Array) -> Array:
        """`residual` at node positions `q` (N, D)."""
        i, j = self.edge_index[self.links].T
        length = jnp.asarray(self.lengths_all[self.links], q.dtype)
        dq = q[i] - q[j]
        return (jnp.sum(dq * dq, -1) - length**2) / (2 * length)

    def link_speed_terms(self, qd: Array) -> Array:
        """`Adot v` at node velocities `qd` (N, D): `|dv|^2 / l` per kept link."""
        i, j = self.edge_index[self.links].T
        dv = qd[i] - qd[j]
        return jnp.sum(dv * dv, -1) / jnp.asarray(self.lengths_all[self.links], qd.dtype)

    def link_directions(self, q: Array) -> Array:
        """(K, D) `(q_i - q_j) / l` of the kept links at positions `q` (N, D): the
        nonzero blocks of the Jacobian (row k is `+u_k` at node i, `-u_k` at node j)."""
        i, j = self.edge_index[self.links].T
        return (q[i] - q[j]) / jnp.asarray(self.lengths_all[self.links, None], q.dtype)

    def jacobian(self, x: Array) -> Array:
        """A(x) = dPhi/dx (K, F), assembled from the link directions (tested against AD)."""
        i, j = self.edge_index[self.links].T
        u = self.link_directions(self.embed(x))
        rows = jnp.arange(self.n_rows)
        full = jnp.zeros((self.n_rows, *self.shape), x.dtype).at[rows, i].set(u).at[rows, j].add(-u)
        return full.reshape(self.n_rows, -1)[:, self.free]

    def jacobian_dot_v(self, x: Array, v: Array) -> Array:
        """`Adot v` (K,): the second directional derivative of Phi along v, which for
        `Phi = (|dq|^2 - l^2) / 2l` is `|dv|^2 / l` (tested against AD)."""
        return self.link_speed_terms(self.embed_velocity(v))


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


def acceleration_fn(scene: Scene, lagrangian: LagrangianFn, force_fn: ForceFn | None = None, *, local_mass: bool = False) -> AccelerationFn:
    """Constrained Euler-Lagrange accelerations of *any* Lagrangian under the scene's
    constraints (module docstring). Returns `accel(q, qd) -> qdd`, all (N, D), with zero
    acceleration at pinned nodes. `force_fn(q, qd) -> (N, D)` adds generalised forces
    (drag, external); pass `None` for none.

    `local_mass=True` declares that the mass matrix `d2L/dqd2` couples only nodes that
    share a link (true of the exact rods and of LGNN's per-link energies). It is then
    assembled from a few Hessian-vector products on a distance-2 colouring of the
    nodes (`_LocalMass`: 3 colours x D products for any chain, instead of one per
    coordinate), and a chain pinned at node 0 (from `CHAIN_SOLVER_MIN_LINKS` links) is
    solved by the linear-time block elimination of `_chain_kkt_solve` (regularised and
    refined like `_solve_kkt`), so a step costs time linear in the chain's length.
    Declaring it for a Lagrangian whose mass matrix is not local gives wrong
    accelerations (tests compare both paths).
    """
    constraints = Constraints(scene)
    local = _LocalMass(scene, constraints) if local_mass else None
    chain_solve = local_mass and is_pinned_chain(scene) and scene.n_links >= CHAIN_SOLVER_MIN_LINKS

    def reduced_lagrangian(x, v):
        return lagrangian(constraints.embed(x), constraints.embed_velocity(v))

    grad_v = jax.grad(reduced_lagrangian, argnums=1)

    def accel(q, qd):
        x, v = constraints.restrict(q), constraints.restrict(qd)
        pi = jax.grad(reduced_lagrangian, argnums=0)(x, v)
        coriolis_v = jax.jvp(lambda y: grad_v(y, v), (x,), (v,))[1]
        rhs = pi - coriolis_v
        if force_fn is not None:
            rhs = rhs + constraints.restrict(force_fn(q, qd))
        if local is None:
            mass = jax.jacfwd(grad_v, argnums=1)(x, v)
        else:
            products = local.products(lambda seed: jax.jvp(lambda w: grad_v(x, w), (v,), (seed,))[1], x.dtype)
            if chain_solve:
                diagonal, upper = local.chain_blocks(products)
                u = constraints.link_directions(q)
                xdd = _chain_kkt_solve(diagonal, upper, u, rhs.reshape(-1, 2), -constraints.jacobian_dot_v(x, v),
                                       KKT_REGULARISATION * jnp.trace(diagonal, axis1=1, axis2=2).mean() / 2, KKT_REFINEMENT_STEPS)
                return constraints.embed_velocity(xdd.reshape(-1))
            mass = local.dense(products)
        xdd = _solve_kkt(mass, constraints.jacobian(x), rhs, -constraints.jacobian_dot_v(x, v))
        return constraints.embed_velocity(xdd)

    return accel


class _LocalMass:
    """A mass matrix over the free coordinates whose only nonzero blocks couple a node
    with itself and with the nodes it shares a link with, from Hessian-vector products.

    Nodes are coloured so that no two nodes of one colour are linked or share a
    neighbour (greedy distance-2 colouring: 3 colours for a chain). The product of M
    with the indicator of colour c, coordinate d, then holds in each node's rows the
    column d of its block with the one node of colour c it couples to. Static index
    arrays (NumPy) map the products to blocks.
    """

    def __init__(self, scene: Scene, constraints: Constraints):
        n, d = constraints.shape
        free_node = constraints.free_mask[:, 0]
        neighbours = [set() for _ in range(n)]
        for a, b in scene.edges:
            if free_node[a] and free_node[b]:
                neighbours[a].add(b)
                neighbours[b].add(a)
        colour = np.full(n, -1)
        for node in np.flatnonzero(free_node):
            near = set(neighbours[node]).union(*(neighbours[k] for k in neighbours[node]))
            taken = {colour[k] for k in near if colour[k] >= 0}
            colour[node] = next(c for c in range(len(taken) + 1) if c not in taken)
        self.n_colours = int(colour.max()) + 1 if free_node.any() else 0
        node_of = constraints.free // d
        coord_of = constraints.free % d
        # Seed (colour, coordinate) of each free coordinate, and the seeds as vectors.
        self.seed_of = colour[node_of] * d + coord_of
        self.seeds = np.zeros((self.n_colours * d, len(constraints.free)))
        self.seeds[self.seed_of, np.arange(len(constraints.free))] = 1.0
        adjacent = np.eye(n, dtype=bool)
        for a, near in enumerate(neighbours):
            adjacent[a, list(near)] = True
        self.coupled = adjacent[np.ix_(node_of, node_of)]
        # A chain pinned at node 0 has free coordinates 2b + i for node b + 1, so its
        # block (b, i, j) is row 2b + i of the product of column 2b + j's seed.
        chain_nodes = (len(constraints.free) // 2) if d == 2 else 0
        block, row, column = np.meshgrid(np.arange(chain_nodes), np.arange(2), np.arange(2), indexing="ij")
        self.diagonal_rows = 2 * block + row
        self.diagonal_seeds = self.seed_of[2 * block + column]
        self.upper_rows = self.diagonal_rows[:-1]
        self.upper_seeds = self.diagonal_seeds[1:]

    def products(self, hvp: Callable[[Array], Array], dtype) -> Array:
        """(S, F) `M @ seed` for every seed."""
        return jax.vmap(hvp)(jnp.asarray(self.seeds, dtype))

    def dense(self, products: Array) -> Array:
        """(F, F) the mass matrix: entry (r, s) is row r of the product of s's seed."""
        return jnp.where(self.coupled, products[self.seed_of[None, :], np.arange(products.shape[1])[:, None]], 0.0)

    def chain_blocks(self, products: Array) -> tuple[Array, Array]:
        """(n, 2, 2) diagonal and (n-1, 2, 2) upper (node b with b+1) blocks of a chain."""
        return products[self.diagonal_seeds, self.diagonal_rows], products[self.upper_seeds, self.upper_rows]


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


def constant_node_mass(scene: Scene) -> np.ndarray:
    """(N*D, N*D) the constant mass matrix of `constant_mass_lagrangian_fn`, assembled
    from per-link blocks: a rod with ends a, b adds `m/4 + I/l^2` to the (a, a) and
    (b, b) blocks and `m/4 - I/l^2` to (a, b) and (b, a), times the D x D identity."""
    n, d = scene.n_nodes, scene.dim
    mass = np.zeros((n, n))
    same = np.asarray(scene.masses) / 4 + np.asarray(scene.inertias) / np.asarray(scene.lengths) ** 2
    cross = np.asarray(scene.masses) / 4 - np.asarray(scene.inertias) / np.asarray(scene.lengths) ** 2
    a, b = scene.edge_index.T
    np.add.at(mass, (a, a), same)
    np.add.at(mass, (b, b), same)
    np.add.at(mass, (a, b), cross)
    np.add.at(mass, (b, a), cross)
    return np.kron(mass, np.eye(d))


def true_acceleration_fn(scene: Scene, solver: str = "auto", *, vectorised: bool = False) -> AccelerationFn:
    """Ground-truth accelerations: the exact rod Lagrangian, plus drag if the scene has it.

    `solver` picks how the constrained Euler-Lagrange equations are solved; all give
    the same accelerations (to round-off, tested) wherever they apply:
    - "generic": `acceleration_fn` on `lagrangian_fn` (the solver learned models use:
      mass matrix by AD, regularised KKT solve). The reference.
    - "schur": the on-manifold equivalent with a constant mass matrix
      (`constant_mass_lagrangian_fn`), factored once per scene, and a Cholesky solve
      of the Schur complement `A M^-1 A^T` for the multipliers (K x K instead of the
      (F + K)-square KKT system, no mass matrix or its derivatives per call).
    - "chain": the same equations for a chain pinned at one end, solved in time linear
      in its length by block elimination from the free end (`_chain_kkt_solve`).
    - "auto": "chain" where it applies (from `CHAIN_SOLVER_MIN_LINKS` links, or any
      length with `vectorised=True`: callers that `vmap` over many states, where the
      scan's elementwise work vectorises over the batch while the small dense
      factorisations run one matrix at a time; measured on 2 cores, chain16 x 100:
      1.5e5 against 6.2e4 steps/s), else "schur", and "generic" for scenes that
      are self-stressed at their initial configuration (T2, T3), whose motion is
      defined by the regularised KKT solve of the exact mass matrix (module docstring),
      and for scenes whose constant mass matrix is singular on the free nodes (a
      link of zero inertia, a node no link touches).
    """
    if solver not in ("auto", "generic", "schur", "chain"):
        raise ValueError(f"unknown solver {solver!r}")
    constraints = Constraints(scene)
    mass = constant_node_mass(scene)[np.ix_(constraints.free, constraints.free)]
    regular_mass = len(mass) == 0 or np.linalg.eigvalsh(mass).min() > 1e-12 * np.abs(mass).max()
    if solver == "auto":
        if constraints.self_stresses or not regular_mass:
            solver = "generic"
        else:
            long_enough = vectorised or scene.n_links >= CHAIN_SOLVER_MIN_LINKS
            solver = "chain" if is_pinned_chain(scene) and long_enough else "schur"
    if solver == "generic":
        return acceleration_fn(scene, lagrangian_fn(scene), drag_force_fn(scene))
    if not regular_mass:
        raise ValueError(f"{scene.name}: the constant mass matrix is singular; use the generic solver")
    if solver == "chain":
        if not is_pinned_chain(scene):
            raise ValueError(f"{scene.name}: the chain solver needs a planar chain pinned at node 0")
        return _chain_acceleration_fn(scene, constraints)
    return _schur_acceleration_fn(scene, constraints, mass)


def vectorised_true_acceleration_fn(scene: Scene) -> AccelerationFn:
    """`true_acceleration_fn` for callers that `vmap` it over many states (batched
    rollouts, data generation): the same accelerations, the solver that vectorises."""
    return true_acceleration_fn(scene, vectorised=True)


def _node_forces_fn(scene: Scene, free_mask: np.ndarray) -> Callable[[Array, Array], Array]:
    """`(q, qd) -> (N, D)` generalised forces on the free nodes (`free_mask` (N, D)):
    gravity (half of each link's weight on each end) plus drag where the scene has it."""
    free_nodes = free_mask.astype(np.float64)
    gravity = np.zeros((scene.n_nodes, scene.dim))
    weight = np.asarray(scene.masses) * float(scene.gravity) / 2
    np.add.at(gravity[:, 1], scene.edge_index[:, 0], -weight)
    np.add.at(gravity[:, 1], scene.edge_index[:, 1], -weight)
    gravity *= free_nodes
    drag = drag_force_fn(scene)

    def forces(q, qd):
        total = jnp.asarray(gravity, q.dtype)
        return total if drag is None else total + drag(q, qd) * jnp.asarray(free_nodes, q.dtype)

    return forces


def _schur_acceleration_fn(scene: Scene, constraints: Constraints, mass: np.ndarray) -> AccelerationFn:
    """The "schur" solver of `true_acceleration_fn`: `a = M^-1 (f - A^T lam)` with
    `(A M^-1 A^T) lam = A M^-1 f + Adot v`, `M` constant (inverted once, in NumPy).
    `A M^-1 A^T` is assembled from `M^-1`'s columns at each link's two nodes, so a call
    costs O(K N D^2) for the products plus the K x K Cholesky."""
    n, d = constraints.shape
    inverse = np.zeros((n * d, n * d))
    inverse[np.ix_(constraints.free, constraints.free)] = np.linalg.inv(mass)
    inverse = inverse.reshape(n, d, n, d)
    forces = _node_forces_fn(scene, constraints.free_mask)
    i, j = constraints.edge_index[constraints.links].T
    # M^-1 A^T = (M^-1[:, i] - M^-1[:, j]) u per link: (N, D, K, D) before contracting u.
    inverse_at_links = inverse[:, :, i, :] - inverse[:, :, j, :]

    def accel(q, qd):
        dtype = q.dtype
        minv = jnp.asarray(inverse, dtype)
        accel_free = jnp.einsum("ndme,me->nd", minv, forces(q, qd))
        if constraints.n_rows == 0:
            return accel_free
        u = constraints.link_directions(q)
        rhs = jnp.sum(u * (accel_free[i] - accel_free[j]), -1) + constraints.link_speed_terms(qd)
        minv_at = jnp.einsum("ndke,ke->ndk", jnp.asarray(inverse_at_links, dtype), u)
        schur = jnp.einsum("ke,kel->kl", u, minv_at[i] - minv_at[j])
        lam = _regularised_spd_solve(schur, rhs)
        return accel_free - jnp.einsum("ndk,k->nd", minv_at, lam)

    return accel


def _regularised_spd_solve(matrix: Array, rhs: Array) -> Array:
    """Cholesky solve of `(S + eps I) x = r`, refined against `S x = r`: exact at regular
    configurations, bounded near singular ones (as `_solve_kkt`)."""
    k = matrix.shape[0]
    eps = KKT_REGULARISATION * jnp.trace(matrix) / k
    factor = jax.scipy.linalg.cho_factor(matrix + eps * jnp.eye(k, dtype=matrix.dtype))
    solution = jax.scipy.linalg.cho_solve(factor, rhs)
    for _ in range(KKT_REFINEMENT_STEPS):
        solution = solution + jax.scipy.linalg.cho_solve(factor, rhs - matrix @ solution)
    return solution


def _inverse_3x3(m: Array) -> Array:
    """Inverse of a (3, 3) matrix by its adjugate: a handful of fused elementwise ops,
    where a LAPACK call per block of the chain elimination would cost more than the
    arithmetic."""
    a, b, c = m[0, 0], m[0, 1], m[0, 2]
    d, e, f = m[1, 0], m[1, 1], m[1, 2]
    g, h, k = m[2, 0], m[2, 1], m[2, 2]
    cofactor = (e * k - f * h, f * g - d * k, d * h - e * g)
    adjugate = jnp.array([
        [cofactor[0], c * h - b * k, b * f - c * e],
        [cofactor[1], a * k - c * g, c * d - a * f],
        [cofactor[2], b * g - a * h, a * e - b * d],
    ])
    return adjugate / (a * cofactor[0] + b * cofactor[1] + c * cofactor[2])


def _chain_acceleration_fn(scene: Scene, constraints: Constraints) -> AccelerationFn:
    """The "chain" solver of `true_acceleration_fn`: the constant-mass equations of a
    planar chain pinned at node 0 by `_chain_kkt_solve`, in time linear in its length.
    A pinned chain's constraint rows are always independent (every link is kept, in
    order), so no regularisation is needed."""
    n = scene.n_links
    node_mass = constant_node_mass(scene).reshape(n + 1, 2, n + 1, 2)
    # (n, 2, 2) blocks (nodes 1..n) and (n-1, 2, 2) blocks (node b with b+1).
    diagonal_mass = node_mass[np.arange(1, n + 1), :, np.arange(1, n + 1), :]
    upper_mass = node_mass[np.arange(1, n), :, np.arange(2, n + 1), :]
    forces = _node_forces_fn(scene, constraints.free_mask)

    def accel(q, qd):
        dtype = q.dtype
        # Link rows: `A a = -Adot v`.
        accel_nodes = _chain_kkt_solve(jnp.asarray(diagonal_mass, dtype), jnp.asarray(upper_mass, dtype), constraints.link_directions(q),
                                       forces(q, qd)[1:], -constraints.link_speed_terms(qd))
        return jnp.concatenate([jnp.zeros((1, 2), dtype), accel_nodes])

    return accel


def _chain_kkt_solve(diagonal_mass: Array, upper_mass: Array, u: Array, node_rhs: Array, link_rhs: Array,
                     eps: Array | float = 0.0, refinement_steps: int = 0) -> Array:
    """Solve the KKT system of a planar chain pinned at node 0 in time linear in n.

    Block b (b = 0..n-1) holds node b+1's acceleration and link b's multiplier. Link b
    joins nodes b and b+1 (row `+u_b` at node b, `-u_b` at node b+1; `u` (n, 2)) and the
    mass matrix couples only neighbouring nodes (`diagonal_mass` (n, 2, 2) for nodes
    1..n, `upper_mass` (n-1, 2, 2) node b with b+1), so the KKT matrix is
    block-tridiagonal with 3 x 3 blocks: diagonal `D_b = [[M_b+1,b+1, -u_b], [-u_b^T,
    -eps]]`, above it `U_b = [[M_b+1,b+2, u_b+1], [0, 0]]`. Eliminating from the free
    end (`D~_b = D_b - U_b D~_b+1^-1 U_b^T`, the articulated inertia of the chain beyond
    node b+1) and substituting back from the pin are two `lax.scan`s; with `eps > 0`
    each refinement step against the exact (`eps = 0`) system costs two more.
    Returns the node accelerations (n, 2).
    """
    n, dtype = u.shape[0], u.dtype

    def blocks(eps_value):
        diagonal = jnp.zeros((n, 3, 3), dtype).at[:, :2, :2].set(diagonal_mass).at[:, :2, 2].set(-u).at[:, 2, :2].set(-u)
        return diagonal.at[:, 2, 2].set(-eps_value)

    upper = jnp.zeros((n - 1, 3, 3), dtype).at[:, :2, :2].set(upper_mass).at[:, :2, 2].set(u[1:])
    diagonal = blocks(eps)
    rhs = jnp.concatenate([node_rhs, link_rhs[:, None]], axis=1)

    def eliminate(carry, block):
        next_inverse, next_reduced = carry
        block_diagonal, block_upper, block_rhs = block
        weight = block_upper @ next_inverse
        inverse = _inverse_3x3(block_diagonal - weight @ block_upper.T)
        reduced = block_rhs - weight @ next_reduced
        return (inverse, reduced), (inverse, weight, reduced)

    def reduce(next_reduced, block):
        block_weight, block_rhs = block
        reduced = block_rhs - block_weight @ next_reduced
        return reduced, reduced

    def substitute(previous, block):
        inverse, reduced, block_upper = block
        solution = inverse @ (reduced - block_upper.T @ previous)
        return solution, solution

    def back_substitute(inverses, reduced):
        first = inverses[0] @ reduced[0]
        _, rest = jax.lax.scan(substitute, first, (inverses[1:], reduced[1:], upper))
        return jnp.concatenate([first[None], rest])

    last_inverse = _inverse_3x3(diagonal[-1])
    _, (inverses, weights, reduced) = jax.lax.scan(eliminate, (last_inverse, rhs[-1]), (diagonal[:-1], upper, rhs[:-1]), reverse=True)
    inverses = jnp.concatenate([inverses, last_inverse[None]])
    solution = back_substitute(inverses, jnp.concatenate([reduced, rhs[-1:]]))
    exact = blocks(0.0) if refinement_steps else None
    for _ in range(refinement_steps):
        # Residual against the exact system: K y = D_b y_b + U_b y_b+1 + U_b-1^T y_b-1.
        product = jnp.einsum("bij,bj->bi", exact, solution)
        product = product.at[:-1].add(jnp.einsum("bij,bj->bi", upper, solution[1:]))
        product = product.at[1:].add(jnp.einsum("bji,bj->bi", upper, solution[:-1]))
        residual = rhs - product
        _, reduced = jax.lax.scan(reduce, residual[-1], (weights, residual[:-1]), reverse=True)
        solution = solution + back_substitute(inverses, jnp.concatenate([reduced, residual[-1:]]))
    return solution[:, :2]


class _LinkGram:
    """The Gram matrix `G = A A^T` of the kept constraint rows, from its sparsity.

    `G_kl` is nonzero only when links k and l share a free node, where it is
    `+-u_k . u_l`; the diagonal counts each link's free ends. The pairs are found once
    per scene. When only consecutive kept links share nodes (a chain) G is tridiagonal
    and solved in linear time; otherwise it is assembled dense and factored by Cholesky.
    """

    def __init__(self, constraints: Constraints):
        i, j = constraints.edge_index[constraints.links].T
        pinned = ~constraints.free_mask[:, 0]
        self.n_rows = constraints.n_rows
        self.free_ends = (~pinned[i]).astype(np.float64) + (~pinned[j]).astype(np.float64)
        ends = [(k, node, sign) for k in range(self.n_rows) for node, sign in ((i[k], 1.0), (j[k], -1.0)) if not pinned[node]]
        by_node: dict[int, list[tuple[int, float]]] = {}
        for k, node, sign in ends:
            by_node.setdefault(int(node), []).append((k, sign))
        pairs = [(a, b, sa * sb) for incident in by_node.values() for x, (a, sa) in enumerate(incident) for b, sb in incident[x + 1 :]]
        pairs = [(min(a, b), max(a, b), sign) for a, b, sign in pairs]
        self.first, self.second, self.sign = (np.asarray(c, dtype) for c, dtype in zip(zip(*pairs), (np.int64, np.int64, np.float64))) if pairs else (
            np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
        self.tridiagonal = bool(np.all(self.second - self.first == 1))

    def solve_fn(self, u: Array, shift: float) -> Callable[[Array], Array]:
        """`r -> (G + shift I)^-1 r` at link directions `u` (K, D), factored once."""
        diag = jnp.asarray(self.free_ends, u.dtype) * jnp.sum(u * u, -1) + shift
        off = jnp.asarray(self.sign, u.dtype) * jnp.sum(u[self.first] * u[self.second], -1)
        if self.tridiagonal:
            upper = jnp.zeros_like(diag).at[self.first].add(off)
            lower = jnp.roll(upper, 1)
            return lambda r: jax.lax.linalg.tridiagonal_solve(lower, diag, upper, r[:, None])[:, 0]
        gram = jnp.diag(diag).at[self.first, self.second].add(off).at[self.second, self.first].add(off)
        factor = jax.scipy.linalg.cho_factor(gram)
        return lambda r: jax.scipy.linalg.cho_solve(factor, r)


def projection_fn(scene: Scene, iterations: int = 4) -> Callable[[Array, Array], tuple[Array, Array]]:
    """Project `(q, qd)` back onto the constraint manifold.

    Positions: Gauss-Newton steps `q <- q - A^T (A A^T)^-1 Phi(q)` (the minimum-norm
    correction; quadratic convergence, so a fixed few steps reach round-off from the
    small drift of one integration step, and larger drifts still converge). Velocities:
    the orthogonal projection onto `A v = 0` at the corrected positions. All products
    with `A` use its per-link blocks (`_LinkGram` solves with `A A^T`), so a chain
    projects in time linear in its length. `A A^T` is SPD at regular configurations;
    a Levenberg-Marquardt shift keeps its factorisation defined at singular ones
    (`REGULAR_PROJECTION_SHIFT` for scenes regular at their initial configuration,
    `PROJECTION_SHIFT` for self-stressed ones, where an unshifted step along a
    self-stress diverges). Pins are exact by construction.
    """
    constraints = Constraints(scene)
    gram = _LinkGram(constraints)
    i, j = constraints.edge_index[constraints.links].T
    free_nodes = constraints.free_mask.astype(np.float64)
    singular = constraints.self_stresses > 0
    shift = PROJECTION_SHIFT if singular else REGULAR_PROJECTION_SHIFT
    # The shift leaves a fraction ~shift / sigma^2 of `A v` per pass; repeated passes
    # with the same factor remove it geometrically (iterative refinement).
    passes = VELOCITY_PROJECTION_PASSES if singular else REGULAR_VELOCITY_PROJECTION_PASSES

    def transpose_times(u, lam):
        force = u * lam[:, None]
        return jnp.zeros(constraints.shape, u.dtype).at[i].add(force).at[j].add(-force) * jnp.asarray(free_nodes, u.dtype)

    def times(u, v):
        return jnp.sum(u * (v[i] - v[j]), -1)

    def project(q, qd):
        if constraints.n_rows == 0:
            return constraints.embed(constraints.restrict(q)), constraints.embed_velocity(constraints.restrict(qd))
        # Pinned nodes are put exactly at their pins, at rest.
        q = jnp.where(constraints.free_mask, q, jnp.asarray(constraints.pin_positions, q.dtype))
        qd = qd * jnp.asarray(free_nodes, qd.dtype)
        for _ in range(iterations):
            u = constraints.link_directions(q)
            q = q - transpose_times(u, gram.solve_fn(u, shift)(constraints.link_residual(q)))
        u = constraints.link_directions(q)
        solve = gram.solve_fn(u, shift)
        for _ in range(passes):
            qd = qd - transpose_times(u, solve(times(u, qd)))
        return q, qd

    return project
