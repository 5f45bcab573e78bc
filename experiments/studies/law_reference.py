r"""Is the float64 reference of a physical-chart law converged, and how far is the default float32 run from it?

    python experiments/studies/law_reference.py [--law aicardi] [--n 64] [--tols 1e-10,1e-12,1e-13,1e-14]
        [--scipy-every 4] [--out docs/figures/law_reference.json]

Four held-out start sets of ``n`` rows each (none of them used to set any of the library's constants):

* ``readme``: the README's starts (`UniformStarts`), seed 31;
* ``near_theta0``: (x, y) uniform in [-2, 2]^2, |theta0| log-uniform in [1e-3, 5e-2] with a random sign, at rest;
* ``wide``: `WideStarts` (|x|, |y| <= 4, |theta0| in (0.05, pi), momentum for half), seed 32;
* ``far``: (x, y) uniform in [-10, 10]^2 with |x| or |y| >= 6, theta0 uniform in (-pi, pi), momentum
  N(0, 0.5^2) per component, seed 33.

Each set is run in float32 at the defaults (the run), and by the library in float64 at each of ``tols``
(rtol = atol, one batch of the whole set). An independent solver, SciPy's ``solve_ivp`` DOP853 at rtol = 1e-12,
atol = 1e-15, integrates every ``scipy_every``-th row of each set on the same vector field
(`jaxsleigh.model.closed_loop.vector_field_law_control`, compiled once in float64) with the control energy
\(E = \int_0^T \|u\|^2 dt\) as a sixth state; it stops once \(\max(|x|, |y|, |\theta \bmod 2\pi|, |p_1|, |p_2|)
< 10^{-9}\), after which the state decays exponentially and the rest of \(E\) is below \(10^{-15}\); its
\(T_\epsilon\) is the last exit from the ball \(|q| \le \epsilon\) (heading modulo \(2\pi\)), located on a grid of
1 ms of the dense output and refined by bisection.

Reported per quantity (control energy, relative; \(T_\epsilon\), seconds; final position, heading modulo
\(2\pi\), absolute) and per tolerance: rows off the tightest tolerance by more than the audit's thresholds (2%,
0.05 s, 1e-3) and the float32 run's rows off by more than 5%, 2% and those thresholds against the converged
reference (the tightest tolerance where it agrees with the next one and with SciPy).
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import load  # noqa: E402
from studies.preset_effort import readme_starts, wide_starts  # noqa: E402

TWO_PI = 2.0 * np.pi
T_FINAL, EPS = 100.0, 0.05
THRESHOLDS = {"energy_rel": 0.02, "T_eps_s": 0.05, "state": 1e-3}


def start_sets(n: int) -> dict:
    rng = np.random.default_rng(30)
    near = np.column_stack([rng.uniform(-2, 2, (n, 2)),
                            rng.choice([-1.0, 1.0], n) * 10 ** rng.uniform(-3, np.log10(5e-2), n)])
    rng = np.random.default_rng(33)
    xy = rng.uniform(-10, 10, (4 * n, 2))
    xy = xy[np.max(np.abs(xy), axis=1) >= 6][:n]
    far = np.column_stack([xy, rng.uniform(-np.pi, np.pi, n), rng.normal(0, 0.5, (n, 2))])
    pad = lambda a: a if a.shape[1] == 5 else np.column_stack([a, np.zeros((len(a), 2))])  # noqa: E731
    return {"readme": pad(readme_starts(n, seed=31)), "near_theta0": pad(near), "wide": pad(wide_starts(n, seed=32)),
            "far": far}


def _run(ics, law, tol=None):
    import jaxsleigh as js

    kw = {} if tol is None else {"x64": True, "stepsize": js.StepSizeController(rtol=tol, atol=tol, max_steps=10**7)}
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = js.run_ensemble(ics, controller=law, t_final=T_FINAL, eps=EPS,
                            run=js.RunOptions(progress=False, audit=False), **kw)
    return {"status": np.asarray(r.status), "E": np.asarray(r.u_energy, np.float64),
            "T": np.asarray(r.T_eps, np.float64), "q": np.asarray(r.q_final, np.float64),
            "steps": np.asarray(r.n_steps), "wall_s": time.perf_counter() - t0}


def scipy_rows(ics, law) -> dict:
    """DOP853 at rtol = 1e-12, atol = 1e-15 on the library's physical-chart field, energy as a sixth state."""
    import jax
    import jax.numpy as jnp

    import jaxsleigh as js
    from jaxsleigh.model.closed_loop import ClosedLoop, vector_field_law_control

    with jax.enable_x64(True):
        args = ClosedLoop(js.paper_plant(), law)

        def g(t, s):
            dy, u = vector_field_law_control(t, s[:5], args)
            return jnp.concatenate([dy, jnp.stack([u[0] * u[0] + u[1] * u[1]])])
        fc = jax.jit(g).lower(jnp.zeros((), jnp.float64), jnp.zeros(6, jnp.float64)).compile()

    def f(t, s):
        return np.asarray(fc(np.float64(t), np.asarray(s, np.float64)))

    def small(t, s):
        th = s[2] - TWO_PI * np.round(s[2] / TWO_PI)
        return max(abs(s[0]), abs(s[1]), abs(th), abs(s[3]), abs(s[4])) - 1e-9
    small.terminal = True

    out = {k: [] for k in ("E", "T", "q", "t_stop", "nfev", "wall_s")}
    with jax.enable_x64(True):
        for y0 in ics:
            _one(f, small, y0, out)
    return {k: np.asarray(v) for k, v in out.items()}


