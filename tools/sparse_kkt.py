"""A negative result kept reproducible (issue 14, item 6): T1's constrained
accelerations by a block-sparse LDL^T of the saddle-point system, against the dense
Schur-complement solver the engine uses. Prints; writes nothing.

    python tools/sparse_kkt.py [SCENE] [BATCH]      default T1 100

The idea was the issue's: a factorisation that uses the truss's sparsity should lift
batched T1 on a CPU to MuJoCo C's throughput. Built here: a nested-dissection order of
the free nodes, each block holding a node's accelerations and the multipliers of the
links it is eliminated last of (padded to one block size), the elimination tree's
levels computed together (gathers, small block products, 0/1 sums, no loop, no LAPACK
call), refined against the exact system like `solvers.solve_kkt`. It agrees with the
engine to round-off (1.6e-13 of the largest acceleration on T1) and is linear in size
with a logarithmic depth (T1: 42 blocks of 5 x 5, 8 levels, 90 blocks of L) -- and
under `vmap` on XLA:CPU it is slower than LAPACK's dense 46 x 46 Cholesky of the Schur
complement, one matrix at a time: XLA runs these small block products at well under 1
GFLOP/s. Measured on this 2-core CPU (2026-11-25, commit 2e4201a, two runs of this
script; timings swing 3x between runs): T1 x 100, 143-256 us per state against 27-97
for the Schur acceleration in the same runs; chain16 x 100, 20-42 against 5-11. Not
used by the engine.
"""

from __future__ import annotations

import functools
import sys
import time
from typing import Callable, NamedTuple

import lgnn
import jax
import jax.numpy as jnp
import numpy as np

from lgnn.physics.constraints import Constraints
from lgnn.physics.solvers import KKT_REFINEMENT_STEPS, KKT_REGULARISATION, refine

Array = jax.Array

# Graphs at most this large are ordered as they are (dissecting them gains no level).
_DISSECTION_LEAF = 2


class Factor(NamedTuple):
    """`K = L D L^T`: `lower` (E, b, b) the blocks of L below the diagonal in the
    pattern's entry order, `pivot_inverse` (n, b, b) the inverses of D's blocks (in
    elimination order)."""

    lower: Array
    pivot_inverse: Array


def _components(vertices: list[int], adjacency: list[set[int]]) -> list[list[int]]:
    """Connected components of the subgraph on `vertices`, each in ascending order."""
    remaining, components = set(vertices), []
    while remaining:
        start = min(remaining)
        seen, frontier = {start}, [start]
        while frontier:
            frontier = [w for v in frontier for w in adjacency[v] if w in remaining and w not in seen and not seen.add(w)]
        remaining -= seen
        components.append(sorted(seen))
    return components


def _bfs_levels(start: int, vertices: set[int], adjacency: list[set[int]]) -> list[list[int]]:
    levels, seen = [[start]], {start}
    while True:
        following = sorted({w for v in levels[-1] for w in adjacency[v] if w in vertices and w not in seen})
        if not following:
            return levels
        seen.update(following)
        levels.append(following)


def nested_dissection(n: int, adjacency: list[set[int]]) -> list[int]:
    """An elimination order of the graph's n vertices: each connected piece is split by
    the middle level of a breadth-first search from a pseudo-peripheral vertex (George
    1973), the two sides ordered first (recursively), the separator last."""

    def order(vertices: list[int]) -> list[int]:
        if len(vertices) <= _DISSECTION_LEAF:
            return vertices
        pieces = _components(vertices, adjacency)
        if len(pieces) > 1:
            return [v for piece in pieces for v in order(piece)]
        inside = set(vertices)
        start = vertices[0]
        for _ in range(3):  # walk to a pseudo-peripheral vertex: the far end of a BFS
            levels = _bfs_levels(start, inside, adjacency)
            far = levels[-1][0]
            if far == start or len(_bfs_levels(far, inside, adjacency)) <= len(levels):
                break
            start = far
        levels = _bfs_levels(start, inside, adjacency)
        if len(levels) < 3:
            return vertices
        middle = len(levels) // 2
        # Only the middle level's vertices that touch the far side separate it.
        beyond = set(levels[middle + 1])
        separator = [v for v in levels[middle] if adjacency[v] & beyond]
        rest = [v for v in vertices if v not in set(separator)]
        return order(rest) + separator

    return order(list(range(n)))


