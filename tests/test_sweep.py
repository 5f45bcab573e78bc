"""Per-trajectory parameters and parameter sweeps.

* a sweep equals the separate runs it replaces (same status, same T_eps to rounding, per start and
  value), across chunk boundaries, for gains and plant parameters (knife edge included);
* the effort summaries per value (median control energy and peak ||u|| of the converged starts)
  equal the medians of the separate runs;
* changing the values does not recompile (the jit caches of the stepper's kernels do not grow);
* per-lane runs of the knife edge and of a sampled plant with viscous damping agree with scipy's
  DOP853 (rtol 1e-10, float64) integrating the physical-chart vector field;
* bad values are refused eagerly, naming the ``--param``;
* ``jaxsleigh sweep`` writes the documented keys, and an interrupted run resumed from its chunks
  writes the same bytes as an uninterrupted one.
"""
from __future__ import annotations

import jax
import numpy as np
import pytest

import jaxsleigh
import jaxsleigh.cli as cli
from jaxsleigh.studies.basin import sample_starts
from jaxsleigh.model.lanes import check_lanes, lane_count, stack_gains, stack_plants
from jaxsleigh.model.params import Gains, PlantParams, gains, load_gains, plant_params
from jaxsleigh.studies.sweep import apply_params, load_sweep, parse_param, save_sweep, sweep
from numpy_field import numpy_field  # noqa: E402

# starts that settle within a short horizon under the tuned gains (and, with m = 3 and l = 1.5, some that do
# not: their T_0.2 are 6.4-8.1 s; with m = 1 and l = 0 every start settles in 1.2-3.9 s, as scipy's Radau says,
# where the step on p2 alone ran out of budget)
STARTS = sample_starts(6, seed=3, x="-1:1", y="-1:1", theta="0.3:1.5")
FAST = dict(t_final=6.0, dt=0.02, eps=0.2, gains="tuned")


@pytest.fixture(scope="module")
def ml_sweep():
    """A 2 x 2 grid over m and l (the knife edge l = 0 included), float64, chunks straddling values."""
    return sweep(STARTS, ["m=1:3:2", "l=0:1.5:2"], x64=True, run=jaxsleigh.RunOptions(chunk_size=5, progress=False),
                 **FAST)


@pytest.fixture(scope="module")
def ml_separate(ml_sweep):
    """The separate runs that ``ml_sweep`` replaces, one per value set."""
    return [jaxsleigh.run_ensemble(STARTS.ics, plant=plant_params(m, 1.0, l), x64=True,
                                   run=jaxsleigh.RunOptions(progress=False), **FAST)
            for m, l in ml_sweep.values]


def test_sweep_equals_separate_runs(ml_sweep, ml_separate):
    r = ml_sweep
    assert r.T_eps.shape == r.status.shape == (4, 6) and r.grid_shape == (2, 2)
    np.testing.assert_array_equal(r.values, [[1, 0], [1, 1.5], [3, 0], [3, 1.5]])
    assert 0 < r.converged.sum() < r.converged.size           # the check means something
    for p, one in enumerate(ml_separate):
        np.testing.assert_array_equal(r.status[p], one.status)
        np.testing.assert_array_equal(np.isfinite(r.T_eps[p]), np.isfinite(one.T_eps))
        np.testing.assert_allclose(r.T_eps[p], one.T_eps, rtol=1e-9, atol=1e-9)


def test_effort_medians_equal_those_of_separate_runs(ml_sweep, ml_separate, tmp_path):
    """Per value set: the median control energy and peak ||u|| of the converged starts."""
    med = ml_sweep.effort_medians()
    assert set(med) == {"u_energy_median", "u_norm_peak_median"}
    for p, one in enumerate(ml_separate):
        c = one.converged
        assert c.any()                                         # every value set has converged starts
        np.testing.assert_allclose(med["u_energy_median"][p], np.median(one.u_energy[c]), rtol=1e-9)
        np.testing.assert_allclose(med["u_norm_peak_median"][p], np.median(one.u_norm_peak[c]), rtol=1e-9)
    assert np.all(med["u_energy_median"] > 0) and np.all(med["u_norm_peak_median"] > 0)
    path = save_sweep(tmp_path / "e.npz", ml_sweep)
    with np.load(path) as z:
        for k, v in med.items():
            assert z[k].shape == (4,)
            np.testing.assert_array_equal(z[k], v)
    assert "median int|u|^2" in ml_sweep.table()
    assert "including those whose adaptive step budget ran out (BUDGET_EXHAUSTED" in ml_sweep.table()
    # a value set with no converged start has NaN medians, without warnings
    none = ml_sweep._replace(T_eps=np.full_like(ml_sweep.T_eps, np.inf))
    assert all(np.isnan(v).all() for v in none.effort_medians().values())


