"""The sampled-data loop honours the tolerances: each hold interval is integrated by the library's adaptive stepper,
landing on every sample instant, so its error against an independent reference (scipy's DOP853 integrating the same
held loop sample by sample) falls with rtol and atol, and its derivatives are those of the scheme."""
from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import jaxsleigh as js
from jaxsleigh.controllers.actuators import Sampler, sampled
from jaxsleigh.controllers.paper import PaperLaw
from jaxsleigh.integrate.sampled import solve_sampled
from jaxsleigh.model.controller import PerTrajectory
from jaxsleigh.status import Status

#: the command line's --ic 1,1,0.5: (x, y, theta) with zero momentum
START = np.array([[1.0, 1.0, 0.5, 0.0, 0.0]])
TS, T_FINAL = 0.2, 30.0


def _plant(y, u, m=2.0, J=1.0, l=1.0, c_eps=0.1):
    """Sleigh eq. 1-2 with the paper's smoothed Coulomb damping (written out here, not the library's), one state."""
    th, p1, p2 = y[2], y[3], y[4]
    inertia = J + m * l * l
    v1, v2 = p1 / m, p2 / inertia
    return np.array([np.cos(th) * v1, np.sin(th) * v1, v2,
                     m * l * v2 * v2 - v1 / np.sqrt(c_eps + p1 * p1) + u[0],
                     -m * l * v1 * v2 - v2 / np.sqrt(c_eps + p2 * p2) + u[1]])


def _reference(law, y0, period, samples):
    """The final state of the held loop, sample by sample: u from ``law`` at the state of each sample instant, held
    by DOP853 at rtol 1e-13, atol 1e-14."""
    law_at = jax.jit(lambda q, v: law(q, v))
    y = np.array(y0, np.float64)
    for k in range(samples):
        u = np.asarray(law_at(jnp.asarray(y[:3]), jnp.asarray(y[3:] / np.array([2.0, 3.0]))), np.float64)
        sol = solve_ivp(lambda t, z: _plant(z, u), (k * period, (k + 1) * period), y, method="DOP853",
                        rtol=1e-13, atol=1e-14)
        assert sol.success
        y = sol.y[:, -1]
    return y


@pytest.fixture(scope="module")
def reference():
    with jax.enable_x64(True):
        return _reference(PaperLaw(), START[0], TS, round(T_FINAL / TS))


def _final_error(reference, **options) -> float:
    with jax.enable_x64(True):
        run = solve_sampled(PaperLaw(), None, START, t_final=T_FINAL, sampler=Sampler(TS), dtype=jnp.float64,
                            save=False, **options)
        assert np.asarray(run.status).tolist() == [Status.OK]
        return float(np.abs(np.asarray(run.q_final)[0] - reference[:3]).max())


def test_the_held_loop_meets_a_tight_tolerance(reference):
    """Ts = 0.2 s, 30 s, float64: final q within 1e-9 of the reference at rtol 1e-11, atol 1e-12 (measured 1.0e-11;
    fixed 20 RK4 substeps per period were 1.4e-5 off whatever the tolerances), within 1e-6 at the defaults."""
    assert _final_error(reference, stepsize=js.StepSizeController(rtol=1e-11, atol=1e-12)) < 1e-9
    assert _final_error(reference) < 1e-6


def test_tighter_tolerances_give_a_smaller_error(reference):
    errors = [_final_error(reference, stepsize=js.StepSizeController(rtol=tol, atol=tol))
              for tol in (1e-6, 1e-8, 1e-10)]
    assert errors[0] > errors[1] > errors[2], errors
    assert errors[0] > 100 * errors[2], errors


def test_fixed_steps_ignore_the_tolerances(reference):
    """``StepSizeController(method="rk4")``: 20 fixed RK4 steps per period, the same error at any tolerance."""
    fixed = js.StepSizeController(method="rk4")
    error = _final_error(reference, stepsize=fixed)
    assert 1e-6 < error < 1e-4
    assert _final_error(reference, stepsize=fixed._replace(rtol=1e-11, atol=1e-12)) == error


