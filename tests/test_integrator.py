"""The integrators: classical RK4 (jaxsleigh.integrate.rk4), batching, compilation caching, adaptive method."""
from __future__ import annotations

import importlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import jaxsleigh as js
import jaxsleigh.integrate.engine as engine
from jaxsleigh.model.closed_loop import ClosedLoop, vector_field
from jaxsleigh.integrate.rk4 import rk4_step, solve_fixed
from jaxsleigh.status import Status

# `jaxsleigh.simulate` the attribute is the function; the module holds the jitted `_outputs`
simulate_mod = importlib.import_module("jaxsleigh.studies.simulate")


def _linear(t, y, lam):
    return lam * y


@pytest.mark.usefixtures("x64")
def test_rk4_step_is_fourth_order_taylor_polynomial_on_linear_ode():
    """For y' = lam y one classical RK4 step multiplies by 1 + z + z^2/2 + z^3/6 + z^4/24, z = h lam."""
    lam = jnp.array([-1.3, 0.4, 2.0])
    y0 = jnp.array([1.0, -2.0, 0.5])
    for h in (0.1, 0.37, 1.0):
        z = h * np.asarray(lam)
        expected = (1 + z + z ** 2 / 2 + z ** 3 / 6 + z ** 4 / 24) * np.asarray(y0)
        np.testing.assert_allclose(rk4_step(_linear, 0.0, y0, h, lam), expected, rtol=1e-14)


@pytest.mark.usefixtures("x64")
def test_rk4_uses_time_correctly():
    """y' = cos(t): RK4 is Simpson's rule, exact for cubics in t -> check against sin with the
    stage times t, t + h/2, t + h (a wrong stage time breaks this)."""
    f = lambda t, y, args: jnp.cos(t) * jnp.ones_like(y)
    ts, ys = solve_fixed(f, jnp.zeros(1), None, t0=1.0, dt=0.05, n_steps=40, save_every=4)
    assert ts.shape == (11,) and ys.shape == (11, 1)
    np.testing.assert_allclose(ts, 1.0 + 0.2 * np.arange(11), rtol=1e-14)
    np.testing.assert_allclose(ys[:, 0], np.sin(ts) - np.sin(1.0), atol=1e-9)


def test_solve_fixed_rejects_bad_save_every():
    with pytest.raises(ValueError, match="multiple"):
        solve_fixed(_linear, jnp.ones(2), jnp.ones(2), dt=0.1, n_steps=10, save_every=3)


_ORDER_STARTS = np.array([[-1.0, 2.0, 2.5, 0.0, 0.0],
                          [0.5, 0.5, 1.0, 0.3, 0.2],
                          [2.0, -1.0, -1.0, 0.0, 0.0]])
_ORDER_T = 5.0
_ORDER_DTS = (0.04, 0.02, 0.01, 0.005)


def _final_state(y0, args, dt, n):
    return solve_fixed(vector_field, y0, args, dt=dt, n_steps=n, save_every=n)[1][-1]


@pytest.mark.usefixtures("x64")
def test_rk4_global_order_is_four(paper_args):
    """Log-log slope of the final error vs dt on the closed loop (float64, 5 s, non-stiff starts),
    against scipy DOP853 at rtol = atol = 1e-13."""
    f = jax.jit(lambda t, y: vector_field(t, y, paper_args))
    refs = []
    for y0 in _ORDER_STARTS:
        sol = solve_ivp(lambda t, y: np.asarray(f(t, jnp.asarray(y))), (0.0, _ORDER_T), y0, method="DOP853",
                        rtol=1e-13, atol=1e-13)
        assert sol.status == 0
        refs.append(sol.y[:, -1])
    refs = np.array(refs)
    errs = []
    for dt in _ORDER_DTS:
        n = int(round(_ORDER_T / dt))
        run = jax.jit(jax.vmap(lambda y0: _final_state(y0, paper_args, dt, n)))
        errs.append(np.max(np.abs(np.asarray(run(jnp.asarray(_ORDER_STARTS))) - refs), axis=1))
    errs = np.array(errs)                              # (n_dt, n_starts)
    assert np.all(errs[-1] > 1e-13), "errors reached the reference's rounding level"
    for j in range(len(_ORDER_STARTS)):
        slope = np.polyfit(np.log(_ORDER_DTS), np.log(errs[:, j]), 1)[0]
        assert 3.7 <= slope <= 4.3, (j, slope, errs[:, j])


@pytest.mark.usefixtures("x64")
def test_vmap_of_solve_fixed_equals_python_loop(sample_states, paper_args):
    y0s = jnp.asarray(sample_states(5, p_scale=0.5, theta_lo=0.5))
    one = lambda y0: solve_fixed(vector_field, y0, paper_args, dt=0.01, n_steps=200, save_every=20)
    ts_b, ys_b = jax.jit(jax.vmap(one))(y0s)
    one_j = jax.jit(one)
    for i in range(y0s.shape[0]):
        ts, ys = one_j(y0s[i])
        np.testing.assert_allclose(ts_b[i], ts, rtol=0, atol=0)
        np.testing.assert_allclose(ys_b[i], ys, rtol=1e-12, atol=1e-13)
    assert ys_b.shape == (5, 11, 5)
    assert not np.allclose(ys_b[:, -1], ys_b[:, 0])   # it moved


