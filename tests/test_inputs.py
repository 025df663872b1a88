"""Every input gets a clear answer (issue 34): a table of bad inputs, each entering
where a user gives it (scene files, CLI options, TOML configs and `--set`, trajectory
files, checkpoints, output paths), and what `lgnn` must answer: its exit status, one
line on stderr naming the problem (no traceback), and nothing written or changed.

Each case runs in-process through `lgnn.cli.main`; the ones that used to hang (a
FIFO with no writer, a checkpoint asking for a million layers) run as a child
process with a timeout. Commands that would start long work once their input is
accepted (`benchmark`'s stages, `dataset export`) have that work replaced by a
sentinel: reaching it means the input was wrongly accepted.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from lgnn import records
from lgnn.cli import main

CHECKPOINT = Path(__file__).resolve().parents[1] / "results/benchmark/checkpoints/lgnn-chain4-s0.npz"
CHAIN4 = {"name": "c", "gravity": 10, "nodes": [[0, 0], [1, 0], [2, 0]], "pinned": [0],
          "links": [{"nodes": [0, 1], "mass": 1, "inertia": 0.1}, {"nodes": [1, 2], "mass": 1, "inertia": 0.1}]}
# Seconds a case may run: a refusal takes a few (a child process starts JAX); more is a
# hang, or long work that a wrongly accepted input started.
TIMEOUT_S = 60
SIMULATE_SHORT = ["--duration", "0.01", "--dt", "1e-3", "--frame-dt", "1e-3", "--quiet"]


# ---------------------------------------------------------------------------------
# Inputs written into the case's folder
# ---------------------------------------------------------------------------------


def scene(**changes) -> str:
    return json.dumps({**CHAIN4, **changes})


def trajectory_arrays(frames: int = 4) -> dict:
    from lgnn.scene import get_scene, scene_to_dict

    chain = get_scene("chain4")
    q = np.repeat(np.asarray(chain.nodes)[None], frames, axis=0)
    return {"t": np.arange(frames) * 1e-3, "q": q, "qd": np.zeros_like(q), "energy": np.zeros(frames),
            "metadata": json.dumps({"scene": scene_to_dict(chain)})}


def trajectory(**changes):
    """A trajectory file of chain4 at rest, with `changes` to its arrays (None: removed)."""

    def write(path: Path):
        arrays = {k: v for k, v in {**trajectory_arrays(), **changes}.items() if v is not None}
        with open(path, "wb") as handle:
            np.savez(handle, **arrays)

    return write


def checkpoint(edit=lambda meta: None, edit_arrays=lambda arrays: None):
    """The committed LGNN chain4 checkpoint with its meta edited by `edit(meta)`, its
    arrays by `edit_arrays(arrays)`, and a valid checksum (a hand edit that the checksum
    cannot catch)."""

    def write(path: Path):
        arrays, meta = records.read(CHECKPOINT, "checkpoint")
        environment = meta.pop("environment", None)
        edit(meta)
        edit_arrays(arrays)
        records.save(path, arrays, meta, environment=environment)

    return write


def text(content: str | bytes):
    def write(path: Path):
        path.write_bytes(content if isinstance(content, bytes) else content.encode())

    return write


def fifo(path: Path):
    os.mkfifo(path)


def char_device(path: Path):
    os.mknod(path, stat.S_IFCHR | 0o666, os.makedev(1, 7))  # /dev/full's numbers


def directory(path: Path):
    path.mkdir()


def set_key(dotted: str, value):
    def edit(meta):
        *parents, last = dotted.split(".")
        table = meta
        for part in parents:
            table = table[part]
        table[last] = value

    return edit


def drop_key(key: str):
    return lambda meta: meta.pop(key)


def as_format_1(history):
    """A format-1 meta (the history a list in the meta) holding `history`."""

    def edit(meta):
        meta.update(format=1, history=history)

    return edit


@dataclasses.dataclass
class Case:
    id: str
    argv: list[str]  # "{tmp}" is the case's folder
    code: int
    words: str  # in the one stderr line
    files: dict = dataclasses.field(default_factory=dict)  # name in {tmp}: writer(path)
    child: bool = False  # run as a child process with a timeout (used to hang)


def simulate(scene_arg: str, *options: str) -> list[str]:
    return ["simulate", scene_arg, *options]


def config_case(id: str, toml: str, words: str) -> Case:
    return Case(f"config-{id}", ["benchmark", "--config", "{tmp}/c.toml", "--out-dir", "{tmp}/b"], 2, words, {"c.toml": text(toml)})


def set_case(id: str, setting: str, words: str, command: str = "benchmark") -> Case:
    argv = (["benchmark", "--out-dir", "{tmp}/b"] if command == "benchmark"
            else ["dataset", "export", "--scene", "chain4", "--profile", "quick", "--out", "{tmp}/d.npz"])
    return Case(f"set-{command}-{id}", [*argv, "--set", setting], 2, words)


BIG = "1" + "0" * 400


def long_chain(links: int) -> str:
    """A valid straight chain of `links` links pinned at one end."""
    return json.dumps({"name": "long", "nodes": [[float(k), 0.0] for k in range(links + 1)], "pinned": [0],
                       "links": [{"nodes": [k, k + 1], "mass": 1.0, "inertia": 0.1} for k in range(links)]})

CASES = [
    # --- scene files: numbers, nesting, names, paths --------------------------------
    Case("scene-huge-int-gravity", ["mjcf", "{tmp}/s.json", "--out", "{tmp}/o.xml"], 2, "gravity", {"s.json": text(scene(gravity=0).replace('"gravity": 0', f'"gravity": {BIG}'))}),
    Case("scene-huge-int-mass", ["mjcf", "{tmp}/s.json", "--out", "{tmp}/o.xml"], 2, "links[0].mass", {"s.json": text(scene().replace('"mass": 1', f'"mass": {BIG}', 1))}),
    Case("scene-huge-int-node", ["mjcf", "{tmp}/s.json", "--out", "{tmp}/o.xml"], 2, "nodes[1]", {"s.json": text(scene().replace("[1, 0]", f"[{BIG}, 0]", 1))}),
    Case("scene-deep-brackets", ["mjcf", "{tmp}/s.json", "--out", "{tmp}/o.xml"], 2, "nested", {"s.json": text("[" * 100_000)}),
    Case("scene-deep-nodes", ["mjcf", "{tmp}/s.json", "--out", "{tmp}/o.xml"], 2, "nested", {"s.json": text(scene(nodes="X").replace('"X"', "[" * 3000 + "]" * 3000))}),
    Case("scene-name-surrogate", ["mjcf", "{tmp}/s.json", "--out", "{tmp}/o.xml"], 2, "name", {"s.json": text(scene(name="X").replace('"X"', '"a\\udcffb"'))}),
    Case("scene-name-nul", ["mjcf", "{tmp}/s.json", "--out", "{tmp}/o.xml"], 2, "name", {"s.json": text(scene(name="a\u0000b"))}),
    Case("scene-name-newline", ["mjcf", "{tmp}/s.json", "--out", "{tmp}/o.xml"], 2, "name", {"s.json": text(scene(name="a\nb"))}),
    Case("scene-path-newline", simulate("{tmp}/a\nb.json", "--out", "{tmp}/o.npz"), 2, "no such scene file"),
    Case("scene-fifo", simulate("{tmp}/s.json", "--out", "{tmp}/o.npz"), 2, "not a regular file", {"s.json": fifo}),
    Case("scene-nan", ["mjcf", "{tmp}/s.json", "--out", "{tmp}/o.xml"], 2, "NaN", {"s.json": text(scene(gravity=0).replace('"gravity": 0', '"gravity": NaN'))}),
    Case("scene-not-utf8", ["mjcf", "{tmp}/s.json", "--out", "{tmp}/o.xml"], 2, "UTF-8", {"s.json": text(b'{"name": "\xff"}')}),
    Case("scene-too-large", simulate("{tmp}/s.json", *SIMULATE_SHORT, "--out", "{tmp}/o.npz"), 2, "coordinates", {"s.json": text(long_chain(10_000))}),
    # --- CLI options: overflow, ranges, formats --------------------------------------
    Case("simulate-duration-overflow", simulate("chain4", "--duration", "1e308", "--out", "{tmp}/o.npz"), 2, "duration"),
    Case("simulate-tiny-dt", simulate("chain4", "--dt", "5e-324", "--frame-dt", "5e-324", "--out", "{tmp}/o.npz"), 2, "steps"),
    Case("simulate-too-many-frames", simulate("chain4", "--dt", "1e-4", "--frame-dt", "1e-4", "--duration", "1e4", "--out", "{tmp}/o.npz"), 2, "frames"),
    Case("simulate-dt-inf", simulate("chain4", "--dt", "inf", "--out", "{tmp}/o.npz"), 2, "--dt"),
    Case("simulate-out-fifo", simulate("chain4", *SIMULATE_SHORT, "--out", "{tmp}/o.npz"), 2, "not a regular file", {"o.npz": fifo}),
    Case("simulate-out-no-suffix", simulate("chain4", *SIMULATE_SHORT, "--out", "{tmp}/o"), 2, ".npz"),
    Case("crosscheck-batch-0", ["crosscheck", "chain4", "--speed", "--batch", "0", "--out-dir", "{tmp}"], 2, "--batch"),
    Case("crosscheck-batch-negative", ["crosscheck", "chain4", "--speed", "--batch", "-5", "--out-dir", "{tmp}"], 2, "--batch"),
    Case("crosscheck-speed-dts-negative", ["crosscheck", "chain4", "--speed", "--speed-dts", "-1e-3", "--out-dir", "{tmp}"], 2, "--speed-dts"),
    Case("crosscheck-batch-dts-nan", ["crosscheck", "chain4", "--speed", "--batch-dts", "nan", "--out-dir", "{tmp}"], 2, "--batch-dts"),
    Case("crosscheck-max-steps-0", ["crosscheck", "chain4", "--speed", "--max-steps", "0", "--out-dir", "{tmp}"], 2, "--max-steps"),
    Case("crosscheck-mjx-depth-negative", ["crosscheck", "chain4", "--mjx-max-depth", "-1", "--out-dir", "{tmp}"], 2, "--mjx-max-depth"),
    Case("plot-out-txt", ["plot", "{tmp}/a.npz", "--out", "{tmp}/p.txt"], 2, "p.txt", {"a.npz": trajectory()}),
    Case("plot-out-no-suffix", ["plot", "{tmp}/a.npz", "--out", "{tmp}/plotfile"], 2, "plotfile", {"a.npz": trajectory()}),
    Case("animate-fps-tiny", ["animate", "{tmp}/a.npz", "--out", "{tmp}/a.gif", "--fps", "1e-300"], 2, "--fps", {"a.npz": trajectory()}),
    Case("animate-speed-huge", ["animate", "{tmp}/a.npz", "--out", "{tmp}/a.gif", "--speed", "1e300"], 2, "--speed", {"a.npz": trajectory()}),
    Case("animate-out-txt", ["animate", "{tmp}/a.npz", "--out", "{tmp}/a.txt"], 2, "a.txt", {"a.npz": trajectory()}),
    Case("stability-cost-size-0", ["stability", "--cost-sizes", "0", "--out", "{tmp}/s.md"], 2, "--cost-sizes"),
    Case("train-batch-size-0", ["train", "--model", "lgnn", "--batch-size", "0", "--out", "{tmp}/k.npz"], 2, "--batch-size"),
    Case("train-patience-negative", ["train", "--model", "lgnn", "--patience", "-1", "--out", "{tmp}/k.npz"], 2, "--patience"),
    Case("train-trajectories-0", ["train", "--model", "lgnn", "--trajectories", "0", "--out", "{tmp}/k.npz"], 2, "--trajectories"),
    Case("train-message-passing-huge", ["train", "--model", "lgnn", "--message-passing", "1000000", "--out", "{tmp}/k.npz"], 2, "message-passing"),
    Case("convergence-halvings-huge", ["convergence", "chain4", "--halvings", "2000", "--out-dir", "{tmp}"], 2, "halvings"),
    Case("benchmark-out-dir-under-file", ["benchmark", "--out-dir", "{tmp}/f/b"], 2, "not a directory", {"f": text("x")}),
    Case("benchmark-out-dir-is-file", ["benchmark", "--out-dir", "{tmp}/f"], 2, "not a directory", {"f": text("x")}),
    Case("dataset-out-txt", ["dataset", "export", "--scene", "chain4", "--profile", "quick", "--out", "{tmp}/d.txt"], 2, ".npz"),
    Case("mjcf-out-fifo", ["mjcf", "chain4", "--out", "{tmp}/o.xml"], 2, "not a regular file", {"o.xml": fifo}),
    # --- TOML configs and --set --------------------------------------------------------
    Case("config-not-utf8", ["benchmark", "--config", "{tmp}/c.toml", "--out-dir", "{tmp}/b"], 2, "UTF-8", {"c.toml": text(b'profile = "quick\xff"\n')}),
    Case("config-deep-arrays", ["benchmark", "--config", "{tmp}/c.toml", "--out-dir", "{tmp}/b"], 2, "nested", {"c.toml": text("seeds = " + "[" * 5000 + "]" * 5000 + "\n")}),
    Case("config-directory", ["benchmark", "--config", "{tmp}/c.toml", "--out-dir", "{tmp}/b"], 2, "not a regular file", {"c.toml": directory}),
    Case("config-fifo", ["benchmark", "--config", "{tmp}/c.toml", "--out-dir", "{tmp}/b"], 2, "not a regular file", {"c.toml": fifo}, child=True),
    Case("set-deep-arrays", ["benchmark", "--out-dir", "{tmp}/b", "--set", "seeds=" + "[" * 5000 + "]" * 5000], 2, "nested"),
    set_case("sample-dt-0", "training.data.sample_dt=0", "sample_dt"),
    set_case("sample-dt-nan", "training.data.sample_dt=nan", "sample_dt"),
    set_case("data-duration-inf", "training.data.duration=inf", "duration"),
    set_case("sample-dt-0", "training.data.sample_dt=0", "sample_dt", "dataset"),
    set_case("sample-dt-nan", "training.data.sample_dt=nan", "sample_dt", "dataset"),
    set_case("data-duration-inf", "training.data.duration=inf", "duration", "dataset"),
    set_case("data-dt-0", "training.data.dt=0", "dt"),
    set_case("data-chunk-0", "training.data.chunk=0", "chunk"),
    set_case("ic-0", "evaluate.initial_conditions=0", "initial_conditions"),
    set_case("ic-negative", "evaluate.initial_conditions=-3", "initial_conditions"),
    set_case("duration-negative", "evaluate.duration=-1", "duration"),
    set_case("duration-0", "evaluate.duration=0", "duration"),
    config_case("duration-1e999", "[evaluate]\nduration = 1e999\n", "duration"),
    set_case("eval-dt-nan", "evaluate.dt=nan", "dt"),
    set_case("eval-dt-0", "evaluate.dt=0", "dt"),
    set_case("eval-dt-negative", "evaluate.dt=-1e-3", "dt"),
    set_case("chunk-0", "evaluate.chunk=0", "chunk"),
    set_case("mujoco-dt-0", "evaluate.mujoco_dt=0", "mujoco_dt"),
    set_case("floor-nan", "evaluate.floor_perturbation=nan", "floor_perturbation"),
    set_case("scene-dt-0", 'evaluate.scene_dts=[["T2", 0.0]]', "scene_dts"),
    set_case("lr-inf", "training.train.learning_rate=inf", "learning rate"),
    set_case("batch-size-0", "training.train.batch_size=0", "batch size"),
    set_case("patience-negative", "training.train.patience=-1", "patience"),
    set_case("minutes-nan", "training.train.minutes=nan", "minutes"),
    set_case("speed-dts-negative", "speed.dts=[-1e-3]", "speed.dts"),
    set_case("speed-horizon-0", "speed.horizon=0", "horizon"),
    set_case("scaling-lengths-0", "scaling.lengths=[0]", "scaling.lengths"),
    set_case("scaling-steps-0", "scaling.steps=0", "steps"),
    set_case("throughput-batch-0", "scaling.throughput_batch=0", "throughput_batch"),
    set_case("scenes-bogus", 'scenes=["bogus"]', "bogus"),
    set_case("train-scenes-bogus", 'train_scenes=["bogus"]', "bogus"),
    set_case("models-bogus", 'models=["bogus"]', "bogus"),
    set_case("seeds-empty", "seeds=[]", "seeds"),
    set_case("mass-scene-bogus", 'mass.scenes=["bogus"]', "bogus"),
    set_case("throughput-scene-bogus", 'scaling.throughput_scenes=["bogus"]', "bogus"),
    config_case("grid-model-missing", '[[grid]]\nmodel = "nonexistent"\ntrain_scene = "chain4"\neval_scenes = ["chain4"]\n', "nonexistent"),
    config_case("grid-train-scene-missing", '[[grid]]\nmodel = "lgnn"\ntrain_scene = "missing.json"\neval_scenes = ["chain4"]\n', "missing.json"),
    config_case("grid-eval-scene-missing", '[[grid]]\nmodel = "lgnn"\ntrain_scene = "chain4"\neval_scenes = ["nope"]\n', "nope"),
    # --- trajectory files for compare and plot -----------------------------------------
    Case("compare-npy", ["compare", "{tmp}/a.npz", "{tmp}/b.npy"], 2, "b.npy", {"a.npz": trajectory(), "b.npy": lambda p: np.save(p, np.zeros(3))}),
    Case("compare-metadata-number", ["compare", "{tmp}/a.npz", "{tmp}/b.npz"], 2, "metadata", {"a.npz": trajectory(metadata="5"), "b.npz": trajectory()}),
    Case("compare-metadata-null", ["compare", "{tmp}/a.npz", "{tmp}/b.npz"], 2, "metadata", {"a.npz": trajectory(metadata="null"), "b.npz": trajectory()}),
    Case("compare-metadata-list", ["compare", "{tmp}/a.npz", "{tmp}/b.npz"], 2, "metadata", {"a.npz": trajectory(), "b.npz": trajectory(metadata="[1, 2]")}),
    Case("compare-metadata-not-json", ["compare", "{tmp}/a.npz", "{tmp}/b.npz"], 2, "metadata", {"a.npz": trajectory(), "b.npz": trajectory(metadata="{")}),
    Case("plot-model-str", ["plot", "{tmp}/a.npz", "{tmp}/b.npz", "--out", "{tmp}/p.png"], 2, "model",
         {"a.npz": trajectory(), "b.npz": trajectory(metadata=json.dumps({"model": "str"}))}),
    Case("compare-q-strings", ["compare", "{tmp}/a.npz", "{tmp}/b.npz"], 2, "q", {"a.npz": trajectory(), "b.npz": trajectory(q=np.full((4, 5, 2), "x"))}),
    Case("compare-q-huge", ["compare", "{tmp}/a.npz", "{tmp}/b.npz"], 2, "q", {"a.npz": trajectory(), "b.npz": trajectory(q=np.full((4, 5, 2), 1e300))}),
    Case("compare-q-nan", ["compare", "{tmp}/a.npz", "{tmp}/b.npz"], 2, "q", {"a.npz": trajectory(), "b.npz": trajectory(q=np.full((4, 5, 2), np.nan))}),
    Case("compare-t-wrong-shape", ["compare", "{tmp}/a.npz", "{tmp}/b.npz"], 2, "t", {"a.npz": trajectory(), "b.npz": trajectory(t=np.zeros((2, 2)))}),
    Case("compare-energy-short", ["compare", "{tmp}/a.npz", "{tmp}/b.npz"], 2, "energy", {"a.npz": trajectory(), "b.npz": trajectory(energy=np.zeros(2))}),
    Case("compare-scene-not-object", ["compare", "{tmp}/a.npz", "{tmp}/b.npz"], 2, "scene", {"a.npz": trajectory(metadata=json.dumps({"scene": 5})), "b.npz": trajectory()}),
    Case("compare-directory", ["compare", "{tmp}/a.npz", "{tmp}/d"], 2, "not a regular file", {"a.npz": trajectory(), "d": directory}),
    Case("compare-fifo", ["compare", "{tmp}/a.npz", "{tmp}/b.npz"], 2, "not a regular file", {"a.npz": trajectory(), "b.npz": fifo}, child=True),
    # --- hand-edited checkpoints with a valid checksum -----------------------------------
    Case("checkpoint-npy", ["checkpoint", "{tmp}/k.npy"], 2, "not a readable lgnn checkpoint", {"k.npy": lambda p: np.save(p, np.zeros(3))}),
    Case("checkpoint-fifo", ["checkpoint", "{tmp}/k.npz"], 2, "k.npz", {"k.npz": fifo}),
    Case("checkpoint-no-epoch", ["checkpoint", "{tmp}/k.npz"], 2, "epoch", {"k.npz": checkpoint(drop_key("epoch"))}),
    Case("checkpoint-no-history", ["checkpoint", "{tmp}/k.npz"], 2, "history", {"k.npz": checkpoint(edit_arrays=lambda a: a.pop("history"))}),
    Case("checkpoint-history-number", ["checkpoint", "{tmp}/k.npz"], 2, "history",
         {"k.npz": checkpoint(edit_arrays=lambda a: a.update(history=np.float64(5)))}),
    Case("checkpoint-history-strings", ["checkpoint", "{tmp}/k.npz"], 2, "history",
         {"k.npz": checkpoint(edit_arrays=lambda a: a.update(history=np.array([["a", "b", "c", "d"]])))}),
    Case("checkpoint-format-1-no-history", ["checkpoint", "{tmp}/k.npz"], 2, "history", {"k.npz": checkpoint(as_format_1(None))}),
    Case("checkpoint-format-1-history-number", ["checkpoint", "{tmp}/k.npz"], 2, "history", {"k.npz": checkpoint(as_format_1(5))}),
    Case("checkpoint-format-1-history-strings", ["checkpoint", "{tmp}/k.npz"], 2, "history", {"k.npz": checkpoint(as_format_1([["a", "b", "c"]]))}),
    Case("checkpoint-elapsed-string", ["checkpoint", "{tmp}/k.npz"], 2, "elapsed_s", {"k.npz": checkpoint(set_key("elapsed_s", "x"))}),
    Case("checkpoint-epoch-string", ["checkpoint", "{tmp}/k.npz"], 2, "epoch", {"k.npz": checkpoint(set_key("epoch", "x"))}),
    Case("checkpoint-best-epoch-string", ["checkpoint", "{tmp}/k.npz"], 2, "best_epoch", {"k.npz": checkpoint(set_key("best_epoch", "x"))}),
    Case("checkpoint-best-val-string", ["checkpoint", "{tmp}/k.npz"], 2, "best_val", {"k.npz": checkpoint(set_key("best_val", "x"))}),
    Case("checkpoint-no-best-val", ["checkpoint", "{tmp}/k.npz"], 2, "'best_val' is missing", {"k.npz": checkpoint(drop_key("best_val"))}),
    Case("checkpoint-epoch-negative", ["checkpoint", "{tmp}/k.npz"], 2, "epoch", {"k.npz": checkpoint(set_key("epoch", -1))}),
    Case("checkpoint-model-dim", ["checkpoint", "{tmp}/k.npz"], 2, "dim", {"k.npz": checkpoint(set_key("model.dim", "2"))}),
    Case("checkpoint-model-hidden", ["checkpoint", "{tmp}/k.npz"], 2, "hidden", {"k.npz": checkpoint(set_key("model.hidden", "10"))}),
    Case("checkpoint-model-latent", ["checkpoint", "{tmp}/k.npz"], 2, "latent", {"k.npz": checkpoint(set_key("model.latent", 2.5))}),
    Case("checkpoint-model-vocabulary", ["checkpoint", "{tmp}/k.npz"], 2, "vocabulary", {"k.npz": checkpoint(set_key("model.vocabulary", 5))}),
    Case("checkpoint-data-scene-list", ["rollout", "chain4", "--model", "{tmp}/k.npz", *SIMULATE_SHORT, "--out", "{tmp}/o.npz"], 2, "scene",
         {"k.npz": checkpoint(set_key("data.scene", ["x"]))}),
    Case("checkpoint-message-passing-huge", ["checkpoint", "{tmp}/k.npz"], 2, "message", {"k.npz": checkpoint(set_key("model.message_passing", 1_000_000))}, child=True),
    # --- partial outputs ---------------------------------------------------------------
    Case("evaluate-initial-conditions-huge", ["evaluate", "chain4", "--model", str(CHECKPOINT), "--initial-conditions", "1000000000", "--out-dir", "{tmp}"], 2,
         "--initial-conditions"),
    Case("evaluate-bad-second-scene", ["evaluate", "chain4", "{tmp}/bad.json", "--model", str(CHECKPOINT), *SIMULATE_SHORT, "--out-dir", "{tmp}/d"], 2, "bad.json",
         {"bad.json": text("{"), "d": directory}),
]


# ---------------------------------------------------------------------------------
# The harness
# ---------------------------------------------------------------------------------


def snapshot(folder: Path) -> dict:
    """Every entry under `folder`: its type, and a regular file's content digest."""
    entries = {}
    for path in sorted(folder.rglob("*")):
        mode = path.lstat().st_mode
        entries[str(path.relative_to(folder))] = hashlib.sha256(path.read_bytes()).hexdigest() if stat.S_ISREG(mode) else stat.S_IFMT(mode)
    return entries


