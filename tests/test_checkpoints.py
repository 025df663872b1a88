"""Checkpoints: leaves by pytree path, inference without the optimiser, stored and
compressed files, the format-1 reader and its conversion (rollouts bit-identical)."""

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lgnn import records
from lgnn.engines.base import SimulationConfig
from lgnn.errors import CheckpointError
from lgnn.learn import checkpoints, data, models, protocol, train
from lgnn.learn.checkpoints import load_model
from lgnn.learn.models import ModelSpec
from lgnn.scene import get_scene

ROOT = Path(__file__).resolve().parents[1]
COMMITTED = ROOT / "results" / "benchmark" / "checkpoints"
SHORT = SimulationConfig(dt=1e-3, frame_dt=1e-2, duration=0.05)

# The names the test model's `init` gives its two parameters: a researcher editing
# the model's code between saving and loading a checkpoint.
KEY_NAMES = {"first": "a_first", "second": "b_second"}


def _zero_acceleration(config, params, scene):
    return lambda q, qd: jnp.zeros_like(q) + 0.0 * (params[KEY_NAMES["first"]][0] + params[KEY_NAMES["second"]][0])


RENAMED = ModelSpec(
    "checkpoint-test-renamed",
    # Two leaves of one shape: read by position, a rename that changes their order
    # would swap them silently.
    init=lambda key, config: {KEY_NAMES["first"]: jnp.array([1.0, 2.0, 3.0]), KEY_NAMES["second"]: jnp.array([4.0, 5.0, 6.0])},
    acceleration=_zero_acceleration,
)


def _save_initial(path, model, config=protocol.TrainConfig()):
    train.save_checkpoint(path, train.initial_state(model, config), model, config)


def test_a_renamed_params_key_is_a_mismatch_naming_its_path(tmp_path, monkeypatch):
    models.register(RENAMED)
    model = models.ModelConfig(RENAMED.name)
    path = tmp_path / "renamed.npz"
    _save_initial(path, model)
    _, best = load_model(path)
    assert sorted(best) == ["a_first", "b_second"]
    np.testing.assert_array_equal(best["a_first"], [1.0, 2.0, 3.0])
    # Renamed so that it sorts after the other key: by position its values would
    # land under "b_second".
    monkeypatch.setitem(KEY_NAMES, "first", "c_first")
    with pytest.raises(CheckpointError, match=r"does not match its model settings \(best/\['a_first'\] is not in the model\)"):
        load_model(path)
    with pytest.raises(CheckpointError, match=r"params/\['a_first'\] is not in the model"):
        train.load_checkpoint(path)
    monkeypatch.setitem(KEY_NAMES, "first", "a_first")
    arrays, meta = records.read(path)
    arrays["best/['a_first']"] = arrays["best/['a_first']"][:2]
    records.save(tmp_path / "short.npz", arrays, meta)
    with pytest.raises(CheckpointError, match=r"best/\['a_first'\] has shape \(2,\), the model \(3,\)"):
        load_model(tmp_path / "short.npz")


def _with_meta(path, target, **changes):
    """A copy of the checkpoint at `path` with some meta fields changed (checksum valid)."""
    arrays, meta = records.read(path)
    environment = meta.pop("environment")
    records.save(target, arrays, {**meta, **changes}, environment, compressed=True)
    return target


def test_load_model_needs_neither_the_optimiser_nor_the_training_settings(tmp_path):
    model = models.ModelConfig.for_scene("lgnn", get_scene("chain4"))
    path = tmp_path / "lgnn.npz"
    _save_initial(path, model)
    odd = _with_meta(path, tmp_path / "odd.npz", train_config={"optimiser_of_the_future": 1})
    loaded, best = load_model(odd)
    assert loaded == model
    # Exact: read back from the file the same initialisation (one process, same key) wrote.
    for a, b in zip(jax.tree.leaves(best), jax.tree.leaves(train.initial_state(model, protocol.TrainConfig()).best_params)):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(CheckpointError, match="checkpoint settings are invalid"):
        train.load_checkpoint(odd)  # resuming needs them
    # A process where optax cannot even be imported still loads the model.
    script = ("import sys; sys.modules['optax'] = None\nimport lgnn; lgnn.configure()\n"
              "from lgnn.learn.checkpoints import load_model\n"
              f"config, params = load_model({str(path)!r}); print(config.name, 'optax' in sys.modules and sys.modules['optax'] is not None)")
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["lgnn", "False"]


