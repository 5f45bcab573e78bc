#!/usr/bin/env bash
# The accelerator's figures (throughput on one GPU): on a machine where JAX sees a GPU,
#
#     OUT=out/accelerator bash experiments/performance/bench_accelerator.sh [STEP ...]
#
# STEP (default: all of them, in this order; each is capped by `timeout`):
#   device    device.txt: the GPU (nvidia-smi), JAX's version and devices, host cores, load average
#   kernel    gpu_kernel.json: experiments/performance/gpu_kernel.py, the fixed-step path as XLA's loop of kernels
#             against the one-kernel path (jaxsleigh.integrate.gpu_plain), N = 10^5 and 10^6, same process
#   scaling   scaling.json: experiments/performance/bench_scaling.py with run_ensemble's defaults, N = 10^4 ... 10^7,
#             (N: $SIZES, default 10000,100000,1000000,10000000)
#             the plain fixed-step path, fixed-step RK4 through the stepper (with summaries) and the
#             adaptive default, float32, 100 s at dt = 0.01
#   bench     bench.json: `jaxsleigh bench --json` (4096 starts, 100 s, float32; the C program on every host core)
#   chunks    chunk<C>.json: bench_scaling at N = 10^6 with chunk_size C = 65536, 262144, 1048576, 4194304
#             (how jaxsleigh.cores.ACCELERATOR_CHUNK was chosen)
#   tests     tests.log: the tests of the one-kernel path, on the GPU (the kernel compiled by Triton, not
#             Pallas' interpreter)
#   studies   studies.json: experiments/performance/gpu_studies.py, a default basin of 10^6 starts and a sweep of
#             8 x 131072 against a basin of the same rows (10 s, median of 2; STUDY_ARGS to change)
#   tail      gpu_tail.json: experiments/performance/gpu_tail.py, the cost of one loop iteration on the 1024 starts nearest
#             theta = 0, with and without CUDA graphs for loops, and on the host's cores
#   f64       f64.json: bench_scaling at N = 10^6 in float64, the plain path and the adaptive default
#   startup   startup.txt: two fresh processes of the README's `jaxsleigh simulate` with a new cache folder
# and all.log, everything the steps printed. Every step (the default) takes about 15 minutes on one H100. A
# shorter run of ~8 minutes (7 minutes on one H100):
#     OUT=... SIZES=1000000,10000000 MODES=plain,adaptive bash experiments/performance/bench_accelerator.sh \
#         device tests bench kernel scaling studies f64 startup
# and `tests tail` about 2 more.
# Run from the repository's root, with jaxsleigh importable (installed, or this folder on PYTHONPATH).
set -u
OUT=${OUT:-out/accelerator}
PY=${PYTHON:-python3}
STEPS=${*:-device kernel scaling bench chunks tests studies f64 startup tail}
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
          $PY -c "import jaxsleigh as js, jax; r = js.run_ensemble([[-3, -2, 0.4]], t_final=1.0, progress=False); print('jaxsleigh runs on', jax.devices()[0].device_kind, r.q_final)"
          echo "host cores: $(nproc)"; uptime; } >"$OUT/device.txt" 2>&1
        tee -a "$LOG" <"$OUT/device.txt" ;;
    kernel)
        step "fixed-step: XLA's loop of kernels against one kernel"
        timeout 120 $PY experiments/performance/gpu_kernel.py --sizes 100000,1000000 --out "$OUT/gpu_kernel.json" 2>&1 \
            | tail -n 60 | tee -a "$LOG" ;;
    scaling)
        step "scaling over N, run_ensemble's defaults"
        timeout 200 $PY experiments/performance/bench_scaling.py --sizes "${SIZES:-10000,100000,1000000,10000000}" --modes "${MODES:-plain,rk4,adaptive}" --horizons '' \
            --timeout 110 --out "$OUT/scaling.json" 2>&1 | tee -a "$LOG" ;;
    bench)
        step "jaxsleigh bench --json"
        timeout 100 $PY -m jaxsleigh.cli bench --json >"$OUT/bench.json" 2>>"$LOG"
        echo "exit $?" | tee -a "$LOG" ;;
    chunks)
        for c in 65536 262144 1048576 4194304; do
            step "N = 10^6, chunk_size $c"
            timeout 50 $PY experiments/performance/bench_scaling.py --sizes 1000000 --horizons '' --chunk-size $c \
                --timeout 45 --out "$OUT/chunk$c.json" 2>&1 | tee -a "$LOG"
        done ;;
    tests)
        step "tests of the one-kernel path on the GPU"
        timeout 120 $PY -m pytest -q -p no:cacheprovider -o addopts="" tests/test_gpu_plain.py >"$OUT/tests.log" 2>&1
        echo "exit $?" >>"$OUT/tests.log"; tail -n 5 "$OUT/tests.log" | tee -a "$LOG" ;;
    studies)
        step "basins and sweeps"
        timeout 200 $PY experiments/performance/gpu_studies.py ${STUDY_ARGS:---sweep-t 10 --repeats 2} --out "$OUT/studies.json" 2>&1 \
            | tee -a "$LOG" ;;
    tail)
        step "the stragglers' loop iteration"
        timeout 170 $PY experiments/performance/gpu_tail.py --n 1024 --t-final 10 --timeout 60 --out "$OUT/gpu_tail.json" 2>&1 \
            | tee -a "$LOG" ;;
    f64)
        step "float64, N = 10^6"
        timeout 120 $PY experiments/performance/bench_scaling.py --sizes 1000000 --modes plain,adaptive --horizons '' --x64 \
            --timeout 55 --out "$OUT/f64.json" 2>&1 | tee -a "$LOG" ;;
    startup)
        step "start-up: two fresh processes of jaxsleigh simulate, a new cache folder"
        cache=$(mktemp -d)
        for i in 1 2; do
            t0=$EPOCHREALTIME
            JAXSLEIGH_CACHE_DIR=$cache timeout 60 $PY -m jaxsleigh.cli simulate --ic=-3,-2,pi/8 --ic 1,1,0.5 \
                --t-final 100 --out "$cache/run$i.npz" >/dev/null 2>&1
            echo "process $i: exit $?, $(awk "BEGIN { print $EPOCHREALTIME - $t0 }") s"
        done | tee "$OUT/startup.txt" | tee -a "$LOG"
        $PY -c "import sys, numpy as np; a, b = (np.load(f) for f in sys.argv[1:]); d = [k for k in a.files if k != 'settings_json' and not np.array_equal(a[k], b[k])]; print('arrays that differ between the two processes:', d or 'none')" \
            "$cache/run1.npz" "$cache/run2.npz" 2>&1 | tee -a "$OUT/startup.txt" | tee -a "$LOG" ;;
    *) echo "unknown step $s (device, kernel, scaling, bench, chunks, tests, studies, f64, startup, tail)" >&2; exit 2 ;;
    esac
done
step done
