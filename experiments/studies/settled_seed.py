"""Where the 0.2 `balanced` gains' energy error comes from: the seed of the settled oscillation, not its resolution.

    python experiments/studies/settled_seed.py [--n 128] [--out docs/figures/settled_seed.json]

Under the 0.2 release's `balanced` gains (k = 0.001467) the settled (w2, p1) oscillation turns unstable near the target
(sigma from -0.85 to +1.24 /s) and grows from the transient's remainder, 1e-9 or less, to 1e-2: most of a 100 s
run's energy is spent by that growth, and its size hangs on the seed. On the README's starts (``readme_starts(n)``
of ``experiments/studies/preset_effort.py``, 100 s, eps 0.05) this runs `jaxsleigh.run_ensemble` against a float64
reference at rtol = atol = 1e-10 in these variants, each in a fresh process:

* ``float32``: every setting at its default;
* ``float64``: float64 at its defaults (rtol = atol = 1e-8);
* ``float32_guard_1e-10``, ``float64_guard_1e-10``: the same with the oscillation guard's absolute tolerance (where
  the pair is weakly damped, near the target) brought down to 1e-10 (`jaxsleigh.integrate.guard`'s ``ATOL_FLOOR``
  and ``ATOL_FACTOR``, set before the first run);
* ``float64_rtol_1e-10``: float64 at rtol = 1e-10, atol at its default; ``float64_atol_1e-10`` (and ``1e-9``): the
  other way round, the absolute tolerance everywhere; ``float32_atol_1e-10``: float32 with that absolute tolerance;
* ``float64_1e-12``: float64 at rtol = atol = 1e-12: how far the reference itself is from converged.

Printed and written per variant: the starts whose energy is more than 5% off the reference (their rows; also against
``float64_1e-12``, ``against_1e-12``), the largest relative difference, the energy percentiles 25/50/75/90 relative
to the reference's, the mean steps and the wall time.
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import ROOT, load, run_py  # noqa: E402
from studies.default_accuracy import BALANCED_02  # noqa: E402  (the 0.2 release's `balanced` gains)

#: variant -> (float64?, rtol, atol, guard's tightened atol or None)
VARIANTS = {
    "reference": (True, 1e-10, 1e-10, None),
    "float32": (False, None, None, None),
    "float64": (True, None, None, None),
    "float32_guard_1e-10": (False, None, None, 1e-10),
    "float64_guard_1e-10": (True, None, None, 1e-10),
    "float64_rtol_1e-10": (True, 1e-10, None, None),
    "float64_atol_1e-10": (True, None, 1e-10, None),
    "float64_atol_1e-9": (True, None, 1e-9, None),
    "float32_atol_1e-10": (False, None, 1e-10, None),
    "float64_1e-12": (True, 1e-12, 1e-12, None),
}

RUN = r"""
import json, sys, time
import numpy as np
import jaxsleigh as js
import jaxsleigh.integrate.guard as guard
sys.path.insert(0, sys.argv[1])
from studies.preset_effort import readme_starts
n, x64, rtol, atol, floor = int(sys.argv[2]), sys.argv[3] == "1", *(json.loads(a) for a in sys.argv[4:7])
if floor is not None:           # the guard's absolute tolerance where the pair is weakly damped: `floor` exactly
    guard.ATOL_FLOOR, guard.ATOL_FACTOR = floor, floor / (1e-8 if x64 else 1e-6)
budget = None if rtol is None and atol is None else 2 * 30 * 10000 + 1000
ss = js.StepSizeController(rtol=rtol, atol=atol, max_steps=budget)
t0 = time.perf_counter()
r = js.run_ensemble(readme_starts(n), gains=js.gains(**json.loads(sys.argv[7])), t_final=100.0, eps=0.05, x64=x64,
                    stepsize=ss, run=js.RunOptions(progress=False))
print(json.dumps({"u_energy": np.asarray(r.u_energy, np.float64).tolist(), "status": r.status.tolist(),
                  "n_steps": r.n_steps.tolist(), "wall_s": round(time.perf_counter() - t0, 1)}))
"""


def compare(run: dict, ref: dict) -> dict:
    e, er = np.array(run["u_energy"]), np.array(ref["u_energy"])
    ok = (np.array(run["status"]) == 0) & (np.array(ref["status"]) == 0)
    rel = np.abs(e[ok] / er[ok] - 1.0)
    off = np.flatnonzero(ok)[rel > 0.05]
    return {"n_compared": int(ok.sum()), "rows_off_5pct": off.tolist(), "share_off_5pct": float(off.size / ok.sum()),
            "max_rel": float(rel.max()),
            "percentiles_rel": {f"p{q}": float(np.percentile(e[ok], q) / np.percentile(er[ok], q) - 1.0)
                                for q in (25, 50, 75, 90)},
            "mean_steps": float(np.mean(run["n_steps"])), "wall_s": run["wall_s"]}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=128, help="README starts (default 128)")
    ap.add_argument("--out", default=str(ROOT / "docs" / "figures" / "settled_seed.json"))
    args = ap.parse_args(argv)
    here = str(ROOT / "experiments")
    out = {"command": "python experiments/studies/settled_seed.py" + "".join(f" {a}" for a in (argv or sys.argv[1:])),
           "gains": BALANCED_02, "starts": f"readme_starts({args.n})", "t_final": 100.0, "eps": 0.05,
           "machine": {"arch": platform.machine(), "python": platform.python_version()}, "load_start": load(),
           "variants": {}}
    runs = {name: run_py(RUN, (here, args.n, int(x64), json.dumps(rtol), json.dumps(atol), json.dumps(floor),
                               json.dumps(BALANCED_02)), {"PYTHONPATH": str(ROOT)})
            for name, (x64, rtol, atol, floor) in VARIANTS.items()}
    ref = runs["reference"]
    out["reference"] = {"mean_steps": float(np.mean(ref["n_steps"])), "wall_s": ref["wall_s"],
                        "status_not_ok": int(np.sum(np.array(ref["status"]) != 0))}
    for name, run in runs.items():
        if name == "reference":
            continue
        row = out["variants"][name] = compare(run, ref)
        if name != "float64_1e-12":          # also against the tighter float64 run
            row["against_1e-12"] = compare(run, runs["float64_1e-12"])
        tight = row.get("against_1e-12", {})
        print(f"{name:22s} off >5%: {len(row['rows_off_5pct']):3d} ({row['share_off_5pct']:.3f}) rows "
              f"{row['rows_off_5pct']}  max {row['max_rel']:.2f}  steps {row['mean_steps']:.0f}  {row['wall_s']} s"
              + (f"  | against 1e-12: {len(tight['rows_off_5pct'])} off, max {tight['max_rel']:.2f}" if tight else ""),
              flush=True)
    out["load_end"] = load()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
