set -o pipefail
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=$PWD:/tmp/site PYTHONUNBUFFERED=1 LGNN_COMMIT=$(cat .ab/commit)
mkdir -p $OUT
python3 results/gpu/training/precision/precision.py --models gns-10-128 cgnode --epochs 200 --data /tmp/ds 2>&1 | grep -v Warn | tee $OUT/precision-h200.jsonl
