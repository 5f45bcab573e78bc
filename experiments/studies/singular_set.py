r"""How the closed loop behaves as the start approaches the singular set theta = 0.

    python experiments/studies/singular_set.py [--out out/singular_set] [--figures docs/figures] [--quick]

At fixed positions (x0, y0) = (1, 1), (-3, -2) (the paper's blue start) and (1, 0), for
|theta0| from 1e-3 to 1 (13 log-spaced values, float64):

* H_d(0), the largest excursion max|q(t)|, the path length of the contact point and the convergence
  time T_eps (|q| <= 0.05 kept) against theta0, with log-log fits y ~ c theta0^a;
* what the engine does there: steps used against theta0 (the default step budget runs out near
  theta0 = 1e-3; raising max_steps fixes it), statuses, float32 against float64;
* the paper's remark that starts near theta = 0 take long, inefficient paths, in pictures.

**Expected exponent of H_d(0).** With p(0) = 0, H_d(0) = (l1 w1^2 + l2 w2^2 + l3 w3^2) / 2 and, from
f_z and f_w (eq. 4, 8), z1 = theta, z2 = x cos(theta) + y sin(theta), z3 = x sin(theta) - y cos(theta),
w2 = z2/z1 - 2 z3/z1^2, w3 = 2 z3/z1^2. As theta0 -> 0 at fixed (x0, y0), z3 -> -y0, so
w2, w3 ~ 1/theta0^2 and H_d(0) ~ 2 (l2 + l3) y0^2 / theta0^4: exponent -4. On the line y0 = 0,
z3 = x0 sin(theta0) ~ x0 theta0 and w2, w3 ~ 1/theta0: H_d(0) ~ (l2 + 4 l3) x0^2 / (2 theta0^2),
exponent -2.

Outputs: ``results.json`` (every number, with the fits) in ``--out``; figures
``singular_scaling.png``, ``singular_paths.png``, ``singular_numerics.png`` in ``--figures``.
Takes ~3 minutes on 2 (shared) CPU cores (``--quick``: ~30 s, coarser and shorter).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

import jaxsleigh as js
from jaxsleigh.studies.basin import PowerLawFit, path_length, power_law_fit
from jaxsleigh.plots.basin import plot_power_laws
from jaxsleigh.plots.paper_figures import plot_paths, save_figure
from jaxsleigh.status import Status

POSITIONS = {"(1, 1)": (1.0, 1.0), "(-3, -2)": (-3.0, -2.0), "(1, 0)": (1.0, 0.0)}
EPS = 0.05
T_WINDOW = 100.0            # horizon of the summaries, the budget study and the path lengths [s]
FIT_MAX = 0.1               # fits use theta0 <= FIT_MAX (the asymptotic regime)


def expected_hd0_exponent(y0: float) -> float:
    return -4.0 if y0 != 0 else -2.0


def expected_hd0(x0: float, y0: float, theta0, gains=None):
    """Leading term of H_d(0) as theta0 -> 0 (see the module docstring)."""
    g = js.paper_gains() if gains is None else gains
    l2, l3 = float(g.L[1]), float(g.L[2])
    th = np.asarray(theta0, float)
    if y0 != 0:
        return 2.0 * (l2 + l3) * y0 ** 2 / th ** 4
    return (l2 + 4.0 * l3) * x0 ** 2 / (2.0 * th ** 2)


def starts_at(pos, theta0):
    th = np.asarray(theta0, float)
    return np.column_stack([np.full_like(th, pos[0]), np.full_like(th, pos[1]), th])


def summaries(theta0, *, x64, max_steps=None, t_final=T_WINDOW):
    """run_ensemble at every position: {label: EnsembleResult}. Not run_basin: a basin stops the starts certified
    not to settle (status 9), and this study follows every start to the horizon."""
    return {lab: js.run_ensemble(starts_at(pos, theta0), eps=EPS, t_final=t_final, x64=x64,
                           stepsize=js.StepSizeController(max_steps=max_steps), run=js.RunOptions(progress=False))
            for lab, pos in POSITIONS.items()}


def t_eps_long(pos, theta0, horizons):
    """T_eps with horizons grown until each start has settled (or the last horizon is reached).

    After the sleigh settles, theta -> 0 and the injected damping k/theta^2 makes the loop stiff:
    the adaptive stepper then needs ~500 steps per second, so each start is run only up to the
    first horizon that it settles within."""
    th = np.asarray(theta0, float)
    T = np.full(th.size, np.inf)
    horizon_used = np.full(th.size, np.nan)
    status = np.zeros(th.size, int)
    steps = np.zeros(th.size, np.int64)
    todo = np.arange(th.size)
    for H in horizons:
        if todo.size == 0:
            break
        r = js.run_ensemble(starts_at(pos, th[todo]), eps=EPS, t_final=H, x64=True,
                      stepsize=js.StepSizeController(max_steps=int(2000 * H)), run=js.RunOptions(progress=False))
        T[todo] = r.T_eps
        status[todo] = r.status
        steps[todo] = r.n_steps + r.n_rejected
        horizon_used[todo] = H
        todo = todo[(r.status == Status.OK) & ~np.isfinite(r.T_eps)]
    return T, horizon_used, status, steps


def fit(theta0, y, lo=0.0, hi=FIT_MAX):
    th = np.asarray(theta0, float)
    y = np.asarray(y, float)
    m = (th >= lo) & (th <= hi) & np.isfinite(y) & (y > 0)
    if m.sum() < 3:
        return None
    return power_law_fit(th[m], y[m])


def local_slopes(x, y):
    """d log y / d log x between consecutive finite points: a power law has them all equal."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    ok = np.isfinite(y) & (y > 0)
    x, y = x[ok], y[ok]
    return [[float(np.sqrt(a * b)), float(np.log(d / c) / np.log(b / a))]
            for a, b, c, d in zip(x[:-1], x[1:], y[:-1], y[1:])]


