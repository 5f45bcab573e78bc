"""A law behind a digital controller (``controller=sampled(law, Ts)``) runs through the studies: simulate,
run_ensemble, run_basin and the command line give what the sampled-data loop computes, in the library's
vocabulary; what cannot take a sampled law yet says so instead of integrating it as if it were continuous."""
from __future__ import annotations

import numpy as np
import pytest

import jaxsleigh as js
from jaxsleigh import RunOptions, SaveAt
from jaxsleigh.cli import main
from jaxsleigh.controllers.actuators import Sampler, sampled, saturate
from jaxsleigh.controllers.paper import PaperLaw
from jaxsleigh.integrate.sampled import solve_sampled
from jaxsleigh.studies.sampled import substeps_for

ICS = np.array([[1.0, 1.0, 0.5, 0.0, 0.0], [-3.0, -2.0, np.pi / 8, 0.0, 0.0], [2.0, -1.0, -1.0, 0.3, -0.2]])
LAW = sampled(js.paper_gains(), 0.05, delay=1)


@pytest.fixture(scope="module")
def reference():
    return solve_sampled(PaperLaw(), None, ICS, t_final=10.0, sampler=Sampler(0.05, delay=1),
                         substeps=substeps_for(0.05, 0.01))


def test_simulate_returns_the_sampled_loop(reference):
    sol = js.simulate(ICS, controller=LAW, t_final=10.0)
    np.testing.assert_array_equal(sol.t, np.asarray(reference.t))
    np.testing.assert_array_equal(sol.q, np.asarray(reference.q))
    np.testing.assert_array_equal(sol.u[:, :-1], np.asarray(reference.u))       # held input per sample
    np.testing.assert_array_equal(sol.u[:, -1], np.asarray(reference.u)[:, -1])
    np.testing.assert_array_equal(sol.u_energy, np.asarray(reference.u_energy))
    assert sol.settings["method"] == "sampled" and sol.settings["sampler"]["delay"] == 1
    assert np.all(np.isnan(sol.Hd)) and np.all(sol.u[:, 0] == 0.0)                # one sample of delay: u = 0 first


def test_run_ensemble_and_basin_summarise_the_sampled_loop(reference):
    r = js.run_ensemble(ICS, controller=LAW, t_final=10.0)
    np.testing.assert_array_equal(r.q_final, np.asarray(reference.q_final))
    np.testing.assert_array_equal(r.T_eps, np.asarray(reference.T_eps))
    u = np.asarray(reference.u)
    np.testing.assert_allclose(r.u_peak, np.abs(u).max(axis=1), rtol=1e-6)
    np.testing.assert_allclose(r.u_abs_int, np.linalg.norm(u, axis=2).sum(axis=1) * 0.05, rtol=1e-5)
    assert np.all(r.max_excursion >= np.linalg.norm(np.asarray(reference.q), axis=2).max(axis=1) - 1e-6)
    assert r.settings["method"] == "sampled" and r.settings["step_method"] == "adaptive" and np.all(np.isnan(r.Hd0))
    np.testing.assert_array_equal(r.n_steps, np.asarray(reference.n_steps))             # the loop's own counts
    np.testing.assert_array_equal(r.n_rejected, np.asarray(reference.n_rejected))
    assert np.all(r.n_steps >= 200) and np.all(r.t_reached == 10.0)                     # a step per period at least
    chunked = js.run_ensemble(ICS, controller=LAW, t_final=10.0, run=RunOptions(chunk_size=2))
    np.testing.assert_allclose(chunked.q_final, r.q_final, rtol=1e-5, atol=1e-6)
    b = js.run_basin(ICS, controller=LAW, t_final=10.0)
    np.testing.assert_array_equal(b.q_final, r.q_final)
    assert b.fraction == np.mean(r.converged)


