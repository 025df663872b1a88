"""Linear solves of the constrained equations, all refined by one routine, `refine`.

Contract: pure JAX functions of arrays (no scene, no jit). None uses a pseudo-inverse:
each factors a *regularised* matrix, which stays nonsingular at singular configurations,
and `refine`s the solution against the exact system, which recovers the exact solution
(to round-off) wherever that exists and bounds it where it does not.

- `solve_kkt`: the dense saddle-point system `[[M, A^T], [A, 0]] [a; lam] = [f; r]`
  by LU, `M` equilibrated by its mean diagonal and `-eps I` in the lower block. Nonsingular whenever `A` has full row rank and
  `M` is positive definite on the null space of `A`, so a singular rod mass matrix
  is no obstacle.
- `regularised_spd_solve`: a symmetric positive semidefinite system (a Schur complement
  `A M^-1 A^T`) by Cholesky with `+eps I`; `spd_solve` without either where the
  system is positive definite at every configuration (a pinned chain's), small ones
  by Gauss-Jordan elimination.
- `chain_kkt_solve`: the KKT system of a chain pinned at node 0 (2D or 3D) in time
  linear in its length: block-tridiagonal elimination from the free end (`chain_sweeps`,
  on a CPU and for large batches) or by cyclic reduction (`cyclic_reduction`,
  log-depth, on an accelerator): `chain_elimination`.
- `LinkGram`: `A A^T` from its per-link sparsity (tridiagonal on chains, tridiagonal
  with a small dense border on T1), for the projection's Gauss-Newton steps.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import functools
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from lgnn import sharding
from lgnn.physics.constraints import Constraints, add_rows, take_rows

Array = jax.Array

# Regularisation of the solves, relative to the scale of the multipliers' system, and
# refinement steps. Every solve regularises in units it is invariant to, so that a
# Lagrangian scaled by any factor (it is defined only up to one; a learned one is
# ~1/10 of the true scale) gets the same dynamics (tests/test_physics.py): the Schur
# complement `S` by `eps = KKT_REGULARISATION * trace(S)/K`; the KKT system after
# equilibrating `M` by its mean diagonal `s` (`solve_kkt`), a compliance
# `eps = KKT_REGULARISATION / s` in the constraint rows (unit vectors, so
# `A M^-1 A^T ~ 1/s`). Three refinement steps reach round-off on every built-in scene
# (the contraction per step is ~eps / sigma_min(A M^-1 A^T)). At singular
# configurations it bounds the multipliers like a very stiff rod, and there the motion
# depends on it: 3e-10 is about what the exact T2 and T3 had when eps was `1e-9 s`
# (2.7e-10 and 2.8e-10 in these units; their 0.1 s references move by 1.3e-6 and
# 6e-5, T3's error in dt being ~1.5e-3), while from 2.5e-10 down T2's reference
# becomes non-finite within 0.003 s and 1e-9 moves T3 by 1.3e-3 (issue 13).
KKT_REGULARISATION = 3e-10
KKT_REFINEMENT_STEPS = 3
# Systems up to this size are factored by a Cholesky factorisation written out entry by
# entry (`cholesky_solve_fn`), which XLA fuses into a few elementwise kernels, instead of
# LAPACK's potrf and potrs, each a custom call whose fixed cost on a CPU exceeds a tiny
# system's arithmetic; and tridiagonal systems up to this size run their sweeps unrolled
# (`spd_tridiagonal_solve`), without a loop's per-iteration cost. Measured on the 2-core
# CPU, one trajectory's RK4 step (`tools/cpu_vs_mujoco.py`): chain4 6.7 us with LAPACK
# and loops, 5.4 us written out; sweeps unrolled up to 8 took chain8 from 10.3 to 11.6
# us, and Cholesky factorisations written out up to 16 took chain16 from about 16 to 90
# us (that code grows as the cube of the size).
UNROLLED_MAX = 4
# `spd_solve` of systems up to this size eliminates by Gauss-Jordan, one whole-matrix
# update per pivot (`gauss_jordan_solve`): a fused kernel each, about 0.3 us on the
# 2-core CPU, against LAPACK's three calls (factorisation, two triangular solves) at
# about 1.75 us together for a 12 x 12 system. One trajectory's RK4 step
# (`results/cpu_vs_mujoco.md`): chain4 5.97 us written out as above, 4.25 eliminated;
# chain4-3d 6.08 and 4.68; chain8 11.2 with LAPACK, 9.57 eliminated. Eliminating 12
# and 16 rows instead made chain12's step 14.4 -> 21.2 us and chain16's 16.2 -> 22.7.
ELIMINATED_MAX = 8
# On a GPU a `lax.scan` is a loop whose every iteration runs a few tiny kernels and reads
# its predicate back to the host, so the sweeps along a long chain cost the loop, not
# their arithmetic, at the batch sizes of an evaluation: a chain100 RK4 step x 100 states
# ran 18 700 kernels averaging 1 us. Unrolled by this factor, a loop trip runs this many
# rows, and XLA fuses their kernels. Measured on one H200, 100 RK4 steps of chain100
# x 100 states (results/gpu/sweeps/): LGNN 3.3-3.5 s to 0.78-0.87 s, the ground truth
# 1.4-2.0 s to 0.37-0.40 s, compilation 10 s to 31 s and 2.5 s to 16 s; unrolled
# whole (100), 0.59-0.79 s and 0.25-0.38 s, compiled in 123 s and 79 s. On a CPU a
# loop iteration costs little and unrolling only lengthens the code: chain100's
# single-trajectory RK4 step on the 2-core CPU took 275-321 us with the loops, 379-386
# us unrolled by 5 and 507-528 us by 10 (`tools/cpu_vs_mujoco.py --scene chain100`,
# two alternated runs of each). Not unrolled there.
ACCELERATOR_SWEEP_UNROLL = 10


# How `chain_kkt_solve` eliminates on an accelerator: "sweeps" (n dependent rows,
# unrolled by `ACCELERATOR_SWEEP_UNROLL`) or "cyclic" (`cyclic_reduction`: 2 log2 n
# rounds of whole-array block work). Measured on one H200, 100 RK4 steps x 100 states
# (results/gpu/sweeps/, last section), sweeps -> cyclic: chain100 LGNN 0.73 -> 0.28 s,
# ground truth 0.32 -> 0.14 s; chain100-3d 0.95 -> 0.33 s and 0.44 -> 0.15 s; each
# compiled in less time, the trajectories the same to every printed digit. A CPU always
# sweeps: there a loop trip costs little, and cyclic reduction's extra arithmetic made
# chain100 x 16 states 1.06 -> 1.38 s (LGNN) and 0.07 -> 0.25 s (ground truth).
ACCELERATOR_CHAIN_ELIMINATION = "cyclic"
# Cyclic reduction's doubled arithmetic wins while a sweep's row leaves the device idle,
# that is, while few systems are solved at once. The float32 ground truth's steps/s on
# one H200, sweeps / cyclic (results/gpu/truth/, `chain_elimination_ab.py`), chain16,
# chain100 and chain100-3d: at 1 024 systems 0.59, 0.42, 0.42; at 8 192 0.80, 0.76,
# 0.64; at 16 384 1.04, 0.96, 0.80; at 32 768 1.10, 1.16, 1.17; at 65 536 1.25, 1.53,
# 1.32 (chain4: 0.94-0.99 up to 8 192). Above this many systems per device the sweeps
# are taken.
CYCLIC_MAX_SYSTEMS = 16384
_SYSTEMS_AT_ONCE: contextvars.ContextVar[int | None] = contextvars.ContextVar("systems_at_once", default=None)


@contextlib.contextmanager
def systems_at_once(count: int | None):
    """Trace the solves inside the block as `count` systems solved at once on each
    device: the batch that a `vmap`ped solve cannot see, for `chain_elimination`'s
    choice (None: not known, as outside the block)."""
    token = _SYSTEMS_AT_ONCE.set(count)
    try:
        yield
    finally:
        _SYSTEMS_AT_ONCE.reset(token)


def chain_elimination() -> str:
    """How `chain_kkt_solve` eliminates on the platform the trace computes on
    (`lgnn.sharding.platform`): "sweeps" on a CPU; on an accelerator
    `ACCELERATOR_CHAIN_ELIMINATION`, or the sweeps where more than `CYCLIC_MAX_SYSTEMS`
    systems are solved at once per device (`systems_at_once`)."""
    if sharding.platform() == "cpu":
        return "sweeps"
    count = _SYSTEMS_AT_ONCE.get()
    return "sweeps" if count is not None and count > CYCLIC_MAX_SYSTEMS else ACCELERATOR_CHAIN_ELIMINATION


def sweep_unroll() -> int:
    """How far `lax.scan` unrolls a sweep along a chain: by `ACCELERATOR_SWEEP_UNROLL`
    on an accelerator, not on a CPU (the platform the trace computes on,
    `lgnn.sharding.platform`)."""
    return 1 if sharding.platform() == "cpu" else ACCELERATOR_SWEEP_UNROLL


def refine(solve: Callable[[Array], Array], residual: Callable[[Array], Array], x: Array, steps: int) -> Array:
    """Iterative refinement: `steps` times `x <- x + solve(residual(x))`.

    `residual(x)` is what the exact equations leave at `x` (`r - K x` for `K x = r`),
    `solve` an approximate inverse of `K` that is cheap to apply again (a factorisation
    of a regularised `K`). Each step multiplies the error by `I - solve K`, whose size
    is ~eps / (the smallest scale of `K`), so a few steps reach round-off at regular
    configurations; at singular ones the iterate stays bounded. The loop is unrolled
    (`steps` is static and small).
    """
    for _ in range(steps):
        x = x + solve(residual(x))
    return x


def solve_kkt(mass: Array, jac: Array, force: Array, accel_rhs: Array) -> Array:
    """Solve `[[M, A^T], [A, 0]] [a; lam] = [force; accel_rhs]` for `a` (F,): LU of the
    regularised matrix (`-eps I` in the lower block), refined against the exact one.
    `mass` (F, F), `jac` (K, F), `force` (F,), `accel_rhs` (K,).

    The system is first equilibrated by the mass scale `s = trace(M)/F`: `[[M/s, A^T],
    [A, 0]] [a; lam/s] = [force/s; accel_rhs]` has the same accelerations, and neither
    it nor its regularisation (`KKT_REGULARISATION` in these units) changes when the
    Lagrangian, hence `M`, `force` and `lam`, is multiplied by a constant."""
    n, k = mass.shape[0], jac.shape[0]
    if k == 0:
        return jnp.linalg.solve(mass, force)
    scale = jnp.trace(mass) / n
    zeros = jnp.zeros((k, k), mass.dtype)
    kkt = jnp.block([[mass / scale, jac.T], [jac, zeros]])
    regularised = kkt.at[n:, n:].set(-KKT_REGULARISATION * jnp.eye(k, dtype=mass.dtype))
    factors = jax.lax.stop_gradient(jax.scipy.linalg.lu_factor(regularised))
    rhs = jnp.concatenate([force / scale, accel_rhs])

    def refined_solve(transposed: bool):
        def solve_with(product, b):  # `product`: the exact system's (or its transpose's)
            solve = functools.partial(jax.scipy.linalg.lu_solve, factors, trans=int(transposed))
            return refine(solve, lambda solution: b - product(solution), solve(b), KKT_REFINEMENT_STEPS)

        return solve_with

    # Derivatives by the implicit function theorem (`custom_linear_solve`): a tangent
    # or cotangent is one more refined solve with the same factors (transposed for a
    # cotangent), not the derivative of the factorisation and of every refinement step.
    # The same derivatives to round-off, of any order, with fewer operations
    # (tests/test_physics.py; `results/gpu/training/README.md` for what it saves).
    return jax.lax.custom_linear_solve(lambda solution: kkt @ solution, rhs, refined_solve(False), transpose_solve=refined_solve(True))[:n]


def tangent_basis(jac: Array) -> tuple[Array, Array, Array]:
    """`(range_basis (F, K), upper (K, K), null_basis (F, F - K))` of a Jacobian `jac`
    (K, F) of full row rank: the complete QR `jac^T = [range_basis, null_basis] [upper;
    0]`, so `null_basis` spans the motions that keep the constraints and both bases are
    orthonormal. By K Householder reflections written out one after another (K is
    static and small where it is used), each a few elementwise products and sums that
    fuse with their neighbours, where a QR is library calls of its own."""
    k, n = jac.shape
    reduced, reflected = jac.T, jnp.eye(n, dtype=jac.dtype)  # H_k ... H_1 jac^T and H_k ... H_1
    for column in range(k):
        head = reduced[column:, column]
        norm = jnp.sqrt(jnp.sum(head * head))
        # The reflection's vector, signed away from cancellation.
        vector = head.at[0].add(jnp.where(head[0] >= 0, norm, -norm))
        vector = vector / jnp.sqrt(jnp.sum(vector * vector))
        reduced = reduced.at[column:].add(-2 * vector[:, None] * jnp.sum(vector[:, None] * reduced[column:], 0))
        reflected = reflected.at[column:].add(-2 * vector[:, None] * jnp.sum(vector[:, None] * reflected[column:], 0))
    return reflected[:k].T, reduced[:k], reflected[k:].T


def cholesky_solve_fn(matrix: Array) -> tuple[Callable[[Array], Array], Array]:
    """`(solve, pivots)` of a symmetric positive definite `matrix` (K, K): `r -> matrix^-1 r`
    for `r` (K,) or (K, R), by a Cholesky factorisation made once, and the factor's
    diagonal. Up to `UNROLLED_MAX` rows the factorisation and the two triangular solves
    are written out entry by entry (the Cholesky-Banachiewicz order); larger systems go
    to LAPACK (`jax.scipy.linalg.cho_factor`). Not positive definite: NaN, as LAPACK's."""
    k = matrix.shape[0]
    if k > UNROLLED_MAX:
        factor = jax.scipy.linalg.cho_factor(matrix)
        return functools.partial(jax.scipy.linalg.cho_solve, factor), jnp.diagonal(factor[0])
    def minus(value: Array, terms: list[Array]) -> Array:
        return functools.reduce(lambda total, term: total - term, terms, value)

    lower: list[list[Array]] = []
    for i in range(k):
        row: list[Array] = []
        for j in range(i + 1):
            partial = minus(matrix[i, j], [row[p] * (row if j == i else lower[j])[p] for p in range(j)])
            row.append(jnp.sqrt(partial) if j == i else partial / lower[j][j])
        lower.append(row)

    def solve(rhs: Array) -> Array:
        forward: list[Array] = []
        for i in range(k):
            forward.append(minus(rhs[i], [lower[i][p] * forward[p] for p in range(i)]) / lower[i][i])
        backward: list[Array] = list(forward)
        for i in reversed(range(k)):
            backward[i] = minus(forward[i], [lower[p][i] * backward[p] for p in range(i + 1, k)]) / lower[i][i]
        return jnp.stack(backward)

    return solve, jnp.stack([lower[i][i] for i in range(k)])


