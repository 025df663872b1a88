"""What training the full profile's grid would take on one GPU at measured rates.

For each training group of the full profile (its seeds train packed in one program,
which runs until its last seed stops): the epochs its committed checkpoints ran
(`results/benchmark/checkpoints/`, the most of its seeds), its packed rate (3 seeds,
the whole training loop) from the given `tools/training_throughput.py --loop` outputs,
matched by model and training scene (a varied or drag chain4 takes chain4's rate, the
same network on the same graph), and so its minutes with the GPU to itself. A group
with a minutes budget (the zoo, the transfer track) is shown with its budget, not
projected. Then the paper track's sum (its groups one after another) and its longest
group (the least wall time any schedule of it can take on one GPU).

    python results/gpu/training/grid_projection.py results/gpu/training/loop-h200-2d.jsonl results/gpu/training/loop-h200-3d.jsonl
    python results/gpu/training/grid_projection.py results/gpu/training/adjoint/loop-h200-*-ab.jsonl

With `--shared JSONL` (the jobs' rates while the paper track's groups trained side by
side, `adjoint/shared_rates_from_checkpoints.py`), it prints instead each group's rate
while sharing against its packed rate alone, the fraction of it kept, and the
fractions' sum: how many groups' worth of work the GPU did at once.

    python results/gpu/training/grid_projection.py --shared results/gpu/training/adjoint/share-14-h200.jsonl \
        results/gpu/training/adjoint/loop-h200-*-ab.jsonl
"""

import argparse
import json

from lgnn.runtime import configure

configure()

from lgnn.bench.profiles import load_profile, train_config, training_jobs  # noqa: E402
from lgnn.learn.train import load_checkpoint  # noqa: E402

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("rates", nargs="+", help="tools/training_throughput.py --loop outputs")
parser.add_argument("--shared", help="the jobs' rates while the groups shared the GPU")
args = parser.parse_args()

# Rows of a variant other than the new one (an A/B measurement's "old") are not this
# code's rates; of repeated rounds the slowest is taken. A later file's rate for a
# model and scene replaces an earlier file's (a newer measurement of some models).
rates = {}
for path in args.rates:
    measured = {}
    for line in open(path):
        row = json.loads(line)
        if row.get("seeds") == 3 and row.get("variant", "new") == "new":
            key = (row["model"], row["scene"])
            measured[key] = min(measured.get(key, float("inf")), row["epochs_per_s"])
    rates.update(measured)

profile = load_profile("full")
groups = {}
for job in training_jobs(profile):
    groups.setdefault(job.group, []).append(job)


def rate_scene(job) -> str:
    """The scene whose measured rate stands for `job`'s (a varied or drag chain4 takes
    chain4's: the same network on the same graph)."""
    return "chain4" if job.scene in ("chain4-varied", "chain4-drag") else job.scene


def rate_alone(job) -> float | None:
    """The packed rate of `job`'s model on its training scene (`rate_scene`)."""
    return rates.get((job.model, rate_scene(job)))


if args.shared:
    shared = {}
    for line in open(args.shared):
        row = json.loads(line)
        shared.setdefault(row["job"].rsplit("-s", 1)[0], []).append(row["shared_epochs_per_s"])
    print("| group | epochs/s, all sharing | epochs/s alone (packed) | fraction kept |")
    print("|---|---|---|---|")
    kept = 0.0
    for group, jobs in groups.items():
        if group not in shared:
            continue
        rate, alone = min(shared[group]), rate_alone(jobs[0])
        kept += rate / alone
        print(f"| {group} | {rate:g} | {alone:g} | {rate / alone:.2f} |")
    print(f"\nSum of the fractions: {kept:.2f} groups' worth of work at once.")
    raise SystemExit

print("| group | epochs (most of its seeds) | packed epochs/s | rate of | minutes alone |")
print("|---|---|---|---|---|")
projected = {}
for group, jobs in groups.items():
    epochs = max(int(load_checkpoint(f"results/benchmark/checkpoints/{job.name}.npz")[0].epoch) for job in jobs)
    job, budget = jobs[0], train_config(profile, jobs[0]).minutes
    if budget is not None:
        print(f"| {group} | {epochs} | | | budget {budget:g} |")
        continue
    rate = rate_alone(job)
    if rate is None:
        print(f"| {group} | {epochs} | not measured | | |")
        continue
    projected[group] = epochs / rate / 60
    print(f"| {group} | {epochs} | {rate:g} | {job.model} on {rate_scene(job)} | {projected[group]:.1f} |")
longest = max(projected, key=projected.get)
print(f"\nProjected groups: {len(projected)}; one after another {sum(projected.values()):.0f} minutes; "
      f"the longest, {longest}, {projected[longest]:.1f} minutes.")
