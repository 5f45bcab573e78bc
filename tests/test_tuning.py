"""Gain tuning (jaxsleigh.tuning): parametrisation, gradients through the integrator against finite
differences, the optimiser loop's safety contract, the command line and the shipped preset."""
from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsleigh as js
from jaxsleigh import tuning as tu
from jaxsleigh.cli import main as cli_main
from jaxsleigh.cli.tune import add_tune
from jaxsleigh.studies.ensemble import run_ensemble
from jaxsleigh.status import Status

# Small budget shared by the API and CLI runs (same shapes and static settings: one compilation).
SMALL = dict(batch=24, n_attempts=2000)
SMALL_LOSS = tu.LossConfig(t_final=15.0)


# ---------------------------------------------------------------------------------------------
# parametrisation
# ---------------------------------------------------------------------------------------------

@pytest.mark.usefixtures("x64")
def test_every_parameter_vector_maps_to_admissible_gains(rng):
    """L > 0, k > 0 and D_hat symmetric with eigenvalues >= the floor, for wild parameters too."""
    for scale in (0.1, 3.0, 20.0):
        for _ in range(50):
            theta = tu.GainParams(rng.normal(scale=scale, size=3), rng.normal(scale=scale), rng.normal(scale=scale, size=3))
            g = tu.gains_from_params(theta)
            L, k, D = np.asarray(g.L), float(g.k), np.asarray(g.D_hat)
            if not (np.all(np.isfinite(L)) and np.isfinite(k) and np.all(np.isfinite(D))):
                continue  # exp overflow of absurd parameters; the tuner rejects non-finite candidates
            assert np.all(L > 0) and k > 0
            np.testing.assert_array_equal(D, D.T)
            assert np.linalg.eigvalsh(D).min() >= tu.D_FLOOR * (1 - 1e-9)
            if scale <= 3.0:
                js.gains(L, k, D)   # the library's own validation accepts them


@pytest.mark.usefixtures("x64")
def test_parametrisation_round_trips(sample_gains):
    for _ in range(10):
        g = sample_gains()
        back = tu.gains_from_params(tu.params_from_gains(g))
        np.testing.assert_allclose(back.L, g.L, rtol=1e-12)
        np.testing.assert_allclose(back.k, g.k, rtol=1e-12)
        np.testing.assert_allclose(back.D_hat, g.D_hat, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="floor"):
        tu.params_from_gains(js.gains(D_hat=[1e-4, 1.0]))


def test_split_and_merge_freeze_the_other_gains():
    theta = tu.params_from_gains("paper")
    trainable, frozen = tu.split_params(theta, "k,L")
    assert set(trainable) == {"log_L", "log_k"}
    moved = {k: v + 1.0 for k, v in trainable.items()}
    merged = tu.merge_params(moved, frozen)
    np.testing.assert_array_equal(merged.d_chol, theta.d_chol)
    np.testing.assert_array_equal(merged.log_L, theta.log_L + 1.0)
    assert tu.parse_tune(None) == ("L", "k", "D_hat")
    with pytest.raises(ValueError, match="subset"):
        tu.parse_tune("L,m")
    with pytest.raises(ValueError, match="subset"):
        tu.parse_tune("")


# ---------------------------------------------------------------------------------------------
# gradients through the integrator
# ---------------------------------------------------------------------------------------------

_FD_ICS = np.array([[1.0, -0.5, 0.8], [-0.6, 0.4, -1.2], [0.3, 0.2, 0.5]])
_FD_GAINS = js.gains([3.0, 0.8, 1.2], 0.05, [[3.0, 0.4], [0.4, 6.0]])


