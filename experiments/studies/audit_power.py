r"""Does a run with a tail of unresolved rows say so? And what does the audit cost?

    python experiments/studies/audit_power.py [--n-tail 256] [--n-held 128] [--n-base 512] [--draws 2000]
        [--cost-n 512,4096] [--reps 3] [--cost-law paper] [--law aicardi --n-law 128 --law-seeds 20240611,7]
        [--share-laws aicardi,astolfi,samson,paper --share-n 500,4096,16384]
        [--out docs/figures/audit_power.json]

**Power.** The 0.2 release's ``balanced`` gains (k = 0.001467) let the settled (w2, p1) oscillation grow from a seed
below every tolerance; on the README's starts (``readme_starts``) the float32 energy of some rows is more than 5% off
the float64 reference (rtol = atol = 1e-10): those rows are the tail. This script runs

* ``tail``: ``n_tail`` README starts under those gains (float32, defaults) and their float64 reference, and
  ``held``: ``n_held`` other README starts (seed 7) the same way, which the flag's threshold was not read from;
* ``base``: ``n_base`` README starts (seed 11) under the paper's gains, float32, defaults: rows without a tail.

A row's result, and so its flag (``result.unresolved``), is its own: each row is a lane of its own, whose bits do not
depend on its batch (``LaneRules(bitwise=True)``, the default). So runs of N = 512 rows with a tail of a given share
are assembled from these rows, ``draws`` times per share: the tail rows drawn from the rows more than 5% off, the
rest from ``base``, shuffled. A run *says so* when one of its rows is flagged or its audit re-runs an off row (the
audit's sample, `jaxsleigh.studies.audit.audit_sample`, takes the flagged rows first; its size here is what the
budget leaves at the default 10% of the run, from the rows' own steps). The audit before the flags re-ran
``rng(0).choice(N, 6)``: it said so only where that draw held a tail row.

**Other laws** (``--other-laws``): the presets ``balanced``, ``tuned``, ``shaped``, the paper's gains and the
literature's laws (``aicardi``, ``astolfi``, ``samson``, `jaxsleigh.controllers`) on ``n_other`` README starts (seed
7), float32 defaults against float64 at 1e-10 (1e-12, then 1e-13, where that disagrees, as the audit confirms): the rows more
than 2% and 5% off, the rows flagged, and the largest difference of a row not flagged.

**A law's own tail** (``--law aicardi``): the law on ``n_law`` README starts of each of ``law_seeds``, float32
defaults against float64 at 1e-10, rows more than 2% off confirmed at 1e-12 and then 1e-13 (as the audit does): the off rows (> 5%)
and, for each cheap per-row quantity the run reports (``RISK_QUANTITIES``), the ranks of the off rows when the rows
are ordered by it (1: first; ties broken against the off rows). Then runs of ``n_run`` (and 4,096) rows of that law with a 2% and
a 5% tail of off rows (the rest its rows that agree, all seeds pooled) are assembled ``draws`` times, and the share of
runs in which the audit's sample (`audit_sample`, the default budget, from the rows' own steps) holds an off row is
reported for the sample's seeded order (what the library does) and for an order by each quantity, and how many rows
the budget let the audit re-run. The law's rows are never flagged (it has no settled pair), so only the sample can
say so.

**Cost.** Warm (every configuration run once before it is timed; medians of ``reps``): the paper's gains on README
starts with ``audit=False`` and with the default audit, for each N in ``cost_n``, and the plain fixed-step path
(``SaveAt(summaries=False)``, RK4, no passivity check) of 4,096 starts both ways, each first in turn. Reported: the audit's own
``wall_s`` and ``share_of_run`` (its record), its line and ``coverage``, and the wall time of the whole call with the
audit over that without. ``--cost-law aicardi``: the same for another law (without the fixed-step path).

**Share per law** (``--share-laws aicardi,astolfi,samson,paper --share-n 500,4096,16384``): each law's default run
(audit on, README starts of seed 11, 100 s), warm, ``reps`` times: the run's ``wall_s`` and the audit's rows,
reference, ``wall_s``, ``share_of_run``, rows judged and not finished (its record), without runs of the audit off.
"""
from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import load  # noqa: E402
from studies.default_accuracy import BALANCED_02  # noqa: E402
from studies.preset_effort import readme_starts  # noqa: E402


def _run(ics, **kw):
    import jaxsleigh as js

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return js.run_ensemble(ics, t_final=100.0, eps=0.05, **kw)


