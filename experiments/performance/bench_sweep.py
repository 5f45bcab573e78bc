"""Cost of a parameter sweep against one ensemble of the same size.

A sweep of P values x N starts runs as P * N rows of one ``run_ensemble`` call whose gains / plant
leaves carry a per-row axis. This benchmark compares, on the same machine, interleaved:

* ``plain``: one ensemble of the P * N starts (N starts tiled P times) with one plant (the paper's);
* ``lanes``: the same P * N rows with per-row parameters all equal to that plant (pure overhead of
  carrying and gathering per-row parameters: the same arithmetic, the same steps);
* ``sweep``: ``jaxsleigh.sweep`` over P values of the mass m (different dynamics, so the step counts
  differ; compared per accepted trajectory-step).

Memory is bounded by the chunk: every variant integrates ``--chunk-size`` rows at a time.
Usage: ``python experiments/performance/bench_sweep.py [--P 8] [--N 512] [--t-final 40] [--repeats 3] [--json out.json]``
"""
from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

import jaxsleigh as js
from jaxsleigh.studies.basin import sample_starts
from jaxsleigh.model.lanes import stack_plants


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--P", type=int, default=8)
    ap.add_argument("--N", type=int, default=512)
    ap.add_argument("--t-final", type=float, default=40.0)
    ap.add_argument("--chunk-size", type=int, default=2048)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json")
    a = ap.parse_args()
    st = sample_starts(a.N, seed=0, theta="0.2:3")
    ics = np.tile(st.ics, (a.P, 1))
    kw = dict(t_final=a.t_final, run=js.RunOptions(chunk_size=a.chunk_size, progress=False))
    same = stack_plants([js.paper_plant()] * (a.P * a.N))
    m_axis = f"m=0.5:4:{a.P}:log"

    def plain():
        r = js.run_ensemble(ics, **kw)
        return r.n_steps.sum()

    def lanes():
        r = js.run_ensemble(ics, plant=same, **kw)
        return r.n_steps.sum()

    def sweep():
        r = js.sweep(st, [m_axis], **kw)
        return r.n_steps.sum()

    variants = {"plain": plain, "lanes": lanes, "sweep": sweep}
    small = dict(kw, t_final=1.0)
    for f in variants.values():          # compile (shapes of the chunk) outside the timings
        f()
    times = {k: [] for k in variants}
    steps = {}
    for _ in range(a.repeats):           # interleaved: machine load hits every variant alike
        for k, f in variants.items():
            t0 = time.perf_counter()
            steps[k] = int(f())
            times[k].append(time.perf_counter() - t0)
    best = {k: min(v) for k, v in times.items()}
    out = {
        "P": a.P, "N": a.N, "rows": a.P * a.N, "t_final": a.t_final, "chunk_size": a.chunk_size,
        "wall_s_best": best, "wall_s_all": times, "accepted_steps": steps,
        "ratio_lanes_over_plain": best["lanes"] / best["plain"],
        "ratio_sweep_over_plain_per_step": (best["sweep"] / steps["sweep"]) / (best["plain"] / steps["plain"]),
        "ratio_sweep_over_plain_wall": best["sweep"] / best["plain"],
        "loadavg": list(os.getloadavg()), "cpu_count": os.cpu_count(), "sweep_param": m_axis,
    }
    del small
    print(json.dumps(out, indent=1))
    if a.json:
        with open(a.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
