"""The constrained graph neural ODE (`cgnode`): a graph network's accelerations, made
to satisfy the scene's known constraints at the acceleration level.

The network is the strong GNS's (`strong_gns`: encoder, `L` unshared message-passing
steps with residuals, decoder; rod features length, mass and inertia on the edges, a
pinned/free node-type embedding, inputs normalised by training-set statistics, no
absolute position). Its output `a` (N, D) is a prediction of the accelerations; the
model's accelerations are the ones closest to it, in the metric of the rods' mass,
that satisfy the link constraints differentiated twice (Gauss's principle of least
constraint):

    qdd = argmin (qdd - a)^T M (qdd - a)   subject to   A qdd = -Adot qd,

that is the KKT system `[[M, A^T], [A, 0]] [qdd; lam] = [M a; -Adot qd]` over the
free coordinates, with `A` the Jacobian of the kept link-length rows
(`physics.Constraints`) and `M` the scene's constant on-manifold node mass
(`physics.constant_node_mass`: the rods' mass matrix in node coordinates is singular
along each rod, this equivalent of it on the constraint manifold is not; the ground
truth's structured solvers use the same). `M a` is the force the network implies, so
`a = M^-1 F` with the true forces `F` (gravity, drag) gives the ground truth exactly,
and any prediction that already satisfies the constraints is returned unchanged.
Why the mass metric and not the Euclidean one: the correction `qdd - a = -M^-1 A^T lam`
is then a constraint force, which does no work; the Euclidean projection removes the
constraint component of `a` as though every node had unit mass. `M` is built from the
same rod features (mass, inertia, length) the network reads, known scene data like
the constraints; the model does not learn it (LGNN, which learns its mass matrix, does
not read link masses).

The solve is the engine's: `solvers.solve_kkt` (regularised LU, refined) over the free
coordinates, or, on a chain pinned at node 0 of `system.CHAIN_SOLVER_MIN_LINKS` links
or more, `solvers.chain_kkt_solve` in time linear in its length, as
`physics.acceleration_fn` does for a graph-local mass. Pinned nodes are not unknowns:
their acceleration is zero. Rollouts integrate these accelerations through the
ground truth's integrators and project positions and velocities after each step like
every model's (`engines.base.Integration`).

Contract (pure functions; `config` is a `ModelConfig`):
- `statistics`, `init`: the strong GNS's (`strong_gns.statistics`, `strong_gns.init`);
- `acceleration(config, params, scene) -> accel(q, qd) -> qdd` (N, D), zero at pins;
- `node_mass(scene, masses, inertias) -> (N, N)`: the constant on-manifold node mass
  of rods of the given (E,) masses and inertias (times the D x D identity);
- `constrained_solve_fn(scene) -> solve(node_mass, q, qd, force) -> qdd`: the
  accelerations of a constant node mass (N, N) under forces (N, D) and the scene's
  constraints (shared with `chgn`).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from lgnn.learn.models import strong_gns
from lgnn.learn.models.registry import ModelSpec, register
from lgnn.physics.solvers import chain_kkt_solve, solve_kkt
from lgnn.physics.system import prepare
from lgnn.runtime import full_precision_matmuls
from lgnn.scene import Scene

statistics = strong_gns.statistics
init = strong_gns.init


def node_mass(scene: Scene, masses, inertias):
    """(N, N) the constant on-manifold mass of rods with masses and inertias (E,) about
    their centres (the scene's lengths), per pair of nodes; times the D x D identity it
    is `physics.constant_node_mass` (tested). A rod with ends a, b adds `m/4 + I/l^2`
    at (a, a) and (b, b) and `m/4 - I/l^2` at (a, b) and (b, a): positive definite on
    its two nodes exactly when `m > 0` and `I > 0`."""
    a, b = scene.edge_index.T
    masses = jnp.asarray(masses)
    rotation = jnp.asarray(inertias) / jnp.asarray(scene.lengths, masses.dtype) ** 2
    same, cross = masses / 4 + rotation, masses / 4 - rotation
    mass = jnp.zeros((scene.n_nodes, scene.n_nodes), masses.dtype)
    return mass.at[a, a].add(same).at[b, b].add(same).at[a, b].add(cross).at[b, a].add(cross)


def constrained_solve_fn(scene: Scene, structured: bool = True):
    """`solve(node_mass, q, qd, force) -> qdd` (N, D): the accelerations of the constant
    node mass `node_mass` (N, N) (times the D x D identity), positive definite on the
    motions that keep link lengths, under generalised forces `force` (N, D) and the
    scene's link constraints at the acceleration level: `M qdd + A^T lam = force`,
    `A qdd = -Adot qd` over the free coordinates, zero at the pins. `structured=False`
    forces the dense solve on long pinned chains (for tests)."""
    system = prepare(scene)
    constraints = system.constraints
    n, d = constraints.shape
    chain = structured and system.long_chain

    def solve(mass, q, qd, force):
        if chain:
            nodes = np.arange(1, n)
            identity = jnp.eye(d, dtype=q.dtype)
            diagonal = mass[nodes, nodes][:, None, None] * identity
            upper = mass[nodes[:-1], nodes[1:]][:, None, None] * identity
            accel = chain_kkt_solve(diagonal, upper, constraints.link_directions(q), force[1:], -constraints.link_speed_terms(qd), regularised=True)
            return jnp.concatenate([jnp.zeros((1, d), q.dtype), accel])
        free = jnp.asarray(constraints.free)
        full = jnp.kron(mass, jnp.eye(d, dtype=mass.dtype))
        x, v = constraints.restrict(q), constraints.restrict(qd)
        xdd = solve_kkt(full[free][:, free], constraints.jacobian(x), constraints.restrict(force), -constraints.jacobian_dot_v(x, v))
        return constraints.embed_velocity(xdd)

    return full_precision_matmuls(solve)


def acceleration(config, params: dict, scene: Scene):
    """`accel(q, qd) -> qdd` (N, D): the network's prediction made to satisfy the
    constraints in the mass metric (module docstring)."""
    network = strong_gns.acceleration(config, params, scene)
    mass = node_mass(scene, np.asarray(scene.masses, np.float64), np.asarray(scene.inertias, np.float64))
    solve = constrained_solve_fn(scene)

    def accel(q, qd):
        m = jnp.asarray(mass, q.dtype)
        # The force the prediction implies, `M a` (at the pins too: their rows are not unknowns).
        return solve(m, q, qd, m @ network(q, qd))

    return accel


# The strong GNS's network and recipe, its accelerations made to satisfy the
# constraints in the rods' mass metric.
CGNODE = register(ModelSpec(
    "cgnode", init, acceleration=acceleration, statistics=statistics,
    latent=128, hidden=128, message_passing=10, weight_decay=1e-8, velocity_noise=5e-4,
))
