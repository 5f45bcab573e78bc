"""The studies' options as small objects: every front takes at most 13 parameters, the objects go down to the
engine whole, and what is wrong is named (the keywords of jaxsleigh 0.1 are refused: test_deprecated_keywords.py)."""
import inspect

import numpy as np
import pytest

import jaxsleigh as js

STARTS = np.array([[1.0, 1.0, 0.5], [-2.0, 1.0, -1.0], [0.5, -1.5, 2.0]])


@pytest.mark.parametrize("front", [js.simulate, js.run_ensemble, js.run_basin, js.sweep])
def test_every_front_takes_at_most_13_parameters(front):
    assert len(inspect.signature(front).parameters) <= 13, inspect.signature(front)


#: the keywords of jaxsleigh 0.1: each lives in one of the three objects, and no front or engine takes them loose
OLD_KEYWORDS = {"method", "rtol", "atol", "max_step", "max_steps", "check_passivity", "save_every", "summaries",
                "chunk_size", "segment", "devices", "cores", "checkpoint_dir", "resume", "progress", "shard", "policy"}


@pytest.mark.parametrize("engine", ["ensemble.run_ensemble_resolved", "basin._run_basin", "sweep._sweep",
                                    "simulate._simulate"])
def test_the_engine_behind_each_front_takes_the_option_objects_whole(engine):
    """The objects go down as they are: the engine behind a front takes ``stepsize`` and ``run`` (not their
    fields one by one, as it did with 15-26 parameters) and at most 13 parameters in all."""
    import importlib

    module, name = engine.split(".")
    params = inspect.signature(getattr(importlib.import_module(f"jaxsleigh.studies.{module}"), name)).parameters
    assert {"stepsize", "run"} <= set(params), engine
    assert not OLD_KEYWORDS & set(params), sorted(OLD_KEYWORDS & set(params))
    assert len(params) <= 13, list(params)