def test_a_model_outside_the_registry_loads_with_its_spec(tmp_path, monkeypatch):
    spec = models.register(ModelSpec("checkpoint-test-own", init=lambda key, config: {"s": jnp.array([0.5, -0.5])}, acceleration=_zero_acceleration))
    path = tmp_path / "own.npz"
    _save_initial(path, models.ModelConfig(spec.name))
    monkeypatch.delitem(models.registry._REGISTRY, spec.name)  # a fresh process: the model's code not imported
    with pytest.raises(CheckpointError, match="'checkpoint-test-own' is defined outside lgnn.*pass its spec to load_model"):
        load_model(path)
    config, params = load_model(path, spec)
    assert config.name == spec.name and config.spec is spec
    np.testing.assert_array_equal(params["s"], [0.5, -0.5])
    other = ModelSpec("checkpoint-test-other", init=spec.init, acceleration=_zero_acceleration)
    with pytest.raises(CheckpointError, match="a checkpoint of model 'checkpoint-test-own', not of 'checkpoint-test-other'"):
        load_model(path, other)


def test_training_stores_checkpoints_the_kept_copies_are_compressed_the_history_an_array(tmp_path):
    """Training's checkpoints are stored (fast to write every few epochs), the slimmer
    copies kept for good deflated; both hold the history as an array."""
    model = models.ModelConfig.for_scene("lgnn", get_scene("chain4"))
    state = train.initial_state(model, protocol.TrainConfig())._replace(history=[(1, 2.0, 3.0, 4.5), (2, 1.5, 2.5)], epoch=2)
    path, kept = tmp_path / "c.npz", tmp_path / "kept.npz"
    train.save_checkpoint(path, state, model, protocol.TrainConfig())
    checkpoints.for_inference(path, kept)
    for written, compression in ((path, zipfile.ZIP_STORED), (kept, zipfile.ZIP_DEFLATED)):
        with zipfile.ZipFile(written) as archive:
            assert {info.compress_type for info in archive.infolist()} == {compression}, written.name
        arrays, meta = records.read(written)
        assert meta["format"] == checkpoints.FORMAT == 2 and "history" not in meta
        assert arrays["history"].shape == (2, 4)
        assert train.load_checkpoint(written)[0].history == state.history


def _write_format_1(path, state: protocol.TrainState, model, config):
    """A checkpoint as format 1 wrote it: leaves `prefix/k` in flatten order, the
    history in the meta, arrays uncompressed."""
    arrays = {f"{prefix}/{k}": np.asarray(leaf) for prefix, tree in (("params", state.params), ("best", state.best_params), ("opt", state.opt_state))
              for k, leaf in enumerate(jax.tree.leaves(tree))}
    meta = {"format": 1, "lgnn": "0", "model": model.to_dict(), "train": protocol.training_key(config), "train_config": config.__dict__,
            "data": None, "epoch": state.epoch, "best_epoch": state.best_epoch, "best_val": state.best_val, "history": state.history,
            "elapsed_s": state.elapsed_s}
    records.save(path, arrays, meta, environment={"commit": "format-1"})


def _tiny_dataset(scene, states=12, seed=0) -> data.Dataset:
    """Random states and targets: enough for Adam to move every parameter and its moments."""
    q, qd, qdd = (np.asarray(scene.nodes) + 0.1 * np.random.default_rng(seed + k).normal(size=(states, *np.shape(scene.nodes))) for k in range(3))
    return data.Dataset(q, qd, qdd, np.zeros(states, int), np.arange(8), np.arange(8, states), np.zeros(states, int))


