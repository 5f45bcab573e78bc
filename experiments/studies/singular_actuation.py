r"""The singular set under real actuation: how long a sampling period, and how small a saturation, the paper's
law tolerates, against the initial heading |theta0|.

For each |theta0| (log-spaced, 0.05 to 1.6) the starts are 8 positions on the circle of radius 2 (both signs of
theta0 alternating), at rest. For each sampling period Ts of a zero-order hold (`controller=sampled(gains, Ts)`,
the plant by RK4 substeps of at most 2 ms between samples) and each saturation level U
(`controller=saturate(gains, U)`, continuous, adaptive RK4), the fraction of them settled (|q| <= 0.05 kept)
within 100 s. From |theta0| <= 0.1 the continuous loop itself does not settle within 100 s, so the sampling
curve asks whether the held loop **tracks** the continuous one: a start tracks when it ran (status OK) and
ends no farther from the origin than twice the continuous run (or inside the ball). The curves: the **longest
Ts** at which at least half the starts track, and the fraction settled against U, one curve per |theta0|.

**Mechanism.** The paper's law asks, from rest, for a force that grows like theta0^-5 off the line y0 = 0
(theta0^-3 on it): the potential force Q_w^T L w with w ~ theta0^-2 and entries of Q_w ~ 1/theta0 (the run
measures |u(0)| and fits the exponent). The continuous loop applies it for an instant and corrects at once;
a zero-order hold applies it for a whole period, which flings the sleigh out of the region where the loop is
well behaved (or to overflow), so the tolerated Ts shrinks as |theta0| does. Saturation removes exactly that
force, and a bounded force still steers: near theta = 0 a saturated loop settles starts that the unsaturated
one flings hundreds of metres away and does not bring back within the horizon.

Usage: ``python experiments/studies/singular_actuation.py [--out docs/figures] [--quick]``; writes
``singular_actuation.json`` and ``singular_actuation.png``. About 2 minutes on 2 cores (float32).
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import jax
import numpy as np

import jaxsleigh as js
from jaxsleigh.controllers.actuators import sampled, saturate
from jaxsleigh.plots.base import new_figure, save_figure


def starts(theta0: float, n: int = 8) -> np.ndarray:
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    sign = np.where(np.arange(n) % 2 == 0, 1.0, -1.0)
    return np.column_stack([2 * np.cos(a), 2 * np.sin(a), sign * theta0])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="docs/figures")
    ap.add_argument("--t-final", type=float, default=100.0)
    ap.add_argument("--quick", action="store_true", help="fewer headings and levels (a smoke run)")
    a = ap.parse_args()
    t0 = time.perf_counter()
    thetas = [0.05, 0.1, 0.2, 0.4, 0.8, 1.6] if not a.quick else [0.1, 0.8]
    periods = [0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2] if not a.quick else [0.01, 0.1]
    levels = [0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 5.0] if not a.quick else [0.1, 1.0]
    g = js.paper_gains()
    ics = np.concatenate([starts(th) for th in thetas])
    n = len(ics) // len(thetas)
    frac = lambda r: r.converged.reshape(len(thetas), n).mean(axis=1)  # noqa: E731

    quiet = js.RunOptions(progress=False)
    free = js.run_ensemble(ics, t_final=a.t_final, run=quiet)
    reach = np.maximum(2 * np.linalg.norm(free.q_final, axis=1), 0.05)
    by_ts = {}
    for Ts in periods:
        dt = min(0.002, Ts)
        r = js.run_ensemble(ics, controller=sampled(g, Ts), t_final=a.t_final, dt=dt, run=quiet)
        tracks = (r.status == js.Status.OK) & (np.linalg.norm(r.q_final, axis=1) <= reach)
        by_ts[Ts] = tracks.reshape(len(thetas), n).mean(axis=1)
        print(f"Ts = {Ts:g}: tracking {np.round(by_ts[Ts], 2).tolist()}, settled {np.round(frac(r), 2).tolist()}",
              flush=True)
    by_u = {}
    for U in levels:
        by_u[U] = frac(js.run_ensemble(ics, controller=saturate(g, U), t_final=a.t_final, run=quiet))
        print(f"U = {U:g}: settled {np.round(by_u[U], 2).tolist()}", flush=True)

    def longest(d):      # the longest Ts below which every period tracks (a period that fails ends the run)
        out = []
        for i in range(len(thetas)):
            ok = None
            for k in sorted(d):
                if d[k][i] < 0.5:
                    break
                ok = k
            out.append(ok)
        return out

    def smallest(d):
        return [min([k for k in d if d[k][i] >= 0.5], default=None) for i in range(len(thetas))]

    min_th = free.min_abs_theta.reshape(len(thetas), n)
    from jaxsleigh.controllers.paper import PaperLaw

    with jax.enable_x64(True):
        law = PaperLaw()
        u0 = np.array([max(float(np.linalg.norm(law(np.asarray(q, np.float64), np.zeros(2)))) for q in starts(th))
                       for th in thetas])
    slope = float(np.polyfit(np.log(thetas), np.log(u0), 1)[0])
    rec = {"theta0": thetas, "continuous_settled": frac(free).tolist(),
           "u0_max": u0.tolist(), "u0_exponent": slope,
           "min_abs_theta_median": np.median(min_th, axis=1).tolist(),
           "sampling": {"period": periods, "tracking": {str(k): v.tolist() for k, v in by_ts.items()},
                        "longest_period": longest(by_ts)},
           "saturation": {"u_max": levels, "settled": {str(k): v.tolist() for k, v in by_u.items()},
                          "smallest_u_max": smallest(by_u)},
           "settings": {"starts_per_theta0": n, "radius": 2.0, "t_final": a.t_final, "eps": 0.05, "dtype": "float32",
                        "criterion": "at least half of the starts settled"},
           "command": [sys.executable.rsplit("/", 1)[-1], *sys.argv],
           "run_info": {"wall_s": time.perf_counter() - t0, "devices": [str(d) for d in jax.devices()],
                        "machine": f"{platform.machine()}, {platform.processor() or 'cpu'}"}}
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "singular_actuation.json").write_text(json.dumps(rec, indent=1, default=float))
    fig = new_figure((10.5, 4.0))
    ax1, ax2 = fig.subplots(1, 2)
    lp = [np.nan if v is None else v for v in rec["sampling"]["longest_period"]]
    ax1.loglog(thetas, lp, "o-", label="longest Ts at which half the starts track the continuous loop")
    ax1.set_xlabel("|θ₀|")
    ax1.set_ylabel("Ts [s]")
    ax1.set_title("zero-order hold (none tracks at |θ₀| ≤ 0.1, even Ts = 2 ms)", fontsize=9)
    ax1.grid(alpha=0.3, which="both")
    ax1.legend(fontsize=7, loc="upper left")
    tw = ax1.twinx()
    tw.loglog(thetas, u0, "s:", color="grey")
    tw.set_ylabel(f"grey: largest |u(0)| from rest [N] (~ |θ₀|^{slope:.1f})", color="grey")
    for i, th in enumerate(thetas):
        ax2.semilogx(levels, [by_u[U][i] for U in levels], "o-", label=f"|θ₀| = {th:g}", color=f"C{i}")
        ax2.axhline(frac(free)[i], color=f"C{i}", lw=0.8, ls=":")
    ax2.set_xlabel("U [N, N m]")
    ax2.set_ylabel(f"fraction settled within {a.t_final:g} s")
    ax2.set_title("saturation |u_i| ≤ U (dotted: unsaturated)", fontsize=9)
    ax2.grid(alpha=0.3, which="both")
    ax2.legend(fontsize=7)
    fig.suptitle(f"The paper's law near θ = 0 under real actuation ({n} starts per |θ₀| on |(x, y)| = 2, "
                 f"{a.t_final:g} s)\nfloat32, {platform.machine()} CPU; {' '.join(rec['command'])}", fontsize=9)
    save_figure(fig, out / "singular_actuation.png")
    print(f"wrote {out}/singular_actuation.{{json,png}} in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
