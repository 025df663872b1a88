"""lgnn: a MuJoCo-validated benchmark suite for learned dynamics of articulated rigid bodies.

The public interface, by lifecycle stage (layers from the bottom; see ARCHITECTURE.md):
- set-up: `configure()` (float64, thread counts, XLA flags), optional, to call first;
  the computing entry points run in float64 without it (`precision(dtype)`, the
  context they use, and float32 only when asked: `get_engine(name, dtype="float32")`);
- scenes (`lgnn.scene`): `Scene`, `State`, `get_scene`, `CATALOGUE`,
  `scene_from_dict`, `load_scene_file`, `sample_initial_states`;
- physics (`lgnn.physics`): `prepare(scene) -> System` (everything static about a
  scene, computed once and cached by content), Lagrangians, constraints, the
  constrained Euler-Lagrange solve as a function transformer; integration
  (`lgnn.integrate`): RK4, Verlet, rollouts;
- metrics (`lgnn.metrics`): one definition each of energy drift, divergence,
  constraint violation, rollout and energy error and their statistics;
- engines (`lgnn.engines`): one interface, `get_engine(name).rollout(scene, config,
  states) -> Trajectory` with neutral settings (`SimulationConfig`: dt, frame
  interval, duration), for the Lagrangian ground truth (`simulate`; its integrator
  and projection an `Integration`), MuJoCo C and MJX (MJCF rendered by `lgnn.engines.mjcf`);
- learned models (`lgnn.learn`): graph features, a model registry (LGNN, GNS, LGN,
  CLNN), data, training; a model as an engine (`lgnn.learn.models.ModelEngine`);
- records (`lgnn.records`): the one on-disk format of datasets, checkpoints and
  benchmark records (arrays, JSON meta, checksum, provenance);
- the benchmark (`lgnn.bench`: grid, stages, report, crosscheck, stability), the
  command line (`lgnn.cli`); for notebooks `train`, `evaluate`, `benchmark` and
  `load_results` (pandas DataFrames), as the commands do (`lgnn.bench.api`).

`import lgnn` loads nothing heavy and changes nothing outside the package (no
environment variable, no JAX setting): the names below are imported on first use, and
runtime set-up is the explicit `configure()`.
"""

import importlib

__version__ = "0.1.0"

# Public name -> the module that defines it; imported on first access (PEP 562), so
# `import lgnn` followed by `lgnn.configure()` can still set the environment before
# numpy and JAX load.
_PUBLIC = {
    "configure": "lgnn.runtime",
    "ConfigError": "lgnn.errors",
    "LgnnError": "lgnn.errors",
    "SceneError": "lgnn.errors",
    "SimulationError": "lgnn.errors",
    "CATALOGUE": "lgnn.scene",
    "Scene": "lgnn.scene",
    "State": "lgnn.scene",
    "get_scene": "lgnn.scene",
    "import_mjcf": "lgnn.engines.mjcf_import",
    "load_scene_file": "lgnn.scene",
    "sample_initial_states": "lgnn.scene",
    "scene_from_dict": "lgnn.scene",
    "scene_to_dict": "lgnn.scene",
    "scene_to_json": "lgnn.scene",
    "Integration": "lgnn.engines.base",
    "SimulationConfig": "lgnn.engines.base",
    "Trajectory": "lgnn.engines.base",
    "simulate": "lgnn.engines.lagrangian",
    "get_engine": "lgnn.engines",
    "ENGINES": "lgnn.engines",
    "batch_of_one": "lgnn.engines",
    "precision": "lgnn.runtime",
    "energy_drift": "lgnn.metrics",
    "train": "lgnn.bench.api",
    "evaluate": "lgnn.bench.api",
    "benchmark": "lgnn.bench.api",
    "load_results": "lgnn.bench.api",
}

__all__ = sorted(_PUBLIC)


def __getattr__(name: str):
    if name in _PUBLIC:
        return getattr(importlib.import_module(_PUBLIC[name]), name)
    raise AttributeError(f"module 'lgnn' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + __all__)
