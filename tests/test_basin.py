"""Basin studies (:mod:`jaxsleigh.studies.basin`), their figures and ``jaxsleigh basin``.

Ground truth: ``T_eps`` from the on-line summaries equals ``T_eps`` read off full trajectories of
:func:`jaxsleigh.simulate` (fixed-step RK4 saved at every step, float32 and float64); the converged
set of the default float32 adaptive run agrees with a float64 reference; an interrupted run resumed
from its chunks writes the same bytes as an uninterrupted one; the standard error of the fraction
is the binomial one (formula and Monte-Carlo spread).
"""
from __future__ import annotations

import math

import numpy as np

from jaxsleigh.plots.base import device_text
import pytest

import jaxsleigh
import jaxsleigh.studies.ensemble
from jaxsleigh import cli
from jaxsleigh.cli.basin import add_basin
from jaxsleigh.errors import FlaggedStartsWarning
from jaxsleigh.studies.basin import (Axis, BasinResult, BasinStarts, array_starts, fraction_by, fraction_converged,
                             grid_starts, load_basin, parse_axis, path_length, power_law_fit, run_basin,
                             sample_starts, save_basin)
from jaxsleigh.status import Status

# a small x-y slice with a mix of converged and unsettled starts (10 of 24 converge)
GRID = dict(x="-2:2:6", y="-1.5:1.5:4", theta=0.9)
FAST = dict(eps=0.31, t_final=30.0, dt=0.05, stepsize=jaxsleigh.StepSizeController(method="rk4"),
            run=jaxsleigh.RunOptions(progress=False))


def _t_eps_from_trajectories(q: np.ndarray, t: np.ndarray, eps: float) -> np.ndarray:
    """First saved time after which |q| <= eps at every later saved time (inf: never settles)."""
    inside = np.linalg.norm(q, axis=-1) <= eps
    out = np.full(q.shape[0], np.inf)
    for i, row in enumerate(inside):
        outside = np.flatnonzero(~row)
        if outside.size == 0:
            out[i] = t[0]
        elif outside[-1] < t.size - 1:
            out[i] = t[outside[-1] + 1]
    return out


@pytest.fixture(scope="module")
def xt_result():
    """A tiny x-theta map (theta = 0 row included) from the default adaptive float32 engine."""
    with pytest.warns(FlaggedStartsWarning, match="6 of 30 initial conditions flagged"):
        return run_basin(grid_starts(x="-2:2:6", y=0.5, theta="-2.5:2.5:5"), eps=0.3, t_final=30.0, dt=0.05,
                         run=jaxsleigh.RunOptions(progress=False))


