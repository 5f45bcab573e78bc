"""Effort-budgeted tuning and the time-effort front: the backtracking wrapper, the control energy
accumulated in the objective's scan, the augmented Lagrangian's gradient, the budget honoured, the
front (both methods, JSON, command line) and the shipped `balanced` preset."""
from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import jaxsleigh as js
from jaxsleigh import tuning as tu
from jaxsleigh.cli import main as cli_main

# shapes and static settings shared with tests/test_tuning.py (one compilation per session)
SMALL = dict(batch=24, n_attempts=2000)
SMALL_LOSS = tu.LossConfig(t_final=15.0)


# ---------------------------------------------------------------------------------------------
# backtracking as an optax wrapper
# ---------------------------------------------------------------------------------------------

def test_backtracking_redoes_the_last_valid_step_shorter_and_vmaps():
    opt = tu.backtracking(optax.sgd(1.0))
    p0 = {"a": jnp.array([1.0, 2.0])}
    g0 = {"a": jnp.array([1.0, -1.0])}
    st = opt.init(p0)
    u, st = opt.update(g0, st, p0, valid=True)
    p1 = optax.apply_updates(p0, u)
    np.testing.assert_allclose(p1["a"], [0.0, 3.0])
    # p1 is invalid: its gradient is ignored, the step from p0 is redone half as long
    u, st = opt.update({"a": jnp.array([1e3, 1e3])}, st, p1, valid=False)
    p2 = optax.apply_updates(p1, u)
    np.testing.assert_allclose(p2["a"], [0.5, 2.5])
    assert float(st.scale) == 0.5
    # valid again: a step from p2 with its own gradient, the scale grows back
    u, st = opt.update(g0, st, p2, valid=True)
    np.testing.assert_allclose(optax.apply_updates(p2, u)["a"], [0.5 - 0.625, 2.5 + 0.625])
    # vmapped: one lane valid, one not
    P = {"a": jnp.stack([p1["a"], p1["a"]])}
    S = jax.vmap(opt.init)({"a": jnp.stack([p0["a"], p0["a"]])})
    G = {"a": jnp.stack([g0["a"], g0["a"]])}
    U, S = jax.vmap(lambda g, s, p, v: opt.update(g, s, p, valid=v))(G, S, P, jnp.array([True, False]))
    out = optax.apply_updates(P, U)["a"]
    np.testing.assert_allclose(out[0], [-1.0, 4.0])    # stepped from p1
    np.testing.assert_allclose(out[1], [1.0, 2.0])     # lane 1 goes back to its anchor p0 (no gradient there yet)


# ---------------------------------------------------------------------------------------------
# the control energy inside the objective
# ---------------------------------------------------------------------------------------------

_ICS = np.array([[1.0, -0.5, 0.8], [-0.6, 0.4, -1.2], [0.3, 0.2, 0.5]])


def _setup(gains, **loss):
    data = tu.make_training_set(_ICS, guard=np.zeros((0, 3)))
    cfg = tu.traced_loss(tu.LossConfig(**loss), jnp.zeros(()).dtype)
    theta = tu.GainParams(*(jnp.asarray(x) for x in tu.params_from_gains(gains)))
    trainable, frozen = tu.split_params(theta, None)
    return data, cfg, trainable, frozen