def test_a_removed_tolerance_keyword_or_one_out_of_range_is_refused():
    with pytest.raises(TypeError, match=re.escape("solve_sampled() got an unexpected keyword argument 'rtol': pass "
                                                  "stepsize=jaxsleigh.StepSizeController(rtol=...)")):
        solve_sampled(PaperLaw(), None, START, t_final=1.0, sampler=Sampler(0.1), rtol=1e-6,
                      stepsize=js.StepSizeController(rtol=1e-7))
    for bad in (0.0, -1e-6, np.nan, np.inf):
        with pytest.raises(ValueError, match="stepsize.atol must be > 0"):
            solve_sampled(PaperLaw(), None, START, t_final=1.0, sampler=Sampler(0.1),
                          stepsize=js.StepSizeController(atol=bad))
    with pytest.raises(ValueError, match="max_steps"):
        solve_sampled(PaperLaw(), None, START, t_final=1.0, sampler=Sampler(0.1),
                      stepsize=js.StepSizeController(method="rk4", max_steps=10))


def test_a_period_that_needs_more_attempts_than_its_share_ends_budget_exhausted():
    """``max_steps`` (per start, over the run) is shared evenly between the periods: a run whose first period needs
    more stops there, its state frozen and its samples NaN from then on, never silently wrong."""
    run = solve_sampled(PaperLaw(), None, START, t_final=1.0, sampler=Sampler(0.1),
                        stepsize=js.StepSizeController(max_steps=10))
    assert np.asarray(run.status).tolist() == [Status.BUDGET_EXHAUSTED]
    assert np.asarray(run.n_steps + run.n_rejected).tolist() == [1]
    assert 0.0 < float(run.t_reached[0]) < 0.1
    assert np.all(np.isnan(np.asarray(run.q)[0, 1:])) and np.all(np.isnan(np.asarray(run.q_final)))
    assert np.isnan(float(run.u_energy[0])) and np.isnan(float(run.T_eps[0]))
    ok = solve_sampled(PaperLaw(), None, START, t_final=1.0, sampler=Sampler(0.1))
    assert np.asarray(ok.status).tolist() == [Status.OK] and int(ok.n_steps[0]) > 10


def _loss(k, y0):
    """Final |q|^2 plus the control energy of the sampled paper law with gain ``k`` from ``y0`` (float64)."""
    law = PaperLaw(js.paper_gains()._replace(k=k))
    run = solve_sampled(law, None, y0[None], t_final=1.0, sampler=Sampler(0.1), dtype=jnp.float64, save=False,
                        stepsize=js.StepSizeController(rtol=1e-10, atol=1e-10))
    return jnp.sum(run.q_final ** 2) + jnp.sum(run.u_energy)


@pytest.mark.slow            # 4 s with the compiled programs cached (tracing the gradient); the quick tier keeps
def test_reverse_mode_gradients_match_finite_differences():     # the forward-mode check of tests/test_actuators.py
    """jax.grad through the adaptive held loop, with respect to a gain of the law and to the start, against central
    differences of the same loop."""
    with jax.enable_x64(True):
        k0, y0 = jnp.asarray(0.1), jnp.asarray([1.0, 1.0, 0.5, 0.0, 0.0])
        loss = jax.jit(_loss)
        g_k, g_y = jax.jit(jax.grad(_loss, argnums=(0, 1)))(k0, y0)
        h = 1e-6
        fd_k = (float(loss(k0 + h, y0)) - float(loss(k0 - h, y0))) / (2 * h)
        np.testing.assert_allclose(float(g_k), fd_k, rtol=1e-5)
        for i in (0, 2):                                     # x0, theta0
            e = jnp.zeros(5).at[i].set(h)
            fd = (float(loss(k0, y0 + e)) - float(loss(k0, y0 - e))) / (2 * h)
            np.testing.assert_allclose(float(g_y[i]), fd, rtol=1e-5, atol=1e-8)
        assert abs(float(g_k)) > 1e-3 and np.all(np.abs(np.asarray(g_y)[[0, 2]]) > 1e-3)


