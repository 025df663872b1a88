"""Checkpoint files: parameters by pytree path, and inference without the optimiser.

A checkpoint is an `lgnn.records` array record (atomic write, checksum). Training
writes its arrays stored as they are: trained float64 parameters deflate by a tenth, and
deflating them took 1.5 s a save for the 51 MB of `cgnode`'s training state, more than
its epoch on a CPU; the slimmer copies the repository keeps (below) are deflated
(`np.savez_compressed`). Reading needs no telling. Format 2 (`FORMAT`) holds:
- `params/<path>`, `best/<path>`, `opt/<path>`: the leaves of the latest parameters,
  the best parameters and the optimiser state, each named by its pytree path
  (`jax.tree_util.keystr`, e.g. `best/['kinetic']['edge_embed']['w']`), so that a key
  renamed in a model's `init` is a mismatch naming the path, never a silently
  permuted leaf;
- `history` (E, 4) float64: per epoch the epoch, training loss, validation loss and
  seconds of training so far (NaN where an entry has no time);
- `meta` (JSON): format, lgnn version, model settings (`ModelConfig.to_dict`),
  training and data settings, progress (epoch, best epoch and loss, seconds), where a
  model defined outside lgnn comes from (`model_source`), the environment that wrote
  it and, for a converted file, `converted_from` (the source's format and sha256).

`load_model(path)` needs only the model's config and its spec's `init` (the tree the
leaves go into): no optimiser, no training settings. The optimiser state is read by
`lgnn.learn.train` for resuming, from its optimiser's template. `content_digest(path)`
is what a record made from a checkpoint keys on: the model settings and the best
parameters, the same for a file converted, re-saved or trained again to them.

A checkpoint may be kept **without its parameters** (`without_parameters`): its meta and
history, and in the meta's `without_parameters` the content digest and learned
parameter count of the checkpoint it came from. Records keyed on that checkpoint still
match it, and tables still read its training; it cannot be rolled out or resumed
(`load_model` and resuming refuse it with one line). The repository keeps the strong
graph networks' checkpoints so (1.6M parameters: about 50 MB each with Adam's state).

A finished checkpoint may be kept **for inference** (`for_inference`): its best
parameters, meta and history, without the latest parameters and the optimiser state
(together about two thirds of a whole checkpoint's arrays), and in the meta's
`for_inference` the sha256 of the file it came from. It has the same content digest,
so it rolls out, scores, times and reads as the whole one does; only resuming refuses
it with one line. The repository keeps the other finished checkpoints so.

Format 1 (leaves `prefix/k` in flatten order, the history in the meta, arrays stored
uncompressed) is still read: `arrays_by_path` names its leaves by the template's paths.
It is never written; `tools/convert_checkpoints.py` converts such files.
"""

from __future__ import annotations

import functools
import json
import math
import os
import zipfile
import zlib
from pathlib import Path
from typing import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from lgnn import archives, records
from lgnn.errors import CheckpointError, ConfigError
from lgnn.learn import models
from lgnn.learn.data import DataConfig, draw_scenes
from lgnn.runtime import in_float64
from lgnn.scene import Scene

FORMAT = 2
# Positional leaves; read (`arrays_by_path`), never written.
LEGACY_FORMAT = 1
# The entries of one epoch in the history array.
HISTORY_FIELDS = ("epoch", "train_loss", "val_loss", "elapsed_s")


def leaves_by_path(prefix: str, tree) -> dict[str, np.ndarray]:
    """`{"prefix/<keystr(path)>": leaf}` for every leaf of `tree`."""
    flat, _ = jax.tree_util.tree_flatten_with_path(tree)
    return {f"{prefix}/{jax.tree_util.keystr(path)}": np.asarray(leaf) for path, leaf in flat}


