"""Actuator models: saturation pieces (laws wrapping laws) and the sampled-data loop (zero-order hold, delay,
noise), the latter checked against scipy integrating the same sampled loop written independently."""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import jaxsleigh as js
from jaxsleigh.controllers.actuators import (NormSaturation, Sampler, Saturation, check_sampler, sampler,
                                             saturate)
from jaxsleigh.controllers.paper import PaperLaw
from jaxsleigh.integrate.sampled import solve_sampled
from jaxsleigh.model.controller import PerTrajectory, apply_law
from jaxsleigh.status import Status

from laws import PD  # noqa: E402

STARTS = np.array([[1.0, 1.0, 0.5, 0.0, 0.0],
                   [-3.0, -2.0, np.pi / 8, 0.0, 0.0],
                   [2.0, -1.0, -1.0, 0.8, -0.5]])     # one with momentum


class TimeLaw(NamedTuple):
    """A time-varying law (u depends on t), to check that t is forwarded."""

    a: float = 1.0
    time_varying = True

    def __call__(self, q, v, t):
        return jnp.stack([self.a * jnp.sin(t) + q[0], self.a * jnp.cos(t) - v[1]])


def _points(rng, n=64, scale=5.0):
    q = rng.uniform(-scale, scale, size=(n, 3))
    v = rng.uniform(-scale, scale, size=(n, 2))
    return jnp.asarray(q), jnp.asarray(v)


# ---------------------------------------------------------------------------------------------- saturation


def test_saturation_bounds_and_equals_law_where_inactive(rng, x64):
    law = PD(kp=3.0, kd=2.0)
    q, v = _points(rng)
    raw = np.asarray(jax.vmap(law)(q, v))
    for u_max in (4.0, (6.0, 2.5)):
        sat = saturate(law, u_max)
        assert isinstance(sat, Saturation)
        u = np.asarray(jax.vmap(sat)(q, v))
        bound = np.broadcast_to(np.asarray(u_max), (2,))
        assert np.all(np.abs(u) <= bound)
        inactive = np.abs(raw) < bound
        assert inactive.any() and (~inactive).any()          # both regimes are exercised
        np.testing.assert_array_equal(u[inactive], raw[inactive])
        np.testing.assert_array_equal(u[~inactive], np.sign(raw[~inactive]) * np.broadcast_to(bound, raw.shape)[~inactive])


def test_norm_saturation_bounds_keeps_direction(rng, x64):
    law = PD(kp=3.0, kd=2.0)
    q, v = _points(rng)
    raw = np.asarray(jax.vmap(law)(q, v))
    sat = saturate(law, 5.0, norm=True)
    assert isinstance(sat, NormSaturation)
    u = np.asarray(jax.vmap(sat)(q, v))
    n_raw, n = np.linalg.norm(raw, axis=1), np.linalg.norm(u, axis=1)
    assert np.all(n <= 5.0 * (1 + 1e-12))
    inside = n_raw < 5.0
    assert inside.any() and (~inside).any()
    np.testing.assert_array_equal(u[inside], raw[inside])
    np.testing.assert_allclose(n[~inside], 5.0, rtol=1e-12)
    # same direction: u = c raw with c > 0
    np.testing.assert_allclose(u[~inside] / n[~inside, None], raw[~inside] / n_raw[~inside, None], rtol=1e-12)