def _one(f, small, y0, out) -> None:
    """One row of `scipy_rows`, appended to ``out``."""
    from scipy.integrate import solve_ivp

    t0 = time.perf_counter()
    sol = solve_ivp(f, (0.0, T_FINAL), np.concatenate([y0, [0.0]]), method="DOP853", rtol=1e-12, atol=1e-15,
                    dense_output=True, events=small)
    assert sol.status in (0, 1), sol.message
    t_end = sol.t[-1]
    grid = np.linspace(0.0, t_end, int(t_end / 1e-3) + 2)
    Y = sol.sol(grid)
    th = Y[2] - TWO_PI * np.round(Y[2] / TWO_PI)
    outside = Y[0] ** 2 + Y[1] ** 2 + th ** 2 > EPS ** 2
    if outside[-1]:
        T = np.inf
    elif not outside.any():
        T = 0.0
    else:
        i = int(np.flatnonzero(outside)[-1])
        lo, hi = grid[i], grid[i + 1]
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            y = sol.sol(mid)
            tm = y[2] - TWO_PI * np.round(y[2] / TWO_PI)
            lo, hi = (mid, hi) if y[0] ** 2 + y[1] ** 2 + tm ** 2 > EPS ** 2 else (lo, mid)
        T = hi
    out["E"].append(sol.y[5, -1])
    out["T"].append(T)
    out["q"].append(sol.y[:3, -1])
    out["t_stop"].append(t_end)
    out["nfev"].append(sol.nfev)
    out["wall_s"].append(time.perf_counter() - t0)