def tail_set(n: int, seed: int) -> dict:
    """The 0.2 gains on ``n`` README starts: float32 defaults against float64 at 1e-10; per row the relative energy
    difference, the flag and the run's steps."""
    import jaxsleigh as js

    ics = readme_starts(n, seed=seed)
    g = js.gains(**BALANCED_02)
    t0 = time.perf_counter()
    r = _run(ics, gains=g, run=js.RunOptions(progress=False, audit=False))
    wall = time.perf_counter() - t0
    ref = _run(ics, gains=g, x64=True, run=js.RunOptions(progress=False, audit=False),
               stepsize=js.StepSizeController(rtol=1e-10, atol=1e-10, max_steps=10**6))
    ok = (r.status == 0) & (ref.status == 0)
    rel = np.where(ok, np.abs(r.u_energy / ref.u_energy - 1.0), 0.0)
    off = rel > 0.05
    return {"n": n, "seed": seed, "wall_s_cold": round(wall, 1), "rel": rel, "off": off, "flag": r.unresolved,
            "steps": r.n_steps.astype(np.float64),
            "summary": {"rows_off_5pct": int(off.sum()), "flagged": int(r.unresolved.sum()),
                        "off_and_flagged": int((off & r.unresolved).sum()),
                        "off_2pct": int((rel > 0.02).sum()), "off_2pct_and_flagged": int(((rel > 0.02) & r.unresolved).sum()),
                        "largest_unflagged_rel": float(rel[~r.unresolved].max())}}


def power(tail: list, base: dict, n_run: int, shares, draws: int) -> dict:
    from jaxsleigh.studies.audit import Audit, audit_sample

    off_flag = np.concatenate([t["flag"][t["off"]] for t in tail])
    off_steps = np.concatenate([t["steps"][t["off"]] for t in tail])
    rng = np.random.default_rng(2024)
    out = {}
    old_rows = np.random.default_rng(0).choice(n_run, size=Audit().count(n_run), replace=False)
    for share in shares:
        m = max(1, round(share * n_run))
        said_new = said_old = by_flag = audited = 0
        for _ in range(draws):
            ti = rng.integers(0, off_flag.size, m)
            bi = rng.choice(base["flag"].size, n_run - m, replace=False)
            flag = np.concatenate([off_flag[ti], base["flag"][bi]])
            steps = np.concatenate([off_steps[ti], base["steps"][bi]])
            is_off = np.concatenate([np.ones(m, bool), np.zeros(n_run - m, bool)])
            perm = rng.permutation(n_run)
            flag, steps, is_off = flag[perm], steps[perm], is_off[perm]
            rows = audit_sample(Audit(), n_run, unresolved=flag, steps=steps)
            f, a = bool(np.any(flag)), bool(np.any(is_off[rows]))
            by_flag += f
            audited += a
            said_new += f or a
            said_old += bool(np.any(is_off[old_rows]))
        out[f"{share:g}"] = {"tail_rows": m, "said_so": said_new / draws, "by_flag": by_flag / draws,
                             "audit_reran_a_tail_row": audited / draws, "old_audit_said_so": said_old / draws}
    return out


def other_laws(names, n: int) -> dict:
    import jaxsleigh as js
    from jaxsleigh.controllers.registry import make_controller

    ics = readme_starts(n, seed=7)
    out = {}
    for name in names:
        law = ({"gains": name} if name in ("balanced", "tuned") else {} if name == "paper"
               else {"controller": js.load_shaped("shaped")} if name == "shaped"
               else {"controller": make_controller(name)})
        t0 = time.perf_counter()
        r = _run(ics, **law, run=js.RunOptions(progress=False, audit=False))
        wall = time.perf_counter() - t0

        def ref(rows, tol, law=law):
            return _run(ics[rows], **law, x64=True, run=js.RunOptions(progress=False, audit=False),
                        stepsize=js.StepSizeController(rtol=tol, atol=tol, max_steps=10**6))
        rows = np.arange(n)
        e = ref(rows, 1e-10)
        rel = np.where((r.status == 0) & (e.status == 0), np.abs(r.u_energy / e.u_energy - 1.0), 0.0)
        for tol in (1e-12, 1e-13):                       # confirmed at 1e-12, then 1e-13, as the audit does
            again = np.flatnonzero(rel > 0.02)
            if again.size:
                e12 = ref(again, tol)
                ok = (e12.status == 0) & (r.status[again] == 0)
                rel[again] = np.where(ok, np.abs(r.u_energy[again] / e12.u_energy - 1.0), rel[again])
        f = r.unresolved
        out[name] = {"rows": n, "off_2pct": int((rel > 0.02).sum()), "off_5pct": int((rel > 0.05).sum()),
                     "flagged": int(f.sum()), "off_2pct_not_flagged": int(((rel > 0.02) & ~f).sum()),
                     "largest_rel_not_flagged": float(rel[~f].max()), "float32_wall_s_cold": round(wall, 1)}
        print(name, json.dumps(out[name]), flush=True)
    return out


