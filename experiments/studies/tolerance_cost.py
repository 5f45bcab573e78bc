r"""What a looser tolerance buys and costs: steps against the error of T_eps, energy and final state.

    python experiments/studies/tolerance_cost.py [--n 1024] [--tols 1e-6,2e-6,3e-6,1e-5]
                                                 [--out docs/figures/tolerance_cost.json]

The paper's closed loop, 100 s, eps = 0.05, on two held-out distributions: ``basin`` (`jaxsleigh.sample_starts`,
seed 5: the default basin's starts, some of them near theta = 0) and ``wide`` (``WideStarts``: |x|, |y| <= 4, one
in eight |theta0| below 0.3, momentum for half; ``experiments/studies/preset_effort.py``). Each is run by
`jaxsleigh.run_ensemble`

* as the reference: float64 at rtol = atol = 1e-10;
* in float32 at rtol = atol = each of ``--tols`` (the first is the float32 default);
* in float64 at the float32 default's tolerance: the same tolerance in another precision, which tells the
  integrator's truncation error from float32's rounding.

Per run (the starts whose status is OK in both it and the reference): the mean attempted steps (the cost in steps:
at this size compilation and the few starts near theta = 0 decide the wall time, and what fewer steps buy a large
basin in time is measured on the accuracy page), the signed difference of T_eps from the reference over the starts
that settle in both (mean, median, 1st and 99th percentiles, the largest in size, how many are more than 1e-3 s
off), how many starts settle in one and not the other, the relative energy difference (99th percentile, largest, the
share more than 5% off) and the final position's distance from the reference's, relative where the reference ends
more than 1 m away (median, largest). Machine, dtype and command are in the JSON.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import load, machine  # noqa: E402
from studies.preset_effort import wide_starts  # noqa: E402


def starts(dist: str, n: int) -> np.ndarray:
    import jaxsleigh as js

    return js.sample_starts(n, seed=5).ics if dist == "basin" else wide_starts(n)


def run(ics, *, x64: bool, tol: float):
    """The 100 s ensemble of ``ics`` at rtol = atol = ``tol``."""
    import jaxsleigh as js

    return js.run_ensemble(ics, t_final=100.0, eps=0.05, x64=x64, stepsize=js.StepSizeController(rtol=tol, atol=tol),
                           run=js.RunOptions(progress=False, audit=False))


def compare(r, ref) -> dict:
    """The figures of one run against the reference (module docstring)."""
    ok = (np.asarray(r.status) == 0) & (np.asarray(ref.status) == 0)
    t, tr = np.asarray(r.T_eps, np.float64), np.asarray(ref.T_eps, np.float64)
    both = ok & np.isfinite(t) & np.isfinite(tr)
    d = t[both] - tr[both]
    e = np.abs(np.asarray(r.u_energy, np.float64)[ok] / np.asarray(ref.u_energy, np.float64)[ok] - 1.0)
    qr = np.asarray(ref.q_final, np.float64)[ok, :2]
    q = np.linalg.norm(np.asarray(r.q_final, np.float64)[ok, :2] - qr, axis=1)
    q = q / np.maximum(1.0, np.linalg.norm(qr, axis=1))
    one_only = ok & (np.isfinite(t) != np.isfinite(tr))
    return {"mean_steps": round(float(np.mean(r.n_steps)), 1), "compared": int(ok.sum()),
            "settled_both": int(both.sum()), "settled_in_one_only": int(one_only.sum()),
            "T_eps_diff_s": {"mean": float(d.mean()), "median": float(np.median(d)), "p1": float(np.percentile(d, 1)),
                             "p99": float(np.percentile(d, 99)), "largest": float(np.abs(d).max()),
                             "over_1e-3": int((np.abs(d) > 1e-3).sum())},
            "energy_rel": {"p99": float(np.percentile(e, 99)), "largest": float(e.max()),
                           "share_over_5pct": float((e > 0.05).mean())},
            "final_position": {"median": float(np.median(q)), "largest": float(q.max())}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=1024)
    ap.add_argument("--tols", default="1e-6,2e-6,3e-6,1e-5")
    ap.add_argument("--dists", default="basin,wide")
    ap.add_argument("--out", default="docs/figures/tolerance_cost.json")
    a = ap.parse_args(argv)
    tols = [float(x) for x in a.tols.split(",")]
    given = sys.argv[1:] if argv is None else argv
    res = {"command": " ".join(["python experiments/studies/tolerance_cost.py", *given]),
           "machine": machine(), "dtype": "float32 (the runs), float64 (the reference, and the run so marked)",
           "law": "paper's gains", "n": a.n, "load_start": load(), "dists": {}}
    for dist in a.dists.split(","):
        ics = starts(dist, a.n)
        ref = run(ics, x64=True, tol=1e-10)
        rows = {}
        for x64, tol in [(False, t) for t in tols] + [(True, tols[0])]:
            rows[f"{'float64' if x64 else 'float32'} {tol:g}"] = row = compare(run(ics, x64=x64, tol=tol), ref)
            print(dist, "float64" if x64 else "float32", tol, json.dumps(row), file=sys.stderr, flush=True)
        res["dists"][dist] = {"reference": "float64, rtol = atol = 1e-10",
                              "reference_status_counts": {int(k): int(v) for k, v in
                                                          zip(*np.unique(np.asarray(ref.status), return_counts=True))},
                              "runs": rows}
    res["load_end"] = load()
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(res, indent=1) + "\n")
    print(f"wrote {a.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