# ---------------------------------------------------------------------------------------------
# ground truth
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("x64", [False, True], ids=["float32", "float64"])
def test_t_eps_equals_t_eps_of_full_trajectories(x64):
    starts = grid_starts(**GRID)
    res = run_basin(starts, x64=x64, **FAST)
    sol = jaxsleigh.simulate(starts.ics, t_final=FAST["t_final"], dt=FAST["dt"], x64=x64,
                             stepsize=jaxsleigh.StepSizeController(method="rk4"), saveat=jaxsleigh.SaveAt(every=1))
    assert np.all(res.status == Status.OK) and np.all(sol.status == Status.OK)
    # no saved |q| is so close to eps that rounding could flip inside/outside
    assert np.min(np.abs(np.linalg.norm(sol.q, axis=-1) - FAST["eps"])) > 1e-4
    ref = _t_eps_from_trajectories(sol.q, sol.t, FAST["eps"])
    assert 5 <= np.isfinite(ref).sum() <= 19, "the grid should mix converged and unsettled starts"
    np.testing.assert_array_equal(np.isfinite(res.T_eps), np.isfinite(ref))
    # float32 time is accumulated in float32: a few ulps per step
    tol = 1e-3 if not x64 else 1e-9
    fin = np.isfinite(ref)
    # T_eps is located on the dense output inside the step that entered the ball: within that step
    assert np.all(res.T_eps[fin] <= ref[fin] + tol) and np.all(res.T_eps[fin] >= ref[fin] - FAST["dt"] - tol)
    assert np.any(res.T_eps[fin] < ref[fin] - 1e-3)          # and really inside it, not at its end
    # the 0.1 release's rule (the end of the entering step) reproduces the saved-trajectory answer
    from jaxsleigh.integrate.observers import ClosestApproach, ControlEffort, ConvergenceTime, Excursion
    old = jaxsleigh.run_ensemble(starts.ics, x64=x64, observers=(ConvergenceTime(1, 0), ClosestApproach(),
                                                                 Excursion(), ControlEffort()),
                                 **{k: v for k, v in FAST.items() if k != "chunk_size"})
    np.testing.assert_allclose(old.T_eps[fin], ref[fin], rtol=0, atol=tol)
    # the other summaries agree with the trajectories as well
    np.testing.assert_allclose(res.Hd0, sol.Hd[:, 0], rtol=1e-5 if not x64 else 1e-12)
    qn = np.linalg.norm(sol.q, axis=-1)
    np.testing.assert_allclose(res.max_excursion, qn.max(axis=1), rtol=1e-5 if not x64 else 1e-12)
    np.testing.assert_allclose(res.min_abs_theta, np.abs(sol.q[..., 2]).min(axis=1), rtol=1e-4 if not x64 else 1e-12)
    assert np.all(res.n_steps == round(FAST["t_final"] / FAST["dt"]))
    assert res.fraction == np.isfinite(ref).mean()


def test_converged_set_agrees_with_float64_reference():
    """Default engine (adaptive, float32) against float64 trajectories saved at every base step."""
    starts = grid_starts(**GRID)
    kw = dict(eps=0.31, t_final=30.0, dt=0.05)
    res = run_basin(starts, run=jaxsleigh.RunOptions(progress=False), **kw)
    ref_sol = jaxsleigh.simulate(starts.ics, x64=True, saveat=jaxsleigh.SaveAt(every=1),
                                 **{k: kw[k] for k in ("t_final", "dt")})
    ref = _t_eps_from_trajectories(ref_sol.q, ref_sol.t, kw["eps"])
    np.testing.assert_array_equal(res.converged, np.isfinite(ref))
    both = np.isfinite(ref)
    # adaptive steps (up to 10 dt) do not land on the save grid: T_eps agrees to a step
    assert np.max(np.abs(res.T_eps[both] - ref[both])) <= 10 * kw["dt"] + 1e-6


# ---------------------------------------------------------------------------------------------
# summaries
# ---------------------------------------------------------------------------------------------

def _synthetic(status, T_eps) -> BasinResult:
    n = len(status)
    z = np.zeros(n)
    return BasinResult(starts=array_starts(np.column_stack([z, z, np.ones(n)])), ics=np.zeros((n, 5)),
                       T_eps=np.asarray(T_eps, float), status=np.asarray(status, np.int32), Hd0=z, Hd_final=z,
                       min_abs_theta=z, max_excursion=z, n_steps=z.astype(int), n_rejected=z.astype(int),
                       q_final=np.zeros((n, 3)), p_final=np.zeros((n, 2)),
                       settings={"eps": 0.05, "t_final": 100.0, "dt": 0.01, "method": "rk4", "dtype": "float32"})