def test_a_loss_config_holds_a_step_policy_that_jit_grad_and_vmap_trace():
    """The policy's numbers are leaves of the config (changing them does not recompile), its method, passivity switch
    and budget static; the settings record keeps one key per number, as before the policy was an object."""
    loss = tu.LossConfig(t_final=5.0)
    cfg = tu.traced_loss(loss, jnp.float32)
    leaves = jax.tree_util.tree_leaves(cfg)
    assert all(isinstance(x, jax.Array) for x in leaves) and cfg.stepsize.method == "adaptive"
    f = jax.jit(lambda c: c.stepsize.rtol * c.t_final)
    assert float(f(cfg)) == pytest.approx(5e-5) and f._cache_size() == 1
    f(tu.traced_loss(loss._replace(stepsize=loss.stepsize._replace(rtol=1e-6)), jnp.float32))
    assert f._cache_size() == 1
    assert float(jax.grad(lambda c: c.stepsize.atol * c.dt)(cfg).stepsize.atol) == pytest.approx(0.01)
    axes = tu.LossConfig(*([None] * len(tu.LossConfig._fields)))._replace(energy_budget=0)
    out = jax.vmap(lambda c: c.energy_budget * c.stepsize.max_step, in_axes=(axes,))(
        cfg._replace(energy_budget=jnp.arange(3.0)))
    np.testing.assert_allclose(out, [0.0, 0.1, 0.2], rtol=1e-6)
    from jaxsleigh.tuning.objective import loss_record
    rec = loss_record(loss)
    assert list(rec)[:8] == ["t_final", "guard_t_final", "probe_t_final", "dt", "max_step", "rtol", "atol", "eps"]
    assert (rec["max_step"], rec["rtol"], rec["atol"]) == (0.1, 1e-5, 1e-5) and "method" not in rec
    with pytest.raises(ValueError, match="loss.stepsize.method must be 'adaptive'"):
        tu.tune(loss=tu.LossConfig(stepsize=js.StepSizeController(method="rk4")), progress=False)


def _fd_setup(t_final, rtol):
    data = tu.make_training_set(_FD_ICS, guard=np.zeros((0, 3)))
    loss = tu.LossConfig(t_final=t_final, stepsize=js.StepSizeController(rtol=rtol, atol=rtol, max_step=0.1))
    cfg = tu.traced_loss(loss, jnp.zeros(()).dtype)
    theta = tu.GainParams(*(jnp.asarray(x) for x in tu.params_from_gains(_FD_GAINS)))
    trainable, frozen = tu.split_params(theta, None)
    return data, cfg, trainable, frozen


def _flat(tree):
    """``ravel_pytree(tree)[0]`` of a dict of arrays, in NumPy (sorted keys): no eager program."""
    return np.concatenate([np.ravel(np.asarray(tree[key])) for key in sorted(tree)])


def _unravel(v, like):
    """``v`` (flat, NumPy) as the dict ``like`` (``ravel_pytree``'s order: sorted keys), split in NumPy (no eager
    program) and put on the device as ``like``'s leaves are (NumPy arguments would retrace the jitted function)."""
    out, i = {}, 0
    for key in sorted(like):
        n = int(np.size(like[key]))
        out[key] = jnp.asarray(np.asarray(v[i:i + n]).reshape(np.shape(like[key])))   # a device array, as ``like``'s
        i += n
    return out


def _central_differences(vg, trainable, frozen, data, cfg, h=1e-5):
    """Central differences of the objective's value, evaluated by the (already compiled) value-and-gradient program
    ``vg`` itself: no second program (a jitted objective) to compile, and the same primal computation."""
    flat = _flat(trainable)
    n = vg._cache_size()

    def f(v):
        return float(vg(_unravel(v, trainable), frozen, data, cfg)[0][0])

    fd = np.array([(f(flat + h * e) - f(flat - h * e)) / (2 * h) for e in np.eye(flat.size)])
    assert vg._cache_size() == n                 # the differences reused the program, not a retrace
    return fd


@pytest.mark.usefixtures("x64")
def test_fixed_step_gradients_equal_central_differences():
    """With fixed RK4 steps the objective is a smooth function of the gains: reverse-mode AD must
    agree with central differences (float64) to the differences' own accuracy."""
    data, cfg, trainable, frozen = _fd_setup(t_final=2.0, rtol=1e-9)
    kw = dict(n_attempts=220, adaptive=False)
    vg = tu.make_value_and_grad(mode="reverse", **kw)
    (value, aux), grad = vg(trainable, frozen, data, cfg)
    assert bool(aux["valid"]) and np.all(np.asarray(aux["lanes"].t_reached) == 2.0)
    fd = _central_differences(vg, trainable, frozen, data, cfg)
    g = _flat(grad)
    assert np.max(np.abs(g)) > 1e-4            # a real signal, not two zeros
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-7 * np.max(np.abs(fd)))


