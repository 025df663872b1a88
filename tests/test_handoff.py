"""A benchmark run handed from one job to the next (`lgnn.bench.handoff`, `lgnn handoff`):
what a fresh machine needs to resume, in a few files within stated limits, taken back
whole or refused in one line, and resumed there as on the machine that stopped."""

import io
import json
import tarfile

import numpy as np
import pytest

from lgnn import records
from lgnn.bench import handoff, profiles
from lgnn.cli import main
from lgnn.errors import ConfigError
from lgnn.learn import checkpoints, models, protocol, train
from lgnn.learn.data import DataConfig

QUICK = profiles.PROFILES["quick"]
# A job finished and evaluated on one of its two scenes (still rolled out: its best
# parameters go), and one cut back mid-training (all of it goes).
FINISHED, TRAINING = "gns-chain4-s0", "clnn-chain4-s0"
CUT_AT = 5


@pytest.fixture(scope="module")
def stopped_run(tmp_path_factory):
    """A quick-profile output folder as a job leaves it: `FINISHED` trained and evaluated
    on chain4, `TRAINING` trained and then cut back to epoch `CUT_AT` (its latest
    parameters and optimiser state kept), as a run stopped there leaves it."""
    out = tmp_path_factory.mktemp("run")
    assert main(["benchmark", "--stage", "train", "--job", FINISHED, "--job", TRAINING, "--out-dir", str(out), "--quiet"]) == 0
    assert main(["benchmark", "--stage", "evaluate", "--job", FINISHED, "--scene", "chain4", "--out-dir", str(out), "--quiet"]) == 0
    path = out / "benchmark" / "checkpoints" / f"{TRAINING}.npz"
    state, meta = train.load_checkpoint(path)
    cut = state._replace(epoch=CUT_AT, history=state.history[:CUT_AT], best_epoch=min(state.best_epoch, CUT_AT))
    train.save_checkpoint(path, cut, models.ModelConfig.from_dict(meta["model"]), protocol.TrainConfig(**meta["train_config"]),
                          DataConfig(**meta["data"]))
    return out


def _member_roles(manifest: dict) -> dict:
    return {member["name"]: member["role"] for member in manifest["members"]}


def test_a_stopped_run_is_handed_back_and_resumes_on_a_fresh_machine(stopped_run, tmp_path, monkeypatch, capsys):
    """Records go as they are, the unfinished checkpoint whole, the finished one with its
    best parameters alone; unpacked into a fresh folder with a fresh dataset cache, the
    files are the same and the benchmark resumes: the unfinished job trains on from its
    epoch, the finished one is reused, its record too."""
    stray = stopped_run / "benchmark" / "runs" / "ground-truth" / ".chain8.npz.x1y2.tmp.npz"  # a stopped write's temporary
    stray.write_bytes(b"half")
    manifest = handoff.pack(QUICK, stopped_run, tmp_path / "back")
    stray.unlink()
    roles = _member_roles(manifest)
    assert not any(".tmp" in name for name in roles)
    assert roles[f"benchmark/checkpoints/{TRAINING}.npz"] == handoff.TRAINING
    assert roles[f"benchmark/checkpoints/{FINISHED}.npz"] == handoff.INFERENCE  # chain8 is not evaluated yet
    assert {f"benchmark/runs/{FINISHED}/chain4.npz", "benchmark/runs/ground-truth/chain4.npz", "benchmark/run.json"} <= set(roles)
    assert manifest["left_out"] == [] and sorted(p.name for p in (tmp_path / "back").iterdir()) == ["handoff.json", "handoff.tar.000"]

    fresh = tmp_path / "fresh"
    handoff.unpack(tmp_path / "back", fresh)
    for name, role in roles.items():
        if role != handoff.INFERENCE:
            assert (fresh / name).read_bytes() == (stopped_run / name).read_bytes(), name
    slim = fresh / "benchmark" / "checkpoints" / f"{FINISHED}.npz"
    assert checkpoints.content_digest(slim) == checkpoints.content_digest(stopped_run / "benchmark" / "checkpoints" / f"{FINISHED}.npz")

    monkeypatch.setenv("LGNN_CACHE", str(tmp_path / "new-machine-cache"))
    capsys.readouterr()
    assert main(["benchmark", "--stage", "train", "--job", FINISHED, "--job", TRAINING, "--out-dir", str(fresh), "--quiet"]) == 0
    assert main(["benchmark", "--stage", "evaluate", "--job", FINISHED, "--scene", "chain4", "--out-dir", str(fresh), "--quiet"]) == 0
    log = capsys.readouterr().err
    assert f"resuming at epoch {CUT_AT}" in log and "reusing finished checkpoint" in log
    assert f"evaluate {FINISHED.split('-')[0]} s0 on chain4" not in log  # its record was handed back
    resumed, _ = train.load_checkpoint(fresh / "benchmark" / "checkpoints" / f"{TRAINING}.npz")
    cut, _ = train.load_checkpoint(stopped_run / "benchmark" / "checkpoints" / f"{TRAINING}.npz")
    assert resumed.epoch == QUICK.training.train.epochs and resumed.history[:CUT_AT] == cut.history


