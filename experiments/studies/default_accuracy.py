"""Are the defaults right for every law? float32 at the default tolerances against a float64 reference.

    python experiments/studies/default_accuracy.py [--n 256] [--laws paper,balanced,...] [--also COMMIT]
                                                   [--out docs/figures/default_accuracy.json]

For every law (the gain presets ``paper``, ``balanced``, ``tuned``; the 0.2 release's ``balanced`` gains, whose
settled phase oscillates, as ``balanced_0.2``; every controller of ``jaxsleigh controllers``: ``shaped``,
``aicardi``, ``astolfi``, ``samson``) and two held-out distributions of starts (``readme``: the README's, and
``wide``: |x|, |y| <= 4, |theta0| in (0.05, pi) with one in eight below 0.3, momentum for half; see
``experiments/studies/preset_effort.py``), `jaxsleigh.run_ensemble` runs 100 s (eps 0.05) twice:

* ``default``: float32, every setting at its default (what a user gets);
* ``reference``: float64 at rtol = atol = 1e-10, twice the step budget.

Printed and written as JSON, per law and distribution: the energy percentiles 25/50/75/90 of both (over the starts
that reached the horizon in both) and their worst relative difference; the share of starts whose energy is more
than 5% off; the median T_0.05 of both; the settled fraction of both; the mean accepted steps of the default run.
A start whose reference spent its step budget (no answer to compare with) is not judged; the rows say how many.
As in the accuracy audit, a start off its 1e-10 reference is run again at 1e-12, and that run is its reference
(``reference_confirmed_at_1e-12`` counts them): at 1e-10 Aicardi's float64 chatters at the target.
The criteria (all must hold): percentiles within 2%, fewer than 2% of starts more than 5% off, median T_0.05 within
0.05 s, settled fraction within 0.005. ``--also COMMIT`` runs the default column again with that commit's library
(a git worktree) in the same run, for a before/after comparison.
"""
from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import ROOT, baseline_tree, load, run_py  # noqa: E402

LAWS = ("paper", "balanced", "tuned", "balanced_0.2", "shaped", "aicardi", "astolfi", "samson")
QS = (25, 50, 75, 90)
#: the 0.2 release's `balanced` gains (k = 0.001467): settled starts oscillate, the case float32's default atol missed
BALANCED_02 = {"L": [2.153, 1.742, 2.492], "k": 0.001467, "D_hat": [[2.565, -0.0328], [-0.0328, 10.824]]}

#: one run in a fresh process: law, distribution, n, dtype mode; prints the per-start arrays as JSON
RUN = r"""
import json, sys
import numpy as np
import jaxsleigh as js                     # first: the library on PYTHONPATH (this tree's, or --also's commit)
sys.path.insert(0, sys.argv[5])
from studies.preset_effort import readme_starts, wide_starts
law, dist, n, mode = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4]
ics = (readme_starts if dist == "readme" else wide_starts)(n)
if len(sys.argv) > 7:                      # only these rows (the confirmation of rows off the 1e-10 reference)
    ics = ics[json.loads(sys.argv[7])]
B02 = json.loads(sys.argv[6])
if law in ("paper", "balanced", "tuned"):
    spec = {"gains": law}
elif law == "balanced_0.2":
    spec = {"gains": js.gains(**B02)}
else:
    from jaxsleigh.controllers.registry import make_controller
    spec = {"controller": make_controller(law)}
kw = {}
if mode.startswith("reference"):
    tol = 1e-12 if mode == "reference_confirm" else 1e-10
    kw = dict(x64=True, stepsize=js.StepSizeController(rtol=tol, atol=tol, max_steps=2 * 30 * 10000 + 1000))
r = js.run_ensemble(ics, t_final=100.0, eps=0.05, run=js.RunOptions(progress=False), **spec, **kw)
f = lambda a: [None if not np.isfinite(v) else float(v) for v in np.asarray(a, np.float64).ravel()]
print(json.dumps({"status": [int(s) for s in r.status], "T_eps": f(r.T_eps), "u_energy": f(r.u_energy),
                  "n_steps": [int(s) for s in r.n_steps], "q_final": f(r.q_final),
                  "audit": (r.run_info or {}).get("audit")}))
"""


