"""The energy-optimal frontier (`jaxsleigh.optimum`): against SciPy's SLSQP on an independent integration,
against a feedback law's own trajectory, its gradients against finite differences, its inverse and its
refusals."""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxsleigh import RunOptions, paper_plant
from jaxsleigh.studies.optimum import (OptimumOptions, OptimumStatus, energy_for_time, initial_guesses, optimum,
                                       rollout, time_for_energy)

EPS = 0.05


def _scipy_rhs(plant):
    m, J, l = plant.m, plant.J, plant.l
    Jt = J + m * l * l
    c, e = plant.damping.scale, plant.damping.eps

    def f(t, s, u):
        x, y, th, p1, p2 = s
        v, w = p1 / m, p2 / Jt
        a = m * l / Jt * p2
        return [v * math.cos(th), v * math.sin(th), w,
                a * w - c * v / math.sqrt(e + p1 * p1) + u[0],
                -a * v - c * w / math.sqrt(e + p2 * p2) + u[1]]
    return f


def _scipy_final(start, u, T, plant, known=None):
    """The state at T under a piecewise-constant input, by SciPy's DOP853 (rtol 1e-9), interval by interval.

    ``known``: a dict of the states already reached, keyed by the bytes of the inputs before them; the integration
    starts from the longest known prefix of ``u`` (each interval is integrated afresh from its start state, so the
    state is the same to the bit) and adds what it computes. A finite-difference Jacobian perturbs one input at a time:
    its points share the prefix before that input, and each integrates 4.5 intervals of 8 on average, not 8."""
    from scipy.integrate import solve_ivp

    f, h, u = _scipy_rhs(plant), T / len(u), np.asarray(u)
    known = {} if known is None else known
    k = len(u)
    while k > 0 and u[:k].tobytes() not in known:
        k -= 1
    s = known[u[:k].tobytes()] if k else np.asarray(start, float)
    for k in range(k, len(u)):
        s = solve_ivp(f, (k * h, (k + 1) * h), s, args=(u[k],), method="DOP853", rtol=1e-9, atol=1e-11).y[:, -1]
        known[u[:k + 1].tobytes()] = s
    return s


def test_frontier_inverse_is_monotone_and_says_where_it_is_outside():
    horizons = np.array([5.0, 10.0, 20.0, 40.0])
    frontier = np.array([[8.0, 4.0, 2.0, 1.0], [9.0, 3.0, 3.0, np.nan]])
    T, where = time_for_energy(horizons, frontier, [np.sqrt(8.0 * 4.0), 3.0])
    assert where.tolist() == [0, 0]
    assert T[0] == pytest.approx(np.sqrt(50.0))          # halfway in log-log between (5, 8) and (10, 4)
    assert T[1] == pytest.approx(10.0)                    # flat stretch: its shortest horizon
    T, where = time_for_energy(horizons, frontier, [100.0, 0.5])
    assert where.tolist() == [-1, 1] and np.isnan(T).all()
    E, where = energy_for_time(horizons, frontier, [np.sqrt(50.0), 50.0])
    assert where.tolist() == [0, 1]
    assert E[0] == pytest.approx(np.sqrt(32.0))
    E, where = energy_for_time(horizons, frontier, [2.0, 7.0])
    assert where[0] == -1 and np.isnan(E[0]) and where[1] == 0
    # E*(T) then T*(E) gives back T inside the solved horizons
    T2, _ = time_for_energy(horizons, frontier[:1], energy_for_time(horizons, frontier[:1], 13.0)[0])
    assert T2[0] == pytest.approx(13.0)


@pytest.mark.parametrize("kwargs, words", [
    ({"horizons": (10.0, 5.0)}, "increase strictly"),
    ({"horizons": (0.0, 5.0)}, "> 0"),
    ({"horizons": (5.0, float("nan"))}, "finite"),
    ({"eps": -1.0}, "eps"),
    ({"options": OptimumOptions(intervals=0)}, "intervals"),
    ({"options": OptimumOptions(guesses=5)}, "guesses"),
    ({"run": RunOptions(chunk_size=0)}, "chunk_size"),
    ({"run": RunOptions(segment=10)}, "optimum.. has no use for run.segment"),
])
def test_bad_input_is_a_value_error_that_says_what_to_change(kwargs, words):
    with pytest.raises(ValueError, match=words):
        optimum([[1.0, 1.0, 0.5]], **kwargs)
    with pytest.raises(ValueError, match="shape"):
        optimum(np.zeros((2, 4)))


