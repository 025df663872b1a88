"""`lgnn dataset export`: a profile's training data of a scene and its evaluation
initial conditions in one documented file (`lgnn.learn.export`), with what a file of
predictions from them must name to be scored (`lgnn.bench.stages.external`)."""

from __future__ import annotations

import dataclasses
import os

import numpy as np

from lgnn.bench.profiles import Profile
from lgnn.bench.stages.evaluate import evaluation_initial_states, truth_key
from lgnn.learn import data, export
from lgnn.scene import get_scene, scene_to_dict


def export_scene(profile: Profile, scene_name: str, out: str | os.PathLike, cache_dir: str | os.PathLike | None, progress: bool = False) -> dict:
    """Write `scene_name`'s training data (the profile's `training.data` settings) and
    evaluation initial conditions to `out`; returns the arrays' shapes."""
    export.check_path(out)
    scene = get_scene(scene_name)
    config = profile.training.data_for(scene_name)
    dataset = data.load_or_generate(config, cache_dir, progress=progress)
    evaluation = evaluation_initial_states(profile, scene)
    simulation = profile.evaluate.simulation(scene_name)
    # One scene's data: every state is of draw 0, which the exported format does not hold.
    arrays = {
        **{name: value for name, value in dataset._asdict().items() if name != "draw"},
        "t": np.tile(np.arange(config.states_per_trajectory) * config.sample_dt, config.n_trajectories),
        "eval_q0": np.asarray(evaluation.q), "eval_qd0": np.asarray(evaluation.qd),
    }
    meta = {
        "scene": scene_to_dict(scene),
        "data": config.to_dict(),
        "profile": profile.name,
        # What a predictions file answering these initial conditions names (`lgnn.bench.stages.external`):
        # the scene as the benchmark names it and the key of its ground truth; `frames` it holds.
        "evaluation": {**dataclasses.asdict(simulation), **dataclasses.asdict(profile.evaluate.integration), "seed": profile.evaluate.ic_seed,
                       "scene": scene_name, "key": truth_key(profile, scene_name), "frames": simulation.n_frames + 1},
    }
    export.export_dataset(out, arrays, meta)
    return {name: value.shape for name, value in arrays.items()}
