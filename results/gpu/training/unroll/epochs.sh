set -o pipefail
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 LGNN_COMMIT=$(cat .ab/commit)
nvidia-smi --query-gpu=name,memory.used --format=csv
mkdir -p $OUT
T=tools/training_throughput.py
# Floors, in the same call.
for d in float64 float32; do echo "gns_floor $d: $(python3 .ab/floors/gns_floor.py 3 $d 2>&1 | tail -1)"; done
for d in float64 float32; do echo "train_floor $d: $(python3 .ab/floors/train_floor.py 3 $d 2>&1 | tail -1)"; done
# A/B: base (HEAD) then this tree, bare epoch, 3 seeds vmapped.
for d in float64 float32; do
  for v in new base; do
    if [ $d = float32 ] && [ $v = base ]; then continue; fi
    if [ $v = base ]; then P=$PWD/.ab/base:/tmp/site; else P=$PWD:/tmp/site; fi
    PYTHONPATH=$P python3 $T --models gns-10-128 cgnode chgn lgnn --batches 100 --dtype $d --epochs 5 --data /tmp/ds 2>&1 | grep -v Warn | sed "s/^/$v $d /" | tee -a $OUT/epochs.jsonl
  done
done