class BlockPattern:
    """The static part of a block-sparse LDL^T (module docstring).

    `edges` (m, 2): the off-diagonal blocks, `K[e0, e1]` given as `off_diagonal[e]` and
    `K[e1, e0]` as its transpose. Attributes: `order` the elimination order of the
    blocks, `levels` how many sequential steps a factorisation or a solve takes,
    `n_entries` the blocks of L (fill included)."""

    def __init__(self, n_blocks: int, block_size: int, edges: np.ndarray):
        edges = np.asarray(edges, np.int64).reshape(-1, 2)
        pairs = {(int(min(a, b)), int(max(a, b))) for a, b in edges}
        if np.any(edges[:, 0] == edges[:, 1]) or (len(edges) and (edges.min() < 0 or edges.max() >= n_blocks)) or len(pairs) < len(edges):
            raise ValueError("edges must join two different blocks of the pattern, each pair once")
        self.n_blocks, self.block_size, self.edges = n_blocks, block_size, edges
        adjacency = [set() for _ in range(n_blocks)]
        for a, b in edges:
            adjacency[a].add(int(b))
            adjacency[b].add(int(a))
        dissected = nested_dissection(n_blocks, adjacency)
        # The elimination tree of that order, then the same tree's columns sorted by
        # level (a topological order of the tree: same fill), so each level's columns
        # and L blocks are contiguous.
        structure, parent = self._symbolic(dissected, adjacency)
        height = np.zeros(n_blocks, np.int64)
        for column in range(n_blocks):
            if parent[column] >= 0:
                height[parent[column]] = max(height[parent[column]], height[column] + 1)
        by_level = np.argsort(height, kind="stable")
        self.order = np.asarray(dissected, np.int64)[by_level]
        structure, _ = self._symbolic(list(self.order), adjacency)
        self.position = np.empty(n_blocks, np.int64)
        self.position[self.order] = np.arange(n_blocks)
        column_level = height[by_level]
        self.levels = int(column_level.max()) + 1 if n_blocks else 0
        self._schedule(structure, column_level)

    @staticmethod
    def _symbolic(order: list[int], adjacency: list[set[int]]) -> tuple[list[list[int]], np.ndarray]:
        """Per column (in elimination order) the rows below it where L is nonzero, and
        the elimination tree's parents (-1 at roots)."""
        n = len(order)
        position = np.empty(n, np.int64)
        position[np.asarray(order, np.int64)] = np.arange(n)
        children: list[list[int]] = [[] for _ in range(n)]
        structure, parent = [], np.full(n, -1, np.int64)
        for column, vertex in enumerate(order):
            rows = {int(position[w]) for w in adjacency[vertex] if position[w] > column}
            for child in children[column]:
                rows.update(r for r in structure[child] if r > column)
            structure.append(sorted(rows))
            if rows:
                parent[column] = min(rows)
                children[parent[column]].append(column)
        return structure, parent

    def _schedule(self, structure: list[list[int]], column_level: np.ndarray) -> None:
        """Index arrays of every level's gathers and segment sums."""
        entry_row = np.asarray([r for rows in structure for r in rows], np.int64)
        entry_column = np.asarray([c for c, rows in enumerate(structure) for _ in rows], np.int64)
        self.n_entries = len(entry_row)
        entry_of = {(int(r), int(c)): e for e, (r, c) in enumerate(zip(entry_row, entry_column))}
        # Where each L entry's K block comes from: edge e as given (+1) or transposed (-1).
        self.entry_edge = np.full(self.n_entries, -1, np.int64)
        self.entry_transposed = np.zeros(self.n_entries, bool)
        for e, (a, b) in enumerate(self.edges):
            pa, pb = int(self.position[a]), int(self.position[b])
            row, column = max(pa, pb), min(pa, pb)
            self.entry_edge[entry_of[(row, column)]] = e
            self.entry_transposed[entry_of[(row, column)]] = pa < pb
        # Updates: for each column k and rows j <= i of its structure, L_ik (D_k L_jk^T)
        # is subtracted from block (i, j), on the diagonal when i == j.
        updates_by_level: list[list[tuple[int, int, int, int]]] = [[] for _ in range(self.levels)]
        for k, rows in enumerate(structure):
            for x, j in enumerate(rows):
                updates_by_level[column_level[j]] += [(entry_of[(i, k)], entry_of[(j, k)], i, j) for i in rows[x:]]
        self._factor_steps, self._forward_steps, self._backward_steps = [], [], []
        starts = np.searchsorted(column_level, np.arange(self.levels + 1))
        entry_starts = np.searchsorted(column_level[entry_column], np.arange(self.levels + 1)) if self.n_entries else np.zeros(self.levels + 1, np.int64)
        for level in range(self.levels):
            first, last = int(starts[level]), int(starts[level + 1])
            entries = np.arange(entry_starts[level], entry_starts[level + 1])
            # Targets: the level's diagonal blocks, then its L entries.
            target = {(c, c): c - first for c in range(first, last)}
            target.update({(int(entry_row[e]), int(entry_column[e])): (last - first) + t for t, e in enumerate(entries)})
            level_updates = [(left, right, target[(i, j)]) for left, right, i, j in updates_by_level[level]]
            left, right, to = (np.asarray(column, np.int64) for column in zip(*level_updates)) if level_updates else (np.zeros(0, np.int64),) * 3
            self._factor_steps.append((first, last, int(entries[0]) if len(entries) else 0, len(entries), left, right,
                                       _summing(to, last - first + len(entries)), entry_column[entries] - first))
            # Forward: rows in this level gather L_jk y_k of their (earlier) columns.
            incoming = np.flatnonzero((entry_row >= first) & (entry_row < last))
            self._forward_steps.append((first, last, incoming, entry_column[incoming], _summing(entry_row[incoming] - first, last - first)))
            # Backward: this level's columns gather L_ij^T x_i of their (later) rows.
            self._backward_steps.append((first, last, entries, entry_row[entries], _summing(entry_column[entries] - first, last - first)))

    def _permuted(self, diagonal: Array, off_diagonal: Array) -> tuple[Array, Array]:
        """K's diagonal blocks in elimination order and its blocks at L's entries (zero
        where only fill is)."""
        diagonal = diagonal[self.order]
        if self.n_entries == 0:
            return diagonal, jnp.zeros((0,) + diagonal.shape[1:], diagonal.dtype)
        transposed = jnp.swapaxes(off_diagonal, -1, -2)
        has_edge = self.entry_edge >= 0
        source = np.where(has_edge, self.entry_edge, 0)
        blocks = jnp.where(self.entry_transposed[:, None, None], transposed[source], off_diagonal[source]) if len(self.edges) else (
            jnp.zeros((self.n_entries,) + diagonal.shape[1:], diagonal.dtype))
        return diagonal, jnp.where(has_edge[:, None, None], blocks, 0.0)

    def factor(self, diagonal: Array, off_diagonal: Array) -> Factor:
        """`L D L^T` of `K` given by `diagonal` (n, b, b) and `off_diagonal` (m, b, b)
        (the pattern's `edges`)."""
        diagonal, entries = self._permuted(diagonal, off_diagonal)
        b, dtype = self.block_size, diagonal.dtype
        lower = jnp.zeros((self.n_entries, b, b), dtype)
        # D_k L_jk^T = T_jk^T, T_jk = L_jk D_k being the block before its division.
        scaled = jnp.zeros((self.n_entries, b, b), dtype)
        inverses = []
        for first, last, entry_start, n_level_entries, left, right, gather_sum, local_column in self._factor_steps:
            n_columns = last - first
            base = jnp.concatenate([diagonal[first:last], entries[entry_start:entry_start + n_level_entries]])
            if len(left):
                products = _block_products(lower[left], jnp.swapaxes(scaled[right], -1, -2))
                base = base - jnp.einsum("tp,pac->tac", gather_sum.astype(dtype), products)
            inverse = _small_inverse(base[:n_columns])
            inverses.append(inverse)
            if n_level_entries:
                level_scaled = base[n_columns:]
                level_lower = _block_products(level_scaled, inverse[local_column])
                lower = jax.lax.dynamic_update_slice_in_dim(lower, level_lower, entry_start, 0)
                scaled = jax.lax.dynamic_update_slice_in_dim(scaled, level_scaled, entry_start, 0)
        return Factor(lower, jnp.concatenate(inverses))

    def solve(self, factor: Factor, rhs: Array) -> Array:
        """`K^-1 rhs` for `rhs` (n, b), from `factor(...)`."""
        lower, pivot_inverse = factor
        dtype = rhs.dtype
        y = rhs[self.order]
        for first, last, incoming, columns, gather_sum in self._forward_steps:
            if len(incoming):
                gathered = jnp.sum(lower[incoming] * y[columns][:, None, :], -1)
                level = y[first:last] - jnp.einsum("te,ea->ta", gather_sum.astype(dtype), gathered)
                y = jax.lax.dynamic_update_slice_in_dim(y, level, first, 0)
        x = jnp.sum(pivot_inverse * y[:, None, :], -1)
        for first, last, entries, rows, gather_sum in reversed(self._backward_steps):
            if len(entries):
                gathered = jnp.sum(lower[entries] * x[rows][:, :, None], -2)
                level = x[first:last] - jnp.einsum("te,ea->ta", gather_sum.astype(dtype), gathered)
                x = jax.lax.dynamic_update_slice_in_dim(x, level, first, 0)
        return x[self.position]

    def multiply(self, diagonal: Array, off_diagonal: Array, x: Array) -> Array:
        """`K x` for `x` (n, b), `K` given as to `factor`."""
        product = jnp.sum(diagonal * x[:, None, :], -1)
        if len(self.edges):
            a, b = self.edges[:, 0], self.edges[:, 1]
            product = product.at[a].add(jnp.sum(off_diagonal * x[b][:, None, :], -1))
            product = product.at[b].add(jnp.sum(off_diagonal * x[a][:, :, None], -2))
        return product


