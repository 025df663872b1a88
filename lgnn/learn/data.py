"""Training data from the ground truth, cached on disk.

Paper text (SPEC): 100 trajectories of the scene from the paper's chain sampler
(`physics.benchmark_initial_states`; a user's scene gets `physics.sample_initial_conditions`),
each 1 s with a state every 0.01 s (100 states, t = 0 .. 0.99 s), 10 000 states in
all, split at random 75:25 into training and validation states. Trajectories are integrated with the ground-truth engine's RK4 at dt 1e-4 with
projection onto the constraints. The targets are the exact accelerations
`physics.true_acceleration_fn(scene)` at the saved states (the paper's code used a
central finite difference of the positions, whose O(dt^2) error we avoid).

Varied draws (`DataConfig.varied_draws = K`, the transfer track): the trajectories come
from K chains as long as the named one, of its dimension, each link's properties drawn by the
varied-chain rule (`lgnn.scene.varied_chain`, seeds `VARIED_DRAW_SEED + k`),
`n_trajectories / K` from each, and `Dataset.draw` says which draw each state is of
(`draw_scenes(config)` the draws' scenes, in order). The split stays one random split of
all states.

`load_or_generate(config, cache_dir)` returns a `Dataset`. The cache file is an
`lgnn.records` record whose name holds a hash of the generating settings (`DataConfig`,
the scene's full description, the lgnn version, the format) and whose meta repeats those
settings (checksummed with the arrays); a file that fails either check is reported on
stderr and regenerated, never used.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import sys
from pathlib import Path
from typing import Literal, NamedTuple

import jax
import numpy as np

from lgnn import physics, sharding
from lgnn import records
from lgnn.errors import ConfigError, check_number
from lgnn.files import user_cache_dir
from lgnn.runtime import in_float64
from lgnn.scene import Scene, get_scene, is_pinned_chain, scene_to_dict, varied_chain
from lgnn.engines.base import Integration, SimulationConfig
from lgnn.engines.lagrangian import rollout_fn

# 2: an `lgnn.records` record (1: its own layout and checksum); part of the key, so
# caches of another format are regenerated, never misread.
DATA_FORMAT = 2
ARRAY_KEYS = ("q", "qd", "qdd", "trajectory", "train", "val", "draw")
# Seeds of the varied draws (`varied_chain(n, VARIED_DRAW_SEED + k)`): none of the
# built-in varied chains' seeds (their lengths, 8, 16 and 100), so no draw is a scene
# the transfer track evaluates on.
VARIED_DRAW_SEED = 1000
# States kept per trajectory at most (the paper's 100; a million is already gigabytes
# of data for the smallest scene's 100 trajectories).
MAX_STATES_PER_TRAJECTORY = 1e6


@dataclasses.dataclass(frozen=True)
class DataConfig:
    # Built-in scene name or scene JSON file.
    scene: str = "chain4"
    # Paper text: 100 trajectories from random initial conditions.
    n_trajectories: int = 100
    # Each trajectory 1 s with a state every 0.01 s: 100 states, 10 000 in all.
    duration: float = 1.0
    sample_dt: float = 0.01
    # Ground-truth integration: RK4 at 1e-4 s (simulate's default, error < 1e-6).
    integrator: str = "rk4"
    dt: float = 1e-4
    # Paper: random 75:25 train/validation split of the states.
    train_fraction: float = 0.75
    # Seed of the initial conditions and of the split.
    seed: int = 0
    # Trajectories integrated per vmapped call on a CPU (the progress bar's steps; an
    # accelerator integrates each draw's trajectories in one call); not in the key.
    chunk: int = 10
    # 0: the scene itself. K > 0: K draws of a planar chain as long as the scene, its
    # links' properties by the varied-chain rule (module docstring), the trajectories
    # shared equally among them. In keys only when set (caches and checkpoints made
    # before it keep theirs).
    varied_draws: int = dataclasses.field(default=0, metadata=records.KEY_UNLESS_DEFAULT)

    def __post_init__(self):
        for name in ("duration", "sample_dt", "dt"):
            check_number(f"training data {name}", getattr(self, name))
        if self.chunk < 1:
            raise ConfigError(f"training data chunk must be >= 1, got {self.chunk}")
        if not self.duration / self.sample_dt <= MAX_STATES_PER_TRAJECTORY:
            raise ConfigError(f"training data duration {self.duration:g} holds more than {MAX_STATES_PER_TRAJECTORY:.0e} states at sample_dt {self.sample_dt:g}")
        if self.n_trajectories < 1:
            raise ConfigError(f"need at least one trajectory, got {self.n_trajectories}")
        if isinstance(self.varied_draws, bool) or not isinstance(self.varied_draws, int) or self.varied_draws < 0:
            raise ConfigError(f"varied draws must be a whole number >= 0, got {self.varied_draws!r}")
        if self.varied_draws and self.n_trajectories % self.varied_draws:
            raise ConfigError(f"{self.n_trajectories} trajectories cannot be shared equally among {self.varied_draws} varied draws")
        if not 0 < self.train_fraction < 1:
            raise ConfigError(f"train fraction must be in (0, 1), got {self.train_fraction}")
        if self.states_per_trajectory < 2:
            raise ConfigError(f"duration {self.duration:g} holds fewer than 2 states at sample-dt {self.sample_dt:g}")
        self.simulation  # validates dt / sample_dt
        self.integration  # validates the integrator's name

    @property
    def states_per_trajectory(self) -> int:
        return round(self.duration / self.sample_dt)

    @property
    def simulation(self) -> SimulationConfig:
        n = self.states_per_trajectory - 1
        return SimulationConfig(self.dt, self.sample_dt, n * self.sample_dt)

    @property
    def integration(self) -> Integration:
        """The ground truth's integration: `integrator`, projected."""
        return Integration(self.integrator, project=True)

    def to_dict(self) -> dict:
        """The settings as checkpoints and records keep them (`records.settings_key`)."""
        return records.settings_key(self)

    def key(self, scene: Scene) -> dict:
        """Everything the data depend on (the cache key)."""
        from lgnn import __version__

        settings = {k: v for k, v in self.to_dict().items() if k != "chunk"}
        return {"format": DATA_FORMAT, "lgnn": __version__, "settings": settings, "scene": scene_to_dict(scene)}


