"""The evaluate stage's parts from its logs: per (model, scene) part the rollouts' run
and compile seconds (as each part's log prints them for its stacked seeds), sorted by
compile seconds, and the totals; parts whose log has no such line are listed as not
finished.

    python results/gpu/evaluate-stage/summarise.py results/gpu/evaluate-stage/h200-254ca7a/logs

With the parent's output as a second argument, also how many parts had ended by 3, 5,
7 and 9 minutes, and each part's window in the stage (a part starts when the one
before it in the parent's output ends, the first `workers` at 0), its rollouts'
seconds per 100 frames (the stage's 1 s at 1 ms frames: 10 calls of the rollout
program) and how many parts on chain100 or chain100-3d (3 seeds x 100 initial
conditions: the GPU's largest batches) ran beside it:

    python results/gpu/evaluate-stage/summarise.py results/gpu/evaluate-stage/h200-99f0e9f/logs \
        results/gpu/evaluate-stage/h200-99f0e9f/parent.log
"""

import re
import sys
from pathlib import Path

LINE = re.compile(r"evaluate (?P<label>.+?) s\d+ on (?P<scene>\S+): rollout error .*?\((?P<run>[\d.]+) s \+ compile (?P<compile>[\d.]+) s")
STARTED = re.compile(r"evaluate (?P<part>\S+): started")
ENDED = re.compile(r"evaluate (?P<part>\S+): done after (?P<minutes>[\d.]+) min")
CALLS = 10  # calls of 100 frames in the stage's 1 s of 1 ms frames
LARGEST = ("chain100-", "chain100-3d-")

rows, unfinished, part_runs = {}, [], {}
for log in sorted(Path(sys.argv[1]).glob("evaluate-*.log")):
    found = [m for m in map(LINE.search, log.read_text().splitlines()) if m]
    part = log.stem.removeprefix("evaluate-")
    if not found:
        unfinished.append(part)
    for m in found:  # one line per seed; the seeds of a label share one program
        rows[(m["label"], m["scene"])] = (float(m["run"]), float(m["compile"]))
    if found:  # the first program's (a GNS part's projected rollouts)
        part_runs[part] = float(found[0]["run"])

print("| model | scene | run s | compile s |\n|---|---|---|---|")
for (label, scene), (run, compile_s) in sorted(rows.items(), key=lambda item: -item[1][1]):
    print(f"| {label} | {scene} | {run:g} | {compile_s:g} |")
print(f"\n{len(rows)} programs: run {sum(r for r, _ in rows.values()):.0f} s, compile {sum(c for _, c in rows.values()):.0f} s in all")
print(f"not finished ({len(unfinished)}): {', '.join(unfinished)}")

if len(sys.argv) > 2:
    now, start, end = 0.0, {}, {}
    for line in Path(sys.argv[2]).read_text().splitlines():
        if m := STARTED.search(line):
            start[m["part"]] = now
        elif m := ENDED.search(line):
            now = end[m["part"]] = float(m["minutes"])
    ended = sorted(end.values())
    print("\n| parts ended by | " + " | ".join(f"{k} min" for k in (3, 5, 7, 9)) + " |\n|---|---|---|---|---|")
    print("| count | " + " | ".join(str(sum(t <= k for t in ended)) for k in (3, 5, 7, 9)) + f" of {len(start)} |")
    print(f"\nlast part ended after {max(ended, default=float('nan'))} min\n")
    largest = [p for p in start if p.startswith(LARGEST)]
    print("| part | window, min | rollouts s | s per 100 frames | largest parts beside it |\n|---|---|---|---|---|")
    for part in sorted(start, key=lambda p: (start[p], p)):
        if part in end and part in part_runs:
            beside = sum(start[p] < end[part] and end.get(p, float("inf")) > start[part] for p in largest if p != part)
            print(f"| {part} | {start[part]:.1f}-{end[part]:.1f} | {part_runs[part]:g} | {part_runs[part] / CALLS:.1f} | {beside} |")
