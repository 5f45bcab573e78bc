"""The accuracy audit (`jaxsleigh.studies.audit`) and what the tuners do with it."""
import warnings
from types import SimpleNamespace

import numpy as np
import pytest

import jaxsleigh as js
from jaxsleigh import cli
from jaxsleigh.errors import AccuracyWarning
from jaxsleigh.studies.audit import REFERENCE_COST, REFERENCE_COST_FIXED, Audit, audit_line, audit_rows, audit_sample


def test_how_many_rows_an_audit_reruns():
    a = Audit()
    assert a.count(499) == 0 and a.count(500) == 5 and a.count(6400) == 64 and a.count(10**7) == 64
    assert Audit(rows=3).count(2) == 2 and Audit(rows=3).count(100) == 3 and Audit(rows=0).count(10**4) == 0


def _fake(energy, status=None, T=None):
    n = len(energy)
    return SimpleNamespace(status=np.zeros(n, np.int32) if status is None else np.asarray(status, np.int32),
                           T_eps=np.full(n, 5.0) if T is None else np.asarray(T, float),
                           u_energy=np.asarray(energy, float), q_final=np.zeros((n, 3)), p_final=np.zeros((n, 2)))


def test_a_row_off_its_reference_is_confirmed_at_the_tighter_tolerance():
    """The 1e-10 reference says rows 1 and 2 are off; at 1e-12 row 1 agrees with the result (1e-10 was wrong there,
    as for Aicardi's law) and row 2 does not, nor at 1e-13, which agrees with 1e-12: the audit fails on row 2 alone
    (its reference converged), and counts row 1 as unconverged."""
    result = _fake([1.0, 2.0, 3.0, 4.0])
    refs = {1e-10: {0: 1.0, 1: 2.5, 2: 3.5, 3: 4.0}, 1e-12: {1: 2.0, 2: 3.55}, 1e-13: {2: 3.56}}
    calls = []

    def rerun(rows, rtol, atol):
        calls.append((tuple(rows), rtol))
        return _fake([refs[rtol][int(i)] for i in rows])

    with pytest.warns(AccuracyWarning, match="audit of this ensemble failed"):
        rec = audit_rows(result, rerun, Audit(rows=4), what="ensemble")
    assert calls == [((0, 1, 2, 3), 1e-10), ((1, 2), 1e-12), ((2,), 1e-13)]
    assert rec["rows_confirmed"] == 2 and rec["rows_confirmed_tighter"] == 1 and rec["reference_unconverged"] == 1
    assert rec["reference_not_converged"] == 0 and not rec["passed"]
    assert rec["worst_energy_rel"] == pytest.approx(0.56 / 3.56)
    assert "FAILED" in audit_line(rec) and "2 re-run at rtol = atol = 1e-12, 1 at rtol = atol = 1e-13" in audit_line(rec)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ok = audit_rows(result, lambda rows, rtol, atol: _fake([[1.0, 2.0, 3.0, 4.0][i] * 1.01 for i in rows]),
                        Audit(rows=4))
    assert ok["passed"] and ok["rows_confirmed"] == 0 and "passed" in audit_line(ok)


