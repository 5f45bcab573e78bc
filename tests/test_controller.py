"""The controller as a piece: a user-written law ``u = law(q, v)`` runs through the engine in the
physical chart, checked against scipy's Radau integrating the same closed loop written independently."""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import jaxsleigh as js
from jaxsleigh.model.charts import PhysicalChart, WChart, chart_for


from laws import PD  # noqa: E402


def _scipy_closed_loop(law_np, m=2.0, J=1.0, l=1.0, eps=0.1, scale=1.0):
    """The sleigh (eq. 1-2) with the paper's smoothed Coulomb damping D = c diag(1/sqrt(eps + p_i^2)),
    written with NumPy only."""
    Jt = J + m * l * l

    def f(t, s):
        x, y, th, p1, p2 = s
        v, w = p1 / m, p2 / Jt
        u = law_np(np.array([x, y, th]), np.array([v, w]))
        a = m * l / Jt * p2
        d1, d2 = scale * v / np.sqrt(eps + p1 * p1), scale * w / np.sqrt(eps + p2 * p2)
        return [np.cos(th) * v, np.sin(th) * v, w, a * w - d1 + u[0], -a * v - d2 + u[1]]

    return f


def _pd_np(kp, kd):
    def law(q, v):
        along = q[0] * np.cos(q[2]) + q[1] * np.sin(q[2])
        return np.array([-kp * along - kd * v[0], -kp * q[2] - kd * v[1]])
    return law


def test_damping_model_is_the_one_scipy_integrates():
    d = js.paper_plant().damping
    p, v = (0.3, -0.6), (0.15, -0.2)
    f = np.asarray(d.force(jnp.zeros(3), tuple(map(jnp.asarray, p)), tuple(map(jnp.asarray, v))))
    np.testing.assert_allclose(f, [v[0] / np.sqrt(0.1 + p[0] ** 2), v[1] / np.sqrt(0.1 + p[1] ** 2)], rtol=1e-6)


@pytest.mark.parametrize("method", ["simulate", "run_ensemble"])
def test_user_law_matches_scipy_radau(method):
    ics = np.array([[-3.0, -2.0, np.pi / 8, 0.0, 0.0], [1.0, 1.0, 0.0, 0.5, -0.3], [2.0, -1.0, -1.0, 0.0, 0.0]])
    law = PD(kp=2.0, kd=1.5)
    if method == "simulate":
        out = js.simulate(ics, controller=law, t_final=10.0, x64=True, saveat=js.SaveAt(every=1000))
        final = np.concatenate([out.q[:, -1], out.p[:, -1]], axis=1)
        status = out.status
    else:
        out = js.run_ensemble(ics, controller=law, t_final=10.0, x64=True)
        final = np.concatenate([out.q_final, out.p_final], axis=1)
        status = out.status
    assert np.all(status == 0)
    f = _scipy_closed_loop(_pd_np(2.0, 1.5))
    for i, y0 in enumerate(ics):
        ref = solve_ivp(f, (0, 10.0), y0, method="Radau", rtol=1e-10, atol=1e-12).y[:, -1]
        np.testing.assert_allclose(final[i], ref, rtol=0, atol=2e-5)


def test_user_law_effort_matches_quadrature_of_scipy_solution():
    ics = np.array([[1.0, -1.0, 0.4, 0.0, 0.0]])
    law = PD(kp=1.0, kd=2.0)
    res = js.run_ensemble(ics, controller=law, t_final=5.0, x64=True)
    f = _scipy_closed_loop(_pd_np(1.0, 2.0))
    lawn = _pd_np(1.0, 2.0)

    def aug(t, s):
        u = lawn(s[:3], np.array([s[3] / 2.0, s[4] / 3.0]))
        return list(f(t, s[:5])) + [u @ u]

    ref = solve_ivp(aug, (0, 5.0), list(ics[0]) + [0.0], method="Radau", rtol=1e-11, atol=1e-12).y[-1, -1]
    np.testing.assert_allclose(res.u_energy[0], ref, rtol=1e-6)
    assert np.isnan(res.Hd0[0]) and np.isnan(res.Hd_final[0])     # H_d belongs to the paper's law


def test_theta_zero_is_not_singular_for_a_user_law():
    sol = js.simulate(np.array([1.0, 0.5, 0.0]), controller=PD(), t_final=2.0, x64=True)
    assert sol.status[0] == 0 and np.all(np.isfinite(sol.q))
    with pytest.raises(ValueError, match="singular set"):
        js.simulate(np.array([1.0, 0.5, 0.0]), t_final=2.0)      # the paper's law: theta0 = 0 refused


