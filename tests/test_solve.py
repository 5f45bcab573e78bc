"""The differentiable solve path: `jaxsleigh.integrate.solve` equals the ensemble engine, and jax.grad / jacfwd of its
outputs with respect to the controller's parameters, the plant's and the start match central finite
differences in float64, under jit and vmap."""
from __future__ import annotations


import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsleigh as js
from jaxsleigh.integrate.horizon import step_budget
from jaxsleigh.integrate.solve import loop_length, solve
from jaxsleigh.integrate.stepper import any_lane


from laws import PD  # noqa: E402


Y0 = np.array([1.0, 1.0, 0.5, 0.1, -0.2])
RK4 = js.StepSizeController(method="rk4")

# The tests share compiled programs (a cold run of this file compiled 36 programs of 0.5-120 s, 730 s in all): outside
# ``jit``, `solve` runs one jitted program per dtype, step budget (static), options and saving, whatever t_final, start,
# gains and tolerances (traced). So every eager float32 run here without saving is at t_final = 2 with its default
# budget `N32` (or that budget given), every one with saving at t_final = 2, every = 50, and every eager float64 adaptive
# run is at the budget `N64` of t_final = 10 (its default there); the float64 saving runs share `TIGHT`, 3 s, every 30.
N32 = step_budget(js.StepSizeController(), 2.0, 0.01, "float32")
N64 = step_budget(js.StepSizeController(), 10.0, 0.01, "float64")
TIGHT = js.StepSizeController(rtol=1e-10, atol=1e-10, max_steps=20_000)


def _fd(f, x, h):
    return (f(x + h) - f(x - h)) / (2 * h)


def test_solve_equals_the_ensemble_engine():
    with jax.enable_x64(True):
        out = solve(js.paper_gains(), jnp.asarray(Y0), t_final=10.0)      # jitted inside: budget N64
    res = js.run_ensemble(Y0[None], t_final=10.0, x64=True)
    np.testing.assert_allclose(np.asarray(out.q_final), res.q_final[0], rtol=1e-12)
    np.testing.assert_allclose(float(out.summaries["u_energy"]), res.u_energy[0], rtol=1e-12)
    np.testing.assert_allclose(float(out.summaries["T_eps"]), res.T_eps[0], rtol=1e-12)
    assert int(out.n_steps) == res.n_steps[0] and int(out.status) == res.status[0] == 0


@pytest.mark.parametrize("method, rtol", [("rk4", 1e-6), ("adaptive", 1e-4)])
def test_gradient_wrt_paper_gain_k_matches_finite_differences(method, rtol):
    g = js.paper_gains()
    with jax.enable_x64(True):
        def energy(k):
            law = js.Gains(jnp.asarray(g.L), jnp.asarray(k, jnp.float64), jnp.asarray(g.D_hat))  # strong type:
            # the finite differences' runs are then those of test_solve_equals_the_ensemble_engine's program
            stepsize = js.StepSizeController(rtol=1e-11, atol=1e-11, method=method, max_steps=N64)
            return solve(law, jnp.asarray(Y0), t_final=8.0, stepsize=stepsize).summaries["u_energy"]
        grad = jax.jit(jax.grad(energy))(0.1)
        fd = _fd(energy, 0.1, 1e-5)
    np.testing.assert_allclose(grad, fd, rtol=rtol)


def test_gradients_wrt_user_law_plant_and_start_match_finite_differences():
    with jax.enable_x64(True):
        def final_x(kp, m, x0):
            plant = js.PlantParams(m, 1.0, 1.0, js.CoulombDamping())
            y0 = jnp.asarray(Y0).at[0].set(x0)
            return solve(PD(kp, 1.5), y0, plant=plant, t_final=5.0, stepsize=RK4).q_final[0]
        grads = jax.jit(jax.grad(final_x, argnums=(0, 1, 2)))(2.0, 2.0, 1.0)
        fds = (_fd(lambda a: final_x(a, 2.0, 1.0), 2.0, 1e-5), _fd(lambda a: final_x(2.0, a, 1.0), 2.0, 1e-5),
               _fd(lambda a: final_x(2.0, 2.0, a), 1.0, 1e-5))
    np.testing.assert_allclose(np.asarray(grads), np.asarray(fds), rtol=1e-6)


