"""Engines: everything that turns a scene and initial states into a `Trajectory`.

- `lagrangian`: the exact constrained Lagrangian engine (`simulate`, `rollout_fn`),
  `SimulationConfig`, `Trajectory`;
- `mujoco`: MJCF rendering, MuJoCo C and MJX (the only module that imports mujoco).
"""
