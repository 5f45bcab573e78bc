r"""The plain fixed-step path on a GPU: XLA's loop of kernels against the one-kernel path
(`jaxsleigh.integrate.gpu_plain`), side by side in one process.

    python experiments/performance/gpu_kernel.py [--sizes 100000,1000000,10000000] [--t-final 100] [--dt 0.01]
                                                 [--blocks 128,256] [--out out/gpu_kernel.json]

For each N: `drive_plain` (final state only, the benchmark workload, float32) with ``kernel=False``
and with ``kernel=True`` for each block size; each compiled and warmed on the same shapes first, then
timed once (``block_until_ready``). Agreement: the one-kernel float32 final states against XLA's
float32 and against XLA's float64 run, relative to each state's largest component, on the tame
starts (float32 and float64 within 1e-3). Off a GPU the one-kernel path runs in Pallas' interpreter:
use tiny sizes there.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jaxsleigh  # noqa: F401  (first: it sets up JAX)
import jax
import jax.numpy as jnp
import numpy as np

from jaxsleigh.integrate import gpu_plain
from jaxsleigh.integrate.engine import check_ics, drive_plain, initial_w, make_horizon
from jaxsleigh.model.closed_loop import ClosedLoop
from jaxsleigh.model.params import paper_gains, paper_plant
from jaxsleigh.studies.bench import machine, workload


def timed(fn):
    fn()                                            # compile and warm up
    t0 = time.perf_counter()
    y, _ = fn()
    return time.perf_counter() - t0, np.asarray(y)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="100000,1000000,10000000")
    ap.add_argument("--t-final", type=float, default=100.0)
    ap.add_argument("--dt", type=float, default=0.01)
    ap.add_argument("--blocks", default="128,256")
    ap.add_argument("--out", default="out/gpu_kernel.json")
    a = ap.parse_args(argv)
    args = ClosedLoop(paper_plant(), paper_gains())
    horizon = make_horizon(a.t_final, a.dt)
    rows = []
    for n in [int(float(v)) for v in a.sizes.split(",")]:
        ics5, st = check_ics(workload(n, 0))
        y0 = initial_w(ics5, st, jnp.float32)
        work = n * horizon.n_steps
        row = {"n": n, "steps": horizon.n_steps}
        wall, y_xla = timed(lambda: drive_plain(y0, st, args, horizon, kernel=False))
        row["xla"] = {"wall_s": wall, "traj_steps_per_s": work / wall}
        print(f"N = {n}: XLA {wall:.3f} s, {work / wall:.3g} traj-steps/s", file=sys.stderr, flush=True)
        with jax.enable_x64(True):
            y64, _ = drive_plain(jnp.asarray(np.asarray(y0), jnp.float64), st, args, horizon, kernel=False)
            y64 = np.asarray(y64)
        scale = np.maximum(np.max(np.abs(y64), axis=1), 1e-30)
        tame = np.all(np.isfinite(y_xla), axis=1) & (np.max(np.abs(y_xla - y64), axis=1) / scale <= 1e-3)
        row["n_tame"] = int(tame.sum())
        row["xla_vs_f64_rel_median"] = float(np.median((np.max(np.abs(y_xla - y64), axis=1) / scale)[tame]))
        for b in [int(v) for v in a.blocks.split(",")]:
            gpu_plain.KERNEL_BLOCK = b          # the default block of run_plain_kernel is read at call time
            wall, y_k = timed(lambda: drive_plain(y0, st, args, horizon, kernel=True))
            finite_k, finite_x = np.all(np.isfinite(y_k), axis=1), np.all(np.isfinite(y_xla), axis=1)
            rel = np.max(np.abs(y_k - y_xla), axis=1) / scale
            rel64 = np.max(np.abs(y_k - y64), axis=1) / scale
            row[f"kernel_{b}"] = {"wall_s": wall, "traj_steps_per_s": work / wall,
                                  "vs_xla_rel_max_tame": float(rel[tame].max()),
                                  "vs_xla_rel_median_tame": float(np.median(rel[tame])),
                                  "vs_f64_rel_median_tame": float(np.median(rel64[tame])),
                                  "finite_mismatch": int((finite_k != finite_x).sum())}
            print(f"N = {n}: kernel block {b}: {wall:.3f} s, {work / wall:.3g} traj-steps/s, "
                  f"vs XLA max {rel[tame].max():.2g}", file=sys.stderr, flush=True)
        rows.append(row)
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps({"machine": machine(), "dtype": "float32", "t_final": a.t_final,
                                           "dt": a.dt, "results": rows}, indent=1) + "\n")
    print(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
