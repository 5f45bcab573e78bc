"""The controllers by name (``--controller``, ``jaxsleigh controllers``) and the comparison (``jaxsleigh compare``,
`jaxsleigh.studies.compare`)."""
from __future__ import annotations

import json

import numpy as np
import pytest

import jaxsleigh as js
from jaxsleigh.cli import main
from jaxsleigh.controllers.actuators import sampler
from jaxsleigh.controllers.registry import CONTROLLERS, controller_class, make_controller
from jaxsleigh.studies.compare import METRICS, _pct, compare, draw_compare_starts


def _run(argv, capsys):
    code = main(argv)
    out = capsys.readouterr()
    return code, out.out, out.err


def test_controllers_lists_every_law_with_its_citation(capsys):
    code, out, _ = _run(["controllers"], capsys)
    lines = out.strip().splitlines()
    assert code == 0 and [ln.split()[0] for ln in lines] == list(CONTROLLERS)
    for name, line in zip(CONTROLLERS, lines):
        cls = controller_class(name)
        assert cls.citation in line and ("nothing" in line) == (cls.needs == ())


def test_every_named_law_is_a_valid_controller_and_runs():
    ics = np.array([[1.0, 1.0, 0.5], [-2.0, 1.0, -1.0]])
    for name in CONTROLLERS:
        law = make_controller(name)
        r = js.run_ensemble(ics, **({"gains": law} if name == "paper" else {"controller": law}), t_final=5.0)
        assert np.all(r.status == js.Status.OK) and np.all(np.isfinite(r.q_final)), name
        assert np.all(np.isfinite(r.u_energy) & (r.u_energy > 0)), name      # each law acts (its own claims:
        # tests/test_literature_*.py)


def test_unknown_controller_is_named_with_the_choices(capsys):
    code, _, err = _run(["simulate", "--controller", "pid", "--ic", "1,1,0.5", "--out", "never.npz"], capsys)
    assert code == 2 and "unknown controller 'pid'" in err and "aicardi" in err


def test_gains_do_not_apply_to_another_law(capsys, tmp_path):
    code, _, err = _run(["simulate", "--controller", "astolfi", "--gains", "tuned", "--ic", "1,1,0.5",
                         "--out", str(tmp_path / "s.npz")], capsys)
    assert code == 2 and "--gains" in err


def test_simulate_with_saturation_keeps_u_within_the_bound(capsys, tmp_path):
    out = tmp_path / "s.npz"
    code, _, _ = _run(["simulate", "--saturation", "3", "--ic=-3,-2,pi/8", "--t-final", "5", "--out", str(out)],
                      capsys)
    u = np.load(out)["u"]
    assert code == 0 and np.nanmax(np.abs(u)) <= 3.0 + 1e-6 and np.nanmax(np.abs(u)) > 2.9   # the bound is hit
    code, _, err = _run(["simulate", "--saturation", "-1", "--ic", "1,1,0.5", "--out", str(out)], capsys)
    assert code == 2 and "--saturation" in err


def test_percentile_is_an_order_statistic_with_infinities():
    assert _pct([1.0, 2.0, np.inf, np.inf], 50) == 2.0
    assert _pct([1.0, np.inf, np.inf, np.inf], 50) == np.inf
    assert np.isnan(_pct([np.nan], 50))


def test_starts_are_reproducible_and_distinct_per_distribution():
    a, b = draw_compare_starts("wide", 8, 3), draw_compare_starts("wide", 8, 3)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(draw_compare_starts("uniform", 8, 3)[:, :2], a[:, :2])
    near = draw_compare_starts("near", 64, 0)
    assert np.all((np.abs(near[:, 2]) >= 0.05) & (np.abs(near[:, 2]) <= 0.3)) and np.all(near[:, 3:] == 0)
    assert np.any(a[:, 3:] != 0)
    with pytest.raises(ValueError, match="unknown start distribution"):
        draw_compare_starts("far", 4, 0)


def test_compare_rows_measure_what_the_ensemble_measures():
    ics = draw_compare_starts("uniform", 6, 1)
    rows = compare({"paper": js.paper_gains()}, {"u": ics}, t_final=60.0)
    r = js.run_ensemble(ics, t_final=60.0)
    (row,) = rows
    assert set(METRICS) <= set(row) and row["n"] == 6
    assert row["settled"] == pytest.approx(np.mean(r.converged))
    assert row["energy_p90"] == pytest.approx(np.percentile(r.u_energy, 90, method="inverted_cdf"))
    assert row["u_peak_max"] == pytest.approx(r.u_norm_peak.max())


