"""Control effort as an output: the observers' quadrature against an independent float64 reference.

The reference integrates the physical-chart closed loop augmented with E' = |u|^2 and A' = |u|
by scipy's DOP853 at rtol = atol = 1e-12 (a dense, high-order quadrature of the same integrands),
and takes the peak of |u| on its dense output every 1e-3 s. jaxsleigh integrates the integrands
with the step's own RK4 weights, so with fixed steps the error falls 16x per halving of dt.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import jaxsleigh as js
from jaxsleigh.model.closed_loop import ClosedLoop, vector_field
from jaxsleigh.model.paper_law import control, measured_velocity  # noqa: F401
from jaxsleigh.model.coordinates import Q_entries
from jaxsleigh.model.plant import velocity
from jaxsleigh.model.smallmat import matvec

T = 10.0
STARTS = np.array([[1.0, 1.0, 0.5, 0.0, 0.0], [-3.0, -2.0, np.pi / 8, 0.0, 0.0], [2.0, -1.0, -1.0, 0.4, -0.3],
                   [-1.0, 2.0, 2.5, 0.0, 0.0]])
#: Starts whose fixed-step error is in its asymptotic regime for dt in 0.02 ... 0.005 (from (1, 1, 0.5)
#: the energy error changes sign near dt = 0.003, so its ratios are not 16 there).
TAME = [2, 3]


@pytest.fixture(scope="module")
def reference():
    """Per start: (energy, abs integral, peak |u1|, peak |u2|, peak |u|) from DOP853 at 1e-12."""
    with jax.enable_x64(True):
        args = ClosedLoop(js.paper_plant(), js.paper_gains())

        def u_of(y):
            q, p = y[:3], y[3:]
            qdot = jnp.stack(matvec(Q_entries(q), velocity(p, args.plant)))
            return control(q, qdot, args.gains)

        def aug(t, Y):
            y = Y[:5]
            u = u_of(y)
            e = jnp.sum(u * u)
            return jnp.concatenate([vector_field(t, y, args), jnp.stack([e, jnp.sqrt(e)])])

        f = jax.jit(aug)
        u_batch = jax.jit(jax.vmap(u_of))
        out = []
        for y0 in STARTS:
            sol = solve_ivp(lambda t, Y: np.asarray(f(t, jnp.asarray(Y))), (0.0, T), np.concatenate([y0, [0, 0]]),
                            method="DOP853", rtol=1e-12, atol=1e-12, dense_output=True)
            assert sol.success
            ts = np.linspace(0.0, T, int(T / 1e-3) + 1)
            u = np.asarray(u_batch(jnp.asarray(sol.sol(ts)[:5].T)))
            mags = np.column_stack([np.abs(u[:, 0]), np.abs(u[:, 1]), np.linalg.norm(u, axis=1)])
            peaks = []
            for j in range(3):           # each peak refined on a 1e-6 s grid around the 1e-3 s grid's best
                tj = ts[np.argmax(mags[:, j])]
                fine = np.clip(np.linspace(tj - 1e-3, tj + 1e-3, 2001), 0.0, T)
                uf = np.asarray(u_batch(jnp.asarray(sol.sol(fine)[:5].T)))
                peaks.append(max(mags[:, j].max(), (np.abs(uf[:, j]) if j < 2 else np.linalg.norm(uf, axis=1)).max()))
            out.append((sol.y[5, -1], sol.y[6, -1], *peaks))
        return np.array(out)


def test_effort_integrals_match_the_reference_quadrature(reference):
    res = js.run_ensemble(STARTS, t_final=T, x64=True,
                          stepsize=js.StepSizeController(rtol=1e-11, atol=1e-11, max_steps=2_000_000),
                          run=js.RunOptions(progress=False))
    assert np.all(res.status == 0)
    np.testing.assert_allclose(res.u_energy, reference[:, 0], rtol=1e-7)
    np.testing.assert_allclose(res.u_abs_int, reference[:, 1], rtol=1e-7)
    # peaks are taken at the steps' end points: never above the true peak, and close to it
    peaks = np.column_stack([res.u_peak, res.u_norm_peak])
    assert np.all(peaks <= reference[:, 2:] * (1 + 1e-9))
    np.testing.assert_allclose(peaks, reference[:, 2:], rtol=2e-2)
    # simulate reports the same integrals (it steps on the save grid, so to the tolerance)
    sol = js.simulate(STARTS, t_final=T, x64=True,
                      stepsize=js.StepSizeController(rtol=1e-11, atol=1e-11, max_steps=2_000_000),
                      saveat=js.SaveAt(every=100))
    np.testing.assert_allclose(sol.effort["u_energy"], reference[:, 0], rtol=1e-7)


def test_effort_quadrature_is_fourth_order(reference):
    """Fixed RK4 on tame starts: the energy error falls 16x per halving of dt (measured 15.6-16.3)."""
    errs = []
    for dt in (0.02, 0.01, 0.005):
        res = js.run_ensemble(STARTS[TAME], t_final=T, dt=dt, x64=True,
                              stepsize=js.StepSizeController(method="rk4"), run=js.RunOptions(progress=False))
        errs.append(np.abs(res.u_energy - reference[TAME, 0]) / reference[TAME, 0])
    errs = np.array(errs)
    ratios = errs[:-1] / errs[1:]
    assert np.all(ratios > 13) and np.all(ratios < 19), ratios


def test_default_float32_effort_is_accurate(reference):
    res = js.run_ensemble(STARTS, t_final=T, run=js.RunOptions(progress=False))
    np.testing.assert_allclose(res.u_energy, reference[:, 0], rtol=2e-3)


def test_observers_only_watch_and_effort_integrals_are_under_error_control():
    """Observers without quadrature rows only watch: the stepper with none of them steps exactly as with them. The
    effort integrals (ControlEffort's rows) are under the step's error norm, so with them a step may be refused that
    the state alone would accept: at least as many steps, the same trajectory to the tolerance."""
    from jaxsleigh.integrate.engine import initial_w
    from jaxsleigh.integrate.observers import ClosestApproach, ConvergenceTime, Excursion
    from jaxsleigh.integrate.stepper import Scan, controls, init_batch, run

    with jax.enable_x64(True):
        args = ClosedLoop(js.paper_plant(), js.paper_gains())
        ctl = controls(js.StepSizeController(rtol=1e-8, atol=1e-8, max_step=0.1), jnp.float64, dt=0.01, eps=0.05,
                       max_steps=10**5)
        st = np.zeros(len(STARTS), np.int32)
        y0 = initial_w(STARTS, st, jnp.float64)
        finals = []
        for obs in ((), (ConvergenceTime(), ClosestApproach(), Excursion()), js.observers.DEFAULT_OBSERVERS):
            s = init_batch(y0, jnp.asarray(st), args, ctl, observers=obs)
            s = jax.jit(lambda s: run(s, 5.0, args, ctl, Scan(3000), adaptive=True, observers=obs))(s)
            finals.append(s)
        # the same steps; the states to rounding (XLA fuses the step's arithmetic differently with observers)
        np.testing.assert_allclose(finals[0].y, finals[1].y, rtol=1e-12, atol=1e-14)
        np.testing.assert_array_equal(finals[0].n_accept, finals[1].n_accept)
        assert np.all(finals[2].n_accept + finals[2].n_reject >= finals[0].n_accept + finals[0].n_reject)
        np.testing.assert_allclose(finals[0].y, finals[2].y, rtol=1e-6, atol=1e-7)
        assert finals[0].quad.shape[0] == 0 and finals[2].quad.shape[0] == 2


def test_effort_is_nan_where_a_start_was_not_integrated():
    with pytest.warns(js.errors.FlaggedStartsWarning):
        res = js.run_ensemble([[1.0, 1.0, 0.5], [1.0, 1.0, 0.0]], t_final=1.0, run=js.RunOptions(progress=False))
    assert np.isfinite(res.u_energy[0]) and np.isnan(res.u_energy[1]) and np.all(np.isnan(res.u_peak[1]))


# ---------------------------------------------------------------------------------------------
# T_eps on the step's dense output
# ---------------------------------------------------------------------------------------------

def _step(y, y_new, k1, k5, t=10.0, h=1.0):
    from jaxsleigh.model.charts import WChart
    from jaxsleigh.integrate.observers import StepInfo

    a = lambda v: jnp.asarray(v, jnp.float64)  # noqa: E731
    return StepInfo(t=a(t), h=a(h), t_new=a(t + h), y=a(y), y_new=a(y_new), k1=a(k1), k5=a(k5), u_new=None,
                    acc=jnp.asarray(True), chart=WChart())


@pytest.mark.usefixtures("x64")
def test_convergence_time_locates_the_entry_inside_a_step():
    from jaxsleigh.integrate.observers import ConvergenceTime
    from jaxsleigh.integrate.stepper import Controls

    ctl = Controls(*(jnp.asarray(v, jnp.float64) for v in (0.01, 0.1, 1e-8, 1e-8, 0.05)), max_steps=jnp.asarray(10))
    ct = ConvergenceTime()
    # |q| = |w1| along w = (w1, 0, 0); w1 falls linearly from 0.2 to 0.02: it enters at w1 = 0.05
    d = [-0.18, 0, 0, 0, 0]
    (t,) = ct.update((jnp.asarray(jnp.inf),), _step([0.2, 0, 0, 0, 0], [0.02, 0, 0, 0, 0], d, d), ctl)
    assert abs(float(t) - (10.0 + 0.15 / 0.18)) < 1e-3
    # inside at both ends but outside in between (w1 = 0.01 + s - s^2 on the dense output): the stay
    # that counts starts at the re-entry, s = (1 + sqrt(0.84)) / 2, not before the step
    (t,) = ct.update((jnp.asarray(3.0),), _step([0.01, 0, 0, 0, 0], [0.01, 0, 0, 0, 0], [1, 0, 0, 0, 0],
                                                  [-1, 0, 0, 0, 0]), ctl)
    assert abs(float(t) - (10.0 + (1 + np.sqrt(0.84)) / 2)) < 1e-3
    # the 0.1 release's rule (samples=1, bisections=0) takes the end of the entering step instead
    (t,) = ConvergenceTime(1, 0).update((jnp.asarray(jnp.inf),), _step([0.2, 0, 0, 0, 0], [0.02, 0, 0, 0, 0], d, d),
                                        ctl)
    assert float(t) == 11.0
    # a step that ends outside resets it; a rejected step changes nothing
    (t,) = ct.update((jnp.asarray(3.0),), _step([0.02, 0, 0, 0, 0], [0.2, 0, 0, 0, 0], [0.18] + [0] * 4,
                                                  [0.18] + [0] * 4), ctl)
    assert float(t) == np.inf
    s = _step([0.02, 0, 0, 0, 0], [0.2, 0, 0, 0, 0], [0.18] + [0] * 4, [0.18] + [0] * 4)._replace(
        acc=jnp.asarray(False))
    assert float(ct.update((jnp.asarray(3.0),), s, ctl)[0]) == 3.0


def test_dense_t_eps_with_long_steps_matches_a_float64_reference():
    """With steps up to 1 s (100 dt), T_eps stays within 1e-3 s of a float64 run at 1e-11."""
    from jaxsleigh.studies.bench import workload

    ics = workload(24, seed=3)
    ref = js.run_ensemble(ics, x64=True,
                          stepsize=js.StepSizeController(rtol=1e-11, atol=1e-11, max_step=0.1, max_steps=4_000_000),
                          run=js.RunOptions(progress=False))
    res = js.run_ensemble(ics, stepsize=js.StepSizeController(max_step=1.0), run=js.RunOptions(progress=False))
    both = np.isfinite(ref.T_eps) & np.isfinite(res.T_eps)
    assert both.sum() >= 18 and np.array_equal(np.isfinite(ref.T_eps), np.isfinite(res.T_eps))
    assert np.max(np.abs(res.T_eps[both] - ref.T_eps[both])) < 1e-3