def test_jitted_batch_does_not_recompile_for_new_ics_or_gains():
    """Gains and initial conditions are traced data: same shapes -> one compilation."""
    traces = []
    plant = js.paper_plant()

    def final(y0, g):
        traces.append(1)                  # runs only while tracing
        return _final_state(y0, ClosedLoop(plant, g), 0.01, 50)

    run = jax.jit(jax.vmap(final, in_axes=(0, None)))
    y0a = jnp.asarray(np.array([[1.0, 1.0, 0.5, 0.0, 0.0], [-3.0, -2.0, np.pi / 8, 0.0, 0.0]]), jnp.float32)
    y0b = jnp.asarray(np.array([[2.0, -1.0, -1.0, 0.1, 0.0], [-1.0, 2.0, 2.5, 0.0, 0.3]]), jnp.float32)
    ga = js.paper_gains()
    gb = js.gains((1.0, 3.0, 0.2), 0.7, [[5.0, 1.0], [1.0, 2.0]])
    ra = run(y0a, ga)
    rb = run(y0b, gb)
    rc = run(y0a, gb)
    assert len(traces) == 1
    assert run._cache_size() == 1
    assert not np.allclose(ra, rc)    # the gains did reach the computation
    assert not np.allclose(ra, rb)


def _jit_cache_sizes():
    """Compiled-executable counts of every jitted function of the engine and simulate modules
    (``engine._segment_batch`` among them), by name."""
    sizes = {}
    for mod in (engine, simulate_mod):
        for name, obj in vars(mod).items():
            if callable(getattr(obj, "_cache_size", None)):
                sizes[f"{mod.__name__}.{name}"] = obj._cache_size()
    return sizes


def test_simulate_does_not_recompile_on_second_call():
    """A second simulate() with new starts, gains and plant values (same shapes, dtype, method and
    horizon) reuses every compiled kernel."""
    ics_a = [[1.0, 1.0, 0.5], [-3.0, -2.0, np.pi / 8], [2.0, -1.0, -1.0]]
    ics_b = [[0.3, -1.0, 1.2], [2.0, 2.0, -1.3], [-1.0, 0.5, 2.0]]
    kw = dict(t_final=1.0, dt=0.01, saveat=js.SaveAt(every=10))
    for method in ("adaptive", "rk4"):
        first = js.simulate(ics_a, **kw, stepsize=js.StepSizeController(method=method))
        sizes = _jit_cache_sizes()
        assert sum(sizes.values()) > 0, "no jitted kernels found: the test would be vacuous"
        sol = js.simulate(ics_b, gains=js.gains((1.0, 1.0, 1.0), 0.3, (2.0, 3.0)),
                          plant=js.plant_params(3.0, 0.5, 0.7), **kw, stepsize=js.StepSizeController(method=method))
        assert np.all(sol.status == Status.OK)
        assert not np.allclose(sol.q[:, -1], first.q[:, -1])
        assert _jit_cache_sizes() == sizes, method


_ADAPTIVE_STARTS = np.array([[-3.0, -2.0, np.pi / 8, 0.0, 0.0],
                             [2.0, -1.0, -1.0, 0.0, 0.0],
                             [1.0, -2.0, 0.7, 1.0, -0.5]])


@pytest.mark.usefixtures("x64")
def test_adaptive_converges_to_reference_as_rtol_tightens(paper_args):
    """dt = 0.1 caps the step (RK4 at 0.1 alone is inaccurate); tightening rtol = atol must drive
    the error against a DOP853 reference down, by more than 100x over 4 decades."""
    t_final, save = 10.0, 0.5
    t_eval = np.arange(0.0, t_final + 1e-9, save)
    f = jax.jit(lambda t, y: vector_field(t, y, paper_args))
    refs = []
    for y0 in _ADAPTIVE_STARTS:
        sol = solve_ivp(lambda t, y: np.asarray(f(t, jnp.asarray(y))), (0.0, t_final), y0, method="DOP853",
                        rtol=1e-12, atol=1e-12, t_eval=t_eval)
        assert sol.status == 0
        refs.append(sol.y[:3].T)
    refs = np.array(refs)
    errs = []
    for tol in (1e-4, 1e-6, 1e-8):
        sol = js.simulate(_ADAPTIVE_STARTS, t_final=t_final, dt=0.1, x64=True,
                          stepsize=js.StepSizeController(rtol=tol, atol=tol), saveat=js.SaveAt(every=5))
        assert np.all(sol.status == Status.OK)
        np.testing.assert_allclose(sol.t, t_eval, atol=1e-12)
        errs.append(np.max(np.abs(sol.q - refs), axis=(1, 2)))
    errs = np.array(errs)
    assert np.all(np.diff(errs, axis=0) < 0), errs
    assert np.all(errs[0] / errs[-1] > 100), errs
    assert np.all(errs[-1] < 1e-6), errs
    # the fixed-step method at the same base step cannot do this: from the stiff paper start it
    # raises H_d or jumps across theta = 0 and is flagged (not returned as silent garbage)
    fixed = js.simulate(_ADAPTIVE_STARTS[:1], t_final=t_final, dt=0.1, x64=True,
                        stepsize=js.StepSizeController(method="rk4"), saveat=js.SaveAt(every=5))
    assert fixed.status[0] in (Status.CROSSED_SINGULAR, Status.NONFINITE, Status.UNRELIABLE)
    assert np.isnan(fixed.q[0, -1]).all()