@pytest.mark.usefixtures("x64")
def test_adaptive_gradients_forward_reverse_and_central_differences():
    """The adaptive step sizes are frozen in the derivative (stop_gradient): the AD gradient is the
    derivative of the discrete map with its step sequence fixed, so it agrees with central
    differences (which let the steps move) to the integration tolerance; forward and reverse mode
    agree to rounding."""
    data, cfg, trainable, frozen = _fd_setup(t_final=4.0, rtol=1e-9)
    kw = dict(n_attempts=2000)
    vg = tu.make_value_and_grad(mode="reverse", **kw)
    (v_r, aux), g_r = vg(trainable, frozen, data, cfg)
    (v_f, _), g_f = tu.make_value_and_grad(mode="forward", **kw)(trainable, frozen, data, cfg)
    assert bool(aux["valid"])
    g_r, g_f = _flat(g_r), _flat(g_f)
    assert float(v_r) == pytest.approx(float(v_f), rel=1e-13)
    np.testing.assert_allclose(g_f, g_r, rtol=1e-9, atol=1e-12)
    fd = _central_differences(vg, trainable, frozen, data, cfg)
    np.testing.assert_allclose(g_r, fd, rtol=1e-3, atol=1e-4 * np.max(np.abs(fd)))


# ---------------------------------------------------------------------------------------------
# the optimiser loop
# ---------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def small_run():
    config = tu.TuneConfig(steps=10, lr=0.3, warmup=1, seed=3, **SMALL)
    return config, tu.tune("paper", config=config, loss=SMALL_LOSS, tune="L,k", progress=False)


def test_small_tune_improves_keeps_frozen_gains_and_returns_valid_gains(small_run):
    config, res = small_run
    h = res.history
    assert res.best_loss < res.initial_loss - 0.05
    assert h.valid[res.best_iteration] and h.loss[res.best_iteration] == pytest.approx(res.best_loss)
    assert np.all(np.diff(h.best) <= 0)
    # D_hat was frozen: returned bit for bit; L and k moved
    np.testing.assert_array_equal(res.gains.D_hat, js.paper_gains().D_hat)
    assert not np.allclose(res.gains.L, js.paper_gains().L) and res.gains.k != js.paper_gains().k
    # the returned gains: every training start, guard start and held-out start (|theta0| down to
    # 0.05) is integrated with status OK by the accurate engine
    train = tu.draw_starts(tu.UniformStarts(), config.batch, config.seed)
    held = tu.UniformStarts(theta_min=0.05)(np.random.default_rng(777), 24)
    ics = np.concatenate([train, tu.guard_starts(), held, [[1.0, 1.0, 0.05], [-2.0, 0.5, -0.05]]])
    r = run_ensemble(ics, gains=res.gains, t_final=30.0, run=js.RunOptions(progress=False))
    assert np.all(r.status == Status.OK)
    assert np.all(np.isfinite(r.q_final)) and np.all(r.min_abs_theta > 0)


def test_tuner_rejects_invalid_candidates_and_backtracks():
    """A step budget that only just fits the paper's gains and a huge learning rate: the stiffer
    candidates run out of budget, each is rejected, the step from the last valid point is halved,
    and the returned gains are those of a valid iteration. Invalid starting gains are an error."""
    config = tu.TuneConfig(steps=6, lr=1.5, warmup=1, seed=3, batch=SMALL["batch"], n_attempts=1100)
    res = tu.tune("paper", config=config, loss=SMALL_LOSS, tune="L,k", progress=False)
    h = res.history
    assert h.valid[0] and h.valid[res.best_iteration]
    rejected = np.flatnonzero(~h.valid)
    assert rejected.size >= 1
    for i in rejected[rejected + 1 < h.loss.size]:
        assert h.lr_scale[i + 1] == pytest.approx(0.5 * h.lr_scale[i])
    assert res.best_loss == pytest.approx(np.min(h.loss[h.valid]))
    with pytest.raises(ValueError, match="raise n_attempts"):
        tu.tune("paper", config=config._replace(steps=2), loss=SMALL_LOSS._replace(t_final=200.0), tune="L,k",
                progress=False)
    # the integration-cost probe: 100 s of the paper's closed loop need ~1400 steps
    with pytest.raises(ValueError, match="probe_budget"):
        tu.tune("paper", config=config._replace(steps=2, probe_budget=500), loss=SMALL_LOSS, tune="L,k",
                progress=False)


