#!/usr/bin/env bash
# The benchmark on one GPU, float64 then float32: the command behind the GPU table of
# docs/benchmarks.md. Usage: bash benchmarks/bench/gpu_benchmark.sh OUT [SECONDS_PER_DTYPE]
# Run from the repository root in an environment with jax[cuda] and the cli extra (all of it:
# the command lines refuse to start without cmaes and optuna, which a GPU image may lack; carry
# their wheels there, with optuna's alembic, colorlog, Mako, SQLAlchemy and greenlet). Only the
# blocks a GPU changes: the rollout (batch_map: one chunk on a GPU by default), the gradients and the
# reference families; compile tables, memory (host RSS), tuner and exported C steps are CPU work.
# If the jaxpr rewriters fail on the installed JAX, the run is repeated without them
# (WMRJAX_JAXPR_REWRITES=0) and the log says so.
set -u
export PYTHONUNBUFFERED=1
out=${1:?usage: gpu_benchmark.sh OUT [SECONDS_PER_DTYPE]}
limit=${2:-240}
mkdir -p "$out"
{
    nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
    python3 -c 'import jax, jaxlib, platform; print("jax", jax.__version__, "jaxlib", jaxlib.__version__, "python", platform.python_version(), jax.devices())'
    nproc
    git rev-parse --short HEAD 2>/dev/null || true
} >"$out/machine.txt" 2>&1
bench() {  # dtype; the sampled-reference rows need float64 (its smoothness check refuses float32)
    local refs=65536
    [ "$1" = float64 ] || refs=0
    timeout "$limit" python3 -m benchmarks.benchmark --out "$out/$1" --dtype "$1" \
        --batches 1024 16384 262144 1048576 --baseline-max-batch 16384 \
        --grad-batch 1024 --grad-batches 1024 65536 --reps 5 --scipy-trajectories 2 \
        --reference-batch "$refs" --compile-types none --memory-batch 0 --no-memory-estimates \
        --export-samples 0 --tuner-problems
}
for dtype in float64 float32; do
    bench "$dtype" >"$out/$dtype.log" 2>&1
    rc=$?
    if [ "$rc" != 0 ] && [ "$rc" != 124 ]; then
        echo "rewriters on: failed (exit $rc), again with WMRJAX_JAXPR_REWRITES=0" >>"$out/$dtype.log"
        WMRJAX_JAXPR_REWRITES=0 bench "$dtype" >>"$out/$dtype.log" 2>&1
    fi
done
