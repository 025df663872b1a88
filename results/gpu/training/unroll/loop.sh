set -o pipefail
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 LGNN_COMMIT=$(cat .ab/commit)
mkdir -p $OUT
T=tools/training_throughput.py
echo "gns_floor float64: $(python3 .ab/floors/gns_floor.py 3 float64 2>&1 | tail -1)"
echo "train_floor float64: $(python3 .ab/floors/train_floor.py 3 float64 2>&1 | tail -1)"
# The training loop (train_seeds: validation, stopping rule, checkpoints written), 3 seeds packed, 10 epochs a call.
PYTHONPATH=$PWD:/tmp/site python3 $T --loop --checkpoints --models gns-10-128 cgnode lgnn lgn --seed-counts 3 --per-call 10 --epochs 20 --data /tmp/ds 2>&1 | grep -v Warn | sed "s/^/new /" | tee -a $OUT/loop.jsonl
PYTHONPATH=$PWD/.ab/base:/tmp/site python3 $T --loop --checkpoints --models gns-10-128 cgnode --seed-counts 3 --per-call 10 --epochs 20 --data /tmp/ds 2>&1 | grep -v Warn | sed "s/^/base /" | tee -a $OUT/loop.jsonl
