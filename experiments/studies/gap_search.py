"""Tuning on the gap to the optimum: a search of the paper law's gains that minimises the median T_law / T*(E_law).

    python experiments/studies/gap_search.py [--train 16] [--generations 20] [--population 10] [--converged-margin 0] [--n 32]

1. Training: ``--train`` starts of the README's distribution (seed 7, not a held-out seed); their energy-optimal
   frontier E*(T) by `jaxsleigh.optimum` (float64, 24 intervals) at 2.5, 5, 10, 20, 40, 80 s.
2. `jaxsleigh.tuning.search` with ``SearchConfig(objective="gap")`` from the ``balanced`` preset, at no more median
   energy than ``balanced`` on the training starts (``energy_margin`` 1) and no fewer settled (``--converged-margin``,
   default 0), float64, atol 1e-8, 100 s (the settings of ``optimum_gap.py``). The training frontier is kept in
   ``out/gap_search_train_N.npz`` and reused.
3. Held out: the starts of ``optimum_gap.py`` (the first ``--n`` of each distribution), their frontier read from
   ``out/optimum_gap.npz`` when that study has been run with the same ``--n`` (solved again otherwise); ``balanced``
   and the searched gains run 100 s there and their time ratios T_law / T*(E_law) are compared (median over the
   starts each settles whose ratio the frontier's horizons cover; a censored ratio is a bound, left out).

Writes ``docs/figures/gap_search.json`` (dtype, machine, load, command, the gains, the figures).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT, load, machine  # noqa: E402
from preset_effort import readme_starts, wide_starts  # noqa: E402

HORIZONS = (2.5, 5.0, 10.0, 20.0, 40.0, 80.0)


def _with_momentum(ics):
    return ics if ics.shape[1] == 5 else np.concatenate([ics, np.zeros((len(ics), 2))], axis=1)


def held_out_frontier(dname, ics):
    """The held-out frontier of ``optimum_gap.py`` (from its npz when it matches), else solved here."""
    from jaxsleigh import OptimumResult, optimum

    path = ROOT / "out" / "optimum_gap.npz"
    if path.exists():
        with np.load(path) as z:
            fr, hz = z[f"{dname}_frontier"], z[f"{dname}_horizons"]
        if fr.shape[0] == len(ics) and tuple(hz) == HORIZONS:
            S, H = fr.shape
            ok = np.isfinite(fr)
            return OptimumResult(starts=ics, horizons=hz, eps=0.05, energy=fr, u=np.zeros((S, H, 1, 2)),
                                 status=np.where(ok, 0, 2).astype(np.int32), q_final=np.zeros((S, H, 3)),
                                 p_final=np.zeros((S, H, 2)), kkt=np.zeros((S, H)),
                                 guess=np.zeros((S, H), np.int32)), "read from out/optimum_gap.npz"
    return optimum(ics, HORIZONS), "solved here"


def law_gap(front, gains, stepsize):
    """Median time ratio and median energy of ``gains`` over the starts it settles, and how many it settles."""
    from jaxsleigh import RunOptions, run_ensemble
    from jaxsleigh.status import Status

    r = run_ensemble(front.starts, gains=gains, t_final=100.0, eps=0.05, x64=True, stepsize=stepsize,
                     run=RunOptions(progress=False))
    ok = (np.asarray(r.status) == Status.OK) & np.isfinite(r.T_eps)
    T = np.where(ok, r.T_eps, np.nan)
    E = np.where(ok, np.asarray(r.u_energy, float), np.nan)
    g = front.gap(T, E)
    t = g.time[np.isfinite(g.time)]
    return {"settled": f"{int(ok.sum())}/{ok.size}", "median_time_ratio": float(np.median(t)) if t.size else None,
            "p25_p75_time_ratio": [float(np.percentile(t, 25)), float(np.percentile(t, 75))] if t.size else None,
            "median_T": float(np.nanmedian(T)), "median_energy": float(np.nanmedian(E))}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--train", type=int, default=16)
    ap.add_argument("--generations", type=int, default=20)
    ap.add_argument("--population", type=int, default=10)
    ap.add_argument("--converged-margin", type=float, default=0.0)
    ap.add_argument("--n", type=int, default=32)
    ap.add_argument("--out", default=str(ROOT / "docs" / "figures" / "gap_search.json"))
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    from jaxsleigh import StepSizeController, optimum
    from jaxsleigh.studies.optimum import load_optimum, save_optimum
    from jaxsleigh.model.params import gains_to_dict
    from jaxsleigh import tuning as tu

    t_start, load_start = time.perf_counter(), load()
    stepsize = StepSizeController(atol=1e-8)
    train = _with_momentum(tu.draw_starts(tu.UniformStarts(), args.train, 7))
    t0 = time.perf_counter()
    cached = ROOT / "out" / f"gap_search_train_{args.train}.npz"      # the training frontier, solved once
    if cached.exists():
        front = load_optimum(cached)
    else:
        front = optimum(train, HORIZONS)
        cached.parent.mkdir(exist_ok=True)
        save_optimum(cached, front)
    print(f"training frontier: {time.perf_counter() - t0:.0f} s, {front.counts()}", flush=True)
    cfg = tu.SearchConfig(generations=args.generations, population=args.population, batch=args.train,
                          energy_margin=1.0, converged_margin=args.converged_margin, objective="gap")
    t0 = time.perf_counter()
    res = tu.search("balanced", config=cfg, reference="balanced", frontier=front, x64=True, stepsize=stepsize)
    t_search = time.perf_counter() - t0
    h = res.history
    print(f"search: {int(h['feasible'].sum())} of {len(h['feasible'])} generations' best feasible", flush=True)
    print(f"search: {t_search:.0f} s; median gap {res.reference['median_gap']:.3f} -> {res.figures['median_gap']:.3f}"
          f" (generation {res.best_generation})", flush=True)
    out = {"command": "python experiments/studies/gap_search.py" + "".join(f" {a}" for a in (argv or sys.argv[1:])),
           "dtype": "float64", "law_method": "adaptive, atol 1e-8, 100 s, eps 0.05", "horizons": list(HORIZONS),
           "machine": machine(), "loadavg_start": load_start,
           "training": {"starts": args.train, "seed": 7, "optimum_status": front.counts(),
                        "reference": res.reference, "searched": res.figures, "best_generation": res.best_generation,
                        "generations": args.generations, "population": args.population,
                        "converged_margin": args.converged_margin, "wall_s": round(t_search, 1),
                        "history_median_gap": [float(v) for v in h["median_gap"]],
                        "history_feasible": [bool(v) for v in h["feasible"]]},
           "gains": gains_to_dict(res.gains), "held_out": {}}
    for dname, ics in {"readme": readme_starts(args.n), "wide": wide_starts(args.n)}.items():
        hf, how = held_out_frontier(dname, _with_momentum(ics))
        rows = {"frontier": how, "balanced": law_gap(hf, "balanced", stepsize),
                "gap_searched": law_gap(hf, res.gains, stepsize)}
        out["held_out"][dname] = rows
        print(f"{dname}: {json.dumps(rows)}", flush=True)
    out["wall_s"] = round(time.perf_counter() - t_start, 1)
    out["loadavg_end"] = load()
    Path(args.out).write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
