"""Accuracy near the singular set against an independent stiff reference.

For starts with |x|, |y| <= 5 and |theta0| from 1e-1 down to 1e-3, integrate with jaxsleigh's
default (adaptive) method and with scipy's Radau (rtol = atol = 1e-10, float64, physical chart,
Jacobian by jax.jacfwd), and report the final position error relative to the trajectory's largest
excursion, the status and the steps used. Radau needs ~1e6 evaluations per 2 s at theta0 = 1e-3,
so the horizon shrinks there (--t-final-tiny).

    python experiments/studies/near_singular_accuracy.py [--n-per 3] [--t-final 100] [--t-final-tiny 2]
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from scipy.integrate import solve_ivp

import jaxsleigh as js
from jaxsleigh.model.closed_loop import ClosedLoop, vector_field
from jaxsleigh.studies.ensemble import run_ensemble


def radau(y0, t_final):
    with jax.enable_x64(True):
        args = ClosedLoop(js.paper_plant(), js.paper_gains())
        f = jax.jit(lambda y: vector_field(0.0, y, args))
        jac = jax.jit(jax.jacfwd(lambda y: vector_field(0.0, y, args)))
        t0 = time.perf_counter()
        sol = solve_ivp(lambda t, y: np.asarray(f(jnp.asarray(y))), (0.0, t_final), np.asarray(y0, float),
                        method="Radau", rtol=1e-10, atol=1e-10, jac=lambda t, y: np.asarray(jac(jnp.asarray(y))))
    return sol.y[:, -1], sol.nfev, time.perf_counter() - t0, sol.status


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n-per", type=int, default=3, help="starts per theta0 (default 3)")
    ap.add_argument("--t-final", type=float, default=100.0)
    ap.add_argument("--t-final-tiny", type=float, default=2.0, help="horizon at |theta0| = 1e-3")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--thetas", default="1e-1,3e-2,1e-2,3e-3,1e-3", help="comma list of |theta0|")
    ap.add_argument("--out", default="out/near_singular_accuracy.json")
    a = ap.parse_args()
    rng = np.random.default_rng(a.seed)
    rows = []
    print("| theta0 | start (x, y) | T [s] | dtype | status | steps | error / max excursion | max excursion [m] | Radau nfev |")
    print("|---|---|---|---|---|---|---|---|---|")
    for th in (float(v) for v in a.thetas.split(",")):
        T = a.t_final if th > 1.5e-3 else a.t_final_tiny
        for _ in range(a.n_per):
            x, y = rng.uniform(-5, 5, 2)
            sgn = rng.choice([-1.0, 1.0])
            ic = np.array([x, y, sgn * th])
            ref, nfev, wall_ref, st = radau(np.r_[ic, 0, 0], T)
            for x64 in (True, False):
                r = run_ensemble(ic[None], t_final=T, x64=x64, stepsize=js.StepSizeController(max_steps=5_000_000),
                                 run=js.RunOptions(progress=False))
                rel = float(np.abs(r.q_final[0] - ref[:3]).max() / r.max_excursion[0])
                row = dict(theta0=float(sgn * th), x=float(x), y=float(y), t_final=T, dtype=r.settings["dtype"],
                           status=int(r.status[0]), steps=int(r.n_steps[0]), rel_error=rel,
                           max_excursion=float(r.max_excursion[0]), radau_nfev=int(nfev), radau_status=int(st))
                rows.append(row)
                print(f"| {sgn * th:+.0e} | ({x:.2f}, {y:.2f}) | {T:g} | {row['dtype']} | {row['status']} | "
                      f"{row['steps']} | {rel:.1e} | {row['max_excursion']:.3g} | {nfev} |", flush=True)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    from jaxsleigh.studies.bench import machine
    Path(a.out).write_text(json.dumps({"rows": rows, "machine": machine()}, indent=1))


if __name__ == "__main__":
    main()