def test_fraction_standard_error_on_a_synthetic_case():
    # 100 of 400 converged: S = 1/4, se = sqrt(S (1 - S) / N)
    s, se = fraction_converged(np.arange(400) < 100)
    assert s == 0.25 and se == pytest.approx(math.sqrt(0.25 * 0.75 / 400), rel=1e-12)
    assert fraction_converged(np.ones(10, bool)) == (1.0, 0.0)
    assert all(math.isnan(v) for v in fraction_converged(np.ones(3, bool), np.zeros(3, bool)))
    # flagged starts (theta0 = 0) leave N; failures and unsettled starts count as not converged
    status = [Status.OK] * 6 + [Status.SINGULAR_START] * 3 + [Status.NONFINITE, Status.BUDGET_EXHAUSTED]
    T = [10.0, 20.0, 30.0, np.inf, np.inf, 5.0, np.nan, np.nan, np.nan, np.nan, np.nan]
    r = _synthetic(status, T)
    assert r.valid.sum() == 8 and r.converged.sum() == 4 and r.failed.sum() == 2 and r.not_converged.sum() == 2
    assert r.fraction == 0.5 and r.fraction_se == pytest.approx(math.sqrt(0.25 / 8))
    d = r.summary()
    assert d["n_flagged"] == 3 and d["T_eps_percentiles"]["p50"] == pytest.approx(15.0)
    # the standard error is the spread of S over independent replicates
    rng = np.random.default_rng(0)
    p, n = 0.3, 500
    draws = rng.random((4000, n)) < p
    spread = np.std(draws.mean(axis=1))
    ses = np.array([fraction_converged(d)[1] for d in draws[:200]])
    assert spread == pytest.approx(math.sqrt(p * (1 - p) / n), rel=0.05)
    assert np.mean(ses) == pytest.approx(spread, rel=0.05)


def test_fraction_by_groups_and_bins():
    v = np.array([1.0, 1.0, 2.0, 2.0, 2.0, 3.0])
    conv = np.array([True, False, True, True, False, True])
    c, f, se, n = fraction_by(v, conv)
    np.testing.assert_array_equal(c, [1, 2, 3])
    np.testing.assert_allclose(f, [0.5, 2 / 3, 1.0])
    np.testing.assert_allclose(se, [math.sqrt(0.25 / 2), math.sqrt(2 / 9 / 3), 0.0])
    np.testing.assert_array_equal(n, [2, 3, 1])
    c, f, se, n = fraction_by(v, conv, bins=np.array([0.0, 1.5, 3.5]))
    np.testing.assert_allclose(f, [0.5, 0.75])
    np.testing.assert_array_equal(n, [2, 4])


def test_power_law_fit_and_path_length():
    x = np.geomspace(1e-3, 1e-1, 9)
    fit = power_law_fit(x, 2.6 * x ** -4.0)
    assert fit.exponent == pytest.approx(-4.0, abs=1e-12) and fit.prefactor == pytest.approx(2.6)
    assert fit.exponent_se < 1e-10 and fit.r2 == pytest.approx(1.0)
    noisy = power_law_fit(x, 3 * x ** 2 * np.exp(0.1 * np.sin(np.arange(9) * 2.0)))
    assert abs(noisy.exponent - 2) < 3 * noisy.exponent_se + 0.05 and noisy.exponent_se > 0
    with pytest.raises(ValueError, match="at least two points"):
        power_law_fit([1.0], [1.0])
    # a square of side 2, walked once, decimated at its corners; NaN after a failure is skipped
    q = np.array([[0, 0, 1], [2, 0, 1], [2, 2, 1], [0, 2, 1], [0, 0, 1], [np.nan] * 3], float)
    assert path_length(q) == pytest.approx(8.0)
    np.testing.assert_allclose(path_length(np.stack([q, 2 * q])), [8.0, 16.0])


# ---------------------------------------------------------------------------------------------
# grids and samples
# ---------------------------------------------------------------------------------------------

