"""Benchmark gradients of the tuning objective through the integrator: reverse mode with
checkpointed segments, reverse mode without checkpointing, forward mode (``jacfwd``), and the
value alone.

    python experiments/performance/bench_gradients.py [--steps 10000] [--batch 256] [--x64] [--repeat 3]

Workload: the objective of :mod:`jaxsleigh.tuning` on ``--batch`` starts of the default
distribution with the paper's gains, all 7 gain parameters free (L: 3, k: 1, D_hat: 3), the
adaptive RK4 capped at ``max_step = dt = 0.01`` over ``steps * dt`` seconds and no early stop,
so that every lane takes exactly ``--steps`` attempted steps (no guard starts). Each variant runs
in a fresh process. Memory: the peak resident set of the process *while running* (its high-water
mark is reset after compilation through ``/proc/self/clear_refs``, so LLVM's compile-time memory
is not counted) and the XLA temporary buffers of the compiled program (its own estimate). Compile
time is excluded from the run time (median of ``--repeat`` runs).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

VARIANTS = {
    "value only": dict(kind="value", segment=100),
    "reverse + checkpoint (segments of 100)": dict(kind="reverse", segment=100),
    "reverse, no checkpoint (one segment)": dict(kind="reverse", segment=None),
    "forward (jacfwd, 7 tangents)": dict(kind="forward", segment=100),
}


def _peak_rss_mb() -> float:
    """High-water mark of the resident set [MB] (VmHWM; falls back to ru_maxrss)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _current_rss_mb() -> float:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


def _reset_peak() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _one(name: str, steps: int, batch: int, x64: bool, repeat: int) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np

    from jaxsleigh import tuning as tu

    spec = VARIANTS[name]
    segment = steps if spec["segment"] is None else spec["segment"]
    with jax.enable_x64(x64):
        dtype = jnp.zeros(()).dtype
        ics = tu.sample_starts(tu.UniformStarts(), batch, 0)
        data = tu.make_training_set(ics, guard=np.zeros((0, 3)), dtype=dtype)
        cfg = tu.LossConfig(t_final=steps * 0.01, dt=0.01, stepsize=tu.TRAINING_STEPSIZE._replace(max_step=0.01),
                            stop_fraction=1e-9)
        cfg = tu.traced_loss(cfg, dtype)
        theta = tu.GainParams(*(jnp.asarray(x, dtype) for x in tu.params_from_gains("paper")))
        trainable, frozen = tu.split_params(theta, None)
        if spec["kind"] == "value":
            fn = jax.jit(lambda tr, fr, d, c: tu.objective(tr, fr, d, c, n_attempts=steps, segment=segment))
        else:
            fn = tu.make_value_and_grad(mode=spec["kind"], n_attempts=steps, segment=segment)
        t0 = time.perf_counter()
        compiled = fn.lower(trainable, frozen, data, cfg).compile()
        compile_s = time.perf_counter() - t0
        mem = compiled.memory_analysis()
        temp = getattr(mem, "temp_size_in_bytes", float("nan")) if mem is not None else float("nan")
        rss_before = _current_rss_mb()
        reset = _reset_peak()
        times = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            out = jax.block_until_ready(compiled(trainable, frozen, data, cfg))
            times.append(time.perf_counter() - t0)
        aux = out[0][1] if spec["kind"] != "value" else out[1]
        attempts = np.asarray(aux["lanes"].n_attempts)
        peak = _peak_rss_mb()
    return {"variant": name, "steps": steps, "batch": batch, "dtype": str(dtype), "run_s": float(np.median(times)),
            "compile_s": compile_s, "peak_rss_mb": peak, "rss_growth_mb": peak - rss_before, "peak_reset": reset,
            "xla_temp_mb": temp / 2 ** 20, "attempts_min": int(attempts.min()), "attempts_max": int(attempts.max())}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, nargs="+", default=[10000],
                        help="attempted steps per lane (several values show how memory scales; default 10000)")
    parser.add_argument("--batch", type=int, default=256, help="starts (default 256)")
    parser.add_argument("--repeat", type=int, default=3, help="timed runs per variant (default 3)")
    parser.add_argument("--x64", action="store_true", help="float64 (default float32)")
    parser.add_argument("--variants", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--one", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.one is not None:
        print(json.dumps(_one(args.one, args.steps[0], args.batch, args.x64, args.repeat)))
        return 0
    names = list(VARIANTS) if args.variants is None else [n for n in VARIANTS if n.split()[0] in args.variants]
    rows = []
    for steps in args.steps:
        for name in names:
            cmd = [sys.executable, os.path.abspath(__file__), "--one", name, "--steps", str(steps),
                   "--batch", str(args.batch), "--repeat", str(args.repeat)] + (["--x64"] if args.x64 else [])
            out = subprocess.run(cmd, capture_output=True, text=True)
            if out.returncode != 0:
                print(f"{name} ({steps} steps) failed:\n{out.stderr[-2000:]}", file=sys.stderr)
                continue
            rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
            r = rows[-1]
            print(f"  done: {name}, {steps} steps: {r['run_s']:.2f} s, peak RSS {r['peak_rss_mb']:.0f} MB",
                  file=sys.stderr, flush=True)
    import jax

    print(f"\nGradient of the tuning objective through {', '.join(map(str, args.steps))} attempted adaptive RK4 "
          f"steps, batch {args.batch}, {rows[0]['dtype'] if rows else ''}, 7 free parameters, "
          f"jax {jax.__version__} on {jax.devices()[0].platform} ({os.cpu_count()} cores)\n")
    print("| variant | steps | run time [s] | compile [s] | peak RSS while running [MB] | growth over "
          "pre-run RSS [MB] | XLA temp buffers [MB] |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['variant']} | {r['steps']} | {r['run_s']:.2f} | {r['compile_s']:.1f} | {r['peak_rss_mb']:.0f} | "
              f"{r['rss_growth_mb']:.0f} | {r['xla_temp_mb']:.1f} |")
    if rows and not all(r["peak_reset"] for r in rows):
        print("\n(peak RSS could not be reset after compilation here: it includes compile-time memory)")
    bad = [r for r in rows if r["attempts_min"] != r["steps"]]
    if bad:
        print("\n(warning: some lanes did not take every step: " + ", ".join(r["variant"] for r in bad) + ")")
    return 0


if __name__ == "__main__":
    sys.exit(main())