def _block_products(left: Array, right: Array) -> Array:
    """`left @ right` of (P, b, b) stacks of small blocks, as a broadcast product and a
    sum: XLA on a CPU runs a batched `dot` of tiny matrices one matrix at a time, and
    this fuses into one loop over the whole batch."""
    return jnp.sum(left[..., :, :, None] * right[..., None, :, :], axis=-2)


def _summing(targets: np.ndarray, n_targets: int) -> np.ndarray:
    """(n_targets, len(targets)) the 0/1 matrix that sums terms into their targets: a
    product with it is a segment sum without a scatter, which XLA runs element by
    element on a CPU (the sums here are a few dozen terms)."""
    matrix = np.zeros((n_targets, len(targets)))
    matrix[targets, np.arange(len(targets))] = 1.0
    return matrix


def _small_inverse(blocks: Array) -> Array:
    """Inverses of `blocks` (n, b, b) by Gauss-Jordan elimination in their own order,
    unrolled over b (static, small): no pivoting (module docstring)."""
    b = blocks.shape[-1]
    augmented = jnp.concatenate([blocks, jnp.broadcast_to(jnp.eye(b, dtype=blocks.dtype), blocks.shape)], axis=-1)
    rows = np.arange(b)[:, None]
    for k in range(b):
        pivot_row = augmented[:, k, :] / augmented[:, k, k, None]
        eliminated = augmented - augmented[:, :, k, None] * pivot_row[:, None, :]
        augmented = jnp.where(rows == k, pivot_row[:, None, :], eliminated)
    return augmented[:, :, b:]