def fit_dict(f):
    return None if f is None else {"exponent": f.exponent, "se": f.exponent_se, "prefactor": f.prefactor,
                                   "r2": f.r2, "n": f.n}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/singular_set", help="folder of results.json (default out/singular_set)")
    parser.add_argument("--figures", default="docs/figures", help="folder of the figures (default docs/figures)")
    parser.add_argument("--quick", action="store_true", help="coarser theta0 grid and shorter horizons (smoke test)")
    args = parser.parse_args(argv)
    out, figs = Path(args.out), Path(args.figures)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    theta0 = np.logspace(-3, 0, 7 if args.quick else 13)
    horizons = (100.0, 400.0) if args.quick else (100.0, 400.0, 1600.0, 6400.0, 25600.0)
    t_eps_min_theta = 0.1 if args.quick else 0.03
    res = {"theta0": theta0.tolist(), "positions": {k: list(v) for k, v in POSITIONS.items()}, "eps": EPS,
           "t_window": T_WINDOW, "fit_range": [0.0, FIT_MAX], "per_position": {}}

    # --- summaries at 100 s: float64 with the default budget and a raised one, float32 ----------
    print("summaries (100 s) ...", flush=True)
    s64 = summaries(theta0, x64=True)
    default_budget = int(next(iter(s64.values())).settings["max_steps"])
    raised_budget = 10 * default_budget
    s64_raised = summaries(theta0, x64=True, max_steps=raised_budget)
    s32 = summaries(theta0, x64=False, max_steps=raised_budget)
    res["budget"] = {"default": default_budget, "raised": raised_budget}

    # --- path lengths over the 100 s window (decimated at 0.01 s; checked at 0.001 s) ------------
    print("paths ...", flush=True)
    paths = {}
    for lab, pos in POSITIONS.items():
        sol = js.simulate(starts_at(pos, theta0), t_final=T_WINDOW, dt=0.01, x64=True, saveat=js.SaveAt(every=1),
                          stepsize=js.StepSizeController(max_steps=raised_budget))
        n20 = int(round(20.0 / 0.01))
        paths[lab] = {"L": path_length(sol.q), "L20": path_length(sol.q[:, :n20 + 1]), "status": sol.status}
    lab0, pos0 = "(1, 1)", POSITIONS["(1, 1)"]
    every_step, budget = js.SaveAt(every=1), js.StepSizeController(max_steps=raised_budget)
    fine = js.simulate(starts_at(pos0, theta0[:1]), t_final=20.0, dt=0.001, x64=True, saveat=every_step,
                       stepsize=budget)
    coarse = js.simulate(starts_at(pos0, theta0[:1]), t_final=20.0, dt=0.01, x64=True, saveat=every_step,
                         stepsize=budget)
    res["path_decimation_check"] = {
        "position": lab0, "theta0": float(theta0[0]), "L_save_0.01": float(path_length(coarse.q)[0]),
        "L_save_0.001": float(path_length(fine.q)[0])}

    # --- T_eps with horizons long enough to settle ----------------------------------------------
    print("T_eps with long horizons ...", flush=True)
    teps = {}
    sel = theta0 >= t_eps_min_theta * (1 - 1e-9)
    for lab, pos in POSITIONS.items():
        T, H, st, steps = t_eps_long(pos, theta0[sel], horizons)
        teps[lab] = (T, H, st, steps)
        print(f"  {lab}: T_eps = {np.round(T, 1).tolist()}", flush=True)

    # --- fits --------------------------------------------------------------------------------------
    for lab, pos in POSITIONS.items():
        r64, rr, r32 = s64[lab], s64_raised[lab], s32[lab]
        T, H, st, steps = teps[lab]
        exc_ok = rr.status == Status.OK
        d = {
            "Hd0": rr.Hd0.tolist(), "Hd0_leading_term": expected_hd0(*pos, theta0).tolist(),
            "max_excursion": rr.max_excursion.tolist(), "min_abs_theta": rr.min_abs_theta.tolist(),
            "path_length_100s": paths[lab]["L"].tolist(), "path_length_20s": paths[lab]["L20"].tolist(),
            "T_eps_100s": rr.T_eps.tolist(),
            "T_eps_theta0": theta0[sel].tolist(), "T_eps": T.tolist(), "T_eps_horizon": H.tolist(),
            "T_eps_status": st.tolist(), "T_eps_attempted_steps": steps.tolist(), "T_eps_local_slopes": local_slopes(theta0[sel], T),
            "T_eps_vs_Hd0_local_slopes": local_slopes(rr.Hd0[sel], T),
            "steps_default_budget": (r64.n_steps + r64.n_rejected).tolist(),
            "status_default_budget": r64.status.tolist(),
            "steps_raised_budget": (rr.n_steps + rr.n_rejected).tolist(), "status_raised_budget": rr.status.tolist(),
            "steps_float32": (r32.n_steps + r32.n_rejected).tolist(), "status_float32": r32.status.tolist(),
            "float32_final_q_rel_error": (np.linalg.norm(r32.q_final - rr.q_final, axis=1)
                                          / np.maximum(np.linalg.norm(rr.q_final, axis=1), 1e-300)).tolist(),
            "float32_max_excursion_rel_error": (np.abs(r32.max_excursion - rr.max_excursion)
                                                / rr.max_excursion).tolist(),
        }
        d["fits"] = {
            "Hd0": fit_dict(fit(theta0, rr.Hd0)),
            "max_excursion": fit_dict(fit(theta0, np.where(exc_ok, rr.max_excursion, np.nan))),
            "path_length_100s": fit_dict(fit(theta0, np.where(paths[lab]["status"] == 0, paths[lab]["L"], np.nan))),
            "steps_100s": fit_dict(fit(theta0, np.where(exc_ok, rr.n_steps + rr.n_rejected, np.nan), hi=0.03)),
            "T_eps": fit_dict(fit(theta0[sel], T, hi=0.32)),
        }
        d["expected_Hd0_exponent"] = expected_hd0_exponent(pos[1])
        res["per_position"][lab] = d
    res["wall_s"] = time.perf_counter() - t_start
    (out / "results.json").write_text(json.dumps(res, indent=1) + "\n")

    # --- figures -------------------------------------------------------------------------------------
    _figure_scaling(res, theta0, figs / "singular_scaling.png")
    _figure_numerics(res, theta0, figs / "singular_numerics.png")
    _figure_paths(figs / "singular_paths.png", horizon=400.0 if args.quick else 2000.0)

    # --- report --------------------------------------------------------------------------------------
    print(f"\nfits y ~ c theta0^a over theta0 <= {FIT_MAX} (T_eps: 0.03 <= theta0 <= 0.32, steps: <= 0.03)")
    print(f"{'position':<10} {'quantity':<18} {'a':>8} {'± se':>7} {'r2':>7}  expected")
    for lab, d in res["per_position"].items():
        for q, f in d["fits"].items():
            if f is None:
                continue
            exp = f"{d['expected_Hd0_exponent']:g}" if q == "Hd0" else ""
            print(f"{lab:<10} {q:<18} {f['exponent']:8.3f} {f['se']:7.3f} {f['r2']:7.4f}  {exp}")
    print("\nT_eps is not a clean power law: local slopes d ln T_eps / d ln theta0 (at the geometric mid-point)")
    for lab, d in res["per_position"].items():
        print(f"  {lab}: " + ", ".join(f"{m:.3g}: {a:.2f}" for m, a in d["T_eps_local_slopes"]))
        print(f"  {lab} against H_d(0): d ln T_eps / d ln H_d(0) = "
              + ", ".join(f"{a:.2f}" for _, a in d["T_eps_vs_Hd0_local_slopes"]))
    print("\nattempted steps of the T_eps runs (horizon H): the settled sleigh sits next to theta = 0, where the loop "
          "is stiff")
    for lab, d in res["per_position"].items():
        print(f"  {lab}: " + ", ".join(f"theta0 {t:.3g}: {n} in H = {h:g} s (T_eps {T:.4g} s)" for t, n, h, T in
                                       zip(d["T_eps_theta0"], d["T_eps_attempted_steps"], d["T_eps_horizon"],
                                           d["T_eps"])))
    print(f"\nstep budget at {T_WINDOW:g} s: default {default_budget}, raised {raised_budget}")
    for lab, d in res["per_position"].items():
        bad = [f"{t:.2g}" for t, s in zip(theta0, d["status_default_budget"]) if s == Status.BUDGET_EXHAUSTED]
        bad_r = [f"{t:.2g}" for t, s in zip(theta0, d["status_raised_budget"]) if s != Status.OK]
        print(f"  {lab}: budget exhausted (default) at theta0 = {bad or 'none'}; not OK with raised budget: "
              f"{bad_r or 'none'}")
    print(f"\nwall {res['wall_s']:.0f} s; wrote {out / 'results.json'} and figures in {figs}")
    return 0