def _arr(xs):
    return np.array([np.nan if v is None else v for v in xs], np.float64)


def confirm(d: dict, ref: dict, rerun) -> tuple:
    """As the accuracy audit (`jaxsleigh.studies.audit`): the rows whose default run is off the 1e-10 reference
    (energy more than 5%, T_0.05 more than 0.05 s, or settled in one only) are run again at rtol = atol = 1e-12,
    and that run, where it finished, is the reference for them: at 1e-10 some laws' float64 is itself wrong
    (Aicardi's chatters at the target and never settles; at 1e-12 it settles as float32 does). Returns the
    reference and the number of rows taken from 1e-12."""
    e, er = _arr(d["u_energy"]), _arr(ref["u_energy"])
    T, Tr = _arr(d["T_eps"]), _arr(ref["T_eps"])
    with np.errstate(invalid="ignore", divide="ignore"):
        off = ((np.abs(e / er - 1.0) > 0.05) | (np.isfinite(T) != np.isfinite(Tr))
               | (np.abs(np.where(np.isfinite(T) & np.isfinite(Tr), T - Tr, 0.0)) > 0.05))
    rows = [int(i) for i in np.nonzero(off & (np.array(ref["status"]) == 0))[0]]
    if not rows:
        return ref, 0
    tight = rerun(rows)
    ref = {k: (list(v) if isinstance(v, list) else v) for k, v in ref.items()}
    taken = 0
    for j, i in enumerate(rows):
        if tight["status"][j] == 0:
            taken += 1
            ref["status"][i], ref["T_eps"][i], ref["u_energy"][i] = (tight["status"][j], tight["T_eps"][j],
                                                                   tight["u_energy"][j])
    return ref, taken


