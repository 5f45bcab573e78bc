"""``jaxsleigh tune`` beyond the paper's gains: a law behind an actuator or from the literature keeps its progress on
Ctrl-C and resumes to the same law, writes its history, names the flag that differs when a resume is refused, says
when the energy budget is not met, and writes a file that the other commands read back."""
from __future__ import annotations

import json

import numpy as np
import pytest

import jaxsleigh as js
from jaxsleigh.cli import main as cli_main
from jaxsleigh.cli.common import EXIT_INTERRUPTED, EXIT_NONE_OK

#: the smallest law tuning worth running: 2 starts, 2 s, float64 (for bitwise comparisons)
TINY = ["--batch", "2", "--t-final", "2", "--x64", "--validate", "0", "--no-progress"]


def _run(argv, capsys):
    rc = cli_main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def _interrupt_after(monkeypatch, n: int) -> None:
    """Ctrl-C just before the law tuner's step ``n`` (0-based), as a user's would arrive between two steps."""
    from jaxsleigh.tuning import law as law_mod

    real = law_mod._Descent._step

    def step(self, step_fn, it, *rest):
        if it == n:
            raise KeyboardInterrupt
        return real(self, step_fn, it, *rest)

    monkeypatch.setattr(law_mod._Descent, "_step", step)


def test_saturated_tuning_interrupted_keeps_its_progress_and_resumes_to_the_same_gains(tmp_path, capsys, monkeypatch):
    whole, out, hist = tmp_path / "whole.json", tmp_path / "t.json", tmp_path / "h.npz"
    base = ["tune", "--saturation", "20", "--steps", "3", *TINY]
    rc, _, err = _run([*base, "--out", whole], capsys)
    assert rc == 0, err
    with monkeypatch.context() as m:
        _interrupt_after(m, 2)
        rc, _, err = _run([*base, "--out", out, "--history", hist], capsys)
    assert rc == EXIT_INTERRUPTED and "--resume" in err, err
    assert json.loads(out.read_text())["meta"]["interrupted"] is True
    assert (tmp_path / "t.json.ckpt.npz").exists()
    with np.load(hist) as z:
        assert len(z["loss"]) == 2
    rc, _, err = _run([*base, "--out", out, "--history", hist], capsys)          # not over it, silently
    assert rc == 2 and "--resume" in err
    rc, _, err = _run([*base, "--out", out, "--history", hist, "--resume"], capsys)
    assert rc == 0, err
    a, b = json.loads(whole.read_text()), json.loads(out.read_text())
    for k in ("L", "k", "D_hat"):
        assert a[k] == b[k]                                                     # bit for bit (JSON keeps every digit)
    assert a["meta"]["history"] == b["meta"]["history"] and "interrupted" not in b["meta"]
    assert b["meta"]["actuator"]["saturation"] == 20.0
    with np.load(hist) as z:
        np.testing.assert_array_equal(z["loss"], a["meta"]["history"]["loss"])
    assert not (tmp_path / "t.json.ckpt.npz").exists()
    assert js.load_gains(out).k == a["k"]                                        # a gains file, for --gains


def test_a_refused_resume_names_the_flag_that_differs_first(tmp_path, capsys, monkeypatch):
    out = tmp_path / "t.json"
    base = ["tune", "--controller", "astolfi", "--steps", "2", "--out", out, *TINY]
    with monkeypatch.context() as m:
        _interrupt_after(m, 1)
        rc, _, err = _run([*base, "--saturation", "20"], capsys)
    assert rc == EXIT_INTERRUPTED, err
    rc, _, err = _run([*base, "--saturation", "30", "--resume"], capsys)
    first = err.splitlines()[0]
    assert rc == 2 and first.startswith("jaxsleigh: error: --saturation 20.0 in the checkpoint vs --saturation "
                                        "30.0 now: "), err
    assert "choose another --out" in first and "{" not in err
    rc, _, err = _run([*base, "--resume"], capsys)
    assert rc == 2 and "--saturation 20.0 in the checkpoint vs no --saturation now" in err