def test_parse_axis_ranges_values_and_errors():
    assert parse_axis("-3:3:64") == Axis(-3.0, 3.0, 64)
    assert parse_axis("-pi:pi/2:5", "theta") == Axis(-math.pi, math.pi / 2, 5)
    assert parse_axis("0.5") == Axis(0.5, 0.5, 1) and parse_axis(2) == Axis(2.0, 2.0, 1)
    assert parse_axis((0, 1, 3)).n == 3
    np.testing.assert_allclose(parse_axis("0:1:5").values(), [0, 0.25, 0.5, 0.75, 1])
    assert parse_axis("-pi:pi:5", "theta").values()[2] == 0.0        # snapped onto the singular set
    bad = {"-3:3": "LO:HI:N", "3:-3:8": "write e.g. --x -3:3:8", "a:1:4": "'a' is not a number",
           "0:1:2.5": "whole number", "0:1:1": "N >= 2", "1:2:3:4": "LO:HI:N", "nan:1:3": "non-finite",
           "1:2:nan": "N = nan must be a whole number", "1:2:inf": "N = inf must be a whole number",
           (0, 1, "a"): "three numbers (lo, hi, n)"}
    for spec, fix in bad.items():
        with pytest.raises(ValueError, match="--x") as e:
            parse_axis(spec, "--x")
        assert fix in str(e.value), (spec, str(e.value))


def test_grid_layout_x_fastest_and_defaults():
    g = grid_starts(x="0:3:4", y=1, theta="1:2:3")
    assert g.kind == "grid" and g.shape == (3, 4) and g.axes == ("x", "theta")
    assert g.ics.shape == (12, 3)
    np.testing.assert_allclose(g.reshape(g.ics[:, 0])[0], [0, 1, 2, 3])         # rows run along x
    np.testing.assert_allclose(g.reshape(g.ics[:, 2])[:, 0], [1, 1.5, 2])     # columns along theta
    assert np.all(g.ics[:, 1] == 1.0)
    d = grid_starts()
    assert d.shape == (64, 64) and d.axes == ("x", "y") and np.allclose(d.ics[:, 2], math.pi / 4)
    held = grid_starts(theta="-1:1:4")
    assert held.axes == ("theta",) and np.all(held.ics[:, :2] == 1.0)
    with pytest.raises(ValueError, match="singular set"):
        grid_starts(x="-1:1:3", theta=0)


def test_samples_are_reproducible_and_in_the_box():
    a = sample_starts(1000, seed=3)
    b = sample_starts(1000, seed=3)
    np.testing.assert_array_equal(a.ics, b.ics)
    assert not np.array_equal(a.ics, sample_starts(1000, seed=4).ics)
    assert np.all(np.abs(a.ics[:, :2]) <= 3) and np.all(np.abs(a.ics[:, 2]) < math.pi)
    assert a.ics[:, 0].std() > 1.5                          # really spread over the box
    c = sample_starts(50, seed=0, x=2.0, theta="0.1:0.2:99")  # N of a range is ignored
    assert np.all(c.ics[:, 0] == 2.0) and np.all((c.ics[:, 2] >= 0.1) & (c.ics[:, 2] <= 0.2))
    for bad, msg in [(dict(n=0), "n must be >= 1"), (dict(n=5, seed=-1), "seed must be >= 0"), (dict(n=1.5), "whole"),
                     (dict(n=5, theta=0), "singular set")]:
        with pytest.raises(ValueError, match=msg):
            sample_starts(**bad)


def test_theta_zero_is_flagged_and_left_out_of_the_fraction(xt_result):
    r = xt_result
    on_set = r.ics[:, 2] == 0.0
    assert on_set.sum() == 6
    assert np.all(r.status[on_set] == Status.SINGULAR_START) and np.all(np.isnan(r.T_eps[on_set]))
    assert r.valid.sum() == 24 and r.fraction == pytest.approx(r.converged.sum() / 24)


# ---------------------------------------------------------------------------------------------
# files and figures
# ---------------------------------------------------------------------------------------------