def test_compare_under_actuators_changes_the_numbers():
    ics = draw_compare_starts("uniform", 4, 2)
    laws = {"paper": js.paper_gains()}
    free = compare(laws, {"u": ics}, t_final=20.0)[0]
    sat = compare(laws, {"u": ics}, t_final=20.0, saturation=1.0)[0]
    assert sat["u_peak_max"] <= np.sqrt(2) * 1.0 + 1e-6 < free["u_peak_max"]
    held = compare(laws, {"u": ics}, t_final=20.0, sampler=sampler(0.5), substeps=50)[0]
    fine = compare(laws, {"u": ics}, t_final=20.0, sampler=sampler(0.005), substeps=2)[0]
    assert fine["energy_p50"] == pytest.approx(free["energy_p50"], rel=0.1)
    assert abs(held["energy_p50"] - free["energy_p50"]) > 0.1 * free["energy_p50"]


def test_compare_takes_the_engine_tolerance():
    """Compare's rows follow the tolerance they are given (they are run_ensemble's at that tolerance); under the gains
    `balanced` had until 2026-11, whose energy after settling once needed atol 1e-8 in float32, the default row now
    agrees with it (docs/evidence/settled-phase.md)."""
    from laws import OLD_BALANCED, OLD_BALANCED_STARTS

    ics, old = np.array(OLD_BALANCED_STARTS), js.gains(**OLD_BALANCED)
    tight = js.StepSizeController(atol=1e-8)
    loose_row, = compare({"old": old}, {"u": ics}, t_final=100.0)
    tight_row, = compare({"old": old}, {"u": ics}, t_final=100.0, stepsize=tight)
    r = js.run_ensemble(ics, gains=old, t_final=100.0, stepsize=tight)
    assert tight_row["energy_p90"] == pytest.approx(np.percentile(r.u_energy, 90, method="inverted_cdf"))
    assert loose_row["energy_p50"] == pytest.approx(tight_row["energy_p50"], rel=0.02)


def test_compare_command_writes_rows_and_a_figure(capsys, tmp_path):
    argv = ["compare", "--controllers", "paper,astolfi", "--starts", "uniform,near", "--samples", "3",
            "--t-final", "10", "--seed", "4"]
    code, out, _ = _run(argv + ["--out", str(tmp_path / "a.json"), "--plot", str(tmp_path / "a.png")], capsys)
    assert code == 0 and (tmp_path / "a.png").stat().st_size > 0
    a = json.loads((tmp_path / "a.json").read_text())
    assert [(r["controller"], r["starts"]) for r in a["rows"]] == [("paper", "uniform"), ("paper", "near"),
                                                                     ("astolfi", "uniform"), ("astolfi", "near")]
    assert a["settings"]["seed"] == 4 and a["command"][:2] == ["jaxsleigh", "compare"]
    assert a["settings"]["atol"] is None and a["settings"]["rtol"] is None
    _run(argv + ["--out", str(tmp_path / "b.json")], capsys)
    assert json.loads((tmp_path / "b.json").read_text())["rows"] == a["rows"]      # same seed, same numbers


def _strict(text: str):
    """``json.loads`` that refuses the non-standard constants ``Infinity``, ``-Infinity`` and ``NaN``."""
    def refuse(name):
        raise ValueError(f"not JSON: {name}")
    return json.loads(text, parse_constant=refuse)


@pytest.fixture(scope="module")
def default_run(tmp_path_factory):
    """``jaxsleigh compare`` with its default laws, tiny: 4 starts per distribution, 5 s (the near starts do not
    settle that soon), with the figure. Returns (exit code, stdout, JSON text, figure path)."""
    import contextlib
    import io

    d = tmp_path_factory.mktemp("compare")
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = main(["compare", "--starts", "near,uniform", "--samples", "4", "--t-final", "5", "--seed", "1",
                     "--out", str(d / "c.json"), "--plot", str(d / "c.png")])
    return code, out.getvalue(), (d / "c.json").read_text(), d / "c.png"