def test_saturation_jit_vmap_grad(rng, x64):
    law = PD(kp=3.0, kd=2.0)
    q, v = _points(rng, n=8)
    for sat in (Saturation(law, 4.0), NormSaturation(law, 4.0), Saturation(NormSaturation(PD(5.0, 1.0), 10.0), (8.0, 4.0))):
        direct = np.asarray(sat(q[0], v[0]))
        jitted = np.asarray(jax.jit(jax.vmap(lambda c, a, b: c(a, b), in_axes=(None, 0, 0)))(sat, q, v))
        np.testing.assert_allclose(jitted[0], direct, rtol=1e-12, atol=1e-12)
        jac = jax.jit(jax.vmap(jax.jacfwd(lambda qq, vv: sat(qq, vv))))(q, v)
        assert np.all(np.isfinite(np.asarray(jac)))

    # derivative with respect to u_max: sign(u_i) where clipped, 0 where not
    qi, vi = jnp.array([3.0, -1.0, 0.4]), jnp.array([0.2, 0.1])
    raw = np.asarray(law(qi, vi))
    g = np.asarray(jax.jacfwd(lambda m: Saturation(law, m)(qi, vi))(jnp.asarray(1.0)))
    np.testing.assert_allclose(g, np.where(np.abs(raw) > 1.0, np.sign(raw), 0.0))
    g = np.asarray(jax.jacfwd(lambda m: NormSaturation(law, m)(qi, vi))(jnp.asarray(1.0)))
    np.testing.assert_allclose(g, raw / np.linalg.norm(raw), rtol=1e-12)
    # inside the bounds the state derivative is the law's
    big = Saturation(law, 1e6)
    np.testing.assert_allclose(np.asarray(jax.jacfwd(lambda qq: big(qq, vi))(qi)),
                               np.asarray(jax.jacfwd(lambda qq: law(qq, vi))(qi)))


def test_norm_saturation_safe_at_zero(x64):
    law = PD(kp=1.0, kd=2.0)
    q0, v0 = jnp.zeros(3), jnp.zeros(2)
    sat = NormSaturation(law, 1.0)
    np.testing.assert_array_equal(np.asarray(sat(q0, v0)), [0.0, 0.0])
    for arg in (0, 1):
        jg = np.asarray(jax.jit(jax.jacrev(lambda a, b: sat(a, b), argnums=arg))(q0, v0))
        jl = np.asarray(jax.jit(jax.jacrev(lambda a, b: law(a, b), argnums=arg))(q0, v0))
        assert np.all(np.isfinite(jg))
        np.testing.assert_allclose(jg, jl)


def test_time_varying_is_forwarded(x64):
    q, v = jnp.array([0.3, 0.2, 0.1]), jnp.array([0.5, -0.4])
    for sat in (Saturation(TimeLaw(), 100.0), NormSaturation(TimeLaw(), 100.0)):
        assert js.controller.is_time_varying(sat)
        for t in (0.0, 1.3):
            u = np.array(apply_law(sat, q, v, t))
            np.testing.assert_allclose(u, np.asarray(TimeLaw()(q, v, t)), rtol=1e-12)
    assert not js.controller.is_time_varying(Saturation(PaperLaw(), 1.0))
    assert not js.controller.is_time_varying(NormSaturation(PD(), 1.0))
    # a plain function is wrapped, stays a valid pytree
    sat = saturate(lambda q, v: jnp.stack([q[0], v[1]]) * 10.0, 1.0)
    np.testing.assert_allclose(np.asarray(jax.jit(lambda c: c(q, v))(sat)), [1.0, -1.0])


def test_per_trajectory_bounds(rng, x64):
    n = 5
    u_max = np.array([0.5, 1.0, 2.0, 3.0, 50.0])
    law = PerTrajectory(Saturation(PD(kp=np.full(n, 3.0), kd=np.full(n, 2.0)), u_max))
    q, v = _points(rng, n=n)
    u = np.stack(apply_law(law, q.T, v.T))          # (2, N)
    raw = np.asarray(jax.vmap(PD(3.0, 2.0))(q, v)).T
    np.testing.assert_allclose(u, np.clip(raw, -u_max, u_max), rtol=1e-12)


@pytest.mark.parametrize("bad", [0.0, -1.0, np.inf, np.nan, (1.0, -2.0), (1.0, np.nan), "x", (1.0, 2.0, 3.0)])
def test_bad_u_max_raises(bad):
    with pytest.raises(ValueError, match="u_max"):
        saturate(PD(), bad)


def test_bad_u_max_norm_raises():
    with pytest.raises(ValueError, match="u_max"):
        saturate(PD(), (1.0, 2.0), norm=True)
    with pytest.raises(ValueError, match="u_max"):
        saturate(PD(), 0.0, norm=True)


