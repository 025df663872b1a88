# The call behind ../README.md's "One part of the evaluation stage", run from the repository
# root on the device with the wheels of jraph, tqdm and mujoco in .whl-eval/.
set -u
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl-eval/*.whl 2>&1 | tail -2
export PYTHONPATH=/tmp/site:$PWD LGNN_CACHE=/tmp/cache LGNN_JAX_CACHE=off
cp -r results /tmp/res
part() {  # $1: unroll, $2: label
  rm -f /tmp/res/benchmark/runs/lgnn-chain4-s{0,1,2}/chain100.npz
  start=$(date +%s.%N)
  python3 -c "
import sys
import lgnn.physics.solvers as solvers
solvers.ACCELERATOR_SWEEP_UNROLL = $1
from lgnn.cli import main
sys.argv = ['lgnn', 'benchmark', '--full', '--stage', 'evaluate', '--out-dir', '/tmp/res', '--scene', 'chain100', '--job', 'lgnn-chain4-s0', '--job', 'lgnn-chain4-s1', '--job', 'lgnn-chain4-s2', '--chunk', '100']
main()
" > $OUT/$2.log 2>&1
  echo "$2 unroll $1: rc $? wall $(python3 -c "print(round($(date +%s.%N) - $start, 1))") s"; grep "rollout error" $OUT/$2.log
}
part 10 unrolled
part 1 loops
