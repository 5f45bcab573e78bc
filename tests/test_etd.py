"""The settled-phase step (`jaxsleigh.integrate.etd`): the exponential RK4 on p2 with the injected damping's
rate frozen per step, checked against its own claims: the phi functions, order 4, classical RK4 where the
rate vanishes, no stability limit from the rate, and T_eps against scipy's Radau."""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import jaxsleigh as js
from jaxsleigh.integrate.etd import etd_stages, phis
from jaxsleigh.integrate.rk4 import rk4_step
from jaxsleigh.model.charts import WChart
from jaxsleigh.model.closed_loop import ClosedLoop, state_to_w
from numpy_field import numpy_field  # noqa: E402

CH = WChart()


def test_phi_functions_match_their_definitions_on_both_sides_of_the_switch():
    z = np.concatenate([-np.geomspace(1e-8, 0.999, 40), -np.geomspace(1.001, 1e6, 40), [0.0]])
    with jax.enable_x64(True):
        p1, p2, p3 = (np.asarray(p) for p in phis(jnp.asarray(z)))
    for zz, a, b, c in zip(z, p1, p2, p3):
        # the definitions, summed exactly enough in Python's floats (series near 0, closed forms away)
        if abs(zz) < 0.5:
            want = [sum(zz ** j / math.factorial(j + k) for j in range(30)) for k in (1, 2, 3)]
        else:
            e1 = math.expm1(zz) / zz
            want = [e1, (e1 - 1) / zz, ((e1 - 1) / zz - 0.5) / zz]
        np.testing.assert_allclose([a, b, c], want, rtol=2e-11, atol=1e-300)   # the series: 14 terms
    # float32 keeps its accuracy near 0, where the closed forms cancel
    zf = [-1e-4, -0.9, -3.0]
    got = np.column_stack([np.asarray(p) for p in phis(jnp.asarray(zf, jnp.float32))])
    want = [[sum(z ** j / math.factorial(j + k) for j in range(40)) for k in (1, 2, 3)] for z in zf]
    np.testing.assert_allclose(got, want, rtol=3e-6)


def _fixed(y0, args, n, T, etd):
    h = T / n

    def body(y, _):
        if etd:
            k1 = CH.field(0.0, y, args)
            dy, *_ = etd_stages(CH.field_and_control, 0.0, y, h, args, k1, CH.stiff_rate(y, args))
            return y + dy, None
        return rk4_step(CH.field, 0.0, y, h, args), None

    return jax.jit(lambda y: jax.lax.scan(body, y, None, length=n)[0])(y0)


def test_exponential_step_is_fourth_order_and_classical_rk4_without_the_rate():
    with jax.enable_x64(True):
        args = ClosedLoop(js.paper_plant(), js.paper_gains())
        y0 = state_to_w(jnp.array([1.0, -0.5, 0.4, 0.2, -0.3]))
        ref = _fixed(y0, args, 2 ** 15, 1.0, etd=False)
        errs = [float(jnp.max(jnp.abs(_fixed(y0, args, n, 1.0, etd=True) - ref))) for n in (50, 100, 200)]
        orders = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
        assert np.all((orders > 3.7) & (orders < 4.5)), orders
        # with k = D22 = 0 the rate is 0 and the step is classical RK4 (to rounding)
        flat = ClosedLoop(js.paper_plant(), js.paper_gains()._replace(k=jnp.asarray(0.0),
                                                                       D_hat=jnp.zeros((2, 2))))
        np.testing.assert_allclose(_fixed(y0, flat, 64, 1.0, etd=True), _fixed(y0, flat, 64, 1.0, etd=False),
                                   rtol=1e-13, atol=1e-15)


