"""`lgnn dataset export`: the training and evaluation data in a documented file that
`lgnn.learn.export.load_exported` reads back exactly (npz always, HDF5 with h5py)."""

import numpy as np
import pytest

from lgnn import cli
from lgnn.errors import ConfigError
from lgnn.learn import data
from lgnn.learn.export import load_exported
from lgnn.scene import get_scene, scene_from_dict

SETTINGS = ["training.data.n_trajectories=2", "training.data.duration=0.1", "training.data.sample_dt=0.02", "evaluate.initial_conditions=2"]


@pytest.mark.parametrize("suffix", [".npz", ".h5"])
def test_export_round_trips_the_training_data_exactly(tmp_path, suffix, capsys):
    if suffix == ".h5":
        pytest.importorskip("h5py")
    out = tmp_path / f"chain4{suffix}"
    args = ["dataset", "export", "--scene", "chain4", "--profile", "quick", "--out", out, "--cache-dir", tmp_path, "--quiet"]
    assert cli.main(args + [a for s in SETTINGS for a in ("--set", s)]) == 0
    assert str(out) in capsys.readouterr().out
    arrays, meta = load_exported(out)
    config = data.DataConfig("chain4", n_trajectories=2, duration=0.1, sample_dt=0.02)
    dataset = data.load_or_generate(config, tmp_path)  # the cached data the export wrote
    assert not dataset.draw.any() and "draw" not in arrays  # one scene's data: no draws to export
    for name, value in dataset._asdict().items():
        if name == "draw":
            continue
        np.testing.assert_array_equal(arrays[name], value)
        assert arrays[name].dtype == value.dtype
    assert scene_from_dict(meta["scene"]) == get_scene("chain4")
    assert meta["data"]["n_trajectories"] == 2 and meta["environment"]["commit"]
    np.testing.assert_array_equal(arrays["t"], np.tile(np.arange(5) * 0.02, 2))
    assert arrays["eval_q0"].shape == (2, 5, 2) and sorted(np.concatenate([arrays["train"], arrays["val"]])) == list(range(10))


def test_a_damaged_or_foreign_file_is_a_one_line_error(tmp_path):
    bad = tmp_path / "x.npz"
    np.savez(bad, q=np.zeros(3))
    with pytest.raises(ConfigError, match="x.npz"):
        load_exported(bad)
    with pytest.raises(ConfigError, match="suffix"):
        load_exported(tmp_path / "x.csv")
