"""A graph-local mass matrix assembled from a few Hessian-vector products.

Contract: `LocalMass(scene, constraints)` holds static NumPy index arrays (a node
colouring and the maps from products to blocks); its methods are pure JAX functions.
It applies to a Lagrangian whose mass matrix `d2L/dqd2` couples a node only with itself
and the nodes it shares a link with (the exact rods, LGNN's per-link energies):
`M` is then recovered from one product per (colour, coordinate) instead of one per
coordinate, 3 x D for any chain whatever its length.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from lgnn.physics.constraints import Constraints
from lgnn.scene import Scene

Array = jax.Array


class LocalMass:
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
        # A chain pinned at node 0 has free coordinates Db + i for node b + 1, so its
        # block (b, i, j) is row Db + i of the product of column Db + j's seed.
        chain_nodes = len(constraints.free) // d
        block, row, column = np.meshgrid(np.arange(chain_nodes), np.arange(d), np.arange(d), indexing="ij")
        self.diagonal_rows = d * block + row
        self.diagonal_seeds = self.seed_of[d * block + column]
        self.upper_rows = self.diagonal_rows[:-1]
        self.upper_seeds = self.diagonal_seeds[1:]

    def products(self, hvp: Callable[[Array], Array], dtype) -> Array:
        """(S, F) `M @ seed` for every seed, from `hvp(seed) -> M @ seed` (F,)."""
        return jax.vmap(hvp)(jnp.asarray(self.seeds, dtype))

    def dense(self, products: Array) -> Array:
        """(F, F) the mass matrix: entry (r, s) is row r of the product of s's seed."""
        return jnp.where(self.coupled, products[self.seed_of[None, :], np.arange(products.shape[1])[:, None]], 0.0)

    def chain_blocks(self, products: Array) -> tuple[Array, Array]:
        """(n, D, D) diagonal and (n-1, D, D) upper (node b with b+1) blocks of a chain."""
        return products[self.diagonal_seeds, self.diagonal_rows], products[self.upper_seeds, self.upper_rows]
