#!/bin/bash
# One preemptible job of the full profile's paper track on a fresh machine: take back the
# last job's hand-back (.handoff/in, if any), run the benchmark until the deadline, hand back.
set -u
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 LGNN_CACHE=/tmp/cache-$RANDOM HOME=$(mktemp -d) XDG_CACHE_HOME=
export XDG_CACHE_HOME=$HOME/.cache
TRACK='tracks=["paper"]'
RUN=/tmp/run-$RANDOM
START=$(date +%s)
if [ -f .handoff/in/handoff.json ]; then python3 -m lgnn handoff unpack .handoff/in --out-dir $RUN || exit 1; fi
nvidia-smi --query-gpu=name,memory.used --format=csv,noheader
python3 -m lgnn --version
timeout -s INT ${DEADLINE:-470} python3 -m lgnn benchmark --full --set "$TRACK" --out-dir $RUN --workers 8 --chunk 100 --quiet > $OUT/job.log 2>&1
echo "benchmark rc=$? after $(( $(date +%s) - START )) s"
python3 -m lgnn handoff pack $RUN --full --set "$TRACK" --to $OUT/back --files 7 --total-mib 36 2>&1 | tail -4
echo "resumed: $(grep -c 'resuming at epoch' $OUT/job.log) reused: $(grep -c 'reusing finished' $OUT/job.log)"
grep -E "stopped|plateau|epoch budget|finished" $OUT/job.log | tail -20
tail -4 $OUT/job.log
echo "job wall $(( $(date +%s) - START )) s"