class Hang(Exception):
    pass


def run_in_process(argv, capsys) -> tuple[int, str]:
    """`main(argv)`'s exit status and stderr; a run past `TIMEOUT_S` is a failure (a
    hang, or work an accepted bad input started)."""

    def alarm(signum, frame):
        raise Hang

    previous = signal.signal(signal.SIGALRM, alarm)
    signal.alarm(TIMEOUT_S)
    try:
        code = main(argv)
    except SystemExit as exit:
        code = exit.code
    except Hang:
        pytest.fail(f"still running after {TIMEOUT_S} s: lgnn {' '.join(argv)}")
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    err = capsys.readouterr().err
    return code, err


def run_child(argv) -> tuple[int, str]:
    try:
        result = subprocess.run([sys.executable, "-m", "lgnn", *argv], capture_output=True, text=True, timeout=TIMEOUT_S, stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired:
        pytest.fail(f"hang: still running after {TIMEOUT_S} s: lgnn {' '.join(argv)}")
    return result.returncode, result.stderr


@pytest.fixture
def sentinels(monkeypatch):
    """Long work that starts only once a command's input is accepted."""

    def started(*args, **kwargs):
        raise AssertionError("wrongly accepted: the command's work started")

    monkeypatch.setattr("lgnn.bench.run.run", started)
    monkeypatch.setattr("lgnn.bench.dataset.export_scene", started)


@pytest.mark.parametrize("case", CASES, ids=[case.id for case in CASES])
def test_every_bad_input_gets_one_line_and_changes_nothing(case, tmp_path, capsys, sentinels, monkeypatch):
    monkeypatch.chdir(tmp_path)
    folder = tmp_path / "case"
    folder.mkdir()
    for name, write in case.files.items():
        write(folder / name)
    before = snapshot(folder)
    argv = [arg.replace("{tmp}", str(folder)) for arg in case.argv]
    code, err = run_child(argv) if case.child else run_in_process(argv, capsys)
    assert "Traceback" not in err, err
    assert code == case.code, err
    if case.code == 0:
        return
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("lgnn: error:") and case.words in lines[0], err
    assert snapshot(folder) == before, "a failed command changed its folder"
    assert not (tmp_path / "lgnn-out").exists()


def test_mjcf_escapes_a_scene_name_into_well_formed_xml(tmp_path, capsys):
    import xml.etree.ElementTree as ElementTree

    (tmp_path / "s.json").write_text(scene(name='a"<&-->b'))
    for form in ("nested", "maximal"):
        out = tmp_path / f"{form}.xml"
        assert main(["mjcf", str(tmp_path / "s.json"), "--form", form, "--out", str(out)]) == 0
        assert ElementTree.parse(out).getroot().get("model") == 'a"<&-->b'


@pytest.mark.skipif(os.geteuid() != 0, reason="creating a character device needs root")
def test_an_output_naming_a_device_is_refused_not_replaced(tmp_path, capsys):
    device = tmp_path / "full"
    char_device(device)
    code, err = run_in_process(["mjcf", "chain4", "--out", str(device)], capsys)
    assert code == 2 and "not a regular file" in err
    assert stat.S_ISCHR(device.lstat().st_mode)


# ---------------------------------------------------------------------------------
# Generated inputs (hypothesis): whatever the input, one of two answers
# ---------------------------------------------------------------------------------

from hypothesis import HealthCheck, example, given, settings, strategies as st  # noqa: E402

from lgnn.engines.base import SimulationConfig  # noqa: E402
from lgnn.errors import ConfigError  # noqa: E402

GENERATED = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-(10**500), 10**500) | st.floats(allow_nan=False, allow_infinity=False) | st.text(max_size=8),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=6), children, max_size=4),
    max_leaves=12,
)


