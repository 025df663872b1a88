"""A mass matrix with graph structure, assembled from a few derivative products.

Contract: `LocalMass(scene, constraints, reach)` and `ChainBandMass(constraints, reach)`
hold static NumPy index arrays (a node colouring and the maps from products to blocks);
their methods are pure JAX functions.
`MassStructure` is what a Lagrangian declares about its mass matrix `d2L/dqd2`:

- local (`reach`): the mass matrix couples a node only with nodes at most `reach`
  links away (1: with itself and the nodes it shares a link with, as the exact rods and
  LGNN's per-link energies do). `M` is then recovered from one Hessian-vector product
  per (colour, coordinate) instead of one per coordinate: 3 x D for any chain at reach 1,
  (2 reach + 1) x D at any reach, whatever the chain's length (`LocalMass`); on a long
  pinned chain (reach + 1) x D, its symmetry used (`ChainBandMass`).
- pooled (`terms`, `supports`, `readout`): `L = readout(p)` of features `p(q, qd)` (P,)
  that are a sum of local terms `terms(q, qd)` (T, P), term t depending on the
  velocities of the nodes `supports[t]` only, as LGN's read-out of its summed node and
  edge embeddings. Then `M = J^T H J + S`: `H` the read-out's P x P Hessian, `J =
  dp/dqd` from one forward product per (colour, coordinate) of a colouring in which no
  support holds two nodes of one colour (`PooledJacobian`: 4 x D for LGN on any chain),
  and `S = sum_c dreadout/dp_c d2p_c/dqd2`, the Hessian of the local sum with the
  read-out's gradient held fixed, local again. The dense matrix is low rank plus local.

`MassStructure.products(system)` counts the products a structure costs on a scene, so the
solve (`dynamics.acceleration_fn`) takes it only where it is cheaper than one product per
coordinate.
"""

from __future__ import annotations

import dataclasses
from collections import deque
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from lgnn.physics.constraints import Constraints
from lgnn.scene import Scene

Array = jax.Array


@dataclasses.dataclass(frozen=True)
class MassStructure:
    """What a Lagrangian declares about `d2L/dqd2` (module docstring). Declaring a reach
    smaller than the true one gives wrong accelerations (tests compare with the dense
    mass matrix); a larger one only costs products."""

    # Nodes further apart than this many links are not coupled.
    reach: int = 1
    # `terms(q, qd) -> (T, P)` and `readout(p) -> L` with `L = readout(terms(q, qd).sum(0))`;
    # term t depends on the velocities of the nodes `supports[t]` only, none of them
    # more than `reach` links apart. None: `L` itself is a sum of terms of `reach`.
    terms: Callable | None = None
    supports: tuple[tuple[int, ...], ...] = ()
    readout: Callable | None = None

    def __post_init__(self):
        if self.reach < 1:
            raise ValueError(f"a mass structure's reach must be >= 1, got {self.reach}")
        if (self.terms is None) != (self.readout is None) or (self.terms is None) != (not self.supports):
            raise ValueError("a pooled mass structure needs terms, their supports and a readout together")

    @property
    def pooled(self) -> bool:
        return self.terms is not None

    def products(self, system) -> int:
        """Derivative products that assemble the mass matrix with this structure on
        `system`'s scene (`physics.prepare`): the local part's Hessian-vector products
        and, pooled, the Jacobian's forward products."""
        dim = system.scene.dim
        pooled = system.pooled_jacobian(self.supports).n_colours * dim if self.pooled else 0
        return system.local_mass(self.reach).n_colours * dim + pooled


# Reach 1: the exact rods, LGNN's per-link energies.
LOCAL = MassStructure(1)


def neighbourhoods(scene: Scene, reach: int) -> list[set]:
    """For each node, the nodes at most `reach` links from it (breadth first, through
    any node)."""
    adjacency = [set() for _ in range(scene.n_nodes)]
    for a, b in scene.edges:
        adjacency[a].add(b)
        adjacency[b].add(a)

    def within(start: int) -> set:
        seen, frontier = {start}, deque([(start, 0)])
        while frontier:
            node, depth = frontier.popleft()
            if depth == reach:
                continue
            for near in adjacency[node] - seen:
                seen.add(near)
                frontier.append((near, depth + 1))
        return seen

    return [within(node) for node in range(scene.n_nodes)]


