"""The linearly implicit Rosenbrock step of the stiff stragglers: its 5x5 solve against NumPy, its order measured
against DOP853, a lane's bits whatever its neighbours' step, saved trajectories that switch, and the basin's fliers
carried to the horizon in agreement with float64 Radau."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import jaxsleigh as js
from jaxsleigh.integrate.engine import STIFF_AFTER, advance_lanes, check_ics, drive_final, initial_w, make_horizon
from jaxsleigh.integrate.rosenbrock import D, lu_factor, lu_solve, lu_solve_transposed, rosenbrock_stages
from jaxsleigh.model.closed_loop import ClosedLoop, state_from_w, state_to_w, vector_field_w, vector_field_w_control
from numpy_field import numpy_field

#: a start of the default basin (seed 5) 2e-4 rad from the singular set: a stiff flight of ~10^5 m
FLIER = [1.9, -0.04, 2e-4]


def test_the_pivoted_solve_agrees_with_numpy():
    """Gaussian elimination with pairwise pivoting, lane by lane, solves as LAPACK does, also where the first pivot
    is zero and where the matrices need a row exchange at every column."""
    rng = np.random.default_rng(3)
    a = rng.normal(size=(5, 5, 16))
    a[0, 0, :4] = 0.0                                  # no pivot in place
    a[:, :, 4] = np.eye(5)[::-1] * np.arange(1, 6)     # a reversal: every column swaps
    b = rng.normal(size=(5, 16))
    with jax.enable_x64(True):
        x = np.stack(lu_solve(lu_factor([[jnp.asarray(a[r, c]) for c in range(5)] for r in range(5)]),
                              [jnp.asarray(v) for v in b]))
        lu = lu_factor([[jnp.asarray(a[r, c]) for c in range(5)] for r in range(5)])
        xt = np.stack(lu_solve_transposed(lu, [jnp.asarray(v) for v in b]))
    ref = np.stack([np.linalg.solve(a[:, :, k], b[:, k]) for k in range(16)], axis=1)
    np.testing.assert_allclose(x, ref, rtol=1e-10, atol=1e-12)
    ref_t = np.stack([np.linalg.solve(a[:, :, k].T, b[:, k]) for k in range(16)], axis=1)   # the reverse pass's solve
    np.testing.assert_allclose(xt, ref_t, rtol=1e-10, atol=1e-12)


def test_the_steps_derivatives_match_finite_differences_and_the_elimination_differentiated():
    """The solves with W are differentiated through their own transposed solve, not through the elimination
    (`jax.lax.custom_linear_solve`): reverse and forward mode of a stiff step from the flier's neighbourhood
    (h |J| >> 1) agree with central differences, and with differentiating the written-out elimination itself."""
    args = ClosedLoop(js.paper_plant(), js.paper_gains())

    def plain(y, h):                  # the same step, the elimination differentiated as written
        f0 = vector_field_w(0.0, y, args)
        hd = h * D
        jac = jax.jacfwd(lambda yy: vector_field_w(0.0, yy, args))(y)
        ft = jnp.zeros_like(y)
        lu = lu_factor([[(1.0 if r == c else 0.0) - hd * jac[r, c] for c in range(5)] for r in range(5)])
        solve = lambda v: jnp.stack(lu_solve(lu, list(v)))  # noqa: E731
        k1 = solve(f0 + hd * ft)
        f1 = vector_field_w(0.5 * h, y + 0.5 * h * k1, args)
        k2 = solve(f1 - k1) + k1
        return h * k2

    with jax.enable_x64(True):
        y0 = state_to_w(jnp.asarray(FLIER + [0.0, 0.0], jnp.float64))
        c = jnp.asarray(np.random.default_rng(1).normal(size=5) / (np.abs(np.asarray(y0)) + 1.0))

        def loss(y, h):
            dy = rosenbrock_stages(vector_field_w_control, 0.0, y, h, args, vector_field_w(0.0, y, args))[0]
            return jnp.sum(c * dy)

        @jax.jit
        def derivatives(y, h):
            rev = jax.grad(loss, argnums=(0, 1))(y, h)
            fwd = jax.jacfwd(loss, argnums=(0, 1))(y, h)
            ref = jax.grad(lambda y, h: jnp.sum(c * plain(y, h)), argnums=(0, 1))(y, h)
            return rev, fwd, ref, jax.jacfwd(lambda yy: vector_field_w(0.0, yy, args))(y)

        h0 = 1e-3
        (gy, gh), fwd, ref, jac = derivatives(y0, h0)
        d = 1e-6 * np.maximum(np.abs(np.asarray(y0)), 1e-3)     # relative steps: the first entry is ~theta
        pts = np.concatenate([np.asarray(y0) + np.diag(d), np.asarray(y0) - np.diag(d)])
        vals = np.asarray(jax.jit(jax.vmap(loss))(jnp.asarray(pts), jnp.full(10, h0)))
        fd = (vals[:5] - vals[5:]) / (2 * d)
        hs = jnp.asarray([h0 * (1 + 1e-6), h0 * (1 - 1e-6)])
        vh = np.asarray(jax.jit(jax.vmap(loss))(jnp.stack([y0, y0]), hs))
        fd_h = (vh[0] - vh[1]) / (2e-6 * h0)
    assert h0 * np.abs(np.asarray(jac)).max() > 10                    # a stiff step: h |J| >> 1
    np.testing.assert_allclose(np.asarray(gy), np.asarray(ref[0]), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(float(gh), float(ref[1]), rtol=1e-9)
    np.testing.assert_allclose(np.asarray(fwd[0]), np.asarray(gy), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(float(fwd[1]), float(gh), rtol=1e-10)
    np.testing.assert_allclose(np.asarray(gy), fd, rtol=1e-5, atol=1e-7 * np.abs(np.asarray(gy)).max())
    np.testing.assert_allclose(float(gh), fd_h, rtol=1e-5)


def _fixed(y0, t1, n, args):
    """``n`` equal Rosenbrock steps over ``[0, t1]`` (float64) and the last step's error estimate."""
    step = jax.jit(lambda t, y, h: rosenbrock_stages(vector_field_w_control, t, y, h, args,
                                                     vector_field_w(t, y, args)))
    y, h = jnp.asarray(y0), t1 / n
    for i in range(n):
        dy, *_, e, _ = step(i * h, y, h)
        y = y + dy
    return np.asarray(y), np.asarray(e)