#: cheap per-row quantities a run reports, each oriented so that a larger value is meant to be more at risk
RISK_QUANTITIES = {
    "n_steps": lambda r: r["n_steps"], "-n_steps": lambda r: -r["n_steps"],
    "n_rejected": lambda r: r["n_rejected"], "rejected_share": lambda r: r["n_rejected"] / np.maximum(r["n_steps"], 1),
    "T_eps": lambda r: r["T_eps"], "time_near_target": lambda r: -r["T_eps"],
    "u_energy": lambda r: r["u_energy"], "-u_energy": lambda r: -r["u_energy"], "u_norm_peak": lambda r: r["u_norm_peak"],
    "min_abs_theta": lambda r: r["min_abs_theta"], "-min_abs_theta": lambda r: -r["min_abs_theta"],
    "final_xy": lambda r: r["xy"], "-final_xy": lambda r: -r["xy"],
    "final_abs_theta": lambda r: r["th"], "-final_abs_theta": lambda r: -r["th"],
    "final_theta_over_min": lambda r: r["th"] / np.maximum(r["min_abs_theta"], 1e-30),
    "max_excursion": lambda r: r["max_excursion"],
}


def law_tail(name: str, n: int, seeds, n_run: int, draws: int) -> dict:
    """``name``'s off rows against float64 and how the cheap per-row quantities rank them (module docstring)."""
    import jaxsleigh as js
    from jaxsleigh.controllers.registry import make_controller
    from jaxsleigh.studies.audit import REFERENCE_COST, Audit, audit_sample

    law = {} if name == "paper" else {"controller": make_controller(name)}
    cols = {k: [] for k in ("rel", "n_steps", "n_rejected", "T_eps", "u_energy", "u_norm_peak", "min_abs_theta", "xy",
                            "th", "max_excursion")}
    out = {"law": name, "sets": {}}
    for seed in seeds:
        ics = readme_starts(n, seed=seed)
        r = _run(ics, **law, run=js.RunOptions(progress=False, audit=False))

        def ref(rows, tol):
            return _run(ics[rows], **law, x64=True, run=js.RunOptions(progress=False, audit=False),
                        stepsize=js.StepSizeController(rtol=tol, atol=tol, max_steps=10**6))
        e = ref(np.arange(n), 1e-10)
        ok = (r.status == 0) & (e.status == 0)
        rel = np.where(ok, np.abs(r.u_energy / np.where(ok, e.u_energy, 1.0) - 1.0), np.nan)
        for tol in (1e-12, 1e-13):                       # confirmed at 1e-12, then 1e-13, as the audit does
            again = np.flatnonzero(~(rel <= 0.02))
            if again.size:
                e12 = ref(again, tol)
                ok = (e12.status == 0) & (r.status[again] == 0)
                rel[again] = np.where(ok, np.abs(r.u_energy[again] / np.where(ok, e12.u_energy, 1.0) - 1.0), np.nan)
        T = np.where(np.isfinite(r.T_eps), r.T_eps, 2 * 100.0)
        row = {"rel": rel, "n_steps": r.n_steps.astype(np.float64), "n_rejected": r.n_rejected.astype(np.float64),
               "T_eps": T, "u_energy": r.u_energy.astype(np.float64), "u_norm_peak": r.u_norm_peak.astype(np.float64),
               "min_abs_theta": r.min_abs_theta.astype(np.float64), "max_excursion": r.max_excursion.astype(np.float64),
               "xy": np.max(np.abs(r.q_final[:, :2]), axis=1).astype(np.float64),
               "th": np.abs(r.q_final[:, 2]).astype(np.float64)}
        off = rel > 0.05
        ranks = {}
        for q, f in RISK_QUANTITIES.items():
            score = np.nan_to_num(f(row), nan=-np.inf)
            # rank 1 = first in the order; an off row tied with others takes the last of their ranks
            ranks[q] = sorted(int(np.sum(score >= score[i])) for i in np.flatnonzero(off))
        out["sets"][f"readme_seed_{seed}_n{n}"] = {
            "off_5pct": np.flatnonzero(off).tolist(), "off_2pct": int((rel > 0.02).sum()),
            "unjudged": int(np.isnan(rel).sum()), "flagged": int(r.unresolved.sum()), "ranks_of_off_rows": ranks}
        print(name, seed, json.dumps(out["sets"][f"readme_seed_{seed}_n{n}"]), flush=True)
        for k in cols:
            cols[k].append(row[k])
    rows = {k: np.concatenate(v) for k, v in cols.items()}
    judged = np.isfinite(rows["rel"])
    off_i, good_i = np.flatnonzero(judged & (rows["rel"] > 0.05)), np.flatnonzero(judged & (rows["rel"] <= 0.02))
    orders = {"seeded (the library)": None, **{q: f for q, f in RISK_QUANTITIES.items()}}
    rng = np.random.default_rng(2024)
    out["power"] = {}
    for n_run, share in ((n_run, 0.02), (n_run, 0.05), (4096, 0.02), (4096, 0.05)):
        m = max(1, round(share * n_run))
        hit = {k: 0 for k in orders}
        fits = []
        for _ in range(draws):
            pick = np.concatenate([rng.choice(off_i, m), rng.choice(good_i, n_run - m)])[rng.permutation(n_run)]
            is_off = rows["rel"][pick] > 0.05
            for k, f in orders.items():
                if f is None:
                    sel = audit_sample(Audit(), n_run, unresolved=np.zeros(n_run, bool), steps=rows["n_steps"][pick])
                    fits.append(sel.size)
                else:                                    # the same budget, the rows taken by the quantity first
                    score = np.nan_to_num(f({c: v[pick] for c, v in rows.items()}), nan=-np.inf)
                    base = np.random.default_rng(0).permutation(n_run)
                    order = base[np.argsort(-score[base], kind="stable")][:Audit().count(n_run)]
                    cum = np.cumsum(REFERENCE_COST * rows["n_steps"][pick][order])
                    sel = order[:int(np.searchsorted(cum, Audit().budget * rows["n_steps"][pick].sum(), side="right"))]
                hit[k] += bool(np.any(is_off[sel]))
        out["power"][f"{share:g} of {n_run}"] = {"tail_rows": m, "rows_re_run": [int(min(fits)), int(max(fits))],
                                      "said_so": {k: v / draws for k, v in hit.items()}}
    print(name, json.dumps(out["power"]), flush=True)
    return out