def test_second_run_and_cli_do_not_recompile(small_run, tmp_path, capsys):
    """``jaxsleigh tune`` writes a gains file that ``jaxsleigh simulate --gains`` accepts, plus the
    history; with the same shapes it reuses the compiled objective of the API run."""
    vg = tu.make_value_and_grad(mode="forward", n_attempts=SMALL["n_attempts"])
    # the tuner's own call names every setting: defaults given or left out are the same function
    assert tu.make_value_and_grad(mode="forward", n_attempts=float(SMALL["n_attempts"]), segment=100,
                                  adaptive=True, d_floor=tu.D_FLOOR) is vg
    n_compiled = vg._cache_size()
    assert n_compiled >= 1                     # the small run compiled it: the check below can fail
    parser = argparse.ArgumentParser(prog="jaxsleigh")
    add_tune(parser.add_subparsers(dest="command"))
    out, hist = tmp_path / "gains.json", tmp_path / "history.npz"
    argv = ["tune", "--out", str(out), "--steps", "3", "--batch", str(SMALL["batch"]), "--seed", "5",
            "--t-final", "15", "--n-attempts", str(SMALL["n_attempts"]), "--tune", "L,k", "--lr", "0.1",
            "--validate", "0", "--history", str(hist), "--no-progress"]
    args = parser.parse_args(argv)
    assert args.func(args) == 0
    assert vg._cache_size() == n_compiled
    stdout = capsys.readouterr().out
    assert "loss" in stdout and str(out) in stdout
    d = json.loads(out.read_text())
    assert set(d) == {"L", "k", "D_hat", "meta"} and d["meta"]["tuned"] == ["L", "k"]
    assert d["meta"]["command"][:2] == ["jaxsleigh", "tune"]
    g = js.load_gains(out)
    np.testing.assert_array_equal(g.D_hat, js.paper_gains().D_hat)
    h = tu.load_history(hist)
    assert h.loss.shape == (3,) and h.L.shape == (3, 3) and h.D_hat.shape == (3, 2, 2)
    rc = cli_main(["simulate", "--ic", "1,1,0.5", "--t-final", "1", "--dt", "0.01", "--save-every", "10",
                   "--gains", str(out), "--out", str(tmp_path / "run.npz")])
    assert rc == 0, capsys.readouterr().err
    with pytest.raises(ValueError, match="subset"):
        args = parser.parse_args(["tune", "--out", str(out), "--tune", "L,q"])
        args.func(args)


# ---------------------------------------------------------------------------------------------
# the shipped preset
# ---------------------------------------------------------------------------------------------

def test_tuned_preset_meets_the_target_on_held_out_starts():
    """Median T_0.05 at least 5x shorter than the paper's gains, fraction converged within 100 s no
    lower, every trajectory OK, with the accurate engine on starts the tuner never saw. The hard starts near the
    singular set fail their audit at 1e-10 (worst state 0.19: they are chaotic), so their figures are float64's at
    1e-10 (``resolved``); the audit's ladder, which re-ran them at 1e-12 and 1e-13 (about half of this test's time)
    and failed all the same, changes none of those figures (bit for bit), and is left out: ``confirm_tol`` and
    ``tightest_tol`` at the reference's 1e-10."""
    g = js.load_gains("tuned")
    meta = json.loads((__import__("pathlib").Path(js.__file__).parent / "presets" / "tuned.json").read_text())["meta"]
    assert "how" in meta and "validation" in meta
    ics = tu.UniformStarts()(np.random.default_rng(20240611), 128)
    paper = tu.validate("paper", ics)
    tuned = tu.validate(g, ics)
    assert paper.n_failed == 0 and tuned.n_failed == 0
    assert tuned.median_T * 5 <= paper.median_T
    assert tuned.frac_converged >= paper.frac_converged
    hard = np.concatenate([tu.guard_starts(), [[0.5, -0.5, 0.05], [-1.0, 2.0, -0.05]]])
    guard = tu.validate(g, hard, t_final=20.0, audit=js.Audit(rows=len(hard), confirm_tol=1e-10, tightest_tol=1e-10))
    assert guard.n_failed == 0


def test_the_gradient_norm_on_the_host_is_optaxs_to_the_bit():
    """The tuner's history records the gradient's norm computed on the host (no program per operation): the same
    bits as `optax.tree.norm` for gradients of every scale, in float32 and float64."""
    import optax

    from jaxsleigh.tuning.optimizer import host_norm

    rng = np.random.default_rng(1)
    for x64 in (False, True):
        with jax.enable_x64(x64):
            dt = np.float64 if x64 else np.float32
            for _ in range(200):
                s = 10.0 ** rng.uniform(-8, 8, 3)
                g = {"log_L": jnp.asarray((s[0] * rng.standard_normal(3)).astype(dt)),
                     "log_k": jnp.asarray(dt(s[1] * rng.standard_normal())),
                     "d_chol": jnp.asarray((s[2] * rng.standard_normal(3)).astype(dt))}
                assert host_norm(g) == float(optax.tree.norm(g))