def test_a_hand_back_keeps_to_its_limits(stopped_run, tmp_path, monkeypatch):
    """Cut into parts of the size given and taken back whole; where the unfinished
    checkpoint does not fit it is left out and named (that job starts again); where the
    records alone do not fit nothing is written."""
    monkeypatch.setattr(handoff, "MANIFEST_RESERVE", 1024)
    whole = handoff.pack(QUICK, stopped_run, tmp_path / "whole")
    stream = whole["bytes"]
    split = handoff.pack(QUICK, stopped_run, tmp_path / "split", handoff.Limits(files=8, file_bytes=stream // 4 + 1, total_bytes=10 * stream))
    assert len(split["parts"]) == 4 and all(part["bytes"] <= stream // 4 + 1 for part in split["parts"])
    handoff.unpack(tmp_path / "split", tmp_path / "from-parts")
    for member in split["members"]:
        name = member["name"]
        assert (tmp_path / "from-parts" / name).stat().st_size == member["bytes"], name

    training = next(m for m in whole["members"] if m["role"] == handoff.TRAINING)
    tight = handoff.Limits(files=8, file_bytes=stream, total_bytes=stream - training["bytes"] + 1024)
    dropped = handoff.pack(QUICK, stopped_run, tmp_path / "tight", tight)
    assert [m["name"] for m in dropped["left_out"]] == [training["name"]] and training["name"] not in _member_roles(dropped)

    with pytest.raises(ConfigError, match="nothing written"):
        handoff.pack(QUICK, stopped_run, tmp_path / "tiny", handoff.Limits(files=2, file_bytes=2048, total_bytes=4096))
    assert not (tmp_path / "tiny").exists() or not any((tmp_path / "tiny").iterdir())


def test_a_damaged_or_foreign_hand_back_is_refused_in_one_line(stopped_run, tmp_path, capsys):
    back = tmp_path / "back"
    assert main(["handoff", "pack", str(stopped_run), "--to", str(back)]) == 0
    assert "handed back" in capsys.readouterr().out
    # Into a folder that holds a run: refused, nothing touched.
    assert main(["handoff", "unpack", str(back), "--out-dir", str(stopped_run)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "already holds a run" in err
    # A manifest that lists other files than its parts hold.
    listed = json.loads((back / "handoff.json").read_text())
    (back / "handoff.json").write_text(json.dumps({**listed, "members": listed["members"][1:]}))
    assert main(["handoff", "unpack", str(back), "--out-dir", str(tmp_path / "listed")]) == 2
    assert "other files than handoff.json lists" in capsys.readouterr().err and not (tmp_path / "listed" / "benchmark").exists()
    # One byte of a part flipped.
    part = back / "handoff.tar.000"
    data = bytearray(part.read_bytes())
    data[len(data) // 2] ^= 1
    part.write_bytes(bytes(data))
    assert main(["handoff", "unpack", str(back), "--out-dir", str(tmp_path / "a")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "handoff.tar.000: missing or damaged" in err and not (tmp_path / "a" / "benchmark").exists()
    # No manifest; a manifest of something else.
    assert main(["handoff", "unpack", str(tmp_path / "nothing"), "--out-dir", str(tmp_path / "b")]) == 2
    assert "no hand-back there" in capsys.readouterr().err
    (back / "handoff.json").write_text(json.dumps({"format": 1, "parts": [{"name": "../x", "bytes": 1, "sha256": ""}]}))
    assert main(["handoff", "unpack", str(back), "--out-dir", str(tmp_path / "b")]) == 2
    assert "not a hand-back manifest" in capsys.readouterr().err
    # A member outside benchmark/, with its part's checksum right.
    evil = io.BytesIO()
    with tarfile.open(fileobj=evil, mode="w") as archive:
        info = tarfile.TarInfo("../outside.txt")
        info.size = 2
        archive.addfile(info, io.BytesIO(b"hi"))
    part.write_bytes(evil.getvalue())
    manifest = {"format": 1, "commit": "x", "profile": "quick", "bytes": len(evil.getvalue()), "members": [], "left_out": [],
                "parts": [{"name": part.name, "bytes": len(evil.getvalue()), "sha256": records.file_digest(part)}]}
    (back / "handoff.json").write_text(json.dumps(manifest))
    assert main(["handoff", "unpack", str(back), "--out-dir", str(tmp_path / "c")]) == 2
    assert "is not a file under benchmark/" in capsys.readouterr().err
    assert not (tmp_path / "outside.txt").exists() and not (tmp_path / "c" / "benchmark").exists()


def test_a_finished_and_fully_evaluated_job_goes_without_its_parameters(stopped_run, tmp_path):
    """Once no stage rolls a finished job out again (every pair recorded, not timed, not
    the mass stage's LGNN), its checkpoint goes as its meta and history alone: what the
    report reads, with the content digest its records are keyed on."""
    only_chain4 = profiles.load_profile("quick", ['scenes=["chain4"]'])
    told = []
    manifest = handoff.pack(only_chain4, stopped_run, tmp_path / "back", log=told.append)
    assert not any("belong to no job" in line for line in told)
    just_gns = profiles.load_profile("quick", ['models=["gns"]'])
    handoff.pack(just_gns, stopped_run, tmp_path / "other", log=told.append)
    assert any(f"1 checkpoints belong to no job of the quick profile given, left out: {TRAINING}.npz" in line for line in told), told
    assert _member_roles(manifest)[f"benchmark/checkpoints/{FINISHED}.npz"] == handoff.HISTORY
    handoff.unpack(tmp_path / "back", tmp_path / "fresh")
    meta, arrays = checkpoints.read(tmp_path / "fresh" / "benchmark" / "checkpoints" / f"{FINISHED}.npz")
    assert not checkpoints.has_parameters(meta) and not any(name.startswith(("params/", "best/", "opt/")) for name in arrays)
    assert np.asarray(arrays["history"]).shape[0] == QUICK.training.train.epochs