def test_a_row_is_off_only_against_a_reference_that_converged():
    r"""Aicardi's law at its goal: float64 at 1e-10 chatters on every row and at 1e-12 on some (row 1: 80% off, its
    final position metres away), while 1e-13 agrees with the result. The row is not off: the result and the tightest
    reference agree, and the audit passes. Where 1e-12 and 1e-13 disagree with each other and with the result (row
    2), the audit cannot confirm the row: it is judged against 1e-13, fails, and the record says the reference did
    not converge."""
    refs = {1e-10: [59283.0, 5214.9, 2469.3], 1e-12: [80.3, 2568.2, 888.1], 1e-13: [80.3, 83.8, 400.0]}
    calls = []

    def rerun(rows, rtol, atol):
        calls.append((tuple(int(i) for i in rows), rtol))
        return _fake(np.array(refs[rtol])[rows])

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rec = audit_rows(_fake([80.3, 83.8]), rerun, Audit(rows=2))
    assert calls == [((0, 1), 1e-10), ((0, 1), 1e-12), ((1,), 1e-13)]
    assert rec["passed"] and rec["worst_energy_rel"] == 0.0 and rec["reference_unconverged"] == 2
    assert rec["reference_not_converged"] == 0
    with pytest.warns(AccuracyWarning, match=r"audit of this result failed.*StepSizeController\(rtol=1e-13, atol=1e-13\)"):
        bad = audit_rows(_fake([80.3, 83.8, 339.6]), rerun, Audit(rows=3))
    assert not bad["passed"] and bad["reference_not_converged"] == 1
    assert bad["worst_energy_rel"] == pytest.approx(60.4 / 400.0)
    assert "1 rows off a reference that did not converge (rtol = atol = 1e-12 and rtol = atol = 1e-13 disagree)" in \
        audit_line(bad)


def test_a_flagged_row_is_not_re_run_at_the_tightest_tolerance():
    """An unresolved row's figures hang on a seed below every tolerance: off at 1e-10 and 1e-12, it is judged against
    1e-12 and reported, without a 1e-13 run that would not settle it."""
    result = _fake([1.0, 2.0])
    result.unresolved = np.array([False, True])
    calls = []

    def rerun(rows, rtol, atol):
        calls.append((tuple(int(i) for i in rows), rtol))
        return _fake(np.array([1.0, 3.0])[rows])

    with pytest.warns(AccuracyWarning):
        rec = audit_rows(result, rerun, Audit(rows=2))
    assert calls == [((0, 1), 1e-10), ((1,), 1e-12)] and rec["rows_confirmed_tighter"] == 0 and not rec["passed"]


def test_a_budgeted_reference_is_held_to_its_steps():
    """A budgeted audit gives its reference at most `REFERENCE_STEPS` steps a row per step of the row in the run (more
    at tighter tolerances); a reference that runs out is not judged, the record's sample counts only the rows judged,
    and the line says so. An audit of rows asked for is not held."""
    from jaxsleigh.studies.audit import REFERENCE_STEPS

    n = 6400
    result = _fake(np.ones(n))
    result.n_steps = np.full(n, 700.0)
    result.n_steps[:10] = 70.0                        # cheap rows: the budget affords some
    asked = []

    def rerun(rows, rtol, atol, max_steps=None):
        asked.append(max_steps)
        return _fake(np.ones(len(rows)), status=np.full(len(rows), js.Status.BUDGET_EXHAUSTED),
                     T=np.full(len(rows), np.nan))

    budgeted = Audit(seed=0, budget=1.0)
    rec = audit_rows(result, rerun, budgeted)
    assert rec["rows"] > 0 and asked[0] == int(np.ceil(REFERENCE_STEPS * result.n_steps[
        audit_sample(budgeted, n, steps=result.n_steps)].max()))
    assert rec["reference_unfinished"] == rec["rows"] and rec["coverage"]["sampled_rows"] == 0
    assert "no row judged" in audit_line(rec) and f"{rec['rows']} rows not judged" in audit_line(rec)
    asked.clear()
    audit_rows(result, rerun, Audit(rows=2))
    assert asked == [None]