class NodeKKT:
    """The saddle-point system of constrained node accelerations with a constant mass
    matrix, `[[M, A^T], [A, 0]] [a; lam] = [f; r]`, as a block-sparse matrix over the
    free nodes (`BlockPattern`): block v holds node v's D accelerations, then the
    multipliers of the kept links assigned to it, padded to one block size with inert
    unknowns (a 1 on the diagonal, zero right-hand side). Each link goes to whichever of
    its free ends the pattern eliminates last, so its multiplier follows every
    coordinate it acts on: its pivot is then bounded by the link's own stiffness against
    the masses, never by the regularisation alone (the order that keeps the
    factorisation stable, `sparse`).

    `solve_fn(u)` factors the system at link directions `u` (K, D), regularised and
    equilibrated exactly as `solve_kkt` (mass scale `s = trace(M)/F`, `-eps` on the
    multipliers' diagonal, so any multiple of the mass gives the same accelerations),
    and returns `(f, r) -> a`: free-node forces (n_free, D) and link right-hand sides
    (K,) to free-node accelerations (n_free, D), refined against the exact system with
    `KKT_REFINEMENT_STEPS` steps. Its cost is linear in the structure's size and its
    sequential depth logarithmic for chains and trusses (`BlockPattern.levels`).
    """

    def __init__(self, constraints: Constraints, node_mass: np.ndarray):
        n, d = constraints.shape
        free_nodes = np.flatnonzero(constraints.free_mask[:, 0])
        block_of = np.full(n, -1, np.int64)
        block_of[free_nodes] = np.arange(len(free_nodes))
        mass = node_mass.reshape(n, d, n, d)[np.ix_(free_nodes, np.arange(d), free_nodes, np.arange(d))]
        self.dim, self.n_blocks = d, len(free_nodes)
        self.free_nodes = free_nodes
        i, j = constraints.edge_index[constraints.links].T
        pairs = {(min(a, b), max(a, b)) for a, b in zip(block_of[i], block_of[j]) if a >= 0 and b >= 0}
        coupled = np.argwhere(np.abs(mass).max(axis=(1, 3)) > 0)
        pairs |= {(int(a), int(b)) for a, b in coupled if a < b}
        edges = np.asarray(sorted(pairs), np.int64).reshape(-1, 2)
        # Each kept link's multiplier goes to the free end eliminated last, so that all
        # the coordinates it acts on come before it.
        position = BlockPattern(self.n_blocks, 1, edges).position
        ends = np.stack([block_of[i], block_of[j]], 1)
        rank = np.where(ends >= 0, position[np.maximum(ends, 0)], -1)
        owner_end = np.argmax(rank, axis=1)
        self.owner = ends[np.arange(len(ends)), owner_end]
        self.other = ends[np.arange(len(ends)), 1 - owner_end]
        # Row k is +u_k at node i (end 0), -u_k at node j (end 1).
        self.owner_sign = np.where(owner_end == 0, 1.0, -1.0)
        self.slot = np.zeros(len(ends), np.int64)
        counts = np.zeros(self.n_blocks, np.int64)
        for k, v in enumerate(self.owner):
            self.slot[k], counts[v] = d + counts[v], counts[v] + 1
        size = d + int(counts.max(initial=0))
        self.pattern = BlockPattern(self.n_blocks, size, edges)
        self.block_size = size
        scale = np.trace(mass.reshape(self.n_blocks * d, -1)) / (self.n_blocks * d)
        base_diagonal = np.zeros((self.n_blocks, size, size))
        base_diagonal[:, :d, :d] = mass[np.arange(self.n_blocks), :, np.arange(self.n_blocks), :] / scale
        inert = np.arange(size)[None, :] >= d + counts[:, None]
        base_diagonal[:, np.arange(size), np.arange(size)] += inert
        self.scale, self.base_diagonal = scale, base_diagonal
        self.base_off = np.zeros((len(edges), size, size))
        self.base_off[:, :d, :d] = mass[edges[:, 0], :, edges[:, 1], :] / scale
        # Where a link's coefficient on its other (free) end sits: the off-diagonal block
        # of (owner, other), in the row of the multiplier or transposed.
        edge_of = {(int(a), int(b)): e for e, (a, b) in enumerate(edges)}
        has_other = self.other >= 0
        self.coupled_links = np.flatnonzero(has_other)
        other_edges = [(edge_of[(min(o, w), max(o, w))], o < w) for o, w in zip(self.owner[has_other], self.other[has_other])]
        self.other_edge = np.asarray([e for e, _ in other_edges], np.int64)
        self.owner_first = np.asarray([first for _, first in other_edges], bool)

    def _blocks(self, u: Array, eps: float) -> tuple[Array, Array]:
        d, dtype = self.dim, u.dtype
        diagonal = jnp.asarray(self.base_diagonal, dtype)
        column = self.owner_sign[:, None] * u
        diagonal = diagonal.at[self.owner, :d, self.slot].set(column).at[self.owner, self.slot, :d].set(column)
        diagonal = diagonal.at[self.owner, self.slot, self.slot].set(-eps)
        off = jnp.asarray(self.base_off, dtype)
        if len(self.coupled_links):
            # The other end's sign is minus the owner's.
            other_column = -column[self.coupled_links]
            slots, first, edges = self.slot[self.coupled_links], self.owner_first, self.other_edge
            off = off.at[edges[first], slots[first], :d].set(other_column[first])
            off = off.at[edges[~first], :d, slots[~first]].set(other_column[~first])
        return diagonal, off

    def solve_fn(self, u: Array) -> Callable[[Array, Array], Array]:
        d = self.dim
        exact = self._blocks(u, 0.0)
        factor = self.pattern.factor(*self._blocks(u, KKT_REGULARISATION))
        solve = functools.partial(self.pattern.solve, factor)

        def accelerations(force: Array, link_rhs: Array) -> Array:
            rhs = jnp.zeros((self.n_blocks, self.block_size), force.dtype).at[:, :d].set(force / self.scale)
            rhs = rhs.at[self.owner, self.slot].set(link_rhs)
            solution = refine(solve, lambda x: rhs - self.pattern.multiply(*exact, x), solve(rhs), KKT_REFINEMENT_STEPS)
            return solution[:, :d]

        return accelerations