def cost(ns, reps: int, law: str = "paper") -> dict:
    import jaxsleigh as js
    from jaxsleigh.controllers.registry import make_controller

    quiet = {"progress": False}
    kw = {} if law == "paper" else {"controller": make_controller(law)}
    cases = {f"{law}_{n}": (readme_starts(n, seed=11), kw) for n in ns}
    if law == "paper":
        cases["plain_fixed_step_4096"] = (readme_starts(4096, seed=11), {
            "saveat": js.SaveAt(summaries=False),
            "stepsize": js.StepSizeController(method="rk4", check_passivity=False)})
    out = {}
    for name, (ics, kw) in cases.items():
        for audit in (False, None):                       # compile (and fill the caches) first
            _run(ics, run=js.RunOptions(audit=audit, **quiet), **kw)
        off, on, recs = [], [], []
        for i in range(reps):                             # interleaved, each first in turn
            for audit in ((False, None) if i % 2 else (None, False)):
                t0 = time.perf_counter()
                r = _run(ics, run=js.RunOptions(audit=audit, **quiet), **kw)
                (on if audit is None else off).append(time.perf_counter() - t0)
                if audit is None:
                    recs.append(r.run_info["audit"])
        rec = recs[-1]
        from jaxsleigh.studies.audit import audit_line

        out[name] = {"wall_s_audit_off": round(statistics.median(off), 3),
                     "wall_s_audit_on": round(statistics.median(on), 3),
                     "speed_with_audit": round(statistics.median(off) / statistics.median(on), 3),
                     "audit_rows": rec.get("rows"), "audit_why": rec.get("why"),
                     "audit_wall_s": [x.get("wall_s") for x in recs],
                     "audit_share_of_run": [x.get("share_of_run") for x in recs],
                     "audit_line": audit_line(rec), "coverage": rec.get("coverage")}
        print(name, json.dumps(out[name]), flush=True)
    return out