def test_the_step_is_second_order_and_its_estimate_third():
    """Global error ~ h^2 against DOP853 (float64, rtol = 1e-12) from the paper's start over 1 s; the local error
    estimate ~ h^3."""
    args = ClosedLoop(js.paper_plant(), js.paper_gains())
    with jax.enable_x64(True):
        y0 = np.asarray(state_to_w(jnp.asarray([1.0, 1.0, 0.5, 0.0, 0.0], jnp.float64)))
        f, jac = numpy_field(args, vector_field_w)
        ref = solve_ivp(f, (0.0, 1.0), y0, method="DOP853", rtol=1e-12, atol=1e-12).y[:, -1]
        errs = [np.abs(_fixed(y0, 1.0, n, args)[0] - ref).max() for n in (50, 100, 200)]
        est = [np.abs(_fixed(y0, h, 1, args)[1]).max() for h in (0.02, 0.01)]
    orders = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert np.all((orders > 1.8) & (orders < 2.3)), (errs, orders)
    assert 2.7 < np.log2(est[0] / est[1]) < 3.3, est


def _start(lanes=64):
    """The first ``lanes`` of 256 starts (float32) as one batch-last host state, not yet stepped (every lane active),
    with their closed loop, horizon (100 s) and step-size policy."""
    rng = np.random.default_rng(5)
    ics5, st = check_ics(np.column_stack([rng.uniform(-3, 3, (256, 2)), rng.uniform(0.05, 3, 256)])[:lanes])
    args = ClosedLoop(js.paper_plant(), js.paper_gains())
    hz = make_horizon(100.0, 0.01)
    step = js.StepSizeController(rtol=1e-6, atol=1e-6, max_steps=10 ** 6, max_step=1.0)
    s = drive_final(initial_w(ics5, st, jnp.float32), st, args, hz, step, eps=0.05, segment=30, stop_at=lanes,
                    finish=False)
    return s, args, hz, step