def regularised_spd_solve(matrix: Array, rhs: Array) -> Array:
    """Cholesky solve of `(S + eps I) x = r`, refined against `S x = r`: exact at regular
    configurations, bounded near singular ones (as `solve_kkt`). `eps` is relative to
    `trace(S)/K`, so `c S` gives `x / c` for any c (scale-free). `matrix` (K, K)."""
    k = matrix.shape[0]
    eps = KKT_REGULARISATION * jnp.trace(matrix) / k
    solve, _ = cholesky_solve_fn(matrix + eps * jnp.eye(k, dtype=matrix.dtype))
    return refine(solve, lambda solution: rhs - matrix @ solution, solve(rhs), KKT_REFINEMENT_STEPS)


# `guarded_spd_solve` solves plainly while the Cholesky factor's smallest pivot squared is
# at least this fraction of its largest (about 1 / the matrix's condition number): a
# plain solve then errs by ~cond x eps <= ~1e-12 of the solution. Measured over 20
# sampled states of each: T1's Schur complement stays above (worst 0.015, cond 1.8e4),
# the slack trusses' fall below (T2-slack 7e-4, T3-slack 1.7e-4) and keep the
# regularised, refined solve.
SPD_PIVOT_RATIO = 1e-3


def guarded_spd_solve(matrix: Array, rhs: Array) -> Array:
    """`spd_solve` where `matrix` (K, K) is safely positive definite (`SPD_PIVOT_RATIO`),
    else `regularised_spd_solve`: for a scene regular at its start whose rows could
    still become dependent in its motion (a rope pulled straight). One trajectory pays
    one Cholesky factorisation at regular configurations instead of the refined four
    solves (T1 on a CPU: 96-100 us a step against 128-134); under `vmap` both branches
    run, so batched callers use `regularised_spd_solve` (`true_acceleration_fn`'s
    `vectorised`), as do accelerators (a branch reads its predicate back to the host)."""
    solve, pivots = cholesky_solve_fn(matrix)
    plain = jnp.all(jnp.isfinite(pivots)) & (jnp.min(pivots) ** 2 >= SPD_PIVOT_RATIO * jnp.max(pivots) ** 2)
    return jax.lax.cond(plain, lambda: solve(rhs), lambda: regularised_spd_solve(matrix, rhs))