def test_save_load_round_trip_and_deterministic_bytes(tmp_path, monkeypatch, xt_result):
    import time

    p1 = save_basin(tmp_path / "a.npz", xt_result)
    real_time = time.time
    monkeypatch.setattr(time, "time", lambda: real_time() + 400 * 86400)   # a later day: no timestamps leak
    p2 = save_basin(tmp_path / "b", xt_result)
    monkeypatch.undo()
    assert p2.name == "b.npz" and p1.read_bytes() == p2.read_bytes()
    with np.load(p1) as z:
        keys = set(z.files)
        assert {"ics", "T_eps", "status", "Hd0", "fraction", "fraction_se", "settings_json", "eps", "t_final",
                "grid_shape", "grid_axes", "axis_x", "axis_theta", "n_steps", "max_excursion"} <= keys
        assert z["ics"].shape == (30, 3) and tuple(z["grid_shape"]) == (5, 6)
        assert list(z["grid_axes"]) == ["x", "theta"] and float(z["fraction"]) == xt_result.fraction
        assert "wall" not in str(z["settings_json"])
    back = load_basin(p1)
    for k in ("T_eps", "status", "Hd0", "max_excursion", "n_steps", "q_final", "unresolved"):
        np.testing.assert_array_equal(getattr(back, k), getattr(xt_result, k))
    assert back.starts.shape == (5, 6) and back.starts.axes == ("x", "theta")
    assert back.fraction == xt_result.fraction and back.settings["eps"] == 0.3


def _stamp_text(fig):
    from jaxsleigh.plots.base import STAMP_GID

    (text,) = [t.get_text() for t in fig.texts if t.get_gid() == STAMP_GID]
    return text


def test_basin_map_shows_the_t_eps_map(xt_result):
    from jaxsleigh.plots import basin as bp

    fig = bp.plot_basin_map(xt_result)
    ax, cbar_ax = fig.axes
    title = fig.get_suptitle()
    assert "settled within the horizon" in title and "basin of attraction" not in title.lower()
    assert "float32" in title and "ε = 0.3" in title and "T = 30 s" in title
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("x₀ [m]", "θ₀ [rad]")
    assert r"$T_\varepsilon$" in cbar_ax.get_ylabel() and "log scale" in cbar_ax.get_ylabel()
    # the heat map holds T_eps of the converged starts (floored at dt for the log scale), nothing else
    heat, flat = ax.collections
    T = xt_result.starts.reshape(xt_result.T_eps)
    conv = xt_result.starts.reshape(xt_result.converged)
    expected = np.where(conv, np.maximum(T, 0.05), np.nan)
    np.testing.assert_array_equal(np.ma.filled(heat.get_array().astype(float), np.nan).reshape(T.shape), expected)
    assert heat.norm.vmax == 30.0                                  # the colour scale reaches the horizon
    # the flat layer: 1 = not settled by T, 2 = failed, 3 = theta0 = 0 (not integrated)
    cats = np.ma.filled(flat.get_array(), 0).reshape(T.shape)
    np.testing.assert_array_equal(cats == 1, xt_result.starts.reshape(xt_result.not_converged))
    np.testing.assert_array_equal(cats == 3, ~xt_result.starts.reshape(xt_result.valid))
    assert (cats == 3).sum() == 6
    # the singular set theta = 0 is a dashed horizontal line at 0
    (line,) = [ln for ln in ax.get_lines() if ln.get_linestyle() == "--"]
    np.testing.assert_array_equal(line.get_ydata(), [0, 0])
    legend = [t.get_text() for t in fig.legends[0].get_texts()]
    assert r"not settled by T ($T_\varepsilon$ = ∞)" in legend and "θ₀ = 0: not integrated" in legend
    assert "singular set θ = 0" in legend
    # provenance: dtype, method and the device the run was on
    text = _stamp_text(fig)
    assert f"device {device_text(None, xt_result.run_info)}" in text
    assert "float32" in fig.get_suptitle() + text and "adaptive RK4" in fig.get_suptitle() + text