def test_forward_mode_and_vmap_over_starts():
    with jax.enable_x64(True):
        starts = jnp.asarray(np.random.default_rng(0).uniform([-2, -2, 0.3], [2, 2, 2], (4, 3)))
        def final_q(kp, y0):
            return solve(PD(kp, 1.5), y0, t_final=3.0, stepsize=RK4).q_final

        @jax.jit
        def both(starts):       # one program (eager, the vmapped transforms compiled some 130 small ones)
            jac = jax.vmap(jax.jacfwd(final_q), in_axes=(None, 0))(2.0, starts)
            return jac, jax.vmap(lambda y: _fd(lambda a: final_q(a, y), 2.0, 1e-5))(starts)
        jac, fd = both(starts)
    assert jac.shape == (4, 3)
    np.testing.assert_allclose(np.asarray(jac), np.asarray(fd), rtol=1e-6, atol=1e-10)


def test_calling_solve_again_compiles_nothing(caplog, monkeypatch):
    """Outside ``jit`` the loop over time (with or without saving) is one jitted program per law, shapes and options:
    a second call, from another start and with another gain (of the same structure), compiles nothing; nor do calls
    at other horizons whose step budgets round up to the same loop (3 s and 100 s: 6,160 and 200,008 attempts, one
    loop of `MIN_LOOP`; each lane still stops at its own budget, and the result is that of a loop exactly as long as
    the attempts it made)."""
    import logging

    import jaxsleigh.integrate.solve as solve_module

    y0, y1 = jnp.asarray([1.0, 1.0, 0.5], jnp.float32), jnp.asarray([-1.0, 2.0, -0.4], jnp.float32)
    g = js.paper_gains()
    first = solve(g, y0, t_final=2.0)
    solve(g, y0, t_final=2.0, saveat=js.SaveAt(every=50))
    other = g._replace(k=g.k * 2)                  # the same structure and dtypes
    with jax.log_compiles(True), caplog.at_level(logging.DEBUG):
        caplog.clear()
        again = solve(other, y1, t_final=2.0)
        saved = solve(other, y1, t_final=2.0, saveat=js.SaveAt(every=50))
        longer = solve(other, y1, t_final=3.0)
        default_horizon = solve(other, y1)
        jax.block_until_ready((again, saved, longer, default_horizon))
    compiled = [r.getMessage() for r in caplog.records if "ompil" in r.getMessage()]
    assert compiled == []
    assert loop_length(6160) == loop_length(200_008) == solve_module.MIN_LOOP
    assert int(default_horizon.status) == js.Status.OK and float(default_horizon.t_reached) == 100.0
    assert not np.allclose(np.asarray(first.q_final), np.asarray(again.q_final))
    used = int(longer.n_steps + longer.n_rejected)
    monkeypatch.setattr(solve_module, "loop_length", lambda n: n)      # a loop of exactly the attempts made
    exact = solve(other, y1, t_final=3.0, stepsize=js.StepSizeController(max_steps=used))
    assert int(longer.status) == int(exact.status) == js.Status.OK
    np.testing.assert_array_equal(np.asarray(exact.q_final), np.asarray(longer.q_final))
    assert float(exact.u_energy) == float(longer.u_energy)


def test_solve_outside_jit_is_one_program():
    """`solve` called outside ``jit`` (as ``jax.grad(energy)(k)`` in the README) traces into one jitted program, with or
    without saving: the start's checks, the maps into and out of the law's chart and the output are inside it (traced
    op by op around the loop, they made ``jax.grad`` compile some 130 small programs)."""
    g, y = js.paper_gains(), jnp.asarray([1.0, 1.0, 0.5, 0.0, 0.0], jnp.float32)   # (5,): no momentum to append
    for saveat in (None, js.SaveAt(every=50)):
        jaxpr = jax.make_jaxpr(lambda k: solve(g._replace(k=k), y, t_final=2.0, saveat=saveat).u_energy)(0.1).jaxpr
        assert [e.primitive.name for e in jaxpr.eqns] in (["jit"], ["pjit"]), [e.primitive for e in jaxpr.eqns]


def test_solve_reports_an_exhausted_budget():
    """A horizon the budget cannot reach (N32 attempts of at most 100 base steps cover < 4,200 s) ends
    ``BUDGET_EXHAUSTED`` short of it, every attempt spent."""
    out = solve(js.paper_gains(), jnp.asarray(Y0, jnp.float32), t_final=1e5,
                stepsize=js.StepSizeController(max_steps=N32))
    assert int(out.status) == js.Status.BUDGET_EXHAUSTED and 0 < float(out.t_reached) < 1e5
    assert int(out.n_steps) + int(out.n_rejected) == N32