def test_a_budget_that_is_not_met_is_said_flagged_and_exits_3(tmp_path, capsys):
    out = tmp_path / "t.json"
    rc, _, err = _run(["tune", "--controller", "astolfi", "--steps", "2", "--out", out, "--energy-budget", "1e-9",
                       *TINY], capsys)
    meta = json.loads(out.read_text())["meta"]
    assert rc == EXIT_NONE_OK and meta["energy_budget_met"] is False and meta["energy_budget"] == 1e-9
    line = next(ln for ln in err.splitlines() if "--energy-budget" in ln)
    assert f"{meta['training_energy']:.4g}" in line and "--energy-budget 1e-09" in line and "not meet" in line


def test_a_tuned_law_is_checked_on_held_out_starts_by_the_accurate_engine_and_audited(tmp_path, capsys):
    """Like the paper's gains, a tuned law is measured on starts the tuner never saw, with the accurate engine, and
    that check is audited in float64: its figures are in the law's file and in the printed table."""
    out = tmp_path / "t.json"
    argv = ["tune", "--controller", "astolfi", "--steps", "1", "--out", out, "--batch", "2", "--t-final", "2",
            "--validate", "3", "--atol", "1e-7", "--no-progress"]
    rc, printed, err = _run(argv, capsys)
    assert rc == 0, err
    v = json.loads(out.read_text())["meta"]["validation"]
    assert set(v) == {"initial", "tuned"}
    for row in v.values():
        assert row["n"] == 3 and row["seed"] == 1000 and row["audit"]["rows"] == 3
        assert isinstance(row["audit"]["passed"], bool) and row["median_energy"] > 0
    assert "| initial |" in printed and "| tuned |" in printed


def test_gradient_tuning_records_its_held_out_check_under_every_tuners_names(tmp_path, capsys):
    """A tiny gradient tuning's held-out validation is written under the names of `jaxsleigh.tuning.validation_dict`
    that the search and a tuned law's file use too, audit included."""
    from jaxsleigh import tuning as tu

    out = tmp_path / "g.json"
    rc, _, err = _run(["tune", "--steps", "1", "--batch", "4", "--t-final", "5", "--n-attempts", "2000", "--tune", "k",
                       "--validate", "2", "--no-progress", "--out", out], capsys)
    assert rc == 0, err
    v = tu.validate("paper", np.array([[1.0, 1.0, 0.5]]), t_final=2.0, progress=False,
                    stepsize=js.StepSizeController(atol=1e-7))
    rows = json.loads(out.read_text())["meta"]["validation"]
    assert set(rows) == {"initial", "tuned"}
    for row in rows.values():
        assert set(row) == set(tu.validation_dict(v)) | {"seed", "rtol", "atol"}


def test_gradient_tuning_that_misses_its_budget_says_so(tmp_path, capsys):
    out = tmp_path / "g.json"
    rc, _, err = _run(["tune", "--out", out, "--steps", "2", "--batch", "4", "--t-final", "5", "--n-attempts", "2000",
                       "--tune", "k", "--validate", "0", "--energy-budget", "1e-9", "--no-progress"], capsys)
    meta = json.loads(out.read_text())["meta"]
    assert rc == EXIT_NONE_OK and meta["energy_budget_met"] is False, err
    assert f"training energy is {meta['training_energy']:.4g}" in err and "--energy-budget 1e-09" in err