def test_basin_map_of_another_field(xt_result):
    from jaxsleigh.plots import basin as bp

    fig = bp.plot_basin_map(xt_result, field="Hd0")
    heat = fig.axes[0].collections[0]
    Hd0 = xt_result.starts.reshape(xt_result.Hd0)
    shown = xt_result.starts.reshape(xt_result.valid & ~xt_result.failed)
    got = np.ma.filled(heat.get_array().astype(float), np.nan).reshape(Hd0.shape)
    np.testing.assert_allclose(got[shown], Hd0[shown], rtol=1e-6)
    assert np.all(np.isnan(got[~shown]))
    assert fig.get_suptitle().startswith("\nH_d(0) [J] at y₀ = 0.5") and "H_d(0)" in fig.axes[1].get_ylabel()


def test_fraction_distribution_scatter_and_power_law_figures(xt_result):
    from jaxsleigh.plots import basin as bp

    res = xt_result
    # fraction against theta0: one point per grid row, the binomial fraction and its error bars
    fig = bp.plot_fraction_vs_theta(res)
    ax = fig.axes[0]
    c, f, se, n = fraction_by(res.ics[:, 2], res.converged, res.valid)
    (bars,) = ax.containers
    assert bars.get_label() == "fraction converged ± s.e."
    points = bars.lines[0]
    np.testing.assert_array_equal(points.get_xdata(), c)
    np.testing.assert_array_equal(points.get_ydata(), f)
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("θ₀ [rad]", "fraction converged")
    assert "float32" in fig.get_suptitle() and "float32" not in _stamp_text(fig)      # said once
    # against the distance
    fig = bp.plot_fraction_vs_distance(res, bins=3)
    c, f, se, n = fraction_by(np.hypot(res.ics[:, 0], res.ics[:, 1]), res.converged, res.valid, bins=3)
    np.testing.assert_array_equal(fig.axes[0].containers[0].lines[0].get_ydata(), f)
    # distribution: every converged start in one bin, and the fraction by t ends at the fraction
    fig = bp.plot_t_eps_distribution(res)
    ax, right = fig.axes
    assert sum(p.get_height() for p in ax.patches) == res.converged.sum()
    assert right.get_lines()[0].get_ydata()[-1] == pytest.approx(res.converged.sum() / res.valid.sum())
    assert ax.get_xlabel() == r"$T_\varepsilon$ [s]" and ax.get_xlim() == (0.0, 30.0)
    # scatter: converged starts at (|theta0|, T_eps), the others at the horizon
    fig = bp.plot_t_eps_scatter(res)
    conv, nc, _ = fig.axes[0].collections
    np.testing.assert_array_equal(conv.get_offsets(), np.column_stack(
        [np.abs(res.ics[res.converged, 2]), np.maximum(res.T_eps[res.converged], 0.05)]))
    np.testing.assert_array_equal(nc.get_offsets()[:, 1], 30.0)
    assert len(nc.get_offsets()) == res.not_converged.sum()
    # power laws: the points and the fitted line
    fit = power_law_fit([0.1, 0.01], [1, 1e4])
    fig = bp.plot_power_laws([0.1, 0.01], {"H": [1.0, 1e4]}, fits={"H": fit}, expected={"H": -4}, title="laws")
    pts, curve = fig.axes[0].get_lines()
    np.testing.assert_array_equal(pts.get_ydata(), [1.0, 1e4])
    np.testing.assert_allclose(curve.get_ydata(), fit(curve.get_xdata()))
    assert fig.axes[0].get_xscale() == fig.axes[0].get_yscale() == "log"
    assert "slope -4.00" in fig.axes[0].get_legend().get_texts()[0].get_text()