def test_the_record_says_what_the_audit_does_not_check():
    """A law without a per-row flag (``flag=None``: the physical chart's) is checked only by the sample: the record
    and the line say so, with the probability that the sample re-runs a row of a 2% tail. At 512 starts the budget
    affords no row, so that probability is 0; a law with a flag names what it detects and the line adds nothing."""
    from jaxsleigh.studies.audit import tail_detection

    assert tail_detection(512, 0) == 0.0 and tail_detection(100, 1) == pytest.approx(0.02)
    assert tail_detection(4096, 3) == pytest.approx(1 - (4014 * 4013 * 4012) / (4096 * 4095 * 4094))
    assert tail_detection(4096, 145) < 0.95 <= tail_detection(4096, 146)
    result = _fake(np.ones(512))
    result.n_steps = np.full(512, 700.0)            # Aicardi's rows at the defaults: no reference row fits 10%
    rec = audit_rows(result, None, Audit())
    assert rec["rows"] == 0 and rec["coverage"]["flag"].startswith("none") and rec["coverage"]["sampled_rows"] == 0
    assert rec["coverage"]["tail_2pct_detection"] == 0.0
    assert "no per-row flag for this law: a 2% tail of off rows is re-run with probability 0% (0 sampled rows)" in \
        audit_line(rec)
    flagged = audit_rows(result, None, Audit(), flag="rows whose settled (w2, p1) oscillation grew")
    assert flagged["coverage"]["flag"].startswith("rows whose") and "per-row" not in audit_line(flagged)
    two = audit_rows(result, lambda rows, rtol, atol: _fake(np.ones(len(rows))), Audit(rows=2))
    assert two["coverage"] == {"flag": rec["coverage"]["flag"], "sampled_rows": 2,
                               "tail_2pct_detection": round(tail_detection(512, 2), 4)}
    assert "probability 4% (2 sampled rows)" in audit_line(two)


def test_a_reference_computed_ahead_is_not_counted_twice():
    """``reference()`` hands over a reference that ran beside the run (its seconds are added by the caller, who
    timed it): waiting for it is not the audit's own time."""
    import time

    def ahead():
        time.sleep(0.5)
        return _fake([1.0, 2.0])

    rec = audit_rows(_fake([1.0, 2.0]), None, Audit(rows=2), reference=ahead)
    assert rec["passed"] and rec["wall_s"] < 0.25


def test_a_different_answer_fails_the_audit_but_unsettled_and_certified_unsettled_agree():
    result = _fake([1.0, 2.0, 3.0], status=[0, 0, js.Status.NOT_SETTLING], T=[5.0, np.inf, np.inf])
    def answer(status, T):
        return lambda rows, rtol, atol: _fake(np.array([1.0, 2.0, 3.0])[rows], status=np.array(status)[rows],
                                              T=np.array(T)[rows])

    assert audit_rows(result, answer([0, 0, 0], [5.0, np.inf, np.inf]), Audit(rows=3))["passed"]
    unfinished = audit_rows(result, answer([4, 0, 0], [np.nan, np.inf, np.inf]), Audit(rows=3))
    assert unfinished["passed"] and unfinished["reference_unfinished"] == 1   # a reference out of budget says nothing
    with pytest.warns(AccuracyWarning):
        rec = audit_rows(result, answer([0, 0, 0], [np.inf, np.inf, np.inf]), Audit(rows=3))
    assert rec["status_mismatch"] == 1 and not rec["passed"]


def test_what_a_run_did_not_measure_is_not_compared():
    """The plain fixed-step path (``SaveAt(summaries=False)``) has no T_eps and no energy (NaN): its OK agrees with a
    reference that settled or not, and only its final positions are judged."""
    result = _fake([np.nan] * 3, T=[np.nan] * 3)
    ref = _fake([1.0, 2.0, 3.0], T=[5.0, np.inf, np.inf])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rec = audit_rows(result, lambda rows, rtol, atol: ref, Audit(rows=3))
    assert rec["passed"] and rec["status_mismatch"] == 0 and rec["worst_T_eps_s"] == 0.0
    moved = _fake([1.0, 2.0, 3.0], T=[5.0, np.inf, np.inf])
    moved.q_final = np.full((3, 3), 0.1)
    with pytest.warns(AccuracyWarning, match=r"x64=True and StepSizeController\(rtol=1e-13") as said:
        assert not audit_rows(result, lambda rows, rtol, atol: moved, Audit(rows=3))["passed"]
    assert "fixed steps" not in str(said[0].message)
    with pytest.warns(AccuracyWarning, match="fixed steps of dt, which no tolerance changes") as said:
        audit_rows(result, lambda rows, rtol, atol: moved, Audit(rows=3), fixed_step=True)
    assert "rtol=" not in str(said[0].message) and "--rtol" not in str(said[0].message)   # (nor would it help)


