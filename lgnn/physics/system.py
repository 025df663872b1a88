"""`prepare(scene) -> System`: everything static about a scene, computed once.

Contract: a `System` is immutable and holds only NumPy data and plain Python values
derived from its scene (no JAX arrays, no compiled functions), each computed on first
use and kept (`functools.cached_property`), so a caller that needs only the free
coordinates never pays for a QR, an SVD or a mass factorisation:

- `constraints`: free coordinates and mask, the kept rows (pivoted QR) and the
  self-stresses at the initial configuration (SVD), see `constraints.Constraints`;
- `gram`: the sparsity of `A A^T` for the projection (`solvers.LinkGram`);
- `local_mass(reach)`: the node colouring of a graph-local mass matrix of that reach;
- `pooled_jacobian(supports)`: the node colouring of the Jacobian of pooled local terms;
- `regular_mass`, `schur_inverse`, `chain_mass_blocks`, `node_gravity`: the constant
  node mass of the exact rods (`energies.constant_node_mass`), whether it is regular on
  the free nodes, its inverse, its chain blocks, and the weight on the free nodes;
- `solver(...)`: which ground-truth solver applies.

`prepare` is cached on the scene's *content* (`Scene` compares and hashes by
`content_key`), so two equal scenes built separately share one System, and every
factory of this package (`acceleration_fn`, `true_acceleration_fn`, `projection_fn`)
gets its static data from it instead of rebuilding it per call.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from lgnn.errors import SceneError
from lgnn.physics.constraints import Constraints
from lgnn.physics.energies import constant_node_mass
from lgnn.physics.local_mass import ChainBandMass, LocalMass, PooledJacobian
from lgnn.physics.solvers import LinkGram
from lgnn.scene import Scene, is_pinned_chain

# The ground-truth solvers of `dynamics.true_acceleration_fn`.
SOLVERS = ("auto", "generic", "schur", "chain")
# Chains of at least this many links use the linear-time block elimination; shorter
# ones the dense solves, whose fixed cost is lower. Measured per RK4 step on one core
# (schur / chain): 16 links 23 / 41 us, 64 links 123 / 156 us, 100 links 289 / 237 us.
CHAIN_SOLVER_MIN_LINKS = 80
# A constant mass matrix is regular when its smallest eigenvalue exceeds this fraction
# of its largest entry (a link of zero inertia or a node no link touches gives 0).
REGULAR_MASS_TOLERANCE = 1e-12


@dataclasses.dataclass(frozen=True)
class System:
    """The static data of `scene`, each part computed on first use (module docstring).
    Build it with `prepare(scene)`, which shares one System per scene content."""

    scene: Scene

    @functools.cached_property
    def constraints(self) -> Constraints:
        return Constraints(self.scene)

    @functools.cached_property
    def gram(self) -> LinkGram:
        return LinkGram(self.constraints)

    @functools.cached_property
    def _local_masses(self) -> dict:
        return {}

    def local_mass(self, reach: int = 1) -> LocalMass | ChainBandMass:
        """The colouring of a mass matrix coupling nodes at most `reach` links apart: on
        a long pinned chain, whose KKT system the block elimination takes, the
        symmetric one of reach + 1 colours (`ChainBandMass`), elsewhere the general one
        (`LocalMass`)."""
        if reach not in self._local_masses:
            self._local_masses[reach] = ChainBandMass(self.constraints, reach) if self.long_chain else LocalMass(self.scene, self.constraints, reach)
        return self._local_masses[reach]

    @functools.cached_property
    def _pooled_jacobians(self) -> dict:
        return {}

    def pooled_jacobian(self, supports: tuple[tuple[int, ...], ...]) -> PooledJacobian:
        """The colouring of the Jacobian of a sum of terms with these node supports."""
        if supports not in self._pooled_jacobians:
            self._pooled_jacobians[supports] = PooledJacobian(self.constraints, supports)
        return self._pooled_jacobians[supports]

    @functools.cached_property
    def is_pinned_chain(self) -> bool:
        return is_pinned_chain(self.scene)

    @property
    def long_chain(self) -> bool:
        """A chain pinned at node 0 long enough for the linear-time elimination."""
        return self.is_pinned_chain and self.scene.n_links >= CHAIN_SOLVER_MIN_LINKS

    def _free_node_mass(self) -> np.ndarray:
        free = self.constraints.free
        return constant_node_mass(self.scene)[np.ix_(free, free)]

    @functools.cached_property
    def regular_mass(self) -> bool:
        """Whether the constant node mass is positive definite on the free coordinates."""
        mass = self._free_node_mass()
        return len(mass) == 0 or np.linalg.eigvalsh(mass).min() > REGULAR_MASS_TOLERANCE * np.abs(mass).max()

    @functools.cached_property
    def schur_inverse(self) -> np.ndarray:
        """(N, D, N, D) the inverse of the constant node mass on the free coordinates,
        zero at the pinned ones."""
        n, d = self.constraints.shape
        free = self.constraints.free
        inverse = np.zeros((n * d, n * d))
        inverse[np.ix_(free, free)] = np.linalg.inv(self._free_node_mass())
        return inverse.reshape(n, d, n, d)

    @functools.cached_property
    def chain_mass_blocks(self) -> tuple[np.ndarray, np.ndarray]:
        """(n, D, D) diagonal blocks (nodes 1..n) and (n-1, D, D) upper blocks (node b
        with b+1) of the constant node mass of a chain of n links pinned at node 0."""
        n, d = self.scene.n_links, self.scene.dim
        node_mass = constant_node_mass(self.scene).reshape(n + 1, d, n + 1, d)
        return node_mass[np.arange(1, n + 1), :, np.arange(1, n + 1), :], node_mass[np.arange(1, n), :, np.arange(2, n + 1), :]

    @functools.cached_property
    def node_gravity(self) -> np.ndarray:
        """(N, D) the generalised gravity force on the free nodes: half of each link's
        weight on each of its ends, zero at the pins."""
        scene = self.scene
        gravity = np.zeros((scene.n_nodes, scene.dim))
        weight = np.asarray(scene.masses) * float(scene.gravity) / 2
        np.add.at(gravity[:, 1], scene.edge_index[:, 0], -weight)
        np.add.at(gravity[:, 1], scene.edge_index[:, 1], -weight)
        if scene.lateral_gravity:  # the same split of the weight along the other axes
            for axis, component in zip((0, *range(2, scene.dim)), scene.lateral_gravity):
                for end in (0, 1):
                    np.add.at(gravity[:, axis], scene.edge_index[:, end], np.asarray(scene.masses) * component / 2)
        for node, mass in scene.point_masses:
            gravity[node] += mass * scene.gravity_vector
        return gravity * self.constraints.free_mask.astype(np.float64)

    def solver(self, requested: str = "auto", vectorised: bool = False) -> str:
        """The ground-truth solver to use (`dynamics.true_acceleration_fn`): `requested`
        itself when it applies (ValueError when not), or for "auto" "generic" on
        self-stressed scenes and singular constant masses, else "chain" on pinned
        chains from `CHAIN_SOLVER_MIN_LINKS` links (any length when `vectorised`),
        else "schur"."""
        if requested not in SOLVERS:
            raise ValueError(f"unknown solver {requested!r}")
        scene = self.scene
        if requested == "auto":
            if self.constraints.self_stresses or not self.regular_mass:
                return "generic"
            long_enough = vectorised or scene.n_links >= CHAIN_SOLVER_MIN_LINKS
            return "chain" if self.is_pinned_chain and long_enough else "schur"
        if requested == "generic":
            return requested
        if not self.regular_mass:
            raise ValueError(f"{scene.name}: the constant mass matrix is singular; use the generic solver")
        if requested == "chain" and not self.is_pinned_chain:
            raise ValueError(f"{scene.name}: the chain solver needs a chain pinned at node 0")
        return requested


# Coordinates (nodes x dimension) of the largest scene prepared: the constant node mass
# and the constraint Jacobian are dense (coordinates^2 and links x coordinates float64),
# 2 GiB each at this size; a 100 000-node chain would need 149 GiB. Refused before any
# allocation, naming the limit.
MAX_COORDINATES = 16_384


@functools.lru_cache(maxsize=64)
def prepare(scene: Scene) -> System:
    """The `System` of `scene`, shared by every scene of the same content; `SceneError`
    (one line) for a scene above `MAX_COORDINATES`."""
    if scene.n_nodes * scene.dim > MAX_COORDINATES:
        raise SceneError(f"scene {scene.name!r}: {scene.n_nodes} nodes in {scene.dim}D are {scene.n_nodes * scene.dim} coordinates, "
                         f"more than the {MAX_COORDINATES} this solver holds in dense matrices")
    return System(scene)