def _colouring(constraints: Constraints, groups) -> tuple[np.ndarray, int, np.ndarray, np.ndarray]:
    """A greedy colouring of the free nodes in which no group holds two free nodes of
    one colour: `(colour, n_colours, seed_of, seeds)`, with `colour` (N,) -1 at pinned
    nodes, `seed_of` (F,) each free coordinate's (colour, coordinate) seed and `seeds`
    (n_colours D, F) those seeds as indicator vectors."""
    n, d = constraints.shape
    free_node = constraints.free_mask[:, 0]
    conflicts = {node: set() for node in np.flatnonzero(free_node)}
    for group in groups:
        members = [k for k in group if free_node[k]]
        for node in members:
            conflicts[node].update(members)
    colour = np.full(n, -1)
    for node in conflicts:
        taken = {colour[k] for k in conflicts[node] if colour[k] >= 0}
        colour[node] = next(c for c in range(len(taken) + 1) if c not in taken)
    n_colours = int(colour.max()) + 1 if free_node.any() else 0
    node_of, coord_of = constraints.free // d, constraints.free % d
    seed_of = colour[node_of] * d + coord_of
    seeds = np.zeros((n_colours * d, len(constraints.free)))
    seeds[seed_of, np.arange(len(constraints.free))] = 1.0
    return colour, n_colours, seed_of, seeds


class LocalMass:
    """A mass matrix over the free coordinates whose only nonzero blocks couple free
    nodes at most `reach` links apart (through any node, pinned ones included), from
    Hessian-vector products.

    Nodes are coloured so that no two nodes of one colour are both coupled to one node
    (greedy colouring; at reach 1, 3 colours for a chain). The product of M with the
    indicator of colour c, coordinate d, then holds in each node's rows the column d of
    its block with the one node of colour c it couples to. Static index arrays (NumPy)
    map the products to blocks.
    """

    def __init__(self, scene: Scene, constraints: Constraints, reach: int = 1):
        n, d = constraints.shape
        free_node = constraints.free_mask[:, 0]
        # The free nodes each free node couples to; two nodes coupled to a common one
        # must differ in colour.
        near = neighbourhoods(scene, reach)
        coupled_to = {node: {k for k in near[node] if free_node[k]} for node in np.flatnonzero(free_node)}
        _, self.n_colours, self.seed_of, self.seeds = _colouring(constraints, coupled_to.values())
        self.reach = reach
        node_of = constraints.free // d
        adjacent = np.eye(n, dtype=bool)
        for node, group in coupled_to.items():
            adjacent[node, list(group)] = True
        self.coupled = adjacent[np.ix_(node_of, node_of)]

    def products(self, hvp: Callable[[Array], Array], dtype) -> Array:
        """(S, F) `M @ seed` for every seed, from `hvp(seed) -> M @ seed` (F,)."""
        return jax.vmap(hvp)(jnp.asarray(self.seeds, dtype))

    def dense(self, products: Array) -> Array:
        """(F, F) the mass matrix: entry (r, s) is row r of the product of s's seed."""
        return jnp.where(self.coupled, products[self.seed_of[None, :], np.arange(products.shape[1])[:, None]], 0.0)


