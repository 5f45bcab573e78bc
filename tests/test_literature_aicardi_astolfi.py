"""Two laws from the literature: Aicardi et al. (1995) and Astolfi (1996).

Each is checked against its paper's claim on the kinematic loop (integrated here with SciPy), then at force
level through `jaxsleigh.simulate` / `jaxsleigh.run_ensemble`, and against an independent SciPy Radau
integration of the force-level loop (plant written out below in NumPy).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.linalg import expm

import jaxsleigh as js
from jaxsleigh.controllers.aicardi import AicardiLaw, polar_coordinates
from jaxsleigh.controllers.astolfi import AstolfiLaw, chained_form
from jaxsleigh.model.controller import as_controller

#: One start per quadrant, headings of both signs, one nearly reversed (theta0 = 3).
STARTS = np.array([(2.0, 1.0, 0.5), (-2.0, 1.5, -1.0), (-1.5, -2.0, 2.0), (2.5, -1.0, -2.5), (0.5, 0.2, 3.0)])

M, I = 2.0, 3.0             # the nominal plant: m = 2, I = J + m l^2 = 3


def wrap(a):
    return np.arctan2(np.sin(a), np.cos(a))


# compiled once per law class (the gains are traced leaves)
_kinematic = jax.jit(jax.vmap(lambda c, q: c.kinematic(q), in_axes=(None, 0)))
_force = jax.jit(lambda c, q, v: c(q, v))


def kinematic_loop(law, starts, t_eval, rtol=1e-11, atol=1e-14):
    """The kinematic closed loop ``qdot = (v cos theta, v sin theta, omega)`` from every start at once (SciPy)."""

    def f(t, y):
        q = y.reshape(-1, 3)
        vw = np.asarray(_kinematic(law, jnp.asarray(q)))
        return np.column_stack([vw[:, 0] * np.cos(q[:, 2]), vw[:, 0] * np.sin(q[:, 2]), vw[:, 1]]).ravel()

    sol = solve_ivp(f, (0.0, t_eval[-1]), np.asarray(starts, float).ravel(), method="DOP853", t_eval=t_eval,
                    rtol=rtol, atol=atol)
    assert sol.success, sol.message
    return sol.y.reshape(len(starts), 3, -1).transpose(0, 2, 1)      # (N, T, 3)


def radau_force_loop(law, y0, t_eval):
    """The force-level closed loop integrated independently: the sleigh (m = 2, J = 1, l = 1, smoothed
    Coulomb damping d_i = v_i / sqrt(0.1 + p_i^2)) in NumPy, ``u`` from the law, SciPy Radau."""

    def f(t, s):
        x, y, th, p1, p2 = s
        v1, v2 = p1 / M, p2 / I
        u1, u2 = np.asarray(_force(law, jnp.asarray(s[:3]), jnp.asarray([v1, v2])))
        d1, d2 = v1 / np.sqrt(0.1 + p1 * p1), v2 / np.sqrt(0.1 + p2 * p2)
        return [v1 * np.cos(th), v1 * np.sin(th), v2, M * 1.0 * v2 * v2 - d1 + u1, -M * 1.0 * v1 * v2 - d2 + u2]

    sol = solve_ivp(f, (0.0, t_eval[-1]), y0, method="Radau", rtol=1e-9, atol=1e-11, t_eval=t_eval)
    assert sol.success, sol.message
    return sol.y.T


def velocity_error(law, sol):
    """``v - v_ref(q)`` along a `Solution` (N, T, 2)."""
    v = sol.p / np.array([M, I])
    ref = np.asarray(jax.vmap(jax.vmap(law.kinematic))(jnp.asarray(sol.q)))
    return v - ref


def check_velocity_loop(law, sol, t_max=3.0):
    """With the exact model the lift makes v - v_ref decay exactly like exp(-K t) (lift.py)."""
    err = velocity_error(law, sol)
    keep = sol.t <= t_max
    predicted = err[:, :1] * np.exp(-law.K * sol.t[keep])[None, :, None]
    assert np.max(np.abs(err[:, keep] - predicted)) < 1e-6 * np.max(np.abs(err[:, 0]))


TOL = js.StepSizeController(rtol=1e-10, atol=1e-12)

#: The starts at rest, and one moving start (x, y, theta, p1, p2) for the comparison with Radau.
MOVING = np.array([-2.0, 1.5, -1.0, 0.4, -0.6])
ICS = np.vstack([np.column_stack([STARTS, np.zeros((len(STARTS), 2))]), MOVING])


def force_level_run(law, t_final):
    """`js.simulate` in float64 (tight tolerances) from ``ICS``: shared by the tests of one law."""
    return js.simulate(ICS, controller=law, t_final=t_final, x64=True, stepsize=TOL)


def check_against_radau(law, sol, times=(2.0, 4.0, 8.0)):
    idx = [int(np.argmin(np.abs(sol.t - t))) for t in times]
    ref = radau_force_loop(law, ICS[-1], np.asarray(sol.t[idx]))
    mine = np.concatenate([sol.q[-1, idx], sol.p[-1, idx]], axis=1)
    assert np.max(np.abs(mine)) > 0.05                       # compared while still moving, not at the goal
    np.testing.assert_allclose(mine, ref, rtol=0, atol=1e-6)


@pytest.fixture(scope="module")
def aicardi_run():
    return force_level_run(AicardiLaw(), 40.0)


@pytest.fixture(scope="module")
def astolfi_run():
    return force_level_run(AstolfiLaw(), 40.0)


# --------------------------------------------------------------------------------------------------------
# contract: names, finiteness at the singular points, jit / vmap / grad
# --------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("Law", [AicardiLaw, AstolfiLaw])
def test_contract_and_finite_at_singular_points(Law, x64):
    law = as_controller(Law())
    assert Law.name in ("aicardi", "astolfi") and Law.name in Law.citation.lower()
    assert set(Law.needs) == {"m", "J", "l", "damping"} and isinstance(Law().model, js.PlantParams)
    v = jnp.array([0.3, -0.2])
    # the singular points: the goal for the polar law, theta = 0 for the sigma-process
    points = [jnp.array([0.0, 0.0, 0.4]), jnp.zeros(3), jnp.array([1e-300, -1e-300, 0.1]),
              jnp.array([1.5, -2.0, 0.0]), jnp.array([1.5, -2.0, 1e-300])]
    with_jac = jax.jit(jax.vmap(lambda c, q, v: (c(q, v), jax.jacfwd(lambda qq: c(qq, v))(q)), in_axes=(None, 0, None)))
    u, g = with_jac(law, jnp.stack(points), v)
    assert np.all(np.isfinite(u)) and np.all(np.isfinite(g)), (u, g)
    plain = jax.jit(jax.vmap(lambda c, q, v: c(q, v), in_axes=(None, 0, None)))
    for c, dtype in ((law, jnp.float32), (Law(model=None), jnp.float64)):
        u = plain(c, jnp.stack(points).astype(dtype), v.astype(dtype))
        assert u.dtype == dtype and np.all(np.isfinite(u)), (dtype, u)
    # vmap equals the loop
    q = jnp.asarray(STARTS)
    vs = jnp.tile(v, (len(STARTS), 1))
    np.testing.assert_allclose(jax.jit(jax.vmap(lambda q, v: law(q, v)))(q, vs), np.stack([_force(law, qi, v) for qi in q]),
                               rtol=1e-12, atol=1e-12)


# --------------------------------------------------------------------------------------------------------
# Aicardi, Casalino, Bicchi, Balestrino (1995)
# --------------------------------------------------------------------------------------------------------

def test_aicardi_lyapunov_derivative_identity(x64, rng):
    """dV/dt = grad V . qdot equals -lambda gamma cos^2(alpha) e^2 - k alpha^2 (the paper's design)."""
    law = AicardiLaw(gamma=0.7, k=1.3, h=2.0)
    lam = 1.7

    @jax.jit
    @jax.vmap
    def both(q):
        v, w = law.kinematic(q)
        qdot = jnp.stack([v * jnp.cos(q[2]), v * jnp.sin(q[2]), w])
        e, alpha, _ = polar_coordinates(q)
        return (jnp.dot(jax.grad(law.lyapunov)(q, lam), qdot),
                -lam * law.gamma * jnp.cos(alpha) ** 2 * e ** 2 - law.k * alpha ** 2)

    vdot, expected = both(jnp.asarray(rng.uniform([-3, -3, -3], [3, 3, 3], size=(50, 3))))
    assert np.all(expected < 0)
    np.testing.assert_allclose(vdot, expected, rtol=1e-10, atol=1e-12)


def test_aicardi_kinematic_loop_converges_with_V_non_increasing(x64):
    law = AicardiLaw()
    t = np.linspace(0.0, 40.0, 801)
    Q = kinematic_loop(law, STARTS, t)
    V = np.asarray(jax.vmap(jax.vmap(law.lyapunov))(jnp.asarray(Q)))
    assert np.all(V[:, 0] > 1.0)
    assert np.all(np.diff(V, axis=1) <= 1e-9 * V[:, :1]), np.max(np.diff(V, axis=1))   # no jump either
    e, alpha, vartheta = (np.asarray(a) for a in jax.vmap(polar_coordinates)(jnp.asarray(Q[:, -1])))
    assert np.all(e < 1e-8) and np.all(np.abs(alpha) < 1e-7) and np.all(np.abs(vartheta) < 1e-7)
    assert np.all(np.abs(Q[:, -1, :2]) < 1e-8) and np.all(np.abs(wrap(Q[:, -1, 2])) < 1e-7)
    # the heading converges modulo 2 pi: the starts whose alpha0 = vartheta0 - theta0 leaves (-pi, pi] unwind
    # by one turn
    n_turns = np.round((Q[:, -1, 2]) / (2 * np.pi))
    e0, alpha0, vartheta0 = (np.asarray(a) for a in jax.vmap(polar_coordinates)(jnp.asarray(STARTS)))
    np.testing.assert_array_equal(n_turns, np.round((STARTS[:, 2] - vartheta0 + alpha0) / (2 * np.pi)))


def test_aicardi_force_level_converges(aicardi_run, x64):
    law, sol = AicardiLaw(), aicardi_run
    assert np.all(sol.status == 0)
    assert np.all(np.isfinite(sol.u))
    qf = sol.q[:, -1]
    assert np.all(np.abs(qf[:, :2]) < 1e-10) and np.all(np.abs(wrap(qf[:, 2])) < 1e-10), qf
    check_velocity_loop(law, sol)

    ens = js.run_ensemble(STARTS, controller=law, t_final=40.0)       # float32, default tolerances
    assert np.all(ens.status == 0)
    assert np.all(np.abs(ens.q_final[:, :2]) < 1e-4) and np.all(np.abs(wrap(ens.q_final[:, 2])) < 1e-4)


def test_aicardi_settles_with_the_heading_modulo_2pi(aicardi_run, x64):
    """The law steers theta to 0 modulo 2 pi, and its chart measures the heading so: T_eps of every start, also
    those that end at theta = +-2 pi, is the last exit from |(x, y, wrap(theta))| <= eps of the float64 solution
    (between its 0.1 s samples), and the float32 engine agrees with it to 1e-3 s. q_final keeps theta as
    integrated."""
    from jaxsleigh.model.charts import PhysicalChart, chart_for

    assert chart_for(AicardiLaw()) == PhysicalChart(heading_modulo=True)
    sol = aicardi_run
    turned = np.abs(sol.q[:, -1, 2]) > 6.0
    assert turned.sum() == 3 and np.allclose(np.abs(sol.q[turned, -1, 2]), 2 * np.pi, atol=1e-8)
    r = np.sqrt(sol.q[..., 0] ** 2 + sol.q[..., 1] ** 2 + wrap(sol.q[..., 2]) ** 2)
    last_out = np.array([np.nonzero(ri > 0.05)[0][-1] for ri in r])
    assert np.all(last_out < len(sol.t) - 1)
    T = np.asarray(sol.T_eps)
    assert np.all((sol.t[last_out] < T) & (T <= sol.t[last_out + 1]))
    ens = js.run_ensemble(ICS, controller=AicardiLaw(), t_final=40.0)
    np.testing.assert_allclose(ens.T_eps, T, rtol=0, atol=1e-3)
    np.testing.assert_allclose(np.abs(ens.q_final[turned, 2]), 2 * np.pi, atol=1e-4)


def test_heading_modulo_chart_follows_wrappers_and_the_sampled_loop(aicardi_run, x64):
    """A saturated or sampled Aicardi law keeps the heading modulo 2 pi (the sampled-data loop's T_eps too); the
    paper's law and a plain physical-chart law measure theta as integrated."""
    from jaxsleigh.controllers.actuators import Saturation, sampled
    from jaxsleigh.integrate.sampled import solve_sampled
    from jaxsleigh.model.charts import PhysicalChart, WChart, chart_for

    assert chart_for(Saturation(AicardiLaw(), 50.0)) == PhysicalChart(heading_modulo=True)
    assert chart_for(AstolfiLaw()) == PhysicalChart() and chart_for(js.paper_gains()) == WChart()
    y = np.array([0.01, 0.0, 2 * np.pi, 0.0, 0.0])
    assert PhysicalChart(heading_modulo=True).q_norm2(y) == pytest.approx(1e-4, rel=1e-9)
    assert PhysicalChart().q_norm2(y) == pytest.approx(1e-4 + 4 * np.pi ** 2, rel=1e-9)
    turned = STARTS[np.abs(aicardi_run.q[:len(STARTS), -1, 2]) > 6.0]
    digital = sampled(AicardiLaw(), period=0.02)
    r = solve_sampled(digital.law, js.paper_plant(), turned, t_final=40.0, sampler=digital.sampler,
                      dtype=jnp.float64)
    assert np.all(np.asarray(r.status) == 0)
    assert np.all(np.isfinite(r.T_eps)) and np.all(np.asarray(r.T_eps) < 15.0)
    assert np.all(np.abs(np.asarray(r.q_final[:, 2])) > 6.0)


def test_aicardi_against_radau(aicardi_run, x64):
    check_against_radau(AicardiLaw(), aicardi_run)


# --------------------------------------------------------------------------------------------------------
# Astolfi (1996)
# --------------------------------------------------------------------------------------------------------

#: (k, p2, p3) and the rate of |q| they predict: set by the slow eigenvalue of A, by k, and by both.
GAINS = [((1.0, 4.5, -6.0), 0.5), ((0.4, 3.4, -8.4), 0.4), ((1.0, 4.0, -6.0), 1.0)]


@pytest.mark.parametrize("gains, rate", GAINS)
def test_astolfi_kinematic_loop_is_linear_and_exponential(gains, rate, x64):
    law = AstolfiLaw(*gains)
    assert law.rate() == pytest.approx(rate, rel=1e-12)
    k, p2, p3 = gains
    assert k > 0 and p2 > k and p3 < -p2                           # the gain conditions (Hurwitz A)
    T = 18.0 / rate
    t = np.linspace(0.0, T, 601)
    Q = kinematic_loop(law, STARTS, t)
    x1, x2, x3 = (np.asarray(a) for a in jax.vmap(jax.vmap(chained_form))(jnp.asarray(Q)))
    # the sigma-process makes the closed loop linear: x1 = theta0 e^{-kt}, (x2, z3) = expm(A t) (x2, z3)(0)
    np.testing.assert_allclose(x1, x1[:, :1] * np.exp(-k * t), rtol=1e-7, atol=1e-13)
    A = law.closed_loop_matrix()
    lin = np.einsum("tij,nj->nti", np.stack([expm(A * ti) for ti in t]), np.column_stack([x2[:, 0], x3[:, 0] / x1[:, 0]]))
    np.testing.assert_allclose(x2, lin[..., 0], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(x3 / x1, lin[..., 1], rtol=1e-6, atol=1e-9)
    # |q| decays at the predicted rate: the slope of log |q| over the second half
    norm = np.linalg.norm(Q, axis=2)
    late = t >= T / 2
    slopes = np.polyfit(t[late], np.log(norm[:, late]).T, 1)[0]
    np.testing.assert_allclose(-slopes, rate, rtol=0.03)
    # and the bound |q(t)| <= C e^{-rate t} holds along the whole run, with C of the size of |q0|
    C = np.max(norm * np.exp(rate * t), axis=1)
    assert np.all(C < 20.0 * norm[:, 0])
    assert np.all(np.sign(x1) == np.sign(STARTS[:, 2:3]))          # theta never reaches 0


def test_astolfi_gains_outside_the_conditions_fail(x64):
    """p3 > -p2 makes det A < 0: an unstable mode, and the kinematic loop does not converge."""
    law = AstolfiLaw(k=1.0, p2=4.0, p3=-3.0)
    assert law.rate() < 0
    Q = kinematic_loop(law, STARTS[:2], np.linspace(0.0, 20.0, 11), rtol=1e-9, atol=1e-12)
    assert np.all(np.linalg.norm(Q[:, -1], axis=1) > 10.0 * np.linalg.norm(STARTS[:2], axis=1))


def test_astolfi_force_level_converges(astolfi_run, x64):
    law, sol = AstolfiLaw(), astolfi_run
    assert np.all(sol.status == 0)
    assert np.all(np.isfinite(sol.u))
    assert np.all(np.linalg.norm(sol.q[:, -1], axis=1) < 1e-12)
    # with K > k the heading of the lifted loop from rest keeps its sign (the chart theta != 0 is never left)
    assert np.all(np.sign(sol.q[:len(STARTS), :, 2]) == np.sign(STARTS[:, 2:3]))
    check_velocity_loop(law, sol)

    ens = js.run_ensemble(STARTS, controller=law, t_final=40.0)        # float32, default tolerances
    assert np.all(ens.status == 0)
    assert np.all(np.linalg.norm(ens.q_final, axis=1) < 1e-6)
    assert np.all(ens.T_eps < 10.0)


def test_astolfi_against_radau(astolfi_run, x64):
    check_against_radau(AstolfiLaw(), astolfi_run)


def test_aicardi_settling_time_is_the_same_in_float32_and_float64():
    """Tuned gains whose heading mode is slower than e (here gamma = 0.36, k = 0.64, h = 0.37: heading rate ~0.085 /s,
    e ~ exp(-0.36 t)) reach the goal's threshold of `polar_coordinates` before the heading settles. The threshold
    depends on the dtype, so it must be small enough not to decide T_0.05: float32 and float64 agree within 0.1 s on
    every start (with a threshold of 4e-7 in float32 they differed by up to 15 s)."""
    law = AicardiLaw(gamma=0.358, k=0.636, h=0.365, K=1.60)
    starts = np.array([(2.0, 1.0, 0.5), (-2.0, 1.5, -1.0), (-1.5, -2.0, 2.0), (2.5, -1.0, -2.5), (0.5, 0.2, 3.0),
                       (-2.8, 0.3, 0.4)])
    r32 = js.run_ensemble(starts, controller=law, t_final=100.0, run=js.RunOptions(progress=False))
    r64 = js.run_ensemble(starts, controller=law, t_final=100.0, x64=True, run=js.RunOptions(progress=False))
    assert np.all(np.isfinite(r64.T_eps)) and np.all(r64.T_eps > 20.0)
    np.testing.assert_allclose(r32.T_eps, r64.T_eps, rtol=0, atol=0.1)


def test_a_diverging_astolfi_run_is_reported_not_ok():
    """Astolfi's law with a slow velocity loop (K = 1.04 < the tuned k's needs) from starts with momentum drives theta
    through 0, where its output ~ x3 / theta is unbounded: in float32 the state stayed finite (|q| ~ 1e20) while the
    energy overflowed to inf, and the run ended status OK. It ends NONFINITE now, in both precisions."""
    from jaxsleigh.studies.compare import draw_compare_starts

    law = AstolfiLaw(k=0.211, p2=1.678, p3=-4.192, K=1.038)
    ics = draw_compare_starts("wide", 256, 0)[[22, 100]]
    for x64 in (False, True):
        r = js.run_ensemble(ics, controller=law, t_final=100.0, x64=x64, run=js.RunOptions(progress=False))
        assert r.status.tolist() == [js.Status.NONFINITE] * 2, (x64, r.status)
        assert not np.any(r.converged)