def test_basin_overview_says_settled_within_the_horizon(xt_result):
    from jaxsleigh.plots import basin as bp

    fig = bp.plot_basin(xt_result)
    title = fig.get_suptitle()
    assert "settled within the horizon" in title and "basin of attraction" not in title.lower()
    assert "float32" in title and "float32" not in _stamp_text(fig)      # said once, in the title
    # map + colour bar, fraction against theta0, distribution + its right axis
    assert len(fig.axes) == 5
    assert fig.axes[0].get_ylabel() == "θ₀ [rad]" and fig.axes[2].get_xlabel() == "θ₀ [rad]"
    assert fig.axes[3].get_xlabel() == r"$T_\varepsilon$ [s]"
    # starts that are not a grid: the scatter instead of the map
    samples = BasinResult(**{**xt_result._asdict(), "starts": array_starts(xt_result.ics)})
    with pytest.raises(ValueError, match="two varying coordinates"):
        bp.plot_basin_map(samples)
    fig = bp.plot_basin(samples)
    assert fig.axes[0].get_ylabel() == r"$T_\varepsilon$ [s]" and fig.axes[0].get_xscale() == "log"
    assert fig.axes[1].get_xscale() == "log"                    # fraction against |theta0| for samples


# ---------------------------------------------------------------------------------------------
# command line
# ---------------------------------------------------------------------------------------------

@pytest.fixture
def basin_main(monkeypatch, capsys):
    """``jaxsleigh.cli.main`` with the basin subcommand registered; returns (rc, stdout, stderr)."""
    def run(argv):
        rc = cli.main(argv)
        out, err = capsys.readouterr()
        return rc, out, err

    return run


CLI_FAST = ["--x", "-2:2:6", "--y", "-1.5:1.5:4", "--theta", "0.9", "--eps", "0.31", "--t-final", "30", "--dt", "0.05",
            "--method", "rk4", "--chunk-size", "6", "--no-progress"]


def test_resume_after_interruption_writes_identical_bytes(tmp_path, monkeypatch, basin_main):
    rc, out, err = basin_main(["basin", *CLI_FAST, "--out", str(tmp_path / "full.npz")])
    assert rc == 0, err
    assert "converged within 30 s" in out and "10/24" in out
    full = (tmp_path / "full.npz").read_bytes()
    assert not (tmp_path / "full.npz.chunks").exists()            # removed after a complete run

    real = jaxsleigh.studies.ensemble.drive_final
    calls = []

    def interrupted(*a, **k):                                     # Ctrl-C during the third chunk
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(jaxsleigh.studies.ensemble, "drive_final", interrupted)
    out_b = tmp_path / "resumed.npz"
    rc, _, err = basin_main(["basin", *CLI_FAST, "--out", str(out_b)])
    assert rc == 130 and "--resume" in err and not out_b.exists()
    chunks = tmp_path / "resumed.npz.chunks"
    assert sorted(p.name for p in chunks.glob("chunk_*.npz")) == ["chunk_000000.npz", "chunk_000001.npz"]
    # a fresh start over the chunks of an unfinished run is refused with the fix in the message
    monkeypatch.setattr(jaxsleigh.studies.ensemble, "drive_final", real)
    rc, _, err = basin_main(["basin", *CLI_FAST, "--out", str(out_b)])
    assert rc == 2 and "--resume" in err and "delete" in err
    # --resume computes only the missing chunks and ends with the same file
    calls.clear()
    monkeypatch.setattr(jaxsleigh.studies.ensemble, "drive_final", lambda *a, **k: (calls.append(1), real(*a, **k))[1])
    rc, out, err = basin_main(["basin", *CLI_FAST, "--resume", "--keep-chunks", "--out", str(out_b)])
    assert rc == 0, err
    assert len(calls) == 2 and "2 chunk(s) resumed" in out
    assert out_b.read_bytes() == full
    # a killed process can also lose a chunk file mid-way: resuming recomputes just that one
    (chunks / "chunk_000002.npz").unlink()
    calls.clear()
    rc, _, err = basin_main(["basin", *CLI_FAST, "--resume", "--out", str(out_b)])
    assert rc == 0, err
    assert len(calls) == 1 and out_b.read_bytes() == full
    # resuming with other settings is refused
    rc, _, _ = basin_main(["basin", *CLI_FAST, "--out", str(tmp_path / "other.npz"), "--keep-chunks"])
    assert rc == 0
    rc, _, err = basin_main(["basin", *CLI_FAST, "--eps", "0.2", "--resume", "--out", str(tmp_path / "other.npz")])
    assert rc == 2 and "--eps 0.31 in the checkpoint vs --eps 0.2 now" in err and "--resume" in err, err