def main(scene_name: str = "T1", batch: int = 100) -> None:
    lgnn.configure()
    import jax

    from lgnn import physics
    from lgnn.physics.energies import constant_node_mass
    from lgnn.physics.system import prepare
    from lgnn.provenance import environment
    from lgnn.scene import get_scene, sample_initial_states

    scene = get_scene(scene_name)
    if scene.drag:
        raise SystemExit(f"{scene_name} has drag, which this measurement leaves out")
    system = prepare(scene)
    constraints = system.constraints
    kkt = NodeKKT(constraints, constant_node_mass(scene))
    gravity = system.node_gravity  # (the scenes this measures have no drag)

    def sparse_accel(q, qd):
        solve = kkt.solve_fn(constraints.link_directions(q))
        free = solve(jnp.asarray(gravity, q.dtype)[kkt.free_nodes], -constraints.link_speed_terms(qd))
        return jnp.zeros(q.shape, q.dtype).at[kkt.free_nodes].set(free)

    states = sample_initial_states(scene, jax.random.PRNGKey(1), batch)
    q, qd = jnp.asarray(states.q), jnp.asarray(states.qd)
    print(f"{scene_name} x {batch}: {kkt.n_blocks} blocks of {kkt.block_size}, {kkt.pattern.levels} levels, "
          f"{kkt.pattern.n_entries} blocks of L; {environment()}")
    results = {}
    for name, accel in (("schur", physics.true_acceleration_fn(scene, "schur")), ("sparse", sparse_accel)):
        run = jax.jit(jax.vmap(accel))
        results[name] = jax.block_until_ready(run(q, qd))
        times = []
        for _ in range(5):
            start = time.perf_counter()
            jax.block_until_ready(run(q, qd))
            times.append((time.perf_counter() - start) / batch * 1e6)
        print(f"{name}: {min(times):.1f}-{max(times):.1f} us per state (5 runs)")
    scale = float(jnp.abs(results["schur"]).max())
    print(f"max difference {float(jnp.abs(results['sparse'] - results['schur']).max()) / scale:.2e} of the largest acceleration")


if __name__ == "__main__":
    main(*(sys.argv[1:2] or ["T1"]), *(int(a) for a in sys.argv[2:3]))