def test_small_runs_say_they_were_not_audited():
    r = js.run_ensemble(np.array([[1.0, 1.0, 0.5]]), t_final=1.0, run=js.RunOptions(progress=False))
    assert r.run_info["audit"]["rows"] == 0 and "fewer than 500" in r.run_info["audit"]["why"]
    assert "audit" not in js.run_ensemble(np.array([[1.0, 1.0, 0.5]]), t_final=1.0,
                                          run=js.RunOptions(progress=False, audit=False)).run_info
    with pytest.raises(ValueError, match="audit must be"):
        js.run_ensemble(np.array([[1.0, 1.0, 0.5]]), t_final=1.0, run=js.RunOptions(audit="yes"))


@pytest.mark.slow
def test_the_audit_passes_the_defaults_and_fails_loose_tolerances():
    """The paper's law over 20 s from six starts: at the defaults every audited row agrees with float64; with fixed
    RK4 steps of 0.05 s (unstable near theta = 0 and in the transient) the audit fails and says so."""
    ics = np.array([[1.0, 1.0, 0.5], [-2.0, 1.5, -1.0], [2.5, -0.5, 2.0], [0.5, -2.0, -0.3], [-1.0, -1.0, 1.2],
                    [3.0, 2.0, -2.5]])
    run = dict(t_final=20.0, run=js.RunOptions(progress=False, audit=Audit(rows=4)))
    good = js.run_ensemble(ics, **run).run_info["audit"]
    assert good["passed"] and good["rows"] == 4 and good["worst_energy_rel"] < 1e-3
    with pytest.warns(AccuracyWarning, match="adaptive method .* or a smaller dt"):
        bad = js.run_ensemble(ics, dt=0.05, stepsize=js.StepSizeController(method="rk4"), **run).run_info["audit"]
    assert not bad["passed"]


@pytest.mark.slow
def test_a_validation_that_fails_its_audit_reports_the_resolved_figures():
    """The situation that fooled the 0.2 search: the old `balanced` gains, two starts whose settled oscillation
    spends most of their energy. At the defaults the guard resolves them and the audit passes; an audit held to
    an energy threshold no float32 run meets (1e-9) fails, and the validation's figures are then float64's at the
    audit's tolerances (what a tuner judges). That audit's references are at rtol = atol = 1e-9, not the default
    1e-10: 57% of the steps (the float64 runs of two rows are most of this test), and a tolerance of the audit's
    own, not the default, is what the figures must follow (float64 at 1e-10 is 8e-5 off them, float32 9e-4)."""
    from laws import OLD_BALANCED, OLD_BALANCED_STARTS

    from jaxsleigh.tuning.validation import validate

    ics, old = np.array(OLD_BALANCED_STARTS), js.gains(**OLD_BALANCED)
    ref = js.run_ensemble(ics, gains=old, x64=True, run=js.RunOptions(progress=False, audit=False),
                          stepsize=js.StepSizeController(rtol=1e-9, atol=1e-9, max_steps=10**6))
    loose = validate(old, ics, audit=Audit(rows=2, energy_rel=1e-9, rtol=1e-9, atol=1e-9))
    assert loose.resolved and not loose.audit["passed"]
    np.testing.assert_allclose(loose.u_energy, ref.u_energy, rtol=1e-6)
    default = validate(old, ics)                 # the guard resolves them at the defaults: no re-run needed
    assert default.audit["passed"] and not default.resolved
    np.testing.assert_allclose(default.u_energy, ref.u_energy, rtol=0.02)


def test_the_command_line_prints_the_audit(tmp_path, capsys):
    argv = ["basin", "--x", "1", "--y", "0.5:1:2", "--theta", "0.5", "--t-final", "1", "--no-progress",
            "--out", tmp_path / "b.npz"]
    assert cli.main([str(a) for a in argv + ["--audit-rows", "0"]]) in (0, 1)
    out = capsys.readouterr().out
    assert "accuracy audit: not run" in out
    assert cli.main([str(a) for a in argv[:-1] + [tmp_path / "c.npz", "--audit-rows", "2"]]) in (0, 1)
    out = capsys.readouterr().out
    assert "accuracy audit (2 rows against float64, rtol = atol = 1e-10): passed" in out


