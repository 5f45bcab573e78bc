r"""The default basin's fliers (the starts near theta = 0 that run long) are stiff: an implicit solver crosses their
100 s in a few thousand steps, and so does the engine once it switches them to its implicit step.

    python experiments/performance/flier_stiffness.py [--n 100000] [--seed 5] [--theta 2e-3] [--radau 3]
        [--out docs/figures/flier_stiffness.json]

1. The starts of the default basin's sample (`jaxsleigh.sample_starts`, ``--n``, ``--seed``) with
   ``|theta0| < --theta`` (where the fliers are) run by the engine at its defaults (float32, adaptive, 100 s, no
   certificate): status, attempted steps, the time reached and |q(100)|.
2. Each of those that takes more than ``STIFF_AFTER`` attempts (2e4: the engine then switches it to the linearly
   implicit Rosenbrock step, `jaxsleigh.integrate.rosenbrock`) or ends with status 4 (its budget of 2e5 attempts used
   up) integrated to 100 s by SciPy's LSODA (float64, rtol = atol = 1e-8, the w chart, the Jacobian from JAX), the
   ``--radau`` first of them also by Radau (the same tolerances): steps, function evaluations, seconds, the distance
   |q(100)| to the target (the ball is 0.05), and the engine's relative difference from it.

What it shows: the explicit step alone reached about 1 s of these flights in 2e5 attempts (the engine before the
switch: status 4 for 38 of the 43 starts), where the implicit solvers cross the whole 100 s in ~2e3 steps and agree
on where the sleigh ends; with the switch the engine crosses it too, and ends where they do.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import ROOT, load, machine  # noqa: E402


def implicit(method: str, f, jac, y0, t_final: float) -> dict:
    """``method`` (a stiff SciPy solver) on the w-chart closed loop from ``y0`` to ``t_final`` (in float64)."""
    from scipy.integrate import solve_ivp

    from jaxsleigh.model.closed_loop import state_from_w

    t0 = time.perf_counter()
    s = solve_ivp(lambda t, y: np.asarray(f(t, y)), (0.0, t_final), y0, method=method, rtol=1e-8, atol=1e-8,
                  jac=lambda t, y: np.asarray(jac(t, y)))
    q = np.asarray(state_from_w(s.y[:, -1]))[:3]
    return {"status": int(s.status), "t_end": float(s.t[-1]), "steps": int(s.t.size - 1), "nfev": int(s.nfev),
            "wall_s": round(time.perf_counter() - t0, 2), "abs_q_end": float(np.linalg.norm(q))}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--theta", type=float, default=2e-3)
    ap.add_argument("--radau", type=int, default=3)
    ap.add_argument("--out", type=Path, default=ROOT / "docs/figures/flier_stiffness.json")
    a = ap.parse_args()
    info = machine()
    import jax
    import jax.numpy as jnp

    import jaxsleigh as js
    from jaxsleigh.integrate.engine import STIFF_AFTER
    from jaxsleigh.model.closed_loop import ClosedLoop, state_to_w, vector_field_w

    ics = js.sample_starts(a.n, seed=a.seed).ics
    near = np.flatnonzero(np.abs(ics[:, 2]) < a.theta)
    t0 = time.perf_counter()
    r = js.run_ensemble(ics[near], t_final=100.0, run=js.RunOptions(progress=False, audit=False))
    engine_s = time.perf_counter() - t0
    attempts = np.asarray(r.n_steps) + np.asarray(r.n_rejected)
    rows = []
    with jax.enable_x64(True):
        args = ClosedLoop(js.paper_plant(), js.paper_gains())
        z = (0.0, jnp.zeros(5))
        f = jax.jit(lambda t, y: vector_field_w(t, y, args)).lower(*z).compile()
        jac = jax.jit(jax.jacfwd(lambda t, y: vector_field_w(t, y, args), argnums=1)).lower(*z).compile()
        for k in np.flatnonzero((np.asarray(r.status) == js.Status.BUDGET_EXHAUSTED) | (attempts > STIFF_AFTER)):
            start = ics[near[k]]
            y0 = np.asarray(state_to_w(jnp.asarray(np.r_[start, 0.0, 0.0], jnp.float64)))
            q_end = float(np.linalg.norm(np.asarray(r.q_final)[k]))
            row = {"row": int(near[k]), "theta0": float(start[2]),
                   "engine": {"status": int(np.asarray(r.status)[k]), "attempts": int(attempts[k]),
                              "t_reached": float(np.asarray(r.t_reached)[k]), "abs_q_end": q_end},
                   "LSODA": implicit("LSODA", f, jac, y0, 100.0)}
            if len(rows) < a.radau:
                row["Radau"] = implicit("Radau", f, jac, y0, 100.0)
            for ref in ("LSODA", "Radau"):
                if ref in row:
                    row["engine"][f"rel_diff_vs_{ref}"] = abs(q_end - row[ref]["abs_q_end"]) / row[ref]["abs_q_end"]
            rows.append(row)
            print(json.dumps(row), flush=True)
    status, counts = np.unique(np.asarray(r.status), return_counts=True)
    lsoda = [x["LSODA"] for x in rows]
    out = {"command": "python experiments/performance/flier_stiffness.py " + " ".join(sys.argv[1:]),
           "dtype": "engine float32 (defaults); SciPy float64", "machine": info, "load": load(),
           "starts": f"jaxsleigh.sample_starts({a.n}, seed={a.seed}) with |theta0| < {a.theta:g}: {near.size}",
           "n": a.n, "seed": a.seed,
           "engine_status": {int(s): int(c) for s, c in zip(status, counts)}, "engine_wall_s": round(engine_s, 2),
           "fliers": len(rows),
           "stiff_after": STIFF_AFTER,
           "summary": {"engine_t_reached_max": max((x["engine"]["t_reached"] for x in rows), default=None),
                       "engine_reached_100_s": sum(x["engine"]["t_reached"] >= 100.0 for x in rows),
                       "engine_attempts_range": [min((x["engine"]["attempts"] for x in rows), default=None),
                                                 max((x["engine"]["attempts"] for x in rows), default=None)],
                       "engine_max_rel_diff_vs_LSODA": max((x["engine"]["rel_diff_vs_LSODA"] for x in rows),
                                                           default=None),
                       "engine_max_rel_diff_vs_Radau": max((x["engine"].get("rel_diff_vs_Radau", 0.0) for x in rows),
                                                           default=None),
                       "LSODA_steps_median": float(np.median([x["steps"] for x in lsoda])) if lsoda else None,
                       "LSODA_steps_max": max((x["steps"] for x in lsoda), default=None),
                       "LSODA_reached_100_s": all(x["status"] == 0 for x in lsoda),
                       "settle_within_100_s": sum(x["abs_q_end"] <= 0.05 for x in lsoda),
                       "abs_q_end_min": min((x["abs_q_end"] for x in lsoda), default=None)},
           "rows": rows}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps(out["summary"]), "->", a.out)


if __name__ == "__main__":
    main()
