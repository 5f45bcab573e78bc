#!/usr/bin/env bash
# The accelerator's figures (issue 11's GPU targets): on a machine where JAX sees a GPU,
#
#     OUT=out/accelerator bash experiments/bench_accelerator.sh [STEP ...]
#
# STEP (default: all of them, in this order; each is capped by `timeout`):
#   device    device.txt: the GPU (nvidia-smi), JAX's version and devices, host cores, load average
#   kernel    gpu_kernel.json: experiments/gpu_kernel.py, the fixed-step path as XLA's loop of kernels
#             against the one-kernel path (jaxsleigh.integrate.gpu_plain), N = 10^5 and 10^6, same process
#   scaling   scaling.json: experiments/bench_scaling.py with run_ensemble's defaults, N = 10^4 ... 10^7,
#             (N: $SIZES, default 10000,100000,1000000,10000000)
#             the plain fixed-step path, fixed-step RK4 through the stepper (with summaries) and the
#             adaptive default, float32, 100 s at dt = 0.01
#   bench     bench.json: `jaxsleigh bench --json` (4096 starts, 100 s, float32; the C program on every host core)
#   chunks    chunk<C>.json: bench_scaling at N = 10^6 with chunk_size C = 65536, 262144, 1048576, 4194304
#             (how jaxsleigh.cores.ACCELERATOR_CHUNK was chosen)
# and all.log, everything the steps printed. About 10 minutes in all on one H100/H200-class GPU.
# Run from the repository's root, with jaxsleigh importable (installed, or this folder on PYTHONPATH).
set -u
OUT=${OUT:-out/accelerator}
PY=${PYTHON:-python3}
STEPS=${*:-device kernel scaling bench chunks}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
LOG="$OUT/all.log"
touch "$LOG"
step() { echo "== $(date -u +%H:%M:%S) $*" | tee -a "$LOG"; }

for s in $STEPS; do
    case $s in
    device)
        step device
        { nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.max.sm --format=csv 2>&1
          $PY -c "import jax, jaxlib; print('jax', jax.__version__, 'jaxlib', jaxlib.__version__, jax.devices())"
          echo "host cores: $(nproc)"; uptime; } >"$OUT/device.txt" 2>&1
        tee -a "$LOG" <"$OUT/device.txt" ;;
    kernel)
        step "fixed-step: XLA's loop of kernels against one kernel"
        timeout 120 $PY experiments/gpu_kernel.py --sizes 100000,1000000 --out "$OUT/gpu_kernel.json" 2>&1 \
            | tail -n 60 | tee -a "$LOG" ;;
    scaling)
        step "scaling over N, run_ensemble's defaults"
        timeout 200 $PY experiments/bench_scaling.py --sizes "${SIZES:-10000,100000,1000000,10000000}" --modes plain,rk4,adaptive --horizons '' \
            --timeout 110 --out "$OUT/scaling.json" 2>&1 | tee -a "$LOG" ;;
    bench)
        step "jaxsleigh bench --json"
        timeout 100 $PY -m jaxsleigh.cli bench --json >"$OUT/bench.json" 2>>"$LOG"
        echo "exit $?" | tee -a "$LOG" ;;
    chunks)
        for c in 65536 262144 1048576 4194304; do
            step "N = 10^6, chunk_size $c"
            timeout 50 $PY experiments/bench_scaling.py --sizes 1000000 --horizons '' --chunk-size $c \
                --timeout 45 --out "$OUT/chunk$c.json" 2>&1 | tee -a "$LOG"
        done ;;
    *) echo "unknown step $s (device, kernel, scaling, bench, chunks)" >&2; exit 2 ;;
    esac
done
step done
