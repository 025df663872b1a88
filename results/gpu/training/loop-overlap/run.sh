# The call behind README.md's section "The next call no longer waits ...": run from the
# repository root on the device, with the wheels of jraph, tqdm and mujoco in .whl-eval/.
set -u
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl-eval/*.whl 2>&1 | tail -2
export LGNN_CACHE=/tmp/cache
mkdir -p /tmp/old && cp -r lgnn /tmp/old/ && git show fda06ce:lgnn/learn/train.py > /tmp/old/lgnn/learn/train.py  # the loop before the change (the call ran it from a copy of that file)
M="lgnn-notebook lgnn lgn"
run() { if [ $1 = old ]; then P=/tmp/old; else P=$PWD; fi
  PYTHONPATH=/tmp/site:$P python3 tools/training_throughput.py --loop --checkpoints --models $M --seed-counts 3 --per-call 10 --epochs 20 --data /tmp/lgnn-datasets > $OUT/$1-$2.jsonl 2> $OUT/$1-$2.err
  echo "$1 $2 $(grep -h epochs_per_s $OUT/$1-$2.jsonl | python3 -c 'import sys,json; print([(json.loads(l)["model"], json.loads(l)["epochs_per_s"]) for l in sys.stdin])')"; }
nvidia-smi --query-gpu=name --format=csv,noheader
python3 train_floor.py  # the floor script the developers' brief provides (shared/tools/train_floor.py) 3 float64 100 > $OUT/floor.txt 2>&1; tail -2 $OUT/floor.txt
run new 1; run old 1; run new 2; run old 2; run new 3