def _segment(counts, n=30, lanes=64):
    """`_start`'s batch whose lanes have made ``counts`` attempts, after a segment of ``n`` more with the switch to
    the implicit step at 1,000 (`jaxsleigh.integrate.engine.advance_lanes`, as the pool of stragglers steps them)."""
    s, args, hz, step = _start(lanes)
    s = s._replace(n_reject=np.asarray(counts, np.int32))
    return advance_lanes(s, args, hz, step, eps=0.05, segment=n, stiff_after=1000)


def test_a_non_finite_implicit_trial_is_rejected_and_the_lane_says_so():
    """A lane whose implicit trials are not finite (its carried slope poisoned with NaN) rejects every one, keeps a
    finite state and ends with a failure status; its neighbours step as if it were not there."""
    s, args, hz, step = _start()
    s = s._replace(n_reject=np.full(64, 1000, np.int32))
    k1 = np.array(s.k1)
    k1[:, 0] = np.nan
    bad = advance_lanes(s._replace(k1=k1), args, hz, step, eps=0.05, segment=200, stiff_after=1000)
    good = advance_lanes(s, args, hz, step, eps=0.05, segment=200, stiff_after=1000)
    assert bad.stiff[0] and bad.n_accept[0] == 0 and np.all(np.isfinite(bad.y[:, 0]))
    assert bad.status[0] in (js.Status.STEP_UNDERFLOW, js.Status.NONFINITE)
    for a, b in zip(jax.tree_util.tree_leaves(bad), jax.tree_util.tree_leaves(good)):
        np.testing.assert_array_equal(a[..., 1:], b[..., 1:])


def test_a_lane_steps_as_its_own_kind_whatever_its_neighbours():
    """Lanes past the switch take the implicit step and the others the explicit one, in one batch: every lane ends
    with the bits it has in a batch of its own kind only, and the two kinds differ."""
    past = np.arange(64) % 2 == 0
    mixed = _segment(np.where(past, 1000, 0))
    implicit = _segment(np.full(64, 1000))
    explicit = _segment(np.zeros(64))
    for a, b, c in zip(jax.tree_util.tree_leaves(mixed), jax.tree_util.tree_leaves(implicit),
                       jax.tree_util.tree_leaves(explicit)):
        np.testing.assert_array_equal(a[..., past], b[..., past])
        np.testing.assert_array_equal(a[..., ~past], c[..., ~past])
    assert not np.array_equal(implicit.y, explicit.y)
    assert np.all(mixed.status == js.Status.OK) and np.all(mixed.n_accept >= 20)    # both kinds stepped


def test_a_lane_on_the_implicit_step_has_the_same_bits_in_the_pools_batch_sizes():
    """The pool of stragglers steps its implicit lanes in batches of their own, of 64 to 256 lanes: a lane ends a
    segment with the same bits in each."""
    runs = [_segment(np.full(m, 1000), lanes=m) for m in (64, 128, 256)]
    for small in runs[:2]:
        for a, b in zip(jax.tree_util.tree_leaves(small), jax.tree_util.tree_leaves(runs[2])):
            np.testing.assert_array_equal(a, b[..., :a.shape[-1]])
    assert np.all(runs[2].stiff) and np.all(runs[2].n_accept >= 20)


