r"""Basins and sweeps on one accelerator: what `jaxsleigh.run_basin` and `jaxsleigh.sweep` do
with their defaults on a GPU, warm, in one process.

    python experiments/performance/gpu_studies.py [--basin-n 1000000] [--sweep-n 131072] [--sweep-t 30] [--repeats 3]
                                                  [--skip-basin] [--x64] [--out out/gpu_studies.json]

* ``basin``: the default basin of ``--basin-n`` starts (`jaxsleigh.sample_starts`, seed 0, 100 s, adaptive):
  wall time, starts per second, the equivalent trajectory-steps per second (N x 10^4 base steps over the wall
  time, as in the scaling benchmark), mean / max steps, the fraction settled and the statuses.
* ``sweep_vs_basin``: a sweep of 8 values of ``k`` x ``--sweep-n`` starts against `run_basin` of the same rows'
  starts (paper gains), ``--sweep-t`` seconds, median of ``--repeats``, interleaved: the sweep's overhead (at most 1.2x on CPU).

A warm-up of each shape compiles first (not timed). Off a GPU it runs too (on the CPU's devices), slowly:
``--basin-n 4096 --sweep-n 512`` for a check of the script.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

KS = [0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0]


def timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--basin-n", type=int, default=1_000_000)
    ap.add_argument("--sweep-n", type=int, default=131_072)
    ap.add_argument("--sweep-t", type=float, default=30.0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--skip-basin", action="store_true")
    ap.add_argument("--x64", action="store_true")
    ap.add_argument("--out", default="out/gpu_studies.json")
    a = ap.parse_args(argv)
    import jax

    import jaxsleigh as js

    log = lambda *m: print(*m, file=sys.stderr, flush=True)  # noqa: E731
    dev = jax.devices()[0]
    res = {"command": "python experiments/performance/gpu_studies.py " + " ".join(sys.argv[1:] if argv is None else argv),
           "device": f"{dev.platform}:{getattr(dev, 'device_kind', '')}", "devices": len(jax.devices()),
           "jax": jax.__version__, "machine": platform.platform(), "host_cores": os.cpu_count(),
           "dtype": "float64" if a.x64 else "float32", "load_before": list(os.getloadavg())}

    kw = dict(x64=a.x64, run=js.RunOptions(progress=False))
    if not a.skip_basin:
        basin_study(js, a, kw, res, log)
    sweep_vs_basin(js, a, kw, res, log)
    res["load_after"] = list(os.getloadavg())
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(res, indent=1) + "\n")
    log(f"wrote {a.out}")
    return 0


def basin_study(js, a, kw, res, log):
    js.run_basin(js.sample_starts(2048, seed=1), **kw)                     # compile, not timed
    starts = js.sample_starts(a.basin_n, seed=0)
    r, wall = timed(lambda: js.run_basin(starts, **kw))
    status = np.asarray(r.status)
    res["basin"] = {"n": a.basin_n, "t_final": 100.0, "wall_s": wall, "starts_per_s": a.basin_n / wall,
                    "equivalent_traj_steps_per_s": a.basin_n * 10_000 / wall,
                    "mean_steps": float(np.mean(r.n_steps)), "max_steps": int(np.max(r.n_steps)),
                    "fraction_settled": float(np.mean(r.converged)),
                    "statuses": {int(s): int(c) for s, c in zip(*np.unique(status, return_counts=True))}}
    log("basin:", json.dumps(res["basin"]))


def sweep_vs_basin(js, a, kw, res, log):
    base = js.sample_starts(a.sweep_n, seed=0)
    rows = np.tile(base.ics, (len(KS), 1))
    sweep = lambda: js.sweep(base, {"k": KS}, t_final=a.sweep_t, **kw)    # noqa: E731
    basin = lambda: js.run_basin(rows, t_final=a.sweep_t, **kw)           # noqa: E731
    sweep(), basin()                                                       # compile
    walls = {"sweep_s": [], "basin_s": []}
    for _ in range(a.repeats):
        for name, fn in (("sweep_s", sweep), ("basin_s", basin)):
            walls[name].append(timed(fn)[1])
    res["sweep_vs_basin"] = {"values": len(KS), "n": a.sweep_n, "rows": len(KS) * a.sweep_n, "t_final": a.sweep_t,
                             **walls, "ratio": float(np.median(walls["sweep_s"]) / np.median(walls["basin_s"]))}
    log("sweep / basin:", json.dumps(res["sweep_vs_basin"]))


if __name__ == "__main__":
    sys.exit(main())
