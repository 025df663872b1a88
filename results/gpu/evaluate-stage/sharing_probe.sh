#!/bin/bash
# How evaluation parts share one GPU: the evaluate stage's costliest program (LGNN's 3
# seeds on chain100, 100 initial conditions) and a latency-bound one (LGNN's 3 seeds on
# T1, one initial condition), alone, then K chain100 parts at once with the T1 part
# started 20 s after them: under a private MPS daemon (the stage's way), with XLA's
# while loops and conditionals captured in CUDA graphs, and without MPS; and "mix":
# the stage's 14 costliest and latency-bound parts at once, 3 calls each, compiled from
# scratch as in the stage, under MPS, with XLA's defaults and with the graphs. Run from
# the repository root on a GPU machine with lgnn importable:
#     bash results/gpu/evaluate-stage/sharing_probe.sh OUTDIR [K [PHASE...]]
# PHASEs: alone mps graphs-alone graphs-mps timeslice (the default) mix graphs-mix.
# Writes OUTDIR/<phase>.jsonl (sharing_probe.py's lines), the CPU's /proc/stat each
# second (cpu.txt), nvidia-smi during each phase and the MPS daemon's logs.
set -u
out=$1; k=${2:-8}; shift $(( $# < 2 ? $# : 2 )); phases=${*:-alone mps graphs-alone graphs-mps timeslice}; big=${BIG_SCENE:-chain100}  # BIG_SCENE: another scene for a dry run on a CPU
mkdir -p "$out"
# As the stage's children: no process preallocates the GPU's memory.
export LGNN_JAX_CACHE=${LGNN_JAX_CACHE:-/tmp/lgnn-probe-cache} PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
graphs="--xla_gpu_enable_command_buffer=FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,CUDNN,CONDITIONAL,WHILE"
probe=${PROBE:-python results/gpu/evaluate-stage/sharing_probe.py}  # PROBE=echo: a dry run
(while true; do echo "$(date +%s.%N | cut -c1-14) $(head -1 /proc/stat)"; sleep 1; done) > "$out/cpu.txt" &
sampler=$!
alone() {  # name: the two parts one after the other
    echo "== $1 $(date +%s)"
    timeout 200 $probe --tag "$1-$big" --job lgnn-chain4 --scene $big --calls 2 >> "$out/$1.jsonl" 2>> "$out/$1.err"
    timeout 100 $probe --tag "$1-T1" --job lgnn-chain4 --scene T1 --calls 5 >> "$out/$1.jsonl" 2>> "$out/$1.err"
    tail -2 "$out/$1.jsonl"
}
beside() {  # name: K chain100 parts, the T1 part 20 s after them
    echo "== $1 $(date +%s)"
    local parts=()
    for _ in $(seq "$k"); do
        timeout 200 $probe --tag "$1-$big" --job lgnn-chain4 --scene $big --calls 2 >> "$out/$1.jsonl" 2>> "$out/$1.err" &
        parts+=($!)
    done
    sleep 20
    timeout 180 $probe --tag "$1-T1" --job lgnn-chain4 --scene T1 --calls 5 >> "$out/$1.jsonl" 2>> "$out/$1.err"
    nvidia-smi > "$out/$1.smi" 2>&1
    wait "${parts[@]}"
    cat "$out/$1.jsonl"
}
with_mps() {  # name, command...: the command under a private MPS daemon, its logs kept
    local name=$1; shift
    export CUDA_MPS_PIPE_DIRECTORY=/tmp/probe-mps-$name/pipe CUDA_MPS_LOG_DIRECTORY=/tmp/probe-mps-$name/log
    mkdir -p "$CUDA_MPS_PIPE_DIRECTORY" "$CUDA_MPS_LOG_DIRECTORY"
    nvidia-cuda-mps-control -d
    "$@"
    echo quit | nvidia-cuda-mps-control
    sleep 1
    for f in "$CUDA_MPS_LOG_DIRECTORY"/*.log; do cp "$f" "$out/$name-$(basename "$f")"; done
    unset CUDA_MPS_PIPE_DIRECTORY CUDA_MPS_LOG_DIRECTORY
}
mixed() {  # name: the mix's parts at once, their programs compiled in the stage's way (no cache)
    echo "== $1 $(date +%s)"
    local parts=() part
    for part in lgnn-chain4:chain100 lgnn-mp1-chain4:chain100 lgnn-mp2-chain4:chain100 lgnn-notebook-chain4:chain100 lgn-chain4:chain100 \
                lgnn-chain4-3d:chain100-3d lgnn-notebook-chain4-3d:chain100-3d lgn-chain4-3d:chain100-3d lgnn-chain4:T1 lgn-chain4:T1 \
                lgnn-chain4:T2-slack lgnn-mp2-chain4:T2-slack lgnn-chain4:T3-slack lgn-chain4:T3-slack; do
        LGNN_JAX_CACHE=off timeout 260 $probe --once --tag "$1-${part#*:}" --job "${part%:*}" --scene "${part#*:}" --calls 3 >> "$out/$1.jsonl" 2>> "$out/$1.err" &
        parts+=($!)
    done
    (sleep 60; nvidia-smi > "$out/$1.smi" 2>&1) &
    wait "${parts[@]}"
    echo "== $1 done $(date +%s)"
}
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader > "$out/machine.txt"; nproc >> "$out/machine.txt"
for phase in $phases; do
    case $phase in
        alone) alone alone ;;
        mps) with_mps mps beside mps ;;
        graphs-alone) XLA_FLAGS="${XLA_FLAGS:-} $graphs" alone graphs-alone ;;
        graphs-mps) XLA_FLAGS="${XLA_FLAGS:-} $graphs" with_mps graphs-mps beside graphs-mps ;;
        timeslice) beside timeslice ;;
        mix) with_mps mix mixed mix ;;
        graphs-mix) XLA_FLAGS="${XLA_FLAGS:-} $graphs" with_mps graphs-mix mixed graphs-mix ;;
        *) echo "unknown phase $phase"; exit 2 ;;
    esac
done
kill $sampler
