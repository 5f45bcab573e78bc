"""Tuning quantiles of the hard settling time under energy budgets (jaxsleigh.tuning.hard_time)."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxsleigh import StepSizeController
from jaxsleigh.model.params import paper_gains
from jaxsleigh.model.shaped_law import shaped_from_gains, shaped_gains
from jaxsleigh.tuning.hard_time import HardTimeConfig, hard_time_problem, tune_by_cma, tune_by_gradient
from jaxsleigh.tuning.starts import UniformStarts

LAW = shaped_gains(L=[0.5, 0.5, 0.5], B=[2.0, 2.0, 2.0], C=[0.5, 0.5, 0.5], k=0.1, D_near=[4.0, 8.0],
                   D_far=[2.0, 4.0], s=1.0)
CFG = HardTimeConfig(t_final=60.0, time_quantiles=(0.5,), time_weights=(1.0,), energy_quantiles=(0.5, 0.9),
                     energy_margin=1.0, stepsize=StepSizeController(max_steps=20_000))


@pytest.fixture(scope="module")
def problem():
    starts = UniformStarts()(np.random.default_rng(5), 17)
    with jax.enable_x64(True):
        yield hard_time_problem(LAW, starts, reference=LAW, cfg=CFG, dtype=jnp.float64)


def test_budgets_are_the_references_quantiles_and_the_reference_is_feasible(problem):
    with jax.enable_x64(True):
        f, aux = problem.value(jnp.asarray(problem.x0))
    np.testing.assert_allclose(problem.budgets, np.asarray(aux["energy_quantiles"]), rtol=1e-9)
    assert bool(aux["feasible"]) and int(aux["n_bad"]) == 0
    np.testing.assert_allclose(float(f), float(aux["T_quantiles"][0]) / CFG.t_final, rtol=1e-12)  # no penalty


def test_objective_gradient_matches_finite_differences(problem):
    """Reverse mode through the checkpointed adaptive RK4 (implicit-function time, quantiles, budgets) against
    central differences of the objective, along a random direction in log-parameters."""
    with jax.enable_x64(True):
        x0 = np.asarray(problem.x0, np.float64)           # host arithmetic in NumPy: no eager program per operation
        d = np.random.default_rng(0).normal(size=x0.shape)
        x0 = x0 + 0.05 * d                                  # off the reference: the budgets' penalty is active
        (_, aux), g = problem.value_and_grad(jnp.asarray(x0))    # device arrays, as the other tests pass (NumPy
        h = 1e-4                                                    # arguments would retrace the programs)
        fd = (float(problem.value(jnp.asarray(x0 + h * d))[0]) - float(problem.value(jnp.asarray(x0 - h * d))[0])) / (2 * h)
        gd = float(np.dot(np.asarray(g), d))
        assert abs(gd) > 1e-3
        assert abs(gd - fd) <= 2e-3 * abs(fd) + 1e-6


def test_tuners_keep_the_best_feasible_and_count_the_budget(problem):
    with jax.enable_x64(True):
        grad = tune_by_gradient(problem, steps=3, lr=0.05)
        cma = tune_by_cma(problem, evaluations=4, population=4, seed=0)
    for run, n in ((grad, 3), (cma, 4)):
        assert len(run.history) == n
        assert [r["trajectory_seconds"] for r in run.history] == [(i + 1) * 17 * CFG.t_final for i in range(n)]
        feas = [r["value"] for r in run.history if r["feasible"]]
        if feas:
            assert run.x is not None and run.value == min(feas)
        else:                                                # nothing feasible: nothing to keep, and it says so
            assert run.x is None and run.value == float("inf")
    assert grad.history[0]["feasible"]                       # starts at the reference: within its own budgets
    assert all(r["gradient_finite"] for r in grad.history)


def test_a_zero_leaf_a_law_without_gains_or_a_sampled_law_is_refused():
    from jaxsleigh.controllers.actuators import sampled
    from jaxsleigh.controllers.aicardi import AicardiLaw

    starts = UniformStarts()(np.random.default_rng(5), 4)
    with pytest.raises(ValueError, match="B must be > 0 to be tuned"):
        hard_time_problem(shaped_from_gains(paper_gains()), starts, cfg=CFG)
    with pytest.raises(ValueError, match="not a number"):
        hard_time_problem(lambda q, v: -v, starts, cfg=CFG)
    with pytest.raises(ValueError, match="sampled law"):
        hard_time_problem(sampled(AicardiLaw(), period=0.1), starts, cfg=CFG)


def test_the_paper_family_moves_in_its_seven_admissible_coordinates():
    from jaxsleigh.tuning.law import law_coordinates

    g = paper_gains()
    with jax.enable_x64(True):
        c = law_coordinates(g, dtype=jnp.float64)
        back = c.law_of(c.x0)
        assert c.x0.shape == (7,) and len(c.names) == 7
        for a, b in zip(back, g):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-15)
        # every coordinate vector is admissible: D_hat stays symmetric positive definite, L and k positive
        x = c.x0 + np.random.default_rng(1).normal(scale=3.0, size=7)
        g2 = c.law_of(x)
        assert np.all(np.asarray(g2.L) > 0) and float(g2.k) > 0
        assert np.all(np.linalg.eigvalsh(np.asarray(g2.D_hat)) > 0)
    with pytest.raises(ValueError, match="tuned as a whole"):
        law_coordinates(g, tune=["L"])


def test_a_literature_law_is_tuned_on_the_same_objective():
    """Aicardi's law (physical chart) on the hard-time objective: the objective's median T is the engine's own
    T_eps on the same starts (the heading measured modulo 2 pi, as the law's chart says), the plant model the law
    carries is not a coordinate, and the gradient is finite over the full 100 s horizon (it was NaN before the
    goal threshold of `polar_coordinates` and the effort observer's sqrt(0) were made safe:
    docs/evidence/shaped-energy.md)."""
    import jaxsleigh as js
    from jaxsleigh.controllers.aicardi import AicardiLaw

    law = AicardiLaw()
    starts = UniformStarts()(np.random.default_rng(5), 9)
    cfg = CFG._replace(t_final=100.0)
    prob = hard_time_problem(law, starts, cfg=cfg)
    assert prob.x0.shape == (4,)                             # gamma, k, h, K; not model.m, model.J, ...
    np.testing.assert_allclose(prob.x0, np.log([law.gamma, law.k, law.h, law.K]), rtol=1e-12)
    (f, aux), g = prob.value_and_grad(jnp.asarray(prob.x0, jnp.float32))
    r = js.run_ensemble(starts, controller=law, t_final=100.0, eps=CFG.eps, run=js.RunOptions(progress=False))
    T = np.where(np.isfinite(r.T_eps), r.T_eps, 100.0)
    assert np.all(r.status == 0)
    np.testing.assert_allclose(float(aux["T_quantiles"][0]), np.median(T), rtol=1e-3)
    assert np.all(np.isfinite(np.asarray(g))) and float(jnp.max(jnp.abs(g))) > 0


def test_a_non_finite_gradient_stops_the_gradient_tuner_and_says_so():
    """Where the objective's gradient is NaN (as Aicardi's lifted law's was near the goal before its goal threshold
    was raised, docs/evidence/shaped-energy.md), the row says ``gradient_finite: False`` and the run stops there: no step is
    taken with it and nothing non-finite becomes the best point."""
    from jaxsleigh.tuning.hard_time import HardTimeProblem

    calls = []

    def value_and_grad(x, lam=None):
        calls.append(np.asarray(x))
        aux = {"T_quantiles": jnp.array([10.0]), "energy_quantiles": jnp.array([1.0]), "settled": jnp.array(1.0),
               "n_bad": jnp.array(0), "feasible": jnp.array(True), "mean_steps": jnp.array(100.0)}
        return (jnp.asarray(0.1), aux), jnp.array([jnp.nan, 1.0])

    prob = HardTimeProblem(np.zeros(2), None, None, value_and_grad, np.ones(1), 0.5, 4, CFG)
    run = tune_by_gradient(prob, steps=5)
    assert len(calls) == 1 and [r["gradient_finite"] for r in run.history] == [False]
    np.testing.assert_array_equal(run.x, np.zeros(2))        # the evaluated point itself is finite and feasible


def test_a_force_that_is_exactly_zero_keeps_the_gradient_finite():
    """A law whose force is exactly 0 (here a PD law at rest on its goal; Aicardi's law once at its goal) has
    ||u|| = sqrt(0) in the effort observer: its derivative there is taken as 0, so the reverse-mode gradient through
    the step loop is finite (0 * inf was NaN) and equals 0, the true value."""
    from jaxsleigh.model.params import paper_plant
    from jaxsleigh.tuning.event_time import settling

    from laws import PD

    y0 = jnp.zeros((3, 5), jnp.float32).at[2, 0].set(1e-3)       # two starts at the goal, at rest; one not
    plant = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float32), paper_plant())

    def energy(kp):
        r = settling(PD(kp=kp, kd=2.0), y0, plant, t_final=5.0, stepsize=StepSizeController(max_steps=2000),
                     reverse=True, segment=100)
        return jnp.sum(r.u_energy[:2])

    g = jax.jit(jax.grad(energy))(jnp.asarray(1.0, jnp.float32))     # one program, not an eager op each
    assert np.isfinite(float(g)) and float(g) == 0.0


def test_multipliers_enter_as_the_augmented_lagrangian(problem):
    """value(x, lam) - value(x, 0) is the sum of psi(c, lam) - psi(c, 0) over the constraints the evaluation reports,
    psi(c, lam) = lam c + mu c^2 / 2 where lam + mu c >= 0, else -lam^2 / (2 mu), mu = 2 x penalty."""
    mu = 2.0 * CFG.penalty

    def psi(c, lam):
        return np.where(lam + mu * c >= 0, lam * c + 0.5 * mu * c * c, -lam * lam / (2 * mu))

    with jax.enable_x64(True):
        x = jnp.asarray(np.asarray(problem.x0, np.float64) + 0.05 * np.random.default_rng(1).normal(size=problem.x0.shape))
        f0, aux = problem.value(x)
        lam = np.array([0.3, 0.0, 2.0])                     # two energy quantiles, then the settled floor
        f1, aux1 = problem.value(x, lam)
    c = np.asarray(aux["constraints"], np.float64)
    assert c.shape == (3,) and np.any(c != 0)
    np.testing.assert_allclose(np.asarray(aux1["constraints"]), c, rtol=0, atol=0)
    np.testing.assert_allclose(float(f1) - float(f0), np.sum(psi(c, lam) - psi(c, 0 * lam)), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(float(f0), float(aux["time_term"]) + np.sum(psi(c, 0 * lam)), rtol=1e-12)


def test_the_method_of_multipliers_lands_on_the_budget_where_the_penalty_stops_outside():
    """On a model problem with the hard-time problem's interface (time exp(-x), one budget c = x <= 0), the penalty
    alone converges to the balance x* > 0 (outside the budget, never feasible); multipliers updated every 5
    evaluations by lam <- max(0, lam + mu min(c, 0.1)) bring x to the budget's edge."""
    from jaxsleigh.tuning.hard_time import HardTimeProblem

    cfg = CFG._replace(energy_quantiles=(0.5,), penalty=1.0)
    mu = 2.0 * cfg.penalty

    def objective(x, lam=np.zeros(2)):
        c = jnp.stack([x[0], jnp.asarray(-1.0)])
        lam = jnp.asarray(lam, c.dtype)
        psi = jnp.where(lam + mu * c >= 0, lam * c + 0.5 * mu * c * c, -lam * lam / (2 * mu))
        t = jnp.exp(-x[0])
        return t + jnp.sum(psi), {"T_quantiles": t[None], "energy_quantiles": jnp.exp(x), "settled": jnp.asarray(1.0),
                                  "n_bad": jnp.asarray(0), "feasible": c[0] <= 1e-6, "mean_steps": jnp.asarray(1.0),
                                  "time_term": t, "constraints": c}

    vg = jax.jit(jax.value_and_grad(objective, has_aux=True))
    prob = HardTimeProblem(np.array([1.0]), None, objective, vg, np.ones(1), 0.0, 1, cfg)
    penalty = tune_by_gradient(prob, steps=300, lr=0.05)
    mult = tune_by_gradient(prob, steps=300, lr=0.05, multiplier_every=5)
    x_pen, x_mult = penalty.history[-1]["x"][0], mult.history[-1]["x"][0]
    assert 0.2 < x_pen < 0.5 and not any(r["feasible"] for r in penalty.history)   # x* = W(1/2) ~ 0.35
    assert abs(x_mult) < 0.02 < x_pen / 10 and mult.x is not None
    lams = [r["lam"][0] for r in mult.history]
    assert lams[:5] == [0.0] * 5 and lams[5] == pytest.approx(mu * min(mult.history[4]["constraints"][0], 0.1))
    assert lams[-1] == pytest.approx(1.0, abs=0.05)           # the budget's true multiplier: exp(-0) = 1