def test_solve_carries_a_stiff_flight_as_simulate_does():
    """A start 2e-4 rad from the singular set flies off stiffly: `solve` takes the same step budget and the same
    flight rule (the implicit step after 20,000 attempts at a tiny mean step) as `simulate`, and ends like it: OK at
    100 s, some 3e5 m away, the final states within the tolerances' reach (before, solve's own 4x budget and its
    explicit-only step left it BUDGET_EXHAUSTED at t = 0.096 s)."""
    y0 = np.array([1.9, -0.04, 2e-4], np.float32)
    out = solve(js.paper_gains(), jnp.asarray(y0), t_final=100.0)
    sol = js.simulate(y0[None], t_final=100.0)
    assert int(out.status) == sol.status[0] == js.Status.OK and float(out.t_reached) == 100.0
    assert abs(sol.q_final[0, 0]) > 1e5
    np.testing.assert_allclose(np.asarray(out.q_final), sol.q_final[0], rtol=1e-4)
    # the implicit step took over: an explicit-only run needs far more than the 24,255 accepted steps of the host
    assert int(out.n_steps) < 2 * sol.n_steps[0]


def test_near_the_singular_set_solve_never_lets_a_nan_through_silently():
    """Starts from 1e-2 down to 1e-7 rad of theta = 0 (both signs, with and without momentum, float32, where the
    flight switch and the overflow checks act): each ends OK with every output finite, or with a status that is not
    OK and NaN outputs; an OK row never carries a NaN or an inf."""
    thetas = [1e-2, -3e-3, 1e-3, -2e-4, 1e-5, 1e-7]
    starts = [[1.0, 1.0, th, 0.0, 0.0] for th in thetas] + [[1.9, -0.04, 2e-4, 0.0, 0.0], [-2.0, 1.0, 1e-3, 0.5, -0.3]]
    seen = set()
    for y in starts:
        out = solve(js.paper_gains(), jnp.asarray(y, jnp.float32), t_final=2.0)
        status = int(out.status)
        seen.add(status)
        values = [np.asarray(out.q_final), np.asarray(out.p_final), np.asarray(out.summaries["u_energy"]),
                  np.asarray(out.summaries["min_abs_theta"])]
        if status == js.Status.OK:
            assert all(np.all(np.isfinite(v)) for v in values), (y, values)
        elif status in js.status.NO_RESULT:
            assert all(np.all(np.isnan(v)) for v in values), (y, status, values)
        else:                                   # out of budget: summaries up to the time reached, never inf
            assert status == js.Status.BUDGET_EXHAUSTED and not any(np.any(np.isinf(v)) for v in values), (y, status)
    assert js.Status.OK in seen and seen - {js.Status.OK}, seen   # both kinds of ending are exercised


@pytest.mark.parametrize("kw, says", [({"t_final": -1.0}, "t_final must be > 0"),
                                      ({"t_final": float("nan")}, "t_final must be finite"),
                                      ({"dt": 0.0}, "dt must be > 0"),
                                      ({"eps": -0.1}, "eps must be > 0")])
def test_solve_refuses_a_setting_that_cannot_run(kw, says):
    """A negative horizon ran as status 0, ``dt = 0`` raised ZeroDivisionError: each is a ValueError naming it."""
    with pytest.raises(ValueError, match=says):
        solve(js.paper_gains(), Y0, **kw)


def test_solve_refuses_no_controller():
    with pytest.raises(ValueError, match="controller must be"):
        solve(None, Y0, t_final=1.0)


def test_solve_reports_a_start_that_cannot_be_integrated():
    """Such starts got ``step_underflow``; now the status that says what is wrong (non-finite ``INVALID_INPUT``,
    theta0 = 0 ``SINGULAR_START``, overflowing the w chart in float32 ``OUT_OF_RANGE``), NaN outputs and summaries,
    traced: vmapped with a good start, whose result is unchanged and whose gradient stays finite."""
    good = [1.0, 1.0, 0.5]
    starts = jnp.asarray(np.array([good, [np.nan, 1.0, 0.5], [1.0, 1.0, 0.0], [1.0, 1.0, 1e-30]], np.float32))

    def first_energy(y):
        out = jax.vmap(lambda y: solve(js.paper_gains(), y, t_final=2.0))(y)
        return out.summaries["u_energy"][0], out

    (_, out), g = jax.jit(jax.value_and_grad(first_energy, has_aux=True))(starts)   # one program: batch and gradient
    S = js.Status
    assert np.asarray(out.status).tolist() == [S.OK, S.INVALID_INPUT, S.SINGULAR_START, S.OUT_OF_RANGE]
    assert np.all(np.isnan(np.asarray(out.q_final[1:]))) and np.all(np.isnan(np.asarray(out.summaries["u_energy"][1:])))
    alone = solve(js.paper_gains(), np.asarray(good, np.float32), t_final=2.0)
    np.testing.assert_allclose(np.asarray(out.q_final[0]), np.asarray(alone.q_final), rtol=1e-5)  # batched code
    assert np.all(np.isfinite(np.asarray(g))) and np.all(np.asarray(g[1:]) == 0) and np.any(np.asarray(g[0]) != 0)
    assert int(solve(js.paper_gains(), np.array([1.0, 1.0, 0.0]), t_final=2.0).status) == S.SINGULAR_START


