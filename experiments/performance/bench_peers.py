r"""jaxsleigh against its peers on the benchmark workload, in one run.

    python experiments/performance/bench_peers.py [--n-ics 4096] [--t-final 100] [--dt 0.01] [--x64] [--seed 0]
                                                  [--skip numpy,scipy,...] [--scipy-n 8] [--repeats 1]
                                                  [--cache out/bench_cache] [--out out/bench_peers.json]

Workload: :func:`jaxsleigh.studies.bench.workload` (``--n-ics`` starts, x, y ~ U(-3, 3), |theta0| ~ U(0.3, pi),
zero momentum), classical RK4 at ``--dt`` up to ``--t-final`` (``steps = t_final / dt``), final state
only, float32 unless ``--x64``. Every JAX figure is warm: a first call on the same shapes compiles and
is not timed. Correctness: final-state max-norm error against the float64 reference
(:func:`jaxsleigh.studies.bench.reference_final`, cached in ``--cache``) ``<= 1e-3`` and finite.

Peers (names for ``--skip``):

``vmap``       plain ``jit(vmap(lax.scan(rk4)))`` in the physical chart with
               :func:`jaxsleigh.model.closed_loop.vector_field`, state (5,) per trajectory (the baseline);
``numpy``      NumPy vectorised RK4, an independent closed loop written here from the formulas
               (five (N,) arrays); checked against ``vector_field`` on random states first;
``diffrax_rk4`` vmapped ``diffrax.diffeqsolve`` with a classical RK4 Butcher tableau
               (an ``AbstractERK`` subclass), ``ConstantStepSize``, ``max_steps = steps``;
``tsit5``      vmapped diffrax ``Tsit5`` + ``PIDController(rtol=1e-6, atol=1e-8)``, ``max_steps=100000``;
``scipy``      ``scipy.integrate.solve_ivp`` RK45 (float64, same tolerances) in a Python loop over
               ``--scipy-n`` starts, extrapolated to N;
``jaxsleigh``  :func:`jaxsleigh.studies.bench.bench`: fixed-step RK4 (``check_passivity=False``), the
               passivity-checked RK4 and the adaptive accurate mode (w chart).

For adaptive methods "trajectory-steps / s" is the equivalent ``N * steps / wall``. The table gives
ratios against the plain vmap peer and against diffrax Tsit5 (correct trajectories / s).
Progress goes to stderr; the table to stdout; everything to ``--out`` as JSON.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
import traceback
from pathlib import Path
from typing import ClassVar

import numpy as np

import jax
import jax.numpy as jnp

from jaxsleigh.studies.bench import CORRECT_TOL, bench, final_state_error, machine, peak_rss_mb, reference_final, workload
from jaxsleigh.model.closed_loop import ClosedLoop, vector_field
from jaxsleigh.model.params import paper_gains, paper_plant
from jaxsleigh.integrate.rk4 import rk4_step

PEERS = ("vmap", "numpy", "diffrax_rk4", "tsit5", "scipy", "jaxsleigh")
TSIT5_RTOL, TSIT5_ATOL, TSIT5_MAX_STEPS = 1e-6, 1e-8, 100_000


def log(*a):
    print(*a, file=sys.stderr, flush=True)


def timed(fn, repeats=1):
    """(best wall of ``repeats`` timed calls after one untimed warm-up call, last output, warm-up wall)."""
    t0 = time.perf_counter()
    fn()
    warm = time.perf_counter() - t0
    best, out = math.inf, None
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out, warm


def row(name, *, wall, n, steps, final=None, ref=None, ok=None, extra=None):
    """One result record; ``final`` (N, 5) is judged against ``ref``; ``ok`` (N,) extra success flags."""
    rec = {"peer": name, "wall_s": wall, "n": n, "traj_steps_per_s": n * steps / wall}
    if final is not None:
        final = np.asarray(final, np.float64)
        err = final_state_error(final[:, :3], final[:, 3:], ref)
        good = np.isfinite(err) & (err <= CORRECT_TOL)
        if ok is not None:
            good &= np.asarray(ok, bool)
        rec.update(correct=int(good.sum()), wrong_or_nonfinite=int((~good).sum()),
                   nonfinite=int((~np.all(np.isfinite(final), axis=1)).sum()),
                   correct_per_s=float(good.sum() / wall),
                   max_error_finite=float(np.max(err[np.isfinite(err)], initial=0.0)))
    if extra:
        rec.update(extra)
    return rec


# ---------------------------------------------------------------------------------------------------
# plain JAX peer: jit(vmap(lax.scan(rk4))) with the library's physical-chart vector field

def run_vmap(y0, args, dt, steps, repeats):
    def one(y, a):
        def body(y, _):
            return rk4_step(vector_field, 0.0, y, dt, a), None
        return jax.lax.scan(body, y, None, length=steps)[0]

    f = jax.jit(jax.vmap(one, in_axes=(0, None)))
    y0 = jnp.asarray(y0)
    wall, out, warm = timed(lambda: jax.block_until_ready(f(y0, args)), repeats)
    return wall, np.asarray(out), {"first_call_s": warm}


# ---------------------------------------------------------------------------------------------------
# NumPy peer: the closed loop written out from the formulas, physical chart, five (N,) arrays

class NumpyClosedLoop:
    """Closed loop (plant eq. 1-2 + control eq. 13 with the *derived* Q_w) on (N,) arrays.

    Constants are Python floats so that float32 arrays stay float32 (NEP 50).
    """

    def __init__(self, plant, gains):
        m, J, l = float(plant.m), float(plant.J), float(plant.l)
        self.inv_m, self.inv_I = 1.0 / m, 1.0 / (J + m * l * l)
        self.gyro = m * l / (J + m * l * l)
        d = plant.damping
        if type(d).__name__ != "CoulombDamping":
            raise NotImplementedError("the NumPy peer implements the paper's Coulomb damping only")
        self.d_eps, self.d_scale = float(d.eps), float(d.scale)
        L = np.asarray(gains.L, np.float64)
        D = np.asarray(gains.D_hat, np.float64)
        self.L1, self.L2, self.L3 = (float(v) for v in L)
        self.k = float(gains.k)
        self.D00, self.D01, self.D10, self.D11 = (float(v) for v in D.ravel())

    def __call__(self, x, y, th, p1, p2):
        c, s = np.cos(th), np.sin(th)
        v1, v2 = p1 * self.inv_m, p2 * self.inv_I          # v = M^{-1} p
        # w = f_w(f_z(q)):  z2 = x c + y s, z3 = x s - y c, w = (th, z2/th - 2 z3/th^2, 2 z3/th^2)
        inv = 1.0 / th
        z2 = x * c + y * s
        z3 = x * s - y * c
        w3 = (2.0 * inv * inv) * z3
        w2 = z2 * inv - w3
        # Q_w^T L w with Q_w = [[0, 1], [1/w1, -(3 w2 + w3)/w1 - w1 w3 / 2], [0, 2 w2 / w1]]
        Lw2 = self.L2 * w2
        f0 = inv * Lw2
        f1 = (self.L1 * th + (-(3.0 * w2 + w3) * inv - 0.5 * th * w3) * Lw2
              + (2.0 * self.L3) * (w2 * inv) * w3)
        # u = -Q_w^T L w - D_hat v - diag(0, k / w1^2) v
        u1 = -f0 - (self.D00 * v1 + self.D01 * v2)
        u2 = -f1 - (self.D10 * v1 + (self.D11 + self.k * inv * inv) * v2)
        # pdot = J(p) v - D(p) v + u,  J(p) = (m l / (J + m l^2)) p2 [[0, 1], [-1, 0]],
        # D(p) = scale diag(1/sqrt(eps + p1^2), 1/sqrt(eps + p2^2))
        a = self.gyro * p2
        p1d = a * v2 - (self.d_scale / np.sqrt(self.d_eps + p1 * p1)) * v1 + u1
        p2d = -a * v1 - (self.d_scale / np.sqrt(self.d_eps + p2 * p2)) * v2 + u2
        return (c * v1, s * v1, v2, p1d, p2d)   # qdot = (cos th v1, sin th v1, v2)


def numpy_rk4(f, y, dt, steps):
    """Classical RK4 on a tuple of (N,) arrays; returns the final tuple."""
    h = y[0].dtype.type(dt)
    h2, h6 = h / 2, h / 6
    for _ in range(steps):
        k1 = f(*y)
        k2 = f(*[yi + h2 * ki for yi, ki in zip(y, k1)])
        k3 = f(*[yi + h2 * ki for yi, ki in zip(y, k2)])
        k4 = f(*[yi + h * ki for yi, ki in zip(y, k3)])
        y = tuple(yi + h6 * (a + 2 * (b + c) + d) for yi, a, b, c, d in zip(y, k1, k2, k3, k4))
    return y


def check_numpy_field(args, dtype, n=2000, seed=1):
    """Compare the NumPy closed loop with ``vector_field`` on random states; returns a dict."""
    rng = np.random.default_rng(seed)
    th = rng.uniform(0.3, np.pi, n) * rng.choice([-1.0, 1.0], n)
    ys = np.column_stack([rng.uniform(-3, 3, (n, 2)), th, rng.uniform(-2, 2, (n, 2))])
    f = NumpyClosedLoop(args.plant, args.gains)

    def jax_field(yy, x64):
        with jax.enable_x64(x64):
            vf = jax.jit(jax.vmap(vector_field, in_axes=(None, 0, None)))
            return np.asarray(vf(0.0, jnp.asarray(yy), args), np.float64)

    truth = jax_field(ys, True)                                      # vector_field in float64
    scale = np.max(np.abs(truth), axis=1)

    def rel(a):
        return float(np.max(np.max(np.abs(a - truth), axis=1) / scale))

    out = {}
    for name, dt in (("float64", np.float64), ("float32", np.float32)):
        yd = ys.astype(dt)
        got = np.column_stack(f(*yd.T)).astype(np.float64)
        # compare on the rounded states, so that only the arithmetic differs
        t_rounded = jax_field(yd.astype(np.float64), True)
        out[f"numpy_{name}_vs_vector_field_f64"] = float(
            np.max(np.max(np.abs(got - t_rounded), axis=1) / np.max(np.abs(t_rounded), axis=1)))
    out["vector_field_f32_vs_f64"] = rel(jax_field(ys.astype(np.float32), False))
    tol = 1e-10 if dtype == np.float64 else 1e-5
    key = f"numpy_{np.dtype(dtype).name}_vs_vector_field_f64"
    out.update(n_states=n, tol=tol, checked=key, passed=bool(out[key] <= tol and out["numpy_float64_vs_vector_field_f64"] <= 1e-10))
    return out


def run_numpy(y0, args, dt, steps, repeats, dtype):
    chk = check_numpy_field(args, dtype)
    log("  NumPy closed loop vs vector_field (max norm-wise relative difference over "
        f"{chk['n_states']} random states): float64 {chk['numpy_float64_vs_vector_field_f64']:.2e}, "
        f"float32 {chk['numpy_float32_vs_vector_field_f64']:.2e} "
        f"(vector_field float32 itself: {chk['vector_field_f32_vs_f64']:.2e}) -> "
        f"{'PASS' if chk['passed'] else 'FAIL'}")
    print(f"NumPy closed-loop check vs jaxsleigh.model.closed_loop.vector_field on {chk['n_states']} random states "
          f"(max relative difference): numpy float64 {chk['numpy_float64_vs_vector_field_f64']:.2e}, "
          f"numpy float32 {chk['numpy_float32_vs_vector_field_f64']:.2e} "
          f"(vector_field float32: {chk['vector_field_f32_vs_f64']:.2e}); tolerance {chk['tol']:.0e}: "
          f"{'PASS' if chk['passed'] else 'FAIL'}")
    if not chk["passed"]:
        raise RuntimeError(f"NumPy closed loop disagrees with vector_field: {chk}")
    f = NumpyClosedLoop(args.plant, args.gains)
    cols = tuple(np.ascontiguousarray(c) for c in np.asarray(y0, dtype).T)
    numpy_rk4(f, cols, dt, 2)                                        # warm-up (allocator, caches)
    best, out = math.inf, None
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        out = numpy_rk4(f, cols, dt, steps)
        best = min(best, time.perf_counter() - t0)
    return best, np.column_stack(out), {"field_check": chk}


# ---------------------------------------------------------------------------------------------------
# diffrax peers

def _diffrax():
    import diffrax

    rk4_tableau = diffrax.ButcherTableau(
        a_lower=(np.array([0.5]), np.array([0.0, 0.5]), np.array([0.0, 0.0, 1.0])),
        b_sol=np.array([1 / 6, 1 / 3, 1 / 3, 1 / 6]),
        b_error=np.zeros(4),                     # no embedded method: constant steps only
        c=np.array([0.5, 0.5, 1.0]))

    class ClassicalRK4(diffrax.AbstractERK):
        """Classical RK4 (diffrax ships none): 4 stages, no error estimate."""
        tableau: ClassVar[diffrax.ButcherTableau] = rk4_tableau
        interpolation_cls: ClassVar = diffrax.ThirdOrderHermitePolynomialInterpolation.from_k

        def order(self, terms):
            del terms
            return 4

    return diffrax, ClassicalRK4


def run_diffrax(y0, args, t_final, dt, steps, repeats, adaptive):
    diffrax, ClassicalRK4 = _diffrax()
    term = diffrax.ODETerm(vector_field)
    if adaptive:
        solver = diffrax.Tsit5()
        ctrl = diffrax.PIDController(rtol=TSIT5_RTOL, atol=TSIT5_ATOL)
        max_steps = TSIT5_MAX_STEPS
    else:
        solver, ctrl, max_steps = ClassicalRK4(), diffrax.ConstantStepSize(), steps

    def one(y, a):
        sol = diffrax.diffeqsolve(term, solver, 0.0, t_final, dt, y, args=a, stepsize_controller=ctrl,
                                  saveat=diffrax.SaveAt(t1=True), max_steps=max_steps, throw=False)
        return sol.ys[-1], sol.result == diffrax.RESULTS.successful, sol.stats["num_accepted_steps"], \
            sol.stats["num_rejected_steps"]

    f = jax.jit(jax.vmap(one, in_axes=(0, None)))
    y0 = jnp.asarray(y0)
    wall, out, warm = timed(lambda: jax.block_until_ready(f(y0, args)), repeats)
    yf, ok, acc, rej = (np.asarray(o) for o in out)
    extra = {"first_call_s": warm, "max_steps": max_steps, "failed": int((~ok).sum()),
             "mean_steps": float(acc.mean()), "max_steps_taken": int(acc.max()),
             "mean_rejected": float(rej.mean())}
    if adaptive:
        extra.update(rtol=TSIT5_RTOL, atol=TSIT5_ATOL)
    return wall, yf, ok, extra


# ---------------------------------------------------------------------------------------------------
# scipy peer: solve_ivp RK45, float64, one trajectory at a time

def run_scipy(y0, args, t_final, n_sub):
    from scipy.integrate import solve_ivp

    f = NumpyClosedLoop(args.plant, args.gains)

    inv_m, inv_I, gyro, d_eps, d_scale = f.inv_m, f.inv_I, f.gyro, f.d_eps, f.d_scale
    L1, L2, L3, k, D00, D01, D10, D11 = f.L1, f.L2, f.L3, f.k, f.D00, f.D01, f.D10, f.D11
    cos, sin, sqrt = math.cos, math.sin, math.sqrt

    def rhs(t, y):
        # the NumPy formulas on Python floats: much faster than NumPy on arrays of 5
        x, yy, th, p1, p2 = y
        c, s = cos(th), sin(th)
        v1, v2 = p1 * inv_m, p2 * inv_I
        inv = 1.0 / th
        z2, z3 = x * c + yy * s, x * s - yy * c
        w3 = 2.0 * inv * inv * z3
        w2 = z2 * inv - w3
        Lw2 = L2 * w2
        f1 = L1 * th + (-(3.0 * w2 + w3) * inv - 0.5 * th * w3) * Lw2 + 2.0 * L3 * w2 * inv * w3
        u1 = -inv * Lw2 - (D00 * v1 + D01 * v2)
        u2 = -f1 - (D10 * v1 + (D11 + k * inv * inv) * v2)
        a = gyro * p2
        return [c * v1, s * v1, v2,
                a * v2 - d_scale / sqrt(d_eps + p1 * p1) * v1 + u1,
                -a * v1 - d_scale / sqrt(d_eps + p2 * p2) * v2 + u2]

    # the scalar rhs is the same formulas as the NumPy one: check it on the first start
    ref_rhs = np.column_stack(f(*np.asarray(y0[:1], np.float64).T))[0]
    assert np.allclose(rhs(0.0, np.asarray(y0[0], np.float64)), ref_rhs, rtol=1e-12, atol=1e-12)
    ys0 = np.asarray(y0[:n_sub], np.float64)
    solve_ivp(rhs, (0.0, min(t_final, 1.0)), ys0[0], method="RK45", rtol=TSIT5_RTOL, atol=TSIT5_ATOL)  # warm-up
    finals, steps, att, ok, per = [], [], [], [], []
    t_all = time.perf_counter()
    for i, y in enumerate(ys0):
        t0 = time.perf_counter()
        sol = solve_ivp(rhs, (0.0, t_final), y, method="RK45", rtol=TSIT5_RTOL, atol=TSIT5_ATOL)
        per.append(time.perf_counter() - t0)
        ok.append(sol.success)
        finals.append(sol.y[:, -1] if sol.success else np.full(5, np.nan))
        steps.append(len(sol.t) - 1)                 # accepted steps
        att.append((sol.nfev - 2) // 6)              # RK45: 6 evaluations per attempt, 2 at the start
        log(f"    scipy {i + 1}/{len(ys0)}: {per[-1]:.2f} s, {steps[-1]} steps")
    wall = time.perf_counter() - t_all
    return wall, np.array(finals), np.array(ok), {
        "n_measured": len(ys0), "wall_measured_s": wall, "s_per_traj": wall / len(ys0),
        "mean_steps": float(np.mean(steps)), "max_steps_taken": int(np.max(steps)),
        "mean_attempted_steps": float(np.mean(att)),
        "s_per_traj_max": float(max(per)), "rtol": TSIT5_RTOL, "atol": TSIT5_ATOL, "dtype": "float64"}


# ---------------------------------------------------------------------------------------------------

def fmt(x, spec=".3g"):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return format(x, spec)


def table(rows, base, tsit):
    def ratio(r, key, b):
        if b is None or r.get(key) is None or not b.get(key):
            return None
        return r[key] / b[key]

    lines = ["| implementation | wall [s] | traj-steps / s | correct / s | wrong or non-finite | steps mean / max "
             "| x vmap (steps/s) | x vmap (correct/s) | x Tsit5 (correct/s) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['label']} | failed: {r['error'][:60]} | | | | | | | |")
            continue
        wrong = r.get("wrong_or_nonfinite")
        if r.get("wrong_range") is not None:
            wrong = f"{r['wrong_range'][0]}-{r['wrong_range'][1]}"
        elif r.get("n_measured") is not None and r["peer"] == "scipy":
            wrong = f"{r['wrong_in_subset']} of {r['n_measured']}"
        sm = "-" if r.get("mean_steps") is None else f"{r['mean_steps']:.0f} / {r['max_steps_taken']}"
        lines.append(
            f"| {r['label']} | {fmt(r['wall_s'])} | {fmt(r['traj_steps_per_s'])} | {fmt(r.get('correct_per_s'))} "
            f"| {wrong if wrong is not None else '-'} | {sm} | {fmt(ratio(r, 'traj_steps_per_s', base), '.2f')} "
            f"| {fmt(ratio(r, 'correct_per_s', base), '.2f')} | {fmt(ratio(r, 'correct_per_s', tsit), '.2f')} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n-ics", type=int, default=4096)
    ap.add_argument("--t-final", type=float, default=100.0)
    ap.add_argument("--dt", type=float, default=0.01)
    ap.add_argument("--x64", action="store_true", help="float64 for every JAX and NumPy peer (scipy is always)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--skip", default="", help=f"comma list of peers to skip: {','.join(PEERS)}")
    ap.add_argument("--scipy-n", type=int, default=8, help="trajectories solve_ivp runs (extrapolated to N)")
    ap.add_argument("--repeats", type=int, default=1, help="timed runs per peer after the warm-up (best kept)")
    ap.add_argument("--cache", default="out/bench_cache", help="reference cache dir ('' for none)")
    ap.add_argument("--out", default="out/bench_peers.json")
    a = ap.parse_args(argv)
    skip = {s.strip() for s in a.skip.split(",") if s.strip()}
    unknown = skip - set(PEERS)
    if unknown:
        ap.error(f"unknown peers in --skip: {sorted(unknown)}; choose from {', '.join(PEERS)}")
    n, dt, t_final = a.n_ics, a.dt, a.t_final
    steps = int(round(t_final / dt))
    if not math.isclose(steps * dt, t_final, rel_tol=1e-9):
        ap.error(f"t_final = {t_final} is not a whole number of steps dt = {dt}")
    cache = a.cache or None
    dtype = np.float64 if a.x64 else np.float32
    mach = machine()
    mach["os_cpu_count"] = os.cpu_count()

    ics = workload(n, a.seed)
    y0 = np.concatenate([ics, np.zeros((n, 2))], axis=1)
    log(f"reference: float64 adaptive rtol = atol = 1e-11 on {n} starts, t_final = {t_final} (cache {cache}) ...")
    t0 = time.perf_counter()
    ref = reference_final(ics, t_final=t_final, cache_dir=cache)
    log(f"  done in {time.perf_counter() - t0:.1f} s")
    args = ClosedLoop(paper_plant(), paper_gains())
    rows = []

    def attempt(peer, label, fn):
        if peer in skip:
            return
        log(f"{label} ...")
        t0 = time.perf_counter()
        try:
            for r in fn():
                r.setdefault("label", label)
                rows.append(r)
                log(f"  {r['label']}: wall {r['wall_s']:.3f} s, {r['traj_steps_per_s']:.3g} traj-steps/s, "
                    f"correct/s {fmt(r.get('correct_per_s'))}")
        except Exception as e:                                    # keep the other peers' figures
            log(traceback.format_exc())
            rows.append({"peer": peer, "label": label, "error": f"{type(e).__name__}: {e}"})
        log(f"  ({time.perf_counter() - t0:.1f} s including warm-up)")

    with jax.enable_x64(a.x64):
        def p_vmap():
            wall, yf, extra = run_vmap(y0.astype(dtype), args, dt, steps, a.repeats)
            yield row("vmap", wall=wall, n=n, steps=steps, final=yf, ref=ref, extra=extra)

        def p_numpy():
            wall, yf, extra = run_numpy(y0, args, dt, steps, a.repeats, dtype)
            yield row("numpy", wall=wall, n=n, steps=steps, final=yf, ref=ref, extra=extra)

        def p_drk4():
            wall, yf, ok, extra = run_diffrax(y0.astype(dtype), args, t_final, dt, steps, a.repeats, False)
            yield row("diffrax_rk4", wall=wall, n=n, steps=steps, final=yf, ref=ref, ok=ok, extra=extra)

        def p_tsit5():
            wall, yf, ok, extra = run_diffrax(y0.astype(dtype), args, t_final, dt, steps, a.repeats, True)
            yield row("tsit5", wall=wall, n=n, steps=steps, final=yf, ref=ref, ok=ok, extra=extra)

        attempt("vmap", "plain jit(vmap(lax.scan(rk4))), physical chart", p_vmap)
        attempt("numpy", "NumPy vectorised RK4", p_numpy)
        attempt("diffrax_rk4", "diffrax vmapped diffeqsolve, classical RK4, constant step", p_drk4)
        attempt("tsit5", f"diffrax Tsit5 + PID (rtol {TSIT5_RTOL:g}, atol {TSIT5_ATOL:g})", p_tsit5)

    def p_scipy():
        n_sub = max(1, min(a.scipy_n, n))
        wall, yf, ok, extra = run_scipy(y0, args, t_final, n_sub)
        r = row("scipy", wall=wall, n=n_sub, steps=steps, final=yf, ref=ref[:n_sub], ok=ok, extra=extra)
        # extrapolate to N: same per-trajectory cost, same fraction correct
        r.update(wrong_in_subset=r["wrong_or_nonfinite"], correct_in_subset=r["correct"],
                 wall_s=wall * n / n_sub, n=n, extrapolated_from=n_sub,
                 wrong_or_nonfinite=None, correct=None)
        yield r

    def p_jaxsleigh():
        res = bench(n_ics=n, t_final=t_final, dt=dt, x64=a.x64, seed=a.seed, repeats=a.repeats, cache_dir=cache)
        wall_rk4 = res["rk4_wall_s"]
        wrong = res["rk4_wrong_or_nonfinite"]
        yield {"peer": "jaxsleigh_rk4", "label": "jaxsleigh plain fixed-step RK4, final state only (w chart)",
               "wall_s": wall_rk4, "n": n, "traj_steps_per_s": res["traj_steps_per_s"],
               "wrong_or_nonfinite": wrong, "correct": n - wrong, "correct_per_s": (n - wrong) / wall_rk4}
        yield {"peer": "jaxsleigh_rk4_summaries", "label": "jaxsleigh fixed-step RK4 + on-line summaries",
               "wall_s": n * steps / res["traj_steps_per_s_with_summaries"], "n": n,
               "traj_steps_per_s": res["traj_steps_per_s_with_summaries"], "wrong_or_nonfinite": wrong,
               "correct": n - wrong,
               "correct_per_s": (n - wrong) * res["traj_steps_per_s_with_summaries"] / (n * steps)}
        wrong_chk = res["rk4_checked_wrong_or_nonfinite"]
        wall_chk = res["rk4_checked_wall_s"]
        yield {"peer": "jaxsleigh_rk4_checked", "label": "jaxsleigh fixed-step RK4, passivity-checked",
               "wall_s": wall_chk, "n": n, "traj_steps_per_s": res["traj_steps_per_s_with_passivity_check"],
               "flagged": res["rk4_checked_flagged"], "wrong_or_nonfinite": wrong_chk, "correct": n - wrong_chk,
               "correct_per_s": (n - wrong_chk) / wall_chk}
        yield {"peer": "jaxsleigh_adaptive", "label": "jaxsleigh adaptive (accurate mode, w chart)",
               "wall_s": res["accurate_wall_s"], "n": n, "traj_steps_per_s": n * steps / res["accurate_wall_s"],
               "correct_per_s": res["correct_traj_per_s"], "wrong_or_nonfinite": res["wrong_or_nonfinite"],
               "correct": n - res["wrong_or_nonfinite"], "max_error": res["accurate_max_error"],
               "mean_steps": res["accurate_mean_steps"], "max_steps_taken": res["accurate_max_steps"],
               "dtype": res["dtype"]}
        rows.append({"peer": "_jaxsleigh_bench_raw", "raw": res})

    attempt("scipy", f"scipy solve_ivp RK45 float64, Python loop ({min(a.scipy_n, n)} starts, extrapolated)",
            p_scipy)
    attempt("jaxsleigh", "jaxsleigh.studies.bench.bench", p_jaxsleigh)

    raw = [r for r in rows if r["peer"] == "_jaxsleigh_bench_raw"]
    rows = [r for r in rows if r["peer"] != "_jaxsleigh_bench_raw"]
    base = next((r for r in rows if r["peer"] == "vmap" and "error" not in r), None)
    tsit = next((r for r in rows if r["peer"] == "tsit5" and "error" not in r), None)
    dname = np.dtype(dtype).name
    header = (f"## Peers on the measured workload\n\n"
              f"N = {n} starts (seed {a.seed}), t_final = {t_final:g} s, dt = {dt:g}, steps = {steps}, "
              f"dtype {dname} (scipy float64), final state only, compile excluded, best of {a.repeats}.\n"
              f"Machine: {mach['processor']}, {mach['platform']}, os.cpu_count() = {mach['os_cpu_count']}, "
              f"jax {mach['jax']} on {', '.join(mach['devices'])}.\n"
              f"Correct: finite and final-state max-norm error <= {CORRECT_TOL:g} against the float64 reference. "
              f"Adaptive rows: traj-steps/s = N * {steps} / wall (equivalent). scipy: measured on "
              f"{min(a.scipy_n, n)} starts, wall extrapolated to N.\n")
    print(header)
    print(table(rows, base, tsit))
    print(f"\npeak RSS of this process: {peak_rss_mb():.0f} MiB")
    out = {"n_ics": n, "t_final": t_final, "dt": dt, "steps": steps, "dtype": dname, "seed": a.seed,
           "repeats": a.repeats, "correct_tol": CORRECT_TOL, "machine": mach, "peak_rss_mb": peak_rss_mb(),
           "baseline": "vmap", "results": rows,
           "jaxsleigh_bench": raw[0]["raw"] if raw else None}
    for r in rows:
        if "error" in r:
            continue
        r["x_vmap_traj_steps"] = r["traj_steps_per_s"] / base["traj_steps_per_s"] if base else None
        r["x_vmap_correct"] = (r["correct_per_s"] / base["correct_per_s"]
                               if base and r.get("correct_per_s") is not None and base["correct_per_s"] else None)
        r["x_tsit5_correct"] = (r["correct_per_s"] / tsit["correct_per_s"]
                                if tsit and r.get("correct_per_s") is not None and tsit["correct_per_s"] else None)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(out, indent=1, default=float) + "\n")
    log(f"wrote {a.out}")
    return 0 if not any("error" in r for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