def write(path: str | os.PathLike, arrays: dict, meta: dict, history: list, environment: dict | None = None, compressed: bool = False) -> None:
    """Write a format-2 checkpoint atomically: `arrays` (`leaves_by_path` names),
    `history` (entries `(epoch, train_loss, val_loss[, elapsed_s])`), `meta` with the
    format set, and the `environment` that made it (default: this process's);
    `compressed`: its arrays deflated (the slimmer copies kept for good)."""
    table = np.full((len(history), len(HISTORY_FIELDS)), np.nan)
    for row, entry in zip(table, history):
        row[: len(entry)] = entry
    records.save(path, {**arrays, "history": table}, {**meta, "format": FORMAT}, environment, compressed=compressed)


def read(path: str | os.PathLike) -> tuple[dict, dict]:
    """`(meta, arrays)` of a checkpoint of a readable format; `CheckpointError` (one
    line) if it is absent, unreadable, corrupt or of another format."""
    try:
        arrays, meta = records.read(path, "checkpoint")
    except records.RecordError as err:
        raise CheckpointError(str(err)) from None
    if meta.get("format") not in (LEGACY_FORMAT, FORMAT):
        raise CheckpointError(f"{path}: checkpoint format {meta.get('format')!r}, expected {FORMAT} (or {LEGACY_FORMAT})")
    problem = meta_problem(meta, arrays)
    if problem:
        raise CheckpointError(f"{path}: invalid checkpoint meta: {problem}")
    return meta, arrays


def meta_problem(meta: dict, arrays: dict) -> str | None:
    """What is wrong with a checkpoint's meta (types and ranges of every field `load_checkpoint`
    reads; a valid checksum says only that nobody edited it by accident), or None."""

    def whole(value, low=0) -> bool:
        return isinstance(value, int) and not isinstance(value, bool) and value >= low

    def real(value) -> bool:
        return isinstance(value, (int, float)) and not isinstance(value, bool)

    def number(value) -> bool:
        try:
            return real(value) and math.isfinite(value)
        except OverflowError:  # an integer beyond every float
            return False

    for key in ("model", "train_config"):
        if not isinstance(meta.get(key), dict):
            return f"{key!r} must be an object, got {meta.get(key)!r}"
    data = meta.get("data")
    if data is not None and not (isinstance(data, dict) and isinstance(data.get("scene"), str)):
        return f"'data' must be an object naming its scene, got {data!r}"
    if not whole(meta.get("epoch")):
        return f"'epoch' must be a whole number >= 0, got {meta.get('epoch')!r}"
    if not whole(meta.get("best_epoch"), -1):  # -1: no validated epoch yet
        return f"'best_epoch' must be a whole number >= -1, got {meta.get('best_epoch')!r}"
    if meta["best_epoch"] > meta["epoch"]:
        return f"'best_epoch' {meta['best_epoch']} is after 'epoch' {meta['epoch']}"
    if "best_val" not in meta:
        return "'best_val' is missing (a number >= 0, or null before any validated epoch)"
    if meta["best_val"] is not None and not (number(meta["best_val"]) and meta["best_val"] >= 0):
        return f"'best_val' must be a number >= 0 or null, got {meta['best_val']!r}"
    if not number(meta.get("elapsed_s", 0.0)) or meta.get("elapsed_s", 0.0) < 0:
        return f"'elapsed_s' must be a number >= 0, got {meta['elapsed_s']!r}"
    inference = meta.get(FOR_INFERENCE)
    if inference is not None and not (isinstance(inference, dict) and isinstance(inference.get("sha256"), str)):
        return f"{FOR_INFERENCE!r} must give the 'sha256' of the checkpoint it came from, got {inference!r}"
    kept = meta.get(WITHOUT_PARAMETERS)
    if kept is not None and not (isinstance(kept, dict) and isinstance(kept.get("content_digest"), str) and whole(kept.get("parameters"))):
        return f"{WITHOUT_PARAMETERS!r} must give the 'content_digest' and 'parameters' count of the checkpoint it came from, got {kept!r}"
    if meta["format"] == FORMAT:
        table = arrays.get("history")
        if table is None or np.ndim(table) != 2 or np.shape(table)[1] != len(HISTORY_FIELDS) or not np.issubdtype(table.dtype, np.floating):
            return f"'history' must be an array of rows {HISTORY_FIELDS}, got {None if table is None else np.shape(table)}"
        return None
    history = meta.get("history")
    # Losses may be NaN or inf (an epoch that diverged is history too).
    if not isinstance(history, list):
        return f"'history' must be a list of [epoch, train loss, validation loss(, seconds)], got {history!r}"
    for k, entry in enumerate(history):
        if not (isinstance(entry, list) and len(entry) in (3, 4) and whole(entry[0]) and all(real(v) for v in entry[1:])):
            return f"'history'[{k}] must be [epoch, train loss, validation loss(, seconds)], got {entry!r}"
    return None


