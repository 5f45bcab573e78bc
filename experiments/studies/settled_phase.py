r"""The settled phase: can an exponential RK4 remove the step limit set by the
stiff injected damping k / theta^2 once the sleigh sits next to theta = 0?

    python experiments/studies/settled_phase.py [--t-final 300] [--gains paper tuned] [--n-starts 6]
                                                [--max-step 0.1 10] [--out out/settled_phase.json]

Near theta = w1 = 0 the p2 equation carries the linear damping term
``-(D22 + k / w1^2) p2 / (J + m l^2)`` whose rate ``lam = -(D22 + k / w1^2) / (J + m l^2)`` grows
without bound as theta -> 0; classical RK4 is stable only for ``|lam h| <~ 2.8``, so the adaptive
default's steps are set by stability there, not by accuracy. Three steppers are prototyped here
(the library's ``jaxsleigh/integrate/stepper.py`` is not changed), all with the library's controller
(``h / 6 (k4 - k5)`` error estimate with FSAL, factor ``clip(0.9 err^-1/4, 0.1, 5)``, rejection on
non-finite values, on a w1 sign change and on a rise of H_d), its T_eps observer (dense output
and bisection, :class:`jaxsleigh.integrate.observers.ConvergenceTime`) and its tolerances:

* ``rk4``: classical RK4 (a copy of the library's adaptive step; checks the prototype);
* ``lawson``: integrating-factor RK4 (Lawson), ``z = exp(-lam (t - t_n)) p2``, lam frozen at the
  step's start; the other four components are plain RK4;
* ``etd``: exponential time differencing RK4 of Cox & Matthews (2002) with the same frozen,
  diagonal lam: it reduces to classical RK4 where lam h -> 0 and integrates ``p2' = lam p2 + g``
  exactly for constant g (the slaved, quasi-static p2 of the settled phase), which Lawson does not.

The error estimate of the exponential steppers is the same difference of the last stage and the
FSAL evaluation, weighted as that stage is in the step (``h f3 (N4 - N5)``, ``h/6 E(0) (K4 - K5)``),
which is the library's estimate where lam h -> 0.

Measured on a few starts of the benchmark workload (x, y ~ U(-3, 3), |theta0| ~ U(0.3, pi)) and
the paper's start, for the paper's gains and the ``tuned`` preset, against a float64 reference
(the library's adaptive RK4 at rtol = atol = 1e-11): attempted steps per simulated second after
the reference's T_eps (the settled phase), final-state error, T_eps error. Float32, like the
default path.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np


LATE = 0.8  # the last 20% of the horizon: the steps/s the settled phase ends with


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--t-final", type=float, default=300.0)
    ap.add_argument("--gains", nargs="+", default=["paper", "tuned"])
    ap.add_argument("--n-starts", type=int, default=6, help="starts from the workload (plus the paper's start)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--methods", nargs="+", default=["rk4", "lawson", "etd"])
    ap.add_argument("--max-step", type=float, nargs="+", default=[0.1, 10.0],
                    help="step caps to try (0.1: the library's 10 dt)")
    ap.add_argument("--rtol", type=float, default=1e-6)
    ap.add_argument("--atol", type=float, default=1e-6)
    ap.add_argument("--max-steps", type=int, default=3_000_000)
    ap.add_argument("--out", default="out/settled_phase.json")
    ap.add_argument("--eig-only", action="store_true",
                    help="only the Jacobian eigenvalues along the first start's float64 trajectory, with and "
                         "without the frozen stiff term lam (what limits each stepper)")
    a = ap.parse_args(argv)
    if a.eig_only:
        return eigenvalues(a)

    import jax
    import jax.numpy as jnp

    import jaxsleigh as js
    from jaxsleigh.studies.bench import workload
    from jaxsleigh.model.closed_loop import ClosedLoop, closed_loop_hamiltonian_w, state_from_w, state_to_w
    from jaxsleigh.integrate.observers import ConvergenceTime, StepInfo

    log = lambda *m: print(*m, file=sys.stderr, flush=True)  # noqa: E731
    ics = workload(a.n_starts, a.seed)
    plant = js.paper_plant()
    dtype = jnp.float32
    eps_ball = 0.05
    f = js.vector_field_w

    class Ctl(NamedTuple):
        eps: jax.Array

    obs = ConvergenceTime()

    def phis(z):
        """phi_1..3(z) for z <= 0 (float32): series for |z| < 1, closed forms otherwise."""
        zs = jnp.where(jnp.abs(z) < 1.0, z, 0.0)

        def series(k):  # phi_k(z) = sum_j z^j / (j + k)!, 14 terms: truncation < 1e-11 for |z| < 1
            term, acc = jnp.ones_like(z), jnp.zeros_like(z)
            for j in range(14):
                acc = acc + term / float(math.factorial(j + k))
                term = term * zs
            return acc

        zl = jnp.where(jnp.abs(z) < 1.0, -1.0, z)
        p1 = jnp.expm1(zl) / zl
        p2 = (p1 - 1.0) / zl
        p3 = (p2 - 0.5) / zl
        small = jnp.abs(z) < 1.0
        return jnp.where(small, series(1), p1), jnp.where(small, series(2), p2), jnp.where(small, series(3), p3)

    def make_run(method: str, args: ClosedLoop, t_final: float, max_step: float):
        I = args.plant.J + args.plant.m * args.plant.l * args.plant.l
        k, D22 = args.gains.k, args.gains.D_hat[1, 1]
        e5 = jnp.array([0.0, 0.0, 0.0, 0.0, 1.0], dtype)

        def lam_of(y):
            return (-(D22 + k / (y[0] * y[0])) / I).astype(dtype)

        def step(y, fy, h):
            """-> y_new, f(y_new), error vector"""
            if method == "rk4":
                k1 = fy
                k2 = f(0.0, y + (0.5 * h) * k1, args)
                k3 = f(0.0, y + (0.5 * h) * k2, args)
                k4 = f(0.0, y + h * k3, args)
                y_new = y + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
                f_new = f(0.0, y_new, args)
                return y_new, f_new, (h / 6.0) * (k4 - f_new)
            lam = lam_of(y)
            N = lambda yy, fyy: fyy - lam * yy[4] * e5  # noqa: E731  (the non-stiff rest)
            E = lambda tau: jnp.where(e5 > 0, jnp.exp(lam * tau), 1.0)  # noqa: E731
            Eh2, Eh = E(0.5 * h), E(h)
            if method == "lawson":
                K1 = N(y, fy)
                Y2 = Eh2 * (y + (0.5 * h) * K1)
                K2 = N(Y2, f(0.0, Y2, args))
                Y3 = Eh2 * y + (0.5 * h) * K2
                K3 = N(Y3, f(0.0, Y3, args))
                Y4 = Eh * y + h * (Eh2 * K3)
                K4 = N(Y4, f(0.0, Y4, args))
                y_new = Eh * y + (h / 6.0) * (Eh * K1 + 2.0 * Eh2 * (K2 + K3) + K4)
                f_new = f(0.0, y_new, args)
                return y_new, f_new, (h / 6.0) * (K4 - N(y_new, f_new))
            # etd: Cox-Matthews ETDRK4 with diagonal L = lam e5 (phi functions of z = lam h)
            p1h, _, _ = phis(lam * 0.5 * h)
            p1, p2, p3 = phis(lam * h)
            a1 = jnp.where(e5 > 0, p1h, 1.0)                     # phi_1(L h / 2)
            f1 = jnp.where(e5 > 0, p1 - 3.0 * p2 + 4.0 * p3, 1.0 / 6.0)
            f2 = jnp.where(e5 > 0, p2 - 2.0 * p3, 1.0 / 6.0)
            f3 = jnp.where(e5 > 0, -p2 + 4.0 * p3, 1.0 / 6.0)
            Nu = N(y, fy)
            A = Eh2 * y + (0.5 * h) * a1 * Nu
            Na = N(A, f(0.0, A, args))
            B = Eh2 * y + (0.5 * h) * a1 * Na
            Nb = N(B, f(0.0, B, args))
            C = Eh2 * A + (0.5 * h) * a1 * (2.0 * Nb - Nu)
            Nc = N(C, f(0.0, C, args))
            y_new = Eh * y + h * (f1 * Nu + 2.0 * f2 * (Na + Nb) + f3 * Nc)
            f_new = f(0.0, y_new, args)
            return y_new, f_new, h * f3 * (Nc - N(y_new, f_new))

        def run_one(y0, t_mark):
            ctl = Ctl(eps=jnp.asarray(eps_ball, dtype))
            fy0 = f(0.0, y0, args)
            tcap = jnp.asarray(t_final, dtype)
            t_late = jnp.asarray(LATE * t_final, dtype)
            carry = dict(t=jnp.zeros((), dtype), t_lo=jnp.zeros((), dtype), y=y0, fy=fy0,
                         h=jnp.asarray(0.01, dtype), Hd=closed_loop_hamiltonian_w(y0, args),
                         n_acc=jnp.int32(0), n_rej=jnp.int32(0), n_settled=jnp.int32(0), n_late=jnp.int32(0), fail=jnp.int32(0),
                         obs=obs.init(jnp.zeros((), dtype), y0, None, ctl),
                         hmin_settled=jnp.asarray(np.inf, dtype), hmax_settled=jnp.zeros((), dtype))

            def cond(c):
                return (c["t"] < tcap) & (c["n_acc"] + c["n_rej"] < a.max_steps) & (c["fail"] == 0)

            def body(c):
                remaining = (tcap - c["t"]) - c["t_lo"]
                hit = remaining <= 1.01 * c["h"]
                h = jnp.where(hit, remaining, c["h"])
                y_new, f_new, errv = step(c["y"], c["fy"], h)
                finite = jnp.all(jnp.isfinite(y_new)) & jnp.all(jnp.isfinite(f_new))
                crossed = jnp.sign(y_new[0]) != jnp.sign(c["y"][0])
                Hd_new = closed_loop_hamiltonian_w(y_new, args)
                rose = Hd_new > c["Hd"] * (1.0 + 1e-6 + 64.0 * jnp.finfo(dtype).eps)
                noise = 16.0 * jnp.finfo(dtype).eps * jnp.abs(h) * jnp.maximum(jnp.abs(c["fy"]), jnp.abs(f_new))
                scale = a.atol + a.rtol * jnp.maximum(jnp.abs(c["y"]), jnp.abs(y_new)) + noise
                err = jnp.max(jnp.abs(errv) / scale)
                good = finite & ~crossed & ~rose
                err = jnp.where(good, err, jnp.inf)
                ok = good & (err <= 1.0)
                fac = jnp.clip(0.9 * jax.lax.rsqrt(jnp.sqrt(err)), 0.1, 5.0)
                h_next = h * fac
                h_next = jnp.where(ok & hit, jnp.maximum(h_next, c["h"]), h_next)
                h_next = jnp.minimum(h_next, max_step).astype(dtype)
                s = c["t"] + h
                bb = s - c["t"]
                t_err = (c["t"] - (s - bb)) + (h - bb)
                t_new = jnp.where(hit, tcap, s)
                t_lo_new = jnp.where(hit, 0.0, c["t_lo"] + t_err).astype(dtype)
                info = StepInfo(t=c["t"], h=h, t_new=t_new + t_lo_new, y=c["y"], y_new=y_new, k1=c["fy"], k5=f_new,
                                u_new=None, acc=ok)
                settled = c["t"] >= t_mark
                return dict(
                    t=jnp.where(ok, t_new, c["t"]).astype(dtype), t_lo=jnp.where(ok, t_lo_new, c["t_lo"]),
                    y=jnp.where(ok, y_new, c["y"]), fy=jnp.where(ok, f_new, c["fy"]), h=h_next,
                    Hd=jnp.where(ok, Hd_new, c["Hd"]),
                    n_acc=c["n_acc"] + ok.astype(jnp.int32), n_rej=c["n_rej"] + (~ok).astype(jnp.int32),
                    n_settled=c["n_settled"] + settled.astype(jnp.int32),
                    n_late=c["n_late"] + (c["t"] >= t_late).astype(jnp.int32),
                    fail=jnp.where(~ok & (h_next < 1e-18), 1, c["fail"]).astype(jnp.int32),
                    obs=obs.update(c["obs"], info, ctl),
                    hmin_settled=jnp.where(settled & ok, jnp.minimum(c["hmin_settled"], h), c["hmin_settled"]),
                    hmax_settled=jnp.where(settled & ok & ~hit, jnp.maximum(c["hmax_settled"], h), c["hmax_settled"]))

            out = jax.lax.while_loop(cond, body, carry)
            return out["y"], out["t"], out["n_acc"], out["n_rej"], out["n_settled"], out["fail"], out["obs"][0], \
                out["hmin_settled"], out["hmax_settled"], out["n_late"], out["y"][0]

        return jax.jit(jax.vmap(run_one))

    results = []
    for gname in a.gains:
        gains = js.load_gains(gname)
        args = ClosedLoop(plant, gains)
        log(f"[{gname}] float64 reference (rtol = atol = 1e-11), {len(ics)} starts, t_final {a.t_final:g} ...")
        t0 = time.perf_counter()
        ref = js.run_ensemble(ics, gains=gains, t_final=a.t_final, x64=True, run=js.RunOptions(progress=False),
                              stepsize=js.StepSizeController(rtol=1e-11, atol=1e-11, max_steps=20_000_000))
        log(f"  {time.perf_counter() - t0:.1f} s; status {ref.status.tolist()}, T_eps {np.round(ref.T_eps, 3).tolist()}")
        ref_state = np.concatenate([ref.q_final, ref.p_final], axis=1)
        lib = js.run_ensemble(ics, gains=gains, t_final=a.t_final, run=js.RunOptions(progress=False),
                              stepsize=js.StepSizeController(max_steps=a.max_steps))
        lib_err = np.max(np.abs(np.concatenate([lib.q_final, lib.p_final], axis=1) - ref_state), axis=1)
        y0w = np.asarray(state_to_w(jnp.asarray(np.concatenate([ics, np.zeros((len(ics), 2))], axis=1).T)).T, np.float32)
        t_mark = np.where(np.isfinite(ref.T_eps), ref.T_eps, np.inf).astype(np.float32)
        row_lib = {"gains": gname, "method": "library adaptive default (float32)", "max_step": 0.1,
                   "n_steps": lib.n_steps.tolist(), "final_err": lib_err.tolist(),
                   "T_eps_err": np.abs(lib.T_eps - ref.T_eps).tolist()}
        results.append(row_lib)
        log(f"  library default: steps {lib.n_steps.tolist()}, final err {np.max(lib_err):.2e}, "
            f"T_eps err {np.nanmax(np.abs(lib.T_eps - ref.T_eps)):.2e}")
        for method in a.methods:
            for ms in a.max_step:
                run = make_run(method, args, a.t_final, ms)
                t0 = time.perf_counter()
                yf, tf, na, nr, ns, fail, teps, hmin, hmax, nl, w1f = (np.asarray(v) for v in run(jnp.asarray(y0w),
                                                                                         jnp.asarray(t_mark)))
                wall = time.perf_counter() - t0
                t0 = time.process_time()
                jax.block_until_ready(run(jnp.asarray(y0w), jnp.asarray(t_mark)))
                cpu_warm = time.process_time() - t0          # compiled: the stepping alone
                st = np.asarray(state_from_w(jnp.asarray(yf.T)).T, np.float64)
                err = np.max(np.abs(st - ref_state), axis=1)
                qerr = np.max(np.abs(st[:, :3] - ref.q_final), axis=1)
                qref = np.max(np.abs(ref.q_final), axis=1)
                settled_span = a.t_final - ref.T_eps
                rate = np.where(settled_span > 1.0, ns / np.maximum(settled_span, 1e-9), np.nan)
                row = {"gains": gname, "method": method, "max_step": ms, "wall_s_incl_compile": wall,
                       "cpu_s_warm": cpu_warm, "cpu_us_per_attempt": 1e6 * cpu_warm / float(np.max(na + nr)),
                       "t_reached": tf.tolist(), "failed": fail.tolist(),
                       "n_accept": na.tolist(), "n_reject": nr.tolist(), "n_settled_attempts": ns.tolist(),
                       "settled_steps_per_s": rate.tolist(), "settled_h_min": hmin.tolist(),
                       "late_steps_per_s": (nl / ((1 - LATE) * a.t_final)).tolist(), "theta_final": w1f.tolist(),
                       "settled_h_max": hmax.tolist(),
                       "final_err": err.tolist(), "q_err": qerr.tolist(), "q_ref_max": qref.tolist(),
                       "T_eps": teps.tolist(), "T_eps_ref": ref.T_eps.tolist(),
                       "T_eps_err": np.abs(teps - ref.T_eps).tolist()}
                results.append(row)
                log(f"  {method:6s} cap {ms:5g}: steps {(na + nr).tolist()} (rej {nr.tolist()}); settled steps/s "
                    f"{np.round(rate, 1).tolist()}, in the last {100 * (1 - LATE):.0f}% of the horizon "
                    f"{np.round(nl / ((1 - LATE) * a.t_final), 1).tolist()}; |theta(T)| {np.abs(w1f).max():.1e}; final err max {np.max(err):.2e}; q err/|q_ref| max "
                    f"{np.max(qerr / np.maximum(qref, 1e-30)):.2e}; T_eps err max {np.nanmax(np.abs(teps - ref.T_eps)):.2e}"
                    f"; failed {int(fail.sum())}; warm {cpu_warm:.2f} CPU s "
                    f"({1e6 * cpu_warm / float(np.max(na + nr)):.1f} us per attempt of the longest lane)")
    out = {"command": "python experiments/studies/settled_phase.py " + " ".join(sys.argv[1:] if argv is None else argv),
           "ics": ics.tolist(), "t_final": a.t_final, "rtol": a.rtol, "atol": a.atol, "dtype": "float32",
           "results": results}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(out, indent=1) + "\n")
    log(f"wrote {a.out}")
    return 0


def eigenvalues(a) -> int:
    """Largest Jacobian eigenvalues of the closed loop at the float64 reference state at a few
    times, with and without the frozen term ``lam`` on p2 that the exponential steppers take out."""
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import jaxsleigh as js
    from jaxsleigh.studies.bench import workload
    from jaxsleigh.model.closed_loop import ClosedLoop, state_to_w

    ics = workload(1, a.seed)
    plant = js.paper_plant()
    I = plant.J + plant.m * plant.l * plant.l
    rows = []
    for gname in a.gains:
        gains = js.load_gains(gname)
        args = ClosedLoop(plant, gains)
        for T in (a.t_final / 3, 2 * a.t_final / 3, a.t_final):
            r = js.run_ensemble(ics, gains=gains, t_final=T, x64=True, run=js.RunOptions(progress=False),
                                stepsize=js.StepSizeController(rtol=1e-10, atol=1e-10, max_steps=20_000_000))
            y = state_to_w(jnp.asarray(np.concatenate([r.q_final[0], r.p_final[0]])))
            jac = np.asarray(jax.jacfwd(lambda yy: js.vector_field_w(0.0, yy, args))(y))
            lam = float(-(gains.D_hat[1, 1] + gains.k / y[0] ** 2) / I)
            rest = jac.copy()
            rest[4, 4] -= lam
            ev = sorted(np.linalg.eigvals(jac), key=abs)
            evr = sorted(np.linalg.eigvals(rest), key=abs)
            row = {"gains": gname, "t": T, "theta": float(y[0]), "lam": lam,
                   "eig_full_largest": [str(np.round(e, 2)) for e in ev[-2:]],
                   "eig_without_lam_largest": [str(np.round(e, 2)) for e in evr[-2:]],
                   # classical RK4 is stable for h |z| <~ 2.785 on the negative real axis, 2.828 on the imaginary
                   "rk4_h_max_full": float(2.785 / abs(ev[-1])), "rk4_h_max_without_lam": float(2.828 / abs(evr[-1]))}
            rows.append(row)
            print(f"{gname:6s} t {T:6.1f}: theta {row['theta']:+.2e}, lam {lam:.3e}; largest eigenvalues "
                  f"{row['eig_full_largest']} -> without lam {row['eig_without_lam_largest']}; RK4 stability "
                  f"h <= {row['rk4_h_max_full']:.2e} -> {row['rk4_h_max_without_lam']:.2e} "
                  f"({1 / row['rk4_h_max_full']:.0f} -> {1 / row['rk4_h_max_without_lam']:.0f} steps/s)")
    out = Path(a.out).with_name(Path(a.out).stem + "_eig.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