def test_a_tuned_law_file_is_read_back_as_the_law(tmp_path, capsys):
    from jaxsleigh.controllers.registry import make_controller
    from jaxsleigh.tuning.law_file import load_controller_record

    out = tmp_path / "a.json"
    rc, _, err = _run(["tune", "--controller", "astolfi", "--steps", "2", "--out", out, *TINY], capsys)
    assert rc == 0, err
    law = load_controller_record(out)
    doc = json.loads(out.read_text())
    assert type(law) is type(make_controller("astolfi"))
    assert [law.k, law.p2, law.p3, law.K] == [doc["params"][n] for n in ("k", "p2", "p3", "K")]
    assert law.k != make_controller("astolfi").k                                  # the tuned gains, not the defaults
    starts = np.array([[1.0, 1.0, 0.5]])
    r = js.run_ensemble(starts, controller=law, t_final=1.0)
    assert np.all(r.status == 0)
    rc, _, err = _run(["simulate", "--controller", out, "--ic", "1,1,0.5", "--t-final", "1", "--out",
                       tmp_path / "s.npz"], capsys)                      # the command line reads it too
    assert rc == 0, err
    with np.load(tmp_path / "s.npz") as z:
        np.testing.assert_allclose(z["q"][0, -1], r.q_final[0], rtol=1e-5, atol=1e-6)
    bad = dict(doc, params={**doc["params"], "q": 1.0})
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    with pytest.raises(ValueError, match="unknown q"):
        load_controller_record(tmp_path / "bad.json")
    (tmp_path / "who.json").write_text(json.dumps(dict(doc, controller="nobody")))
    with pytest.raises(ValueError, match="unknown controller 'nobody'"):
        load_controller_record(tmp_path / "who.json")


def test_an_invalid_starting_law_is_explained_in_command_line_terms(tmp_path, capsys):
    # 20 attempts: the fewest the up-front check lets through for 2 s (steps of at most 10 x --dt), too few to get there
    rc, _, err = _run(["tune", "--controller", "astolfi", "--steps", "1", "--out", tmp_path / "a.json",
                       "--n-attempts", "20", *TINY], capsys)
    assert rc == 2 and "--n-attempts" in err and "jaxsleigh simulate --controller astolfi" in err, err
    assert "jaxsleigh.run_ensemble" not in err


#: a gradient tuning of the paper's k small enough to interrupt in seconds
GRADIENT = ["tune", "--steps", "2", "--batch", "4", "--t-final", "5", "--n-attempts", "2000", "--tune", "k",
            "--validate", "0", "--no-progress"]


def test_a_refused_gradient_resume_names_the_flag_not_the_settings(tmp_path, capsys, monkeypatch):
    from jaxsleigh.tuning import optimizer

    real = optimizer._Bar.update

    def interrupt(self, it, row):
        real(self, it, row)
        raise KeyboardInterrupt

    out = tmp_path / "g.json"
    with monkeypatch.context() as m:
        m.setattr(optimizer._Bar, "update", interrupt)
        rc, _, err = _run([*GRADIENT, "--out", out], capsys)
    assert rc == EXIT_INTERRUPTED, err
    rc, _, err = _run([*GRADIENT, "--out", out, "--lr", "0.1", "--resume"], capsys)
    assert rc == 2 and err.startswith("jaxsleigh: error: --lr 0.05 in the checkpoint vs --lr 0.1 now"), err
    assert "config." not in err and "{" not in err


def test_the_gradient_tuners_advice_names_flags(tmp_path, capsys):
    # 50 attempts: the fewest the up-front check lets through for 5 s, too few for the starts to get there
    rc, _, err = _run([*GRADIENT[:8], "50", *GRADIENT[9:], "--out", tmp_path / "g.json"], capsys)
    assert rc == 2 and "not a valid candidate" in err and "raise --n-attempts, shorten --t-final" in err, err
    assert "n_attempts" not in err and "t_final" not in err


def test_a_vmapped_front_resumes_only_from_its_checkpoint_and_never_writes_over_an_interrupted_front(tmp_path,
                                                                                                      capsys):
    out = tmp_path / "f.json"
    rc, _, err = _run(["tune", "--pareto", "2", "--front-method", "vmap", "--resume", "--out", out, "--no-progress"],
                      capsys)
    assert rc == 2 and "--resume: no checkpoint" in err and "f.json.ckpt.npz" in err, err
    kept = '{"method": "warm", "interrupted": true, "points": []}'
    out.write_text(kept)                                   # the finished points of an interrupted warm front
    rc, _, err = _run(["tune", "--pareto", "2", "--front-method", "vmap", "--steps", "1", "--batch", "4", "--t-final",
                       "2", "--n-attempts", "500", "--validate", "0", "--out", out, "--no-progress"], capsys)
    assert rc == 2 and "holds the finished points of an interrupted front" in err and out.read_text() == kept, err
