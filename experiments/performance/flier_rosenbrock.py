r"""A linearly implicit step on the basin's fliers: the library's Rosenbrock pair, float32 and float64, against LSODA.

    python experiments/performance/flier_rosenbrock.py [--k 8] [--tol 1e-6] [--fliers docs/figures/flier_stiffness.json]
        [--out docs/figures/flier_rosenbrock.json]

The first ``--k`` fliers of ``--fliers`` (written by ``experiments/performance/flier_stiffness.py``: starts of the
default basin's sample that run long: the explicit step alone used up its budget of 2e5 attempts on them) are
integrated over 100 s in the w chart by the modified Rosenbrock pair of order 2(3) of Shampine and Reichelt
(MATLAB's ``ode23s``; SIAM J. Sci. Comput. 18(1), 1997) as the engine takes it,
`jaxsleigh.integrate.rosenbrock.rosenbrock_stages` (its module docstring has the formulas), here with a plain
controller of its own instead of the engine's: a step accepted where
\(\max_i |e_i| / (\mathrm{tol} (1 + \max(|y_i|, |y_{1,i}|))) \le 1\), the next \(h\) from the error to the power
1/3 (safety 0.9, factors 0.2 to 5). The step is jitted, the loop is on the host (one lane at a time: a measure of
steps, not of speed). Reported per flier and dtype: accepted and rejected steps, and |q(100)| against LSODA's
(float64, rtol = atol = 1e-8). `experiments/performance/flier_stiffness.py` measures the engine itself.
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

def rosenbrock_step(field_and_control, args):
    """One jitted step ``(y, h, tol) -> (y1, error ratio)`` of the library's pair for the vector field."""
    import jax
    import jax.numpy as jnp

    from jaxsleigh.integrate.rosenbrock import rosenbrock_stages

    @jax.jit
    def step(y, h, tol):
        f0, _ = field_and_control(0.0, y, args)
        dy, _, _, err, _ = rosenbrock_stages(field_and_control, 0.0, y, h, args, f0)
        y1 = y + dy
        return y1, jnp.max(jnp.abs(err) / (tol * (1.0 + jnp.maximum(jnp.abs(y), jnp.abs(y1)))))

    return step


def integrate(step, y0, t_final: float, tol: float, dtype, max_attempts: int = 200_000) -> dict:
    """The host loop of adaptive steps from ``y0`` over ``[0, t_final]``."""
    import jax
    import jax.numpy as jnp

    from jaxsleigh.model.closed_loop import state_from_w

    y, t, h, n, rej = jnp.asarray(y0, dtype), 0.0, 1e-6, 0, 0
    t0 = time.perf_counter()
    while t < t_final and n + rej < max_attempts:
        h = min(h, t_final - t)
        y1, e = step(y, jnp.asarray(h, dtype), jnp.asarray(tol, dtype))
        e = float(e)
        if np.isfinite(e) and e <= 1.0:
            y, t, n = y1, t + h, n + 1
        else:
            rej += 1
        h *= min(5.0, max(0.2, 0.9 * max(e, 1e-10) ** (-1.0 / 3.0))) if np.isfinite(e) else 0.2
    with jax.enable_x64(True):
        q = np.asarray(state_from_w(jnp.asarray(y, jnp.float64)))[:3]
    return {"t_end": round(t, 6), "steps": n, "rejected": rej, "abs_q_end": float(np.linalg.norm(q)),
            "wall_s": round(time.perf_counter() - t0, 2)}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--k", type=int, default=8)
    ap.add_argument("--tol", type=float, default=1e-6)
    ap.add_argument("--fliers", type=Path, default=ROOT / "docs/figures/flier_stiffness.json")
    ap.add_argument("--out", type=Path, default=ROOT / "docs/figures/flier_rosenbrock.json")
    a = ap.parse_args()
    info = machine()
    import jax
    import jax.numpy as jnp

    import jaxsleigh as js
    from jaxsleigh.model.closed_loop import ClosedLoop, state_to_w, vector_field_w_control

    src = json.loads(a.fliers.read_text())
    ics = js.sample_starts(src["n"], seed=src["seed"]).ics
    fliers = src["rows"][:a.k]
    with jax.enable_x64(True):
        y0s = [np.asarray(state_to_w(jnp.asarray(np.r_[ics[r["row"]], 0.0, 0.0], jnp.float64))) for r in fliers]
    rows = [{"row": r["row"], "theta0": r["theta0"], "engine_attempts": r["engine"]["attempts"],
             "engine_t_reached": r["engine"]["t_reached"], "LSODA_abs_q_end": r["LSODA"]["abs_q_end"]}
            for r in fliers]
    for name, x64 in (("float32", False), ("float64", True)):
        with jax.enable_x64(x64):
            dtype = jnp.float64 if x64 else jnp.float32
            args = jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype), ClosedLoop(js.paper_plant(),
                                                                                   js.paper_gains()))
            step = rosenbrock_step(vector_field_w_control, args)
            for row, y0 in zip(rows, y0s):
                res = integrate(step, y0, 100.0, a.tol, dtype)
                res["rel_diff_q_end_vs_LSODA"] = abs(res["abs_q_end"] - row["LSODA_abs_q_end"]) / row["LSODA_abs_q_end"]
                row[name] = res
                print(row["row"], name, json.dumps(res), flush=True)
    summary = {name: {"all_reach_100_s": all(r[name]["t_end"] >= 100.0 for r in rows),
                      "steps_range": [min(r[name]["steps"] for r in rows), max(r[name]["steps"] for r in rows)],
                      "rejected_range": [min(r[name]["rejected"] for r in rows), max(r[name]["rejected"] for r in rows)],
                      "max_rel_diff_q_end_vs_LSODA": max(r[name]["rel_diff_q_end_vs_LSODA"] for r in rows)}
               for name in ("float32", "float64")}
    out = {"command": "python experiments/performance/flier_rosenbrock.py " + " ".join(sys.argv[1:]),
           "dtype": "float32 and float64", "machine": info, "load": load(), "tol": a.tol,
           "method": "modified Rosenbrock 2(3) (Shampine and Reichelt 1997), jaxsleigh.integrate.rosenbrock.rosenbrock_stages, "
                     "w chart, host loop",
           "summary": summary, "rows": rows}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps(summary, indent=1), "->", a.out)


if __name__ == "__main__":
    main()
