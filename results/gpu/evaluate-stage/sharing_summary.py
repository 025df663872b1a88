"""The tables of the README's section on how the parts share the GPU, from
`sharing_probe.sh`'s lines: per phase, each part's compile seconds, seconds per call of
100 frames, the CPU seconds its process spent and its timed window (seconds from the
phase's first start), and the phase's wall time.

    python results/gpu/evaluate-stage/sharing_summary.py results/gpu/evaluate-stage/sharing-h200"""
import json
import sys
from pathlib import Path

PHASES = ("alone", "mps", "graphs-alone", "graphs-mps", "timeslice", "mix", "graphs-mix")

folder = Path(sys.argv[1])
for phase in PHASES:
    path = folder / f"{phase}.jsonl"
    if not path.exists():
        continue
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    first = min(row["started"] for row in rows)
    print(f"\n{phase}: {len(rows)} parts, {max(row['ended'] for row in rows) - first:.1f} s from the first start to the last end\n")
    print("| model | scene | compile s | s per call | CPU s | timed window, s | finite |")
    print("|---|---|---|---|---|---|---|")
    for row in sorted(rows, key=lambda row: (row["scene"], row["job"], row["timed_from"])):
        window = f"{row['timed_from'] - first:.1f}-{row['ended'] - first:.1f}"
        print(f"| {row['job']} | {row['scene']} | {row['compile_s']} | {row['per_call_s']} | {row['process_s']} | {window} | {row['finite']} |")