@pytest.mark.parametrize("kw, word", [({"period": 0.0}, "period"), ({"period": -0.1}, "period"),
                                      ({"period": np.inf}, "period"), ({"period": 0.1, "delay": 1.5}, "delay"),
                                      ({"period": 0.1, "delay": -1}, "delay"), ({"period": 0.1, "noise": -0.1}, "noise"),
                                      ({"period": 0.1, "noise": np.nan}, "noise"), ({"period": 0.1, "seed": 1.5}, "seed")])
def test_bad_sampler_raises(kw, word):
    with pytest.raises(ValueError, match=word):
        sampler(**kw)
    with pytest.raises(ValueError, match=word):
        solve_sampled(PaperLaw(), None, STARTS, t_final=1.0, sampler=Sampler(**kw))


def test_sampler_checks_and_solve_options():
    assert check_sampler(Sampler(0.1, 2.0, 0, 3)) == Sampler(0.1, 2, 0.0, 3)
    with pytest.raises(ValueError, match="whole number of sampling periods"):
        solve_sampled(PaperLaw(), None, STARTS, t_final=1.05, sampler=Sampler(0.1))
    with pytest.raises(ValueError, match="ics"):
        solve_sampled(PaperLaw(), None, np.ones((2, 4)), t_final=1.0, sampler=Sampler(0.1))
    with pytest.raises(ValueError, match="substeps"):
        solve_sampled(PaperLaw(), None, STARTS, t_final=1.0, sampler=Sampler(0.1), substeps=0)


# ------------------------------------------------------------------------------ saturated continuous loop


def test_saturated_law_through_simulate_and_ensemble():
    law = Saturation(PaperLaw(), 5.0)
    ics = STARTS[:2, :3]
    sol = js.simulate(ics, controller=law, t_final=20.0)
    assert np.all(sol.status == Status.OK)
    u = np.asarray(sol.u)
    assert np.all(np.isfinite(u))
    assert np.all(np.abs(u) <= 5.0 * (1 + 1e-6))
    assert np.abs(u).max() > 4.99               # the bound is reached (the paper's law asks for more)
    ens = js.run_ensemble(ics, controller=law, t_final=20.0)
    assert np.all(ens.status == Status.OK)
    assert np.all(np.asarray(ens.u_peak) <= 5.0 * (1 + 1e-6))
    np.testing.assert_allclose(ens.q_final, sol.q[:, -1], rtol=1e-3, atol=1e-3)


# ---------------------------------------------------------------------------------- sampled loop vs scipy


def _plant_np(y, u, m=2.0, J=1.0, l=1.0, c_eps=0.1):
    """Sleigh eq. 1-2 with the paper's smoothed Coulomb damping, for a stack of rows y (N, 5), u (N, 2)."""
    th, p1, p2 = y[:, 2], y[:, 3], y[:, 4]
    I = J + m * l * l
    v1, v2 = p1 / m, p2 / I
    d1, d2 = v1 / np.sqrt(c_eps + p1 ** 2), v2 / np.sqrt(c_eps + p2 ** 2)
    return np.column_stack([np.cos(th) * v1, np.sin(th) * v1, v2,
                            m * l * v2 * v2 - d1 + u[:, 0], -m * l * v1 * v2 - d2 + u[:, 1]])


def _scipy_sampled(law, ics, Ts, K):
    """The sampled loop sample by sample: u from the law at the sampled state, held by DOP853."""
    law_j = jax.jit(jax.vmap(lambda q, v: law(q, v)))
    y = np.array(ics, dtype=np.float64)
    n = len(y)
    ys, us = [y.copy()], []
    for k in range(K):
        v = y[:, 3:] / np.array([2.0, 3.0])
        u = np.asarray(law_j(jnp.asarray(y[:, :3]), jnp.asarray(v)), np.float64)
        sol = solve_ivp(lambda t, z: _plant_np(z.reshape(n, 5), u).ravel(), (k * Ts, (k + 1) * Ts), y.ravel(),
                        method="DOP853", rtol=1e-11, atol=1e-12)
        assert sol.success
        y = sol.y[:, -1].reshape(n, 5)
        ys.append(y.copy())
        us.append(u)
    return np.stack(ys, axis=1), np.stack(us, axis=1)