def test_compare_defaults_to_every_listed_law(default_run):
    from jaxsleigh.controllers.registry import controller_names

    code, _, text, _ = default_run
    rec = json.loads(text)
    assert code == 0 and "shaped" in controller_names()
    assert rec["settings"]["controllers"] == controller_names()
    assert list(dict.fromkeys(r["controller"] for r in rec["rows"])) == controller_names()


def test_compare_writes_strict_json_with_null_for_what_did_not_settle(default_run):
    _, _, text, _ = default_run
    rec = _strict(text)                                  # raises on Infinity / NaN
    near = [r for r in rec["rows"] if r["starts"] == "near" and r["controller"] == "paper"]
    assert near and near[0]["settled"] == 0.0 and near[0]["median_T"] is None and near[0]["p90_T"] is None
    for r in rec["rows"]:
        T, E = r["per_start"]["T_eps"], r["per_start"]["energy"]
        assert len(T) == len(E) == r["n"] == 4
        assert sum(t is not None for t in T) == round(r["settled"] * r["n"])       # null: did not settle
        assert all(t is None or 0 <= t <= 5.0 for t in T) and all(e is None or e > 0 for e in E)


def test_compare_rows_on_stdout_say_the_settled_share(default_run):
    code, out, text, _ = default_run
    rec = json.loads(text)
    lines = [ln for ln in out.splitlines() if "settled" in ln]
    assert code == 0 and len(lines) == len(rec["rows"])
    for line, r in zip(lines, rec["rows"]):
        k = round(r["settled"] * r["n"])
        assert line.split()[:2] == [r["controller"], r["starts"]]
        assert f"settled {k}/{r['n']} ({100 * r['settled']:.1f}%) by 5 s" in line
        if r["median_T"] is None:
            assert "median T_0.05 >5 s" in line
        else:
            assert f"median T_0.05 {r['median_T']:.3g} s" in line


def test_compare_row_lines_tell_unsettled_and_diverged_apart_from_undefined():
    from jaxsleigh.cli.compare import row_lines

    row = {"controller": "astolfi", "starts": "wide", "n": 4, "settled": 0.25, "median_T": np.inf, "p90_T": np.inf,
           "energy_p50": 12.0, "energy_p90": np.inf, "u_peak_max": np.inf}
    (line,) = row_lines([row], eps=0.05, t_final=100.0)
    assert "settled 1/4 (25.0%) by 100 s" in line and "median T_0.05 >100 s" in line
    assert "energy p50/p90 12 / inf N² s" in line and "peak |u| inf" in line
    (line,) = row_lines([dict(row, energy_p50=np.nan, energy_p90=np.nan, u_peak_max=np.nan)], eps=0.05,
                        t_final=100.0)
    assert "energy p50/p90 n/a / n/a" in line and "peak |u| n/a" in line


def test_compare_figure_shows_each_law_as_distributions(default_run):
    """The default figure: per start distribution, the ECDF of T_eps (ending at the settled share) and of the
    energy (log axis), every law in the legend, units on the axes, the settings and the command in the title."""
    from jaxsleigh.plots.base import STAMP_GID
    from jaxsleigh.plots.compare import plot_compare_ecdf

    _, _, text, png = default_run
    rec = json.loads(text)
    assert png.stat().st_size > 0
    fig = plot_compare_ecdf(rec)
    laws = list(dict.fromkeys(r["controller"] for r in rec["rows"]))
    axes = fig.axes
    assert len(axes) == 2 * 2                              # two distributions, two panels each
    for d, (ax_t, ax_e) in zip(["near", "uniform"], zip(axes[::2], axes[1::2])):
        rows = {r["controller"]: r for r in rec["rows"] if r["starts"] == d}
        assert ax_t.get_title(loc="left").startswith(f"{d} starts")
        assert [ln.get_label().split(":")[0] for ln in ax_t.get_lines() if not ln.get_label().startswith("_")] == laws
        assert [t.get_text().split(":")[0] for t in ax_t.get_legend().get_texts()] == laws
        for ln in [ln for ln in ax_t.get_lines() if not ln.get_label().startswith("_")]:
            r = rows[ln.get_label().split(":")[0]]
            assert ln.get_ydata()[-1] == pytest.approx(r["settled"])      # unsettled starts never reach 1
            assert ln.get_xdata()[-1] == 5.0
        assert "[s]" in ax_t.get_xlabel() and "settled" in ax_t.get_ylabel()
        assert ax_e.get_xscale() == "log" and "N² s" in ax_e.get_xlabel()
    title = fig.get_suptitle()
    assert "4 starts per distribution" in title and "float32" in title and "horizon T = 5 s" in title
    assert "jaxsleigh compare --starts near,uniform" in title
    assert "None" not in title and "saturation" not in title and "hold" not in title
    stamp = [t.get_text() for t in fig.texts if t.get_gid() == STAMP_GID][0]
    assert "method unknown" not in stamp and "adaptive RK4" in stamp
    rec["settings"].update(saturation=20.0, sample_period=0.05)
    title = plot_compare_ecdf(rec).get_suptitle()
    assert "saturation |u_i| ≤ 20" in title and "zero-order hold every 0.05 s" in title