def test_gain_sweep_equals_separate_runs_and_does_not_recompile():
    from jaxsleigh.integrate import engine
    from jaxsleigh.integrate import stepper

    base = load_gains("tuned")
    kw = dict(FAST, gains=base, x64=True, run=jaxsleigh.RunOptions(chunk_size=5, progress=False))
    r1 = sweep(STARTS, ["k=0.05:0.4:3:log"], **kw)
    sizes = (engine._segment_batch._cache_size(), stepper.init_batch_lanes._cache_size())
    r2 = sweep(STARTS, ["k=0.07:0.5:3"], **kw)                       # other values, same shapes
    r3 = sweep(STARTS, {"d22": [2.0, 5.0, 9.0]}, **kw)               # another parameter, same shapes
    assert (engine._segment_batch._cache_size(), stepper.init_batch_lanes._cache_size()) == sizes
    assert not np.array_equal(r1.T_eps, r2.T_eps)
    for p, k in enumerate(r2.values[:, 0]):
        one = jaxsleigh.run_ensemble(STARTS.ics, **dict(kw, gains=gains(base.L, k, base.D_hat)))
        np.testing.assert_array_equal(r2.status[p], one.status)
        np.testing.assert_allclose(r2.T_eps[p], one.T_eps, rtol=1e-9, atol=1e-9)
    assert r3.names == ("d22",) and r3.fraction.shape == (3,)


def test_results_record_the_parameters_each_row_used():
    plants = stack_plants([plant_params(2, 1, 1), plant_params(0.5, 3, 0.0), plant_params(4, 0.2, 2)])
    res = jaxsleigh.run_ensemble(STARTS.ics[:3], plant=plants, x64=True, run=jaxsleigh.RunOptions(progress=False),
                                 **FAST)
    np.testing.assert_array_equal(res.params["m"], [2, 0.5, 4])
    np.testing.assert_array_equal(res.params["l"], [1, 0, 2])
    np.testing.assert_array_equal(res.params["coulomb_eps"], [0.1] * 3)
    assert res.settings["plant"]["m"] == {"per_trajectory": 3, "min": 0.5, "max": 4.0}
    assert len(res.settings["lanes_sha256"]) == 64
    with pytest.raises(ValueError, match="3 lanes but there are 6"):
        jaxsleigh.run_ensemble(STARTS.ics, plant=plants, **FAST)
    with pytest.raises(ValueError, match="same number of lanes"):
        lane_count(plants, stack_gains([gains()] * 2))
    with pytest.raises(ValueError, match="mass m|plant.m must be > 0, got -1.0 in lane 1"):
        check_lanes(PlantParams(np.array([1.0, -1.0]), 1.0, 1.0), None)


def _reference_final(y0, plant, g, t_final):
    """scipy DOP853, rtol 1e-10, float64, on the physical-chart vector field (one plant)."""
    from scipy.integrate import solve_ivp

    args = jaxsleigh.ClosedLoop(plant, g)
    with jax.enable_x64(True):
        f, _ = numpy_field(args)
        sol = solve_ivp(f, (0.0, t_final), y0, method="DOP853", rtol=1e-10, atol=1e-12)
    assert sol.success
    return sol.y[:, -1]


