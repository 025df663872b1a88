"""Predictions made outside lgnn, scored as the benchmark scores its own models.

A researcher exports a scene's evaluation initial conditions (`lgnn dataset export`:
`eval_q0`, `eval_qd0` and, in its meta, `evaluation.key`, the settings of the scene's
ground truth), rolls them out in their own framework and saves the states at every
frame in a predictions file (docs/formats.md, "Predictions"): an `.npz` with

- `q`, `qd` (C, F, N, D): positions and velocities of every node at every frame, frame
  0 the exported initial conditions (C of them, in their order), F = duration /
  frame_dt + 1 frames `frame_dt` apart;
- `scene` (string): the scene's name as the benchmark names it (`chain8`);
- `key` (string): the export's `evaluation.key`, so a file answers one scene's initial
  conditions and settings and no other;
- `model` (string): the name its row gets (tables write `MODEL (external)`);
- `about` (string, optional): what made them (framework, version, a link).

`read_predictions` checks a file against the profile (one line naming the file and the
problem: a missing array, a wrong shape or frame count, another scene or settings
key, a frame 0 that is not the exported initial conditions); it does not refuse
non-finite or exploding frames: from the first one the divergence rule flags, a
rollout's errors count as each metric's maximum, as a model's do. Energies are never
read from the file: every metric that needs them computes the scene's true
Hamiltonian of the predicted states (`lgnn.metrics.score_rollouts`).

`evaluate_external` scores a file against the scene's ground truth and each reference
engine, from the same initial conditions and with the same functions as a trained
model's pair (`evaluate.score_against_truth`, `evaluate.record_arrays`), and writes the
record `benchmark/runs/external/<model>/<scene>.npz` (`store.Layout.external_record`),
keyed on the scene's ground truth (`lgnn.bench.stages.truth.truth_key`) and the file's content.
`load_externals` finds every such record under the output folder and its base whose
ground truth is the profile's, with or without the file that made it: a record is a
submission, which later reports keep showing. An external row has no checkpoint,
parameters or training time, and says so.
"""

from __future__ import annotations

import dataclasses
import os
import re
import zipfile
from pathlib import Path

import numpy as np

from lgnn import archives, metrics, records
from lgnn.bench import claims, store
from lgnn.bench.grid import Pair, external_pair
from lgnn.bench.profiles import Profile, evaluation_scenes
from lgnn.bench.stages import evaluate
from lgnn.bench.stages import truth as truth_stage
from lgnn.bench.store import log
from lgnn.errors import ConfigError
from lgnn.scene import get_scene

# Arrays a predictions file must hold (strings as 0-d arrays, `np.savez(..., scene="chain8")`).
ARRAYS = ("q", "qd", "scene", "key", "model")
# How far frame 0 may be from the exported initial conditions (a float32 copy is within it).
INITIAL_TOLERANCE = 1e-5
# A model name: what a table column and a file name can both hold.
MODEL_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")


@dataclasses.dataclass(frozen=True)
class Predictions:
    """A checked predictions file: `q`, `qd` (C, F, N, D) float64, frame 0 the exact
    initial conditions; `scene`, `model`, `about`; `path` and its content's `digest`."""

    path: Path
    scene: str
    model: str
    about: str
    q: np.ndarray
    qd: np.ndarray
    digest: str

    @property
    def pair(self) -> Pair:
        return external_pair(self.model, self.scene)


def _text(arrays, name: str, path: Path) -> str:
    value = arrays[name]
    if value.shape != () or value.dtype.kind != "U":
        raise ConfigError(f"{path}: '{name}' must be a string (np.savez(..., {name}='...')), got an array of shape {value.shape} and dtype {value.dtype}")
    return str(value)