def test_compare_refuses_a_sample_count_beyond_its_bound_before_any_work(capsys, tmp_path, monkeypatch):
    import jaxsleigh.studies.compare as study

    def never(*a, **k):
        raise AssertionError("the starts were drawn: the bound was not checked first")
    monkeypatch.setattr(study, "draw_compare_starts", never)
    code, _, err = _run(["compare", "--samples", "2000000000", "--out", str(tmp_path / "x.json")], capsys)
    assert code == 2 and "--samples must be <= 100000" in err and not (tmp_path / "x.json").exists()


def test_compare_refuses_a_horizon_too_long_naming_its_own_flag(capsys, tmp_path, monkeypatch):
    import jaxsleigh.studies.compare as study

    def never(*a, **k):
        raise AssertionError("the starts were drawn: the horizon was not checked first")
    monkeypatch.setattr(study, "draw_compare_starts", never)
    code, _, err = _run(["compare", "--t-final", "1e9", "--out", str(tmp_path / "x.json")], capsys)
    assert code == 2 and "--t-final 1e+09 s" in err and "at most 500000 s" in err and "shorter --t-final" in err
    assert "--dt" not in err and "larger dt" not in err         # compare has no --dt to change
    with pytest.raises(ValueError, match="t_final"):
        compare({"paper": js.paper_gains()}, {"u": draw_compare_starts("uniform", 2, 0)}, t_final=1e9)


def test_compare_help_names_every_law_null_and_no_dt(capsys):
    """The help lists the default laws from the registry, says what null means, and names no --dt (compare
    has none: its sampled loop steps to the tolerances, landing on each sample instant)."""
    from jaxsleigh.controllers.registry import controller_names

    code, out, _ = _run(["compare", "--help"], capsys)
    text = " ".join(out.split())
    assert code == 0 and ",".join(controller_names()) in text and "null" in text and "did not settle" in text
    assert "--dt" not in text and "landing on each sample instant" in text


def test_compare_equal_energy_tunes_the_literature_laws_to_the_papers_budget(capsys, tmp_path):
    """--equal-energy: the budget is the paper's training energy on the tuner's training starts; the paper's
    gains stay as published, shaped keeps its preset, Astolfi's law is tuned and compared tuned."""
    from jaxsleigh import tuning
    from jaxsleigh.model.controller import controller_record

    code, out, _ = _run(["compare", "--equal-energy", "--train", "2", "--steps", "2", "--controllers",
                         "paper,astolfi,shaped", "--starts", "uniform", "--samples", "2", "--t-final", "5",
                         "--out", str(tmp_path / "e.json")], capsys)
    rec = _strict((tmp_path / "e.json").read_text())
    eq = rec["equal_energy"]
    budget = tuning.training_energy("paper", config=tuning.TuneConfig(batch=2, seed=0),
                                    loss=tuning.LossConfig(t_final=30.0))["energy"]
    assert code == 0 and eq["budget"] == pytest.approx(budget, rel=1e-6) and f"budget {budget:.4g}" in out
    assert eq["settings"]["train"] == 2 and eq["settings"]["steps"] == 2 and rec["settings"]["equal_energy"]
    laws = eq["laws"]
    assert laws["paper"] == {"as": "published", "law": controller_record(js.paper_gains())}
    assert laws["shaped"] == {"as": "preset", "law": controller_record(make_controller("shaped"))}
    assert laws["astolfi"]["as"] == "tuned" and laws["astolfi"]["steps"] == 2
    # the tuning's wall time varies between runs: in the sidecar, not in the table
    assert "wall_s" not in laws["astolfi"]
    assert json.loads((tmp_path / "e.run.json").read_text())["tuning_wall_s"]["astolfi"] > 0
    default = controller_record(make_controller("astolfi"))["params"]
    tuned = laws["astolfi"]["law"]["params"]
    assert tuned[".k"] != default[".k"] and tuned[".model.m"] == default[".model.m"]     # gains move, the model stays
    (row,) = [r for r in rec["rows"] if r["controller"] == "astolfi"]
    (untuned,) = compare({"astolfi": make_controller("astolfi")}, {"uniform": draw_compare_starts("uniform", 2, 0)},
                         t_final=5.0)
    assert row["energy_p50"] != pytest.approx(untuned["energy_p50"], rel=1e-3)        # the tuned law was compared


