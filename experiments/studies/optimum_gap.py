"""How far every feedback law is from the energy-optimal limit, start by start.

    python experiments/studies/optimum_gap.py [--n 32] [--horizons 2.5,5,10,20,40,80] [--out docs/figures/optimum_gap.json]

For held-out starts of two distributions (those of ``preset_effort.py``: ``readme``, x, y ~ U(-3, 3), |theta0| ~
U(0.3, pi), at rest, seed 20240611; ``wide``, x, y ~ U(-4, 4), |theta0| ~ U(0.05, pi) with one in eight below
0.3, momentum for half, seed 20240612; the first ``--n`` of each), every law of ``jaxsleigh controllers`` with
its defaults and every preset of the paper's law runs 100 s (float64, adaptive, atol 1e-8, eps 0.05), giving
its ``T_law`` (T_0.05) and ``E_law`` (int_0^100 |u|^2 dt, all its effort, settling included). The optimum
(`jaxsleigh.optimum`, float64, 24 intervals, defaults) gives the frontier E*(T) on ``--horizons`` per start.
Per law and start:

* time ratio ``T_law / T*(E_law)``: how much longer than the fastest rest-in-the-ball at the law's energy;
* energy ratio ``E_law / E*(T_law)``: how much more energy than the least at the law's time.

Outside the solved horizons the inverse is censored (the JSON counts those starts per side: ``T* < T_min``
makes the time ratio at least ``T_law / T_min``; ``T_law > T_max`` makes the energy ratio at least
``E_law / E*(T_max)``; both bounds are used in the quantiles, and said). Written: the JSON (dtype, machine,
load, command) and ``docs/figures/optimum_gap.png`` (ECDFs per law; the frontier of three starts with the
laws' points).
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

sys.path.insert(0, str(ROOT))

QS = (10, 25, 50, 75, 90)


def laws():
    """name -> keyword of run_ensemble: every law of `jaxsleigh controllers` and the paper law's presets."""
    from jaxsleigh.controllers.registry import controller_names, make_controller

    out = {}
    for name in controller_names():
        out[name] = {"gains": "paper"} if name == "paper" else {"controller": make_controller(name)}
    for preset in ("balanced", "tuned"):
        out[f"paper:{preset}"] = {"gains": preset}
    return out


