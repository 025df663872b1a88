"""The evaluate stage's parts from its logs: per (model, scene) part the rollouts' run
and compile seconds (as each part's log prints them for its stacked seeds), sorted by
compile seconds, and the totals; parts whose log has no such line are listed as not
finished.

    python results/gpu/evaluate-stage/summarise.py results/gpu/evaluate-stage/h200-254ca7a/logs
"""

import re
import sys
from pathlib import Path

LINE = re.compile(r"evaluate (?P<label>.+?) s\d+ on (?P<scene>\S+): rollout error .*?\((?P<run>[\d.]+) s \+ compile (?P<compile>[\d.]+) s")

rows, unfinished = {}, []
for log in sorted(Path(sys.argv[1]).glob("evaluate-*.log")):
    found = [m for m in map(LINE.search, log.read_text().splitlines()) if m]
    if not found:
        unfinished.append(log.stem.removeprefix("evaluate-"))
    for m in found:  # one line per seed; the seeds of a label share one program
        rows[(m["label"], m["scene"])] = (float(m["run"]), float(m["compile"]))

print("| model | scene | run s | compile s |\n|---|---|---|---|")
for (label, scene), (run, compile_s) in sorted(rows.items(), key=lambda item: -item[1][1]):
    print(f"| {label} | {scene} | {run:g} | {compile_s:g} |")
print(f"\n{len(rows)} programs: run {sum(r for r, _ in rows.values()):.0f} s, compile {sum(c for _, c in rows.values()):.0f} s in all")
print(f"not finished ({len(unfinished)}): {', '.join(unfinished)}")