def answered_cleanly(code, err: str, folder: Path, before: dict, written: Path | None = None) -> None:
    """The property: exit 0 (with `written` present), or exit 2 or 3 with one
    `lgnn: error:` line and the folder as it was."""
    assert "Traceback" not in err, err
    if code == 0:
        assert written is None or written.is_file()
        return
    lines = err.strip().splitlines()
    assert code in (2, 3) and len(lines) == 1 and lines[0].startswith("lgnn: error:"), err
    assert snapshot(folder) == before


def mutated(document: dict, path: tuple, value) -> dict:
    """`document` with the entry at `path` (keys and indices) set to `value`."""
    document = json.loads(json.dumps(document))
    node = document
    for step in path[:-1]:
        node = node[step]
    node[path[-1]] = value
    return document


SCENE_PATHS = st.sampled_from([("name",), ("gravity",), ("drag",), ("nodes",), ("nodes", 1), ("nodes", 1, 0), ("pinned",), ("pinned", 0),
                               ("links",), ("links", 0), ("links", 0, "nodes"), ("links", 0, "nodes", 1), ("links", 1, "mass"),
                               ("links", 1, "inertia"), ("links", 0, "length"), ("links", 0, "type"), ("velocities",), ("extra",)])


@GENERATED
@given(path=SCENE_PATHS, value=JSON_VALUES)
def test_generated_scene_files_are_rendered_or_refused_in_one_line(tmp_path_factory, capsys, path, value):
    folder = tmp_path_factory.mktemp("scene")
    (folder / "s.json").write_text(json.dumps(mutated(CHAIN4, path, value)))
    before = snapshot(folder)
    code, err = run_in_process(["mjcf", str(folder / "s.json"), "--out", str(folder / "o.xml")], capsys)
    answered_cleanly(code, err, folder, before, folder / "o.xml")
    if code == 0:
        import xml.etree.ElementTree as ElementTree

        ElementTree.parse(folder / "o.xml")


