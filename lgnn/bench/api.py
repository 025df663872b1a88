"""The benchmark from Python (a notebook's way in): `train` (from `train_recipe`, the
full profile's), `evaluate`, `benchmark` and `load_results`, exported as `lgnn.train`, `lgnn.evaluate`, `lgnn.benchmark` and
`lgnn.load_results` (imported on first use: `import lgnn` stays light).

Each does what its command does, with the same defaults and checks (bad input is an
`lgnn.ConfigError` of one line), and returns what a notebook wants: a path, a
training state, or pandas DataFrames (tidy: one row per scene, model, metric, ...).
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

from lgnn.errors import ConfigError

# `load_results`' tables: name -> file under the results folder's `benchmark/`.
RESULT_TABLES = {"summary": "summary.csv.gz", "curves": "curves.csv.gz", "speed": "speed_error.csv", "mass": "mass_matrix.csv"}


def train_recipe():
    """The training settings `train` and `lgnn train` start from: the full profile's
    (`lgnn.bench.profiles.PROFILES["full"].training`: data, batch, learning rate and its
    schedule, plateau rule), so their checkpoints are trained as the committed ones are."""
    from lgnn.bench.profiles import PROFILES

    return PROFILES["full"].training


def train(model: str, out: str | os.PathLike, scene: str = "chain4", *, epochs: int | None = None, seed: int = 0,
          minutes: float | None = None, trajectories: int | None = None, varied_draws: int = 0, link_features: bool = False, resume: bool = False,
          cache_dir: str | os.PathLike | None = None, progress: bool = False):
    """Train `model` (a built-in name or `file.py:ATTR` / `module:ATTR`) on `scene` with
    the full profile's recipe (as `lgnn train`), writing the checkpoint `out` every
    10 epochs (the recipe's `checkpoint_every`) and at the end; `epochs`, `minutes`,
    `trajectories` override the recipe's budget and data size; `varied_draws` trains on
    that many varied draws of the chain (`lgnn train --varied-draws`), and
    `link_features` gives the model each link's mass, inertia ratio and length
    (`--link-features`). Returns the final training state (`best_val`, `best_epoch`, `epoch`, ...)."""
    from lgnn.learn import data, models
    from lgnn.learn import train as training
    from lgnn.scene import get_scene

    recipe = train_recipe()
    if Path(out).exists() and not resume:
        raise ConfigError(f"{out} exists: resume=True to continue training it, or choose another out")
    data_config = dataclasses.replace(recipe.data_for(scene), varied_draws=varied_draws, **({"n_trajectories": trajectories} if trajectories else {}))
    config = dataclasses.replace(recipe.train, seed=seed, minutes=minutes, **({"epochs": epochs} if epochs else {}))
    structure = get_scene(scene)
    name = models.load_spec(model).name if ":" in model else model
    model_config = models.ModelConfig.for_scene(name, structure, link_features=link_features)
    dataset = data.load_or_generate(data_config, cache_dir or data.default_cache_dir(), progress=progress)
    return training.train(model_config, config, dataset, data.draw_scenes(data_config), out=out, data_config=data_config, resume=resume, progress=progress)


def evaluate(checkpoint: str | os.PathLike, scenes, *, initial_conditions: int = 1, seed: int = 0, duration: float = 1.0,
             model_code: str | None = None, progress: bool = False):
    """Score a checkpoint on `scenes` (a name or several) against the Lagrangian engine
    and MuJoCo C, as `lgnn evaluate`: a DataFrame of its summary rows (`scene, model,
    reference, metric, unit, initial_conditions, gmean, low, high, final, diverged`)."""
    import pandas as pd

    from lgnn.bench import evaluation
    from lgnn.engines.base import SimulationConfig
    from lgnn.learn.checkpoints import load_model
    from lgnn.learn.models import load_spec
    from lgnn.scene import get_scene

    if model_code:
        load_spec(model_code)
    model, params = load_model(checkpoint)
    scenes = [get_scene(name) for name in ([scenes] if isinstance(scenes, str) else scenes)]
    scored, _ = evaluation.evaluate_on_scenes(model, params, scenes, SimulationConfig(duration=duration), initial_conditions, seed, progress=progress)
    return pd.DataFrame(evaluation.summary_rows(scored), columns=evaluation.SUMMARY_COLUMNS)


def benchmark(profile: str | os.PathLike = "quick", out: str | os.PathLike | None = None, *, stages=None, settings=(), add_models=(),
              predictions=(), with_results: str | os.PathLike | None = None, progress: bool = False) -> Path:
    """Run the benchmark as `lgnn benchmark` does: `profile` a shipped name or a config
    file, `settings` its `KEY=VALUE` overrides, `add_models` (`--add-model`),
    `predictions` (`--add-predictions`), `with_results` (`--with-results`); the output
    folder (default the profile's). `load_results(that folder)` reads its tables."""
    from lgnn.bench.run import run

    chosen = benchmark_profile(profile, settings=settings, add_models=add_models, predictions=predictions, with_results=with_results)
    return run(chosen, out, tuple(stages) if stages else None, progress=progress)


def benchmark_profile(profile: str | os.PathLike = "quick", *, settings=(), add_models=(), predictions=(), with_results: str | os.PathLike | None = None):
    """The `lgnn.bench.profiles.Profile` that `benchmark`, `lgnn benchmark` and `lgnn
    leaderboard` run: `profile` a shipped name or a config file with its `KEY=VALUE`
    `settings`, `add_models` added to its grid, `predictions` files to score and
    `with_results` a results folder to rank beside. Those paths (and an added model's
    `file.py`) are relative to the working directory, never to a config's folder (as
    the config's own `base` and models are)."""
    import json

    from lgnn.bench import profiles

    overrides = [*settings, *([f"base={json.dumps(str(Path(with_results).resolve()))}"] if with_results else [])]
    added = tuple(f"{Path(code).resolve()}:{name}" if code.endswith(".py") else model
                  for model in add_models for code, _, name in (model.rpartition(":"),))
    chosen = profiles.load_profile(profile, overrides, added)
    return dataclasses.replace(chosen, predictions=(*chosen.predictions, *(str(Path(p).resolve()) for p in predictions)))


def load_results(folder: str | os.PathLike = "results", table: str = "summary"):
    """A results folder's table as a DataFrame: `summary` (`benchmark/summary.csv.gz`: scene,
    model, seed, metric, statistic, value and provenance), `curves`, `speed` or `mass`."""
    import pandas as pd

    if table not in RESULT_TABLES:
        raise ConfigError(f"unknown results table {table!r} (choose from {', '.join(RESULT_TABLES)})")
    path = Path(folder) / "benchmark" / RESULT_TABLES[table]
    if not path.is_file():
        raise ConfigError(f"{path}: no such results table (lgnn benchmark writes it)")
    try:
        return pd.read_csv(path, comment="#")
    except pd.errors.EmptyDataError:  # a report of no records yet
        return pd.DataFrame()