# The meta entries of a checkpoint kept without its parameters (`without_parameters`)
# and of one kept for inference (`for_inference`).
WITHOUT_PARAMETERS = "without_parameters"
FOR_INFERENCE = "for_inference"


def learned_parameter_count(params) -> int:
    """How many numbers a model learned: its parameters' leaves, the training-set
    statistics (`models.STATISTICS`, never trained) apart."""
    learned = {k: v for k, v in params.items() if k != models.STATISTICS} if isinstance(params, dict) else params
    return sum(int(np.size(leaf)) for leaf in jax.tree_util.tree_leaves(learned))


def without_parameters(source: str | os.PathLike, target: str | os.PathLike) -> None:
    """Write the checkpoint at `source` to `target` without its parameters and optimiser
    state (module docstring): the meta, history and environment kept, plus
    `without_parameters` (the source's content digest, learned parameter count and the
    sha256 of its bytes). `source` is only read."""
    meta, arrays = read(source)
    if WITHOUT_PARAMETERS in meta:
        kept = meta[WITHOUT_PARAMETERS]
    else:
        _, params = load_model(source)
        kept = {"content_digest": content_digest(source), "parameters": learned_parameter_count(params), "sha256": records.file_digest(source)}
    _write_slimmer(target, meta, arrays, {}, WITHOUT_PARAMETERS, kept)


def for_inference(source: str | os.PathLike, target: str | os.PathLike) -> None:
    """Write the checkpoint at `source` to `target` with its best parameters, meta,
    history and environment only (module docstring), plus `for_inference` (the sha256
    of the first whole file it came from). `CheckpointError` (one line) for a source
    without parameters or of the legacy format. `source` is only read."""
    meta, arrays = read(source)
    refuse_without_parameters(source, meta, "kept for inference")
    if meta["format"] != FORMAT:
        raise CheckpointError(f"{source}: checkpoint format {meta['format']}; convert it first (tools/convert_checkpoints.py)")
    kept = meta.get(FOR_INFERENCE) or {"sha256": records.file_digest(source)}
    best = {name: value for name, value in arrays.items() if name.startswith("best/")}
    _write_slimmer(target, meta, arrays, best, FOR_INFERENCE, kept)


def _write_slimmer(target: str | os.PathLike, meta: dict, arrays: dict, kept_arrays: dict, entry: str, source: dict) -> None:
    """Write to `target` a slimmer copy of the checkpoint read as `(meta, arrays)`:
    `kept_arrays` of its arrays, its history, environment and meta, and in the meta's
    `entry` what it keeps of its `source`."""
    rest = {key: value for key, value in meta.items() if key not in ("format", "history", "environment", entry)}
    write(target, kept_arrays, {**rest, entry: source}, history(meta, arrays), meta.get("environment"), compressed=True)


def has_parameters(meta: dict) -> bool:
    """Whether a checkpoint's meta (`read`) comes with its (best) parameters."""
    return WITHOUT_PARAMETERS not in meta


def resumable(meta: dict) -> bool:
    """Whether a checkpoint's meta (`read`) comes with what training resumes from: its
    latest parameters and the optimiser state."""
    return has_parameters(meta) and FOR_INFERENCE not in meta