@pytest.mark.usefixtures("x64")
def test_objective_energy_is_the_engines_for_the_same_steps():
    """The objective's u_energy and u_norm_peak are the engine's effort observer's: on the same steps they equal what
    `solve` reports to rounding, fixed RK4 steps of dt as the engine takes them and adaptive steps from the same
    first step (the energy's own error estimate is under the step's norm in both, so the steps agree too)."""
    from jaxsleigh.integrate.stepper import WhileActive, controls, init_batch, run, starting_step
    from jaxsleigh.model.closed_loop import ClosedLoop
    data, cfg, tr, fr = _setup("paper", t_final=2.0, stop_fraction=1e-6)
    gains = tu.gains_from_params(fr)
    # the objective's lanes by the value-and-gradient programs that tests/test_tuning.py compiles (same shapes and
    # static settings), not by an eager objective (a program per operation)
    (_, aux), _ = tu.make_value_and_grad(mode="reverse", n_attempts=220, adaptive=False)(tr, fr, data, cfg)
    lanes = aux["lanes"]
    assert np.all(np.asarray(lanes.t_reached) == 2.0)
    solve = jax.jit(lambda y0: js.solve(gains, y0, t_final=2.0, dt=0.01,          # one program for the 3 starts
                                        stepsize=js.StepSizeController(method="rk4")))
    rk4 = [solve(jnp.asarray(y0)) for y0 in _ICS]
    np.testing.assert_allclose(np.asarray(lanes.u_energy), [float(o.u_energy) for o in rk4], rtol=1e-12)
    np.testing.assert_allclose(np.asarray(lanes.u_norm_peak), [float(o.u_norm_peak) for o in rk4], rtol=1e-12)
    # adaptive: the objective's lanes against the engine's stepper with every default observer, same first step
    (_, aux), _ = tu.make_value_and_grad(mode="reverse", n_attempts=2000)(tr, fr, data, cfg)
    lanes = aux["lanes"]
    y0w = data.groups[0][0]
    args = ClosedLoop(js.paper_plant(), gains)
    ctl = controls(cfg.stepsize, y0w.dtype, dt=cfg.dt, eps=cfg.eps, max_steps=2000)

    @jax.jit                                  # one program, not an eager program per operation of the stepper
    def engine(y0w):
        s = starting_step(init_batch(y0w, jnp.zeros(y0w.shape[0], jnp.int32), args, ctl), ctl)
        return run(s, 2.0, args, ctl, WhileActive(), adaptive=True)

    s = engine(y0w)
    assert np.all(np.asarray(s.t) == 2.0)
    np.testing.assert_array_equal(np.asarray(lanes.n_attempts), np.asarray(s.n_accept + s.n_reject))
    np.testing.assert_allclose(np.asarray(lanes.u_energy), np.asarray(s.quad[0]), rtol=1e-12)


@pytest.mark.usefixtures("x64")
def test_objective_energy_agrees_with_the_accurate_engine():
    """int |u|^2 dt integrated in the objective's run (the engine's quadrature) = the accurate engine's effort over
    the same horizon (no lane stops: stop_fraction tiny), float64, tight tolerances."""
    data, cfg, tr, fr = _setup("paper", t_final=5.0, stop_fraction=1e-6,
                                 stepsize=js.StepSizeController(rtol=1e-8, atol=1e-8, max_step=0.1))
    (_, aux), _ = tu.make_value_and_grad(mode="reverse", n_attempts=2000)(tr, fr, data, cfg)   # the program above
    assert np.all(np.asarray(aux["lanes"].t_reached) == 5.0)
    v = tu.validate("paper", _ICS, t_final=5.0, x64=True, stepsize=js.StepSizeController(rtol=1e-9, atol=1e-9))
    # the objective's steps at 1e-8 vs the accurate engine's at 1e-9
    np.testing.assert_allclose(np.asarray(aux["lanes"].u_energy), v.u_energy, rtol=1e-3)
    assert float(aux["energy"]) == pytest.approx(np.exp(np.mean(np.log(v.u_energy))), rel=1e-3)
    np.testing.assert_allclose(np.asarray(aux["lanes"].u_norm_peak), v.u_norm_peak, rtol=5e-3)


@pytest.mark.usefixtures("x64")
def test_augmented_lagrangian_gradient_equals_central_differences():
    """Fixed RK4 steps: the loss with an active budget (lambda > 0, g > 0) is smooth in the gains and
    its AD gradient matches central differences; without a budget the loss is the soft time exactly."""
    data, cfg, tr, fr = _setup("paper", t_final=2.0)
    kw = dict(n_attempts=220, adaptive=False)
    vg = tu.make_value_and_grad(mode="reverse", **kw)       # tests/test_tuning.py's program: same shapes and settings
    (value0, aux0), _ = vg(tr, fr, data, cfg)
    assert float(value0) == float(aux0["soft"]) and np.isneginf(float(aux0["constraint"]))
    cfg = cfg._replace(energy_budget=jnp.asarray(0.5 * float(aux0["energy"])), multiplier=jnp.asarray(0.3),
                       penalty=jnp.asarray(2.0))
    (value, aux), grad = vg(tr, fr, data, cfg)
    assert float(aux["constraint"]) == pytest.approx(np.log(2.0))
    assert float(value) > float(aux["soft"]) + 0.3 * np.log(2.0)
    # central differences of the value, by the same compiled program (no jitted objective of its own)
    keys = sorted(tr)
    flat = np.concatenate([np.ravel(np.asarray(tr[k])) for k in keys])
    sizes = np.cumsum([np.size(tr[k]) for k in keys])[:-1]

    def f(v):
        tv = {k: jnp.asarray(x.reshape(np.shape(tr[k]))) for k, x in zip(keys, np.split(v, sizes))}   # as tr's
        return float(vg(tv, fr, data, cfg)[0][0])

    n = vg._cache_size()
    h = 1e-5
    fd = np.array([(f(flat + h * e) - f(flat - h * e)) / (2 * h) for e in np.eye(flat.size)])
    assert vg._cache_size() == n
    g = np.concatenate([np.ravel(np.asarray(grad[k])) for k in keys])
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-7 * np.max(np.abs(fd)))