def test_the_sample_takes_the_unresolved_rows_first_and_fits_its_budget():
    """The unresolved rows come first (in a seeded order), then the others; the same rows every time. With the run's
    steps the sample is cut to what fits the budget: a reference row costs `REFERENCE_COST` times its run steps'
    share of the run."""
    n = 1000
    flags = np.zeros(n, bool)
    flags[[7, 300, 901]] = True
    rows = audit_sample(Audit(), n, unresolved=flags)
    assert rows.size == 10 and {7, 300, 901} <= set(rows.tolist())
    assert np.array_equal(rows, audit_sample(Audit(), n, unresolved=flags))
    steps = np.full(n, 100.0)
    fits = int(0.10 * n / REFERENCE_COST)                 # rows of equal steps within 10% of the run
    cut = audit_sample(Audit(), n, unresolved=flags, steps=steps)
    assert cut.size == min(10, fits) and set(cut.tolist()) <= {7, 300, 901}
    assert audit_sample(Audit(budget=None), n, unresolved=flags, steps=steps).size == 10
    # fixed steps are cheaper lane-steps: a reference row costs more of them
    assert audit_sample(Audit(), n, unresolved=flags, steps=steps, fixed_step=True).size == int(
        0.10 * n / REFERENCE_COST_FIXED)
    assert audit_sample(Audit(rows=5), n, unresolved=flags, steps=steps).size == 5     # asked for: whatever it costs


def test_a_large_run_is_taken_to_cost_less_per_lane_step():
    """Above `BATCH_STARTS` the budget takes a run's lane-steps to cost less (it batches its lanes better and keeps
    both cores busy, the reference's few lanes do not): 16,384 starts of 720 steps a row afford 6 rows, not the 10 of
    an estimate linear in the steps; 4,096 starts and fewer are unchanged. A function of N, not of the machine."""
    from jaxsleigh.studies.audit import BATCH_STARTS, run_scale

    assert run_scale(500) == run_scale(BATCH_STARTS) == 1.0 and run_scale(16384) == pytest.approx(4 ** -0.4)
    assert run_scale(65536) < run_scale(16384) < run_scale(8192) < 1.0
    assert audit_sample(Audit(), 4096, steps=np.full(4096, 720.0)).size == 2
    assert audit_sample(Audit(), 16384, steps=np.full(16384, 720.0)).size == 6
    assert audit_sample(Audit(budget=None), 16384, steps=np.full(16384, 720.0)).size == 64


def test_unresolved_rows_are_counted_warned_and_in_the_line():
    result = _fake([1.0, 2.0, 3.0, 4.0])
    result.unresolved = np.array([False, True, False, False])
    with pytest.warns(AccuracyWarning, match=r"1 of 4 rows of this ensemble are unresolved \(rows 1; result.unresolved"):
        rec = audit_rows(result, lambda rows, rtol, atol: _fake(np.array([1.0, 2.0, 3.0, 4.0])[rows]), Audit(rows=1),
                         what="ensemble", run_wall_s=10.0)
    assert rec["rows"] == 1 and rec["unresolved_rows"] == 1 and rec["unresolved_audited"] == 1 and rec["passed"]
    assert "share_of_run" in rec and "1 rows unresolved" in audit_line(rec) and "of the run)" in audit_line(rec)


#: the 0.2 release's `balanced` gains, whose settled oscillation grows from a seed below every tolerance
_GROWING = {"L": [2.153, 1.742, 2.492], "k": 0.001467, "D_hat": [[2.565, -0.0328], [-0.0328, 10.824]]}