# the adaptive steps resolve the fast transient of the smoothed Coulomb damping when |u| is large (the second start
# asks for |u| ~ 1700, p crosses the damping's scale sqrt(0.1) in ~ 2e-4 s) at the float64 defaults
@pytest.mark.parametrize("Ts, t_final", [(0.1, 5.0), (0.01, 1.0)])
def test_sampled_matches_scipy(x64, Ts, t_final):
    K = int(round(t_final / Ts))
    run = solve_sampled(PaperLaw(), None, STARTS, t_final=t_final, sampler=Sampler(Ts), dtype=jnp.float64)
    assert run.q.dtype == jnp.float64
    assert np.all(np.asarray(run.status) == Status.OK)
    ys, us = _scipy_sampled(PaperLaw(), STARTS, Ts, K)
    np.testing.assert_allclose(np.asarray(run.t), Ts * np.arange(K + 1), rtol=1e-12)
    q, p = np.asarray(run.q), np.asarray(run.p)
    assert q.shape == (3, K + 1, 3) and p.shape == (3, K + 1, 2) and run.u.shape == (3, K, 2)
    scale = np.maximum(1.0, np.abs(ys).max(axis=(1, 2)))[:, None, None]      # per row: ~1e-6 relative
    assert np.all(np.abs(q - ys[:, :, :3]) <= 1e-6 * scale), np.abs(q - ys[:, :, :3]).max(axis=(1, 2))
    assert np.all(np.abs(p - ys[:, :, 3:]) <= 1e-6 * scale), np.abs(p - ys[:, :, 3:]).max(axis=(1, 2))
    uscale = np.maximum(1.0, np.abs(us).max(axis=(1, 2)))[:, None, None]
    assert np.all(np.abs(np.asarray(run.u) - us) <= 1e-6 * uscale)
    np.testing.assert_array_equal(np.asarray(run.q_final), q[:, -1])
    np.testing.assert_array_equal(np.asarray(run.p_final), p[:, -1])
    energy = (us ** 2).sum(axis=(1, 2)) * Ts
    np.testing.assert_allclose(np.asarray(run.u_energy), energy, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(run.u_norm_peak), np.linalg.norm(us, axis=2).max(axis=1), rtol=1e-6)
    assert np.all(np.asarray(run.min_abs_theta) <= np.abs(ys[:, :, 2]).min(axis=1) + 1e-9)
    assert np.all(np.asarray(run.min_abs_theta) > 0)


def test_substeps_is_the_accuracy_knob_of_fixed_steps_only(x64):
    """With fixed RK4 steps (``method="rk4"``) fewer substeps, larger error against scipy, falling like h^4 (a start
    with moderate u, where h resolves the plant's time scales); the adaptive steps' error does not depend on them
    (they only set the first step tried)."""
    Ts, K = 0.1, 20
    ys, _ = _scipy_sampled(PaperLaw(), STARTS[2:], Ts, K)

    def error(substeps, **kw):
        run = solve_sampled(PaperLaw(), None, STARTS[2:], t_final=Ts * K, sampler=Sampler(Ts), substeps=substeps,
                            dtype=jnp.float64, **kw)
        return np.abs(np.asarray(run.q) - ys[:, :, :3]).max()

    fixed = [error(ss, stepsize=js.StepSizeController(method="rk4")) for ss in (1, 2)]
    assert fixed[0] > 1e-8
    assert 10.0 < fixed[0] / fixed[1] < 25.0, fixed
    adaptive = [error(ss) for ss in (1, 2)]
    assert max(adaptive) < 1e-8 and max(adaptive) < 0.1 * fixed[1], (adaptive, fixed)


# ------------------------------------------------------------------------------- sampled vs continuous


def test_small_period_approaches_continuous_and_large_one_does_not():
    ics = np.array([[1.0, 1.0, 0.5], [2.0, -1.0, -1.0], [-1.0, 0.5, 2.0]])
    cont = js.run_ensemble(ics, controller=PaperLaw(), t_final=20.0)
    assert np.all(cont.status == Status.OK)
    fine = solve_sampled(PaperLaw(), None, ics, t_final=20.0, sampler=Sampler(0.005), substeps=2)
    assert np.all(np.asarray(fine.status) == Status.OK)
    err_fine = np.abs(np.asarray(fine.q_final) - cont.q_final).max()
    assert err_fine < 0.05, err_fine
    np.testing.assert_allclose(np.asarray(fine.u_energy), cont.u_energy, rtol=0.1)
    coarse = solve_sampled(PaperLaw(), None, ics, t_final=20.0, sampler=Sampler(0.5), substeps=20)
    st = np.asarray(coarse.status)
    err_coarse = np.nan_to_num(np.abs(np.asarray(coarse.q_final) - cont.q_final), nan=np.inf).max()
    assert err_coarse > 0.5 and err_coarse > 20 * err_fine, (err_coarse, err_fine, st)


