"""Steps set by accuracy: the adaptive default before and after T_eps is located on the step's
dense output, for several caps on the step.

    python experiments/studies/adaptive_steps.py [--n 4096] [--n-tuned 512] [--caps 10,30,100,1000]

"before" is the 0.1 release's behaviour: T_eps is the end of the step that entered the ball
(``ConvergenceTime(samples=1, bisections=0)``) and the step is capped at 10 dt = 0.1 s. "dense"
locates the entry on the cubic Hermite dense output of the step (the default
``ConvergenceTime()``). Each configuration runs the workload of ``jaxsleigh bench`` (x, y ~ U(-3, 3),
|theta0| ~ U(0.3, pi), zero momentum, 100 s, float32) with the paper's gains and, on fewer starts,
with the ``tuned`` preset, against a float64 reference (rtol = atol = 1e-11, cap 0.1 s, T_eps on
the dense output with 8 samples and 30 bisections). Prints a Markdown table.
"""
from __future__ import annotations

import argparse
import time

import numpy as np

import jaxsleigh as js
from jaxsleigh.studies.bench import workload
from jaxsleigh.integrate.observers import DEFAULT_OBSERVERS, ClosestApproach, ControlEffort, ConvergenceTime, Excursion

OLD = (ConvergenceTime(samples=1, bisections=0), ClosestApproach(), Excursion(), ControlEffort())
REF = (ConvergenceTime(samples=8, bisections=30), ClosestApproach(), Excursion(), ControlEffort())


def run(ics, gains, **kw):
    js.run_ensemble(ics[:64], gains=gains, run=js.RunOptions(progress=False), **kw)            # compile
    t0 = time.perf_counter()
    r = js.run_ensemble(ics, gains=gains, run=js.RunOptions(progress=False), **kw)
    return r, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=4096)
    ap.add_argument("--n-tuned", type=int, default=512)
    ap.add_argument("--caps", default="10,30,100,1000", help="caps on the step, in units of dt = 0.01")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    caps = [int(c) for c in a.caps.split(",")]
    print("| gains | configuration | cap [s] | mean steps | max steps | wall [s] | correct traj/s | "
          "max final-state error | wrong (> 1e-3) | max abs(T_eps - T_ref) [s] | T_eps off by > 1e-3 s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for name, n in (("paper", a.n), ("tuned", a.n_tuned)):
        gains = js.load_gains(name)
        ics = workload(n, a.seed)
        ref, _ = run(ics, gains, x64=True, observers=REF,
                     stepsize=js.StepSizeController(rtol=1e-11, atol=1e-11, max_step=0.1, max_steps=4_000_000))
        assert np.all(ref.status == 0), "the reference failed"
        yref = np.concatenate([ref.q_final, ref.p_final], axis=1)
        configs = [("before (0.1 release)", 10, OLD)] + [("dense T_eps", c, DEFAULT_OBSERVERS) for c in caps]
        for label, cap, obs in configs:
            r, wall = run(ics, gains, stepsize=js.StepSizeController(max_step=cap * 0.01), observers=obs)
            err = np.max(np.abs(np.concatenate([r.q_final, r.p_final], axis=1) - yref), axis=1)
            err[~np.isfinite(err)] = np.inf
            wrong = (err > 1e-3) | (r.status != 0)
            both = np.isfinite(r.T_eps) & np.isfinite(ref.T_eps)
            dT = np.abs(r.T_eps[both] - ref.T_eps[both])
            disagree = int(np.sum(np.isfinite(r.T_eps) != np.isfinite(ref.T_eps)))
            print(f"| {name} | {label} | {cap * 0.01:g} | {r.n_steps.mean():.0f} | {r.n_steps.max()} | {wall:.2f} | "
                  f"{np.sum(~wrong) / wall:.3g} | {err.max():.2g} | {int(wrong.sum())} | {dT.max():.2g} | "
                  f"{int(np.sum(dT > 1e-3)) + disagree} |", flush=True)


if __name__ == "__main__":
    main()
