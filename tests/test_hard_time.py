"""Tuning quantiles of the hard settling time under energy budgets (jaxsleigh.tuning.hard_time)."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxsleigh.model.params import paper_gains
from jaxsleigh.model.shaped_law import shaped_from_gains, shaped_gains
from jaxsleigh.tuning.hard_time import HardTimeConfig, hard_time_problem, tune_by_cma, tune_by_gradient
from jaxsleigh.tuning.starts import UniformStarts

LAW = shaped_gains(L=[0.5, 0.5, 0.5], B=[2.0, 2.0, 2.0], C=[0.5, 0.5, 0.5], k=0.1, D_near=[4.0, 8.0],
                   D_far=[2.0, 4.0], s=1.0)
CFG = HardTimeConfig(t_final=60.0, time_quantiles=(0.5,), time_weights=(1.0,), energy_quantiles=(0.5, 0.9),
                     energy_margin=1.0, max_steps=20_000)


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
        x0 = jnp.asarray(problem.x0)
        d = jnp.asarray(np.random.default_rng(0).normal(size=x0.shape))
        x0 = x0 + 0.05 * d                                  # off the reference: the budgets' penalty is active
        (_, aux), g = problem.value_and_grad(x0)
        h = 1e-4
        fd = (problem.value(x0 + h * d)[0] - problem.value(x0 - h * d)[0]) / (2 * h)
        assert abs(float(jnp.dot(g, d))) > 1e-3
        assert abs(float(jnp.dot(g, d)) - float(fd)) <= 2e-3 * abs(float(fd)) + 1e-6


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


def test_a_law_outside_the_w_chart_or_with_a_zero_leaf_is_refused():
    starts = UniformStarts()(np.random.default_rng(5), 4)
    with pytest.raises(ValueError, match="B = 0 has no logarithm"):
        hard_time_problem(shaped_from_gains(paper_gains()), starts, cfg=CFG)
    with pytest.raises(ValueError, match="w-chart law"):
        hard_time_problem(lambda q, v: -v, starts, cfg=CFG)
