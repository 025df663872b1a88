"""Energies and forces of a scene's rods in Cartesian node coordinates.

Contract: each function takes a concrete `Scene` and returns (or is) a pure function of
node arrays `q, qd` of shape (N, D); per-link quantities have shape (E,). Gravity acts
along -y. Nothing here builds constraints or solves anything: these are the inputs of
the constrained Euler-Lagrange transformer (`dynamics.acceleration_fn`).

A rod with ends at `q_i, q_j` has its centre of mass at the midpoint, mass `m`,
moment of inertia `I` about its centre, so `T = 1/2 m |v_cm|^2 + 1/2 I |omega_perp|^2`
and `V = m g y_cm`, in 2D and 3D alike (D = 2 or 3). In 3D a thin rod's spin about its
own axis is invisible to its two end nodes and no force here excites it, so only the
angular velocity perpendicular to the rod enters: `omega_perp = dq x dqd / |dq|^2`,
and for a rod of fixed length `|omega_perp|^2 l^2 = |dqd|^2`, so everything built on
the node description (the constant on-manifold mass, the solvers) carries over. Its mass matrix `d2T/dqd2` is singular along the rod (stretching costs
no kinetic energy), which the solver handles (`dynamics`); `constant_mass_lagrangian_fn`
is the regular on-manifold equivalent the structured solvers factor once.

A scene's point masses (`Scene.point_masses`) add `1/2 m |qd_k|^2` and `m g y_k` at
their nodes (`point_mass_energies`); scenes without them compute exactly as before.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from lgnn.scene import Scene

Array = jax.Array
LagrangianFn = Callable[[Array, Array], Array]
ForceFn = Callable[[Array, Array], Array]
EnergyFn = Callable[[Array, Array], Array]


def _link_kinematics(scene: Scene, q: Array, qd: Array):
    i, j = scene.edge_index.T
    dq = q[i] - q[j]
    dqd = qd[i] - qd[j]
    v_cm = 0.5 * (qd[i] + qd[j])
    return dq, dqd, v_cm


def angular_speed_squared(dq: Array, dqd: Array) -> Array:
    """|omega_perp|^2 of rods with axis `dq` and end-velocity difference `dqd` (..., D):
    in 2D the rod's omega^2, in 3D its angular velocity perpendicular to the rod.

    `|dq x dqd|^2 / |dq|^4`, written with Lagrange's identity
    `|a x b|^2 = |a|^2 |b|^2 - (a.b)^2` so it holds in 2D and 3D alike.
    """
    dq2 = jnp.sum(dq * dq, -1)
    cross2 = dq2 * jnp.sum(dqd * dqd, -1) - jnp.sum(dq * dqd, -1) ** 2
    return cross2 / dq2**2


def kinetic_energy_per_link(scene: Scene, q: Array, qd: Array) -> Array:
    """(E,) exact rod kinetic energy `1/2 m |v_cm|^2 + 1/2 I |omega_perp|^2`."""
    dq, dqd, v_cm = _link_kinematics(scene, q, qd)
    m, inertia = jnp.asarray(scene.masses), jnp.asarray(scene.inertias)
    return 0.5 * m * jnp.sum(v_cm * v_cm, -1) + 0.5 * inertia * angular_speed_squared(dq, dqd)


def potential_energy_per_link(scene: Scene, q: Array) -> Array:
    """(E,) gravitational energy `m g y_cm` (gravity along -y), `-m g . r_cm` where the
    scene's gravity also has lateral components."""
    i, j = scene.edge_index.T
    y_cm = 0.5 * (q[i, 1] + q[j, 1])
    energy = jnp.asarray(scene.masses) * jnp.asarray(scene.gravity) * y_cm
    if scene.lateral_gravity:
        lateral = [0, *range(2, scene.dim)]
        r_cm = 0.5 * (q[i][:, lateral] + q[j][:, lateral])
        energy = energy - jnp.asarray(scene.masses) * (r_cm @ jnp.asarray(scene.lateral_gravity, q.dtype))
    return energy