@pytest.mark.parametrize("extra, message", [
    (["--controllers", "paper,lqr"], "--controllers"),
    (["--starts", "far"], "--starts"),
    (["--delay", "1"], "--sample-period"),
    (["--sample-period", "0.3"], "whole number"),
    (["--noise", "-1"], "--noise"),
    (["--atol", "0"], "--atol must be a finite number > 0"),
    (["--train", "4"], "add --equal-energy"),
])
def test_compare_refuses_bad_options_naming_them(capsys, tmp_path, extra, message):
    code, _, err = _run(["compare", "--samples", "2", "--t-final", "10", "--out", str(tmp_path / "x.json")] + extra,
                        capsys)
    assert code == 2 and message in err and not (tmp_path / "x.json").exists()


def test_near_the_singular_set_nothing_turns_nan_silently():
    """The paper's law evaluated from measurements (PaperLaw, no w chart) and its saturated version, from theta0 = 0,
    1e-8 and 1e-3: a row is either OK with a finite state or flagged with NaN outputs, in the engine, in simulate
    and in the sampled loop; compare counts the flagged rows as failed and never as settled."""
    from jaxsleigh.controllers.paper import PaperLaw
    from jaxsleigh.controllers.actuators import saturate
    from jaxsleigh.integrate.sampled import solve_sampled

    ics = np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 1e-8], [1.0, 1.0, 1e-3]])
    for law in (PaperLaw(), saturate(js.paper_gains(), 5.0)):
        r = js.run_ensemble(ics, controller=law, t_final=5.0)
        s = js.simulate(ics, controller=law, t_final=2.0)
        ss = solve_sampled(law, None, ics, t_final=5.0, sampler=sampler(0.1))
        for status, final in ((r.status, r.q_final), (s.status, s.q[:, -1]),
                              (np.asarray(ss.status), np.asarray(ss.q_final))):
            ok = status == js.Status.OK
            assert np.all(np.isfinite(final[ok])) and np.all(np.isnan(final[~ok])), (law, status)
        assert r.status[0] != js.Status.OK                  # theta0 = 0 exactly: the law is undefined there
        (row,) = compare({"p": law}, {"s": ics}, t_final=5.0)
        assert row["failed"] == int(np.sum(r.status != js.Status.OK)) and row["settled"] == 0.0


def test_gain_names_leave_out_the_plant_model_and_the_actuator_bound():
    from jaxsleigh.controllers.actuators import saturate
    from jaxsleigh.tuning import gain_names

    assert gain_names(make_controller("astolfi")) == ["k", "p2", "p3", "K"]
    assert gain_names(saturate(make_controller("samson"), 5.0)) == ["law.k1", "law.k2", "law.k3", "law.alpha",
                                                                      "law.nu", "law.K"]


def test_tuning_keeps_declared_positive_gains_positive():
    """A law's ``positive`` gains are tuned as logarithms: a large first step that would take k through zero
    cannot (Aicardi's law, whose Lyapunov argument needs k, h > 0)."""
    from jaxsleigh.model.controller import positive_names
    from jaxsleigh.tuning import LossConfig, tune_law
    from jaxsleigh.controllers.actuators import saturate

    law = make_controller("aicardi")
    assert positive_names(law) == {"gamma", "k", "h", "K"}
    assert positive_names(saturate(law, 5.0)) == {"law.gamma", "law.k", "law.h", "law.K"}
    starts = draw_compare_starts("uniform", 4, 5)[:, :3]
    res = tune_law(law, starts, loss=LossConfig(t_final=5.0, energy_budget=1.0), steps=3, lr=2.0)
    assert all(float(getattr(res.law, n)) > 0 for n in ("gamma", "k", "h", "K"))
    with pytest.raises(ValueError, match="must be > 0"):
        tune_law(law._replace(k=-1.0), starts, loss=LossConfig(t_final=5.0), steps=1)