def draw_scenes(config: DataConfig) -> tuple[Scene, ...]:
    """The scenes the data come from: the named scene, or its varied draws (module
    docstring), which need a chain pinned at one end; the draws have its dimension."""
    scene = get_scene(config.scene)
    if not config.varied_draws:
        return (scene,)
    if not is_pinned_chain(scene):
        raise ConfigError(f"varied draws need a chain pinned at one end; {scene.name!r} is not one")
    return tuple(varied_chain(scene.n_links, VARIED_DRAW_SEED + k, name=f"{scene.name}-draw{k}", dim=scene.dim)
                 for k in range(config.varied_draws))


class Dataset(NamedTuple):
    """States `q, qd` and targets `qdd`, each (S, N, D); `trajectory` (S,) the source
    trajectory of each state; `train`, `val` index arrays of the split; `draw` (S,) the
    varied draw each state is of (`draw_scenes`; zeros without draws)."""

    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    trajectory: np.ndarray
    train: np.ndarray
    val: np.ndarray
    draw: np.ndarray


@in_float64
def generate(config: DataConfig, progress: bool = False) -> Dataset:
    """Integrate the trajectories and compute exact accelerations (module docstring)."""
    from tqdm.auto import tqdm

    scenes = draw_scenes(config)
    per_draw = config.n_trajectories // len(scenes)
    label = get_scene(config.scene).name + (f" ({config.varied_draws} varied draws)" if config.varied_draws else "")
    qs, qds, qdds = [], [], []
    with tqdm(total=config.n_trajectories, desc=f"data {label}", unit="traj", disable=not progress, leave=False) as bar:
        for k, scene in enumerate(scenes):
            run, targets = _compiled(scene, config.simulation, config.integration)
            # Draw k's initial conditions from seed + 1000 k: without draws, the data seed itself.
            initial_q, initial_qd = physics.benchmark_initial_states(scene, per_draw, config.seed + 1000 * k)
            # One batch shape for every call (the last batch padded): one compile, sharded
            # over every local device. On an accelerator a rollout is latency-bound, so a
            # call of 10 trajectories takes about as long as one of 100: chain4's data
            # took 10 calls of about 1.4 s each after an 11 s compile on one H200
            # (results/gpu/training/README.md); there the whole draw is one call.
            size = sharding.padded_size(per_draw if sharding.platform() != "cpu" else min(config.chunk, per_draw))
            for start in range(0, per_draw, size):
                take = min(size, per_draw - start)
                frames = run(*(sharding.pad_batch(a[start : start + take], size) for a in (initial_q, initial_qd)))
                q = frames.q.reshape(-1, scene.n_nodes, scene.dim)
                qd = frames.qd.reshape(q.shape)
                states = take * config.states_per_trajectory
                qs.append(np.asarray(q)[:states])
                qds.append(np.asarray(qd)[:states])
                qdds.append(np.asarray(targets(q, qd))[:states])
                bar.update(take)
    q, qd, qdd = (np.concatenate(a) for a in (qs, qds, qdds))
    if not (np.isfinite(q).all() and np.isfinite(qd).all() and np.isfinite(qdd).all()):
        raise ConfigError(f"data for {label}: the ground truth produced non-finite states; try a smaller dt")
    count = len(q)
    order = np.random.default_rng(config.seed).permutation(count)
    n_train = round(config.train_fraction * count)
    trajectory = np.repeat(np.arange(config.n_trajectories), config.states_per_trajectory)
    draw = np.repeat(np.arange(len(scenes)), per_draw * config.states_per_trajectory)
    return Dataset(q, qd, qdd, trajectory, np.sort(order[:n_train]), np.sort(order[n_train:]), draw)