def point_mass_energies(scene: Scene, q: Array, qd: Array) -> tuple[Array, Array]:
    """The kinetic and potential energy `(T, V)` of the scene's point masses
    (`1/2 m |qd_k|^2`, `-m g . q_k`), zeros without any."""
    if not scene.point_masses:
        return jnp.zeros((), q.dtype), jnp.zeros((), q.dtype)
    nodes = np.array([node for node, _ in scene.point_masses])
    masses = jnp.asarray(np.array([mass for _, mass in scene.point_masses]), q.dtype)
    kinetic = 0.5 * jnp.sum(masses * jnp.sum(qd[nodes] ** 2, -1))
    return kinetic, -jnp.sum(masses * (q[nodes] @ jnp.asarray(scene.gravity_vector, q.dtype)))


def lagrangian_fn(scene: Scene) -> LagrangianFn:
    """The exact Lagrangian `L(q, qd) = T - V` of the scene's rods and point masses."""

    def lagrangian(q, qd):
        value = jnp.sum(kinetic_energy_per_link(scene, q, qd)) - jnp.sum(potential_energy_per_link(scene, q))
        if scene.point_masses:
            kinetic, potential = point_mass_energies(scene, q, qd)
            value = value + kinetic - potential
        return value

    return lagrangian


def constant_mass_lagrangian_fn(scene: Scene) -> LagrangianFn:
    """A Lagrangian equal to `lagrangian_fn` on the constraint manifold, with a constant,
    positive definite mass matrix: `1/2 m |v_cm|^2 + 1/2 (I / l^2) |dqd|^2 - V`.

    On the manifold `dq . dqd = 0` and `|dq| = l`, so `omega^2 = |dqd|^2 / l^2`; both give
    the same trajectories (tested). Used to cross-check the singular-`M` handling.
    """
    m, inertia, length = (jnp.asarray(a) for a in (scene.masses, scene.inertias, scene.lengths))

    def lagrangian(q, qd):
        _, dqd, v_cm = _link_kinematics(scene, q, qd)
        kinetic = 0.5 * m * jnp.sum(v_cm * v_cm, -1) + 0.5 * inertia / length**2 * jnp.sum(dqd * dqd, -1)
        value = jnp.sum(kinetic) - jnp.sum(potential_energy_per_link(scene, q))
        if scene.point_masses:
            point_kinetic, point_potential = point_mass_energies(scene, q, qd)
            value = value + point_kinetic - point_potential
        return value

    return lagrangian


def constant_node_mass(scene: Scene) -> np.ndarray:
    """(N*D, N*D) the constant mass matrix of `constant_mass_lagrangian_fn`, assembled
    from per-link blocks: a rod with ends a, b adds `m/4 + I/l^2` to the (a, a) and
    (b, b) blocks and `m/4 - I/l^2` to (a, b) and (b, a), and a point mass m at node k
    adds m to the (k, k) block, times the D x D identity."""
    n, d = scene.n_nodes, scene.dim
    mass = np.zeros((n, n))
    same = np.asarray(scene.masses) / 4 + np.asarray(scene.inertias) / np.asarray(scene.lengths) ** 2
    cross = np.asarray(scene.masses) / 4 - np.asarray(scene.inertias) / np.asarray(scene.lengths) ** 2
    a, b = scene.edge_index.T
    np.add.at(mass, (a, a), same)
    np.add.at(mass, (b, b), same)
    np.add.at(mass, (a, b), cross)
    np.add.at(mass, (b, a), cross)
    for node, point_mass in scene.point_masses:
        mass[node, node] += point_mass
    return np.kron(mass, np.eye(d))


def energy_fn(scene: Scene) -> EnergyFn:
    """The exact Hamiltonian `H(q, qd) = T + V` of the scene."""

    def energy(q, qd):
        value = jnp.sum(kinetic_energy_per_link(scene, q, qd)) + jnp.sum(potential_energy_per_link(scene, q))
        if scene.point_masses:
            kinetic, potential = point_mass_energies(scene, q, qd)
            value = value + kinetic + potential
        return value

    return energy