def compare(d: dict, ref: dict) -> dict:
    """The default run ``d`` against the reference ``ref`` (per-start arrays of one law and distribution). A start
    whose reference did not finish (its step budget spent: no answer to compare with) is not judged, as in the
    accuracy audit; it is counted in ``n_reference_unfinished``."""
    judged = np.array(ref["status"]) == 0
    ok = (np.array(d["status"]) == 0) & judged
    e, er = _arr(d["u_energy"])[ok], _arr(ref["u_energy"])[ok]
    T, Tr = _arr(d["T_eps"])[judged], _arr(ref["T_eps"])[judged]
    T = np.where(np.isnan(T), np.inf, T)
    Tr = np.where(np.isnan(Tr), np.inf, Tr)
    pct = {f"p{q}": [float(np.percentile(e, q)), float(np.percentile(er, q))] for q in QS}
    worst = max(abs(a / b - 1.0) for a, b in pct.values())
    rel = np.abs(e / er - 1.0)
    both = np.isfinite(T) & np.isfinite(Tr)
    med, med_r = float(np.median(T)), float(np.median(Tr))
    out = {
        "n": len(d["status"]), "n_compared": int(ok.sum()), "n_reference_unfinished": int((~judged).sum()),
        "energy_percentiles_default_vs_reference": pct,
        "energy_percentile_worst_rel": worst,
        "share_energy_off_5pct": float(np.mean(rel > 0.05)),
        "energy_rel_max": float(rel.max()),
        "T_median": [med if math.isfinite(med) else None, med_r if math.isfinite(med_r) else None],
        "T_median_diff_s": abs(med - med_r) if math.isfinite(med) and math.isfinite(med_r) else
                           (0.0 if med == med_r else None),
        "T_eps_max_diff_s_both_settled": float(np.max(np.abs(T[both] - Tr[both]))) if both.any() else None,
        "settled_fraction": [float(np.mean(np.isfinite(T))), float(np.mean(np.isfinite(Tr)))],
        "mean_steps": float(np.mean(d["n_steps"])),
        "audit": d.get("audit"),
    }
    out["passes"] = bool(worst <= 0.02 and out["share_energy_off_5pct"] < 0.02
                         and (out["T_median_diff_s"] is not None and out["T_median_diff_s"] <= 0.05)
                         and abs(out["settled_fraction"][0] - out["settled_fraction"][1]) <= 0.005)
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=256, help="starts per distribution (default 256)")
    ap.add_argument("--laws", default=",".join(LAWS))
    ap.add_argument("--dists", default="readme,wide")
    ap.add_argument("--also", default=None, help="also run the default column with this commit's library")
    ap.add_argument("--out", default=str(ROOT / "docs" / "figures" / "default_accuracy.json"))
    ap.add_argument("--merge", action="store_true",
                    help="replace these rows in an existing --out and keep its others (each row names its command)")
    args = ap.parse_args(argv)
    here = str(ROOT / "experiments")
    env_now = {"PYTHONPATH": str(ROOT)}
    base = baseline_tree(args.also) if args.also else None
    out = {"command": "python experiments/studies/default_accuracy.py" + "".join(f" {a}" for a in (argv or sys.argv[1:])),
           "dtype": "float32 (default) against float64 at rtol = atol = 1e-10 (reference)",
           "machine": {"arch": platform.machine(), "python": platform.python_version()}, "load_start": load(),
           "t_final": 100.0, "eps": 0.05, "rows": {}}
    if args.merge and Path(args.out).exists():
        old = json.loads(Path(args.out).read_text())
        out["rows"] = {k: dict(v, command=v.get("command", old["command"])) for k, v in old["rows"].items()}
        if isinstance(old.get("partial"), str) or old.get("earlier_rows"):   # rows parsed from an interrupted run
            out["earlier_rows"] = old.get("earlier_rows") or old["partial"]
    for dist in args.dists.split(","):
        for law in args.laws.split(","):
            t0 = time.perf_counter()
            d = run_py(RUN, (law, dist, args.n, "default", here, json.dumps(BALANCED_02)), env_now)
            t1 = time.perf_counter()
            ref = run_py(RUN, (law, dist, args.n, "reference", here, json.dumps(BALANCED_02)), env_now)
            ref, confirmed = confirm(d, ref, lambda rows: run_py(
                RUN, (law, dist, args.n, "reference_confirm", here, json.dumps(BALANCED_02), json.dumps(rows)), env_now))
            row = compare(d, ref)
            row["reference_confirmed_at_1e-12"] = confirmed
            row["wall_s_default"] = round(t1 - t0, 1)
            row["command"] = out["command"]
            if base is not None:
                old = run_py(RUN, (law, dist, args.n, "default", here, json.dumps(BALANCED_02)),
                             {"PYTHONPATH": str(base)})
                row["before"] = {k: v for k, v in compare(old, ref).items() if k != "audit"}
            out["rows"][f"{law}/{dist}"] = row
            print(f"{law:13s} {dist:6s} worst pct {row['energy_percentile_worst_rel']:.3f}  "
                  f">5%: {row['share_energy_off_5pct']:.3f}  dT50 {row['T_median_diff_s']}  "
                  f"settled {row['settled_fraction']}  steps {row['mean_steps']:.0f}  "
                  f"{'PASS' if row['passes'] else 'FAIL'}"
                  + (f"  | before: worst {row['before']['energy_percentile_worst_rel']:.3f} "
                     f">5% {row['before']['share_energy_off_5pct']:.3f} steps {row['before']['mean_steps']:.0f}"
                     if base is not None else ""), flush=True)
    out["load_end"] = load()
    out["partial"] = len(out["rows"]) < len(LAWS) * 2
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