def spd_solve(matrix: Array, rhs: Array) -> Array:
    """Solve `S x = r` for an `S` (K, K) known to be positive definite at every
    configuration (a pinned chain's Schur complement: its rows are always independent),
    with neither regulariser nor refinement: `regularised_spd_solve` refines back to
    this same solution (to round-off) at three more pairs of triangular solves, most of
    a small scene's acceleration (chain12 on a CPU). By Gauss-Jordan elimination up to
    `ELIMINATED_MAX` rows, else by a Cholesky factorisation."""
    if matrix.shape[0] <= ELIMINATED_MAX:
        return gauss_jordan_solve(matrix, rhs)
    return cholesky_solve_fn(matrix)[0](rhs)


def gauss_jordan_solve(matrix: Array, rhs: Array) -> Array:
    """`matrix^-1 rhs` for a positive definite `matrix` (K, K) and `rhs` (K,) or (K, R)
    by Gauss-Jordan elimination without pivoting, which a positive definite matrix
    never needs (its pivots are the squares of its Cholesky factor's diagonal): K
    updates of the whole augmented matrix, each one fused kernel, unrolled."""
    k = matrix.shape[0]
    augmented = jnp.concatenate([matrix, rhs.reshape(k, -1)], 1)
    identity = jnp.eye(k, dtype=matrix.dtype)
    for pivot in range(k):
        # Row `pivot` divided by its pivot; that multiple of it taken from every other row.
        scaled = augmented[pivot] / augmented[pivot, pivot]
        augmented = augmented - jnp.outer(augmented[:, pivot] - identity[:, pivot], scaled)
    return augmented[:, k:].reshape(rhs.shape)


