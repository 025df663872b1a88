"""The paper track's 14 training groups trained side by side on one GPU (the benchmark's
train stage, `--workers 14`, under its MPS daemon), cut off after a few minutes: each
group's epochs per second while all 14 shared the GPU (from its checkpoints' history,
epoch 10 to its last checkpoint, `shared_rates_from_checkpoints.py`), against its
packed rate alone (the slower `new` round of the A/B files), and what fraction of its
alone rate it kept. The fractions' sum is how many groups' worth of work the GPU did at
once.

    python results/gpu/training/adjoint/shared_rates.py results/gpu/training/adjoint/share-14-h200.jsonl \
        results/gpu/training/adjoint/loop-h200-*-ab.jsonl
"""

import json
import sys

shared = {}
for line in open(sys.argv[1]):
    row = json.loads(line)
    group = row["job"].rsplit("-s", 1)[0]
    shared[group] = min(shared.get(group, float("inf")), row["shared_epochs_per_s"])
alone = {}
for path in sys.argv[2:]:
    for line in open(path):
        row = json.loads(line)
        if row.get("seeds") == 3 and row.get("variant", "new") == "new":
            key = (row["model"], row["scene"])
            alone[key] = min(alone.get(key, float("inf")), row["epochs_per_s"])

print("| group | epochs/s, 14 groups sharing | epochs/s alone (packed) | fraction kept |")
print("|---|---|---|---|")
total = 0.0
for group, rate in sorted(shared.items()):
    model, scene = (group.rsplit("-chain4", 1)[0], "chain4" + group.rsplit("-chain4", 1)[1])
    scene = "chain4-3d" if scene == "chain4-3d" else "chain4"  # a varied or drag chain4 takes chain4's rate
    fraction = rate / alone[(model, scene)]
    total += fraction
    print(f"| {group} | {rate:g} | {alone[(model, scene)]:g} | {fraction:.2f} |")
print(f"\nSum of the fractions: {total:.2f} groups' worth of work at once.")
