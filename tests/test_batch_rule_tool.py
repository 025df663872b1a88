"""`tools/batch_rule.py --summarise`: the table of convergence per GPU-second reads the
median over seeds (a seed that stopped keeps its best), the rate after the first
call, and the seconds a variant took to the protocol run's end MSE."""

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _tool(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ROOT / "tools" / "batch_rule.py"), *args], cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)},
                          capture_output=True, text=True, timeout=300)


def _row(variant, protocol, curves, stop):
    return {"model": "lgnn", "scene": "chain4", "variant": variant, "protocol": protocol, "batch": 100, "learning_rate": 1e-3,
            "seeds": [0, 1, 2], "seconds": 3.0, "epochs": [int(c[-1][0]) for c in curves], "stop": stop, "curves": curves}


def test_the_table_takes_medians_over_seeds_and_times_the_variant_to_the_protocols_end(tmp_path):
    # [epoch, best MSE so far, seconds]. The third protocol seed stopped at epoch 20
    # with 2.0: at epoch 30 the seeds hold 0.25, 0.5 and 2.0, median 0.5.
    protocol = _row("protocol", True, [[[10, 1.0, 1.0], [20, 0.5, 2.0], [30, 0.25, 3.0]],
                                       [[10, 2.0, 1.0], [20, 1.0, 2.0], [30, 0.5, 3.0]],
                                       [[10, 4.0, 1.0], [20, 2.0, 2.0]]], [None, None, "plateau (best improved by under 1% in epochs 0-20)"])
    fast = _row("fast", False, [[[10, 0.6, 1.0], [20, 0.4, 1.5], [30, 0.3, 2.0]]] * 3, ["minutes cap"] * 3)
    path = tmp_path / "runs.jsonl"
    path.write_text("\n".join(json.dumps(r) for r in ({"environment": {}}, fast, protocol)) + "\n")
    done = _tool("--summarise", str(path))
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    rows = [dict(zip(header, (c.strip() for c in line.strip("|").split("|")))) for line in lines[2:]]
    assert [r["variant"] for r in rows] == ["protocol", "fast"]  # the protocol first
    first, second = rows
    assert first["epochs/s"] == "10.0" and second["epochs/s"] == "20.0"  # (30 - 10) epochs over (3 - 1) and (2 - 1) s
    assert first["MSE at the end"] == "0.5" and first["stopped by"] == "budget; plateau"
    assert second["MSE at the end"] == "0.3" and second["stopped by"] == "minutes cap"
    assert second["s to the protocol run's end MSE"] == "1.5" and first["s to the protocol run's end MSE"] == ""
    assert first["MSE at 30 s"] == "0.5"


def test_a_setting_that_is_not_a_training_field_is_refused_in_one_line_before_any_data(tmp_path):
    for setting, error in (("learning_rat=3e-3", "name a TrainConfig field and its value"), ("decay_steps=abc", "'abc' is not a number of decay_steps's kind")):
        done = _tool("--models", "lgnn:1", "--data", str(tmp_path / "data"), "--set", setting)
        assert done.returncode != 0 and done.stderr.strip().splitlines() == [f"error: --set {setting!r}: {error}"]
    assert not (tmp_path / "data").exists()