def test_a_start_that_is_not_finite_gets_a_status_not_a_number():
    res = optimum([[np.nan, 1.0, 0.5]], horizons=(5.0,), options=OptimumOptions(intervals=4, outer=1, inner=1))
    assert res.status.tolist() == [[OptimumStatus.INVALID_INPUT]] and np.isnan(res.energy).all()


def test_gradient_through_the_simulator_matches_finite_differences():
    from jaxsleigh.integrate.open_loop import piecewise_constant_final

    plant = paper_plant()
    start = np.array([1.0, -0.5, 0.7, 0.2, -0.1])
    u = np.random.default_rng(0).normal(size=(4, 2))
    with jax.enable_x64(True):
        def cost(u):
            yT = piecewise_constant_final(jnp.asarray(start), u, 3.0, plant, substeps=5)
            return jnp.sum(yT[:3] ** 2) + jnp.sum(jnp.sin(yT[3:]))
        g = np.asarray(jax.grad(cost)(jnp.asarray(u)))
        fd = np.zeros_like(u)
        for idx in np.ndindex(*u.shape):
            d = np.zeros_like(u)
            d[idx] = 1e-6
            fd[idx] = (float(cost(jnp.asarray(u + d))) - float(cost(jnp.asarray(u - d)))) / 2e-6
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-8)


def test_initial_guess_is_the_plants_inverse_dynamics_of_a_turn_drive_turn():
    """Integrated, the guess ends near the origin at rest (the solver then only corrects it)."""
    start = np.array([1.5, -1.0, 2.0, 0.0, 0.0])
    for u in initial_guesses(start, 20.0, 200, count=2):
        end = rollout(start, u, 20.0, max_dt=0.01)
        assert np.linalg.norm(end[:3]) < 0.1 and np.linalg.norm(end[3:]) < 0.05, end


STARTS = np.array([[1.0, 1.0, math.pi / 4, 0.0, 0.0], [-1.5, 0.5, -2.0, 0.0, 0.0]])


@pytest.mark.slow
def test_scipy_slsqp_on_an_independent_integration_finds_the_same_optimum():
    """Coarse grid (8 intervals, T = 10): SciPy's SLSQP, with the dynamics by DOP853 and started from the guess
    that won, reaches the same least energy within 1 %, and the solution is feasible under that integration."""
    from scipy.optimize import minimize

    plant, N, T = paper_plant(), 8, 10.0
    opts = OptimumOptions(intervals=N)
    res = optimum(STARTS, (T,), options=opts)
    assert (res.status == OptimumStatus.CONVERGED).all(), res.status
    h = T / N
    for i, start in enumerate(STARTS):
        end = _scipy_final(start, res.u[i, 0], T, plant)
        assert np.linalg.norm(end[:3]) <= EPS * (1 + 1e-3) and np.linalg.norm(end[3:]) <= 2e-3
        x0 = initial_guesses(start, T, N, plant, count=opts.guesses)[res.guess[i, 0]].ravel()
        known = {}

        def final(x):
            return _scipy_final(start, x.reshape(N, 2), T, plant, known)

        cons = [{"type": "eq", "fun": lambda x: final(x)[3:]},
                {"type": "ineq", "fun": lambda x: EPS ** 2 - final(x)[:3] @ final(x)[:3]}]
        sp = minimize(lambda x: h * x @ x, x0, jac=lambda x: 2 * h * x, constraints=cons, method="SLSQP",
                      options={"maxiter": 300, "ftol": 1e-12})
        assert sp.success, sp.message
        E_sp = h * sp.x @ sp.x
        assert res.energy[i, 0] == pytest.approx(E_sp, rel=0.01), (res.energy[i, 0], E_sp)