def test_settled_steps_are_not_capped_by_the_damping_rate():
    """With the tuned gains classical RK4 is stable only for h |lambda| <= 2.8, lambda growing like
    1 / theta^2 as the sleigh settles; between 30 s and 40 s the exponential step takes fewer steps than that
    bound allows at 30 s (not many fewer: the next limit is an oscillatory mode whose frequency grows like
    1 / theta, docs/evidence/settled-phase.md), and ends on the final state of a tight float64 run."""
    start = [[1.0, -1.0, 0.6]]
    a, b = (js.simulate(start, gains="tuned", t_final=t, save_every=100) for t in (30.0, 40.0))
    ref = js.simulate(start, gains="tuned", t_final=40.0, save_every=100, x64=True, rtol=1e-11, atol=1e-11,
                      max_steps=10 ** 7)
    assert a.status[0] == b.status[0] == ref.status[0] == 0
    g, pl = js.load_gains("tuned"), js.paper_plant()
    theta30 = float(a.q[0, -1, 2])
    lam30 = (float(np.asarray(g.D_hat)[1, 1]) + float(g.k) / theta30 ** 2) / (pl.J + pl.m * pl.l ** 2)
    classical_at_least = 10.0 * lam30 / 2.8
    taken = int(b.n_steps[0]) - int(a.n_steps[0])
    assert taken < 0.95 * classical_at_least, (taken, classical_at_least)
    np.testing.assert_allclose(b.q[0, -1], ref.q[0, -1], atol=2e-5)


@pytest.mark.parametrize("gains", ["paper", "tuned"])
def test_t_eps_within_a_millisecond_of_radau(gains):
    starts = np.array([[-3.0, -2.0, np.pi / 8], [2.0, 1.5, -0.9], [0.5, -2.5, 2.0]])
    g = js.paper_gains() if gains == "paper" else js.load_gains(gains)
    args = ClosedLoop(js.paper_plant(), g)
    T, eps = 60.0, 0.05
    res = js.run_ensemble(starts, gains=None if gains == "paper" else gains, t_final=T, eps=eps, progress=False)
    f, jac = numpy_field(args)
    with jax.enable_x64(True):
        for i, s in enumerate(starts):
            y0 = np.array([*s, 0.0, 0.0])
            # rtol 1e-8: the same T_eps on the 1e-4 s grid as rtol 1e-10, at a third of the calls (tuned: 1e5)
            sol = solve_ivp(f, (0.0, T), y0, method="Radau", rtol=1e-8, atol=1e-10, jac=jac, dense_output=True)
            ts = np.linspace(0.0, T, 600_001)
            qn = np.linalg.norm(sol.sol(ts)[:3], axis=0)
            out = np.flatnonzero(qn > eps)
            if out.size == 0 or out[-1] == ts.size - 1:
                assert not np.isfinite(res.T_eps[i])
                continue
            assert res.T_eps[i] == pytest.approx(ts[out[-1] + 1], abs=1e-3), (gains, i)


def test_near_theta_zero_nothing_non_finite_passes_as_ok():
    """Starts down to theta0 = 1e-6, several parts per chunk (so stragglers go through the tail batch), float32:
    a start either ends OK with a finite state and summaries, or with another status and NaN outputs."""
    rng = np.random.default_rng(5)
    n = 2200
    ics = np.column_stack([rng.uniform(-3, 3, (n, 2)), rng.uniform(0.3, 3, n) * rng.choice([-1, 1], n)])
    ics[:60, 2] = np.geomspace(1e-6, 0.05, 60) * np.resize([1, -1], 60)
    r = js.run_ensemble(ics, t_final=5.0, chunk_size=n, max_steps=4000, progress=False)
    ok = r.status == 0
    assert (~ok).any() and ok.sum() > 0.9 * n                # some stiff starts gave up, and said so
    fields = np.column_stack([r.q_final, r.p_final, r.Hd_final, r.u_energy, r.min_abs_theta])
    assert np.all(np.isfinite(fields[ok]))
    assert np.all(np.isnan(r.q_final[~ok])) and np.all(np.isin(r.status[~ok], [s.value for s in js.Status]))