def test_a_run_with_a_tail_of_unresolved_rows_says_so():
    """39 README starts whose oscillation stays damped under the 0.2 `balanced` gains, and one (2.5%, row 30) whose
    oscillation grows back out near the target: float32's energy of that row is 16% off float64's (1e-10), the others
    agree. A random draw of two rows (the audit before the flags) misses it and passes; the row is flagged from the
    run's own final state and summaries, the audit re-runs it first, and the run says so."""
    from jaxsleigh.tuning.starts import UniformStarts

    readme = UniformStarts()(np.random.default_rng(20240611), 256)
    good = [0, 6, 10, 14, 18, 20, 22, 24, 35, 36, 39, 54, 58, 61, 78, 80, 81, 85, 90, 93, 102, 104, 110, 112, 115,
            122, 126, 130, 135, 136, 144, 148, 149, 152, 158, 171, 172, 174, 180]
    rows = good[:30] + [21] + good[30:]           # the growing start at row 30
    old_draw = np.random.default_rng(0).choice(len(rows), size=2, replace=False)
    assert 30 not in old_draw                      # the draw of the audit before the flags passed this run
    with pytest.warns(AccuracyWarning) as said:
        r = js.run_ensemble(readme[rows], gains=js.gains(**_GROWING), t_final=100.0,
                            run=js.RunOptions(progress=False, audit=Audit(rows=2)))
    assert np.flatnonzero(r.unresolved).tolist() == [30]
    rec = r.run_info["audit"]
    assert rec["unresolved_rows"] == 1 and rec["unresolved_audited"] == 1 and not rec["passed"]
    assert rec["worst_energy_rel"] > 0.05
    assert any("1 of 40 rows of this ensemble are unresolved" in str(w.message) for w in said)
    assert "1 rows unresolved" in audit_line(rec)


def test_a_physical_chart_law_run_states_what_its_audit_covers():
    """Aicardi's law is integrated in the physical chart, which has no settled pair to test: its run's audit record
    says it has no per-row flag, and what its sample would see (nothing here: too few starts); the paper's law names
    its flag."""
    from jaxsleigh.controllers.registry import make_controller

    ics = np.array([[1.0, 1.0, 0.5], [-2.0, 1.5, -1.0]])
    r = js.run_ensemble(ics, controller=make_controller("aicardi"), t_final=1.0, run=js.RunOptions(progress=False))
    cov = r.run_info["audit"]["coverage"]
    assert cov["flag"].startswith("none") and cov["sampled_rows"] == 0 and cov["tail_2pct_detection"] == 0.0
    assert "no per-row flag for this law" in audit_line(r.run_info["audit"])
    paper = js.run_ensemble(ics, t_final=1.0, run=js.RunOptions(progress=False)).run_info["audit"]
    assert "result.unresolved" in paper["coverage"]["flag"] and "per-row" not in audit_line(paper)


#: README starts (seed 31) whose float64 reference at 1e-12 chatters about the goal in a batch of 64
#: (``experiments/studies/law_reference.py``): 1e-13 and 1e-14 agree with each other and with float32's defaults
_AICARDI_CHATTER = np.array([[-1.6663503575867429, -0.8231830715343826, 2.834346037239873],
                             [-2.4888218627870806, 0.3336374050001947, 2.7501180543954757]])


def test_the_reference_of_aicardis_law_converges_and_the_audit_passes_its_defaults():
    """Float64 at 1e-13 and 1e-14 agree on Aicardi's law (energy, T_eps, final position within the audit's
    thresholds by orders of magnitude), float32 at its defaults agrees with them, and the audit of that run, whose
    1e-10 reference chatters about the goal, starts at the law's 1e-12 and passes."""
    from jaxsleigh.controllers.registry import make_controller

    law = make_controller("aicardi")
    quiet = js.RunOptions(progress=False, audit=False)
    refs = [js.run_ensemble(_AICARDI_CHATTER, controller=law, x64=True, run=quiet,
                            stepsize=js.StepSizeController(rtol=tol, atol=tol, max_steps=10**6)) for tol in (1e-13, 1e-14)]
    np.testing.assert_allclose(refs[0].u_energy, refs[1].u_energy, rtol=1e-5)
    np.testing.assert_allclose(refs[0].T_eps, refs[1].T_eps, atol=1e-4)
    r = js.run_ensemble(_AICARDI_CHATTER, controller=law, run=js.RunOptions(progress=False, audit=Audit(rows=2)))
    np.testing.assert_allclose(r.u_energy, refs[1].u_energy, rtol=1e-3)
    rec = r.run_info["audit"]
    assert rec["passed"] and rec["reference_not_converged"] == 0 and rec["reference_unfinished"] == 0
    assert rec["reference"] == "float64, rtol = atol = 1e-12" and rec["tightest"] == "rtol = atol = 1e-14"
    assert rec["worst_energy_rel"] < 1e-3 and rec["coverage"]["flag"].startswith("none")