def _conds(jaxpr) -> int:
    """The ``cond`` equations of a jaxpr, nested ones included."""
    n = 0
    for e in jaxpr.eqns:
        n += e.primitive.name == "cond"
        for p in e.params.values():
            for q in p if isinstance(p, (tuple, list)) else [p]:
                inner = getattr(q, "jaxpr", q)
                n += _conds(getattr(inner, "jaxpr", inner)) if hasattr(getattr(inner, "jaxpr", inner), "eqns") else 0
    return n


def test_a_vmapped_solve_skips_the_segments_after_every_start_is_done():
    """Under `jax.vmap` a segment of the loop is skipped once every start of the batch is done, as for one start: the
    test is one branch for the batch (`any_lane`: the batch's any, unbatched), where a select per start ran every
    start to the end of the static budget (a 64-start gradient over 20 s: 61 s, now 0.5 s). So the static length,
    the budget rounded up to a power of four, costs nothing (`test_calling_solve_again_compiles_nothing`)."""
    assert jax.vmap(any_lane)(jnp.asarray([[False, False], [False, True]])).tolist() == [True, True]
    assert jax.vmap(any_lane)(jnp.zeros((3, 2), bool)).tolist() == [False] * 3
    starts = jnp.asarray([[1.0, 1.0, 0.5], [2.0, -1.0, 1.0]], jnp.float32)
    jaxpr = jax.make_jaxpr(jax.vmap(lambda y: solve(js.paper_gains(), y, t_final=1.0).q_final))(starts).jaxpr
    assert _conds(jaxpr) >= 1                 # the segments' skip (every per-start cond became a select)


def test_a_float32_start_too_close_to_theta_zero_is_out_of_range_with_nan_outputs():
    """theta0 = 1e-7 in float32: its w-chart state is finite but its |u|^2 (~1e41) overflows, so no step could be
    accepted; it ended ``STEP_UNDERFLOW`` with the start as its final state and 0 as its energy. It is
    ``OUT_OF_RANGE`` now, as the host fronts flag it, every output NaN; a start whose H_d overflows too."""
    for y0 in ([1.0, 0.0, 1e-7], [1e30, 1e30, 0.5]):
        out = solve(js.paper_gains(), jnp.asarray(y0, jnp.float32), t_final=2.0)
        assert int(out.status) == js.Status.OUT_OF_RANGE, y0
        assert np.all(np.isnan(np.asarray(out.q_final))) and np.all(np.isnan(np.asarray(out.p_final)))
        for name in ("T_eps", "u_energy", "u_abs_int", "u_norm_peak", "min_abs_theta", "max_excursion"):
            assert np.isnan(float(getattr(out, name))), (y0, name)
    with pytest.warns(js.errors.FlaggedStartsWarning, match="row 0 .*out_of_range.*effort integrand"):
        res = js.run_ensemble(np.array([[1.0, 0.0, 1e-7], [1.0, 0.0, 0.5]]), t_final=1.0,
                              run=js.RunOptions(progress=False))
    assert res.status.tolist() == [js.Status.OUT_OF_RANGE, js.Status.OK] and np.isnan(res.u_energy[0])


