#!/usr/bin/env bash
# `lgnn simulate chain16 --duration 10` (dt 1e-4: 100 000 RK4 steps) on a GPU machine,
# whole processes, no compilation cache: the package as it was at commit 00213aa (on
# the GPU) against this tree's (on the host's CPU, `rollouts.ground_truth_platform`),
# 3 rounds alternated, then the largest difference between the two trajectories.
# Before running, here:  mkdir -p .probe/old && git archive 00213aa lgnn | tar -x -C .probe/old
# and carry `.probe` (with the jraph wheel in .probe/whl/) to the machine.
set -u
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .probe/whl/*.whl >/dev/null 2>&1
new=$PWD
for round in 1 2 3; do
  for v in old new; do
    dir=$new; [ "$v" = old ] && dir=$new/.probe/old
    ( cd /tmp && LGNN_JAX_CACHE=off LGNN_CACHE=/tmp/cache-$v PYTHONPATH=/tmp/site:$dir /usr/bin/time -f "$v round $round: %e s wall, %U s user" python3 -m lgnn simulate chain16 --duration 10 --out /tmp/$v.npz --quiet ) 2>&1 | tail -1
  done
done
PYTHONPATH=/tmp/site:$new python3 -c "
import numpy as np
a, b = np.load('/tmp/old.npz'), np.load('/tmp/new.npz')
print('frames', a['q'].shape, 'largest node coordinate difference old vs new:', float(np.max(np.abs(a['q'] - b['q']))))
"