@pytest.mark.slow
def test_never_above_a_feedback_law_that_ends_at_rest_in_the_ball():
    """The paper's law from the same starts, float64, 100 s: where it ends at rest in the ball, its trajectory is
    a feasible point of the problem at T = 100, so E*(100) (24 intervals) must not exceed its energy."""
    from jaxsleigh import run_ensemble

    T = 100.0
    law = run_ensemble(STARTS[:1, :3], t_final=T, eps=EPS, x64=True, run=RunOptions(progress=False))
    at_rest = (np.linalg.norm(law.q_final, axis=1) <= EPS) & (np.linalg.norm(law.p_final, axis=1) <= 1e-3)
    assert at_rest.all(), (law.q_final, law.p_final)
    res = optimum(STARTS[:1], (T,), options=OptimumOptions(intervals=8, max_dt=0.25))
    assert (res.status <= OptimumStatus.NOT_STATIONARY).all(), res.status
    for i, start in enumerate(STARTS[:1]):     # feasible under a fine independent check too
        end = rollout(start, res.u[i, 0], T, max_dt=0.01)
        assert np.linalg.norm(end[:3]) <= EPS * 1.01 and np.linalg.norm(end[3:]) <= 2e-3
    assert np.all(res.energy[:, 0] <= np.asarray(law.u_energy)), (res.energy[:, 0], law.u_energy)


@pytest.mark.slow
def test_command_line_small_run_resumable_output_and_bad_input(tmp_path, capsys):
    from jaxsleigh.cli import main

    out = tmp_path / "opt.npz"
    cmd = ["optimum", "--samples", "2", "--seed", "3", "--horizons", "10", "--intervals", "8", "--out", str(out)]
    assert main(cmd) == 0, capsys.readouterr().err
    assert "converged" in capsys.readouterr().out
    with np.load(out) as z:
        assert z["energy"].shape == (2, 1) and np.all(z["status"] <= OptimumStatus.NOT_STATIONARY)
        assert np.isfinite(z["energy"]).all() and str(z["kind"]) == "optimum"
    # the chunks of an unfinished run are refused without --resume, and continued with it
    (tmp_path / "opt.npz.chunks").mkdir()
    (tmp_path / "opt.npz.chunks" / "chunk_000000.npz").write_bytes(b"")
    assert main(cmd) == 2 and "--resume" in capsys.readouterr().err
    assert main(cmd + ["--resume"]) == 0
    capsys.readouterr()
    for bad, words in ((["--horizons", "5,2"], "increase strictly"), (["--intervals", "0"], "--intervals"),
                       (["--eps", "nan"], "--eps")):
        assert main(cmd[:3] + bad + ["--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert words in err and "Traceback" not in err


def test_a_saved_optimum_reads_back_and_a_wrong_file_is_refused_by_name(tmp_path):
    import jaxsleigh

    res = optimum(np.array([[1.0, 1.0, 0.5]]), horizons=(10.0,),
                  options=OptimumOptions(intervals=4, outer=2, inner=10, guesses=1))
    path = jaxsleigh.save_optimum(tmp_path / "sub" / "opt", res)
    assert path.name == "opt.npz" and path.read_bytes() == jaxsleigh.save_optimum(tmp_path / "again", res).read_bytes()
    back = jaxsleigh.load_optimum(path)
    np.testing.assert_array_equal(back.energy, res.energy)
    np.testing.assert_array_equal(back.u, res.u)
    assert back.settings == res.settings and back.eps == res.eps
    basin = jaxsleigh.save_basin(tmp_path / "b.npz", jaxsleigh.run_basin(np.array([[1.0, 1.0, 0.5]]), t_final=1.0))
    with pytest.raises(ValueError, match="is a basin result.*load_basin"):
        jaxsleigh.load_optimum(basin)
    with pytest.raises(ValueError, match="is a bound on the optimum.*read it with jaxsleigh.load_optimum"):
        jaxsleigh.load_basin(path)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="cannot read .*junk.npz"):
        jaxsleigh.load_optimum(tmp_path / "junk.npz")