def block_product(a: Array, b: Array) -> Array:
    """`a @ b` for small blocks `a` (..., R, K) and `b` (..., K, C) or (..., K), the
    leading axes alike, as K elementwise multiply-adds in order k = 0, 1, ...: no dot,
    so on an accelerator one row of a sweep along a chain, products and the adjugate
    inverse, fuses into a few elementwise kernels where a dot is a kernel of its own
    (`chain_kkt_solve`)."""
    columns = b if b.ndim == a.ndim else b[..., None]
    product = a[..., :, :1] * columns[..., :1, :]
    for k in range(1, a.shape[-1]):
        product = product + a[..., :, k:k + 1] * columns[..., k:k + 1, :]
    return product if b.ndim == a.ndim else product[..., 0]


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


def _inverse_4x4(m: Array) -> Array:
    """Inverse of a (4, 4) matrix by its adjugate, from the 2 x 2 minors of its top and
    bottom row pairs (Laplace expansion): the spatial chain's blocks, for the reason of
    `_inverse_3x3` (LU per block made the 3D chain elimination ~2.5x slower than the
    Schur solve at 100 links)."""
    (a00, a01, a02, a03), (a10, a11, a12, a13), (a20, a21, a22, a23), (a30, a31, a32, a33) = m
    s0, s1, s2 = a00 * a11 - a10 * a01, a00 * a12 - a10 * a02, a00 * a13 - a10 * a03
    s3, s4, s5 = a01 * a12 - a11 * a02, a01 * a13 - a11 * a03, a02 * a13 - a12 * a03
    c5, c4, c3 = a22 * a33 - a32 * a23, a21 * a33 - a31 * a23, a21 * a32 - a31 * a22
    c2, c1, c0 = a20 * a33 - a30 * a23, a20 * a32 - a30 * a22, a20 * a31 - a30 * a21
    adjugate = jnp.array([
        [a11 * c5 - a12 * c4 + a13 * c3, -a01 * c5 + a02 * c4 - a03 * c3, a31 * s5 - a32 * s4 + a33 * s3, -a21 * s5 + a22 * s4 - a23 * s3],
        [-a10 * c5 + a12 * c2 - a13 * c1, a00 * c5 - a02 * c2 + a03 * c1, -a30 * s5 + a32 * s2 - a33 * s1, a20 * s5 - a22 * s2 + a23 * s1],
        [a10 * c4 - a11 * c2 + a13 * c0, -a00 * c4 + a01 * c2 - a03 * c0, a30 * s4 - a31 * s2 + a33 * s0, -a20 * s4 + a21 * s2 - a23 * s0],
        [-a10 * c3 + a11 * c1 - a12 * c0, a00 * c3 - a01 * c1 + a02 * c0, -a30 * s3 + a31 * s1 - a32 * s0, a20 * s3 - a21 * s1 + a22 * s0],
    ])
    return adjugate / (s0 * c5 - s1 * c4 + s2 * c3 + s3 * c2 - s4 * c1 + s5 * c0)


def chain_kkt_solve(diagonal_mass: Array, upper_mass: Array, u: Array, node_rhs: Array, link_rhs: Array, *,
                    regularised: bool = False, cyclic: bool | None = None) -> Array:
    """Solve the KKT system of a chain pinned at node 0 in time linear in n, in D = 2 or 3.

    Block b (b = 0..n-1) holds node b+1's acceleration and link b's multiplier. Link b
    joins nodes b and b+1 (row `+u_b` at node b, `-u_b` at node b+1; `u` (n, D)) and the
    mass matrix couples only neighbouring nodes (`diagonal_mass` (n, D, D) for nodes
    1..n, `upper_mass` (n-1, D, D) node b with b+1), so the KKT matrix is
    block-tridiagonal with (D+1) x (D+1) blocks: diagonal `D_b = [[M_b+1,b+1, -u_b], [-u_b^T,
    -eps]]`, above it `U_b = [[M_b+1,b+2, u_b+1], [0, 0]]`. Eliminating from the free
    end (`D~_b = D_b - U_b D~_b+1^-1 U_b^T`, the articulated inertia of the chain beyond
    node b+1) and substituting back from the pin are two `lax.scan`s. As in
    `solve_kkt`, the mass blocks and node forces are equilibrated by the mass scale (the
    mean diagonal of M), so the solve is the same for any multiple of the Lagrangian;
    `regularised` sets `eps = KKT_REGULARISATION` in these units and refines against
    the exact (`eps = 0`) system with `KKT_REFINEMENT_STEPS` steps, each costing two
    more scans; without it `eps = 0` (a pinned chain's rows are independent).
    `cyclic`: the same system factored by cyclic reduction (`cyclic_reduction`) instead
    of the sweeps (None: `chain_elimination`'s choice for the platform).
    `node_rhs` (n, D), `link_rhs` (n,). Returns the node accelerations (n, D).
    """
    (n, d), dtype = u.shape, u.dtype
    inverse_block = {2: _inverse_3x3, 3: _inverse_4x4}[d]
    scale = jnp.trace(diagonal_mass, axis1=1, axis2=2).mean() / d
    diagonal_mass, upper_mass, node_rhs = diagonal_mass / scale, upper_mass / scale, node_rhs / scale
    eps = KKT_REGULARISATION if regularised else 0.0

    def blocks(eps_value):
        diagonal = jnp.zeros((n, d + 1, d + 1), dtype).at[:, :d, :d].set(diagonal_mass).at[:, :d, d].set(-u).at[:, d, :d].set(-u)
        return diagonal.at[:, d, d].set(-eps_value)

    upper = jnp.zeros((n - 1, d + 1, d + 1), dtype).at[:, :d, :d].set(upper_mass).at[:, :d, d].set(u[1:])
    diagonal = blocks(eps)
    rhs = jnp.concatenate([node_rhs, link_rhs[:, None]], axis=1)

    solution, solve = eliminate_chain(diagonal, upper, rhs, inverse_block, cyclic)

    if not regularised:
        return solution[:, :d]
    exact = blocks(0.0)
    return refine(solve, lambda y: rhs - block_tridiagonal_product(exact, upper, y), solution, KKT_REFINEMENT_STEPS)[:, :d]