def test_a_sampled_run_checkpoints_and_resumes_like_any_other(tmp_path):
    whole = js.run_ensemble(ICS, controller=LAW, t_final=2.0, run=RunOptions(chunk_size=1))
    ck = tmp_path / "chunks"
    js.run_ensemble(ICS, controller=LAW, t_final=2.0, run=RunOptions(chunk_size=1, checkpoint_dir=ck))
    (sorted(ck.glob("chunk_*"))[1]).unlink()                        # an interrupted run: one chunk missing
    resumed = js.run_ensemble(ICS, controller=LAW, t_final=2.0, run=RunOptions(chunk_size=1, checkpoint_dir=ck, resume=True))
    assert resumed.run_info["chunks_reused"] == 2
    for k in ("q_final", "T_eps", "u_energy", "status"):
        np.testing.assert_array_equal(getattr(resumed, k), getattr(whole, k))
    with pytest.raises(Exception, match="period"):                  # another sampler is another run
        js.run_ensemble(ICS, controller=sampled(js.paper_gains(), 0.1), t_final=2.0,
                        run=RunOptions(chunk_size=1, checkpoint_dir=ck, resume=True))


def test_the_ensembles_step_a_sampled_law_with_the_whole_policy():
    """The policy given to `run_ensemble` reaches the sampled loop whole, its safety and factor limits included (as
    in `simulate`): a smaller safety and a tighter growth limit take more steps."""
    policy = js.StepSizeController(safety=0.5, factor_max=2.0)
    a = js.run_ensemble(ICS, controller=LAW, t_final=2.0)
    b = js.run_ensemble(ICS, controller=LAW, t_final=2.0, stepsize=policy)
    assert np.all(b.n_steps >= a.n_steps) and b.n_steps.sum() > a.n_steps.sum()


def test_the_tuner_tunes_a_sampled_law_on_the_sampled_loop():
    """tune_law differentiates through the sampled-data loop: its energy is the studies' energy of the same law,
    and the energy budget pulls it down; the sampler's numbers and the plant model are not tuned."""
    from jaxsleigh.controllers.registry import make_controller
    from jaxsleigh.tuning import LossConfig, gain_names, tune_law

    starts = ICS[:, :3]
    law = sampled(make_controller("astolfi"), 0.05)
    assert gain_names(law) == ["law.k", "law.p2", "law.p3", "law.K"]
    res = tune_law(law, starts, loss=LossConfig(t_final=10.0, energy_budget=10.0), steps=4, lr=0.1)
    e0 = js.run_ensemble(starts, controller=law, t_final=10.0).u_energy
    assert res.history["energy"][0] == pytest.approx(np.exp(np.mean(np.log(e0))), rel=1e-4)
    assert res.history["energy"][-1] < 0.8 * res.history["energy"][0]
    assert res.law.sampler == law.sampler and float(res.law.law.k) != float(law.law.k)


def test_a_sweep_of_a_sampled_law_equals_separate_runs():
    """The law's gains and the plant vary per trajectory behind one sampler."""
    ics = ICS[[0, 2], :3]
    sw = js.sweep(ics, ["law.gains.k=0.05:0.2:2", "m=1:3:2"], controller=LAW, t_final=5.0)
    assert sw.settings["method"] == "sampled"
    for row, (k, m) in enumerate(sw.values):
        one = js.run_ensemble(ics, plant=js.plant_params(m=m), controller=sampled(js.gains(k=k), 0.05, delay=1),
                              t_final=5.0)
        np.testing.assert_allclose(sw.u_energy[row], one.u_energy, rtol=1e-6)
        np.testing.assert_array_equal(sw.status[row], one.status)


def test_the_sampling_period_matters_in_the_studies():
    # the gentle starts (from (-3, -2, pi/8) the first second's |u| ~ 1e3 makes any held loop drift; see
    # tests/test_sampled_accuracy.py for the loop's accuracy)
    ics = ICS[[0, 2]]
    fine = js.run_ensemble(ics, controller=sampled(js.paper_gains(), 0.01), t_final=20.0)
    coarse = js.run_ensemble(ics, controller=sampled(js.paper_gains(), 0.5), t_final=20.0)
    cont = js.run_ensemble(ics, t_final=20.0)
    assert np.abs(fine.q_final - cont.q_final).max() < 0.2 < np.abs(coarse.q_final - cont.q_final).max()


