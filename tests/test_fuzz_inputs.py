"""Property-based fuzzing of the input layer (Hypothesis).

The contract: whatever a user passes, the answer is a ``ValueError`` that names what to change, or a
result whose bad rows are flagged by their status; never a traceback, never a silent NaN (a row
with status OK is finite everywhere; a row that is not finite or sits on theta = 0 is flagged).
"""
from __future__ import annotations

import importlib
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import jaxsleigh as js
from jaxsleigh import cli
from jaxsleigh.studies.config import solve_config
from jaxsleigh.errors import JaxsleighWarning
from jaxsleigh.status import NOT_INTEGRATED, Status

FUZZ = settings(max_examples=60, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])

special = st.sampled_from([0.0, -0.0, np.nan, np.inf, -np.inf, 1e-200, -1e-30, 1e-8, 1e30, 1e300, 3.0, -2.5, 0.5])
coord = st.one_of(special, st.floats(-10, 10, allow_nan=False))
weird = st.one_of(special, st.floats(-100, 100), st.booleans(), st.just("x"), st.complex_numbers(max_magnitude=5),
                  st.just(None), st.integers(-3, 3))


@FUZZ
@given(ics=st.lists(st.lists(coord, min_size=3, max_size=3), min_size=3, max_size=3),
       L=st.one_of(st.lists(weird, min_size=3, max_size=3), st.lists(st.floats(0.1, 5), min_size=3, max_size=3),
                   st.lists(weird, min_size=1, max_size=4)),
       k=st.one_of(weird, st.floats(0.01, 1)),
       D=st.one_of(st.lists(st.floats(0.5, 9), min_size=2, max_size=2), st.lists(weird, min_size=2, max_size=2)))
def test_simulate_answers_any_input_with_a_message_or_flagged_rows(ics, L, k, D):
    arr = np.array(ics, dtype=float)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", JaxsleighWarning)   # flagged rows are checked below
            sol = js.simulate(arr, gains=js.Gains(L, k, D), t_final=0.05, dt=0.01, saveat=js.SaveAt(every=1))
    except ValueError as e:
        assert len(str(e)) > 10
        return
    ok = sol.status == Status.OK
    for field in (sol.q, sol.p, sol.u, sol.Hd):
        assert np.all(np.isfinite(field[ok])), "a row with status OK holds a non-finite value"
    nonfinite_rows = ~np.all(np.isfinite(sol.q.reshape(len(ok), -1)), axis=1)
    assert np.all(~ok[nonfinite_rows]), "a NaN in a row whose status says OK"
    bad_input = ~np.all(np.isfinite(arr), axis=1) | (arr[:, 2] == 0)
    assert np.all(np.isin(sol.status[bad_input], NOT_INTEGRATED))
    assert np.all(np.isnan(sol.q[np.isin(sol.status, NOT_INTEGRATED)]))


@FUZZ
@given(t_final=weird, dt=weird, save_every=weird, method=st.sampled_from(["adaptive", "rk4", "euler", 3]),
       rtol=st.one_of(st.none(), weird), max_step=st.one_of(st.none(), weird),
       max_steps=st.one_of(st.none(), weird, st.integers(-5, 2**40)), x64=st.one_of(st.booleans(), weird),
       eps=weird)
def test_solve_config_accepts_exactly_the_valid_options(t_final, dt, save_every, method, rtol, max_step, max_steps,
                                                         x64, eps):
    try:
        cfg = solve_config(t_final=t_final, dt=dt, save_every=save_every, x64=x64, eps=eps,
                           stepsize=js.StepSizeController(method=method, rtol=rtol, max_step=max_step,
                                                          max_steps=max_steps))
    except ValueError as e:
        assert len(str(e)) > 10
        return
    h, ss = cfg.horizon, cfg.stepsize
    assert 1 <= h.n_steps and h.n_steps % h.save_every == 0
    assert np.isfinite([h.t_final, h.dt, ss.rtol, ss.atol, ss.max_step, cfg.eps]).all()
    assert min(h.dt, ss.rtol, ss.atol, ss.max_step, cfg.eps) > 0
    assert 1 <= ss.max_steps < 2**31 - 1 and isinstance(ss.max_steps, int)
    assert ss.method in ("adaptive", "rk4") and isinstance(cfg.x64, bool)


class _Reached(Exception):
    """Raised by the stub integrator: validation passed and the work would start."""


TOKENS = ["0", "-1", "nan", "inf", "-inf", "1e300", "1e-300", "pi", "-pi/8", "abc", "", "3000000000", "1.5",
          "10", "0.01", "1,1", "1,1,0", "1,1,0.5", "2,1,1", "0,1,1", "1,1,1,1,1", "--x64", "tuned", "paper",
          "nope.json", "1e-30"]


@FUZZ
@given(opts=st.lists(st.tuples(st.sampled_from(["--t-final", "--dt", "--save-every", "--max-steps", "--ic",
                                                 "--params", "--gains", "--method", "--damping"]),
                               st.sampled_from(TOKENS)), min_size=1, max_size=5))
def test_the_command_line_never_shows_a_traceback(tmp_path, capsys, monkeypatch, opts):
    def stub(*a, **k):
        raise _Reached

    monkeypatch.setattr(importlib.import_module("jaxsleigh.cli.simulate"), "simulate", stub, raising=False)
    monkeypatch.setattr(importlib.import_module("jaxsleigh.studies.simulate"), "drive_saving", stub)
    argv = ["simulate", "--out", str(tmp_path / "x.npz")]
    for flag, value in opts:
        argv += [flag, value]
    if "--ic" not in argv:
        argv += ["--ic", "1,1,0.5"]
    try:
        rc = cli.main(argv)
    except _Reached:
        return
    _, err = capsys.readouterr()
    assert rc == 2 and err.startswith("jaxsleigh: error: ") and "Traceback" not in err, (argv, err)


