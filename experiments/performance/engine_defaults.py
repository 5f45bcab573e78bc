r"""The measurements behind the engine's defaults: every core, the step-size controller's exponents, the step
budget near theta = 0, and how many straggling lanes a part hands over (float32 unless stated).

    python experiments/performance/engine_defaults.py [--out docs/figures/engine_defaults.json]

* ``plain_cores``: the plain fixed-step path (4096 starts, 100 s) on one core and on every core, best of 3.
* ``controllers``: mean steps and T_eps / final-state errors on 512 benchmark starts (paper gains, 100 s) for
  the I controller (alpha 0.25, beta 0), Hairer & Wanner's PI (0.175, 0.1) and the default (0.15, 0.05),
  against this tree's float64 run at rtol = atol = 1e-11.
* ``stiff_start``: attempts of the default step from (3, 3, 1e-2), 10 s, float32 and float64.
* ``tail_lanes``: the default 10^5-start basin (`sample_starts`, seed 0, 100 s) with ``TAIL_LANES`` 0 (every
  part finishes its own stragglers), 16 and 128, wall time.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import jax
import numpy as np

import jaxsleigh as js
from jaxsleigh.integrate import stepsize
from jaxsleigh.studies import ensemble as ens
from jaxsleigh.studies.bench import workload


def best(fn, n=3):
    fn()
    ts = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return min(ts)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="docs/figures/engine_defaults.json")
    a = ap.parse_args(argv)
    log = lambda *m: print(*m, file=sys.stderr, flush=True)  # noqa: E731
    out = {"command": "python experiments/performance/engine_defaults.py", "cores": js.cores.available_cores(),
           "load_before": [round(x, 2) for x in os.getloadavg()]}
    ics = workload(4096, 0)
    kw = dict(stepsize=js.StepSizeController(method="rk4", check_passivity=False), saveat=js.SaveAt(summaries=False))
    one = best(lambda: js.run_ensemble(ics, run=js.RunOptions(cores=1, progress=False), **kw))
    every = best(lambda: js.run_ensemble(ics, run=js.RunOptions(progress=False), **kw))
    out["plain_cores"] = {"one_core_s": one, "every_core_s": every, "speedup": one / every}
    log("plain path:", out["plain_cores"])

    small = ics[:512]
    ref = js.run_ensemble(small, x64=True, stepsize=js.StepSizeController(rtol=1e-11, atol=1e-11, max_steps=5_000_000),
                          run=js.RunOptions(progress=False))
    out["controllers"] = {}
    for name, (al, be) in {"I": (0.25, 0.0), "PI Hairer-Wanner": (0.175, 0.1), "PI default": (0.15, 0.05)}.items():
        stepsize.PI_ALPHA, stepsize.PI_BETA = al, be
        jax.clear_caches()                       # the exponents are constants of the compiled step
        r = js.run_ensemble(small, run=js.RunOptions(progress=False))
        both = np.isfinite(r.T_eps) & np.isfinite(ref.T_eps)
        dT = r.T_eps[both] - ref.T_eps[both]
        err = np.max(np.abs(np.column_stack([r.q_final - ref.q_final, r.p_final - ref.p_final])), axis=1)
        out["controllers"][name] = {"alpha": al, "beta": be, "mean_steps": float(r.n_steps.mean()),
                                    "mean_attempts": float((r.n_steps + r.n_rejected).mean()),
                                    "T_eps_error_max": float(np.abs(dT).max()),
                                    "T_eps_error_median_signed": float(np.median(dT)),
                                    "final_error_median": float(np.median(err))}
        log(name, out["controllers"][name])
    stepsize.PI_ALPHA, stepsize.PI_BETA = 0.15, 0.05
    jax.clear_caches()

    out["stiff_start"] = {}
    for x64 in (False, True):
        s = js.simulate([3.0, 3.0, 1e-2], x64=x64, t_final=10.0, saveat=js.SaveAt(every=10),
                        stepsize=js.StepSizeController(max_steps=10**6))
        out["stiff_start"]["float64" if x64 else "float32"] = {"status": int(s.status[0]),
                                                                "attempts": int(s.n_steps[0] + s.n_rejected[0])}
    log("stiff start:", out["stiff_start"])

    starts = js.sample_starts(100_000, seed=0)
    js.run_basin(js.sample_starts(2048, seed=1), run=js.RunOptions(progress=False))
    out["tail_lanes"] = {}
    for lanes in (0, 16, 128):
        ens.TAIL_LANES = lanes
        t0 = time.perf_counter()
        js.run_basin(starts, run=js.RunOptions(progress=False))
        out["tail_lanes"][str(lanes)] = time.perf_counter() - t0
        log(f"TAIL_LANES {lanes}: {out['tail_lanes'][str(lanes)]:.1f} s")
    out["load_after"] = [round(x, 2) for x in os.getloadavg()]
    Path(a.out).write_text(json.dumps(out, indent=1) + "\n")
    log(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