def _figure_scaling(res, theta0, path):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 8.6), layout="constrained")
    axes = fig.subplots(2, 2)
    pp = res["per_position"]
    specs = [
        ("Hd0", "H_d(0) [J]", "H_d(0): leading term 2(l₂+l₃)y₀²/θ₀⁴ (y₀ ≠ 0), (l₂+4l₃)x₀²/(2θ₀²) (y₀ = 0) dotted"),
        ("max_excursion", "max |q(t)|", "Largest excursion max|q(t)| over 100 s"),
        ("path_length_100s", "path length over 100 s [m]", "Path length of the contact point, first 100 s"),
        ("T_eps", "T_ε [s]", "Convergence time T_ε (|q| ≤ 0.05 kept; horizon grown up to 25600 s)"),
    ]
    for ax, (key, ylabel, title) in zip(axes.flat, specs):
        series, fits, ranges = {}, {}, {}
        x = np.asarray(pp["(1, 1)"]["T_eps_theta0"] if key == "T_eps" else theta0)
        for lab, d in pp.items():
            series[lab] = np.asarray(d[key], float)
            f = d["fits"].get(key)
            if f is not None:
                fits[lab] = PowerLawFit(f["exponent"], f["se"], f["prefactor"], f["r2"], f["n"])
                y = series[lab]
                used = x[np.isfinite(y) & (y > 0) & (x <= (0.32 if key == "T_eps" else FIT_MAX))]
                ranges[lab] = (used.min(), used.max())
        expected = {lab: d["expected_Hd0_exponent"] for lab, d in pp.items()} if key == "Hd0" else None
        plot_power_laws(x, series, ax, fits=fits, fit_ranges=ranges, expected=expected, ylabel=ylabel, title=title)
        if key == "Hd0":
            for i, (lab, d) in enumerate(pp.items()):
                ax.loglog(theta0, d["Hd0_leading_term"], ":", color=f"C{i}", linewidth=1.0)
        if key == "T_eps":
            text = "local slopes, large → small θ₀:\n" + "\n".join(
                f"{lab}: " + ", ".join(f"{a:.1f}" for _, a in d["T_eps_local_slopes"][::-1])
                for lab, d in pp.items())
            ax.text(0.02, 0.03, text, transform=ax.transAxes, fontsize=7, va="bottom", color="0.25")
    fig.suptitle("Approaching the singular set θ = 0 at fixed positions (x₀, y₀) (float64, adaptive RK4; "
                 f"lines: least-squares fits over θ₀ ≤ {FIT_MAX:g}, T_ε over its settled points ≤ 0.32)", fontsize=11)
    save_figure(fig, path)


