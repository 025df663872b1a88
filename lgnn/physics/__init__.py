"""Constrained Lagrangian mechanics of a scene in Cartesian node coordinates.

Contract: every factory here takes a concrete `Scene` and returns pure functions of node
arrays `q, qd` of shape (N, D) (no batching: `vmap` them; nothing here calls `jit`, but `sample_initial_conditions`,
which returns checked NumPy arrays).
Use float64 (`lgnn.configure()`) where accuracy matters.

One module per idea, from the bottom up:
- `energies`: rod kinematics, kinetic and potential energy, the exact and the
  constant-mass Lagrangians, the Hamiltonian of any Lagrangian, linear drag;
- `constraints`: the independent link-length rows over the free coordinates
  (`Constraints`: exact pins, redundant rows dropped by a pivoted QR, self-stresses
  counted by an SVD) and the violation measures;
- `solvers`: the regularised KKT, Schur-complement, chain-elimination and Gram solves,
  all refined by one routine, `refine`; no pseudo-inverse anywhere;
- `local_mass`: what a Lagrangian declares about its mass matrix (`MassStructure`:
  graph-local of some reach, or a read-out of pooled local features) and its assembly
  from coloured derivative products;
- `system`: `prepare(scene) -> System`, everything static about a scene computed
  once, cached by scene content;
- `dynamics`: the Euler-Lagrange transformer `acceleration_fn(scene, lagrangian,
  force_fn)` (true and learned Lagrangians go through the same solve), the equations'
  pieces it solves (`euler_lagrange`), and the ground-truth `true_acceleration_fn`;
- `projection`: `projection_fn`, back onto the constraint manifold after a step;
- `sampling`: `sample_initial_conditions(scene, count, seed)`, random initial states of
  any scene on its constraint manifold; `sample_states` (the paper's chain sampler where
  it applies); `own_or_sampled_states`, `lgnn evaluate`'s rule; `benchmark_initial_states`,
  the benchmark's rule.
"""

from lgnn.physics.constraints import Constraints, constraint_violation, velocity_constraint_violation
from lgnn.physics.dynamics import (
    AccelerationFn,
    EulerLagrange,
    acceleration_fn,
    euler_lagrange,
    mass_matrix_fn,
    parametrised_acceleration_fn,
    true_acceleration_fn,
    uses_mass_structure,
    uses_tangent_solve,
    vectorised_true_acceleration_fn,
)
from lgnn.physics.energies import (
    ForceFn,
    LagrangianFn,
    angular_speed_squared,
    constant_mass_lagrangian_fn,
    constant_node_mass,
    damping_force_fn,
    dissipative_force_fn,
    drag_force_fn,
    energy_fn,
    hamiltonian_fn,
    kinetic_energy_per_link,
    lagrangian_fn,
    point_mass_energies,
    potential_energy_per_link,
    rail_damping_force_fn,
)
from lgnn.physics.local_mass import LOCAL, MassStructure, neighbourhoods
from lgnn.physics.projection import projection_fn
from lgnn.physics.sampling import benchmark_initial_states, own_or_sampled_states, sample_initial_conditions, sample_states
from lgnn.physics.solvers import refine
from lgnn.physics.system import System, prepare

__all__ = [
    "AccelerationFn",
    "Constraints",
    "EulerLagrange",
    "ForceFn",
    "LOCAL",
    "LagrangianFn",
    "MassStructure",
    "System",
    "acceleration_fn",
    "angular_speed_squared",
    "benchmark_initial_states",
    "constant_mass_lagrangian_fn",
    "constant_node_mass",
    "constraint_violation",
    "damping_force_fn",
    "dissipative_force_fn",
    "drag_force_fn",
    "energy_fn",
    "euler_lagrange",
    "hamiltonian_fn",
    "kinetic_energy_per_link",
    "lagrangian_fn",
    "mass_matrix_fn",
    "neighbourhoods",
    "own_or_sampled_states",
    "parametrised_acceleration_fn",
    "point_mass_energies",
    "potential_energy_per_link",
    "prepare",
    "projection_fn",
    "rail_damping_force_fn",
    "refine",
    "sample_initial_conditions",
    "sample_states",
    "true_acceleration_fn",
    "uses_mass_structure",
    "uses_tangent_solve",
    "vectorised_true_acceleration_fn",
    "velocity_constraint_violation",
]