TRAJECTORY_ARRAYS = st.sampled_from(["t", "q", "qd", "energy"])
ARRAY_VALUES = st.sampled_from([np.zeros(0), np.zeros((4, 5, 2)), np.full((4, 5, 2), 1e300), np.full(4, np.nan), np.array(["a"] * 4),
                                np.zeros((4, 5, 3)), np.zeros((3, 5, 2)), np.ones(4, bool), np.zeros((4, 5, 2), complex), np.zeros(4)])


@GENERATED
@given(array=TRAJECTORY_ARRAYS, value=ARRAY_VALUES, metadata=JSON_VALUES)
def test_generated_trajectory_files_are_compared_or_refused_in_one_line(tmp_path_factory, capsys, array, value, metadata):
    folder = tmp_path_factory.mktemp("trajectory")
    trajectory()(folder / "a.npz")
    trajectory(**{array: value})(folder / "b.npz")
    trajectory(metadata=json.dumps(metadata))(folder / "c.npz")
    before = snapshot(folder)
    for other in ("b.npz", "c.npz"):
        code, err = run_in_process(["compare", str(folder / "a.npz"), str(folder / other)], capsys)
        answered_cleanly(code, err, folder, before)


CHECKPOINT_PATHS = st.sampled_from(["epoch", "best_epoch", "best_val", "history", "elapsed_s", "data", "data.scene", "model.name",
                                    "model.message_passing", "model.latent", "model.hidden", "model.dim", "model.n_nodes",
                                    "model.vocabulary", "model.drag", "train_config", "train_config.batch_size"])


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(key=CHECKPOINT_PATHS, value=JSON_VALUES)
@example(key="elapsed_s", value=10**400)  # an integer beyond every float (hypothesis found it: OverflowError)
def test_generated_checkpoint_edits_are_read_or_refused_in_one_line(tmp_path_factory, capsys, key, value):
    folder = tmp_path_factory.mktemp("checkpoint")
    checkpoint(set_key(key, value))(folder / "k.npz")
    before = snapshot(folder)
    code, err = run_in_process(["checkpoint", str(folder / "k.npz")], capsys)
    answered_cleanly(code, err, folder, before)