def _figure_numerics(res, theta0, path):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 4.6), layout="constrained")
    ax1, ax2 = fig.subplots(1, 2)
    pp = res["per_position"]
    b = res["budget"]
    for i, (lab, d) in enumerate(pp.items()):
        for key, st_key, style, name in [("steps_default_budget", "status_default_budget", "o-", "default budget"),
                                         ("steps_raised_budget", "status_raised_budget", "s--", "10× budget")]:
            y = np.asarray(d[key], float)
            st = np.asarray(d[st_key])
            ax1.loglog(theta0, y, style, color=f"C{i}", markersize=4, linewidth=1.0,
                       markerfacecolor="none" if "raised" in key else f"C{i}", label=f"{lab}, {name}")
            bad = st == Status.BUDGET_EXHAUSTED
            if bad.any():
                ax1.loglog(theta0[bad], y[bad], "x", color="red", markersize=9, markeredgewidth=2)
        ax2.loglog(theta0, np.maximum(d["float32_final_q_rel_error"], 1e-12), "o-", color=f"C{i}", markersize=4,
                   label=f"{lab}: final q")
        ax2.loglog(theta0, np.maximum(d["float32_max_excursion_rel_error"], 1e-12), "^:", color=f"C{i}",
                   markersize=4, label=f"{lab}: max|q|")
    ax1.axhline(b["default"], color="k", linestyle=":", linewidth=1)
    ax1.text(theta0[-1], b["default"] * 1.15, f"default budget {b['default']}", ha="right", fontsize=7)
    ax1.axhline(b["raised"], color="0.4", linestyle=":", linewidth=1)
    ax1.text(theta0[-1], b["raised"] * 1.15, f"raised budget {b['raised']}", ha="right", fontsize=7)
    ax1.plot([], [], "x", color="red", label="budget exhausted (status 4)")
    ax1.set_xlabel("θ₀ [rad]")
    ax1.set_ylabel("attempted steps in 100 s (accepted + rejected)")
    ax1.set_title("Steps used by the adaptive stepper (float64)", fontsize=10)
    ax1.legend(fontsize=6.5, ncol=2)
    ax1.grid(True, which="both", alpha=0.25)
    ax2.set_xlabel("θ₀ [rad]")
    ax2.set_ylabel("relative difference float32 vs float64")
    ax2.set_title("float32 against float64 at 100 s (same budget; statuses OK)", fontsize=10)
    ax2.legend(fontsize=6.5, ncol=2)
    ax2.grid(True, which="both", alpha=0.25)
    save_figure(fig, path)