def hamiltonian_fn(lagrangian: LagrangianFn) -> EnergyFn:
    """`H = qd . dL/dqd - L` of any Lagrangian (for learned models)."""

    def hamiltonian(q, qd):
        value, momentum_dot_qd = jax.jvp(lambda v: lagrangian(q, v), (qd,), (qd,))
        return momentum_dot_qd - value

    return hamiltonian


def link_angular_velocity(dq: Array, dqd: Array) -> Array:
    """(...,) planar links' angular velocities `(dq x dqd) / |dq|^2` (D = 2); the sign
    does not depend on which end `dq` starts from."""
    return (dq[..., 0] * dqd[..., 1] - dq[..., 1] * dqd[..., 0]) / jnp.sum(dq * dq, -1)


def damping_force_fn(scene: Scene) -> ForceFn | None:
    """The joints' viscous damping (`Scene.dampers`, planar): the generalised force
    `-dD/dqd` of the dissipation `D = 1/2 sum damping (omega_e - omega_p)^2` (a pin's
    `omega_p` is 0), as MuJoCo's joint damping; `None` when the scene has none."""
    if not scene.dampers:
        return None
    i, j = scene.edge_index.T
    link, other, damping = (np.array(column) for column in zip(*scene.dampers))
    to_world = other < 0
    other = np.where(to_world, 0, other).astype(np.int64)
    link = link.astype(np.int64)

    def dissipation(q, qd):
        omega = link_angular_velocity(q[j] - q[i], qd[j] - qd[i])
        relative = omega[link] - jnp.where(to_world, 0.0, omega[other])
        return 0.5 * jnp.sum(jnp.asarray(damping, q.dtype) * relative**2)

    def force(q, qd):
        return -jax.grad(dissipation, argnums=1)(q, qd)

    return force


def rail_damping_force_fn(scene: Scene) -> ForceFn | None:
    """The rails' viscous damping (`Scene.rails`): `-damping * qd_k[axis]` along each
    damped rail, as MuJoCo's slide-joint damping; `None` when no rail is damped."""
    damped = [(node, axis, damping) for node, axis, damping in scene.rails if damping]
    if not damped:
        return None
    coefficients = np.zeros((scene.n_nodes, scene.dim))
    for node, axis, damping in damped:
        coefficients[node, axis] = damping

    def force(q, qd):
        return -jnp.asarray(coefficients, qd.dtype) * qd

    return force


def dissipative_force_fn(scene: Scene) -> ForceFn | None:
    """The scene's own non-conservative forces: drag, joint damping and rail damping
    (`None` without any)."""
    forces = [f for f in (drag_force_fn(scene), damping_force_fn(scene), rail_damping_force_fn(scene)) if f is not None]
    if not forces:
        return None
    if len(forces) == 1:
        return forces[0]
    return lambda q, qd: sum(f(q, qd) for f in forces)


def drag_force_fn(scene: Scene, coefficients: Array | None = None) -> ForceFn | None:
    """Linear drag: each link feels `-c * v_cm`, split equally between its two nodes.

    `coefficients` (E,) gives each link its own `c` (a learned drag); by default every
    link has the scene's `drag`, and the result is `None` when that is zero, so no drag
    term is built at all. Returns `force(q, qd) -> (N, D)`.
    """
    if coefficients is None and scene.drag == 0:
        return None
    # Each end gets half of `-c v_cm`, and `v_cm` is half the ends' velocity sum.
    scale = -0.25 * (scene.drag if coefficients is None else coefficients[:, None])
    i, j = scene.edge_index.T

    def force(q, qd):
        half = scale * (qd[i] + qd[j])
        return jnp.zeros_like(qd).at[i].add(half).at[j].add(half)

    return force