def refuse_unresumable(path: str | os.PathLike, meta: dict) -> None:
    """`CheckpointError` (one line) for resuming a checkpoint kept without what
    training resumes from."""
    refuse_without_parameters(path, meta, "resumed")
    if not resumable(meta):
        raise CheckpointError(f"{path}: kept for inference (its best parameters, without the optimiser state), so it cannot be resumed; "
                              f"train the model again for a checkpoint that can")


def refuse_without_parameters(path: str | os.PathLike, meta: dict, use: str) -> None:
    """`CheckpointError` (one line) for `use` of a checkpoint kept without its parameters."""
    if not has_parameters(meta):
        raise CheckpointError(f"{path}: kept without its parameters (its records and training history only), so it cannot be {use}; "
                              f"train the model again (lgnn benchmark --stage train) for a checkpoint with them")


def model_config(path: str | os.PathLike, meta: dict, spec: models.ModelSpec | None = None) -> models.ModelConfig:
    """The `ModelConfig` a checkpoint's `meta` names. `spec`: the model's own
    `ModelSpec` (registered here), for a model defined outside lgnn; without it such a
    model must be registered already (one `CheckpointError` line says how)."""
    name = meta["model"].get("name")
    if spec is not None:
        if spec.name != name:
            raise CheckpointError(f"{path}: a checkpoint of model {name!r}, not of {spec.name!r}")
        models.register(spec)
    elif name not in models.model_names():
        # Never imported from a file's say-so: loading code is the user's decision.
        source = meta.get("model_source")
        where = f" ({source})" if source else ""
        option = f", the config's model reference, or the command's --model-code {source}" if source else ""
        raise CheckpointError(f"{path}: model {name!r} is defined outside lgnn{where}: load it first "
                              f"(lgnn.learn.models.load_spec, or pass its spec to load_model{option})")
    try:
        return models.ModelConfig.from_dict(meta["model"])
    except (ConfigError, TypeError) as err:
        raise CheckpointError(f"{path}: checkpoint settings are invalid ({err})") from None


def arrays_by_path(path: str | os.PathLike, meta: dict, arrays: dict, templates: Mapping[str, object]) -> dict:
    """The checkpoint's leaves named by pytree path. Format 2 names them so already;
    format 1's `prefix/k` (the k-th leaf in flatten order) are renamed after the paths
    of `templates[prefix]` (only those prefixes are returned)."""
    if meta["format"] == FORMAT:
        return arrays
    renamed = {}
    for prefix, template in templates.items():
        flat, _ = jax.tree_util.tree_flatten_with_path(template)
        stored = sum(name.startswith(f"{prefix}/") for name in arrays)
        if stored != len(flat):
            raise CheckpointError(f"{path}: checkpoint does not match its model settings ({stored} {prefix} arrays, the model has {len(flat)})")
        renamed.update({f"{prefix}/{jax.tree_util.keystr(key)}": arrays.get(f"{prefix}/{k}") for k, (key, _) in enumerate(flat)})
    return renamed


def restore(path: str | os.PathLike, template, arrays: dict, prefix: str):
    """`template`'s tree (arrays, or their `jax.ShapeDtypeStruct`s) with each leaf
    replaced by the array `prefix/<its path>` (in the template leaf's dtype); `CheckpointError` naming the first path that is
    missing, of another shape, or stored but not in the template."""
    flat, treedef = jax.tree_util.tree_flatten_with_path(template)
    names = [f"{prefix}/{jax.tree_util.keystr(key)}" for key, _ in flat]
    extra = sorted({name for name in arrays if name.startswith(f"{prefix}/")} - set(names))
    if extra:
        raise CheckpointError(f"{path}: checkpoint does not match its model settings ({extra[0]} is not in the model)")
    restored = []
    for name, (_, leaf) in zip(names, flat):
        stored = arrays.get(name)
        if stored is None:
            raise CheckpointError(f"{path}: checkpoint does not match its model settings (no {name})")
        shape, dtype = (leaf.shape, leaf.dtype) if isinstance(leaf, jax.ShapeDtypeStruct) else (np.shape(leaf), jnp.asarray(leaf).dtype)
        if stored.shape != shape:
            raise CheckpointError(f"{path}: checkpoint does not match its model settings ({name} has shape {stored.shape}, the model {shape})")
        restored.append(jnp.asarray(stored, dtype=dtype))
    return jax.tree_util.tree_unflatten(treedef, restored)