def _figure_paths(path, horizon=2000.0):
    from matplotlib.figure import Figure

    pos = (-3.0, -2.0)
    thetas = [math.pi / 8, 0.2, 0.1, 0.03]
    sol = js.simulate(starts_at(pos, thetas), t_final=horizon, dt=0.01, x64=True, saveat=js.SaveAt(every=10),
                      stepsize=js.StepSizeController(max_steps=int(10_000 * horizon)))
    fig = Figure(figsize=(12, 10), layout="constrained")
    axes = fig.subplots(2, 2)
    L = path_length(sol.q)
    for i, (ax, th) in enumerate(zip(axes.flat, thetas)):
        one = sol._replace(q=sol.q[i:i + 1], p=sol.p[i:i + 1], u=sol.u[i:i + 1], Hd=sol.Hd[i:i + 1],
                           status=sol.status[i:i + 1])
        plot_paths(one, ax, legend=False)
        qn = np.linalg.norm(sol.q[i], axis=-1)
        outside = np.flatnonzero(qn > EPS)
        settled = outside.size and outside[-1] < qn.size - 1
        when = f"settled (|q| ≤ {EPS:g}) at {sol.t[outside[-1] + 1]:.0f} s" if settled else \
            f"not settled by {horizon:g} s: |q| = {qn[-1]:.3g}"
        name = "π/8, the paper's blue run" if abs(th - math.pi / 8) < 1e-12 else f"{th:g}"
        ax.set_title(f"start (−3, −2, θ₀ = {name}), H_d(0) = {sol.Hd[i, 0]:.3g}\n"
                     f"path {L[i]:.3g} m, max|q| = {np.nanmax(qn):.3g}, {when}", fontsize=9)
    fig.suptitle(f"Starts closer to θ = 0 carry more energy H_d(0) and take longer, wider paths (float64, adaptive "
                 f"RK4, {horizon:g} s, saved every 0.1 s; note the axis scales)", fontsize=11)
    save_figure(fig, path)


if __name__ == "__main__":
    sys.exit(main())