def banded_chain_kkt_solve(band_mass: Array, u: Array, node_rhs: Array, link_rhs: Array, *, regularised: bool = False,
                           cyclic: bool | None = None, low_rank: tuple[Array, Array] | None = None) -> Array:
    """`chain_kkt_solve` for a mass matrix that couples nodes up to r links apart:
    `band_mass` (n, r+1, D, D), block k of row b coupling node b+1 with node b+1+k (zero
    past the chain's end); `u`, `node_rhs`, `link_rhs` and the result as there.

    Over the (D+1)-blocks of `chain_kkt_solve` (node b+1's acceleration, link b's
    multiplier) the KKT matrix is block-banded with r blocks on each side, so groups of
    r consecutive blocks make it block-tridiagonal with r (D+1)-square blocks (padded
    with identity blocks to whole groups). That system is eliminated as the chain's
    (`chain_sweeps` or `cyclic_reduction`, the groups' blocks inverted by LU),
    equilibrated by the mass scale, regularised and refined as in `chain_kkt_solve`.
    The groups' pivots are Schur complements on whole groups, each link's row beside its
    own node: nonsingular for a positive definite mass, as the chain's are.

    `low_rank = (factor (n, D, P), core (P, P))` adds `factor core factor^T` to the
    mass (LGN's pooled read-out: the features' Jacobian and the read-out's curvature,
    `physics.euler_lagrange`). It is solved by the Woodbury identity on top of the
    banded elimination, P more solves with its factorisation and a P-square LU, and
    refined against the whole system, so the mass is never assembled (a dense KKT LU
    costs O((F + K)^3)). The banded part must itself be regular: a learned mass can be
    indefinite, and where the banded part alone is near-singular the refinement
    (against the exact system) is what recovers the accuracy."""
    n, width, d = band_mass.shape[0], band_mass.shape[1], u.shape[1]
    reach, e, dtype = width - 1, d + 1, u.dtype
    groups = -(-n // reach)
    size, side = groups * reach, reach * e
    trace = jnp.trace(band_mass[:, 0], axis1=1, axis2=2).sum()
    if low_rank is not None:
        factor, core = low_rank
        # Equilibrated by the whole mass's mean diagonal, as `solve_kkt` does.
        flat = factor.reshape(n * d, -1)
        trace = trace + jnp.sum(core * (flat.T @ flat))
    scale = trace / (n * d)
    band_mass, node_rhs = band_mass / scale, node_rhs / scale
    eps = KKT_REGULARISATION if regularised else 0.0

    def couplings(eps_value):
        # (size, r+1, D+1, D+1): block a of the KKT matrix with block a+k.
        c = jnp.zeros((size, width, e, e), dtype).at[:n, :, :d, :d].set(band_mass)
        c = c.at[:n, 0, :d, d].set(-u).at[:n, 0, d, :d].set(-u).at[:n, 0, d, d].set(-eps_value)
        c = c.at[:n - 1, 1, :d, d].set(u[1:])
        return c.at[n:, 0].set(jnp.eye(e, dtype=dtype))

    # Static maps from the couplings to the groups' blocks: within group g, block (i, j)
    # is coupling (g r + min(i, j), |j - i|), transposed below the diagonal; from group
    # g to g+1, block (i, j) is coupling (g r + i, r + j - i) where j <= i, else zero.
    g, i, j = np.meshgrid(np.arange(groups), np.arange(reach), np.arange(reach), indexing="ij")
    within_source, within_offset, below = g * reach + np.minimum(i, j), np.abs(j - i), j < i
    across_source, across_offset, across = (g * reach + i)[:-1], np.minimum(reach + j - i, reach)[:-1], (j <= i)[:-1]

    def grouped(blocks):
        # (G, r, r, D+1, D+1) -> (G, r (D+1), r (D+1)).
        return jnp.swapaxes(blocks, 2, 3).reshape(blocks.shape[0], side, side)

    def tridiagonal(c):
        inside = c[within_source, within_offset]
        inside = jnp.where(below[..., None, None], jnp.swapaxes(inside, -1, -2), inside)
        return grouped(inside), grouped(jnp.where(across[..., None, None], c[across_source, across_offset], 0.0))

    diagonal, upper = tridiagonal(couplings(eps))
    rhs = jnp.zeros((size, e), dtype).at[:n, :d].set(node_rhs).at[:n, d].set(link_rhs).reshape(groups, side)
    solution, banded_solve = eliminate_chain(diagonal, upper, rhs, jnp.linalg.inv, cyclic)
    solve, low_rank_product = banded_solve, None
    if low_rank is not None:
        # The factor in the KKT layout (zero in the links' rows), (G, r (D+1), P).
        border = jnp.zeros((size, e, factor.shape[-1]), dtype).at[:n, :d].set(factor).reshape(groups, side, -1)
        correct, low_rank_product = woodbury(banded_solve, border, core / scale)
        # The banded solution the elimination already gave, corrected: no second solve.
        solution = correct(solution)

        def solve(r):
            return correct(banded_solve(r))

    if regularised:
        exact, _ = tridiagonal(couplings(0.0))

        def residual(y):
            r = rhs - block_tridiagonal_product(exact, upper, y)
            return r if low_rank_product is None else r - low_rank_product(y)

        solution = refine(solve, residual, solution, KKT_REFINEMENT_STEPS)
    return solution.reshape(size, e)[:n, :d]


def woodbury(solve: Callable[[Array], Array], border: Array, core: Array) -> tuple[Callable[[Array], Array], Callable[[Array], Array]]:
    """`(correct, product)` for the system `K + B C B^T`, from `solve` (`r -> K^-1 r`, `r`
    of `border`'s leading shape), `border` `B` (..., P) and `core` `C` (P, P):
    `product(y) = B C B^T y` and, by the Woodbury identity, `correct(K^-1 r) = (K + B C
    B^T)^-1 r`, that is `correct(y) = y - K^-1 B (I + C B^T K^-1 B)^-1 C B^T y`: P
    solves by `solve` once and a P-square LU here, no solve per call (a caller that
    already holds `K^-1 r` pays none). `C` is never inverted, so it may be singular or
    indefinite; `I + C B^T K^-1 B` is regular exactly where `K + B C B^T` is (given
    `K`)."""
    axes = tuple(range(border.ndim - 1))

    def transposed_product(y):
        return jnp.tensordot(border, y, axes=(axes, axes))

    columns = jax.vmap(solve, in_axes=-1, out_axes=-1)(border)
    capacitance = jax.scipy.linalg.lu_factor(jnp.eye(core.shape[0], dtype=core.dtype) + core @ jnp.tensordot(border, columns, axes=(axes, axes)))

    def correct(y):
        return y - columns @ jax.scipy.linalg.lu_solve(capacitance, core @ transposed_product(y))

    return correct, lambda y: border @ (core @ transposed_product(y))


def block_tridiagonal_product(diagonal: Array, upper: Array, x: Array) -> Array:
    """`K x` for the symmetric block-tridiagonal `K` of `cyclic_reduction`'s arguments
    and `x` (n, R): `D_b x_b + U_b x_b+1 + U_b-1^T x_b-1`, the residual of the chain
    solves' refinement."""
    product = jnp.einsum("bij,bj->bi", diagonal, x)
    product = product.at[:-1].add(jnp.einsum("bij,bj->bi", upper, x[1:]))
    return product.at[1:].add(jnp.einsum("bji,bj->bi", upper, x[:-1]))


def eliminate_chain(diagonal: Array, upper: Array, rhs: Array, inverse_block: Callable[[Array], Array],
                    cyclic: bool | None) -> tuple[Array, Callable[[Array], Array]]:
    """`(solution, solve)` of a symmetric block-tridiagonal system (`cyclic_reduction`'s
    arguments) for `rhs`: by cyclic reduction where `cyclic`, else by `chain_sweeps`
    (None: `chain_elimination`'s choice); `solve` reuses the factorisation."""
    if cyclic if cyclic is not None else chain_elimination() == "cyclic":
        factored = cyclic_reduction(diagonal, upper, inverse_block)
        return factored.solve(rhs), factored.solve
    return chain_sweeps(diagonal, upper, rhs, inverse_block)


def chain_sweeps(diagonal: Array, upper: Array, rhs: Array, inverse_block: Callable[[Array], Array]) -> tuple[Array, Callable[[Array], Array]]:
    """`(solution, solve)`: the symmetric block-tridiagonal system of `cyclic_reduction`'s
    arguments solved for `rhs` (n, R) by two sweeps along the chain, `lax.scan`s
    unrolled by `sweep_unroll`: elimination from the last block (`D~_b = D_b - U_b
    D~_b+1^-1 U_b^T`), which also reduces `rhs`, then substitution back from the first.
    `solve(rhs)` solves again with the same factorisation, two sweeps."""
    unroll = sweep_unroll()

    def eliminate(carry, block):
        next_inverse, next_reduced = carry
        block_diagonal, block_upper, block_rhs = block
        weight = block_product(block_upper, next_inverse)
        inverse = inverse_block(block_diagonal - block_product(weight, block_upper.T))
        reduced = block_rhs - block_product(weight, next_reduced)
        return (inverse, reduced), (inverse, weight, reduced)

    def reduce(next_reduced, block):
        block_weight, block_rhs = block
        reduced = block_rhs - block_product(block_weight, next_reduced)
        return reduced, reduced

    def substitute(previous, block):
        inverse, reduced, block_upper = block
        solution = block_product(inverse, reduced - block_product(block_upper.T, previous))
        return solution, solution

    def back_substitute(inverses, reduced):
        first = block_product(inverses[0], reduced[0])
        _, rest = jax.lax.scan(substitute, first, (inverses[1:], reduced[1:], upper), unroll=unroll)
        return jnp.concatenate([first[None], rest])

    # The factorisation and the first solve share one elimination pass.
    last_inverse = inverse_block(diagonal[-1])
    _, (inverses, weights, reduced) = jax.lax.scan(eliminate, (last_inverse, rhs[-1]), (diagonal[:-1], upper, rhs[:-1]), reverse=True, unroll=unroll)
    inverses = jnp.concatenate([inverses, last_inverse[None]])

    def solve(residual):
        _, reduced = jax.lax.scan(reduce, residual[-1], (weights, residual[:-1]), reverse=True, unroll=unroll)
        return back_substitute(inverses, jnp.concatenate([reduced, residual[-1:]]))

    return back_substitute(inverses, jnp.concatenate([reduced, rhs[-1:]])), solve


class ReductionLevel(NamedTuple):
    """One level of `cyclic_reduction`: its odd blocks' `inverse`s, their couplings to
    the even blocks before and after them (`lower`, `upper`), and the weights that carry
    the odd rows into the even ones (`left`, `right`), each (B, R, R)."""

    inverse: Array
    lower: Array
    upper: Array
    left: Array
    right: Array


@dataclasses.dataclass(frozen=True)
class CyclicReduction:
    """A block-tridiagonal system of `size` blocks factored by cyclic reduction
    (`cyclic_reduction`): its `levels` from the whole (padded) system down, and `last`,
    the inverse of the one block left at the bottom. `solve(rhs)` applies it."""

    levels: tuple[ReductionLevel, ...]
    last: Array
    size: int

    def solve(self, rhs: Array) -> Array:
        """The solution (n, R) of the factored system for `rhs` (n, R)."""
        reduced = jnp.zeros((2 ** len(self.levels),) + rhs.shape[1:], rhs.dtype).at[:self.size].set(rhs)
        odd_rows = []
        for level in self.levels:
            even, odd = reduced[0::2], reduced[1::2]
            odd_rows.append(odd)
            # Even block 2k's neighbours are odd blocks k-1 (none before block 0, whose `left` is 0) and k.
            reduced = even - block_product(level.left, jnp.roll(odd, 1, axis=0)) - block_product(level.right, odd)
        solution = block_product(self.last, reduced[0])[None]
        for level, odd in zip(reversed(self.levels), reversed(odd_rows)):
            following = jnp.concatenate([solution[1:], jnp.zeros_like(solution[:1])])
            odd_solution = block_product(level.inverse, odd - block_product(level.lower, solution) - block_product(level.upper, following))
            solution = jnp.stack([solution, odd_solution], axis=1).reshape((-1,) + solution.shape[1:])
        return solution[:self.size]


def cyclic_reduction(diagonal: Array, upper: Array, inverse_block: Callable[[Array], Array]) -> CyclicReduction:
    """Factor the symmetric block-tridiagonal matrix of diagonal blocks `diagonal` (n,
    R, R) and blocks above them `upper` (n-1, R, R) (block b couples b to b+1; below
    the diagonal, their transposes) by cyclic reduction: the system, padded to a power
    of two with identity blocks, eliminates its odd blocks into the even ones, log2 n
    times. Each level is whole-array block work, so on an accelerator a solve is about
    2 log2 n rounds of elementwise kernels, where the sweeps of `chain_kkt_solve` are n
    dependent rows; the arithmetic is about twice the sweeps'. It inverts the odd
    blocks of each level (`inverse_block`, one (R, R) block), Schur complements of the
    matrix on sets of whole blocks: a chain's KKT matrix with a positive definite mass
    has them all nonsingular (each link's row has its own block's node)."""
    n, r = diagonal.shape[0], diagonal.shape[1]
    size = 2 ** max(0, (n - 1).bit_length())
    diag = jnp.concatenate([diagonal, jnp.broadcast_to(jnp.eye(r, dtype=diagonal.dtype), (size - n, r, r))])
    up = jnp.zeros((size, r, r), diagonal.dtype).at[:n - 1].set(upper)
    low = jnp.concatenate([jnp.zeros_like(up[:1]), jnp.swapaxes(up[:-1], 1, 2)])  # block b's coupling to b-1
    invert = jax.vmap(inverse_block)
    levels = []
    while len(diag) > 1:
        inverse = invert(diag[1::2])
        # Even block 2k's neighbours are odd blocks k-1 (rolled in; block 0 has no coupling before it) and k.
        left = block_product(low[0::2], jnp.roll(inverse, 1, axis=0))
        right = block_product(up[0::2], inverse)
        upper_before, lower_before = jnp.roll(up[1::2], 1, axis=0), jnp.roll(low[1::2], 1, axis=0)
        levels.append(ReductionLevel(inverse, low[1::2], up[1::2], left, right))
        diag = diag[0::2] - block_product(left, upper_before) - block_product(right, low[1::2])
        low, up = -block_product(left, lower_before), -block_product(right, up[1::2])
    return CyclicReduction(tuple(levels), inverse_block(diag[0]), n)


def spd_tridiagonal_solve(lower: Array, diag: Array, upper: Array, rhs: Array) -> Array:
    """Solve `T x = rhs` for a symmetric positive definite tridiagonal `T` (diagonal
    `diag` (K,), `lower[k] = T[k, k-1]`, `upper[k] = T[k, k+1]`, `lower[0]` and
    `upper[-1]` ignored as in `jax.lax.linalg.tridiagonal_solve`), `rhs` (K, R): an
    LDL^T sweep down and a substitution up, two `lax.scan`s of elementwise work. Stable
    without pivoting for SPD `T`, and under `vmap` the work vectorises over the batch,
    where LAPACK's `gtsv` (the lax primitive on CPU) runs one system at a time: ~1.7x
    faster on T1's Gram matrix x 100 states. On a GPU the scans cost nothing measurable
    against cuSPARSE's `gtsv` and the dense Cholesky they replace (one H100, `lgnn
    gpu-truth`, 1024-65536 states, float32: T1 4.47e5 / 7.54e5 / 8.12e5 steps/s against
    4.45e5 / 7.54e5 / 8.08e5, chain100 equal to 3 digits; 2026-11-24)."""

    def sweep(carry, row):
        previous_pivot, previous_reduced, previous_upper = carry
        row_lower, row_diag, row_upper, row_rhs = row
        weight = row_lower / previous_pivot
        pivot = row_diag - weight * previous_upper
        reduced = row_rhs - weight * previous_reduced
        return (pivot, reduced, row_upper), (pivot, reduced)

    # Short systems unrolled whole (`UNROLLED_MAX`): a loop's iterations cost more than their rows.
    unroll = True if diag.shape[0] <= UNROLLED_MAX else sweep_unroll()
    first = (diag[0], rhs[0], upper[0])
    _, (pivots, reduced) = jax.lax.scan(sweep, first, (lower[1:], diag[1:], upper[1:], rhs[1:]), unroll=unroll)
    pivots, reduced = jnp.concatenate([diag[:1], pivots]), jnp.concatenate([rhs[:1], reduced])

    def substitute(following, row):
        pivot, row_reduced, row_upper = row
        solution = (row_reduced - row_upper * following) / pivot
        return solution, solution

    last = reduced[-1] / pivots[-1]
    _, rest = jax.lax.scan(substitute, last, (pivots[:-1, None], reduced[:-1], upper[:-1, None]), reverse=True, unroll=unroll)
    return jnp.concatenate([rest, last[None]])


# Kept links that share nodes with non-neighbouring links (a scene's loop-closing
# braces) are eliminated as a dense border of the otherwise tridiagonal Gram matrix
# (`LinkGram`) when there are at most this many; past that a dense Cholesky of the
# whole matrix is cheaper than the border's extra tridiagonal right-hand sides.
MAX_GRAM_BORDER = 8


class LinkGram:
    """The Gram matrix `G = A A^T` of the kept constraint rows, from its sparsity.

    `G_kl` is nonzero only when links k and l share a free node, where it is
    `+-u_k . u_l`; the diagonal counts each link's free ends. The pairs are found once
    per scene. A rail's node (free along one axis only) counts only its free
    coordinates in those products (`partial`). When only consecutive kept links share nodes (a chain) G is tridiagonal
    and solved in linear time. When that holds after setting aside a few `border` links
    (T1: a chain of ropes and three braces that close loops) G is solved by block
    elimination: the tridiagonal rest, then the small dense Schur complement of the
    border (`bordered`). Otherwise it is assembled dense and factored by Cholesky.
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
        pairs = [(a, b, sa * sb, node) for node, incident in by_node.items() for x, (a, sa) in enumerate(incident) for b, sb in incident[x + 1 :]]
        pairs = [(min(a, b), max(a, b), sign, node) for a, b, sign, node in pairs]
        # Some node free in some coordinates only (a rail's): products over its free ones.
        mask = constraints.free_mask.astype(np.float64)
        self.partial = bool(np.any(constraints.free_mask.any(1) & ~constraints.free_mask.all(1)))
        self.end_masks = (mask[i], mask[j]) if self.partial else None
        self.pair_masks = mask[[node for *_, node in pairs]] if self.partial and pairs else np.zeros((0, mask.shape[1]))
        pairs = [pair[:3] for pair in pairs]
        # int32 indices: the same dtype whether or not the caller traces with 64-bit
        # types (the projection runs in full precision inside a float32 rollout, and
        # int64 indices there met int32 ones in JAX's index arithmetic).
        self.first, self.second, self.sign = (np.asarray(c, dtype) for c, dtype in zip(zip(*pairs), (np.int32, np.int32, np.float64))) if pairs else (
            np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros(0))
        self.tridiagonal = bool(np.all(self.second - self.first == 1))
        self.border = self._border() if not self.tridiagonal else None
        self.bordered = self.border is not None

    def _border(self) -> np.ndarray | None:
        """The links to set aside so that the rest share nodes only with their neighbours
        in order (each non-neighbouring pair loses its later link, which on T1 are the
        braces listed after the chain), or None when that takes more than
        `MAX_GRAM_BORDER` or leaves a rest that is not tridiagonal."""
        border: set[int] = set()
        for a, b in zip(self.first, self.second):
            if b - a > 1 and a not in border:
                border.add(int(b))
        main = np.setdiff1d(np.arange(self.n_rows), sorted(border))
        position = np.full(self.n_rows, -1)
        position[main] = np.arange(len(main))
        both_main = (position[self.first] >= 0) & (position[self.second] >= 0)
        if len(border) > MAX_GRAM_BORDER or len(main) == 0 or np.any(position[self.second][both_main] - position[self.first][both_main] != 1):
            return None
        return np.asarray(sorted(border), np.int64)

    def solve_fn(self, u: Array, shift: float, one_system: bool = False) -> Callable[[Array], Array]:
        """`r -> (G + shift I)^-1 r` (K,) at link directions `u` (K, D), factored once.
        `one_system`: the caller solves one system on a CPU, not under `vmap`, where
        LAPACK's `gtsv` (one call) solves a tridiagonal part faster than the sweeps'
        two loops (`spd_tridiagonal_solve`; the same operations, so the same result):
        one trajectory's RK4 step on the 2-core CPU, the 12-link held-out chain
        13.8-14.7 -> 13.2-13.9 us, chain8 9.6-10.1 -> 8.8-9.3, chain16 unchanged
        (`results/cpu_vs_mujoco.md`)."""
        tridiagonal_solve = jax.lax.linalg.tridiagonal_solve if one_system else spd_tridiagonal_solve
        if self.partial:
            first_mask, second_mask = (jnp.asarray(m, u.dtype) for m in self.end_masks)
            diag = jnp.sum(u * u * (first_mask + second_mask), -1) + shift
            off = jnp.asarray(self.sign, u.dtype) * jnp.sum(take_rows(u, self.first) * take_rows(u, self.second) * jnp.asarray(self.pair_masks, u.dtype), -1)
        else:
            diag = jnp.asarray(self.free_ends, u.dtype) * jnp.sum(u * u, -1) + shift
            off = jnp.asarray(self.sign, u.dtype) * jnp.sum(take_rows(u, self.first) * take_rows(u, self.second), -1)
        if self.tridiagonal:
            upper = add_rows(jnp.zeros_like(diag), self.first, off)
            lower = jnp.roll(upper, 1)
            return lambda r: tridiagonal_solve(lower, diag, upper, r[:, None])[:, 0]
        gram = jnp.diag(diag).at[self.first, self.second].add(off).at[self.second, self.first].add(off)
        if self.bordered:
            return _bordered_tridiagonal_solve_fn(gram, self.border, tridiagonal_solve)
        return cholesky_solve_fn(gram)[0]


def _bordered_tridiagonal_solve_fn(matrix: Array, border: np.ndarray, tridiagonal_solve: Callable[..., Array]) -> Callable[[Array], Array]:
    """`r -> matrix^-1 r` for an SPD `matrix` (K, K) that is tridiagonal once the rows and
    columns `border` (static, a few) are taken out: `T x_m + E x_b = r_m`,
    `E^T x_m + C x_b = r_b`, so `x_b` solves the small SPD Schur complement
    `C - E^T T^-1 E` (Cholesky) and `x_m = T^-1 (r_m - E x_b)`. Linear in K for a fixed
    border; the Schur complement is factored once, `T^-1 E` kept for every `r`."""
    main = np.setdiff1d(np.arange(matrix.shape[0]), border)
    tri = matrix[main[:, None], main[None, :]]
    lower, diag, upper = jnp.diagonal(tri, -1), jnp.diagonal(tri), jnp.diagonal(tri, 1)
    lower, upper = jnp.pad(lower, (1, 0)), jnp.pad(upper, (0, 1))
    coupling = matrix[main[:, None], border[None, :]]
    tri_solve = functools.partial(tridiagonal_solve, lower, diag, upper)
    tri_coupling = tri_solve(coupling)
    schur = matrix[border[:, None], border[None, :]] - coupling.T @ tri_coupling
    border_solve, _ = cholesky_solve_fn(schur)

    def solve(r):
        reduced = tri_solve(r[main, None])[:, 0]
        border_part = border_solve(r[border] - coupling.T @ reduced)
        return jnp.zeros_like(r).at[main].set(reduced - tri_coupling @ border_part).at[border].set(border_part)

    return solve