def test_a_law_that_float64_resolves_only_tighter_is_audited_there_at_its_cost():
    """Aicardi's law declares the loosest tolerance at which float64 resolves it (1e-12; at 1e-10 its reference
    chatters about the goal): its audit starts there, confirms at 1e-13 and 1e-14, and the budget counts those rows
    (100)^(1/5) times dearer, so a 4,096-start run of 720 steps a row affords 1 row, not the 2 of a law audited at
    1e-10. The laws that declare nothing keep the default ladder and rows."""
    from jaxsleigh.controllers.registry import make_controller
    from jaxsleigh.model.controller import PerTrajectory
    from jaxsleigh.studies.audit import for_law

    a = for_law(Audit(), make_controller("aicardi"))
    assert (a.rtol, a.atol, a.confirm_tol, a.tightest_tol) == (1e-12, 1e-12, 1e-13, 1e-14)
    assert for_law(Audit(), PerTrajectory(make_controller("aicardi"))) == a
    for name in ("astolfi", "samson"):
        assert for_law(Audit(), make_controller(name)) == Audit()
    assert for_law(None, make_controller("aicardi")) is None
    assert for_law(Audit(rtol=1e-13, atol=1e-13), make_controller("aicardi")).rtol == 1e-13
    steps = np.full(4096, 720)
    assert audit_sample(Audit(), 4096, steps=steps).size == 2
    assert audit_sample(a, 4096, steps=steps).size == 1


def test_the_law_check_compiles_once_per_kind_of_law():
    """Every front checks a law at a test point under jit, the audit's float64 references included (one call per
    rung of its ladder): that check is compiled once per kind of law, not at every call, where it cost the laws of
    the physical chart 0.1-0.2 s a call, more than their reference rows."""
    from jaxsleigh.controllers.registry import make_controller
    from jaxsleigh.model.controller import _at_test_point, as_controller

    for name in ("aicardi", "astolfi"):
        law = make_controller(name)
        as_controller(law)
        size = _at_test_point._cache_size()
        as_controller(make_controller(name))
        as_controller(law._replace(**{law._fields[0]: getattr(law, law._fields[0]) * 2.0}))
        assert _at_test_point._cache_size() == size


def test_a_validation_resolved_in_float64_uses_the_tolerance_its_law_needs(monkeypatch):
    """A validation whose audit fails re-runs every start in float64 at the audit's reference tolerance: for a law
    that float64 resolves only tighter (Aicardi's declares 1e-12), at that tolerance, as the audit itself does, not
    at the 1e-10 where its reference chatters."""
    from jaxsleigh.controllers.registry import make_controller
    from jaxsleigh.tuning import validation

    seen = []
    real = validation.run_ensemble

    def spy(*args, **kw):
        seen.append(kw.get("stepsize"))
        return real(*args, **kw)

    monkeypatch.setattr(validation, "run_ensemble", spy)
    ics = np.array([[1.0, 1.0, 0.5], [-2.0, 1.5, -1.0]])
    v = validation.validate(make_controller("aicardi"), ics, t_final=1.0, audit=Audit(rows=2, energy_rel=1e-12))
    assert v.resolved and len(seen) == 2
    assert seen[1].rtol == seen[1].atol == 1e-12