# ---------------------------------------------------------------------------------------------
# a budgeted run honours its budget; the probe is a guard, inactive at the result
# ---------------------------------------------------------------------------------------------

def test_budgeted_tune_returns_gains_within_the_budget_with_the_probe_inactive():
    config = tu.TuneConfig(steps=8, lr=0.2, warmup=1, seed=3, verify=2, **SMALL)
    e_paper = tu.training_energy("paper", config=config, loss=SMALL_LOSS)["energy"]
    budget = 2.0 * e_paper
    res = tu.tune("paper", config=config, loss=SMALL_LOSS._replace(energy_budget=budget), tune="L,k", progress=False)
    h, i = res.history, res.best_iteration
    assert h.feasible[i] and h.energy[i] <= budget and h.constraint[i] <= 0
    assert h.soft_loss[i] < h.soft_loss[0]                       # faster than the paper's gains
    assert res.best_loss == pytest.approx(h.soft_loss[i])
    assert np.all(h.multiplier >= 0) and not h.probe_active[i]
    pr = res.settings["probe_at_result"]
    assert pr["active"] is False and pr["max_attempts_training_starts"] < pr["probe_budget"]
    assert tu.training_energy(res.gains, config=config, loss=SMALL_LOSS)["energy"] == pytest.approx(h.energy[i],
                                                                                                    rel=1e-4)


# ---------------------------------------------------------------------------------------------
# the front: both methods, its JSON, the command line
# ---------------------------------------------------------------------------------------------

# the budgeted run's shapes and static settings (SMALL: batch, step budget, probe size; SMALL_LOSS), so that the
# fronts and the command line reuse its compiled objective, gradient, probe and verification programs
TINY = tu.TuneConfig(steps=3, lr=0.2, warmup=1, seed=1, verify=1, **SMALL)
TINY_LOSS = SMALL_LOSS


@pytest.mark.parametrize("method", ["warm", "vmap"])
def test_front_points_respect_their_budgets(method, tmp_path):
    e = tu.training_energy("paper", config=TINY, loss=TINY_LOSS)["energy"]
    budgets = [0.5 * e, 3.0 * e]
    front = tu.pareto_front(budgets, method=method, config=TINY, loss=TINY_LOSS, warm_steps=2, tune_names="L,k")
    assert front.method == method and len(front.points) == 2 and front.evaluations >= 4
    for p, b in zip(front.points, budgets):
        assert p.budget == pytest.approx(b)
        if p.train["feasible"]:
            assert p.train["training_energy"] <= b * (1 + 1e-6)
        js.gains(p.gains.L, p.gains.k, p.gains.D_hat)
    held = tu.UniformStarts()(np.random.default_rng(9), 4)
    front = tu.evaluate_front(front, held, t_final=10.0)
    path = tu.save_front(front, tmp_path / "front.json", references={"paper": tu.validate("paper", held, t_final=10.0)})
    doc = tu.load_front(path)
    assert len(doc["points"]) == 2 and set(doc["references"]) == {"paper"}
    for p in doc["points"]:
        assert {"L", "k", "D_hat", "budget", "evaluation"} <= set(p)
        assert {"median_T_0.05_s", "median_se_s", "frac_converged", "median_energy", "median_peak_u",
                "mean_adaptive_steps"} <= set(p["evaluation"])
        tu.point_gains(p)


