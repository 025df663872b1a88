"""The link-length constraints of a scene, over its free coordinates.

Contract: `Constraints(scene)` holds static NumPy data (which coordinates are free,
which links are kept as independent rows) and pure JAX functions of positions and
velocities. Functions named `link_*` take node arrays (N, D); the others take free
coordinates `x, v` (F,). Rows are `Phi_k = (|q_i - q_j|^2 - l^2) / 2l` for the kept
links k = (i, j): scaled by 1/l, so Jacobian rows are unit vectors and links of very
different lengths are equally well conditioned.

Pins are exact: pinned nodes are not unknowns (`embed` puts them at their pins), so no
pin rows exist; a rail's node likewise has only its coordinate along the rail free. Redundant rows (a link between two pinned nodes, an over-braced truss)
are dropped once per scene by a rank-revealing (column-pivoted) QR of the Jacobian at
a random *generic* configuration, so exactly the structurally redundant rows go; the
kept rows span the same constraint manifold. A structure can still lose rank at
particular configurations (a self-stressed tensegrity at rest, a rope pulled exactly
taut): `self_stresses` counts those dependencies at the scene's initial configuration
(an SVD, computed on first use).

`constraint_violation` and `velocity_constraint_violation` measure a state against
*every* link and pin, dropped rows included.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from lgnn.scene import Scene

Array = jax.Array

# Relative size of a pivot of the constraint Jacobian's QR below which its row is
# redundant (the Jacobian rows are unit vectors, so this is an absolute angle scale).
RANK_TOLERANCE = 1e-9


def _span(index: np.ndarray) -> tuple[int, int] | None:
    """`(start, stop)` where the static `index` is the contiguous range start..stop-1
    (a chain's links and ends, its free coordinates), else None."""
    index = np.asarray(index)
    if index.ndim != 1 or len(index) == 0 or not np.array_equal(index, np.arange(index[0], index[0] + len(index))):
        return None
    return int(index[0]), int(index[0]) + len(index)


# Static indices as slices where they are contiguous: on a small scene XLA's gathers
# and scatters cost more than the arithmetic around them (chain12 on a CPU), and a
# slice or a pad is exactly the same values.
def take_rows(x: Array, index: np.ndarray) -> Array:
    """`x[index]` along the first axis, for a static `index`."""
    span = _span(index)
    return x[index] if span is None else x[span[0] : span[1]]


def add_rows(x: Array, index: np.ndarray, values: Array) -> Array:
    """`x.at[index].add(values)` for a static `index` (repeated indices accumulate)."""
    span = _span(index)
    if span is None:
        return x.at[index].add(values)
    return x + jnp.pad(values, [(span[0], x.shape[0] - span[1])] + [(0, 0)] * (x.ndim - 1))


def set_rows(x: Array, index: np.ndarray, values: Array) -> Array:
    """`x.at[index].set(values)` for a static `index` without repeats."""
    span = _span(index)
    if span is None:
        return x.at[index].set(values)
    return jnp.concatenate([x[: span[0]], values, x[span[1] :]])


class Constraints:
    """The scene's independent link-length constraints over the free coordinates.

    Attributes (all static NumPy): `shape` (N, D); `free` indices into the flattened
    (N*D) coordinates of the free (unpinned) nodes, `free_mask` (N, D) the same as a
    mask; `links` the link indices kept as constraint rows, `redundant` the others
    (both found on first use, as is `self_stresses`).
    """

    def __init__(self, scene: Scene):
        n, d = scene.n_nodes, scene.dim
        # A rail's node is free along its axis only (`Scene.fixed_mask`).
        free_mask = ~scene.fixed_mask
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
        self._candidate = candidate

    @functools.cached_property
    def links(self) -> np.ndarray:
        """Indices of the links kept as rows: those independent at a random generic
        configuration (structural rank), by a column-pivoted QR."""
        candidate = self._candidate
        if len(candidate) == 0:
            return candidate
        generic = np.random.default_rng(0).normal(size=self.pin_positions.shape)
        jac = self._jacobian_np(candidate, generic)
        _, r, pivots = scipy.linalg.qr(jac.T, mode="economic", pivoting=True)
        diag = np.abs(np.diag(r))
        rank = int(np.sum(diag > RANK_TOLERANCE * max(diag[0], 1.0)))
        return np.sort(candidate[pivots[:rank]])

    @functools.cached_property
    def always_independent(self) -> bool:
        """Whether the kept rows are independent at *every* configuration with links of
        nonzero length, not only at a generic one: the kept links, every pinned node
        taken as one ground node, form a forest. Ordered from the ground, each link's row
        is then the only one with a block (its unit vector) at its far node, so `A` has
        full row rank everywhere; a cycle (a truss, a rope pinned at both ends) can lose
        it (a taut rope, a self-stressed tensegrity)."""
        ground = -1
        root = {node: ground for node in np.flatnonzero(~self.free_mask.any(1))}

        def find(node):
            while root.setdefault(node, node) != node:
                node = root[node]
            return node

        for i, j in self.edge_index[self.links]:
            a, b = find(int(i)), find(int(j))
            if a == b:
                return False
            root[max(a, b)] = min(a, b)
        return True

    @functools.cached_property
    def redundant(self) -> np.ndarray:
        """Indices of the links dropped as redundant (the complement of `links`)."""
        return np.setdiff1d(np.arange(len(self.lengths_all)), self.links)

    @functools.cached_property
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
        full = set_rows(jnp.asarray(self.pin_positions, x.dtype).ravel(), self.free, x)
        return full.reshape(self.shape)

    def embed_velocity(self, v: Array) -> Array:
        """Free velocities (F,) -> node velocities (N, D), zero at the pins."""
        return set_rows(jnp.zeros(self.shape[0] * self.shape[1], v.dtype), self.free, v).reshape(self.shape)

    def restrict(self, full: Array) -> Array:
        """(N, D) -> free coordinates (F,)."""
        return take_rows(full.reshape(-1), self.free)

    def link_vectors(self, q: Array, q_low: Array | None = None) -> Array:
        """(K, D) `q_i - q_j` of the kept links at positions `q` (N, D), plus the
        difference of the positions' rounding remainders `q_low` where given
        (`integrate.compensated_add`): a link's vector is then as accurate as its own
        length allows, not only as the positions' larger scale does."""
        i, j = self.edge_index[self.links].T
        dq = take_rows(q, i) - take_rows(q, j)
        return dq if q_low is None else dq + (take_rows(q_low, i) - take_rows(q_low, j))

    def link_residual(self, q: Array, q_low: Array | None = None) -> Array:
        """Phi (K,) at node positions `q` (N, D) (plus `q_low`, see `link_vectors`):
        `(|dq|^2 - l^2) / 2l` per kept link, zero on the manifold."""
        length = jnp.asarray(self.lengths_all[self.links], q.dtype)
        dq = self.link_vectors(q, q_low)
        return (jnp.sum(dq * dq, -1) - length**2) / (2 * length)

    def link_speed_terms(self, qd: Array) -> Array:
        """`Adot v` at node velocities `qd` (N, D): `|dv|^2 / l` per kept link."""
        i, j = self.edge_index[self.links].T
        dv = take_rows(qd, i) - take_rows(qd, j)
        return jnp.sum(dv * dv, -1) / jnp.asarray(self.lengths_all[self.links], qd.dtype)

    def link_directions(self, q: Array, q_low: Array | None = None) -> Array:
        """(K, D) `(q_i - q_j) / l` of the kept links at positions `q` (N, D) (plus
        `q_low`, see `link_vectors`): the nonzero blocks of the Jacobian (row k is `+u_k`
        at node i, `-u_k` at node j)."""
        return self.link_vectors(q, q_low) / jnp.asarray(self.lengths_all[self.links, None], q.dtype)

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
    """Max absolute error of link lengths and pin positions (and rails' fixed
    coordinates) at positions `q` (N, D)."""
    i, j = scene.edge_index.T
    stretch = jnp.abs(jnp.linalg.norm(q[i] - q[j], axis=-1) - jnp.asarray(scene.lengths))
    worst = jnp.max(stretch)
    if scene.rails:
        fixed = scene.fixed_mask
        return jnp.maximum(worst, jnp.max(jnp.where(fixed, jnp.abs(q - jnp.asarray(scene.nodes, q.dtype)), 0.0)))
    if scene.pinned:
        pins = np.asarray(scene.pinned)
        worst = jnp.maximum(worst, jnp.max(jnp.abs(q[pins] - jnp.asarray(scene.nodes[pins]))))
    return worst


def velocity_constraint_violation(scene: Scene, q: Array, qd: Array) -> Array:
    """Max absolute rate of change of link lengths (and pin velocity, and rails'
    fixed coordinates' velocity) at (q, qd)."""
    i, j = scene.edge_index.T
    dq = q[i] - q[j]
    rate = jnp.abs(jnp.sum(dq * (qd[i] - qd[j]), -1)) / jnp.linalg.norm(dq, axis=-1)
    worst = jnp.max(rate)
    if scene.rails:
        return jnp.maximum(worst, jnp.max(jnp.where(scene.fixed_mask, jnp.abs(qd), 0.0)))
    if scene.pinned:
        worst = jnp.maximum(worst, jnp.max(jnp.abs(qd[np.asarray(scene.pinned)])))
    return worst
