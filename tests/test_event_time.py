"""The hard settling time's implicit-function derivative (jaxsleigh.tuning.event_time) against finite differences."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsleigh as js
from jaxsleigh.integrate.engine import check_ics, initial_w
from jaxsleigh.model.charts import WChart
from jaxsleigh.model.params import paper_gains, paper_plant
from jaxsleigh.model.shaped_law import shaped_gains
from jaxsleigh.tuning.event_time import settling

SHAPED = shaped_gains(L=[0.5, 0.5, 0.5], B=[2.0, 2.0, 2.0], C=[0.5, 0.5, 0.5], k=0.1, D_near=[4.0, 8.0],
                      D_far=[2.0, 4.0], s=1.0)


def _starts(n=33, seed=0):
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-3, 3, (n, 2)), rng.choice([-1, 1], n) * rng.uniform(0.3, np.pi, n)])


def _run(ics, t_final):
    ics5, st = check_ics(ics)
    y0w = initial_w(ics5, st, jnp.float64, WChart())
    plant = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64), paper_plant())
    return jax.jit(lambda c: settling(c, y0w, plant, t_final=t_final,
                                          stepsize=js.StepSizeController(rtol=1e-9, atol=1e-9)))


@pytest.mark.parametrize("law,field,index", [("shaped", "L", 0), ("shaped", "B", 1), ("paper", "k", None)])
def test_median_settling_time_derivative_matches_finite_differences(law, field, index):
    """d median(T_eps) / d(parameter) by the implicit function theorem (forward mode through the adaptive RK4 and
    its dense output) against central differences of the hard median; and the value is the engine's T_eps."""
    ics = _starts()
    with jax.enable_x64(True):
        c = jax.tree_util.tree_map(jnp.asarray, SHAPED if law == "shaped" else paper_gains())
        f = _run(ics, 100.0)

        def with_value(x):
            leaf = getattr(c, field)
            return c._replace(**{field: x if index is None else leaf.at[index].set(x)})

        x0 = getattr(c, field) if index is None else getattr(c, field)[index]
        r = f(c)
        ref = js.run_ensemble(ics, controller=c, t_final=100.0, x64=True,
                              stepsize=js.StepSizeController(rtol=1e-9, atol=1e-9))
        settled = np.isfinite(ref.T_eps)
        assert settled.sum() >= 20
        np.testing.assert_array_equal(np.asarray(r.settled), settled)
        np.testing.assert_allclose(np.asarray(r.T)[settled], ref.T_eps[settled], atol=1e-4)
        med = lambda x: jnp.median(f(with_value(x)).T)  # noqa: E731
        _, grad = jax.jvp(med, (x0,), (jnp.ones_like(x0),))
        h = 1e-3 * float(x0)
        fd = (med(x0 + h) - med(x0 - h)) / (2 * h)
        assert abs(float(grad)) > 1e-2
        assert abs(float(grad) - float(fd)) <= 1e-3 * abs(float(fd)) + 1e-6


def test_unsettled_starts_count_the_horizon_with_no_derivative():
    ics = _starts(9, seed=3)
    with jax.enable_x64(True):
        c = jax.tree_util.tree_map(jnp.asarray, SHAPED)
        f = _run(ics, 5.0)                             # too short a horizon for any start to settle
        T, dT = jax.jvp(lambda x: f(c._replace(k=x)).T, (c.k,), (jnp.ones_like(c.k),))
        assert not np.any(np.asarray(f(c).settled))
        np.testing.assert_array_equal(np.asarray(T), 5.0)
        np.testing.assert_array_equal(np.asarray(dT), 0.0)
