"""A mass matrix with graph structure, assembled from a few derivative products.

Contract: `LocalMass(scene, constraints, reach)` holds static NumPy index arrays (a node
colouring and the maps from products to blocks); its methods are pure JAX functions.
`MassStructure` is what a Lagrangian declares about its mass matrix `d2L/dqd2`:

- local (`reach`): the mass matrix couples a node only with nodes at most `reach`
  links away (1: with itself and the nodes it shares a link with, as the exact rods and
  LGNN's per-link energies do). `M` is then recovered from one Hessian-vector product
  per (colour, coordinate) instead of one per coordinate: 3 x D for any chain at reach 1,
  (2 reach + 1) x D at any reach, whatever the chain's length.
- pooled (`features`, `readout`): `L = readout(p)` of features `p(q, qd)` (P,) that are a
  sum of local terms of that reach, as LGN's read-out of its summed node and edge
  embeddings. Then `M = J^T H J + S`: `J = dp/dqd` (P reverse products), `H` the
  read-out's P x P Hessian, and `S = sum_c dreadout/dp_c d2p_c/dqd2`, the Hessian of the
  local sum with the read-out's gradient held fixed, local again. The dense matrix is
  low rank plus local.

`MassStructure.products(local, dim)` counts the products a structure costs, so the solve
(`dynamics.acceleration_fn`) takes it only where it is cheaper than one product per
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
    # `features(q, qd) -> (P,)` and `readout(p) -> L` with `L = readout(features(q, qd))`,
    # the features a sum of terms of `reach`; None: `L` itself is such a sum.
    features: Callable | None = None
    readout: Callable | None = None
    # P, the number of features (reverse products for `J`); 0 when not pooled.
    n_features: int = 0

    def __post_init__(self):
        if self.reach < 1:
            raise ValueError(f"a mass structure's reach must be >= 1, got {self.reach}")
        if (self.features is None) != (self.readout is None) or (self.features is None) != (self.n_features == 0):
            raise ValueError("a pooled mass structure needs features, readout and their number together")

    @property
    def pooled(self) -> bool:
        return self.features is not None

    def products(self, local: "LocalMass", dim: int) -> int:
        """Derivative products that assemble the mass matrix with this structure."""
        return local.n_colours * dim + self.n_features


# Reach 1: the exact rods, LGNN's per-link energies.
LOCAL = MassStructure(1)


def _within(adjacency: list[set], start: int, reach: int) -> set:
    """Nodes at most `reach` links from `start` (breadth first)."""
    seen, frontier = {start}, deque([(start, 0)])
    while frontier:
        node, depth = frontier.popleft()
        if depth == reach:
            continue
        for near in adjacency[node] - seen:
            seen.add(near)
            frontier.append((near, depth + 1))
    return seen


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
        adjacency = [set() for _ in range(n)]
        for a, b in scene.edges:
            adjacency[a].add(b)
            adjacency[b].add(a)
        # The free nodes each free node couples to; two nodes coupled to a common one
        # must differ in colour.
        coupled_to = {node: {k for k in _within(adjacency, node, reach) if free_node[k]} for node in np.flatnonzero(free_node)}
        conflicts = {node: set() for node in coupled_to}
        for group in coupled_to.values():
            for node in group:
                conflicts[node] |= group
        colour = np.full(n, -1)
        for node in coupled_to:
            taken = {colour[k] for k in conflicts[node] if colour[k] >= 0}
            colour[node] = next(c for c in range(len(taken) + 1) if c not in taken)
        self.reach = reach
        self.n_colours = int(colour.max()) + 1 if free_node.any() else 0
        node_of = constraints.free // d
        coord_of = constraints.free % d
        # Seed (colour, coordinate) of each free coordinate, and the seeds as vectors.
        self.seed_of = colour[node_of] * d + coord_of
        self.seeds = np.zeros((self.n_colours * d, len(constraints.free)))
        self.seeds[self.seed_of, np.arange(len(constraints.free))] = 1.0
        adjacent = np.eye(n, dtype=bool)
        for node, group in coupled_to.items():
            adjacent[node, list(group)] = True
        self.coupled = adjacent[np.ix_(node_of, node_of)]
        # A chain pinned at node 0 has free coordinates Db + i for node b + 1, so its
        # block (b, i, j) is row Db + i of the product of column Db + j's seed (reach 1).
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
        """(n, D, D) diagonal and (n-1, D, D) upper (node b with b+1) blocks of a chain
        (reach 1 only: nothing else is nonzero)."""
        if self.reach != 1:
            raise ValueError("chain blocks hold a mass matrix of reach 1 only")
        return products[self.diagonal_seeds, self.diagonal_rows], products[self.upper_seeds, self.upper_rows]