@functools.lru_cache(maxsize=8)
def _compiled(scene: Scene, sim: SimulationConfig, integration: Integration):
    """Jitted, vmapped trajectory and target functions, cached per scene content,
    settings and integration (regenerating a cache in the same process does not recompile)."""
    run = sharding.batch_jit(jax.vmap(rollout_fn(scene, sim, physics.vectorised_true_acceleration_fn, integration)))
    return run, sharding.batch_jit(jax.vmap(physics.vectorised_true_acceleration_fn(scene)))


def cache_path(config: DataConfig, cache_dir: str | os.PathLike) -> Path:
    scene = get_scene(config.scene)
    safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in scene.name)
    return Path(cache_dir) / f"data-{safe}-{records.digest(config.key(scene))[:16]}.npz"


def save(dataset: Dataset, config: DataConfig, path: str | os.PathLike) -> None:
    """Write `dataset` as an `lgnn.records` record whose meta holds the settings key."""
    records.save(path, dataset._asdict(), {"key": config.key(get_scene(config.scene))})


def load(config: DataConfig, path: str | os.PathLike) -> Dataset:
    """Read a cached dataset; raises `ConfigError` (one line) if it is corrupt or stale."""
    try:
        arrays, meta = records.read(path, "data cache")
    except records.RecordError as err:
        raise ConfigError(str(err)) from None
    if records.digest(meta.get("key")) != records.digest(config.key(get_scene(config.scene))):
        raise ConfigError(f"{path}: stale data cache (generated with other settings)")
    if "draw" not in arrays and not config.varied_draws:  # written before draws: all of the one scene
        arrays["draw"] = np.zeros(len(arrays.get("q", ())), np.int64)
    if set(arrays) != set(ARRAY_KEYS):
        raise ConfigError(f"{path}: not a readable lgnn data cache (arrays {sorted(arrays)})")
    return Dataset(**arrays)


def default_cache_dir() -> Path:
    """Where datasets are cached unless told otherwise: `datasets/` in the user's lgnn
    cache (`lgnn.files.user_cache_dir`), whatever the working directory."""
    return user_cache_dir() / "datasets"


def load_or_generate(config: DataConfig, cache_dir: str | os.PathLike | None | Literal["default"] = "default", progress: bool = False) -> Dataset:
    """The cached dataset of `config`, generating (and caching) it when absent, corrupt
    or stale. The cache is `cache_dir` ("default": `default_cache_dir()`); `None`
    disables it."""
    if cache_dir == "default":
        cache_dir = default_cache_dir()
    if cache_dir is None:
        return generate(config, progress)
    path = cache_path(config, cache_dir)
    if path.exists():
        try:
            return load(config, path)
        except ConfigError as err:
            print(f"lgnn: warning: {err}; regenerating", file=sys.stderr)
    dataset = generate(config, progress)
    path.parent.mkdir(parents=True, exist_ok=True)
    save(dataset, config, path)
    return dataset