def summary(t_ratio, e_ratio, wT, wE, ok, near):
    def q(a):
        a = a[np.isfinite(a)]
        return {f"p{k}": float(np.percentile(a, k)) for k in QS} if a.size else None

    return {"n": int(ok.size), "settled": int(ok.sum()),
            "time_ratio": q(t_ratio), "energy_ratio": q(e_ratio),
            "time_ratio_censored_low_bound": int(np.sum(ok & (wT == -1))),
            "time_ratio_undefined": int(np.sum(ok & (wT == 1))),
            "energy_ratio_censored_low_bound": int(np.sum(ok & (wE == 1))),
            "energy_ratio_undefined": int(np.sum(ok & (wE == -1))),
            "energy_ratio_below_1": int(np.sum(e_ratio < 1)),
            "median_energy_ratio_near_theta0": (float(np.nanmedian(e_ratio[near])) if np.isfinite(e_ratio[near]).any()
                                                else None),
            "median_energy_ratio_far": (float(np.nanmedian(e_ratio[~near])) if np.isfinite(e_ratio[~near]).any()
                                        else None),
            "median_time_ratio_near_theta0": (float(np.nanmedian(t_ratio[near])) if np.isfinite(t_ratio[near]).any()
                                              else None),
            "median_time_ratio_far": (float(np.nanmedian(t_ratio[~near])) if np.isfinite(t_ratio[~near]).any()
                                      else None)}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=32, help="starts per distribution (default 32)")
    ap.add_argument("--horizons", default="2.5,5,10,20,40,80")
    ap.add_argument("--out", default=str(ROOT / "docs" / "figures" / "optimum_gap.json"))
    args = ap.parse_args(argv)
    horizons = tuple(float(v) for v in args.horizons.split(","))


    from jaxsleigh import RunOptions, StepSizeController, optimum, run_ensemble
    from jaxsleigh.status import Status

    t_start, load_start = time.perf_counter(), load()
    dists = {"readme": readme_starts(args.n), "wide": wide_starts(args.n)}
    out = {"command": "python experiments/studies/optimum_gap.py" + "".join(f" {a}" for a in (argv or sys.argv[1:])),
           "dtype": "float64", "eps": 0.05, "law_t_final": 100.0, "law_method": "adaptive, atol 1e-8",
           "horizons": list(horizons), "optimum": "jaxsleigh.optimum, 24 intervals, default OptimumOptions",
           "E_law": "int_0^100 |u|^2 dt (the law's whole effort, settling included)",
           "T_law": "T_0.05: the start of the last stay in |q| <= 0.05",
           "machine": machine(),
           "loadavg_start": load_start, "distributions": {}}
    keep = {}
    for dname, ics in dists.items():
        if ics.shape[1] == 3:
            ics = np.concatenate([ics, np.zeros((len(ics), 2))], axis=1)
        t0 = time.perf_counter()
        res = optimum(ics, horizons)
        t_opt = time.perf_counter() - t0
        print(f"{dname}: optimum {t_opt:.0f} s: {res.counts()}", flush=True)
        near = np.abs(ics[:, 2]) < 0.3
        rows, pts = {}, {}
        for lname, kw in laws().items():
            r = run_ensemble(ics, t_final=100.0, eps=0.05, x64=True, run=RunOptions(progress=False),
                             stepsize=StepSizeController(atol=1e-8), **kw)
            okr = np.asarray(r.status) == Status.OK
            T_law = np.where(okr & np.isfinite(r.T_eps), r.T_eps, np.nan)
            E_law = np.where(okr, np.asarray(r.u_energy, float), np.nan)
            g = res.gap(T_law, E_law)            # outside the horizons a ratio is a bound (g.*_at_least), NaN here
            t_ratio, e_ratio, wT, wE = g.time, g.energy, g.time_where, g.energy_where
            ok = np.isfinite(T_law) & np.isfinite(E_law)
            rows[lname] = summary(t_ratio, e_ratio, wT, wE, ok, near)
            pts[lname] = (T_law, E_law, t_ratio, e_ratio)
            print(f"  {lname:15s} {json.dumps({k: rows[lname][k] for k in ('settled', 'time_ratio', 'energy_ratio')})}",
                  flush=True)
        out["distributions"][dname] = {"n": int(len(ics)), "near_theta0": int(near.sum()),
                                       "optimum_status": res.counts(), "optimum_wall_s": round(t_opt, 1),
                                       "median_frontier": [float(np.nanmedian(c)) for c in res.frontier().T],
                                       "laws": rows}
        keep[dname] = (res, pts)
    arrays = {}
    for dname, (res, pts) in keep.items():
        arrays[f"{dname}_horizons"], arrays[f"{dname}_frontier"] = res.horizons, res.frontier()
        for lname, p in pts.items():
            for key, a in zip(("T_law", "E_law", "time_ratio", "energy_ratio"), p):
                arrays[f"{dname}_{lname}_{key}"] = a
    (ROOT / "out").mkdir(exist_ok=True)
    np.savez(ROOT / "out" / "optimum_gap.npz", **arrays)
    out["wall_s"] = round(time.perf_counter() - t_start, 1)
    out["loadavg_end"] = load()
    Path(args.out).write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {args.out}")
    figure(keep, Path(args.out).with_suffix(".png"))


def figure(keep, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(15, 8.5))
    names = list(next(iter(keep.values()))[1])
    colour = {n: f"C{i}" for i, n in enumerate(names)}        # one colour per law in every panel
    marker = dict(zip(names, "osD^vx*"))
    for row, (dname, (res, pts)) in enumerate(keep.items()):
        for col, (k, label) in enumerate(((3, r"energy ratio $E_{law} / E^*(T_{law})$"),
                                          (2, r"time ratio $T_{law} / T^*(E_{law})$"))):
            ax = axes[row, col]
            for lname, p in pts.items():
                a = np.sort(p[k][np.isfinite(p[k])])
                ax.step(a if a.size else [np.nan], np.arange(1, a.size + 1) / p[k].size if a.size else [np.nan],
                        where="post", color=colour[lname], label=f"{lname} ({a.size}/{p[k].size})")
            ax.set_xscale("log")
            ax.set_xlabel(label)
            ax.set_ylabel("fraction of starts")
            ax.set_title(f"{dname} starts")
            ax.axvline(1, color="k", lw=0.8)
            ax.grid(True, which="both", alpha=0.3)
        ax = axes[row, 2]
        fr = res.frontier()
        for i, c in zip(range(3), ("k", "0.45", "0.7")):
            ax.loglog(res.horizons, fr[i], "-", color=c, lw=2, label=f"E*(T), start {i}")
            for lname, p in pts.items():
                if np.isfinite(p[0][i]) and np.isfinite(p[1][i]):
                    ax.loglog(p[0][i], p[1][i], marker[lname], color=colour[lname], ms=7, mfc="none", mew=1.5,
                              mec=colour[lname])
        for lname in names:
            ax.plot([], [], marker[lname], color=colour[lname], mfc="none", label=lname)
        ax.set_xlabel("T [s]")
        ax.set_ylabel(r"energy $\int |u|^2 dt$")
        ax.set_title(f"{dname}: frontier of 3 starts (lines), each law's (T_law, E_law) on them", fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=6, ncol=2)
        axes[row, 0].legend(fontsize=7, title="settled / starts", title_fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
