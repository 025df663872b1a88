"""The training budget by a stated rule, read from a results folder's checkpoints: the
smallest epoch budget B at which doubling it to 2B changes no model's rank on one
training scene's track, models ranked by their best validation MSE within the budget
(median over seeds).

    python tools/budget_rule.py --results results --scene chain4
    python tools/budget_rule.py --results results --scene chain4-3d --budgets 100 200 400 800 1600

Each checkpoint keeps its run's validation MSE at every epoch, so a run's best within
any budget it reached is known without training again. A run that ended by the
protocol's own rules (the epoch budget or the plateau rule) keeps its best at every
larger budget; a run cut off before (a wall-clock cap, an interrupted job) says nothing
past its last epoch, and a budget it did not reach is "unknown" for its model. The rule
is decided only where every model is known at both B and 2B.

What this does not show: the leaderboard ranks by rollout error, which needs the
parameters at each budget, and checkpoints keep only the best of the whole run. The
validation MSE is the training side's reading of the same question (which model fits
the dynamics better within B epochs); a rank that moves there may or may not move in
rollout error.
"""
import argparse
import dataclasses
from pathlib import Path

import numpy as np

from lgnn.bench import grid, profiles, store
from lgnn.learn import checkpoints, protocol

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--results", default="results", help="a results folder (its benchmark/checkpoints/)")
parser.add_argument("--scene", default=grid.TRAINING_SCENE, help="the training scene whose models are ranked (the paper track's)")
parser.add_argument("--budgets", nargs="+", type=int, default=[25, 50, 100, 200, 400, 800, 1600, 3200, 6400])
args = parser.parse_args()

profile = profiles.get_profile("full")
layout = store.Layout(Path(args.results))
jobs = [job for job in profiles.training_jobs(profile) if job.scene == args.scene and not job.varied_draws]
if not jobs:
    raise SystemExit(f"no training job of the full profile trains on {args.scene!r} alone")


def best_within(job) -> tuple[callable, str]:
    """`best(B)`: the run's best validation MSE within B epochs (None where the run says
    nothing: cut off before B), and how the run ended."""
    meta, arrays = checkpoints.read(layout.checkpoint(job))
    history = checkpoints.history(meta, arrays)
    epochs = np.array([entry[0] for entry in history])
    val = np.array([entry[2] for entry in history])
    running = np.fmin.accumulate(np.where(np.isnan(val), np.inf, val))
    config = dataclasses.replace(profiles.train_config(profile, job), minutes=None)  # the protocol's own rules only
    state = protocol.TrainState(None, None, None, float(running[-1]), int(meta["best_epoch"]), int(epochs[-1]), history, 0.0)
    ended = protocol.stop_reason(state, config)

    def best(budget: int):
        if budget > epochs[-1] and ended is None:
            return None
        return float(running[min(budget, epochs[-1]) - 1])

    return best, ended or f"cut off at epoch {epochs[-1]}"


models: dict[str, list] = {}
endings: dict[str, list[str]] = {}
for job in jobs:
    if not layout.checkpoint(job).exists():
        continue
    best, ended = best_within(job)
    models.setdefault(job.model, []).append(best)
    endings.setdefault(job.model, []).append(ended)


def scores(budget: int) -> dict[str, float | None]:
    out = {}
    for model, runs in models.items():
        values = [run(budget) for run in runs]
        out[model] = None if any(v is None for v in values) else float(np.median(values))
    return out


def ranking(budget: int) -> list[str] | None:
    score = scores(budget)
    if any(v is None for v in score.values()):
        return None
    return sorted(score, key=lambda model: score[model])


print(f"Models trained on {args.scene} alone, ranked by best validation MSE within B epochs (median over seeds), "
      f"from {args.results}/benchmark/checkpoints:\n")
print("| model | seeds | how each seed's run ended |")
print("|---|---|---|")
for model, ended in endings.items():
    print(f"| {model} | {len(ended)} | {'; '.join(ended)} |")
print("\n| B | ranking at B (best first) | unknown at B | ranking at 2B the same | the same among the models known at 2B |")
print("|---|---|---|---|---|")
verdicts = []
for budget in args.budgets:
    score = scores(budget)
    unknown = [m for m, v in score.items() if v is None]
    now, doubled = ranking(budget), ranking(2 * budget)
    same = "undetermined" if now is None or doubled is None else ("yes" if now == doubled else "no")
    shown = " < ".join(sorted((m for m in score if score[m] is not None), key=lambda m: score[m]))
    later = scores(2 * budget)
    known = [m for m in score if score[m] is not None and later[m] is not None]
    among = "yes" if sorted(known, key=lambda m: score[m]) == sorted(known, key=lambda m: later[m]) else "no"
    print(f"| {budget} | {shown} | {', '.join(unknown)} | {same} | {among} ({len(known)} models) |")
    verdicts.append((budget, same))
# The smallest B from which on every doubling keeps the ranking (every later B read too).
stable = [b for k, (b, _) in enumerate(verdicts) if all(same == "yes" for _, same in verdicts[k:])]
print()
if stable:
    print(f"The rule's budget: {stable[0]} epochs (every doubling read from there on keeps the ranking).")
else:
    last = max((b for b, same in verdicts if same != "undetermined"), default=None)
    print("The rule's budget: undetermined from these checkpoints: "
          + ("no budget is decided (a model is unknown at every B read)." if last is None else
             f"decided up to B = {last}; past it a model is unknown, or a doubling changes a rank."))
