#!/bin/bash
# Ray scale, evaluation stage: chain100 (100 initial conditions over 0.2 s) for the four
# LGNN variants' committed checkpoints, through `--executor ray --workers 4`, on 4 GPUs
# and on 1 (CUDA_VISIBLE_DEVICES), one MPS daemon; the ground truth prepared untimed.
set -u
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 LGNN_JAX_CACHE=off
export CUDA_MPS_PIPE_DIRECTORY=/tmp/mps/pipe CUDA_MPS_LOG_DIRECTORY=/tmp/mps/log
SUBSET=(--full --stage evaluate --scene chain100 --set 'models=["lgnn","lgnn-mp1","lgnn-mp2","lgnn-notebook"]' --set evaluate.duration=0.2)
checkpoints() { mkdir -p $1/benchmark/checkpoints; cp results/benchmark/checkpoints/lgnn{,-mp1,-mp2,-notebook}-chain4-s?.npz $1/benchmark/checkpoints/; }
case $1 in
install)
  cat /tmp/carry1/part-aa .ray2/part-ab > /tmp/ray-2.60.0-cp312-cp312-manylinux2014_x86_64.whl
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site /tmp/ray-*.whl /tmp/carry1/*.whl .ray2/mujoco*.whl .ray2/jraph*.whl .ray2/tqdm*.whl .ray2/msgpack*.whl || exit 1
  for m in click:click filelock:filelock yaml:pyyaml jsonschema:jsonschema referencing:referencing rpds:rpds attrs:attrs jsonschema_specifications:jsonschema_specifications; do
    python3 -c "import ${m%%:*}" 2>/dev/null || python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .ray2/${m##*:}*.whl
  done
  python3 -c "import ray, mujoco, jax; print('ray', ray.__version__, 'mujoco', mujoco.__version__, 'jax', jax.__version__, jax.devices())" || exit 1
  nvidia-smi --query-gpu=name,memory.total --format=csv,noheader; nproc; git log -1 --format=%h 2>/dev/null
  mkdir -p $CUDA_MPS_PIPE_DIRECTORY $CUDA_MPS_LOG_DIRECTORY; nvidia-cuda-mps-control -d && echo "MPS daemon started"
  # untimed: chain100's ground truth (computed while evaluating the cheapest variant, on one GPU)
  s0=$(date +%s); checkpoints /tmp/prep
  LGNN_CACHE=/tmp/prepcache CUDA_VISIBLE_DEVICES=0 timeout 300 python3 -m lgnn benchmark "${SUBSET[@]}" --job lgnn-mp1-chain4-s0 --out-dir /tmp/prep > $OUT/log-prep.txt 2>&1
  echo "prep rc $? $(( $(date +%s) - s0 )) s"; ls /tmp/prepcache/datasets/ground-truth ;;
run)  # name, CUDA_VISIBLE_DEVICES, timeout
  nvidia-smi --query-gpu=index,utilization.gpu --format=csv,noheader,nounits -l 2 > $OUT/util-$2.csv &
  smi=$!; start=$(date +%s.%N)
  cp -r /tmp/prepcache /tmp/cache-$2; checkpoints /tmp/scale-$2
  LGNN_CACHE=/tmp/cache-$2 CUDA_VISIBLE_DEVICES=$3 timeout $4 python3 -m lgnn benchmark "${SUBSET[@]}" --executor ray --workers 4 --out-dir /tmp/scale-$2 > $OUT/log-$2.txt 2>&1; rc=$?
  python3 -c "import time; print('$2: rc $rc, wall %.1f s' % (time.time() - $start))"
  kill $smi; pkill -f "lgnn benchmark"; pkill -f raylet; pkill -f gcs_server; sleep 2
  cp /tmp/scale-$2/benchmark/logs/*.log $OUT/ 2>/dev/null; for f in $OUT/evaluate-*.log; do mv $f ${f%.log}-$2.log; done
  python3 - "$OUT/util-$2.csv" <<'PY'
import csv, statistics, sys
by = {}
for row in csv.reader(open(sys.argv[1])):
    if len(row) == 2: by.setdefault(row[0].strip(), []).append(float(row[1]))
print({k: round(statistics.mean(v), 1) for k, v in by.items()})
PY
  ;;
esac
