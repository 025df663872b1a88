"""The constrained Euler-Lagrange transformer and the ground-truth accelerations.

Contract: every factory takes a concrete `Scene`, gets the scene's static data from
`prepare(scene)`, and returns a pure `accel(q, qd) -> qdd` of node arrays (N, D) (no
batching: `vmap` it; no `jit`), with zero acceleration at pinned nodes.

`acceleration_fn(scene, lagrangian, force_fn)` solves, for *any* Lagrangian (exact or
learned), the constrained Euler-Lagrange equations of the paper (Eq. acc) over the free
coordinates

    M qdd + A^T lam = Pi - C qd + F,      A qdd = -Adot qd,

with `M = d2L/dqd2`, `C = d2L/dqd dq`, `Pi = dL/dq`, `F` non-conservative and external
forces (drag), `A = dPhi/dq` the Jacobian of the kept link-length rows
(`constraints`). `M` of rods is singular (stretching a rod costs no kinetic energy),
so `M` is never inverted: the KKT system is solved as a whole (`solvers.solve_kkt`),
nonsingular whenever `M` is positive definite on the motions that keep link lengths.

At singular configurations (a self-stressed tensegrity such as T2 or T3 at rest, a
rope pulled exactly taut) the KKT matrix itself is singular, the multipliers are not
unique and the acceleration-level equations no longer encode the constraints fully
(to first order a taut rope may move sideways). The regularised, refined solve then
gives the acceleration with minimum-norm multipliers, and the position projection of
the integrators (`projection`, which enforces the exact constraints, second-order
terms included) keeps the structure on the constraint set. The inextensible model is
itself singular there (a taut rope under a transverse load needs infinite tension), so
expect less: T2 is prestress-stable (rigid with inextensible links), its exact motion
is rest, and this engine keeps it within ~5e-5 of rest over 0.1 s; T3 is partly
locked, partly free, and its trajectory converges only at first order in dt (measured
over 0.1 s: 1.7e-3 between dt = 1e-4 and 5e-5), with energy lost in the first steps
as the projection removes the sideways kick.

Speed comes from structure, never from a different model: `true_acceleration_fn`
solves the exact rods through their constant on-manifold mass matrix (a Schur
complement, or a linear-time block elimination on chains), and
`acceleration_fn(..., mass=LOCAL)` builds a graph-local mass matrix from coloured
Hessian-vector products (`local_mass`, which also serves learned Lagrangians of a
larger reach and LGN's pooled read-out). Each is tested against the general path.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from lgnn import sharding
from lgnn.physics.constraints import take_rows
from lgnn.physics.energies import Array, ForceFn, LagrangianFn, dissipative_force_fn, lagrangian_fn
from lgnn.physics.local_mass import LOCAL, LocalMass, MassStructure
from lgnn.physics.solvers import (banded_chain_kkt_solve, chain_kkt_solve, guarded_spd_solve, regularised_spd_solve, solve_kkt, spd_solve,
                                  tangent_basis)
from lgnn.physics.system import System, prepare
from lgnn.runtime import full_precision_matmuls
from lgnn.scene import Scene

AccelerationFn = Callable[[Array, Array], Array]


@dataclasses.dataclass(frozen=True)
class EulerLagrange:
    """The pieces of `acceleration_fn`'s constrained Euler-Lagrange equations, each a
    pure function of the free coordinates `x` and velocities `v`
    (`Constraints.restrict`), unbatched: what `acceleration_fn` solves, and what a
    profile of one acceleration times part by part (`tools/lgn_mass_costs.py`).

    - `right_hand_side(x, v)` (F,): `Pi - C qd`, the forces less the Coriolis product;
    - `mass_matrix(x, v)` (F, F): `M`, from the declared structure's products where
      `structured`, else by forward differentiation, one product per coordinate;
    - `mass_products(x, v)`: where `structured`, `(products (S, F), low_rank)`: the
      local part's products with its colouring's seeds, and the pooled read-out's
      low-rank part `J^T H J` as its factors `(J^T (F, P), H (P, P))` (the features'
      transposed Jacobian and the read-out's curvature), or None;
    - `tangent_products(x, v, accel, directions)`: `(Pi - C qd - M accel (F,),
      M directions (F, R))` from one reverse pass and R + 1 forward products, without
      assembling `M` (`parametrised_acceleration_fn`'s tangent-space solve);
    - `pooled_jacobian(x, v)` (F, P): where the structure is pooled, the transposed
      Jacobian of the summed terms by the velocities (forward products);
    - `local`: the local part's colouring (`System.local_mass`), None unless
      `structured`; `chain_solve`: the mass matrix is structured on a long pinned
      chain, so the block elimination solves it (`solvers.chain_kkt_solve` at reach 1,
      `solvers.banded_chain_kkt_solve` beyond or with a pooled low-rank part)."""

    right_hand_side: Callable[[Array, Array], Array]
    mass_matrix: Callable[[Array, Array], Array]
    mass_products: Callable[[Array, Array], tuple] | None
    tangent_products: Callable[[Array, Array, Array, Array], tuple[Array, Array]]
    pooled_jacobian: Callable[[Array, Array], Array] | None
    local: LocalMass | None
    chain_solve: bool

    @property
    def structured(self) -> bool:
        return self.local is not None


def euler_lagrange(scene: Scene, lagrangian: LagrangianFn, mass: MassStructure | None = None) -> EulerLagrange:
    """The pieces of the constrained Euler-Lagrange equations of `lagrangian` on
    `scene` (`EulerLagrange`), its mass matrix assembled from `mass`'s structure where
    that is fewer products (`acceleration_fn`, `uses_mass_structure`)."""
    system = prepare(scene)
    constraints = system.constraints
    structured = mass is not None and uses_mass_structure(scene, mass)
    local = system.local_mass(mass.reach) if structured else None
    pooled = system.pooled_jacobian(mass.supports) if structured and mass.pooled else None

    def reduced(fn):
        return lambda x, v: fn(constraints.embed(x), constraints.embed_velocity(v))

    reduced_lagrangian = reduced(lagrangian)
    grad_v = jax.grad(reduced_lagrangian, argnums=1)
    terms = reduced(mass.terms) if pooled is not None else None

    def right_hand_side(x, v):
        pi = jax.grad(reduced_lagrangian, argnums=0)(x, v)
        coriolis_v = jax.jvp(lambda y: grad_v(y, v), (x,), (v,))[1]
        return pi - coriolis_v

    def tangent_products(x, v, accel, directions):
        # One batch of forward products of both gradients: along (qd, accel), whose
        # velocity gradient's tangent is `C qd + M accel`, and along (0, direction).
        gradients = jax.grad(reduced_lagrangian, argnums=(0, 1))
        along = lambda dx, dv: jax.jvp(gradients, (x, v), (dx, dv))  # noqa: E731
        x_tangents = jnp.concatenate([v[None], jnp.zeros_like(directions.T)])
        v_tangents = jnp.concatenate([accel[None], directions.T])
        (pi, _), (_, products) = jax.vmap(along, out_axes=((None, None), 0))(x_tangents, v_tangents)
        return pi - products[0], products[1:].T

    def mass_products(x, v):
        if pooled is None:
            return local.products(lambda seed: jax.jvp(lambda w: grad_v(x, w), (v,), (seed,))[1], x.dtype), None
        values, linear = jax.linearize(lambda w: terms(x, w), v)
        p = jnp.sum(values, 0)
        slope, curvature = jax.grad(mass.readout)(p), jax.hessian(mass.readout)(p)
        jacobian_t = pooled.transposed(linear, x.dtype)
        # The local sum weighted by the read-out's slope at this state, held fixed.
        grad_local = jax.grad(lambda w: jnp.dot(jnp.sum(terms(x, w), 0), jax.lax.stop_gradient(slope)))
        products = local.products(lambda seed: jax.jvp(grad_local, (v,), (seed,))[1], x.dtype)
        return products, (jacobian_t, curvature)

    def pooled_jacobian(x, v):
        return pooled.transposed(jax.linearize(lambda w: terms(x, w), v)[1], x.dtype)

    def mass_matrix(x, v):
        if local is None:
            return jax.jacfwd(grad_v, argnums=1)(x, v)
        products, low_rank = mass_products(x, v)
        if low_rank is None:
            return local.dense(products)
        jacobian_t, curvature = low_rank
        return local.dense(products) + jacobian_t @ curvature @ jacobian_t.T

    return EulerLagrange(right_hand_side, mass_matrix, mass_products if structured else None, tangent_products,
                         pooled_jacobian if pooled is not None else None, local, structured and system.long_chain)


def acceleration_fn(scene: Scene, lagrangian: LagrangianFn, force_fn: ForceFn | None = None, *, mass: MassStructure | None = None) -> AccelerationFn:
    """Constrained Euler-Lagrange accelerations of *any* Lagrangian under the scene's
    constraints (module docstring). Returns `accel(q, qd) -> qdd`, all (N, D), with zero
    acceleration at pinned nodes. `force_fn(q, qd) -> (N, D)` adds generalised forces
    (drag, external); pass `None` for none.

    `mass` declares the structure of the mass matrix `d2L/dqd2` (`local_mass.MassStructure`),
    so it is assembled from fewer derivative products than one per coordinate, where
    that is fewer (`uses_mass_structure`):
    - `LOCAL` (reach 1: only nodes that share a link are coupled, true of the exact rods
      and of LGNN's per-link energies): a few Hessian-vector products on a colouring of
      the nodes (3 colours x D products for any chain; 2 on a long one, where the
      matrix's symmetry recovers the rest, `local_mass.ChainBandMass`), and a chain
      pinned at node 0 (from `CHAIN_SOLVER_MIN_LINKS` links) is solved by the
      linear-time block elimination of
      `solvers.chain_kkt_solve` (regularised and refined like `solvers.solve_kkt`), so a
      step costs time linear in the chain's length;
    - a larger reach r: 2r + 1 colours x D products on a chain (r + 1 on a long one);
      a long pinned chain's KKT system, block-banded, by
      `solvers.banded_chain_kkt_solve` (groups of r links, block-tridiagonal), linear
      in the length too; elsewhere the dense KKT solve;
    - pooled (LGN's read-out of summed embeddings): the low-rank part from the features'
      Jacobian (forward products on a colouring of the terms' supports), the rest local;
      on a long pinned chain the banded elimination with the low-rank part added by the
      Woodbury identity (`solvers.woodbury`), never the dense matrix.
    Declaring a structure the Lagrangian does not have gives wrong accelerations (tests
    compare every declared structure with the dense path). The equations' pieces are
    `euler_lagrange`'s.
    """
    constraints = prepare(scene).constraints
    equations = euler_lagrange(scene, lagrangian, mass)

    def accel(q, qd):
        x, v = constraints.restrict(q), constraints.restrict(qd)
        rhs = _with_forces(equations.right_hand_side(x, v), constraints, force_fn, q, qd)
        if equations.chain_solve:
            (products, low_rank), u = equations.mass_products(x, v), constraints.link_directions(q)
            d = constraints.shape[1]
            node_rhs, link_rhs = rhs.reshape(-1, d), -constraints.jacobian_dot_v(x, v)
            if equations.local.reach == 1 and low_rank is None:
                xdd = chain_kkt_solve(*equations.local.chain_blocks(products), u, node_rhs, link_rhs, regularised=True)
            else:
                factors = None if low_rank is None else (low_rank[0].reshape(-1, d, low_rank[0].shape[-1]), low_rank[1])
                xdd = banded_chain_kkt_solve(equations.local.band_blocks(products), u, node_rhs, link_rhs, regularised=True, low_rank=factors)
            return constraints.embed_velocity(xdd.reshape(-1))
        return constraints.embed_velocity(_dense_solve(equations, constraints, x, v, rhs)[0])

    return full_precision_matmuls(accel)


def _with_forces(rhs: Array, constraints, force_fn: ForceFn | None, q: Array, qd: Array) -> Array:
    """`rhs` (F,) plus the non-conservative and external forces `F` of `force_fn` at the
    node states `q`, `qd`, over the free coordinates: `Pi - C qd + F` from `Pi - C qd`."""
    return rhs if force_fn is None else rhs + constraints.restrict(force_fn(q, qd))


def _dense_solve(equations: EulerLagrange, constraints, x: Array, v: Array, rhs: Array) -> tuple[Array, Array, Array]:
    """`(xdd, M, A)`: the accelerations over the free coordinates `x`, `v` with forces
    `rhs`, from the dense KKT solve of the mass matrix `M` and constraint Jacobian `A`
    (which the adjoint solves again, `parametrised_acceleration_fn`)."""
    mass, jacobian = equations.mass_matrix(x, v), constraints.jacobian(x)
    return solve_kkt(mass, jacobian, rhs, -constraints.jacobian_dot_v(x, v)), mass, jacobian


# The tangent-space solve (`_tangent_solve`) writes its QR out row by row
# (`solvers.tangent_basis`), so it is taken on scenes of at most this many constraint
# rows (the training chains have 4).
TANGENT_SOLVE_MAX_ROWS = 16


def _tangent_solve(equations: EulerLagrange, constraints, force_fn: ForceFn | None, x: Array, v: Array, q: Array,
                   qd: Array) -> tuple[Array, Array, tuple[Array, Array]]:
    """`(xdd, null_basis, factors)`: the accelerations over the free coordinates from
    the equations restricted to the motions that keep the constraints, for a Jacobian
    `A` of full row rank. With `A^T = [Y, N] [R; 0]` (`solvers.tangent_basis`), `xdd =
    a_p + N z`: `a_p = Y R^-T r` meets `A xdd = r = -Adot qd`, and `(N^T M N) z = N^T
    (f - M a_p)` with `f = Pi - C qd + F`. `M` enters only through `M N` and `C qd + M
    a_p`: F - K + 1 forward products, against F + 1 for the dense solve's `M` and
    Coriolis product (`EulerLagrange.tangent_products`). `factors` are the LU factors
    of `N^T M N`, which the adjoint solves again."""
    jacobian = constraints.jacobian(x)
    range_basis, upper, null_basis = tangent_basis(jacobian)
    particular = range_basis @ jax.scipy.linalg.solve_triangular(upper, -constraints.jacobian_dot_v(x, v), trans="T")
    remainder, mass_null = equations.tangent_products(x, v, particular, null_basis)
    remainder = _with_forces(remainder, constraints, force_fn, q, qd)
    factors = jax.scipy.linalg.lu_factor(null_basis.T @ mass_null)
    return particular + null_basis @ jax.scipy.linalg.lu_solve(factors, null_basis.T @ remainder), null_basis, factors


def parametrised_acceleration_fn(scene: Scene, build: Callable) -> Callable[[object, Array, Array], Array]:
    """`accel(params, q, qd) -> qdd`: `acceleration_fn(scene, lagrangian, force_fn,
    mass=mass)(q, qd)` for `(lagrangian, force_fn, mass) = build(params)`, whose
    derivative by `params` (what training takes) comes from the adjoint of the
    constrained equations instead of differentiating through the solve and the
    mass matrix's Hessian.

    Why: with `K [a; mu] = [f; r]` (`K` the symmetric KKT matrix of `M`, `A`; `f = Pi -
    C qd + F`; `r` free of the parameters), a cotangent `abar` of `a` pulls back to
    `lam^T (df - dM a)` with `K [lam; nu] = [abar; 0]`: the derivative by the
    parameters of the scalar `S = lam^T f - lam^T M a` at fixed `lam`, `a`, `x`, `v`.
    Its Lagrangian terms are directional derivatives of `L`: `lam^T Pi = DL (lam, 0)`
    and `lam^T (C qd + M a) = D2L[(0, lam), (qd, a)]`, two nested forward products
    along single directions. The ordinary route differentiates the Hessian (one
    product per coordinate, each through a reverse pass) in reverse: third derivatives
    of the network along every column. The same gradient to round-off
    (tests/test_physics.py), from one more KKT solve and the reverse pass of `S`: LGN
    trained 1.8x faster on one GPU, LGNN 2.2x (results/gpu/training/README.md).

    Where the constraint rows are independent at every configuration (a chain, a tree:
    `Constraints.always_independent`) and that takes fewer forward products than
    assembling `M`, the forward solve works in the constraints' tangent space
    (`_tangent_solve`): on chain4-3d 9 forward products instead of 13. The same
    accelerations to round-off as the KKT solve, which `acceleration_fn` keeps for
    every scene (a cycle's rows can lose rank, where its regularised solve is needed).

    The derivatives by `q` and `qd` are the ordinary ones (traced only where taken:
    training does not take them). Where `acceleration_fn` solves a long chain by
    elimination, the whole function is the ordinary one."""
    constraints = prepare(scene).constraints

    def equations_of(params):
        """`(force_fn, equations, tangent)`: `tangent` whether the forward solve is
        `_tangent_solve` (`uses_tangent_solve`)."""
        lagrangian, force_fn, mass = build(params)
        return force_fn, euler_lagrange(scene, lagrangian, mass), uses_tangent_solve(scene, mass)

    def ordinary(params, q, qd):
        lagrangian, force_fn, mass = build(params)
        return acceleration_fn(scene, lagrangian, force_fn, mass=mass)(q, qd)

    @full_precision_matmuls
    def forward(params, q, qd):
        force_fn, equations, tangent = equations_of(params)
        x, v = constraints.restrict(q), constraints.restrict(qd)
        if tangent:
            xdd, *system_factors = _tangent_solve(equations, constraints, force_fn, x, v, q, qd)
        else:
            rhs = _with_forces(equations.right_hand_side(x, v), constraints, force_fn, q, qd)
            xdd, *system_factors = _dense_solve(equations, constraints, x, v, rhs)
        return constraints.embed_velocity(xdd), (params, q, qd, xdd, tuple(system_factors))

    @full_precision_matmuls
    def backward(residuals, qdd_bar):
        params, q, qd, xdd, system_factors = residuals
        x, v = constraints.restrict(q), constraints.restrict(qd)
        abar = constraints.restrict(qdd_bar)
        # K is symmetric: the adjoint system is K itself; in the tangent space, its
        # solution's acceleration part is N (N^T M N)^-1 N^T abar.
        if equations_of(params)[2]:
            null_basis, factors = system_factors
            lam = null_basis @ jax.scipy.linalg.lu_solve(factors, null_basis.T @ abar)
        else:
            mass, jacobian = system_factors
            lam = solve_kkt(mass, jacobian, abar, jnp.zeros(jacobian.shape[0], xdd.dtype))

        def pulled_back(params):  # S = lam^T f - lam^T M a, at fixed lam, a, x, v
            lagrangian, force_fn, _ = build(params)
            reduced = lambda y, w: lagrangian(constraints.embed(y), constraints.embed_velocity(w))  # noqa: E731
            along_lam = lambda y, w: jax.jvp(lambda w_: reduced(y, w_), (w,), (lam,))[1]  # noqa: E731  DL (0, lam)
            generalised = jax.jvp(lambda y: reduced(y, v), (x,), (lam,))[1]
            inertial = jax.jvp(along_lam, (x, v), (v, xdd))[1]
            total = generalised - inertial
            return total if force_fn is None else total + jnp.dot(lam, constraints.restrict(force_fn(q, qd)))

        params_bar = jax.grad(pulled_back)(params)
        q_bar, qd_bar = jax.vjp(lambda q_, qd_: ordinary(params, q_, qd_), q, qd)[1](qdd_bar)
        return params_bar, q_bar, qd_bar

    adjoint = jax.custom_vjp(lambda params, q, qd: forward(params, q, qd)[0])
    adjoint.defvjp(forward, backward)

    def accel(params, q, qd):
        if equations_of(params)[1].chain_solve:
            return ordinary(params, q, qd)
        return adjoint(params, q, qd)

    return accel


def uses_tangent_solve(scene: Scene, mass: MassStructure | None) -> bool:
    """Whether `parametrised_acceleration_fn` solves in the constraints' tangent space
    (`_tangent_solve`) on `scene` for a Lagrangian declaring `mass`: where the rows are
    independent at every configuration (`Constraints.always_independent`), at most
    `TANGENT_SOLVE_MAX_ROWS`, and the solve takes fewer forward products than
    assembling the mass matrix (one per coordinate, or the declared structure's)."""
    system = prepare(scene)
    constraints = system.constraints
    coordinates, rows = len(constraints.free), constraints.n_rows
    assembly = mass.products(system) if mass is not None and uses_mass_structure(scene, mass) else coordinates
    return constraints.always_independent and 0 < rows <= TANGENT_SOLVE_MAX_ROWS and coordinates - rows < assembly


def uses_mass_structure(scene: Scene, mass: MassStructure) -> bool:
    """Whether `acceleration_fn` assembles the mass matrix from `mass`'s structure on
    `scene`: when it takes fewer products than the dense path's one per free
    coordinate, and at reach 1 always (a long chain then gets the block elimination)."""
    system = prepare(scene)
    if mass == LOCAL:
        return True
    return mass.products(system) < len(system.constraints.free)


def mass_matrix_fn(lagrangian: LagrangianFn) -> Callable[[Array, Array], Array]:
    """`M(q, qd) = d2L/dqd2` over all node coordinates, shape (N*D, N*D)."""

    def mass_matrix(q, qd):
        flat = lambda v: lagrangian(q, v.reshape(qd.shape))  # noqa: E731
        return jax.hessian(flat)(qd.reshape(-1))

    return mass_matrix


def true_acceleration_fn(scene: Scene, solver: str = "auto", *, vectorised: bool = False) -> AccelerationFn:
    """Ground-truth accelerations: the exact rod Lagrangian, plus drag and joint damping
    where the scene has them.

    `solver` picks how the constrained Euler-Lagrange equations are solved; all give
    the same accelerations (to round-off, tested) wherever they apply:
    - "generic": `acceleration_fn` on `lagrangian_fn` (the solver learned models use:
      mass matrix by AD, regularised KKT solve). The reference.
    - "schur": the on-manifold equivalent with a constant mass matrix
      (`constant_mass_lagrangian_fn`), factored once per scene, and a Cholesky solve
      of the Schur complement `A M^-1 A^T` for the multipliers (K x K instead of the
      (F + K)-square KKT system, no mass matrix or its derivatives per call).
    - "chain": the same equations for a chain pinned at one end, solved in time linear
      in its length by block elimination from the free end (`solvers.chain_kkt_solve`).
    - "auto": "chain" where it applies (from `CHAIN_SOLVER_MIN_LINKS` links, or any
      length with `vectorised=True`: callers that `vmap` over many states, where the
      scan's elementwise work vectorises over the batch while the small dense
      factorisations run one matrix at a time; measured on 2 cores, chain16 x 100:
      1.5e5 against 6.2e4 steps/s), else "schur", and "generic" for scenes that
      are self-stressed at their initial configuration (T2, T3), whose motion is
      defined by the regularised KKT solve of the exact mass matrix (module docstring),
      and for scenes whose constant mass matrix is singular on the free nodes (a
      link of zero inertia, a node no link touches).
    The choice is `System.solver`; a solver that does not apply is a ValueError.
    """
    system = prepare(scene)
    solver = system.solver(solver, vectorised)
    if solver == "generic":
        return acceleration_fn(scene, lagrangian_fn(scene), dissipative_force_fn(scene))
    # Full-precision products: a ground truth in float32 on a GPU is otherwise TF32's.
    # The guarded Schur solve is a branch per call: on a CPU it saves a single
    # trajectory the refinement; on an accelerator a branch reads its predicate back to
    # the host, and under `vmap` both branches run.
    guarded = not vectorised and sharding.platform() == "cpu"
    return full_precision_matmuls(_chain_acceleration_fn(system) if solver == "chain" else _schur_acceleration_fn(system, guarded=guarded))


def vectorised_true_acceleration_fn(scene: Scene) -> AccelerationFn:
    """`true_acceleration_fn` for callers that `vmap` it over many states (batched
    rollouts, data generation): the same accelerations, the solver that vectorises."""
    return true_acceleration_fn(scene, vectorised=True)


def _node_forces_fn(system: System) -> Callable[[Array, Array], Array]:
    """`(q, qd) -> (N, D)` generalised forces on the free nodes: gravity (half of each
    link's weight on each end) plus drag and joint damping where the scene has them."""
    free_nodes = system.constraints.free_mask.astype(np.float64)
    gravity = system.node_gravity
    dissipative = dissipative_force_fn(system.scene)

    def forces(q, qd):
        total = jnp.asarray(gravity, q.dtype)
        return total if dissipative is None else total + dissipative(q, qd) * jnp.asarray(free_nodes, q.dtype)

    return forces


def _schur_acceleration_fn(system: System, guarded: bool = False) -> AccelerationFn:
    """The "schur" solver of `true_acceleration_fn`: `a = M^-1 (f - A^T lam)` with
    `(A M^-1 A^T) lam = A M^-1 f + Adot v`, `M` constant (inverted once, in NumPy).
    `A M^-1 A^T` is assembled from `M^-1`'s columns at each link's two nodes, so a call
    costs O(K N D^2) for the products plus the K x K Cholesky. A pinned chain's
    rows are always independent, so its Schur complement is solved as it is
    (`solvers.spd_solve`), any other scene's regularised and refined, or with `guarded`
    (one trajectory, not vmapped) plainly where it is safely positive definite
    (`solvers.guarded_spd_solve`)."""
    constraints = system.constraints
    solve = spd_solve if system.is_pinned_chain else guarded_spd_solve if guarded else regularised_spd_solve
    inverse = system.schur_inverse
    forces = _node_forces_fn(system)
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
        rhs = jnp.sum(u * (take_rows(accel_free, i) - take_rows(accel_free, j)), -1) + constraints.link_speed_terms(qd)
        minv_at = jnp.einsum("ndke,ke->ndk", jnp.asarray(inverse_at_links, dtype), u)
        schur = jnp.einsum("ke,kel->kl", u, take_rows(minv_at, i) - take_rows(minv_at, j))
        lam = solve(schur, rhs)
        return accel_free - jnp.einsum("ndk,k->nd", minv_at, lam)

    return accel


def _chain_acceleration_fn(system: System) -> AccelerationFn:
    """The "chain" solver of `true_acceleration_fn`: the constant-mass equations of a
    chain pinned at node 0 (2D or 3D) by `solvers.chain_kkt_solve`, in time linear in its
    length. A pinned chain's constraint rows are always independent (every link is
    kept, in order), so no regularisation is needed."""
    constraints = system.constraints
    diagonal_mass, upper_mass = system.chain_mass_blocks
    forces = _node_forces_fn(system)

    def accel(q, qd):
        dtype = q.dtype
        # Link rows: `A a = -Adot v`.
        accel_nodes = chain_kkt_solve(jnp.asarray(diagonal_mass, dtype), jnp.asarray(upper_mass, dtype), constraints.link_directions(q),
                                      forces(q, qd)[1:], -constraints.link_speed_terms(qd))
        return jnp.concatenate([jnp.zeros((1, accel_nodes.shape[1]), dtype), accel_nodes])

    return accel