def test_the_flight_rule_reads_the_mean_step():
    """A lane flies once it has made the switch's attempts at a mean step below a tenth of the base step, stays
    flying, and never with the switch off (0) or once it has stopped. Tighter tolerances than the dtype's default
    lower the bar as they shrink an accurate explicit step, by (tol / default)^(1/5)."""
    from jaxsleigh.integrate.engine import FLIGHT_STEP, flight_step, flying
    from jaxsleigh.integrate.stepper import controls

    def ctl(tol=None):
        return controls(js.StepSizeController(rtol=tol, atol=tol), np.float32, dt=0.01, eps=0.05, max_steps=10**6,
                        xp=np)

    s = _segment(np.zeros(64), n=1)._replace(stiff=np.zeros(64, bool))
    n = 1000 + np.asarray(s.n_accept) + np.asarray(s.n_reject)
    slow = np.arange(64) % 3 == 0
    t = np.where(slow, 0.5, 2.0) * FLIGHT_STEP * 0.01 * n
    s = s._replace(n_reject=np.full(64, 1000, np.int32) + s.n_reject, t=t.astype(np.float32))
    np.testing.assert_array_equal(flying(s, ctl(), 1000), slow)
    np.testing.assert_array_equal(flying(s, ctl(1e-4), 1000), slow)       # looser than the default: the same bar
    np.testing.assert_array_equal(flying(s, ctl(1e-6 * 0.25 ** 5), 1000), np.zeros(64, bool))   # bar / 4 < t / n
    np.testing.assert_array_equal(flying(s, ctl(), 2000), np.zeros(64, bool))
    np.testing.assert_array_equal(flying(s, ctl(), 0), np.zeros(64, bool))
    stopped = s._replace(status=np.where(slow, js.Status.NOT_SETTLING, s.status).astype(np.int32))
    assert not flying(stopped, ctl(), 1000).any()
    was = s._replace(stiff=np.arange(64) == 1)
    np.testing.assert_array_equal(flying(was, ctl(), 1000), slow | (np.arange(64) == 1))
    assert flight_step(1e-8, 1e-8, np.float64) == FLIGHT_STEP == flight_step(1e-6, 1e-6, np.float32)
    assert flight_step(1e-10, 1e-8, np.float64) == pytest.approx(FLIGHT_STEP * 0.01 ** 0.2)


def test_saved_trajectories_switch_a_flight_and_leave_every_other_lane_alone():
    """`drive_saving` (simulate's driver) stops a lane that has not flown at the checks (here 300 attempts, then
    every 100) and lets it go on from there: the lanes that do not fly end with the bits of a run without the checks,
    a near-singular one flies and ends differently (its saved rows finite)."""
    from jaxsleigh.integrate.engine import drive_saving

    ics5, st = check_ics([[1.0, 1.0, 0.5], [-2.0, 1.5, 2.0], FLIER, [0.5, -2.5, -1.0]])
    args = ClosedLoop(js.paper_plant(), js.paper_gains())
    hz = make_horizon(2.0, 0.01, save_every=10)
    step = js.StepSizeController(rtol=1e-6, atol=1e-6, max_steps=10 ** 6, max_step=1.0)
    y0w = initial_w(ics5, st, jnp.float32)
    kw = dict(eps=0.05, block=8)
    plain, ys0 = drive_saving(y0w, st, args, hz, step, **kw)
    switched, ys1 = drive_saving(y0w, st, args, hz, step, stiff_after=300, segment=100, **kw)
    assert switched.stiff.tolist() == [False, False, True, False]
    calm = ~switched.stiff
    for a, b in zip(jax.tree_util.tree_leaves(plain), jax.tree_util.tree_leaves(switched)):
        np.testing.assert_array_equal(a[..., calm], b[..., calm])
    np.testing.assert_array_equal(ys0[calm], ys1[calm])
    assert switched.status.tolist() == [js.Status.OK] * 4 and np.all(np.isfinite(ys1[2]))
    assert switched.n_accept[2] + switched.n_reject[2] < plain.n_accept[2] + plain.n_reject[2]