def test_a_plain_function_is_a_controller():
    def law(q, v):
        return -1.0 * jnp.stack([v[0] + q[0], v[1] + q[2]])

    sol = js.simulate(np.array([1.0, 0.5, 0.3]), controller=law, t_final=2.0, x64=True)
    assert sol.status[0] == 0
    assert "FunctionLaw" in sol.settings["controller"]["type"]


def test_law_parameters_are_traced_and_do_not_recompile():
    from jaxsleigh.integrate import engine

    ics = np.array([[1.0, 0.5, 0.3]])
    js.run_ensemble(ics, controller=PD(1.0, 2.0), t_final=1.0)
    size = engine._segment_batch._cache_size()
    r = js.run_ensemble(ics, controller=PD(3.0, 2.5), t_final=1.0)
    assert engine._segment_batch._cache_size() == size
    assert r.status[0] == 0


def test_gradient_of_a_law_through_the_stepper_matches_finite_differences():
    """The stepper is a pure JAX function of the law's parameters: d(final x)/d(kp) by jax.grad equals
    central finite differences (float64, fixed-step RK4)."""
    from jaxsleigh.model.closed_loop import ClosedLoop
    from jaxsleigh.integrate.stepper import controls
    from jaxsleigh.integrate.stepper import WhileActive, init_state, run

    with jax.enable_x64(True):
        ctl = controls(js.StepSizeController(rtol=1e-8, atol=1e-8, max_step=0.01), jnp.float64, dt=0.01, eps=0.05,
                       max_steps=10**4)
        y0 = jnp.array([1.0, -0.5, 0.4, 0.0, 0.0])

        def final_x(kp):
            args = ClosedLoop(js.paper_plant(), PD(kp, 1.5))
            s = init_state(y0, jnp.int32(0), args, ctl)
            return run(s, 2.0, args, ctl, WhileActive(), adaptive=False).y[0]

        # one program (forward mode: the value and its derivative) for the derivative and the differences, not an
        # eager program per operation of the stepper
        jvp = jax.jit(lambda kp: jax.jvp(final_x, (kp,), (jnp.ones_like(kp),)))
        g = float(jvp(2.0)[1])
        h = 1e-5
        fd = (float(jvp(2.0 + h)[0]) - float(jvp(2.0 - h)[0])) / (2 * h)
        assert jvp._cache_size() == 1
        np.testing.assert_allclose(g, fd, rtol=1e-6)


def test_charts_are_chosen_by_the_controller():
    assert isinstance(chart_for(js.paper_gains()), WChart)
    assert isinstance(chart_for(PD()), PhysicalChart)


@pytest.mark.parametrize("bad, match", [
    (42, "feedback law"),
    (lambda q, v: jnp.zeros(3), "shape \\(2,\\)"),
    (lambda q, v: jnp.array([jnp.nan, 0.0]), "non-finite"),
    (lambda q, v: q["x"], "failed when called"),
    (lambda q, v: jnp.stack([-v[0], -v[1]]) * (1.0 + 0.5j), "real u .*complex128"),
])
def test_bad_controllers_are_refused_with_a_message(bad, match):
    with pytest.raises(ValueError, match=match):
        js.simulate(np.array([1.0, 0.5, 0.3]), controller=bad, t_final=1.0)


def test_a_law_returning_complex_numbers_is_refused_by_solve_before_the_run():
    """Its imaginary part was dropped without a word; `solve` (which takes a law as it is, possibly traced) refuses
    it where the law is traced, naming the dtype."""
    with pytest.raises(ValueError, match="real u .*complex"):
        js.solve(_Complex(), jnp.asarray([1.0, 0.5, 0.3]), t_final=1.0)


class _Complex(NamedTuple):
    k: float = 1.0

    def __call__(self, q, v):
        return jnp.stack([-self.k * v[0], -self.k * v[1]]) * (1.0 + 0.5j)


class _NaNFarOut(NamedTuple):
    """Finite at the validation point, NaN beyond |(x, y)| = 2."""

    k: float = 1.0

    def __call__(self, q, v):
        return jnp.where(q[0] ** 2 + q[1] ** 2 > 4.0, jnp.nan, 1.0) * jnp.stack([-self.k * v[0], -self.k * v[1]])


def test_gains_and_controller_together_are_refused():
    with pytest.raises(ValueError, match="not both"):
        js.run_ensemble(np.array([[1.0, 0.5, 0.3]]), gains="paper", controller=PD(), t_final=1.0)


def test_paper_gains_given_as_controller_are_the_paper_law():
    ics = np.array([[1.0, 0.5, 0.3]])
    a = js.run_ensemble(ics, controller=js.paper_gains(), t_final=5.0)
    b = js.run_ensemble(ics, t_final=5.0)
    np.testing.assert_array_equal(a.q_final, b.q_final)


