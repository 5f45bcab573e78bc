"""The hard settling time's implicit-function derivative (jaxsleigh.tuning.event_time) against finite differences."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsleigh as js
from jaxsleigh.integrate.engine import check_ics, initial_w
from jaxsleigh.integrate.horizon import step_budget
from jaxsleigh.integrate.stepsize import check_policy
from jaxsleigh.model.charts import WChart
from jaxsleigh.model.params import paper_gains, paper_plant
from jaxsleigh.model.shaped_law import shaped_gains
from jaxsleigh.tuning.event_time import settling

SHAPED = shaped_gains(L=[0.5, 0.5, 0.5], B=[2.0, 2.0, 2.0], C=[0.5, 0.5, 0.5], k=0.1, D_near=[4.0, 8.0],
                      D_far=[2.0, 4.0], s=1.0)


def _starts(n=33, seed=0):
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-3, 3, (n, 2)), rng.choice([-1, 1], n) * rng.uniform(0.3, np.pi, n)])


#: the budget of attempts given explicitly (the default of a 100 s horizon in float64), so that the horizon is a
#: traced argument: one program per law family serves every horizon, parameter and direction of this module
STEPSIZE = js.StepSizeController(rtol=1e-9, atol=1e-9)
_BUDGETED = STEPSIZE._replace(max_steps=step_budget(check_policy(STEPSIZE), 100.0, 0.01, jnp.float64))


@jax.jit
def _settle_jvp(c, dc, y0w, plant, t_final):
    """``(settling, median T), (their tangents along dc)`` of the law ``c`` on the chart starts ``y0w``: forward mode
    through the adaptive RK4 and its dense output (the implicit function theorem), the median of the hard T."""
    def run(c):
        r = settling(c, y0w, plant, t_final=t_final, stepsize=_BUDGETED)
        return r, jnp.median(r.T)

    return jax.jvp(run, (c,), (dc,))


def _setup(ics, law):
    """Arguments of `_settle_jvp` in float64 NumPy (one signature): the law's leaves, the chart starts, the plant."""
    ics5, st = check_ics(ics)
    y0w = np.asarray(initial_w(ics5, st, jnp.float64, WChart()))
    plant = jax.tree_util.tree_map(lambda x: np.asarray(x, np.float64), paper_plant())
    c = jax.tree_util.tree_map(lambda x: np.array(x, np.float64), law)
    return c, y0w, plant


def _direction(c, field, index):
    """The tangent of ``c`` that moves ``field`` (entry ``index``, or the scalar) alone by 1."""
    dc = jax.tree_util.tree_map(np.zeros_like, c)
    getattr(dc, field)[... if index is None else index] = 1.0
    return dc


@pytest.mark.parametrize("law,field,index", [("shaped", "L", 0), ("shaped", "B", 1), ("paper", "k", None)])
def test_median_settling_time_derivative_matches_finite_differences(law, field, index):
    """d median(T_eps) / d(parameter) by the implicit function theorem (forward mode through the adaptive RK4 and
    its dense output) against central differences of the hard median; and the value is the engine's T_eps."""
    ics = _starts()
    with jax.enable_x64(True):
        c, y0w, plant = _setup(ics, SHAPED if law == "shaped" else paper_gains())
        dc = _direction(c, field, index)
        (r, _), (_, grad) = _settle_jvp(c, dc, y0w, plant, 100.0)
        ref = js.run_ensemble(ics, controller=c, t_final=100.0, x64=True, stepsize=STEPSIZE)
        settled = np.isfinite(ref.T_eps)
        assert settled.sum() >= 20
        np.testing.assert_array_equal(np.asarray(r.settled), settled)
        np.testing.assert_allclose(np.asarray(r.T)[settled], ref.T_eps[settled], atol=1e-4)
        x0 = float(getattr(c, field)[... if index is None else index])
        h = 1e-3 * x0

        def med(x):                                   # the hard median at the parameter x (the same program)
            return float(_settle_jvp(jax.tree_util.tree_map(lambda a, d: a + (x - x0) * d, c, dc), dc, y0w, plant,
                                     100.0)[0][1])

        fd = (med(x0 + h) - med(x0 - h)) / (2 * h)
        assert _settle_jvp._cache_size() <= 2          # one program per law family, whatever the parameter
        assert abs(float(grad)) > 1e-2
        assert abs(float(grad) - float(fd)) <= 1e-3 * abs(float(fd)) + 1e-6


def test_unsettled_starts_count_the_horizon_with_no_derivative():
    """The starts of the test above (and its program) with a horizon too short for any start to settle: T is the
    horizon and its derivative 0."""
    with jax.enable_x64(True):
        c, y0w, plant = _setup(_starts(), SHAPED)
        (r, _), (dr, _) = _settle_jvp(c, _direction(c, "k", None), y0w, plant, 5.0)
        assert not np.any(np.asarray(r.settled))
        np.testing.assert_array_equal(np.asarray(r.T), 5.0)
        np.testing.assert_array_equal(np.asarray(dr.T), 0.0)