def test_cli_pareto_writes_the_front_and_its_figure(tmp_path, capsys, monkeypatch):
    """... and --atol reaches every held-out evaluation (the points and the references), recorded in the file."""
    seen = []
    real = tu.validate

    def spy(*a, **k):
        seen.append(k.get("stepsize"))
        return real(*a, **k)

    monkeypatch.setattr(tu, "validate", spy)
    monkeypatch.setattr(tu.pareto, "validate", spy)
    out, png = tmp_path / "front.json", tmp_path / "front.png"
    rc = cli_main(["tune", "--pareto", "2", "--out", str(out), "--plot", str(png), "--steps", "2", "--warm-steps", "1",
                   "--batch", str(SMALL["batch"]), "--t-final", "15", "--n-attempts", str(SMALL["n_attempts"]), "--tune", "L,k", "--validate", "4",
                   "--budgets", "5:50", "--atol", "1e-7", "--no-progress"])
    assert rc == 0, capsys.readouterr().err
    doc = json.loads(out.read_text())
    assert [round(p["budget"]) for p in doc["points"]] == [5, 50]
    assert set(doc["references"]) == {"paper", "tuned"} and doc["command"][:2] == ["jaxsleigh", "tune"]
    assert png.stat().st_size > 10_000
    assert len(seen) == 4 and all(s is not None and s.atol == 1e-7 for s in seen)
    assert doc["held_out"]["atol"] == 1e-7 and doc["held_out"]["rtol"] is None
    from jaxsleigh.plots.tuning import _front_caption        # the figure says what made it

    caption = _front_caption(doc)
    assert "4 held-out starts" in caption and "float32" in caption and "atol 1e-07" in caption
    assert "jaxsleigh tune --pareto 2" in caption


# ---------------------------------------------------------------------------------------------
# the shipped preset
# ---------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def balanced_vs_paper():
    # 2048 starts: a median of control energies (they span three decades) moves by ~5% between samples of
    # 256 starts; on 2048 by ~2%. atol 1e-8: the tolerance the preset was searched and accepted at (float32's
    # default 1e-6 does not resolve energy spent after settling; docs/evidence/settled-phase.md)
    ics = tu.UniformStarts()(np.random.default_rng(20240613), 2048)
    ss = js.StepSizeController(atol=1e-8)
    return tu.validate("paper", ics, stepsize=ss), tu.validate("balanced", ics, stepsize=ss)


def _energy_at(v, q=(50, 75, 90)):
    return np.percentile(v.u_energy[v.status == 0], q)


def test_balanced_preset_meets_its_criteria_on_starts_it_never_saw(balanced_vs_paper):
    """`balanced` on 2048 starts that neither its search nor its acceptance check saw
    (experiments/studies/balanced_search.py checked 2048 others): no start failing or crossing theta = 0, no fewer
    converged, and the control energy at the 50th, 75th and 90th percentiles within 2% of the paper's (the search
    held them at or below the paper's on its own starts: a percentile of 2048 moves by ~2% between samples)."""
    preset = __import__("pathlib").Path(js.__file__).parent / "presets" / "balanced.json"
    meta = json.loads(preset.read_text())["meta"]
    assert "how" in meta and {"paper", "balanced", "tuned"} <= set(meta["validation"]) and meta["atol"] == 1e-8
    paper, bal = balanced_vs_paper
    assert bal.n_failed == 0 and bal.n_crossed == 0
    assert np.all(_energy_at(bal) <= 1.02 * _energy_at(paper)), _energy_at(bal) / _energy_at(paper)
    assert bal.frac_converged >= paper.frac_converged


def test_balanced_preset_is_faster_than_the_papers_gains(balanced_vs_paper):
    """Median T_0.05 at least 1.2x shorter than the paper's gains' (1.24x on these starts; 2x was the aim, which
    the previous preset met only where float32 missed the energy it spent after settling: docs/how-to/tuning.md)."""
    paper, bal = balanced_vs_paper
    assert 1.2 * bal.median_T <= paper.median_T


def test_balanced_near_the_singular_set_flags_what_it_cannot_integrate():
    """`balanced` from starts down to |theta0| = 1e-4 (float32, a small step budget so that some give up): a start
    either ends OK with finite figures or with another status and NaN outputs, never a silent NaN or inf."""
    th = np.geomspace(1e-4, 0.05, 24) * np.resize([1, -1], 24)
    ics = np.column_stack([np.resize([2.0, -1.5, 0.5], 24), np.resize([1.0, 2.5, -2.0], 24), th])
    r = js.run_ensemble(ics, gains="balanced", t_final=5.0,
                        stepsize=js.StepSizeController(max_steps=3000), run=js.RunOptions(progress=False))
    ok = r.status == 0
    assert ok.any() and (~ok).any()                     # both paths: integrated, and flagged
    fields = np.column_stack([r.q_final, r.p_final, r.Hd_final, r.u_energy, r.min_abs_theta])
    assert np.all(np.isfinite(fields[ok]))
    assert np.all(np.isnan(r.q_final[~ok])) and np.all(np.isin(r.status[~ok], [s.value for s in js.Status]))