def read_predictions(profile: Profile, path: str | os.PathLike) -> Predictions:
    """The predictions file at `path`, checked against `profile`'s evaluation (module
    docstring); `ConfigError` (one line naming the file) otherwise."""
    path = Path(path)
    if path.suffix != ".npz":
        raise ConfigError(f"{path}: predictions are an .npz file (docs/formats.md, 'Predictions')")
    if not path.is_file():
        raise ConfigError(f"{path}: no such predictions file")
    problem = archives.npz_problem(path)
    if problem:
        raise ConfigError(f"{path}: not a predictions file: {problem}")
    try:
        with np.load(path, allow_pickle=False) as handle:
            missing = [name for name in ARRAYS if name not in handle.files]
            if missing:
                raise ConfigError(f"{path}: a predictions file needs arrays {', '.join(ARRAYS)}; missing {', '.join(missing)}")
            arrays = {name: handle[name] for name in (*ARRAYS, *(("about",) if "about" in handle.files else ()))}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as err:
        raise ConfigError(f"{path}: not a readable .npz file ({err})") from None
    scene_name, key, model = (_text(arrays, name, path) for name in ("scene", "key", "model"))
    about = _text(arrays, "about", path) if "about" in arrays else ""
    if not MODEL_NAME.match(model):
        raise ConfigError(f"{path}: 'model' must be 1-64 letters, digits or . _ - (starting with a letter or digit), got {model!r}")
    scenes = evaluation_scenes(profile)
    if scene_name not in scenes:
        raise ConfigError(f"{path}: scene {scene_name!r} is not evaluated by the {profile.name} profile (choose from {', '.join(scenes)})")
    expected_key = truth_stage.truth_key(profile, scene_name)
    if key != expected_key:
        raise ConfigError(f"{path}: key {key!r} is not this profile's evaluation of {scene_name} ({expected_key}): the predictions answer "
                          f"other initial conditions or settings; export them again with lgnn dataset export --scene {scene_name} and the same profile")
    scene = get_scene(scene_name)
    states = truth_stage.evaluation_initial_states(profile, scene)
    frames = profile.evaluate.simulation(scene_name).n_frames + 1
    shape = (len(states.q), frames, scene.n_nodes, scene.dim)
    for name in ("q", "qd"):
        value = arrays[name]
        if value.dtype.kind not in "fiu":
            raise ConfigError(f"{path}: '{name}' must hold numbers, got dtype {value.dtype}")
        if value.ndim != 4:
            raise ConfigError(f"{path}: '{name}' must be (initial conditions, frames, nodes, dimension) = {shape}, got shape {value.shape}")
        if value.shape[1] != frames:
            raise ConfigError(f"{path}: '{name}' has {value.shape[1]} frames, expected {frames} (frame 0 the initial conditions, then one every "
                              f"{profile.evaluate.frame_dt:g} s for {profile.evaluate.duration:g} s)")
        if value.shape != shape:
            raise ConfigError(f"{path}: '{name}' has shape {value.shape}, expected {shape} (initial conditions, frames, nodes, dimension)")
    q, qd = np.asarray(arrays["q"], np.float64), np.asarray(arrays["qd"], np.float64)
    for name, first, exact in (("q", q[:, 0], states.q), ("qd", qd[:, 0], states.qd)):
        if not np.allclose(first, exact, rtol=0, atol=INITIAL_TOLERANCE):
            worst = np.nanmax(np.abs(first - exact)) if np.isfinite(first).all() else float("nan")
            raise ConfigError(f"{path}: frame 0 of '{name}' is not the exported initial conditions (largest difference {worst:.3g}, "
                              f"tolerance {INITIAL_TOLERANCE:g}): start each rollout from eval_q0, eval_qd0 in their order")
    # Frame 0 is the exact initial state (a float32 copy of it would shift every error and the divergence bounds).
    q[:, 0], qd[:, 0] = states.q, states.qd
    return Predictions(path, scene_name, model, about, q, qd, records.file_digest(path))


def external_key(profile: Profile, predictions: Predictions) -> str:
    """What an external record depends on: its scene's ground truth and the file's content."""
    return records.digest({"truth": truth_stage.truth_key(profile, predictions.scene), "predictions": predictions.digest})


def evaluate_external(profile: Profile, path: str | os.PathLike, out: Path, progress: bool = True) -> Path:
    """Score the predictions file at `path` against its scene's ground truth (computed,
    or read from `out` or the profile's base) and write its record; a record of the same
    file and ground truth is reused."""
    predictions = read_predictions(profile, path)
    layout = store.layout(profile, out)
    record, key = layout.external_record(predictions.model, predictions.scene), external_key(profile, predictions)
    with claims.once(record):
        if evaluate.has_arrays(layout.load(record, key), evaluate.pair_needs(profile)):
            return record
        truth = truth_stage.ground_truth(profile, predictions.scene, progress, out)
        if not np.allclose(truth.states.q, predictions.q[:, 0], rtol=1e-9, atol=1e-12):
            raise ConfigError(f"{predictions.scene}: the stored ground truth starts from other initial conditions than the evaluation's; "
                              f"remove {truth_stage.truth_file(profile, predictions.scene)} to recompute it")
        scene = get_scene(predictions.scene)
        scored = evaluate.score_against_truth(profile, scene, metrics.trajectory_of(scene, truth.truth.t, predictions.q, predictions.qd), truth)
        frame_dt = profile.evaluate.frame_dt
        arrays = {"t": evaluate.curve_times(predictions.q.shape[1], frame_dt), **evaluate.record_arrays("", scored, frame_dt),
                  **evaluate.snapshot(profile, predictions.scene, "model", predictions.q)}
        meta = dict(external=True, model=predictions.model, label=predictions.pair.label, scene=predictions.scene, about=predictions.about,
                    file=predictions.path.name, file_digest=predictions.digest, truth_key=truth_stage.truth_key(profile, predictions.scene),
                    initial_conditions=len(predictions.q), mujoco_reference=truth_stage.REFERENCE_VERSION)
        store.save(record, key, arrays, meta)
    diverged = int(np.sum(scored[0].diverged >= 0))
    log(f"external {predictions.model} on {predictions.scene}: rollout error "
        f"{float(np.exp(np.mean(arrays['rollout_error/per_ic_log']))):.3g}" + (f", {diverged} diverged" if diverged else ""))
    return record


def load_externals(profile: Profile, out: Path) -> list[tuple[Pair, tuple[dict, dict]]]:
    """`(external_pair, (arrays, meta))` of every external record under `out` and the
    profile's base (`out`'s first where both hold one) made against the profile's ground
    truth of one of its evaluation scenes and holding every recorded metric; by scene,
    then model."""
    layout = store.layout(profile, out)
    found = []
    for scene in evaluation_scenes(profile):
        wanted = truth_stage.truth_key(profile, scene)
        for path in layout.external_records(scene):
            record = layout.load(path)
            if (record is not None and record[1].get("truth_key") == wanted and record[1].get("external")
                    and evaluate.has_arrays(record, evaluate.pair_needs(profile))):
                found.append((external_pair(record[1]["model"], scene), record))
    return found


def check_predictions(profile: Profile) -> None:
    """Every predictions file of the profile read and checked, before any stage runs."""
    for path in profile.predictions:
        read_predictions(profile, path)