def test_cli_outputs_plot_and_sidecar(tmp_path, basin_main):
    import json

    np.save(tmp_path / "ics.npy", np.array([[1.0, 1.0, 0.9], [0.5, -0.5, -2.0], [0.0, 0.0, 0.0]]))
    rc, out, err = basin_main(["basin", "--ics", str(tmp_path / "ics.npy"), "--eps", "0.3", "--t-final", "30",
                               "--dt", "0.05", "--out", str(tmp_path / "f.npz"), "--plot", str(tmp_path / "f.png")])
    assert rc == 0, err
    assert "1 of 3 starts flagged" in err
    from matplotlib.image import imread

    assert imread(tmp_path / "f.png").shape[:2] == (930, 1950)      # plot_basin's 13 x 6.2 in at 150 dpi
    side = json.loads((tmp_path / "f.run.json").read_text())
    assert side["command"][:2] == ["jaxsleigh", "basin"] and side["wall_s"] > 0
    with np.load(tmp_path / "f.npz") as z:
        assert z["ics"].shape == (3, 3) and str(z["kind"]) == "array" and int(z["n_valid"]) == 2
        assert list(z["status"])[2] == Status.SINGULAR_START
    rc, _, err = basin_main(["basin", "--samples", "16", "--seed", "2", "--theta", "0.3:pi", "--t-final", "1",
                             "--dt", "0.05", "--out", str(tmp_path / "s.npz")])
    assert rc == 0, err
    with np.load(tmp_path / "s.npz") as z:
        np.testing.assert_array_equal(z["ics"], sample_starts(16, seed=2, theta="0.3:pi").ics)
        assert int(z["seed"]) == 2 and z["box"][2, 0] == 0.3


@pytest.mark.parametrize("argv, message", [
    (["--x", "-3:3"], "write LO:HI:N (e.g. --x -3:3:64)"),
    (["--theta", "pi:-pi:8"], "LO must be below HI"),
    (["--y", "0:1:one"], "'one' is not a number"),
    (["--theta", "0"], "singular set"),
    (["--ics", "missing.npy"], "not found"),
    (["--ics", "missing.npy", "--x", "1"], "cannot be combined with --ics"),
    (["--seed", "3"], "--seed seeds --samples and --noise only"),
    (["--samples", "10", "--theta", "1:0.5"], "write e.g. --theta 0.5:1"),
    (["--samples", "0"], "--samples must be >= 1"),
    (["--eps", "-1"], "--eps must be a finite number > 0"),
    (["--t-final", "1.005"], "whole multiple of --dt"),
    (["--gains", "nope.json"], "not found"),
    (["--samples", "4", "--ics", "a.npy"], "not allowed with argument"),
])
def test_cli_bad_input_messages(tmp_path, basin_main, argv, message):
    rc, out, err = basin_main(["basin", *argv, "--out", str(tmp_path / "x.npz")])
    assert rc == 2 and message in err, err
    assert not (tmp_path / "x.npz").exists()


def test_negative_ranges_parse_without_equals_sign(basin_main):
    import argparse

    parser = argparse.ArgumentParser()
    add_basin(parser.add_subparsers())
    args = parser.parse_args(["basin", "--x", "-3:3:8", "--theta", "-pi:pi:8", "--y", "-1", "--out", "o.npz"])
    assert (args.x, args.theta, args.y) == ("-3:3:8", "-pi:pi:8", "-1")


def test_array_starts_validation():
    assert array_starts([1.0, 2.0, 0.5]).ics.shape == (1, 3)
    assert isinstance(array_starts(np.ones((4, 5))), BasinStarts)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        array_starts(np.ones((4, 4)))
