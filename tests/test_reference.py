"""simulate() against an independent reference: scipy's Radau (rtol 1e-9, atol 1e-11) on the
physical-chart closed loop ``vector_field`` in float64, with its Jacobian from ``jax.jacfwd``,
over the paper's 100 s horizon. (At rtol 1e-10, atol 1e-12 it took 1.7x the calls and moved q by at most 2.3e-10,
p by 2.1e-9: four orders below the tightest bar here, 1e-5; the table below was measured against it.)

Measured when these tolerances were set (max over the 0.1 s output grid of max |q - q_ref|):

================================  =========  =========  =========  =========  =========  =========
start                             (-3,-2,    (1,1,      (2,-1,     (-1,2,     (1,-2,.7,  (-2,1,-.4,
                                  pi/8)      .5)        -1)        2.5)       1,-.5)     -.8,.6)
================================  =========  =========  =========  =========  =========  =========
adaptive, float64                 3.5e-7     5.4e-9     1.2e-9     1.8e-9     1.1e-7     1.2e-7
rk4 (dt = 0.01), float64          1.5e-2     7.0e-6     2.0e-9     2.5e-9     2.2e-5     1.7e-5
adaptive, float32 (varies ~10%)   9.7e-5     3.5e-6     2.5e-6     9.6e-6     5.6e-6     6.6e-6
================================  =========  =========  =========  =========  =========  =========

The paper's start (initial w = (0.39, -18.1, 9.1), so large potential forces) is too stiff for
fixed-step RK4 at dt = 0.01: it is 1.5e-2 off while reporting status OK. The rk4 comparison
therefore uses the other starts only; test_adaptive_beats_fixed_rk4_on_the_stiff_paper_start
records the gap.
"""
from __future__ import annotations

import jax
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import jaxsleigh as js
from jaxsleigh.model.closed_loop import ClosedLoop
from jaxsleigh.status import Status
from numpy_field import numpy_field  # noqa: E402

pytestmark = pytest.mark.slow

T_FINAL = 100.0
DT = 0.01
SAVE_EVERY = 10
STARTS = {
    "paper": (-3.0, -2.0, np.pi / 8, 0.0, 0.0),
    "a": (1.0, 1.0, 0.5, 0.0, 0.0),
    "b": (2.0, -1.0, -1.0, 0.0, 0.0),
    "c": (-1.0, 2.0, 2.5, 0.0, 0.0),
    "momentum1": (1.0, -2.0, 0.7, 1.0, -0.5),
    "momentum2": (-2.0, 1.0, -0.4, -0.8, 0.6),
}
NAMES = list(STARTS)
ICS = np.array([STARTS[k] for k in NAMES])
NON_STIFF = [k for k in NAMES if k != "paper"]

TOL_Q = {("adaptive", True): 1e-5, ("rk4", True): 1e-4, ("adaptive", False): 1e-3}


@pytest.fixture(scope="module")
def radau_reference():
    """(n_starts, T, 5) reference states on the simulate() output grid."""
    t_eval = np.linspace(0.0, T_FINAL, int(round(T_FINAL / (DT * SAVE_EVERY))) + 1)
    with jax.enable_x64(True):
        args = ClosedLoop(js.paper_plant(), js.paper_gains())
        f, jac = numpy_field(args)
        refs = []
        for y0 in ICS:
            sol = solve_ivp(f, (0.0, T_FINAL), y0, method="Radau", rtol=1e-9, atol=1e-11, jac=jac, t_eval=t_eval)
            assert sol.status == 0, sol.message
            refs.append(sol.y.T)
    return t_eval, np.array(refs)


@pytest.fixture(scope="module")
def runs():
    """simulate() of all starts with each (method, x64) combination, computed once."""
    out = {}
    for method, x64 in TOL_Q:
        out[method, x64] = js.simulate(ICS, t_final=T_FINAL, dt=DT, x64=x64,
                                       stepsize=js.StepSizeController(method=method),
                                       saveat=js.SaveAt(every=SAVE_EVERY))
    return out


def _q_errors(sol, ref):
    return {k: float(np.max(np.abs(sol.q[i] - ref[i, :, :3]))) for i, k in enumerate(NAMES)}


@pytest.mark.parametrize("method,x64", list(TOL_Q), ids=["adaptive-float64", "rk4-float64", "adaptive-float32"])
def test_simulate_matches_radau(method, x64, runs, radau_reference):
    t_eval, ref = radau_reference
    sol = runs[method, x64]
    np.testing.assert_allclose(sol.t, t_eval, atol=1e-9)
    assert sol.q.shape == (len(NAMES), t_eval.size, 3)
    names = NAMES if method == "adaptive" else NON_STIFF
    assert all(sol.status[NAMES.index(k)] == Status.OK for k in names)
    errs = _q_errors(sol, ref)
    print(f"\nmax |q - q_radau| ({method}, {'float64' if x64 else 'float32'}): "
          + ", ".join(f"{k}={errs[k]:.2e}" for k in names))
    bad = {k: errs[k] for k in names if not errs[k] <= TOL_Q[method, x64]}
    assert not bad, bad
    # the trajectories are not trivial: they travel from |q| ~ 1-4 to near the origin
    for i, k in enumerate(names):
        assert np.linalg.norm(ref[NAMES.index(k), 0, :3]) > 0.5
        assert np.linalg.norm(ref[NAMES.index(k), -1, :3]) < 0.1


def test_momenta_match_radau_adaptive_float64(runs, radau_reference):
    _, ref = radau_reference
    sol = runs["adaptive", True]
    assert np.max(np.abs(sol.p - ref[:, :, 3:])) < 1e-4


def test_adaptive_beats_fixed_rk4_on_the_stiff_paper_start(runs, radau_reference):
    _, ref = radau_reference
    i = NAMES.index("paper")
    err_adaptive = np.max(np.abs(runs["adaptive", True].q[i] - ref[i, :, :3]))
    err_rk4 = np.max(np.abs(runs["rk4", True].q[i] - ref[i, :, :3]))
    assert err_adaptive < 1e-2 * err_rk4
