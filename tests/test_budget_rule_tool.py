"""`tools/budget_rule.py`: the smallest epoch budget whose doubling changes no model's
rank, read from checkpoints' validation curves; a run cut off short of the protocol's
rules says nothing past its last epoch."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from lgnn.bench import grid, profiles, store
from lgnn.learn import models, train
from lgnn.scene import get_scene

ROOT = Path(__file__).resolve().parents[1]


def _checkpoint(folder: Path, model_name: str, val: np.ndarray) -> None:
    """A chain4 checkpoint of the full profile's job whose run had validation MSE `val`
    at epochs 1..len(val) (untrained parameters: the tool reads the history alone)."""
    profile = profiles.PROFILES["full"]
    job = grid.TrainingJob(model_name, grid.TRAINING_SCENE, 0)
    model, config = models.ModelConfig.for_scene(model_name, get_scene(job.scene)), profiles.train_config(profile, job)
    history = [(k + 1, float(v), float(v), float(k)) for k, v in enumerate(val)]
    best = int(np.argmin(val))
    state = train.initial_state(model, config)._replace(best_val=float(val[best]), best_epoch=best + 1, epoch=len(val), history=history)
    path = store.Layout(folder).checkpoint(job)
    path.parent.mkdir(parents=True, exist_ok=True)
    train.save_checkpoint(path, state, model, config)


def _tool(*args: str) -> str:
    done = subprocess.run([sys.executable, str(ROOT / "tools" / "budget_rule.py"), *args], cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)},
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_the_budget_is_where_doubling_stops_changing_the_ranking_and_a_cut_off_run_leaves_it_open(tmp_path):
    epochs = np.arange(1, 601)
    # lgnn falls fast, then stops improving at epoch 100: the plateau rule ends it at 300.
    # gns falls slowly and passes lgnn at epoch 150 (4 / e^1.2), then flattens (plateau at 500).
    lgnn = np.where(epochs < 100, 1.0 / epochs, 0.01)[:300]
    gns = np.where(epochs < 300, 4.0 / epochs ** 1.2, 4.0 / 300 ** 1.2)[:500]
    _checkpoint(tmp_path, "lgnn", lgnn)
    _checkpoint(tmp_path, "gns", gns)
    table = _tool("--results", str(tmp_path), "--budgets", "50", "100", "200", "400")
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.strip("|").split("|")] for line in table.splitlines()
            if line.startswith("| ") and line.split("|")[1].strip().isdigit()}
    # At 50 and 100 lgnn leads; at 200 gns leads, and keeps the lead at 400 and 800.
    assert rows["50"][1] == "lgnn < gns" and rows["100"][3] == "no" and rows["200"][1] == "gns < lgnn"
    assert rows["200"][3] == "yes" and rows["400"][3] == "yes"
    assert "The rule's budget: 200 epochs" in table, table
    # gns cut off at epoch 250 (before its plateau): nothing is known of it past 250.
    _checkpoint(tmp_path, "gns", gns[:250])
    table = _tool("--results", str(tmp_path), "--budgets", "50", "100", "200", "400")
    assert "cut off at epoch 250" in table and "undetermined" in table and "The rule's budget: undetermined" in table, table