class ChainBandMass:
    """`LocalMass` for a chain pinned at node 0, from (reach + 1) x D Hessian-vector
    products instead of (2 reach + 1) x D: the mass matrix's symmetry recovers what
    the fewer colours mix.

    Chain node b (free node b + 1, coordinates Db..Db+D-1) takes colour b mod w, w =
    reach + 1. Row b of the product with colour (b + k) mod w, coordinate j, then holds
    `P(b, k) = B(b, k) + B(b - l, l)^T` (l = w - k, for k >= 1 and b >= l), where
    `B(b, k)` is the D x D block coupling node b with node b + k: the window of nodes
    coupled to b holds two of that colour, b + k and b + k - w. The diagonal blocks come
    out alone (k = 0). By symmetry `B(b, k) = P(b, k) - P(b - l, l)^T + B(b - w, k)`,
    so each block is a sum along its residue class mod w: a cumulative sum, no
    sequential recovery. Round-off grows with the chain's length over w (the terms
    summed), tested against the dense matrix on long chains.
    """

    def __init__(self, constraints: Constraints, reach: int):
        n_free, d = len(constraints.free), constraints.shape[1]
        n = n_free // d
        self.reach, width = reach, reach + 1
        self.n_colours = min(width, n)
        self.seeds = np.zeros((self.n_colours * d, n_free))
        chain_node, coordinate = np.arange(n_free) // d, np.arange(n_free) % d
        self.seeds[(chain_node % width) * d + coordinate, np.arange(n_free)] = 1.0
        block, offset, row, column = np.meshgrid(np.arange(n), np.arange(width), np.arange(d), np.arange(d), indexing="ij")
        # Product (b, k, i, j): row Db + i of the seed of colour (b + k) mod w, coordinate j
        # (a colour past the last, only where node b + k is past the chain's end, clipped).
        self.rows, self.product_seeds = d * block + row, np.minimum((block + offset) % width, self.n_colours - 1) * d + column
        self.inside = (block + offset < n)[..., 0, 0]
        partner = width - np.arange(width)
        self.has_partner = (np.arange(width)[None, :] >= 1) & (np.arange(n)[:, None] >= partner[None, :])
        self.partner_block = np.maximum(np.arange(n)[:, None] - partner[None, :], 0)
        self.partner_offset = np.minimum(np.broadcast_to(partner, (n, width)), width - 1)
        # Residue classes: block b is b = g w + s; summed over g.
        self.groups = -(-n // width)
        self.n, self.width, self.d = n, width, d
        # Dense assembly: entry (Db + i, D(b + k) + j) of block (b, k, i, j), inside the
        # chain; the diagonal blocks (k = 0) apart from those above them.
        columns = d * (block + offset) + column
        self.diagonal_entries = (self.rows[:, 0].reshape(-1), columns[:, 0].reshape(-1))
        above = self.inside.copy()
        above[:, 0] = False
        self.above, self.above_entries = above, (self.rows[above].reshape(-1), columns[above].reshape(-1))

    def products(self, hvp: Callable[[Array], Array], dtype) -> Array:
        """(S, F) `M @ seed` for every seed, from `hvp(seed) -> M @ seed` (F,)."""
        return jax.vmap(hvp)(jnp.asarray(self.seeds, dtype))

    def band_blocks(self, products: Array) -> Array:
        """(n, reach + 1, D, D) blocks of the chain's mass matrix: block k of row b
        couples node b+1 with node b+1+k, zero past the chain's end
        (`solvers.banded_chain_kkt_solve`)."""
        mixed = products[self.product_seeds, self.rows]
        partner = jnp.swapaxes(mixed[self.partner_block, self.partner_offset], -1, -2)
        differences = mixed - jnp.where(self.has_partner[..., None, None], partner, 0.0)
        n, width, d = self.n, self.width, self.d
        padded = jnp.zeros((self.groups * width, width, d, d), products.dtype).at[:n].set(differences)
        summed = jnp.cumsum(padded.reshape(self.groups, width, width, d, d), axis=0).reshape(-1, width, d, d)[:n]
        blocks = jnp.concatenate([mixed[:, :1], summed[:, 1:]], axis=1)
        return jnp.where(self.inside[..., None, None], blocks, 0.0)

    def chain_blocks(self, products: Array) -> tuple[Array, Array]:
        """(n, D, D) diagonal and (n-1, D, D) upper (node b with b+1) blocks of a chain
        (reach 1 only: nothing else is nonzero)."""
        if self.reach != 1:
            raise ValueError("chain blocks hold a mass matrix of reach 1 only")
        blocks = self.band_blocks(products)
        return blocks[:, 0], blocks[:-1, 1]

    def dense(self, products: Array) -> Array:
        """(F, F) the mass matrix, its blocks below the diagonal the transposes of those
        above."""
        blocks = self.band_blocks(products)
        zeros = jnp.zeros((self.n * self.d,) * 2, products.dtype)
        above = zeros.at[self.above_entries].set(blocks[self.above].reshape(-1))
        return zeros.at[self.diagonal_entries].set(blocks[:, 0].reshape(-1)) + above + above.T


class PooledJacobian:
    """The Jacobian `J = dp/dqd` over the free coordinates of pooled features `p =
    sum_t terms_t` (`MassStructure`), from forward products on a colouring of the nodes.

    No two free nodes of one colour lie in one term's support (greedy colouring; 4
    colours for LGN's terms on a chain, whose edge embeddings see 4 nodes). The forward
    product of the terms with the indicator of colour c, coordinate d then holds in each
    term's row its derivative by coordinate d of its one node of colour c; summing the
    rows into those coordinates' columns gives `J`. A reverse product per feature would
    cost one backward pass per feature (16 for LGN) instead.
    """

    def __init__(self, constraints: Constraints, supports: tuple[tuple[int, ...], ...]):
        n, d = constraints.shape
        colour, self.n_colours, _, self.seeds = _colouring(constraints, supports)
        self.n_free = n_free = len(constraints.free)
        # column[s, t]: the free coordinate whose derivative the product of seed s holds
        # in term t's row; n_free (dropped) where the term has no node of s's colour.
        free_index = np.full((n, d), n_free)
        free_index[constraints.free // d, constraints.free % d] = np.arange(n_free)
        self.column = np.full((self.n_colours * d, len(supports)), n_free)
        for term, support in enumerate(supports):
            for node in support:
                if colour[node] >= 0:
                    self.column[colour[node] * d + np.arange(d), term] = free_index[node]

    def transposed(self, linear: Callable[[Array], Array], dtype) -> Array:
        """(F, P) `J^T` from `linear(seed) -> (T, P)`, the terms' forward product."""
        products = jax.vmap(linear)(jnp.asarray(self.seeds, dtype))
        rows = products.reshape(-1, products.shape[-1])
        return jax.ops.segment_sum(rows, self.column.reshape(-1), num_segments=self.n_free + 1)[:-1]
