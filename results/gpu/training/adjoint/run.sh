# The measurements of this folder, on one GPU, from the repository's root, with the
# wheels of jraph and mujoco installed. `old` is the package before the adjoint
# (commit c3e9dbc; OLD_COMMIT or OLD_TREE choose another), `new` the working tree's.
#
#   bash results/gpu/training/adjoint/run.sh ab chain4-3d "lgn lgnn" "clnn lgnn-notebook gns" > loop-h200-3d-ab.jsonl
#   bash results/gpu/training/adjoint/run.sh ab chain4 "lgn lgnn-mp2" "lgnn lgnn-mp1 clnn lgnn-notebook gns" > loop-h200-2d-ab.jsonl
#   bash results/gpu/training/adjoint/run.sh alone chain4-3d "lgn lgnn clnn lgnn-notebook gns" > alone-h200-3d.jsonl
#   bash results/gpu/training/adjoint/run.sh alone chain4 "lgn lgnn-mp2 lgnn lgnn-mp1 clnn lgnn-notebook gns" > alone-h200-2d.jsonl
#   bash results/gpu/training/adjoint/run.sh share 210 > share-14-h200.jsonl 2> share-14-h200-console.txt
#
# `share` runs the benchmark's train stage of the paper track's 14 groups from scratch,
# side by side (`--workers 14`), into a fresh folder and dataset cache, stops it after
# the given seconds and prints each job's rate from its checkpoints.
#
# Each JSON line of an A/B run is tagged with its variant and round (the environment
# line is printed once). The tables: tools/training_throughput.py --summarise.
set -e
MODE=$1 SCENE=$2  # SCENE: with `share`, the seconds
loop() {  # loop SEEDS MODELS...
    local seeds=$1; shift
    python3 tools/training_throughput.py --loop --checkpoints --models "$@" --scene "$SCENE" --seed-counts "$seeds" --per-call 10 --epochs 20 | grep --line-buffered '^{'
}
tag() {  # tag VARIANT ROUND: the variant and round added to each measurement line
    python3 -c 'import json, sys
for line in sys.stdin:
    row = json.loads(line)
    if "environment" in row:
        print(line, end="") if sys.argv[3] == "first" else None
        continue
    print(json.dumps({"variant": sys.argv[1], **({"round": int(sys.argv[2])} if sys.argv[2] != "-" else {}), **row}))' "$@"
}
if [ "$MODE" = alone ]; then loop 1 $3; exit; fi
if [ "$MODE" = share ]; then
    JOBS=""
    for m in lgnn lgnn-mp1 lgnn-mp2 lgnn-notebook gns lgn clnn; do for s in 0 1 2; do JOBS="$JOBS --job $m-chain4-s$s"; done; done
    for t in lgnn-chain4-varied lgnn-chain4-drag lgnn-chain4-3d lgnn-notebook-chain4-3d gns-chain4-3d lgn-chain4-3d clnn-chain4-3d; do
        for s in 0 1 2; do JOBS="$JOBS --job $t-s$s"; done; done
    OUTDIR=$(mktemp -d)
    LGNN_CACHE=$OUTDIR/cache timeout "$SCENE" python3 -m lgnn benchmark --full --stage train --out-dir "$OUTDIR" --workers 14 $JOBS >&2 || true
    python3 results/gpu/training/adjoint/shared_rates_from_checkpoints.py "$OUTDIR"
    exit
fi
# `old`: the package at OLD_COMMIT (default c3e9dbc), or the copy of one in OLD_TREE.
if [ -n "$OLD_TREE" ]; then OLD=$OLD_TREE; else OLD=$(mktemp -d) && git archive "${OLD_COMMIT:-c3e9dbc}" lgnn | tar -x -C "$OLD"; fi
first=first
for round in 1 2; do
    loop 3 $3 | tag new $round $first; first=no
    PYTHONPATH="$OLD:$PYTHONPATH" loop 3 $3 | tag old $round no
done
[ -n "$4" ] && loop 3 $4 | tag new - no