def test_solve_takes_a_sampled_law_on_the_same_stepper(reference):
    """``js.solve(sampled(law, Ts), y0)`` is the sampled-data loop through the front door: the same program as
    `solve_sampled` for a batch of one (bitwise), meeting the same tolerance against the DOP853 reference; the held
    loop has no H_d (NaN)."""
    with jax.enable_x64(True):
        law = sampled(PaperLaw(), TS)
        tight = js.StepSizeController(rtol=1e-11, atol=1e-12)
        out = js.solve(law, jnp.asarray(START[0]), t_final=T_FINAL, stepsize=tight)
        run = solve_sampled(PaperLaw(), None, START, t_final=T_FINAL, sampler=Sampler(TS), dtype=jnp.float64,
                            save=False, stepsize=tight)
        assert int(out.status) == Status.OK
        np.testing.assert_array_equal(np.asarray(out.q_final), np.asarray(run.q_final)[0])
        assert float(out.u_energy) == float(run.u_energy[0]) and float(out.T_eps) == float(run.T_eps[0])
        assert int(out.n_steps) == int(run.n_steps[0]) > 1000
        assert np.abs(np.asarray(out.q_final) - reference[:3]).max() < 1e-9
        assert np.isnan(float(out.Hd0)) and np.isnan(float(out.Hd_final))


def test_solve_carries_the_observers_it_is_given_under_a_sampled_law():
    from jaxsleigh.integrate.observers import ConvergenceTime
    law = sampled(PaperLaw(), 0.1)
    out = js.solve(law, jnp.asarray([1.0, 1.0, 0.5]), t_final=1.0, observers=(ConvergenceTime(),))
    assert sorted(out.summaries) == ["T_eps"] and out.u_energy is None
    assert int(out.status) == Status.OK and float(out.T_eps) == np.inf         # 1 s is too short to settle


def test_solve_refuses_a_sampled_law_it_cannot_run():
    y0 = jnp.asarray([1.0, 1.0, 0.5])
    with pytest.raises(ValueError, match="whole number of sampling periods"):
        js.solve(sampled(PaperLaw(), 0.3), y0, t_final=1.0)
    with pytest.raises(ValueError, match="must be concrete"):
        jax.jit(lambda c: js.solve(c, y0, t_final=1.0).u_energy)(sampled(PaperLaw(), 0.1))
    with pytest.raises(ValueError, match="vmap solve"):
        js.solve(PerTrajectory(sampled(PaperLaw(), 0.1)), y0, t_final=1.0)


def _solve_loss(k, y0):
    """`_loss` through `js.solve`: final |q|^2 plus the control energy, one start."""
    law = sampled(PaperLaw(js.paper_gains()._replace(k=k)), 0.1)
    out = js.solve(law, y0, t_final=1.0, stepsize=js.StepSizeController(rtol=1e-10, atol=1e-10))
    return jnp.sum(out.q_final ** 2) + out.u_energy


@pytest.mark.slow
def test_gradients_through_solve_of_a_sampled_law_match_finite_differences():
    with jax.enable_x64(True):
        k0, y0 = jnp.asarray(0.1), jnp.asarray([1.0, 1.0, 0.5, 0.0, 0.0])
        loss = jax.jit(_solve_loss)
        g_k = float(jax.jit(jax.grad(_solve_loss))(k0, y0))
        h = 1e-6
        fd_k = (float(loss(k0 + h, y0)) - float(loss(k0 - h, y0))) / (2 * h)
        np.testing.assert_allclose(g_k, fd_k, rtol=1e-5)
        assert abs(g_k) > 1e-3


def test_solve_saves_the_samples_of_a_sampled_law():
    law = sampled(PaperLaw(), 0.1)
    out = js.solve(law, jnp.asarray([1.0, 1.0, 0.5]), t_final=1.0, saveat=js.SaveAt(every=10))
    run = solve_sampled(PaperLaw(), None, START[:, :3], t_final=1.0, sampler=Sampler(0.1), substeps=10)
    assert out.t.shape == (11,) and out.q.shape == (11, 3) and out.u.shape == (10, 2)
    np.testing.assert_array_equal(np.asarray(out.q), np.asarray(run.q)[0])
    np.testing.assert_array_equal(np.asarray(out.u), np.asarray(run.u)[0])
    with pytest.raises(ValueError, match="must be the sampling period"):
        js.solve(law, jnp.asarray([1.0, 1.0, 0.5]), t_final=1.0, saveat=js.SaveAt(every=5))