def test_the_objects_reach_the_engine_whole():
    """Tolerances, step cap, saved steps, chunk and segment given as objects: the same numbers as the engine run
    on the same objects (`run_ensemble_resolved`), and the settings record them."""
    from jaxsleigh.studies.ensemble import run_ensemble_resolved

    ss, at, run = (js.StepSizeController(rtol=1e-7, atol=1e-7, max_step=0.5), js.SaveAt(every=100),
                   js.RunOptions(chunk_size=2, segment=200))
    a = js.run_ensemble(STARTS, t_final=5.0, stepsize=ss, saveat=at, run=run)
    b = run_ensemble_resolved(STARTS, plant=None, gains=None, controller=None, t_final=5.0, dt=0.01, eps=0.05,
                              x64=False, observers=None, stepsize=ss, saveat=at, run=run)
    for k in ("q_final", "T_eps", "u_energy", "n_steps", "status"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
    np.testing.assert_array_equal(a.q, b.q)
    assert (a.settings["rtol"], a.settings["max_step"], a.settings["save_every"], a.settings["chunk_size"]) == \
        (1e-7, 0.5, 100, 2)


def test_the_policy_reaches_the_stepper():
    """A smaller safety factor takes more steps (the policy's numbers are traced into the step)."""
    a = js.run_ensemble(STARTS, t_final=5.0)
    b = js.run_ensemble(STARTS, t_final=5.0, stepsize=js.StepSizeController(safety=0.5))
    assert np.all(b.n_steps >= a.n_steps) and b.n_steps.sum() > a.n_steps.sum()
    c = js.run_basin(STARTS, t_final=5.0, stepsize=js.StepSizeController(safety=0.5))
    ran = c.status == js.Status.OK                 # a basin stops the starts certified not to settle (status 9)
    assert ran.any()
    np.testing.assert_array_equal(c.n_steps[ran], b.n_steps[ran])
    assert np.all(c.n_steps[~ran] <= b.n_steps[~ran])


def test_the_configuration_holds_the_policy_resolved_once():
    """`solve_config` resolves the step policy once into `SolveConfig.stepsize` (every number set, the caller's
    safety and factor limits kept): the one object the engine runs and the settings record, with no copies of its
    fields beside it."""
    from jaxsleigh.integrate.horizon import default_max_steps
    from jaxsleigh.studies.config import SolveConfig, solve_config

    assert not {"method", "rtol", "atol", "max_step", "max_steps", "check_passivity"} & set(SolveConfig._fields)
    assert not hasattr(SolveConfig, "step_controller")
    given = js.StepSizeController(rtol=1e-7, safety=0.8, factor_min=0.2, factor_max=3.0)
    cfg = solve_config(t_final=5.0, x64=True, stepsize=given)
    assert cfg.stepsize == given._replace(atol=1e-8, max_step=1.0, max_steps=default_max_steps(cfg.horizon, True,
                                                                                                  "float64"))
    assert all(v is not None for v in cfg.stepsize)
    s = cfg.settings()
    assert {k: s[k] for k in ("method", "rtol", "atol", "max_step", "max_steps", "check_passivity")} == \
        {k: getattr(cfg.stepsize, k) for k in ("method", "rtol", "atol", "max_step", "max_steps", "check_passivity")}


@pytest.mark.parametrize("call, err, match", [
    (lambda: js.run_ensemble(STARTS, rtoll=1e-6), TypeError, "unexpected keyword argument 'rtoll'"),
    (lambda: js.run_ensemble(STARTS, rtol=1e-6, stepsize=js.StepSizeController(rtol=1e-7)), TypeError,
     r"unexpected keyword argument 'rtol': pass stepsize=jaxsleigh.StepSizeController\(rtol=...\)"),
    (lambda: js.simulate(STARTS, run=js.RunOptions(chunk_size=4)), ValueError, "no use for run.chunk_size"),
    (lambda: js.simulate(STARTS, saveat=js.SaveAt(summaries=False)), ValueError, "no use for saveat.summaries"),
    (lambda: js.simulate(STARTS, run=js.RunOptions(audit=False)), ValueError, "no use for run.audit"),
    (lambda: js.run_basin(STARTS, run=js.RunOptions(segment=500)), ValueError, "no use for run.segment"),
    (lambda: js.sweep(STARTS, ["k=0.1:0.2:2"], run=[4]), ValueError, "run must be a jaxsleigh.RunOptions, got list"),
    (lambda: js.simulate(STARTS, saveat=js.SaveAt), ValueError, "saveat must be a jaxsleigh.SaveAt, got type"),
    (lambda: js.run_ensemble(STARTS, stepsize=js.StepSizeController(safety=1.5)), ValueError,
     "stepsize.safety must be in"),
    (lambda: js.run_ensemble(STARTS, stepsize=js.StepSizeController(factor_max=0.5)), ValueError,
     "stepsize.factor_max must be > 1"),
    (lambda: js.run_ensemble(STARTS, stepsize=js.StepSizeController(method="euler")), ValueError,
     "stepsize.method must be"),
    (lambda: js.run_ensemble(STARTS, stepsize=js.StepSizeController(rtol=-1.0)), ValueError, "rtol must be > 0"),
    (lambda: js.run_basin(STARTS, saveat=js.SaveAt(every=10)), TypeError, "unexpected keyword argument 'saveat'"),
    (lambda: js.run_ensemble(STARTS, stepsize={"rtol": 1e-6}), ValueError, "StepSizeController"),
])
def test_wrong_options_are_named(call, err, match):
    with pytest.raises(err, match=match):
        call()


@pytest.mark.parametrize("policy, says", [
    (js.StepSizeController(safety=1.5), r"stepsize.safety must be in \(0, 1\]"),
    (js.StepSizeController(factor_min=1.0), r"stepsize.factor_min must be in \(0, 1\)"),
    (js.StepSizeController(atol=float("nan")), r"stepsize.atol must be > 0 and finite"),
    (js.StepSizeController(max_steps=0), r"stepsize.max_steps must be >= 1"),
    (js.StepSizeController(method="euler"), r"stepsize.method must be 'adaptive' or 'rk4'")])
def test_one_policy_check_for_every_front(policy, says):
    """The studies, `jaxsleigh.solve`, the sampled-data loop and the traced settling time check a step policy in one
    place, with one message
    (`jaxsleigh.integrate.stepsize.check_policy`): ``solve`` ran a safety factor of 1.5 and the sampled loop a
    ``factor_min`` of 1 without a word before."""
    from jaxsleigh.controllers.actuators import Sampler
    from jaxsleigh.integrate.sampled import solve_sampled
    from jaxsleigh.tuning.event_time import settling

    for call in (lambda: js.run_ensemble(STARTS, stepsize=policy),
                 lambda: js.solve(js.paper_gains(), STARTS[0], t_final=1.0, stepsize=policy),
                 lambda: solve_sampled(js.paper_gains(), None, STARTS, t_final=1.0, sampler=Sampler(0.1),
                                       stepsize=policy),
                 lambda: settling(js.paper_gains(), np.ones((1, 5)), js.paper_plant(), t_final=1.0, stepsize=policy)):
        with pytest.raises(ValueError, match=says):
            call()