SETTINGS = st.sampled_from(["seeds", "scenes", "models", "evaluate.initial_conditions", "evaluate.duration", "evaluate.dt",
                            "evaluate.frame_dt", "evaluate.chunk", "evaluate.scene_dts", "training.data.sample_dt",
                            "training.data.n_trajectories", "training.train.learning_rate", "training.train.batch_size",
                            "speed.dts", "speed.horizon", "scaling.lengths", "mass.scenes", "grid"])
TOML_VALUES = st.sampled_from(["0", "-1", "1e999", "-1e999", "nan", "inf", "1e-300", "1e300", "3", "0.5", "true", '"x"', "[]", "[0]",
                               "[-1e-3]", '["bogus"]', "[[1, 2]]", '[["T2", 0.0]]', "{a = 1}", "chain4", "[chain4, T1]"])


@GENERATED
@given(key=SETTINGS, value=TOML_VALUES)
def test_generated_settings_are_accepted_or_refused_before_any_stage(tmp_path_factory, capsys, monkeypatch, key, value):
    folder = tmp_path_factory.mktemp("settings")
    started = []
    monkeypatch.setattr("lgnn.bench.run.run", lambda profile, *args, **kwargs: started.append(profile) or folder)
    monkeypatch.setattr("lgnn.bench.run.STAGES", ())
    before = snapshot(folder)
    code, err = run_in_process(["benchmark", "--out-dir", str(folder / "b"), "--stage", "all", "--set", f"{key}={value}"], capsys)
    answered_cleanly(code, err, folder, before)
    assert (code == 0) == bool(started)