def test_what_cannot_take_a_sampled_law_says_so(tmp_path):
    with pytest.raises(ValueError, match="save_every"):
        js.run_ensemble(ICS, controller=LAW, t_final=1.0, saveat=SaveAt(every=10))
    with pytest.raises(ValueError, match="period cannot vary per trajectory"):
        js.sweep(ICS[:, :3], ["sampler.period=0.05:0.1:2"], controller=LAW, t_final=1.0)
    with pytest.raises(ValueError, match="whole number of sampling periods"):
        js.simulate(ICS, controller=sampled(js.paper_gains(), 0.3), t_final=10.0)


def test_command_line_simulate_with_a_digital_saturated_controller(tmp_path, capsys):
    out = tmp_path / "s.npz"
    code = main(["simulate", "--ic=-3,-2,pi/8", "--sample-period", "0.05", "--delay", "1", "--noise", "0.001",
                 "--seed", "3", "--saturation", "50", "--t-final", "5", "--out", str(out)])
    d = np.load(out)
    assert code == 0 and d["u"].shape == (1, 101, 2) and np.nanmax(np.abs(d["u"])) == pytest.approx(50.0)
    law = sampled(saturate(js.paper_gains(), 50.0), 0.05, delay=1, noise=0.001, seed=3)
    np.testing.assert_array_equal(d["q"], js.simulate([-3.0, -2.0, np.pi / 8], controller=law, t_final=5.0).q)
    capsys.readouterr()
    assert main(["simulate", "--ic", "1,1,0.5", "--noise", "0.1", "--out", str(out)]) == 2
    assert "--sample-period" in capsys.readouterr().err


def test_command_line_basin_with_a_digital_controller_gives_the_same_bytes_twice(tmp_path, capsys):
    argv = ["basin", "--x", "-2:2:3", "--y", "-2:2:2", "--theta", "0.8", "--sample-period", "0.05", "--noise", "0.001",
            "--seed", "2", "--t-final", "10", "--chunk-size", "2"]
    assert main(argv + ["--out", str(tmp_path / "a.npz")]) == 0
    assert main(argv + ["--out", str(tmp_path / "b.npz")]) == 0
    b = js.load_basin(tmp_path / "b.npz")
    assert b.settings["method"] == "sampled" and b.settings["sampler"] == {"period": 0.05, "delay": 0,
                                                                         "noise": 0.001, "seed": 2}
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()      # same command, same bytes
    capsys.readouterr()


def test_noise_makes_astolfi_s_law_diverge_whatever_the_tolerances():
    """With Ts = 0.05 and a 0.001 measurement noise Astolfi's law divides by a measured heading that crosses 0
    (theta decays like e^(-kt) to the noise): the held force reaches 1e5 N and flings the sleigh hundreds of metres
    away, faster and faster, until a period needs more steps than its share of the budget. Every start ends so at
    the default tolerances and at 100x tighter ones alike (the loop is not at fault), while the noiseless law
    settles them."""
    from jaxsleigh.controllers.registry import make_controller

    law, ics = make_controller("astolfi"), np.array([[1.0, 1.0, 0.5, 0.0, 0.0], [-2.0, 1.0, 1.0, 0.0, 0.0]])
    for tol in (None, 1e-8):
        noisy = solve_sampled(law, None, ics, t_final=20.0, sampler=Sampler(0.05, 0, 1e-3, 0),
                              stepsize=js.StepSizeController(rtol=tol, atol=tol))
        assert np.asarray(noisy.status).tolist() == [js.Status.BUDGET_EXHAUSTED] * 2
        assert np.all(np.asarray(noisy.t_reached) < 20.0)
        assert np.all(np.nanmax(np.abs(np.asarray(noisy.u)), axis=(1, 2)) > 1e5)
        assert np.all(np.nanmax(np.linalg.norm(np.asarray(noisy.q), axis=2), axis=1) > 300.0)
    clean = solve_sampled(law, None, ics, t_final=20.0, sampler=Sampler(0.05, 0, 0.0, 0), save=False)
    assert np.asarray(clean.status).tolist() == [0, 0] and np.all(np.isfinite(np.asarray(clean.T_eps)))
