"""Files from others never run code and never exhaust the machine: every reader of
checkpoints, records, trajectories, predictions, exported datasets and scene files is fed
a pickled object, an array header claiming terabytes, a member that inflates past the
limit and JSON nested past the limit, and refuses each in one line before allocating.

The pickled object would create a file if it were ever unpickled; the test checks that
no file appears. The inflation limit is lowered for the test (a real 2 GiB member would
take seconds to write); the rule is the same.
"""

import io
import json
import struct
import zipfile

import numpy as np
import pytest

from lgnn import archives, records
from lgnn.bench.api import benchmark_profile
from lgnn.bench.stages import external
from lgnn.cli import main
from lgnn.errors import ConfigError, LgnnError
from lgnn.learn import export
from lgnn.scene.schema import load_scene_file
from lgnn.trajectory import Trajectory


class _Touch:
    """Unpickling this creates `path`: the proof that a reader ran code."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


def _npy(shape, dtype, data: bytes) -> bytes:
    """A .npy member: a version 1.0 header for `shape` and `dtype`, then `data`."""
    header = repr({"descr": np.lib.format.dtype_to_descr(np.dtype(dtype)), "fortran_order": False, "shape": tuple(shape)}).encode()
    header += b" " * (-(len(header) + 11) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header + data


def _archive(path, members: dict, compression=zipfile.ZIP_STORED):
    with zipfile.ZipFile(path, "w", compression) as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    return path


def _pickled(path, marker):
    buffer = io.BytesIO()
    np.save(buffer, np.array([_Touch(marker)], dtype=object), allow_pickle=True)
    return _archive(path, {"meta.npy": buffer.getvalue(), "q.npy": buffer.getvalue()})


def _claims_terabytes(path):
    return _archive(path, {"q.npy": _npy((2**40,), np.float64, b"\0" * 8)})


def _inflates(path):
    buffer = io.BytesIO()
    np.save(buffer, np.zeros(2**20))  # 8 MiB of zeros, a few KiB deflated
    return _archive(path, {"q.npy": buffer.getvalue()}, zipfile.ZIP_DEFLATED)


def _readers(profile):
    """Every reader of a file from elsewhere, each raising an LgnnError (one line) or
    returning what it read."""
    return {
        "record": lambda path: records.read(path),
        "checkpoint": lambda path: _cli_refuses(["checkpoint", str(path)]),
        "trajectory": lambda path: Trajectory.load(path),
        "predictions": lambda path: external.read_predictions(profile, path),
        "exported dataset": lambda path: export.load_exported(path),
    }


def _cli_refuses(argv):
    if main(argv) != 2:
        raise AssertionError(f"lgnn {' '.join(argv)} did not refuse")
    raise ConfigError("refused")


@pytest.fixture(scope="module")
def readers():
    return _readers(benchmark_profile("quick"))


@pytest.mark.parametrize("reader", ["record", "checkpoint", "trajectory", "predictions", "exported dataset"])
@pytest.mark.parametrize("make, says", [
    (_pickled, "holds Python objects (pickled), which lgnn never loads"),
    (_claims_terabytes, "claims an array of shape (1099511627776,)"),
    (_inflates, "inflates to 0.00781 GiB, over the 0.00391 GiB limit for one array"),
])
def test_every_reader_refuses_before_allocating(tmp_path, readers, reader, make, says, monkeypatch, capsys):
    monkeypatch.setattr(archives, "MAX_ARRAY_BYTES", 2**22)
    marker = tmp_path / "ran-code"
    path = make(tmp_path / "bad.npz", marker) if make is _pickled else make(tmp_path / "bad.npz")
    with pytest.raises(LgnnError) as raised:
        readers[reader](path)
    message = str(raised.value) if reader != "checkpoint" else capsys.readouterr().err
    assert says in message and "\n" not in message.strip(), message
    assert not marker.exists()


def test_an_archive_of_many_members_or_bytes_is_refused(tmp_path, monkeypatch):
    small = _npy((1,), np.float64, b"\0" * 8)
    path = _archive(tmp_path / "many.npz", {f"a{k}.npy": small for k in range(5)})
    monkeypatch.setattr(archives, "MAX_MEMBERS", 4)
    assert "5 members, more than the 4" in archives.npz_problem(path)
    monkeypatch.setattr(archives, "MAX_MEMBERS", 4096)
    monkeypatch.setattr(archives, "MAX_ARCHIVE_BYTES", 4 * len(small))
    assert "its members inflate to" in archives.npz_problem(path)


def test_meta_nested_past_the_limit_is_refused(tmp_path, capsys):
    deep = nested = {}
    for _ in range(archives.MAX_JSON_DEPTH):
        nested["x"] = {}
        nested = nested["x"]
    record = tmp_path / "deep.npz"
    records.save(record, {"a": np.zeros(1)}, {"deep": deep})  # a checksum recomputed, as a forger would
    with pytest.raises(records.RecordError, match="its meta is JSON nested deeper than 64 levels"):
        records.read(record)
    assert main(["checkpoint", str(record)]) == 2
    assert "nested deeper than 64 levels" in capsys.readouterr().err

    scene = tmp_path / "deep.json"
    scene.write_text(json.dumps({"name": "deep", "extra": deep}))
    with pytest.raises(LgnnError, match="not a scene: JSON nested deeper than 64 levels"):
        load_scene_file(scene)

    trajectory = tmp_path / "deep-trajectory.npz"
    np.savez(trajectory, t=np.zeros(2), q=np.zeros((2, 1, 2)), qd=np.zeros((2, 1, 2)), energy=np.zeros(2), metadata=json.dumps(deep))
    with pytest.raises(ConfigError, match="nested deeper than 64 levels"):
        Trajectory.load(trajectory)


def test_what_lgnn_writes_passes():
    """The checks refuse nothing lgnn writes: a record, a compressed one, a trajectory."""
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        records.save(folder / "r.npz", {"a": np.arange(6.0).reshape(2, 3), "s": np.array("text")}, {"m": [1, {"k": 2}]})
        records.save(folder / "c.npz", {"a": np.zeros((40, 40)), "b": np.ones(3, np.int32)}, {}, compressed=True)
        Trajectory(np.arange(2.0), np.zeros((2, 1, 2)), np.zeros((2, 1, 2)), np.zeros(2)).save(folder / "t.npz")
        for name in ("r.npz", "c.npz", "t.npz"):
            assert archives.npz_problem(folder / name) is None


def test_a_checkpoint_naming_code_never_imports_it(tmp_path, capsys):
    """A checkpoint from elsewhere that names a model file (`model_source`) is read, rolled
    out and verified without importing it: only --model-code (and --add-model, or a
    config's grid) import code."""
    import shutil
    from pathlib import Path

    marker = tmp_path / "ran-code"
    code = tmp_path / "evil.py"
    code.write_text(f"open({str(marker)!r}, 'w')\n")
    results = Path(__file__).resolve().parents[1] / "results" / "benchmark"
    folder = tmp_path / "submitted" / "benchmark"
    (folder / "checkpoints").mkdir(parents=True)
    checkpoint = folder / "checkpoints" / "lgnn-chain4-s0.npz"
    shutil.copy(results / "checkpoints" / "lgnn-chain4-s0.npz", checkpoint)
    arrays, meta = records.read(checkpoint)
    meta["model"] = {**meta["model"], "name": "evil"}
    meta["model_source"] = f"{code}:SPEC"
    environment = meta.pop("environment")
    records.save(checkpoint, arrays, meta, environment)

    for argv in (["checkpoint", str(checkpoint)], ["rollout", "chain4", "--model", str(checkpoint), "--duration", "0.01", "--out", str(tmp_path / "r.npz")]):
        assert main(argv) == 2
        assert "is defined outside lgnn" in capsys.readouterr().err
    assert main(["leaderboard", "verify", str(folder.parent), "--quiet", "--set", "models=['lgnn']", "--set", "scenes=['chain4']",
                 "--set", "tracks=['paper']"]) == 1
    assert "lgnn: failed: " in capsys.readouterr().out
    assert not marker.exists()


@pytest.mark.parametrize("text", ["[1]", "[" * 100 + "]" * 100, "{" + '"a":{' * 70 + "}" * 71])
def test_a_hand_back_manifest_that_is_not_one_is_refused(tmp_path, text, capsys):
    from lgnn.bench.handoff import MANIFEST

    (tmp_path / "back").mkdir()
    (tmp_path / "back" / MANIFEST).write_text(text)
    assert main(["handoff", "unpack", str(tmp_path / "back"), "--out-dir", str(tmp_path / "out")]) == 2
    assert "hand-back manifest" in capsys.readouterr().err