@given(dt=st.floats(), frame_dt=st.floats(), duration=st.floats())
def test_a_simulation_config_is_bounded_or_refused(dt, frame_dt, duration):
    try:
        config = SimulationConfig(dt, frame_dt, duration)
    except ConfigError as err:
        assert "\n" not in str(err)
        return
    from lgnn.engines.base import MAX_FRAMES, MAX_STEPS

    assert 1 <= config.n_frames <= MAX_FRAMES and config.n_frames * config.steps_per_frame <= MAX_STEPS


# `lgnn ARGS` as started from a terminal, where Ctrl-C is delivered. A process started in
# the background by a non-interactive shell (`nohup pytest &`) inherits SIGINT ignored,
# and Python then installs no handler: its children could not be interrupted at all.
_AT_A_TERMINAL = """
import signal, sys
signal.signal(signal.SIGINT, signal.default_int_handler)
from lgnn.cli import entry
entry()
"""
INTERRUPTS = 20
# Processes interrupted at once: the moments stay random (each process's own clock),
# the test's wall time a fifth of one after another.
INTERRUPTED_AT_ONCE = 5


def test_simulate_interrupted_at_random_moments_exits_130_in_one_line(tmp_path):
    """Ctrl-C at 20 random moments over `lgnn simulate` (imports, compilation, the run,
    the interpreter's ending): exit 130 with the one line `lgnn: interrupted`, or exit 0
    when the signal comes after the process could take it; an output is whole or absent.
    Never a traceback, a crash or an end by the signal itself (the console script's
    `entry`: one that came while the interpreter ended did end so)."""
    import random

    from lgnn.engines.base import Trajectory

    generator = random.Random(34)
    moments = sorted(0.05 + 5.0 * generator.random() for _ in range(INTERRUPTS))
    seen = {}
    for batch in range(0, INTERRUPTS, INTERRUPTED_AT_ONCE):
        started = time.monotonic()
        children = {}
        for trial in range(batch, min(batch + INTERRUPTED_AT_ONCE, INTERRUPTS)):
            out = tmp_path / f"o{trial}.npz"
            children[trial] = (out, subprocess.Popen([sys.executable, "-c", _AT_A_TERMINAL, "simulate", "chain4", "--duration", "0.2", "--out", str(out),
                                                      "--quiet"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                                      env=dict(os.environ, LGNN_JAX_CACHE="off")))  # (each compiles, as a first run)
        for trial, (out, child) in children.items():
            time.sleep(max(0.0, started + moments[trial] - time.monotonic()))
            child.send_signal(signal.SIGINT)
        for trial, (out, child) in children.items():
            err = child.communicate(timeout=TIMEOUT_S)[1]
            seen[child.returncode] = seen.get(child.returncode, 0) + 1
            assert "Traceback" not in err and child.returncode in (0, 130), (trial, moments[trial], child.returncode, err)
            if child.returncode == 130:
                assert err.strip() == "lgnn: interrupted", err
            if child.returncode == 0 or out.exists():  # interrupted after the (atomic) save: a whole file
                assert Trajectory.load(out).q.shape[1:] == (5, 2)
    assert seen.get(130, 0) >= INTERRUPTS // 2, seen  # most moments fall inside the command, not before or after it
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")], "a temporary file was left"


_INTERRUPTED_WHILE_ENDING = """
import atexit, os, signal, sys, time
signal.signal(signal.SIGINT, signal.default_int_handler)  # (as at a terminal: _AT_A_TERMINAL)
# Registered first, so run last, after lgnn's and JAX's: a Ctrl-C while the interpreter ends.
atexit.register(lambda: (os.kill(os.getpid(), signal.SIGINT), time.sleep(2)))
from lgnn.cli import entry
entry()
"""


def test_a_ctrl_c_while_the_interpreter_ends_exits_130_in_one_line():
    """The command has returned and the interpreter is running its exit handlers when
    Ctrl-C comes: the one line and 130, as at any other moment (Python's own handler
    raised KeyboardInterrupt inside the handler instead)."""
    child = subprocess.run([sys.executable, "-c", _INTERRUPTED_WHILE_ENDING, "scenes"], capture_output=True, text=True, timeout=TIMEOUT_S)
    assert child.returncode == 130 and child.stderr.strip() == "lgnn: interrupted", (child.returncode, child.stderr)
    assert "chain4" in child.stdout  # the command's output, flushed before leaving


def test_a_ctrl_c_just_after_the_temporary_file_is_made_leaves_nothing(tmp_path, monkeypatch):
    """`files.atomic_path`: an interrupt between the temporary file's creation and the
    body (here at its permissions) removes it, and the target is never written; the
    random moments above found such a file left once."""
    from lgnn import files

    def interrupted(*_):
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "chmod", interrupted)
    with pytest.raises(KeyboardInterrupt):
        files.write_text_atomic(tmp_path / "out.txt", "whole")
    assert list(tmp_path.iterdir()) == []


