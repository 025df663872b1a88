"""One record format (`lgnn.records`): round trip, one-line errors naming the file, and
the checksum every committed record was written with."""

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from lgnn import records

ROOT = Path(__file__).resolve().parents[1]


def test_round_trip_keeps_arrays_meta_and_records_the_environment(tmp_path):
    arrays = {"a/0": np.arange(6.0).reshape(2, 3), "b": np.array([1, 2], np.int32)}
    records.save(tmp_path / "r.npz", arrays, {"key": "k", "format": 1, "value": 0.5})
    read, meta = records.read(tmp_path / "r.npz")
    assert set(read) == set(arrays)
    for name, value in arrays.items():
        assert read[name].dtype == value.dtype
        np.testing.assert_array_equal(read[name], value)
    assert meta["key"] == "k" and meta["value"] == 0.5
    assert set(meta["environment"]) == {"commit", "versions", "device"}
    records.save(tmp_path / "s.npz", arrays, {}, environment={"commit": "c"})
    assert records.read(tmp_path / "s.npz")[1]["environment"] == {"commit": "c"}


def test_damaged_records_are_one_line_naming_the_file(tmp_path):
    path = tmp_path / "r.npz"
    records.save(path, {"x": np.ones(3)}, {"key": "k"})
    with np.load(path) as stored:
        raw = dict(stored)
    raw["x"] = raw["x"] + 1e-12
    np.savez(tmp_path / "tampered.npz", **raw)
    (tmp_path / "short.npz").write_bytes(path.read_bytes()[:100])
    np.savez(tmp_path / "other.npz", x=np.ones(3))  # an .npz, but no record
    cases = {"tampered.npz": "corrupt thing (checksum mismatch)", "short.npz": "not a readable lgnn thing",
             "other.npz": "not a readable lgnn thing", "absent.npz": "no such thing file"}
    for name, words in cases.items():
        with pytest.raises(records.RecordError) as info:
            records.read(tmp_path / name, "thing")
        message = str(info.value)
        assert "\n" not in message and message.startswith(str(tmp_path / name)) and words in message, message


def test_json_records_match_on_their_key(tmp_path):
    path = tmp_path / "r.json"
    assert records.load_json(path, "k") is None
    records.save_json(path, "k", {"rows": [{"x": 1.5}]})
    assert records.load_json(path, "k")["rows"] == [{"x": 1.5}]
    assert records.load_json(path, "other") is None
    assert list(json.loads(path.read_text())) == ["key", "rows", "environment"]
    path.write_text("{not json")
    with pytest.raises(records.RecordError, match="not a readable JSON record"):
        records.load_json(path, "k")


def test_digest_is_sha256_of_sorted_json():
    assert records.digest({"b": (1, 2), "a": None}) == hashlib.sha256(b'{"a": null, "b": [1, 2]}').hexdigest()
    assert records.digest({"a": 1, "b": 2}) == records.digest({"b": 2, "a": 1})


def test_committed_checkpoints_and_records_keep_valid_checksums():
    """The checksum is the algorithm the committed files were written with."""
    paths = sorted((ROOT / "results" / "benchmark").rglob("*.npz"))
    assert len(paths) >= 6
    for path in paths:
        arrays, meta = records.read(path)
        assert arrays and "format" in meta