def diff(a: dict, ref: dict) -> dict:
    """Per row: relative energy, |dT| (0 where neither settled, inf where one did), final position (heading mod 2 pi)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        dE = np.abs(a["E"] / ref["E"] - 1.0)
        dT = np.where(np.isinf(a["T"]) & np.isinf(ref["T"]), 0.0, np.abs(a["T"] - ref["T"]))
        dq = a["q"] - ref["q"]
        dq[:, 2] -= TWO_PI * np.round(dq[:, 2] / TWO_PI)
        dy = np.max(np.abs(dq), axis=1)
    return {"dE": np.nan_to_num(dE, nan=np.inf), "dT": np.nan_to_num(dT, nan=np.inf),
            "dy": np.nan_to_num(dy, nan=np.inf)}


def count(d: dict) -> dict:
    off = (d["dE"] > THRESHOLDS["energy_rel"]) | (d["dT"] > THRESHOLDS["T_eps_s"]) | (d["dy"] > THRESHOLDS["state"])
    fin = lambda v: float(np.max(v)) if np.all(np.isfinite(v)) else None  # noqa: E731
    return {"rows": int(d["dE"].size), "energy_off_5pct": int(np.sum(d["dE"] > 0.05)),
            "energy_off_2pct": int(np.sum(d["dE"] > 0.02)), "T_eps_off_0.05s": int(np.sum(d["dT"] > 0.05)),
            "final_position_off_1e-3": int(np.sum(d["dy"] > 1e-3)), "off_any_threshold": int(off.sum()),
            "off_rows": np.flatnonzero(off).tolist(),
            "worst_energy_rel": fin(d["dE"]), "worst_T_eps_s": fin(d["dT"]), "worst_final_position": fin(d["dy"])}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--law", default="aicardi")
    ap.add_argument("--n", type=int, default=64)
    ap.add_argument("--tols", default="1e-10,1e-12,1e-13,1e-14")
    ap.add_argument("--scipy-every", type=int, default=4, help="0: no SciPy rows")
    ap.add_argument("--sets", default="readme,near_theta0,wide,far")
    ap.add_argument("--out", default="out/law_reference.json")
    a = ap.parse_args(argv)
    import jax

    from jaxsleigh.controllers.registry import make_controller

    law = make_controller(a.law)
    tols = [float(x) for x in a.tols.split(",")]
    doc = {"command": "python experiments/studies/law_reference.py " + " ".join(sys.argv[1:]),
           "machine": {"arch": platform.machine(), "processor": platform.processor(), "python": platform.python_version(),
                       "jax": jax.__version__},
           "law": a.law, "dtype": "float32 run at the defaults; float64 references", "t_final": T_FINAL, "eps": EPS,
           "thresholds": THRESHOLDS, "load_start": load(), "sets": {}}
    sets = start_sets(a.n)
    for name in a.sets.split(","):
        ics = sets[name]
        run = _run(ics, law)
        refs = {tol: _run(ics, law, tol) for tol in tols}
        tight = refs[tols[-1]]
        rec = {"rows": len(ics), "float32_wall_s": round(run["wall_s"], 1),
               "float32_steps_median": float(np.median(run["steps"])),
               "float64": {f"{t:g}": {"wall_s": round(refs[t]["wall_s"], 1),
                                      "steps_median": float(np.median(refs[t]["steps"])),
                                      "steps_max": int(np.max(refs[t]["steps"])),
                                      "status_not_ok": int(np.sum(refs[t]["status"] != 0)),
                                      "against_tightest": count(diff(refs[t], tight))} for t in tols[:-1]},
               "float32_against": {f"{t:g}": count(diff(run, refs[t])) for t in tols}}
        if a.scipy_every:
            rows = np.arange(0, len(ics), a.scipy_every)
            sp = scipy_rows(ics[rows], law)
            sub = lambda r: {k: v[rows] for k, v in r.items() if k in ("E", "T", "q")}  # noqa: E731
            rec["scipy"] = {"rows": rows.tolist(), "wall_s": round(float(sp["wall_s"].sum()), 1),
                            "nfev_median": float(np.median(sp["nfev"])),
                            "t_stop_range": [float(sp["t_stop"].min()), float(sp["t_stop"].max())],
                            "float64_against_scipy": {f"{t:g}": count(diff(sub(refs[t]), sp)) for t in tols},
                            "float32_against_scipy": count(diff(sub(run), sp))}
        doc["sets"][name] = rec
        print(name, json.dumps(rec), flush=True)
    doc["load_end"] = load()
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(doc, indent=1) + "\n")


if __name__ == "__main__":
    main()
