"""Robustness of the paper's claim (Remarks 1-2): the law needs neither m, J, l nor the friction.

With the paper's gains fixed, plants are sampled log-uniformly (m in [0.5, 8] kg, J in [0.1, 10]
kg m^2, l in [0.05, 3] m, a quarter of them with l = 0 exactly: the knife edge) for each damping
family, with random levels: Coulomb (scale c in [0.1, 10], smoothing eps in [0.01, 1]), viscous
(c1, c2 in [0.1, 10]) and none. A family's plants x starts run as ONE sweep (``jaxsleigh.sweep``
with explicit value sets). The knife edge (l = 0, the paper's m, J and Coulomb friction, and
sampled m, J) is also run on its own.

Per family: the fraction of starts converged within the horizon (|q| <= eps from T_eps on),
pooled and per plant, and the T_eps distribution; per plant, the fraction against m, J, l and the
damping level. Writes ``docs/figures/robustness.png``, ``docs/figures/robustness_params.png`` and
``docs/figures/robustness.json``.

Usage: ``python experiments/studies/robustness.py [--plants 16] [--starts 48] [--t-final 100] [--out docs/figures]``
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import jaxsleigh as js
from jaxsleigh.studies.basin import fraction_converged, sample_starts, t_eps_percentiles
from jaxsleigh.model.damping import CoulombDamping, NoDamping, ViscousDamping
from jaxsleigh.model.params import PlantParams


def log_uniform(rng, lo, hi, n):
    return np.exp(rng.uniform(np.log(lo), np.log(hi), n))


def sample_family(family: str, n: int, rng):
    """(base plant, explicit value sets) for one damping family."""
    vals = {"m": log_uniform(rng, 0.5, 8.0, n), "J": log_uniform(rng, 0.1, 10.0, n),
            "l": log_uniform(rng, 0.05, 3.0, n)}
    vals["l"][: max(1, n // 4)] = 0.0                       # the knife edge is part of every family
    if family == "coulomb":
        vals["coulomb_scale"] = log_uniform(rng, 0.1, 10.0, n)
        vals["coulomb_eps"] = log_uniform(rng, 0.01, 1.0, n)
        damping = CoulombDamping()
    elif family == "viscous":
        vals["c1"] = log_uniform(rng, 0.1, 10.0, n)
        vals["c2"] = log_uniform(rng, 0.1, 10.0, n)
        damping = ViscousDamping()
    elif family == "none":
        damping = NoDamping()
    elif family == "knife edge":
        vals["l"] = np.zeros(n)
        vals["m"][0], vals["J"][0] = 2.0, 1.0             # the paper's inertia, on the knife edge
        damping = CoulombDamping()
    else:
        raise ValueError(family)
    return PlantParams(2.0, 1.0, 1.0, damping), vals


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--plants", type=int, default=16, help="plants per family")
    ap.add_argument("--starts", type=int, default=48, help="Monte-Carlo starts per plant")
    ap.add_argument("--t-final", type=float, default=100.0)
    ap.add_argument("--eps", type=float, default=0.05)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="docs/figures")
    a = ap.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(a.seed)
    starts = sample_starts(a.starts, seed=a.seed + 1)          # |x|, |y| <= 3, theta in (-pi, pi)
    families = ["coulomb", "viscous", "none", "knife edge"]
    results, summary = {}, {}
    for fam in families:
        plant, vals = sample_family(fam, a.plants, rng)
        t0 = time.perf_counter()
        r = js.sweep(starts, vals, plant=plant, gains="paper", t_final=a.t_final, eps=a.eps,
                     run=js.RunOptions(progress=False))
        wall = time.perf_counter() - t0
        results[fam] = r
        S, se = fraction_converged(r.converged, r.valid)
        per = r.fraction
        codes, counts = r.status_counts()
        summary[fam] = {
            "plants": a.plants, "starts": a.starts, "wall_s": wall, "fraction": S, "fraction_se": se,
            "per_plant_fraction_min": float(per.min()), "per_plant_fraction_median": float(np.median(per)),
            "per_plant_fraction_max": float(per.max()),
            "knife_edge_fraction": float(fraction_converged(r.converged[vals["l"] == 0],
                                                            r.valid[vals["l"] == 0])[0]),
            "T_eps_percentiles": dict(zip(["p10", "p25", "p50", "p75", "p90"],
                                          t_eps_percentiles(r.T_eps[r.converged]).tolist())),
            "status_counts": {js.Status(int(c)).name.lower(): int(n) for c, n in zip(codes, counts.sum(0)) if n},
            "values": {k: np.asarray(v).tolist() for k, v in vals.items()},
            "per_plant_fraction": per.tolist(),
        }
        print(f"{fam:>10}: S = {S:.3f} +- {se:.3f} over {a.plants} plants x {a.starts} starts "
              f"(per plant {per.min():.2f} .. {np.median(per):.2f} .. {per.max():.2f}); knife edge "
              f"{summary[fam]['knife_edge_fraction']:.3f}; T_eps p50 {summary[fam]['T_eps_percentiles']['p50']:.3g} s; "
              f"statuses {summary[fam]['status_counts']} ({wall:.0f} s)", flush=True)
    # the paper's plant on the same starts, for reference
    ref = js.run_basin(starts, t_final=a.t_final, eps=a.eps, run=js.RunOptions(progress=False))
    summary["paper plant"] = {"fraction": ref.fraction, "fraction_se": ref.fraction_se,
                              "T_eps_percentiles": ref.summary()["T_eps_percentiles"]}
    print(f"paper plant: S = {ref.fraction:.3f} +- {ref.fraction_se:.3f}")
    summary["settings"] = {"t_final": a.t_final, "eps": a.eps, "seed": a.seed, "gains": "paper",
                           "ranges": {"m": [0.5, 8], "J": [0.1, 10], "l": [0.05, 3, "and 0 for a quarter"],
                                      "coulomb_scale": [0.1, 10], "coulomb_eps": [0.01, 1], "c1": [0.1, 10],
                                      "c2": [0.1, 10]}}
    (out / "robustness.json").write_text(json.dumps(summary, indent=1) + "\n")

    from matplotlib.figure import Figure

    colors = {"coulomb": "C0", "viscous": "C1", "none": "C2", "knife edge": "C3"}
    fig = Figure(figsize=(12, 4.4), layout="constrained")
    ax1, ax2 = fig.subplots(1, 2)
    for i, fam in enumerate(families):
        per = results[fam].fraction
        ax1.scatter(np.full(per.size, i) + rng.uniform(-0.12, 0.12, per.size), per, s=18, color=colors[fam])
        S, se = summary[fam]["fraction"], summary[fam]["fraction_se"]
        ax1.errorbar(i + 0.3, S, yerr=se, fmt="D", color="k", capsize=3)
        r = results[fam]
        t = np.sort(r.T_eps[r.converged])
        n_valid = r.valid.sum()
        ax2.step(t, np.arange(1, t.size + 1) / n_valid, where="post", color=colors[fam], label=fam)
    ax1.axhline(ref.fraction, ls="--", color="grey", lw=1, label=f"paper plant ({ref.fraction:.2f})")
    ax1.set_xticks(range(len(families)), families)
    ax1.set_ylabel(f"fraction converged within {a.t_final:g} s")
    ax1.set_ylim(-0.03, 1.03)
    ax1.legend(fontsize=8, loc="lower left")
    ax1.set_title("per sampled plant (dots), pooled +- s.e. (diamonds)", fontsize=10)
    t_ref = np.sort(ref.T_eps[ref.converged])
    ax2.step(t_ref, np.arange(1, t_ref.size + 1) / ref.valid.sum(), where="post", color="grey", ls="--",
             label="paper plant")
    ax2.set_xlabel("T_eps [s]")
    ax2.set_ylabel("fraction of starts settled by T_eps")
    ax2.set_xscale("log")
    ax2.legend(fontsize=8)
    ax2.set_title("T_eps distribution per family (pooled over plants)", fontsize=10)
    fig.suptitle(f"paper's gains, {a.plants} sampled plants per family x {a.starts} starts, |q| <= {a.eps:g}",
                 fontsize=10)
    fig.savefig(out / "robustness.png", dpi=130)

    fig = Figure(figsize=(13, 3.8), layout="constrained")
    axes = fig.subplots(1, 4)
    for fam in families:
        v, per = summary[fam]["values"], results[fam].fraction
        for ax, name in zip(axes[:3], ("m", "J", "l")):
            x = np.asarray(v[name])
            ax.scatter(np.where(x == 0, 0.02, x), per, s=14, color=colors[fam], label=fam)
        lvl = v.get("coulomb_scale") or (np.sqrt(np.asarray(v["c1"]) * np.asarray(v["c2"])).tolist()
                                         if "c1" in v else None)
        if lvl is not None and fam != "knife edge":
            axes[3].scatter(lvl, per, s=14, color=colors[fam], label=fam)
    for ax, name in zip(axes, ("m [kg]", "J [kg m^2]", "l [m] (l = 0 drawn at 0.02)",
                               "damping level (Coulomb c, viscous sqrt(c1 c2))")):
        ax.set_xscale("log")
        ax.set_xlabel(name, fontsize=9)
        ax.set_ylim(-0.03, 1.03)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("fraction converged (per plant)")
    axes[0].legend(fontsize=7)
    fig.savefig(out / "robustness_params.png", dpi=130)
    print(f"wrote {out / 'robustness.png'}, {out / 'robustness_params.png'}, {out / 'robustness.json'}")


if __name__ == "__main__":
    main()