def shares(laws, ns, reps: int) -> dict:
    import jaxsleigh as js
    from jaxsleigh.controllers.registry import make_controller

    out = {}
    for n in ns:
        ics = readme_starts(n, seed=11)
        for law in laws:
            kw = {} if law == "paper" else {"controller": make_controller(law)}
            _run(ics, run=js.RunOptions(progress=False), **kw)           # compile (and fill the caches) first
            recs = []
            for _ in range(reps):
                r = _run(ics, run=js.RunOptions(progress=False), **kw)
                a = r.run_info["audit"]
                recs.append({"run_wall_s": round(r.run_info["wall_s"], 3), "rows": a.get("rows"),
                             "reference": a.get("reference"), "wall_s": a.get("wall_s"),
                             "share_of_run": a.get("share_of_run"), "why": a.get("why"),
                             "judged": (a.get("coverage") or {}).get("sampled_rows"),
                             "unfinished": a.get("reference_unfinished"), "passed": a.get("passed")})
            out[f"{law}_{n}"] = recs
            print(law, n, json.dumps(recs), flush=True)
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n-tail", type=int, default=256)
    ap.add_argument("--n-held", type=int, default=128)
    ap.add_argument("--n-base", type=int, default=512)
    ap.add_argument("--n-run", type=int, default=512)
    ap.add_argument("--draws", type=int, default=2000)
    ap.add_argument("--cost-n", default="512,4096")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--cost-law", default="paper", help="the law whose runs the cost is measured on (e.g. aicardi)")
    ap.add_argument("--skip-power", action="store_true")
    ap.add_argument("--skip-cost", action="store_true")
    ap.add_argument("--other-laws", default="", help="e.g. balanced,tuned,shaped,paper,aicardi,astolfi,samson")
    ap.add_argument("--n-other", type=int, default=128)
    ap.add_argument("--law", default="", help="a law's own tail and the order of the audit (e.g. aicardi)")
    ap.add_argument("--n-law", type=int, default=128)
    ap.add_argument("--law-seeds", default="20240611,7")
    ap.add_argument("--share-laws", default="", help="e.g. aicardi,astolfi,samson,paper: the audit's share per law")
    ap.add_argument("--share-n", default="500,4096,16384")
    ap.add_argument("--out", default="out/audit_power.json")
    a = ap.parse_args(argv)
    import jax

    import jaxsleigh as js

    doc = {"command": "python experiments/studies/audit_power.py " + " ".join(sys.argv[1:]),
           "machine": {"arch": platform.machine(), "python": platform.python_version(), "jax": jax.__version__},
           "dtype": "float32 runs, float64 reference (rtol = atol = 1e-10; a law's reference_tol where tighter)", "load_start": load()}
    if not a.skip_power:
        tail = [tail_set(a.n_tail, 20240611), tail_set(a.n_held, 7)]
        ics = readme_starts(a.n_base, seed=11)
        r = _run(ics, run=js.RunOptions(progress=False, audit=False))
        base = {"flag": r.unresolved, "steps": r.n_steps.astype(np.float64)}
        doc["tail_sets"] = {f"readme_seed_{t['seed']}_n{t['n']}": t["summary"] for t in tail}
        doc["base"] = {"law": "paper", "n": a.n_base, "flagged": int(base["flag"].sum())}
        doc["power"] = power(tail, base, a.n_run, (0.02, 0.03, 0.05), a.draws)
        print(json.dumps({k: doc[k] for k in ("tail_sets", "base", "power")}, indent=1), flush=True)
    if a.other_laws:
        doc["other_laws"] = other_laws(a.other_laws.split(","), a.n_other)
    if a.law:
        doc["law_tail"] = law_tail(a.law, a.n_law, [int(x) for x in a.law_seeds.split(",")], a.n_run, a.draws)
    if not a.skip_cost:
        doc["cost"] = cost([int(x) for x in a.cost_n.split(",")], a.reps, a.cost_law)
    if a.share_laws:
        doc["share"] = shares(a.share_laws.split(","), [int(x) for x in a.share_n.split(",")], a.reps)
    doc["load_end"] = load()
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(doc, indent=1) + "\n")


if __name__ == "__main__":
    main()
