"""`LEADERBOARD.md`: per track and dimension, one row per model with its rollout-error
cell on each scene, its rank there, parameters, training time and overall rank (the
rule is stated in the file)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from lgnn import metrics
from lgnn.bench.grid import PAPER_TRACK, TRAINING_SCENES, TRANSFER_TRACK, Pair
from lgnn.bench.profiles import Profile, evaluation_pairs
from lgnn.bench.stages.evaluate import load_pairs, load_truths
from lgnn.bench.stages.external import load_externals
from lgnn.bench.stages.train import load_checkpoints
from lgnn.bench.report.summary import ALL_SEEDS, DIMENSION_NAMES, EXACT_NO_DRAG, EXTERNAL_MARK, REST, interval_cell, scene_groups, tables, unrankable_scenes
from lgnn.files import write_text_atomic
from lgnn.learn.models import get_spec
from lgnn.scene import get_scene

# The leaderboard's file under the output folder, beside README.md.
LEADERBOARD = "LEADERBOARD.md"
# The metric the leaderboard ranks by.
RANKED_METRIC = "rollout_error"


def write_leaderboard(profile: Profile, out: Path, command: str | None = None, env: dict | None = None) -> Path:
    """Write `LEADERBOARD.md` under `out` alone, from the records there and in the
    profile's base (the statistics `tables` gives README.md's tables); its path. `env`:
    the environment its header names (default this process's, taken before writing)."""
    from lgnn.provenance import environment

    env = env or environment()
    out = Path(out)
    summary, _ = tables(load_truths(profile, out), load_pairs(profile, out) + load_externals(profile, out), profile.evaluate.references)
    path = out / LEADERBOARD
    write_text_atomic(path, leaderboard_markdown(profile, out, summary, load_checkpoints(profile, out), env, command))
    return path


def _cell_row(wide, scene: str, model: str) -> dict | None:
    """The summary row a table cell shows (`summary_markdown`): over every seed where
    several, else the one seed's, with its seed count (a trained model's)."""
    match = wide[(wide.scene == scene) & (wide.model == model) & (wide.metric == RANKED_METRIC)]
    if (match.seed == ALL_SEEDS).any():
        match = match[match.seed == ALL_SEEDS]
    if not len(match):
        return None
    row = match.iloc[0].to_dict()
    trained = model not in (REST, EXACT_NO_DRAG) and not model.endswith(EXTERNAL_MARK)
    return {**row, **({"seeds": 1} if trained and row["seed"] != ALL_SEEDS else {})}


def _ranks(values: dict[str, float]) -> dict[str, int]:
    """Competition ranks ("1, 2, 2, 4") of `{model: value}`, lower first; equal values share the better rank."""
    ordered = sorted(values.values())
    return {model: 1 + ordered.index(value) for model, value in values.items()}


def _trained(checkpoints: list) -> dict[str, tuple[str, str]]:
    """`{job label: (parameters, training)}` of the trained models' checkpoints
    (`stages.train.load_checkpoints`, each read once):
    learned parameters of the best epoch (training-set statistics apart) and the median
    over seeds of the recorded training minutes, with the device (GPU-minutes only on a
    GPU); "not recorded" where a checkpoint holds no time."""
    from lgnn.learn import checkpoints as checkpoint_files

    found: dict[str, list] = {}
    for trained in checkpoints:
        found.setdefault(trained.job.label, []).append((trained.job, trained.state, trained.meta))
    result = {}
    for model, runs in found.items():
        _, state, meta = runs[0]
        count = (checkpoint_files.learned_parameter_count(state.best_params) if checkpoint_files.has_parameters(meta)
                 else meta[checkpoint_files.WITHOUT_PARAMETERS]["parameters"])
        times = [state.elapsed_s for _, state, _ in runs if state.elapsed_s > 0]
        devices = sorted({meta.get("environment", {}).get("device", "unknown device").split(";")[0] for _, _, meta in runs})
        unit = "GPU-minutes" if all("(gpu)" in device for device in devices) else "minutes"
        training = (f"{np.median(times) / 60:.3g} {unit} ({len(times)} seed{'s' if len(times) != 1 else ''}, median; {', '.join(devices)})"
                    if times else "not recorded")
        result[model] = (f"{count:,}", training)
    return result


def leaderboards(pairs: list[Pair]) -> list[tuple[str, int, list[Pair]]]:
    """`(heading, dimension, pairs)` of each leaderboard: per dimension, the paper's
    track (models trained on its main training scene, `TRAINING_SCENES`), then the
    transfer track's (models trained on varied draws, `grid.TRANSFER_TRACK`) per
    dimension of the scenes they are evaluated on."""
    boards = [(f"{DIMENSION_NAMES.get(dim, f'{dim}D')}: trained on {main}", dim, [p for p in pairs if p.job.scene == main and not p.job.varied_draws])
              for dim, main in TRAINING_SCENES.items()]
    transfer: dict[int, list[Pair]] = {}
    for pair in pairs:
        if pair.job.track == TRANSFER_TRACK:
            transfer.setdefault(get_scene(pair.scene).dim, []).append(pair)
    for dim, board in transfer.items():
        sources = ", ".join(dict.fromkeys(p.job.trained_on for p in board))
        boards.append((f"{DIMENSION_NAMES.get(dim, f'{dim}D')}, transfer track: trained on {sources}", dim, board))
    return boards


# What a leaderboard cell without a record says (`_missing_cell`).
NOT_EVALUATED = "not evaluated"
FIXED_SIZE_CELL = "— (fixed size)"


def _verification_text(kept: dict | None) -> str:
    """The paragraph that says what the `verified` column means, and which command set it."""
    from lgnn.bench.verify import TOLERANCE

    if kept is None:
        return ("**Verified**: not checked yet. `lgnn leaderboard verify` re-derives every row from this folder's checkpoints and "
                "records and marks it here (docs/benchmark.md, \"Verifying a leaderboard\").")
    env = kept.get("environment") or {}
    scenes = "every scene it is evaluated on" if kept.get("scenes") == "all" else "its smallest evaluation scene"
    return (f"**Verified** by `{kept.get('command') or 'lgnn leaderboard verify'}` at commit {env.get('commit', '?')} on "
            f"{env.get('device', '?')} (`benchmark/verification.json`; docs/benchmark.md, \"Verifying a leaderboard\"): \"yes (SCENES)\": "
            "every record of the row carries the key of its checkpoint and the profile's settings, and its seeds, rolled out again "
            f"from the first {kept.get('conditions', '?')} evaluation initial condition(s) of {scenes} against a ground truth computed "
            f"again, give every metric of the records within {kept.get('tolerance', TOLERANCE):g} (in log); \"no: parameters not "
            "kept\": the checkpoints hold no parameters, so nothing here can roll them out again; \"no: records changed since\": "
            "the row's records are not those verified; \"failed\": the command names the disagreement.")


def _missing_cell(label: str, scene: str, board: list[Pair]) -> str:
    """A leaderboard cell with no record: a pair of the board's grid not evaluated yet, a
    fixed-size model on a scene it cannot run (the grid evaluates it on its training
    system alone), or a pair outside the grid."""
    if any((pair.label, pair.scene) == (label, scene) for pair in board):
        return NOT_EVALUATED
    fixed = any(pair.label == label and get_spec(pair.job.model).fixed_size for pair in board if not pair.job.external)
    return FIXED_SIZE_CELL if fixed else "—"


def leaderboard_markdown(profile: Profile, out: Path, summary, checkpoints: list, env: dict, command: str | None = None) -> str:
    """`LEADERBOARD.md`: per leaderboard (`leaderboards`: each dimension's paper track
    and transfer track), one row per model it ranks and per external prediction, the rollout error
    cell of README.md's table on each scene of the grid with its rank there, parameters,
    training minutes, and the overall rank (module's rule, stated in the file)."""
    from lgnn.bench import verify

    unrankable = unrankable_scenes(out)
    kept, row_marks = verify.marks(profile, out)
    wide = (summary.pivot_table(index=["scene", "model", "seed", "metric"], columns="statistic", values="value", aggfunc="first").reset_index()
            if not summary.empty else None)
    trained = _trained(checkpoints)
    shown = "lgnn leaderboard" + (" --full" if profile.name == "full" else f" (profile {profile.name})")
    lines = [f"# Leaderboard ({profile.name} profile)", "",
             f"Written by `{command or shown}` from the benchmark's records (`benchmark/runs/` of this folder"
             + (f" and of `{profile.base}`" if profile.base else "") + "); nothing here is edited by hand. "
             f"Written at commit {env['commit']}. Every cell is the one of `README.md`'s table \"{metrics.METRICS[RANKED_METRIC].heading}\" "
             "(the same records and statistics, `benchmark/summary.csv.gz`): geometric mean over frames and initial conditions "
             "[bootstrap 95% interval], over every training seed where several; lower is better.", "",
             "**Ranks.** On each scene the models with a number are ranked by that geometric mean, lowest first; equal values share "
             "the better rank. A scene that cannot rank models (the reference does not converge in dt) ranks none. The overall rank "
             "orders the models with a number on every ranked scene of the table by the mean of their scene ranks; ties are broken by "
             "the geometric mean of their cells over those scenes, then by name. A model without a number on every scene has no "
             "overall rank and follows, by name. `rest` (the initial state held) is the bar any model must clear, never ranked. "
             f"\"{NOT_EVALUATED}\": a pair of the grid with no record yet; \"{FIXED_SIZE_CELL}\": a model tied to its training "
             "system's size (CLNN, CHNN), which the grid evaluates on that system alone; \"—\": a pair outside the grid "
             "(an external prediction answers only the scenes it was made for).", "",
             "**Parameters and training** come from the checkpoints: the learned parameters of the best epoch (training-set "
             "statistics apart) and the training minutes recorded in them (median over seeds; seeds trained together in one "
             "program share one wall time), with the device; GPU-minutes only where every seed trained on a GPU. Rows marked "
             f"`{EXTERNAL_MARK.strip()}` are predictions made outside lgnn from the same initial conditions (no checkpoint, "
             "parameters or training time here).", "",
             _verification_text(kept), "",
             "**Add a row.** A model of your own (`docs/models.md`), trained with the full profile's recipe and ranked beside these "
             "results, read in place:", "", "```bash", "lgnn benchmark --full --add-model my_model.py:SPEC --with-results results", "```", "",
             "or predictions made in another framework from the exported initial conditions (`docs/benchmark.md`, \"Predictions made "
             "elsewhere\"):", "", "```bash", "lgnn benchmark --full --add-predictions chain8-mine.npz --with-results results", "```", "",
             "Then open a pull request adding what the command wrote under its output folder: the checkpoint "
             "(`benchmark/checkpoints/JOB.npz`) and records (`benchmark/runs/JOB/`) of a model, with its file and an `[[add]]` "
             "entry of the full profile, or the records `benchmark/runs/external/MODEL/` of predictions. This file is then "
             f"regenerated from the records: `{shown}`, and every row re-derived before it is marked verified: `lgnn leaderboard "
             "verify results` (with `--predictions FILE.npz` for predictions, which are scored again).", ""]
    if wide is None:
        return "\n".join([*lines, "(no results)", ""])
    for heading, dim, board in leaderboards(evaluation_pairs(profile)):
        scenes = [s for s in scene_groups([p.scene for p in board], board[0].job.track if board else PAPER_TRACK).get(dim, [])]
        if not scenes:
            continue
        names = {p.label: p.job.model + ("" if p.projected else " (unprojected)") for p in board if p.scene in scenes}
        labels = list(names)
        labels += sorted({m for m in wide.model.unique() if m.endswith(EXTERNAL_MARK) and m not in labels
                          and (wide[wide.model == m].scene.isin(scenes)).any()})
        cells = {label: {scene: _cell_row(wide, scene, label) for scene in scenes} for label in labels}
        ranked = [scene for scene in scenes if scene not in unrankable]
        ranks = {scene: _ranks({label: cells[label][scene]["gmean"] for label in labels if cells[label][scene] is not None
                                and math.isfinite(cells[label][scene].get("gmean", math.nan))}) for scene in ranked}
        complete = [label for label in labels if all(label in ranks[scene] for scene in ranked)]
        mean_rank = {label: float(np.mean([ranks[scene][label] for scene in ranked])) for label in complete}
        log_mean = {label: float(np.mean([math.log(cells[label][scene]["gmean"]) for scene in ranked])) for label in complete}
        order = sorted(complete, key=lambda label: (mean_rank[label], log_mean[label], label))
        order += sorted(label for label in labels if label not in complete)
        lines += [f"## {heading}", "",
                  "| rank | model | parameters | training | verified | " + " | ".join(
                      f"{scene}{' (not rankable)' if scene in unrankable else ''}" for scene in scenes) + " | mean scene rank |",
                  "|---" * (len(scenes) + 6) + "|"]
        for k, label in enumerate(order):
            model = names.get(label, label)
            parameters, training = (("—", "— (external)") if label.endswith(EXTERNAL_MARK) else
                                    trained.get(label.removesuffix(" (unprojected)"), ("not recorded", "not recorded")))
            row = [str(k + 1) if label in mean_rank else "—", model, parameters, training, row_marks.get(label, "not checked")]
            for scene in scenes:
                cell = cells[label][scene]
                row.append(_missing_cell(label, scene, board) if cell is None else "not rankable" if scene in unrankable
                           else f"{interval_cell(cell)} (rank {ranks[scene][label]})" if label in ranks[scene] else interval_cell(cell))
            row.append(f"{mean_rank[label]:.2f}" if label in mean_rank else f"— ({sum(label in ranks[s] for s in ranked)} of {len(ranked)} scenes)")
            lines.append("| " + " | ".join(row) + " |")
        rest = [_cell_row(wide, scene, REST) for scene in scenes]
        lines.append("| — | rest (baseline) | — | — | — | " + " | ".join("" if r is None else interval_cell(r) for r in rest) + " | — |")
        lines.append("")
    return "\n".join(lines)
