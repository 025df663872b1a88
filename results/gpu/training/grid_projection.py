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
"""

import json
import sys

from lgnn.runtime import configure

configure()

from lgnn.bench.grid import load_profile, train_config, training_jobs  # noqa: E402
from lgnn.learn.train import load_checkpoint  # noqa: E402

# Rows of a variant other than the new one (an A/B measurement's "old") are not this
# code's rates; of repeated rounds the slowest is taken.
rates = {}
for path in sys.argv[1:]:
    for line in open(path):
        row = json.loads(line)
        if row.get("seeds") == 3 and row.get("variant", "new") == "new":
            key = (row["model"], row["scene"])
            rates[key] = min(rates.get(key, float("inf")), row["epochs_per_s"])

profile = load_profile("full")
groups = {}
for job in training_jobs(profile):
    groups.setdefault(job.group, []).append(job)

print("| group | epochs (most of its seeds) | packed epochs/s | rate of | minutes alone |")
print("|---|---|---|---|---|")
projected = {}
for group, jobs in groups.items():
    epochs = max(int(load_checkpoint(f"results/benchmark/checkpoints/{job.name}.npz")[0].epoch) for job in jobs)
    job, budget = jobs[0], train_config(profile, jobs[0]).minutes
    if budget is not None:
        print(f"| {group} | {epochs} | | | budget {budget:g} |")
        continue
    scene = "chain4" if job.scene in ("chain4-varied", "chain4-drag") else job.scene
    rate = rates.get((job.model, scene))
    if rate is None:
        print(f"| {group} | {epochs} | not measured | | |")
        continue
    projected[group] = epochs / rate / 60
    print(f"| {group} | {epochs} | {rate:g} | {job.model} on {scene} | {projected[group]:.1f} |")
longest = max(projected, key=projected.get)
print(f"\nProjected groups: {len(projected)}; one after another {sum(projected.values()):.0f} minutes; "
      f"the longest, {longest}, {projected[longest]:.1f} minutes.")