def test_converted_checkpoints_roll_out_bit_identically(tmp_path):
    scene = get_scene("chain4")
    # GNS: the cheapest model to compile; the format does not depend on the model.
    model = models.ModelConfig.for_scene("gns", scene)
    config = protocol.TrainConfig(learning_rate=1e-2, batch_size=4, epochs=2, warmup_steps=1)
    state = train.train(model, config, _tiny_dataset(scene), scene)
    source, target = tmp_path / "old", tmp_path / "new"
    source.mkdir()
    _write_format_1(source / "lgnn.npz", state, model, config)
    before = (source / "lgnn.npz").read_bytes()
    tool = [sys.executable, str(ROOT / "tools" / "convert_checkpoints.py")]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    done = subprocess.run([*tool, str(source), str(target)], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert (source / "lgnn.npz").read_bytes() == before  # the source is only read
    old, new = train.load_checkpoint(source / "lgnn.npz"), train.load_checkpoint(target / "lgnn.npz")
    assert old[1]["format"] == 1 and new[1]["format"] == 2
    assert new[1]["converted_from"] == {"format": 1, "sha256": records.file_digest(source / "lgnn.npz")}
    assert new[1]["environment"] == {"commit": "format-1"} and new[0].history == old[0].history == state.history
    for a, b in zip(jax.tree.leaves(old[0]), jax.tree.leaves(new[0])):
        np.testing.assert_array_equal(a, b)  # the conversion copies each leaf's bytes
    # What records made from the checkpoint key on: unchanged by the conversion.
    assert checkpoints.content_digest(source / "lgnn.npz") == checkpoints.content_digest(target / "lgnn.npz")
    runs = [models.rollout(*load_model(path), scene, SHORT) for path in (source / "lgnn.npz", target / "lgnn.npz")]
    # Exact: one compiled rollout (cached per config) run twice in this process on
    # bit-equal parameters.
    np.testing.assert_array_equal(runs[0].q, runs[1].q)
    np.testing.assert_array_equal(runs[0].qd, runs[1].qd)
    # Never into the source folder.
    refused = subprocess.run([*tool, str(source), str(source)], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1 and "another folder" in refused.stderr


def test_committed_checkpoints_are_converted_and_keep_their_content():
    """Every committed checkpoint is format 2: the paper's grid's are format-1 files
    converted by tools/convert_checkpoints.py; the records made from the format-1 files
    load under their keys (bench/test_keys.py), whose `content_digest` is the converted
    file's: the same settings and best parameters."""
    from lgnn.bench import profiles

    paper = {"lgnn", "lgnn-mp1", "lgnn-mp2", "lgnn-notebook", "gns", "lgn", "clnn"}
    papers_grid = {job.name for job in profiles.training_jobs(profiles.load_profile("full", ['tracks=["paper"]'])) if job.model in paper}
    for path in sorted(COMMITTED.glob("*.npz")):
        meta, _ = checkpoints.read(path)
        assert meta["format"] == checkpoints.FORMAT, path.name
        if path.stem in papers_grid:
            assert meta["converted_from"]["format"] == checkpoints.LEGACY_FORMAT, path.name
    model, _ = load_model(COMMITTED / "lgnn-notebook-chain4-s0.npz")
    assert model.name == "lgnn-notebook" and train.load_checkpoint(COMMITTED / "lgnn-notebook-chain4-s0.npz")[0].epoch > 0


@pytest.mark.parametrize("kept", [False, True], ids=["stored", "deflated"])
def test_a_damaged_checkpoint_is_one_line(tmp_path, kept):
    """A byte flipped anywhere in a stored or deflated leaf: a `CheckpointError`, never
    zlib's or zipfile's traceback."""
    model = models.ModelConfig.for_scene("lgnn", get_scene("chain4"))
    path = tmp_path / "good.npz"
    _save_initial(tmp_path / "whole.npz", model)
    if kept:
        checkpoints.for_inference(tmp_path / "whole.npz", path)
    else:
        (tmp_path / "whole.npz").rename(path)
    raw = path.read_bytes()
    with zipfile.ZipFile(path) as archive:
        leaf = max(archive.infolist(), key=lambda info: info.compress_size if info.filename.startswith("best/") else 0)
    start = leaf.header_offset + 30 + int.from_bytes(raw[leaf.header_offset + 26 : leaf.header_offset + 28], "little") + int.from_bytes(raw[leaf.header_offset + 28 : leaf.header_offset + 30], "little")
    for offset in range(start, start + leaf.compress_size, max(1, leaf.compress_size // 40)):
        damaged = bytearray(raw)
        damaged[offset] ^= 0xFF
        (tmp_path / "damaged.npz").write_bytes(bytes(damaged))
        with pytest.raises(CheckpointError, match="damaged.npz: (not a readable lgnn checkpoint|corrupt checkpoint)"):
            load_model(tmp_path / "damaged.npz")


def _briefly_trained(tmp_path, name: str):
    """`(scene, model config, train config, checkpoint path, state)` of `name` trained
    for 2 epochs on chain4's tiny dataset, its checkpoint `tmp_path / "whole.npz"`."""
    scene = get_scene("chain4")
    model = models.ModelConfig.for_scene(name, scene)
    config = protocol.TrainConfig(learning_rate=1e-2, batch_size=4, epochs=2, warmup_steps=1)
    path = tmp_path / "whole.npz"
    return scene, model, config, path, train.train(model, config, _tiny_dataset(scene), scene, out=path)


def test_a_checkpoint_kept_without_parameters_keeps_its_records_and_training_only(tmp_path, capsys):
    """`lgnn checkpoint --without-parameters`: the copy's content digest (what records
    key on), training history and learned parameter count are the checkpoint's; rolling
    it out or resuming it is one line; the source is only read."""
    from lgnn import cli

    scene, model, config, full, state = _briefly_trained(tmp_path, "gns")
    slim = tmp_path / "slim.npz"
    before = full.read_bytes()
    assert cli.main(["checkpoint", str(full), "--without-parameters", str(slim)]) == 0
    assert full.read_bytes() == before and slim.stat().st_size < full.stat().st_size / 2
    assert checkpoints.content_digest(slim) == checkpoints.content_digest(full)
    kept, meta = train.load_checkpoint(slim)
    assert kept.params is None and kept.history == state.history and (kept.epoch, kept.best_val) == (state.epoch, state.best_val)
    _, params = load_model(full)
    assert meta[checkpoints.WITHOUT_PARAMETERS]["parameters"] == checkpoints.learned_parameter_count(params) > 0
    with pytest.raises(CheckpointError, match="slim.npz: kept without its parameters .* cannot be rolled out"):
        load_model(slim)
    with pytest.raises(CheckpointError, match="cannot be resumed"):
        train.train(model, config, _tiny_dataset(scene), scene, out=slim, resume=True)
    # Again from the slim copy: the same digest and count, never its own.
    again = tmp_path / "again.npz"
    checkpoints.without_parameters(slim, again)
    assert checkpoints.read(again)[0][checkpoints.WITHOUT_PARAMETERS] == meta[checkpoints.WITHOUT_PARAMETERS]
    capsys.readouterr()
    assert cli.main(["checkpoint", str(full), "--without-parameters", str(full)]) == 2
    assert "another file" in capsys.readouterr().err


def test_a_checkpoint_kept_for_inference_rolls_out_as_the_whole_one_but_does_not_resume(tmp_path, capsys):
    """`lgnn checkpoint --for-inference`: the copy has the whole checkpoint's content
    digest (what records key on), best parameters, history and budget, and is smaller;
    resuming it is one line."""
    from lgnn import cli

    scene, model, config, whole, state = _briefly_trained(tmp_path, "lgnn")
    kept = tmp_path / "kept.npz"
    before = whole.read_bytes()
    assert cli.main(["checkpoint", str(whole), "--for-inference", str(kept)]) == 0
    assert whole.read_bytes() == before and kept.stat().st_size < whole.stat().st_size
    assert checkpoints.content_digest(kept) == checkpoints.content_digest(whole)
    restored, meta = train.load_checkpoint(kept)
    assert restored.params is None and restored.opt_state is None
    assert restored.history == state.history and (restored.epoch, restored.best_epoch, restored.best_val) == (state.epoch, state.best_epoch, state.best_val)
    assert meta[checkpoints.FOR_INFERENCE]["sha256"] == records.file_digest(whole)
    for ours, theirs in zip(jax.tree.leaves(load_model(kept)[1]), jax.tree.leaves(load_model(whole)[1])):
        np.testing.assert_array_equal(ours, theirs)
    with pytest.raises(CheckpointError, match="kept.npz: kept for inference .* cannot be resumed"):
        train.train(model, config, _tiny_dataset(scene), scene, out=kept, resume=True)
    # Again from the kept copy: it names the whole file it first came from.
    again = tmp_path / "again.npz"
    checkpoints.for_inference(kept, again)
    assert checkpoints.read(again)[0][checkpoints.FOR_INFERENCE] == meta[checkpoints.FOR_INFERENCE]
    slim = tmp_path / "slim.npz"
    checkpoints.without_parameters(whole, slim)
    with pytest.raises(CheckpointError, match="slim.npz: kept without its parameters .* cannot be kept for inference"):
        checkpoints.for_inference(slim, tmp_path / "never.npz")
    assert not (tmp_path / "never.npz").exists()
    capsys.readouterr()
    assert cli.main(["checkpoint", str(whole), "--for-inference", str(tmp_path / "a.npz"), "--without-parameters", str(tmp_path / "b.npz")]) == 2
    assert "one of" in capsys.readouterr().err
