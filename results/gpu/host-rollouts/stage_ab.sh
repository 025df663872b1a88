#!/usr/bin/env bash
# The evaluate stage's single-initial-condition parts (T1, T2-slack, T3-slack; the
# paper track's planar models whose committed checkpoints hold parameters), 16 workers
# on one GPU machine, twice from fresh caches: small rollout batches on the host's CPU
# (the default, `evaluate.host_rollouts` 16), then everything on the GPU
# (`--set evaluate.host_rollouts=0`), each cut at LIMIT seconds. Logs to $OUT.
set -u
LIMIT=${LIMIT:-280}
JOBS=()
for model in lgnn lgnn-mp1 lgnn-mp2 lgnn-notebook gns lgn clnn chgn; do
  for seed in 0 1 2; do JOBS+=(--job "$model-chain4-s$seed"); done
done
for variant in host gpu; do
  out=/tmp/ab-$variant
  mkdir -p "$out/benchmark/checkpoints"
  for model in lgnn lgnn-mp1 lgnn-mp2 lgnn-notebook gns lgn clnn chgn; do
    cp results/benchmark/checkpoints/$model-chain4-s?.npz "$out/benchmark/checkpoints/"
  done
  extra=()
  [ "$variant" = gpu ] && extra=(--set evaluate.host_rollouts=0)
  began=$(date +%s.%N)
  LGNN_CACHE=/tmp/cache-$variant LGNN_JAX_CACHE=/tmp/jax-$variant timeout "$LIMIT" python3 -m lgnn benchmark --full --stage evaluate \
    --scene T1 --scene T2-slack --scene T3-slack "${JOBS[@]}" --workers 16 --chunk 100 --out-dir "$out" "${extra[@]}" > "$OUT/$variant.log" 2>&1
  rc=$?
  echo "$variant: rc $rc, $(python3 -c "import time; print(round(time.time() - $began, 1))") s" | tee -a "$OUT/summary.txt"
  tar czf "$OUT/logs-$variant.tgz" -C "$out/benchmark" logs
done