def test_saveat_gives_the_trajectory_of_the_host_front():
    """``saveat=SaveAt(every=n)``: the traced trajectory at the save times, as `js.simulate` saves it (float64, the
    same steps landing on the same save times: equal to rounding), the input there too, and its final state."""
    with jax.enable_x64(True):      # the settings of the trajectory loss below: one compiled program for both
        out = solve(js.paper_gains(), jnp.asarray(Y0), t_final=3.0, stepsize=TIGHT, saveat=js.SaveAt(every=30))
        sim = js.simulate(Y0, t_final=3.0, stepsize=TIGHT, saveat=js.SaveAt(every=30), x64=True)
    assert out.t.shape == (11,) and out.q.shape == (11, 3) and out.p.shape == (11, 2) and out.u.shape == (11, 2)
    np.testing.assert_allclose(np.asarray(out.t), np.asarray(sim.t), rtol=1e-15)
    np.testing.assert_allclose(np.asarray(out.q), np.asarray(sim.q).reshape(11, 3), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(np.asarray(out.p), np.asarray(sim.p).reshape(11, 2), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(np.asarray(out.u), np.asarray(sim.u).reshape(11, 2), rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(np.asarray(out.q[-1]), np.asarray(out.q_final), rtol=1e-12)
    assert int(out.status) == 0 and solve(js.paper_gains(), Y0[:3], t_final=2.0).t is None


def test_saveat_shares_the_budget_between_the_save_intervals():
    """A save interval that needs more than its share of ``max_steps`` ends the run ``BUDGET_EXHAUSTED`` there: the
    states it did not reach are NaN, never stale (the summaries are up to ``t_reached``, as without saving)."""
    # the stiff flight's start (test_solve_carries_a_stiff_flight_as_simulate_does): its explicit steps need some
    # 1e5 attempts in the first save interval, far more than its share of the default budget (N32 / 4)
    out = solve(js.paper_gains(), jnp.asarray([1.9, -0.04, 2e-4], jnp.float32), t_final=2.0, saveat=js.SaveAt(every=50))
    assert int(out.status) == js.Status.BUDGET_EXHAUSTED
    q = np.asarray(out.q)
    after = np.asarray(out.t) > float(out.t_reached)
    assert float(out.t_reached) < 2.0 and after.sum() >= 1 and np.all(np.isnan(q[after]))
    assert np.all(np.isfinite(q[~after])) and np.isfinite(float(out.u_energy))   # start saved; summaries to t_reached


def test_saveat_near_and_on_the_singular_set():
    """Vmapped with a good start: a start 1e-3 rad off theta = 0 with momentum, which float32 cannot carry through
    its default budget, ends with a status that says so, its start saved and every later state NaN, never a stale or
    silent number; a start on the set ends ``SINGULAR_START`` with every saved state and input NaN; the good start's
    trajectory is the one it has alone."""
    starts = jnp.asarray(np.array([Y0, [1.0, 1.0, 1e-3, 0.1, -0.2], [1.0, 1.0, 0.0, 0.1, -0.2]], np.float32))
    out = jax.jit(jax.vmap(lambda y: solve(js.paper_gains(), y, t_final=2.0, saveat=js.SaveAt(every=50))))(starts)
    status = np.asarray(out.status).tolist()
    assert status[0] == js.Status.OK and status[1] not in (js.Status.OK, js.Status.NONFINITE)
    assert status[2] == js.Status.SINGULAR_START
    q, p, u, t = (np.asarray(a) for a in (out.q, out.p, out.u, out.t))
    assert np.all(np.isfinite(q[0])) and np.all(np.isfinite(p[0])) and np.all(np.isfinite(u[0]))
    after = t[1] > float(out.t_reached[1])
    assert np.all(np.isfinite(q[1, 0])) and after.sum() >= 1
    assert np.all(np.isnan(q[1, after])) and np.all(np.isnan(p[1, after])) and np.all(np.isnan(u[1, after]))
    assert np.all(np.isnan(q[2])) and np.all(np.isnan(p[2])) and np.all(np.isnan(u[2]))
    alone = solve(js.paper_gains(), starts[0], t_final=2.0, saveat=js.SaveAt(every=50))
    np.testing.assert_allclose(q[0], np.asarray(alone.q), rtol=1e-5, atol=1e-6)


@pytest.mark.slow
def test_gradient_of_a_trajectory_loss_matches_finite_differences():
    """d/dk of the summed squared distance along the saved trajectory (float64, tight tolerances)."""
    g = js.paper_gains()

    def loss(k):
        out = solve(g._replace(k=k), jnp.asarray(Y0), t_final=3.0, stepsize=TIGHT, saveat=js.SaveAt(every=30))
        return jnp.sum(out.q ** 2)

    with jax.enable_x64(True):
        k0 = jnp.asarray(g.k)       # float64, as the host-front test's gains (one program for both)
        grad = float(jax.jit(jax.grad(loss))(k0))
        fd = float(_fd(loss, k0, 1e-6))      # eager: the jitted saving run of the host-front test
    np.testing.assert_allclose(grad, fd, rtol=1e-5)
    assert abs(grad) > 1e-3


@pytest.mark.parametrize("saveat, says", [(js.SaveAt(every=0), "whole number of base steps"),
                                          (js.SaveAt(every=3), "multiple of saveat.every"),
                                          (js.SaveAt(every=10, summaries=False), "summaries"),
                                          ({"every": 10}, "jaxsleigh.SaveAt")])
def test_solve_refuses_a_saveat_it_cannot_keep(saveat, says):
    with pytest.raises(ValueError, match=says):
        solve(js.paper_gains(), Y0[:3], t_final=1.0, saveat=saveat)
