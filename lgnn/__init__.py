"""lgnn: a MuJoCo-validated benchmark suite for learned dynamics of articulated rigid bodies.

The public interface, by lifecycle stage:
- scenes: `Scene`, `State`, `get_scene`, `BUILTIN_SCENES`, `scene_from_dict`,
  `load_scene_file`, `sample_initial_states`;
- physics: `lgnn.physics` (Lagrangians, constraints, the constrained Euler-Lagrange
  solve as a function transformer);
- integration: `lgnn.integrate` (RK4, velocity Verlet, rollouts);
- the ground-truth engine: `SimulationConfig`, `simulate`, `Trajectory`.
- learned models: `lgnn.graphs` (graph features), `lgnn.models` (LGNN, GNS, LGN, CLNN),
  `lgnn.data` (cached training data), `lgnn.train` (training, checkpoints).
"""

import os as _os

# The dense systems solved here are small (at most a few hundred unknowns), where
# OpenBLAS's thread pool (used by numpy, scipy and jaxlib's CPU LAPACK) only adds
# contention: a 300x300 LU took 83 ms with it and 3 ms without on 2 cores. Set before
# numpy loads OpenBLAS; an explicit setting by the user wins.
_os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
# XLA's CPU concurrency-optimised scheduler deadlocks (all threads idle, forever) on
# vmapped rollouts whose steps hold several batched LAPACK calls (measured: chain16 x
# 100, one RK4 step with projection, jax 0.10). Read when the CPU backend starts.
_DEADLOCK_FLAG = "--xla_cpu_enable_concurrency_optimized_scheduler=false"
if _DEADLOCK_FLAG not in _os.environ.get("XLA_FLAGS", ""):
    _os.environ["XLA_FLAGS"] = (_os.environ.get("XLA_FLAGS", "") + " " + _DEADLOCK_FLAG).strip()

from lgnn.errors import ConfigError, LgnnError, SceneError, SimulationError
from lgnn.scene import Scene, State, load_scene_file, scene_from_dict, scene_to_dict, scene_to_json
from lgnn.scenes import BUILTIN_SCENES, get_scene, sample_initial_states
from lgnn.simulate import SimulationConfig, Trajectory, simulate

__version__ = "0.1.0"

__all__ = [
    "BUILTIN_SCENES",
    "ConfigError",
    "LgnnError",
    "Scene",
    "SceneError",
    "SimulationConfig",
    "SimulationError",
    "State",
    "Trajectory",
    "get_scene",
    "load_scene_file",
    "sample_initial_states",
    "scene_from_dict",
    "scene_to_dict",
    "scene_to_json",
    "simulate",
]