@pytest.mark.parametrize("value", [True, 1 + 2j, "1", None, [1.0], np.array([1.0, 2.0])])
def test_scalar_options_refuse_what_is_not_a_number(value):
    with pytest.raises(ValueError, match="t_final"):
        solve_config(t_final=value)


@pytest.mark.parametrize("argv", [
    ["simulate", "--ic", "1,1,0.5", "--t-final", "1", "--sample-period", "1e-320"],     # t_final / period = inf
    ["simulate", "--ic", "1,1,0.5", "--t-final", "1", "--sample-period", "1e-12"],      # 1e12 samples
    ["basin", "--x", "-1:1:2", "--y", "1", "--theta", "0.5", "--t-final", "1", "--sample-period", "1e-320"],
    ["paper", "--dt", "1e-320"],
    ["basin", "--x", "1:2:inf", "--y", "1", "--theta", "0.5"],
    ["basin", "--x", "1:2:nan", "--y", "1", "--theta", "0.5"],
])
def test_overflowing_numbers_on_the_command_line_are_refused_with_a_message(tmp_path, capsys, argv):
    """Found by running every numeric flag of every command with nan, inf, 1e999, 1e-320, ...: these ended in an
    OverflowError traceback (a count of steps, samples or points that is not finite or does not fit)."""
    out = ["--out", str(tmp_path / ("p" if argv[0] == "paper" else "x.npz"))]
    rc = cli.main(argv + out)
    _, err = capsys.readouterr()
    assert rc == 2 and err.startswith("jaxsleigh: error: ") and "Traceback" not in err, err
    assert any(w in err for w in ("more than one run can take", "whole number of points")), err


class _Work(BaseException):
    """Raised by the stubs in place of the work: the command got past every check."""


def _no_work(*a, **k):
    raise _Work


#: where each command's work begins (stubbed: the test is about the checks before it)
WORK = [("jaxsleigh.studies.ensemble", "_run_chunks"), ("jaxsleigh.studies.optimum", "_solve_starts"), ("jaxsleigh.studies.simulate", "drive_saving"),
        ("jaxsleigh.studies.simulate", "sampled_solution"), ("jaxsleigh.tuning.optimizer", "_iterate"),
        ("jaxsleigh.tuning.pareto", "_front_vmap"), ("jaxsleigh.tuning.pareto", "_front_warm"),
        ("jaxsleigh.tuning.pareto", "random_search"), ("jaxsleigh.tuning.cma_search", "search"),
        ("jaxsleigh.tuning.law", "_adam_descent"), ("jaxsleigh.studies.bench", "c_limit"),
        ("jaxsleigh.studies.bench", "bench")]


#: what each command needs besides the option under test, its output file, and the options that name paths
#: (not numbers; left out); experiments/studies/fuzz_cli_flags.py uses them too
COMMAND_ARGS = {"simulate": ["--ic", "1,1,0.5", "--t-final", "1"],
                "basin": ["--x", "-1:1:2", "--y", "1", "--theta", "0.5", "--t-final", "1"],
                "sweep": ["--param", "k=0.1:1:2", "--samples", "2", "--t-final", "1"],
                "compare": ["--t-final", "1"], "tune": [], "bench": [], "paper": [], "controllers": [],
                "optimum": ["--samples", "1", "--horizons", "1"]}
OUTPUTS = {"simulate": "s.npz", "basin": "b.npz", "sweep": "w.npz", "compare": "c.npz", "tune": "t.json", "paper": "p",
           "optimum": "o.npz"}
PATH_OPTIONS = {"--out", "--plot", "--ics", "--gains-out", "--cache-dir", "--cache", "--history", "--json",
                "--help"}


def test_no_numeric_flag_of_any_command_shows_a_traceback(tmp_path, capsys, monkeypatch):
    """Every option of every command that takes a value, given a subnormal (1e-320) and inf: a message and exit
    code 2, or the command's work reached; never a traceback (two of these were OverflowErrors)."""
    import argparse

    monkeypatch.chdir(tmp_path)                             # a path option missed below writes here, not in the checkout
    for mod, name in WORK:
        monkeypatch.setattr(importlib.import_module(mod), name, _no_work)
    base, outputs, paths = COMMAND_ARGS, OUTPUTS, PATH_OPTIONS
    commands = next(a for a in cli.build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices
    assert set(commands) == set(base), sorted(commands)          # a new command: add it here
    failures, ran = [], 0
    for command, parser in commands.items():
        out = ["--out", str(tmp_path / outputs[command])] if command in outputs else []
        flags = [a.option_strings[-1] for a in parser._actions if a.option_strings and a.nargs != 0
                 and not isinstance(a, argparse.BooleanOptionalAction) and a.option_strings[-1] not in paths]
        for flag in flags:
            for token in ("1e-320", "inf"):
                argv = [command, *base[command], *out, flag, token]
                ran += 1
                capsys.readouterr()                         # what an earlier command said
                try:
                    rc = cli.main(argv)
                except _Work:
                    continue
                err = capsys.readouterr().err
                if rc not in (0, 2) or "Traceback" in err or (rc == 2 and not err.startswith("jaxsleigh: error: ")):
                    failures.append((argv, rc, err[-300:]))
    assert ran > 150 and not failures, failures