# ------------------------------------------------------------------------------------------ delay, noise


def _law_on_samples(law, run, Ts):
    """The law evaluated on the recorded samples: (N, K+1, 2)."""
    v = np.asarray(run.p) / np.array([2.0, 3.0])
    f = jax.vmap(jax.vmap(lambda q, v: law(q, v)))
    return np.asarray(f(jnp.asarray(run.q), jnp.asarray(v, run.q.dtype)))


def test_delay_shifts_controls_by_whole_samples():
    law, Ts, tf = PaperLaw(), 0.05, 3.0
    r0 = solve_sampled(law, None, STARTS, t_final=tf, sampler=Sampler(Ts), substeps=5)
    r1 = solve_sampled(law, None, STARTS, t_final=tf, sampler=Sampler(Ts, delay=1), substeps=5)
    for r in (r0, r1):
        assert np.all(np.asarray(r.status) == Status.OK)
    u0, u1 = np.asarray(r0.u), np.asarray(r1.u)
    # no delay: the control of sample k is the law at the measurement of sample k
    np.testing.assert_allclose(u0, _law_on_samples(law, r0, Ts)[:, :-1], rtol=1e-4, atol=1e-4)
    # delay 1: u[0] = 0, u[k] = law at the measurement of sample k - 1
    np.testing.assert_array_equal(u1[:, 0], 0.0)
    np.testing.assert_allclose(u1[:, 1:], _law_on_samples(law, r1, Ts)[:, :-2], rtol=1e-4, atol=1e-4)
    # the first interval runs open-loop (u = 0): the undelayed run's first control is absent from it
    assert np.all(np.abs(u0[:, 0]) > 1e-3)
    assert np.abs(np.asarray(r1.q_final) - np.asarray(r0.q_final)).max() > 1e-3


def test_noise_is_seeded_and_zero_noise_is_noiseless():
    law, Ts, tf = PaperLaw(), 0.05, 3.0

    def go(**kw):
        return solve_sampled(law, None, STARTS, t_final=tf, sampler=Sampler(Ts, **kw), substeps=5)

    clean = go()
    a, b, c = go(noise=0.01, seed=1), go(noise=0.01, seed=1), go(noise=0.01, seed=2)
    zero = go(noise=0.0, seed=7)
    for f in ("q", "p", "u", "u_energy", "T_eps"):
        np.testing.assert_array_equal(np.asarray(getattr(a, f)), np.asarray(getattr(b, f)))
        np.testing.assert_array_equal(np.asarray(getattr(zero, f)), np.asarray(getattr(clean, f)))
    assert np.asarray(a.u).tobytes() == np.asarray(b.u).tobytes()
    assert not np.array_equal(np.asarray(a.u), np.asarray(c.u))
    assert not np.array_equal(np.asarray(a.u), np.asarray(clean.u))
    # u is the law at the noisy measurement, not at the state: it differs from the law on the samples
    assert np.abs(np.asarray(a.u)[:, 0] - _law_on_samples(law, a, Ts)[:, 0]).max() > 1e-4


# --------------------------------------------------------------------------------------- failures, grad


