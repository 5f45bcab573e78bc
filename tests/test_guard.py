"""The settled oscillation's guard (`jaxsleigh.integrate.guard`): its damping \\(\\sigma\\) and frequency are the complex
pair's of the Jacobian, the guard acts only near the target where the pair is weakly damped, and not at all for the
paper's gains."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsleigh as js
from jaxsleigh.integrate import guard
from jaxsleigh.model.charts import WChart

#: settled states in the w chart (w1 = theta small, the rest smaller), where the pair is fast
STATES = np.array([[0.02, 1e-4, -2e-4, 1e-4, 0.0], [-0.01, -3e-4, 1e-4, 0.0, 1e-5], [0.05, 2e-3, 1e-3, -1e-3, 2e-4]])
#: states near the target where the `balanced` gains' pair is weakly damped: sigma = -0.55 / s at omega = 171 rad/s
#: (guarded), and sigma = -0.35 / s at omega = 507 rad/s (faster than FASTEST: left alone)
WEAK = np.array([0.00302107, 0.00300406, -0.00071043, -0.00025541, -0.00595812])
FAST = np.array([0.00101785, -0.00069916, 0.03874416, -0.00072213, -0.0023888])


def _pair(field, y, args):
    """The complex pair of the full 5x5 Jacobian at ``y`` (the one of largest imaginary part)."""
    J = np.asarray(jax.jacfwd(lambda v: field(0.0, v, args))(jnp.asarray(y)))
    ev = np.linalg.eigvals(J)
    return ev[np.argmax(ev.imag)]


@pytest.mark.parametrize("gains", ["paper", "balanced", "tuned"])
def test_sigma_and_omega_are_the_jacobians_complex_pair(x64, gains):
    """\\(\\sigma \\pm i\\omega\\) from the (w2, p1, p2) block by Newton's method equals the block's own eigenvalues to
    rounding, and the full Jacobian's pair to 1% where it is settled."""
    args = js.ClosedLoop(js.paper_plant(), js.load_gains(gains))
    chart = WChart()
    for y in (*STATES, WEAK, FAST):
        sigma, omega2 = map(float, guard.pair_damping(chart.field, 0.0, jnp.asarray(y), args))
        J = np.asarray(jax.jacfwd(lambda v: chart.field(0.0, v, args))(jnp.asarray(y)))
        block = np.linalg.eigvals(J[np.ix_([1, 3, 4], [1, 3, 4])])
        pair = block[np.argmax(block.imag)]
        assert omega2 > 0 and pair.imag > 0
        np.testing.assert_allclose([sigma, np.sqrt(omega2)], [pair.real, pair.imag], rtol=1e-8, atol=1e-9)
        full = _pair(chart.field, y, args)
        np.testing.assert_allclose(np.sqrt(omega2), full.imag, rtol=1e-2)
        assert abs(sigma - full.real) <= 1e-2 * abs(full)


def test_the_guard_caps_steps_only_near_the_target_where_the_pair_is_weak(x64):
    """``(cap, atol)``: the cap is 0.5/omega and atol/100 (not below 1e-8) where |q| <= 4 eps, sigma > -0.75 and
    omega < 500 rad/s; inf and atol where the pair is well damped (the paper's gains settle with sigma < -1), faster,
    or far from the target."""
    chart = WChart()
    eps, atol = 0.05, 1e-6
    seen = set()
    for gains in ("paper", "balanced"):
        args = js.ClosedLoop(js.paper_plant(), js.load_gains(gains))
        for y in (*STATES, WEAK, FAST):
            y = jnp.asarray(y)
            sigma, omega2 = map(float, guard.pair_damping(chart.field, 0.0, y, args))
            cap, tol = map(float, guard.oscillation_guard(chart, 0.0, y, args, atol, eps))
            weak = sigma > -guard.DAMPING
            guarded = weak and np.sqrt(omega2) < guard.FASTEST
            seen.add((weak, guarded))
            if guarded:
                assert cap == pytest.approx(guard.PHASE / np.sqrt(omega2))
                assert tol == pytest.approx(max(atol / 100, guard.ATOL_FLOOR))
            else:
                assert cap == np.inf and tol == atol
            far = y.at[1].set(2.0)                          # |q| > 4 eps: never guarded
            assert float(guard.oscillation_guard(chart, 0.0, far, args, atol, eps)[0]) == np.inf
    assert seen == {(False, False), (True, True), (True, False)}     # every branch was checked
    paper = js.ClosedLoop(js.paper_plant(), js.paper_gains())
    assert all(float(guard.pair_damping(chart.field, 0.0, jnp.asarray(y), paper)[0]) < -guard.DAMPING for y in STATES)