def test_per_trajectory_law_equals_separate_runs_and_records_its_values():
    from jaxsleigh.model.controller import PerTrajectory

    ics = np.array([[1.0, 0.5, 0.3], [-1.0, 1.0, -0.6], [2.0, 0.0, 1.0]])
    kps = np.array([0.5, 2.0, 4.0])
    lanes = js.run_ensemble(ics, controller=PerTrajectory(PD(kp=kps, kd=np.full(3, 1.5))), t_final=4.0, x64=True)
    for i, kp in enumerate(kps):
        one = js.run_ensemble(ics[i:i + 1], controller=PD(kp, 1.5), t_final=4.0, x64=True)
        np.testing.assert_allclose(lanes.q_final[i], one.q_final[0], rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(lanes.u_energy[i], one.u_energy[0], rtol=1e-12)
    np.testing.assert_array_equal(lanes.params["kp"], kps)


def test_per_trajectory_plant_under_a_user_law():
    ics = np.array([[1.0, 0.5, 0.3], [1.0, 0.5, 0.3]])
    plant = js.PlantParams(np.array([1.0, 4.0]), 1.0, 1.0, js.CoulombDamping())
    res = js.run_ensemble(ics, plant=plant, controller=PD(), t_final=4.0, x64=True)
    for i, m in enumerate((1.0, 4.0)):
        one = js.run_ensemble(ics[:1], plant=js.plant_params(m, 1.0, 1.0), controller=PD(), t_final=4.0, x64=True)
        np.testing.assert_allclose(res.q_final[i], one.q_final[0], rtol=1e-12, atol=1e-14)
    assert not np.allclose(res.q_final[0], res.q_final[1])


def test_user_law_through_run_basin():
    res = js.run_basin(js.grid_starts(x=(-1, 1, 3), y=(-1, 1, 2), theta=0.4), controller=PD(2.0, 1.5), t_final=5.0)
    assert res.status.shape == (6,) and np.all(res.status == 0)
    assert res.settings["controller"]["type"] == "PD"


def test_a_user_law_is_tuned_by_gradient_and_its_loss_gradient_matches_finite_differences(caplog):
    """... and a second `tune_law` with other starts, another starting gain and other tolerances (the same horizon,
    which sets the static step budget) compiles nothing."""
    import logging

    from jaxsleigh.tuning import LossConfig, tune_law
    from jaxsleigh.tuning.law import law_loss

    starts = np.array([[1.0, 0.5, 0.4], [-1.0, 1.0, -0.5], [0.5, -1.0, 1.0]])
    cfg = LossConfig(t_final=6.0, stepsize=js.StepSizeController(rtol=1e-8, atol=1e-8, max_step=0.1))
    with jax.enable_x64(True):
        y0 = jnp.asarray(np.concatenate([starts, np.zeros((3, 2))], axis=1))
        f = lambda kp: law_loss(PD(kp, 1.5), y0, js.paper_plant(), cfg, n_attempts=2000, adaptive=False)[0]  # noqa
        vg = jax.jit(jax.value_and_grad(f))     # one program for the gradient and the differences (not eager ops)
        _, g = vg(1.0)
        fd = (float(vg(1.0 + 1e-5)[0]) - float(vg(1.0 - 1e-5)[0])) / 2e-5
        assert vg._cache_size() == 1
    np.testing.assert_allclose(g, fd, rtol=1e-5)
    res = tune_law(PD(1.0, 1.5), starts, tune=["kp"], loss=LossConfig(t_final=6.0), steps=6, lr=0.2, x64=True)
    assert res.history["loss"].shape == (6,) and np.all(res.history["valid"])
    assert res.loss < res.history["loss"][0]                      # it improved on the starting law
    assert isinstance(res.law, PD) and res.law.kd == 1.5 and res.law.kp != 1.0
    other = np.array([[0.8, -0.5, 0.6], [1.0, 1.0, -0.4], [-0.5, -1.0, 0.9]])
    looser = LossConfig(t_final=6.0, stepsize=js.StepSizeController(rtol=2e-5, atol=2e-5, max_step=0.1))
    with jax.log_compiles(True), caplog.at_level(logging.DEBUG):
        caplog.clear()
        again = tune_law(PD(0.8, 1.5), other, tune=["kp"], loss=looser, steps=2, lr=0.2, x64=True)
    assert [r.getMessage() for r in caplog.records if "ompil" in r.getMessage()] == []
    assert np.all(again.history["valid"]) and again.law.kp != 0.8


def test_user_law_through_a_sweep_of_its_parameter_and_the_plant():
    starts = np.array([[1.0, 0.5, 0.3], [-1.0, 1.0, -0.6]])
    sw = js.sweep(starts, ["kp=0.5:2:2", "m=1:4:2"], controller=PD(1.0, 1.5), t_final=4.0, x64=True)
    assert sw.values.shape == (4, 2) and sw.status.shape == (4, 2) and np.all(sw.status == 0)
    for p, (kp, m) in enumerate(sw.values):
        one = js.run_ensemble(starts, plant=js.plant_params(m, 1.0, 1.0), controller=PD(kp, 1.5), t_final=4.0,
                              x64=True)
        np.testing.assert_allclose(sw.T_eps[p], one.T_eps, rtol=1e-12)
    assert sw.settings["controller"]["type"] == "PD" and sw.settings["gains"] is None
    with pytest.raises(ValueError, match="gain of the paper's law"):
        js.sweep(starts, ["k=0.1:0.2:2"], controller=PD(), t_final=1.0)
    with pytest.raises(ValueError, match="unknown parameter 'kq'"):
        js.sweep(starts, ["kq=0.1:0.2:2"], controller=PD(), t_final=1.0)


def test_a_user_law_that_blows_up_ends_with_a_status_never_a_silent_nan():
    def law(q, v):                       # finite at the validation point, infinite beyond x = 5
        return jnp.where(q[0] > 5.0, jnp.inf, 1.0) * jnp.stack([-q[0] - v[0], -q[2] - v[1]])

    res = js.run_ensemble(np.array([[6.0, 0.0, 0.3], [1.0, 0.5, 0.3]]), controller=law, t_final=2.0)
    assert res.status[1] == js.Status.OK and np.all(np.isfinite(res.q_final[1]))
    assert res.status[0] == js.Status.NONFINITE                # not STEP_UNDERFLOW: the field is not finite there
    assert np.all(np.isnan(res.q_final[0])) and np.isnan(res.T_eps[0]) and np.isnan(res.u_energy[0])
    fixed = js.run_ensemble(np.array([[6.0, 0.0, 0.3]]), controller=law, t_final=2.0,
                            stepsize=js.StepSizeController(method="rk4"))
    assert fixed.status[0] == js.Status.NONFINITE and np.all(np.isnan(fixed.q_final[0]))


def test_results_of_a_user_law_are_saved_and_loaded(tmp_path):
    from jaxsleigh.files.npz import FORMAT_VERSION, write_npz
    from jaxsleigh.plots.paper_figures import load_solution

    res = js.run_basin(js.grid_starts(x=(-1, 1, 2), y=(-1, 1, 2), theta=0.4), controller=PD(), t_final=2.0)
    back = js.load_basin(js.save_basin(tmp_path / "b.npz", res))
    np.testing.assert_array_equal(back.T_eps, res.T_eps)
    assert back.settings["controller"]["type"] == "PD"
    sol = js.simulate(np.array([1.0, 0.5, 0.3]), controller=PD(), t_final=1.0)
    path = write_npz(tmp_path / "s.npz", sol, ics=np.array([[1.0, 0.5, 0.3]]))
    np.testing.assert_array_equal(load_solution(path).q, sol.q)
    with np.load(path) as z:
        assert int(z["format_version"]) == FORMAT_VERSION


def test_a_law_that_is_nan_far_out_ends_nonfinite_with_nan_outputs_in_every_front():
    """The adaptive step shrank to its floor on NaN trials and the run was reported ``STEP_UNDERFLOW`` with the
    start as its final state and 0 as its energy; a NaN field is ``NONFINITE``, and a failed row's outputs are NaN
    in `solve`, `simulate`, `run_ensemble` and `run_basin` alike."""
    law = _NaNFarOut()
    out = js.solve(law, jnp.asarray([3.0, 0.0, 0.3]), t_final=1.0)
    assert int(out.status) == js.Status.NONFINITE
    assert np.all(np.isnan(np.asarray(out.q_final))) and np.all(np.isnan(np.asarray(out.p_final)))
    assert all(np.all(np.isnan(np.asarray(v))) for v in out.summaries.values())
    ics = np.array([[3.0, 0.0, 0.3], [0.1, 0.0, 0.3]])
    for res in (js.run_ensemble(ics, controller=law, t_final=1.0, run=js.RunOptions(progress=False)),
                js.simulate(ics, controller=law, t_final=1.0),
                js.run_basin(ics, controller=law, t_final=1.0, run=js.RunOptions(progress=False))):
        assert res.status.tolist() == [js.Status.NONFINITE, js.Status.OK]
        for name in ("q_final", "T_eps", "u_energy", "u_abs_int", "u_norm_peak", "max_excursion"):
            value = np.asarray(getattr(res, name), np.float64)
            assert np.all(np.isnan(value[0])), name
            assert not np.any(np.isnan(value[1])), name