def history(meta: dict, arrays: dict) -> list[tuple]:
    """The per-epoch history `[(epoch, train_loss, val_loss[, elapsed_s]), ...]`."""
    if meta["format"] == LEGACY_FORMAT:
        return [tuple(entry) for entry in meta.get("history", [])]
    rows = arrays.get("history", np.zeros((0, len(HISTORY_FIELDS))))
    return [(int(epoch), float(train_loss), float(val_loss)) + (() if math.isnan(elapsed) else (float(elapsed),))
            for epoch, train_loss, val_loss, elapsed in rows]


def seconds_per_epoch(path: str | os.PathLike) -> float | None:
    """A checkpoint's seconds of training per epoch (its history's last entry), None
    where the file, its history or its timing is missing: a hint to schedule by (the
    benchmark starts its costliest parts first), so read without the checksum `read`
    checks and without the parameters."""
    if archives.npz_problem(path) is not None:
        return None
    try:
        with np.load(path, allow_pickle=False) as stored:
            rows = np.asarray(stored["history"], dtype=float)
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile, zlib.error):
        return None
    if rows.ndim != 2 or rows.shape[1] != len(HISTORY_FIELDS) or not len(rows):
        return None
    epoch, elapsed = rows[-1, 0], rows[-1, 3]
    return float(elapsed / epoch) if np.isfinite(elapsed) and epoch > 0 else None


def params_template(model: models.ModelConfig):
    """The shapes and dtypes of `model`'s parameters (`jax.ShapeDtypeStruct` leaves):
    running `init` would compile each of its random draws (1.5 s of a CPU, 7 s of a
    GPU's `lgnn evaluate`), only for them to be replaced by the stored leaves."""
    return jax.eval_shape(lambda key: models.init(key, model), jax.random.PRNGKey(0))


def content_digest(path: str | os.PathLike) -> str:
    """sha256 (hex) of what a checkpoint's rollouts depend on: its model settings (the
    meta's `model`) and its best parameters, each leaf by pytree path, dtype, shape and
    bytes. Independent of the file's format, compression, optimiser state, history and
    environment, so records keyed on it (the benchmark's evaluation, mass, speed and
    scaling records) follow a converted checkpoint. `CheckpointError` if unusable."""
    try:
        stat = os.stat(path)
    except OSError as err:
        raise CheckpointError(f"{path}: cannot read the checkpoint ({err.strerror})") from None
    return _content_digest(str(Path(path).resolve()), (stat.st_ino, stat.st_size, stat.st_mtime_ns, stat.st_ctime_ns))


@functools.lru_cache(maxsize=1024)  # keyed on the file's identity: a rewritten file is read again
def _content_digest(path: str, identity: tuple) -> str:
    meta, arrays = read(path)
    if not has_parameters(meta):
        return meta[WITHOUT_PARAMETERS]["content_digest"]
    if meta["format"] == LEGACY_FORMAT:  # leaves by position: named after the model's tree
        arrays = arrays_by_path(path, meta, arrays, {"best": params_template(model_config(path, meta))})
    best = {name: value for name, value in arrays.items() if name.startswith("best/")}
    return records.checksum(best, json.dumps(meta["model"], sort_keys=True))