_INTERRUPTED_COMPILATION = """
import os, signal, sys, threading
signal.signal(signal.SIGINT, signal.default_int_handler)  # (as at a terminal: _AT_A_TERMINAL)
from jax._src import compiler
from lgnn.cli import main

compile_and_load, returned = compiler.backend_compile_and_load, []

def interrupted_compilation(*args, **kwargs):
    threading.Timer(0.05, os.kill, (os.getpid(), signal.SIGINT)).start()
    executable = compile_and_load(*args, **kwargs)
    returned.append(True)
    return executable

compiler.backend_compile_and_load = interrupted_compilation
code = main(sys.argv[1:])
print("compilations that returned:", len(returned))
sys.exit(code)
"""


def test_a_ctrl_c_during_an_xla_compilation_is_taken_once_the_compilation_returns(tmp_path):
    """JAX waits for an XLA compilation interruptibly while the compilation goes on in
    XLA's threads: leaving then crashed the process under the compiler thread (a
    segmentation fault after "lgnn: interrupted", in about 1 of 10 interrupts). The
    Ctrl-C is held until the compilation has returned, then the command stops: exit 130,
    one line, and Python's normal shutdown."""
    out = tmp_path / "o.npz"
    child = subprocess.run([sys.executable, "-c", _INTERRUPTED_COMPILATION, "simulate", "chain4", "--duration", "0.05", "--out", str(out), "--quiet"],
                           env=dict(os.environ, LGNN_JAX_CACHE="off"), capture_output=True, text=True, timeout=TIMEOUT_S)
    assert child.returncode == 130, child.stderr
    assert child.stderr == "lgnn: interrupted\n"
    assert child.stdout == "compilations that returned: 1\n"  # the first one, then no other
    assert not out.exists()


def test_a_ctrl_c_while_numpy_and_jax_load_is_held_until_they_have(monkeypatch, capsys):
    """Ctrl-C during `configure()` (where numpy and jaxlib run their C initialisation,
    which prints the traceback of an exception raised inside it) does not interrupt it:
    the load completes, then the command stops with exit 130 and one line."""
    import lgnn.runtime

    if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        pytest.skip("the test runner owns SIGINT here")
    loaded = []
    configure = lgnn.runtime.configure

    def interrupted_configure(**kwargs):
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)  # the signal is handled by now
        configure(**kwargs)
        loaded.append(True)

    monkeypatch.setattr(lgnn.runtime, "configure", interrupted_configure)
    assert main(["scenes"]) == 130
    assert loaded == [True]
    assert capsys.readouterr().err == "lgnn: interrupted\n"