def test_knife_edge_and_sampled_plant_agree_with_scipy():
    from jaxsleigh.model.damping import CoulombDamping

    knife = plant_params(2.0, 1.0, 0.0, "coulomb")                       # l = 0: the knife edge
    sampled = plant_params(0.7, 3.1, 0.4, CoulombDamping(0.3, 2.5))      # a sampled plant and friction level
    plants = [knife, knife, sampled, sampled]
    ics = STARTS.ics[:4]
    g = load_gains("tuned")
    t_final = 3.0
    res = jaxsleigh.run_ensemble(ics, plant=stack_plants(plants), gains=g, t_final=t_final, x64=True,
                                 run=jaxsleigh.RunOptions(progress=False))
    sol = jaxsleigh.simulate(ics, plant=stack_plants(plants), gains=g, t_final=t_final, x64=True,
                             saveat=jaxsleigh.SaveAt(every=50))
    assert sol.settings["params"]["l"] == [0.0, 0.0, 0.4, 0.4]
    for i, plant in enumerate(plants):
        ref = _reference_final(np.concatenate([ics[i], [0, 0]]), plant, g, t_final)
        np.testing.assert_allclose(np.concatenate([res.q_final[i], res.p_final[i]]), ref, rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(np.concatenate([sol.q[i, -1], sol.p[i, -1]]), ref, rtol=1e-6, atol=1e-7)


def test_values_are_checked_eagerly_naming_the_param():
    with pytest.raises(ValueError, match=r"--param m=-1:2:4: m must be > 0"):
        parse_param("m=-1:2:4")
    with pytest.raises(ValueError, match="a log range needs LO > 0"):
        parse_param("J=0:1:3:log")
    with pytest.raises(ValueError, match="unknown parameter 'mass'"):
        parse_param("mass=1:2:3")
    with pytest.raises(ValueError, match=r"--param d12=3:9:3 must be positive definite"):
        sweep(STARTS, ["d12=3:9:3"], t_final=1.0)
    with pytest.raises(ValueError, match="add --damping viscous"):
        apply_params(["c1"], [[1.0]], plant_params(damping="coulomb"))
    p, g = apply_params(["l", "k"], [[0.0, 0.2], [1.0, 0.3]])
    assert isinstance(g, Gains) and np.shape(p.l) == (2,) and np.shape(g.L) == (3, 2)


# ---------------------------------------------------------------------------------------------
# command line
# ---------------------------------------------------------------------------------------------

CLI = ["sweep", "--param", "k=0.05:0.4:3:log", "--samples", "6", "--seed", "3", "--x", "-1:1", "--y", "-1:1",
       "--theta", "0.3:1.5", "--gains", "tuned", "--eps", "0.2", "--t-final", "12", "--dt", "0.02",
       "--chunk-size", "6", "--no-progress"]
KEYS = {"names", "values", "ics", "T_eps", "status", "fraction", "fraction_se", "T_eps_percentiles",
        "status_counts", "status_codes", "n_valid", "n_converged", "grid_shape", "axis_k", "settings_json",
        "eps", "t_final", "dt", "method", "dtype", "max_steps", "gains_L", "gains_k", "gains_D_hat", "params",
        "damping", "u_energy", "u_norm_peak", "u_energy_median", "u_norm_peak_median"}


def test_cli_writes_documented_keys_and_resumes_byte_identically(tmp_path, monkeypatch, capsys):
    rc = cli.main([*CLI, "--out", str(tmp_path / "full.npz"), "--plot", str(tmp_path / "full.png")])
    out, err = capsys.readouterr()
    assert rc == 0, err
    full = (tmp_path / "full.npz").read_bytes()
    assert (tmp_path / "full.png").stat().st_size > 5000
    with np.load(tmp_path / "full.npz") as z:
        assert KEYS <= set(z.files)
        assert z["values"].shape == (3, 1) and z["ics"].shape == (6, 5) and z["T_eps"].shape == (3, 6)
        assert z["fraction"].shape == z["fraction_se"].shape == (3,) and str(z["names"][0]) == "k"
    r = load_sweep(tmp_path / "full.npz")
    assert r.names == ("k",) and r.axes[0].log

    real = jaxsleigh.studies.ensemble.drive_final
    calls = []

    def interrupted(*a, **k):                                       # Ctrl-C during the second chunk
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(jaxsleigh.studies.ensemble, "drive_final", interrupted)
    out_b = tmp_path / "resumed.npz"
    assert cli.main([*CLI, "--out", str(out_b)]) == 130 and not out_b.exists()
    assert "--resume" in capsys.readouterr().err
    monkeypatch.setattr(jaxsleigh.studies.ensemble, "drive_final", real)
    rc = cli.main([*CLI, "--resume", "--out", str(out_b)])
    out, err = capsys.readouterr()
    assert rc == 0, err
    assert "1 chunk(s) resumed" in out
    assert out_b.read_bytes() == full
    # a bad range is refused before anything runs, naming its --param
    rc = cli.main(["sweep", "--param", "m=0:2:3", "--out", str(tmp_path / "bad.npz")])
    assert rc == 2 and "--param m=0:2:3: m must be > 0" in capsys.readouterr().err


def test_save_is_deterministic(ml_sweep, tmp_path):
    a = save_sweep(tmp_path / "a.npz", ml_sweep).read_bytes()
    b = save_sweep(tmp_path / "b.npz", ml_sweep._replace(run_info={"wall_s": 1.0})).read_bytes()
    assert a == b
    back = load_sweep(tmp_path / "a.npz")
    np.testing.assert_array_equal(back.fraction, ml_sweep.fraction)
    assert back.grid_shape == (2, 2)