@in_float64  # parameters restored in the precision they were trained in
def load_model(path: str | os.PathLike, spec: models.ModelSpec | None = None) -> tuple[models.ModelConfig, dict]:
    """`(ModelConfig, best params)` of a checkpoint, for inference: built from the
    model settings and `init` alone (`spec`: a model defined outside lgnn, see
    `model_config`). `CheckpointError` (one line) if the file is unusable."""
    meta, arrays = read(path)
    refuse_without_parameters(path, meta, "rolled out")
    model = model_config(path, meta, spec)
    template = params_template(model)
    return model, restore(path, template, arrays_by_path(path, meta, arrays, {"best": template}), "best")


def physics_differences(meta: dict, scene: Scene) -> list[str]:
    """How `scene`'s physical parameters differ from the scene a checkpoint was trained
    on (gravity, drag, joint damping, point masses, the link masses, inertias and lengths: values the model never
    saw; the number of links and how they connect may differ, that is the zero-shot
    generalisation the benchmark measures): one phrase each, empty when they agree or when the
    training scene is unknown or no longer loadable (a moved scene file)."""
    from lgnn.errors import SceneError
    from lgnn.scene import get_scene

    source = (meta.get("data") or {}).get("scene")
    draws = (meta.get("data") or {}).get("varied_draws", 0)
    try:
        trained = get_scene(source) if source else None
        if trained is not None and draws:
            return _outside_the_draws(scene, draw_scenes(DataConfig(scene=source, n_trajectories=draws, varied_draws=draws)))
    except (SceneError, ConfigError):
        return []
    if trained is None:
        return []
    differences = _gravity_and_drag_differences(scene, trained)
    for name in ("masses", "inertias", "lengths"):
        values, trained_values = (np.unique(np.round(getattr(s, name), 12)) for s in (scene, trained))
        if values.shape != trained_values.shape or not np.allclose(values, trained_values):
            differences.append(f"link {name} {_values(values)} (trained on {_values(trained_values)})")
    return differences


def _gravity_and_drag_differences(scene: Scene, trained: Scene) -> list[str]:
    differences = []
    if scene.dim != trained.dim or not np.allclose(trained.gravity_vector, scene.gravity_vector):
        differences.append(f"gravity {_gravity_text(scene)} (trained on {_gravity_text(trained)})")
    if not np.isclose(trained.drag, scene.drag):
        differences.append(f"drag {scene.drag:g} (trained on {trained.drag:g})")
    damping, trained_damping = (sorted({round(b, 12) for _, _, b in s.dampers}) for s in (scene, trained))
    if damping != trained_damping:
        shown = [_values(np.asarray(d)) if d else "none" for d in (damping, trained_damping)]
        differences.append(f"joint damping {shown[0]} (trained on {shown[1]})")
    point_masses, trained_point_masses = (sorted({round(m, 12) for _, m in s.point_masses}) for s in (scene, trained))
    if point_masses != trained_point_masses:
        shown = [_values(np.asarray(m)) if m else "none" for m in (point_masses, trained_point_masses)]
        differences.append(f"point masses {shown[0]} (trained on {shown[1]})")
    return differences


def _gravity_text(scene: Scene) -> str:
    return f"{np.round(scene.gravity_vector, 12).tolist()}" if scene.lateral_gravity else f"{float(scene.gravity):g}"


def _outside_the_draws(scene: Scene, draws: tuple[Scene, ...]) -> list[str]:
    """`physics_differences` of a model trained on varied draws: the gravity and drag of
    the draws, and link values outside the range the draws spanned."""
    differences = _gravity_and_drag_differences(scene, draws[0])
    for name in ("masses", "inertias", "lengths"):
        seen = np.concatenate([getattr(draw, name) for draw in draws])
        values = np.asarray(getattr(scene, name))
        low, high = seen.min() * (1 - 1e-12), seen.max() * (1 + 1e-12)
        if values.min() < low or values.max() > high:
            differences.append(f"link {name} from {values.min():g} to {values.max():g} (trained on {seen.min():g} to {seen.max():g})")
    return differences


def _values(values: np.ndarray) -> str:
    shown = ", ".join(f"{v:g}" for v in values[:4])
    return f"{{{shown}{', ...' if len(values) > 4 else ''}}}"