def _failing_rows(laws, starts, **_):
    """`compare`'s rows where every start of ``samson`` ended NONFINITE and the others OK (no run)."""
    from jaxsleigh.studies.compare import _row

    rows = []
    for name in laws:
        for sname, ics in starts.items():
            n = len(ics)
            status = np.full(n, js.Status.NONFINITE if name == "samson" else js.Status.OK)
            T = np.full(n, np.nan if name == "samson" else 3.0)
            E = np.full(n, np.nan if name == "samson" else 2.0)
            rows.append({"controller": name, "starts": sname, "n": n,
                         **_row(T, status, E, E, np.full(n, 0.1)), "audit": None})
    return rows


def test_compare_says_how_many_starts_failed_by_status_and_exits_3_when_a_law_failed_everywhere(
        capsys, tmp_path, monkeypatch):
    """Rows whose every start failed printed "settled 0/4 ... energy n/a" and exited 0; the line now says how many
    failed and with which status, the JSON counts them by status, and the exit code is 3 when every start of a law
    failed."""
    import jaxsleigh.studies.compare as study

    monkeypatch.setattr(study, "compare", _failing_rows)
    argv = ["compare", "--starts", "near,uniform", "--samples", "4", "--t-final", "5"]
    code, out, err = _run([*argv, "--controllers", "paper,samson", "--out", str(tmp_path / "f.json")], capsys)
    lines = [ln for ln in out.splitlines() if ln.startswith("samson")]
    assert code == 3 and len(lines) == 2 and all("failed 4/4 (4 nonfinite)" in ln for ln in lines)
    assert "every start of samson failed" in err
    assert not any("failed" in ln for ln in out.splitlines() if ln.startswith("paper"))
    rec = json.loads((tmp_path / "f.json").read_text())
    assert [r["failed_statuses"] for r in rec["rows"] if r["controller"] == "samson"] == [{"nonfinite": 4}] * 2
    code, _, err = _run([*argv, "--controllers", "paper", "--out", str(tmp_path / "g.json")], capsys)
    assert code == 0 and "failed" not in err


def test_equal_energy_says_when_a_law_did_not_reach_the_budget(capsys, tmp_path, monkeypatch):
    """A law tuned to 0.53x the budget was reported as tuned, compared as at equal energy; its record says
    ``budget_reached: false`` with the ratio, and its printed lines say that it is not at equal energy."""
    import jaxsleigh.studies.compare as study
    import jaxsleigh.tuning.budget as budget
    from jaxsleigh.tuning.law import LawTuneResult

    def fake_tune(law, starts, *, loss, **_):
        energy = 0.53 * loss.energy_budget if type(law).__name__.lower().startswith("samson") else loss.energy_budget
        return LawTuneResult(*([None] * len(LawTuneResult._fields)))._replace(
            law=law, energy=energy, loss=1.0, history={"loss": [1.0, 1.0]})

    monkeypatch.setattr(budget, "tune_law", fake_tune)
    said = []
    eq = budget.tune_to_budget(["samson", "astolfi"], train=2, steps=2, budget=10.0, log=said.append)
    assert eq.laws_info["samson"]["budget_reached"] is False and eq.laws_info["samson"]["energy_ratio"] == 0.53
    assert eq.laws_info["astolfi"]["budget_reached"] is True
    (samson,) = [s for s in said if s.startswith("samson")]
    assert "0.53x the budget" in samson and "NOT reached" in samson and "not at equal energy" in samson
    real = budget.tune_to_budget
    monkeypatch.setattr(budget, "tune_to_budget", lambda names, **k: real(names, **{**k, "budget": 10.0}))
    monkeypatch.setattr(study, "compare", _failing_rows)
    code, out, _ = _run(["compare", "--equal-energy", "--train", "2", "--steps", "2", "--controllers", "astolfi,samson",
                         "--starts", "near", "--samples", "2", "--t-final", "5", "--out", str(tmp_path / "e.json")],
                        capsys)
    rec = json.loads((tmp_path / "e.json").read_text())
    assert rec["equal_energy"]["laws"]["samson"]["budget_reached"] is False
    assert "samson: not at equal energy: its training energy is 0.53x the budget" in out
    assert "astolfi: not at equal energy" not in out