@pytest.mark.slow
def test_a_flier_reaches_the_horizon_where_float64_radau_ends():
    """A flight that explicit steps alone do not carry through the budget of 2e5 attempts crosses 100 s after the
    switch in a fraction of it, and ends within 1e-4 (relative) of SciPy's Radau (float64, rtol = atol = 1e-8,
    w chart)."""
    r = js.run_ensemble([FLIER], t_final=100.0, run=js.RunOptions(progress=False, audit=False))
    sim = js.simulate([FLIER], t_final=100.0, run=js.RunOptions(progress=False))   # the saved trajectory too
    for x in (r, sim):
        assert x.status.tolist() == [js.Status.OK] and x.t_reached[0] == 100.0
        assert STIFF_AFTER < x.n_steps[0] + x.n_rejected[0] < 100_000
    assert np.all(np.isfinite(sim.q))
    args = ClosedLoop(js.paper_plant(), js.paper_gains())
    with jax.enable_x64(True):
        f, jac = numpy_field(args, vector_field_w)
        y0 = np.asarray(state_to_w(jnp.asarray(np.r_[FLIER, 0.0, 0.0], jnp.float64)))
        sol = solve_ivp(f, (0.0, 100.0), y0, method="Radau", rtol=1e-8, atol=1e-8, jac=jac)
        q_ref = np.asarray(state_from_w(jnp.asarray(sol.y[:, -1])))[:3]
    assert sol.status == 0 and np.linalg.norm(q_ref) > 1e3          # a flight: it does not settle
    for x in (r, sim):
        np.testing.assert_allclose(x.q_final[0], q_ref, rtol=1e-4, atol=1e-4 * np.linalg.norm(q_ref))


@pytest.mark.slow
def test_a_slow_lane_that_does_not_fly_stays_explicit(monkeypatch):
    """The tuned gains' settled phase takes this held-out start ~85,000 explicit steps (at ~2e-3 s, a fifth of the
    base step): it is slow, not stiff, and must not switch (on the second-order step it used up its budget). It ends
    with the bits of a run without the switch."""
    import jaxsleigh.studies.ensemble as ens

    start = [[-1.85146552, -1.91892328, 1.25548718]]
    kw = dict(gains=js.load_gains("tuned"), t_final=100.0, run=js.RunOptions(progress=False, audit=False))
    r = js.run_ensemble(start, **kw)
    assert r.status.tolist() == [js.Status.OK] and r.n_steps[0] + r.n_rejected[0] > 2 * STIFF_AFTER
    monkeypatch.setattr(ens, "STIFF_AFTER", 0)
    plain = js.run_ensemble(start, **kw)
    for f in ("q_final", "p_final", "T_eps", "n_steps", "u_energy"):
        np.testing.assert_array_equal(getattr(r, f), getattr(plain, f), err_msg=f)


def test_the_budget_exhausted_description_names_the_flight_rules_attempts():
    """`jaxsleigh.status` sits below the engine and writes the flight rule's count as text: the two change together."""
    from jaxsleigh.status import DESCRIPTIONS

    assert f"after {STIFF_AFTER:,} attempts" in DESCRIPTIONS[js.Status.BUDGET_EXHAUSTED]


def test_a_tight_tolerance_is_not_taken_for_a_stiff_flight():
    """A `tuned` lane whose theta keeps shrinking after it settles (to ~2e-3 by 100 s) takes small, accurate explicit
    steps at rtol = atol = 1e-10 in float64: 4.8e-2 base steps on average, under the default bar of a tenth. With the
    bar fixed it moved to the implicit step near t = 40 s and used up 10^6 attempts by t = 58 s; with the bar scaled
    to the tolerance it stays explicit and reaches the horizon (the accuracy audit's reference of this row)."""
    r = js.run_ensemble([[2.4191735301044286, -0.6299369384391906, 0.6509511783387154]], gains="tuned",
                        t_final=100.0, x64=True, run=js.RunOptions(progress=False, audit=False),
                        stepsize=js.StepSizeController(rtol=1e-10, atol=1e-10, max_steps=1_000_994))
    assert r.status[0] == js.Status.OK and r.n_steps[0] < 300_000
    assert r.T_eps[0] == pytest.approx(10.4118, abs=1e-3)
    assert r.settings["flight_step"] == pytest.approx(0.1 * 0.01 ** 0.2)