def test_theta_zero_start_is_flagged_not_silent():
    ics = np.array([[1.0, 1.0, 0.5, 0.0, 0.0], [1.0, 1.0, 0.0, 0.0, 0.0], [np.nan, 0.0, 0.3, 0.0, 0.0]])
    run = solve_sampled(PaperLaw(), None, ics, t_final=1.0, sampler=Sampler(0.1), substeps=4)
    st = np.asarray(run.status)
    assert st[0] == Status.OK
    assert st[1] == Status.NONFINITE
    assert st[2] == Status.INVALID_INPUT
    for f in ("q_final", "p_final", "T_eps", "u_energy", "u_norm_peak", "min_abs_theta"):
        x = np.asarray(getattr(run, f))
        assert not np.any(np.isnan(x[0])), f          # T_eps may be inf (not settled in 1 s), never NaN
        assert np.all(np.isnan(x[1:])), f
    q = np.asarray(run.q)
    np.testing.assert_array_equal(q[1, 0], [1.0, 1.0, 0.0])       # the start itself was valid
    assert np.all(np.isnan(q[1, 1:])) and np.all(np.isnan(q[2]))
    assert np.all(np.isnan(np.asarray(run.u)[1:]))
    assert np.all(np.isfinite(q[0])) and np.all(np.isfinite(np.asarray(run.u)[0]))
    # the good row is not touched by the bad ones
    alone = solve_sampled(PaperLaw(), None, np.repeat(ics[:1], 3, axis=0), t_final=1.0, sampler=Sampler(0.1),
                          substeps=4)
    np.testing.assert_array_equal(np.asarray(alone.q)[0], q[0])


def test_grad_through_sampled_loop_and_saturation(x64):
    """d(control energy)/d(u_max) through the whole sampled loop, against central differences."""
    ics = STARTS[:2]

    def energy(u_max):
        run = solve_sampled(Saturation(PaperLaw(), u_max), None, ics, t_final=0.5, sampler=Sampler(0.1),
                            substeps=2, dtype=jnp.float64)
        return jnp.sum(run.u_energy)

    # forward mode (cheaper to compile here); reverse mode goes through the same program
    vg = jax.jit(lambda m: jax.jvp(energy, (m,), (jnp.ones_like(m),)))
    e0, g = vg(jnp.asarray(3.0))
    h = 1e-5
    fd = (float(vg(jnp.asarray(3.0 + h))[0]) - float(vg(jnp.asarray(3.0 - h))[0])) / (2 * h)
    assert np.isfinite(float(g)) and float(g) > 0
    np.testing.assert_allclose(float(g), fd, rtol=1e-5)


def test_time_varying_law_is_evaluated_at_the_sample_instants():
    Ts, K = 0.1, 10
    law = Saturation(TimeLaw(a=2.0), 1.5)          # time-varying through the wrapper
    run = solve_sampled(law, None, STARTS[:1, :3], t_final=Ts * K, sampler=Sampler(Ts), substeps=2)
    assert np.asarray(run.status)[0] == Status.OK
    tk = Ts * np.arange(K)
    q, v = np.asarray(run.q)[0, :-1], np.asarray(run.p)[0, :-1] / np.array([2.0, 3.0])
    expect = np.clip(np.column_stack([2.0 * np.sin(tk) + q[:, 0], 2.0 * np.cos(tk) - v[:, 1]]), -1.5, 1.5)
    np.testing.assert_allclose(np.asarray(run.u)[0], expect, rtol=1e-5, atol=1e-5)
    assert np.abs(np.asarray(run.u)[0, :, 0] - np.clip(q[:, 0], -1.5, 1.5)).max() > 0.1    # t was used


def test_near_theta_zero_the_sampled_loop_reports_every_row():
    """Starts just off the singular set under the sampled paper law: a row is OK with finite results, or it carries
    a status that says why not; never OK with a NaN or inf in what it reports."""
    ics = np.array([[1.0, 1.0, th, 0.0, 0.0] for th in (1e-2, 1e-4, 1e-6, -1e-6)] + [[3.0, -2.0, 1e-5, 1.0, -1.0]])
    run = solve_sampled(PaperLaw(), None, ics, t_final=2.0, sampler=Sampler(0.1), substeps=4)
    st = np.asarray(run.status)
    for f in ("q_final", "p_final", "u_energy", "u_norm_peak", "min_abs_theta"):
        x = np.asarray(getattr(run, f)).reshape(len(ics), -1)
        assert np.all(np.isfinite(x[st == Status.OK])), f
        assert np.all(np.isnan(x[st != Status.OK])), f
    assert np.all(~np.isnan(np.asarray(run.T_eps)[st == Status.OK]))
