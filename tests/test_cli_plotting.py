"""The command line contract (``jaxsleigh simulate`` / ``jaxsleigh paper``) and the plotting layer."""
from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys

import numpy as np

from jaxsleigh.plots.base import device_text
import pytest

import jaxsleigh
from jaxsleigh.plots import paper_figures as plotting
from jaxsleigh.cli import main
from jaxsleigh.plots.paper_run import PAPER_ICS
from jaxsleigh.studies.simulate import Solution
from jaxsleigh.status import Status

SIM_KEYS = {"t", "q", "p", "u", "Hd", "status", "n_steps", "settings_json", "dt", "t_final", "save_every",
            "method", "dtype", "gains_L", "gains_k", "gains_D_hat", "params", "damping"}
TINY = ["--t-final", "1", "--dt", "0.01", "--save-every", "10"]


def _run(argv, capsys):
    rc = main(argv)
    out, err = capsys.readouterr()
    return rc, out, err


def test_simulate_contract_and_settings_round_trip(tmp_path, capsys):
    out = tmp_path / "run.npz"
    # "--ic -3,..." (negative first entry, no '=') must work too
    rc, stdout, err = _run(["simulate", "--ic", "-3,-2,pi/8", "--ic=3,2,-1.5", *TINY, "--out", str(out)], capsys)
    assert rc == 0, err
    assert "2 trajectories: 2 integrated; " in stdout and " settled" in stdout and str(out) in stdout
    with np.load(out, allow_pickle=False) as z:
        data = {k: z[k] for k in z.files}
    assert SIM_KEYS <= set(data)
    n, T = 2, 11
    assert data["t"].shape == (T,) and np.allclose(data["t"], np.linspace(0, 1, T))
    assert data["q"].shape == (n, T, 3) and data["p"].shape == (n, T, 2) and data["u"].shape == (n, T, 2)
    assert data["Hd"].shape == (n, T) and data["status"].shape == (n,) and data["n_steps"].shape == (n,)
    assert data["status"].dtype.kind == "i" and np.all(data["status"] == 0)
    np.testing.assert_allclose(data["q"][:, 0], [[-3, -2, math.pi / 8], [3, 2, -1.5]])
    # scalar keys agree with the JSON settings, which agree with the library's defaults
    s = json.loads(str(data["settings_json"]))
    assert float(data["dt"]) == s["dt"] == 0.01 and float(data["t_final"]) == s["t_final"] == 1.0
    assert int(data["save_every"]) == s["save_every"] == 10
    assert str(data["method"]) == s["method"] == "adaptive" and str(data["dtype"]) == s["dtype"] == "float32"
    np.testing.assert_array_equal(data["gains_L"], s["gains"]["L"])
    assert float(data["gains_k"]) == s["gains"]["k"] == 0.1
    np.testing.assert_array_equal(data["gains_D_hat"], [[4, 0], [0, 8]])
    np.testing.assert_array_equal(data["params"], [2, 1, 1])
    assert str(data["damping"]) == "coulomb" and s["plant"]["damping"] == "CoulombDamping"
    np.testing.assert_allclose(np.asarray(s["ics"])[:, :3], [[-3, -2, math.pi / 8], [3, 2, -1.5]])
    assert s["command"][:2] == ["jaxsleigh", "simulate"]
    # the file holds what the library computes with those settings
    ref = jaxsleigh.simulate(np.asarray(s["ics"]), t_final=s["t_final"], dt=s["dt"],
                             stepsize=jaxsleigh.StepSizeController(method=s["method"]),
                             saveat=jaxsleigh.SaveAt(every=s["save_every"]))
    np.testing.assert_allclose(data["q"], ref.q, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(data["u"], ref.u, rtol=1e-5, atol=1e-5)


def test_ics_file_gains_json_and_options(tmp_path, capsys):
    ics = np.array([[1.0, -1.0, 0.7, 0.5, -0.2], [-2.0, 0.5, -2.0, 0.0, 0.0]])
    np.save(tmp_path / "ics.npy", ics)
    gains = {"L": [1.0, 0.4, 0.6], "k": 0.2, "D_hat": [[4.0, 1.0], [1.0, 8.0]]}
    (tmp_path / "g.json").write_text(json.dumps(gains))
    out = tmp_path / "g.npz"
    rc, _, err = _run(["simulate", "--ics", str(tmp_path / "ics.npy"), *TINY, "--gains", str(tmp_path / "g.json"),
                       "--params", "1.5,0.5,0.8", "--damping", "viscous", "--method", "rk4", "--out", str(out)],
                      capsys)
    assert rc == 0, err
    with np.load(out) as z:
        np.testing.assert_array_equal(z["gains_D_hat"], gains["D_hat"])
        np.testing.assert_array_equal(z["gains_L"], gains["L"])
        assert float(z["gains_k"]) == 0.2
        np.testing.assert_array_equal(z["params"], [1.5, 0.5, 0.8])
        assert str(z["damping"]) == "viscous" and str(z["method"]) == "rk4"
        np.testing.assert_allclose(z["p"][:, 0], ics[:, 3:], atol=1e-6)   # momentum start kept
        assert np.all(z["status"] == 0)


def test_batch_with_a_singular_start_is_flagged(tmp_path, capsys):
    rc, stdout, err = _run(["simulate", "--ic", "1,1,0", "--ic", "1,1,0.5", *TINY, "--out", str(tmp_path / "b")],
                           capsys)
    assert rc == 0, err
    assert "1 of 2 initial conditions flagged" in err
    assert "1 singular_start" in stdout
    with np.load(tmp_path / "b.npz") as z:   # .npz appended
        assert list(z["status"]) == [Status.SINGULAR_START, Status.OK]
        assert np.all(np.isnan(z["q"][0])) and np.all(np.isfinite(z["q"][1]))


def _write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return str(p)


@pytest.mark.parametrize("case, expect", [
    (["--ic", "1,1,0"], "theta0 != 0"),
    (["--ic", "1,1,nan"], "non-finite"),
    (["--ic", "1,1,abc"], "could not parse --ic"),
    (["--ic", "1,1"], "X,Y,THETA"),
    (["--ic", "1,1,1", "--dt", "0"], "--dt must be a finite number > 0"),
    (["--ic", "1,1,1", "--t-final", "1.005", "--dt", "0.01"], "whole multiple of --dt"),
    (["--ic", "1,1,1", "--save-every", "3"], "--save-every"),
    (["--ic", "1,1,1", "--params", "0,1,1"], "mass m must be > 0"),
    (["--ic", "1,1,1", "--params", "2,1"], "--params"),
    (["--ic", "1,1,1", "--gains", "BADGAINS"], "L must have 3 entries"),
    (["--ic", "1,1,1", "--gains", "NOTJSON"], "not valid JSON"),
    (["--ic", "1,1,1", "--gains", "missing.json"], "not found"),
    (["--ics", "BADSHAPE"], "shape (2, 4)"),
    (["--ics", "missing.npy"], "not found"),
    (["--ic", "1,1,1", "--damping", "sticky"], "invalid choice"),
    (["--ic", "1,1,1", "--atol", "0"], "--atol must be a finite number > 0"),
    (["--ic", "1,1,1", "--method", "rk4", "--rtol", "1e-7", "--atol", "1e-8"], "--rtol and --atol set the adaptive"),
    ([], "one of the arguments --ics --ic is required"),
])
def test_bad_input_exits_2_with_a_message(tmp_path, capsys, case, expect):
    files = {"BADGAINS": _write(tmp_path, "bad.json", json.dumps({"L": [1, 2], "k": 0.1, "D_hat": [1, 1]})),
             "NOTJSON": _write(tmp_path, "not.json", "{L: 1"),
             "missing.json": str(tmp_path / "missing.json"), "missing.npy": str(tmp_path / "missing.npy")}
    np.save(tmp_path / "bad.npy", np.ones((2, 4)))
    files["BADSHAPE"] = str(tmp_path / "bad.npy")
    argv = ["simulate", *[files.get(a, a) for a in case], *([] if "--dt" in case else TINY[2:4]),
            "--out", str(tmp_path / "x.npz")]
    rc, _, err = _run(argv, capsys)
    assert rc == 2
    assert err.startswith("jaxsleigh: error: ") and expect in err, err
    assert "Traceback" not in err
    assert not (tmp_path / "x.npz").exists()


@pytest.mark.parametrize("cmd", ["simulate", "basin", "sweep"])
def test_tolerance_flags_reach_the_engine_and_the_record(tmp_path, capsys, cmd):
    """--rtol / --atol set the adaptive error control (more steps at tighter ones) and the output records them."""
    where = {"simulate": ["--ic=-3,-2,pi/8", "--ic", "2,1,-1.5", "--t-final", "20"],
             "basin": ["--x", "-2:2:2", "--y", "1", "--theta", "0.5", "--t-final", "20"],
             "sweep": ["--x", "-2:2:2", "--y", "1", "--theta", "0.5", "--param", "k=0.05:0.1:2", "--t-final", "20"]}[cmd]
    steps = {}
    for tag, tol in (("default", []), ("tight", ["--rtol", "1e-7", "--atol", "1e-8"])):
        out = tmp_path / f"{tag}.npz"
        rc, _, err = _run([cmd, *where, *tol, "--out", str(out), "--no-progress"], capsys)
        assert rc == 0, err
        with np.load(out, allow_pickle=False) as z:
            settings = json.loads(str(z["settings_json"]))
            steps[tag] = np.asarray(z["n_steps"]).sum()
        if tag == "tight":
            assert settings["rtol"] == 1e-7 and settings["atol"] == 1e-8, settings
    assert steps["tight"] > steps["default"]


def test_help_documents_status_codes(capsys):
    rc, stdout, _ = _run(["simulate", "--help"], capsys)
    assert rc == 0
    for s in Status:
        assert f"{int(s)} = {s.name.lower()}" in stdout
    assert "--save-every" in stdout and "--x64" in stdout


def test_paper_subcommand_writes_every_figure(tmp_path, capsys):
    out = tmp_path / "paper"
    rc, stdout, err = _run(["paper", "--out", str(out), "--dt", "0.05", "--t-final", "1"], capsys)
    assert rc == 0, err
    for name in ("fig2_paths", "fig3_configuration", "fig4_momentum", "fig5_control", "fig_hamiltonian"):
        f = out / f"{name}.png"
        assert f.exists() and f.stat().st_size > 10_000, name
        assert f.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with np.load(out / "paper.npz") as z:
        assert SIM_KEYS <= set(z.files)
        assert z["q"].shape[0] == len(PAPER_ICS)
        assert float(z["dt"]) == 0.05 and float(z["t_final"]) == 1.0
    assert "(−3, −2, π/8)" in stdout


def _tiny_solution(bad: bool = True) -> Solution:
    t = np.linspace(0.0, 2.0, 21)
    n = 3
    q = np.stack([np.stack([(-1.0 + 0.3 * i) * np.exp(-t), 0.5 * np.exp(-t), (0.4 + 0.2 * i) * np.exp(-t)], -1)
                  for i in range(n)])
    p = np.stack([np.stack([np.exp(-t), -0.3 * np.exp(-t)], -1)] * n)
    u = np.stack([np.stack([-50.0 * np.exp(-5 * t), 3 * np.exp(-t)], -1)] * n)
    Hd = np.exp(-np.arange(n)[:, None] - t)
    status = np.zeros(n, np.int32)
    if bad:
        status[2] = Status.BUDGET_EXHAUSTED
        for a in (q, p, u):
            a[2, 12:] = np.nan
        Hd[2, 12:] = np.nan
    settings = {"dtype": "float64", "method": "rk4", "dt": 0.01, "plant": {"m": 2.0, "J": 1.0, "l": 1.0}}
    return Solution(t, q, p, u, Hd, status, np.full(n, 200), np.zeros(n), settings)


def _data_lines(ax):
    return [line for line in ax.get_lines() if not line.get_label().startswith("_")]


# plotting function -> (y-labels of its axes, the arrays each axis must show, one row per run)
_FIGURES = {
    "plot_configuration": (["x [m]", "y [m]", "θ [rad]"], lambda s: [s.q[..., 0], s.q[..., 1], s.q[..., 2]]),
    "plot_momentum": (["p₁ [kg m/s] (symlog)", "p₂ [kg m²/s] (symlog)"], lambda s: [s.p[..., 0], s.p[..., 1]]),
    "plot_control": (["u₁ [N] (symlog)", "u₂ [N m] (symlog)"], lambda s: [s.u[..., 0], s.u[..., 1]]),
    "plot_hamiltonian": (["H_d [J]"], lambda s: [s.Hd]),
}


@pytest.mark.parametrize("name", sorted(_FIGURES))
def test_time_histories_plot_the_solution(name):
    sol = _tiny_solution()
    fig = getattr(plotting, name)(sol)
    ylabels, expected = _FIGURES[name]
    assert [ax.get_ylabel() for ax in fig.axes] == ylabels
    assert fig.axes[-1].get_xlabel() == "time t [s]"
    for ax, data in zip(fig.axes, expected(sol)):
        lines = _data_lines(ax)
        assert len(lines) == sol.q.shape[0]
        for i, line in enumerate(lines):
            np.testing.assert_array_equal(line.get_xdata(), sol.t)
            np.testing.assert_array_equal(line.get_ydata(), data[i])      # NaN after the failed run stopped
        assert [line.get_linestyle() for line in lines] == ["-", "-", "--"]   # status != 0 is dashed
    if name == "plot_hamiltonian":
        assert fig.axes[0].get_yscale() == "log"
    if name in ("plot_control", "plot_momentum"):
        assert {ax.get_yscale() for ax in fig.axes} == {"symlog"}
    title = fig.get_suptitle()
    assert "float64" in title and "fixed-step RK4" in title and "dt = 0.01 s" in title
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert labels[:2] == ["(−1, 0.5, 0.4)", "(−0.7, 0.5, 0.6)"]
    assert "budget_exhausted" in labels[2] and any("status ≠ 0" in s for s in labels)


def test_paths_plot_the_contact_point_and_the_sleigh():
    from matplotlib.patches import Polygon

    sol = _tiny_solution()
    fig = plotting.plot_paths(sol)
    (ax,) = fig.axes
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("x [m]", "y [m]")
    assert "Paths of the contact point" in fig.get_suptitle() and "t ∈ [0, 2] s" in fig.get_suptitle()
    lines = _data_lines(ax)
    assert len(lines) == 3
    for i, line in enumerate(lines):
        np.testing.assert_array_equal(line.get_xdata(), sol.q[i, :, 0])
        np.testing.assert_array_equal(line.get_ydata(), sol.q[i, :, 1])
    # a ghosted sleigh at each start and the solid target
    bodies = [p for p in ax.patches if isinstance(p, Polygon)]
    assert len(bodies) == 4
    assert sorted(p.get_alpha() for p in bodies) == [0.3, 0.3, 0.3, 1.0]
    target = next(p for p in bodies if p.get_alpha() == 1.0)
    np.testing.assert_allclose(target.get_xy()[:5], plotting.sleigh_outline(0, 0, 0, size=0.07 * 1.0)["body"],
                               atol=0.05)
    # the failed run's last finite point is marked with a cross
    crosses = [line for line in ax.get_lines() if line.get_marker() == "x"]
    assert len(crosses) == 1
    np.testing.assert_array_equal(crosses[0].get_xydata()[0], sol.q[2, 11, :2])


def test_provenance_stamp_names_dtype_method_and_device():
    from jaxsleigh.plots.base import STAMP_GID

    sol = _tiny_solution()
    for fn in (plotting.plot_paths, plotting.plot_configuration):
        fig = fn(sol)
        (text,) = [t.get_text() for t in fig.texts if t.get_gid() == STAMP_GID]
        # the title names dtype, method and step; the stamp adds what it does not say
        assert "float64, fixed-step RK4, dt = 0.01 s" in fig.get_suptitle()
        assert text.startswith("device not recorded")   # the synthetic solution does not say where it ran
        assert "float64" not in text and "dt = " not in text
    settings = {**sol.settings, "dtype": "float32", "method": "adaptive", "rtol": 1e-6, "atol": 1e-9,
                "devices": ["cuda:0"]}
    fig = plotting.plot_momentum(sol._replace(settings=settings))
    (text,) = [t.get_text() for t in fig.texts if t.get_gid() == STAMP_GID]
    assert "float32, adaptive RK4" in fig.get_suptitle() and "float" not in text and "adaptive RK4" not in text
    assert "rtol = 1e-06, atol = 1e-09" in text and "device cuda:0" in text
    # a real run records its device, and the figure drawn from its file names it
    real = jaxsleigh.simulate(np.array([[1.0, 1.0, 0.5]]), t_final=0.1, dt=0.01,
                              stepsize=jaxsleigh.StepSizeController(method="rk4"))
    fig = plotting.plot_hamiltonian(real)
    (text,) = [t.get_text() for t in fig.texts if t.get_gid() == STAMP_GID]
    assert "float32" in fig.get_suptitle() and f"device {device_text(None, real.run_info)}" in text


def test_the_stamp_names_each_setting_once_with_the_title():
    from matplotlib.figure import Figure

    from jaxsleigh.plots.base import provenance_line, stamp

    settings = {"dtype": "float32", "method": "adaptive", "dt": 0.01, "rtol": 1e-6, "atol": 1e-6, "eps": 0.35,
                "t_final": 2.0, "devices": ["cpu:0"]}
    fig = Figure()
    fig.suptitle("Basin (float32, adaptive RK4, dt = 0.01 s, ε = 0.3)")
    text = stamp(fig, settings).get_text()
    assert text.startswith("rtol = 1e-06, atol = 1e-06  ·  ε = 0.35  ·  T = 2 s  ·  device cpu:0"), text
    # alone (no title), it names everything
    assert provenance_line(settings).startswith("float32  ·  adaptive RK4  ·  dt = 0.01 s  ·  rtol")


def test_save_figure_writes_the_format_of_the_suffix(tmp_path):
    fig = plotting.plot_configuration(_tiny_solution())
    for suffix, magic in ((".png", b"\x89PNG\r\n\x1a\n"), (".pdf", b"%PDF"), (".svg", b"<?xml")):
        path = plotting.save_figure(fig, tmp_path / "sub" / f"f{suffix}")
        assert path.read_bytes()[:len(magic)] == magic


def test_plotting_into_given_axes_and_from_npz(tmp_path, capsys):
    from matplotlib.figure import Figure

    fig = Figure()
    ax = fig.add_subplot()
    assert plotting.plot_paths(_tiny_solution(bad=False), ax=ax) is fig
    assert "float64" in ax.get_title()
    assert plotting.format_start([-3, -2, math.pi / 8]) == "(−3, −2, π/8)"
    assert plotting.format_start([3, -1, -2.5]) == "(3, −1, −2.5)"
    g = plotting.sleigh_outline(1.0, 2.0, math.pi / 2, size=1.0)
    np.testing.assert_allclose(g["com"], [1.0, 3.0], atol=1e-12)   # centre of mass l ahead


def test_console_script_reports_errors_without_traceback(tmp_path):
    exe = shutil.which("jaxsleigh")
    cmd = [exe] if exe else [sys.executable, "-m", "jaxsleigh.cli"]
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    r = subprocess.run([*cmd, "simulate", "--ic", "1,1,0", "--out", str(tmp_path / "x.npz")],
                       capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 2
    assert r.stderr.startswith("jaxsleigh: error: ") and "theta0" in r.stderr and "Traceback" not in r.stderr


# ---------------------------------------------------------------------------------------------
# figures for a publication: no stamp on request, a readable momentum axis, no overlapping footer
# ---------------------------------------------------------------------------------------------

_PAPER_PLOTS = ("plot_paths", "plot_configuration", "plot_momentum", "plot_control", "plot_hamiltonian")


def _stamp_texts(fig):
    from jaxsleigh.plots.base import STAMP_GID

    return [t.get_text() for t in fig.texts if t.get_gid() == STAMP_GID or "jaxsleigh " in t.get_text()]


@pytest.mark.parametrize("name", _PAPER_PLOTS)
def test_stamp_false_leaves_the_provenance_line_off(name):
    sol = _tiny_solution()
    fn = getattr(plotting, name)
    (line,) = _stamp_texts(fn(sol))
    assert "device not recorded" in line
    fig = fn(sol, stamp=False)
    assert _stamp_texts(fig) == []
    assert not any("device" in t.get_text() for t in fig.texts)
    assert "float64" in fig.get_suptitle()              # the title still says what produced the data
    with pytest.raises(ValueError, match="^stamp must be True .* or False"):
        fn(sol, stamp="no")


def test_paper_no_stamp_draws_the_figures_without_it(tmp_path, capsys, monkeypatch):
    saved = {}
    real_save = plotting.save_figure

    def spy(fig, path, **kw):
        saved[os.path.basename(str(path))] = _stamp_texts(fig)
        return real_save(fig, path, **kw)

    monkeypatch.setattr(plotting, "save_figure", spy)
    rc, _, err = _run(["paper", "--out", str(tmp_path / "p"), "--dt", "0.05", "--t-final", "0.5", "--no-stamp"],
                      capsys)
    assert rc == 0, err
    assert sorted(saved) == sorted(f"{n}.png" for n in ("fig2_paths", "fig3_configuration", "fig4_momentum",
                                                          "fig5_control", "fig_hamiltonian"))
    assert all(v == [] for v in saved.values()), saved


def test_momentum_spike_does_not_flatten_the_rest():
    """A p2 spike of 23 at t ~ 0 against values below 1 later: the axes are symlog with the linear
    band below the spike, so the later values keep most of the axis; ``scale="linear"`` is there."""
    sol = _tiny_solution(bad=False)
    t = sol.t
    p = np.stack([np.stack([0.8 * np.exp(-t / 3), 23.0 * np.exp(-20 * t) + 0.3 * np.sin(t)], -1)] * 3)
    sol = sol._replace(p=p)
    fig = plotting.plot_momentum(sol)
    ax_p2 = fig.axes[1]
    assert ax_p2.get_yscale() == "symlog"
    thresh = ax_p2.yaxis.get_transform().linthresh
    late = np.abs(p[:, t > 0.5, 1]).max()
    assert late <= thresh < 23.0
    lin = plotting.plot_momentum(sol, scale="linear")
    assert {ax.get_yscale() for ax in lin.axes} == {"linear"}
    with pytest.raises(ValueError, match="scale must be 'symlog' or 'linear'"):
        plotting.plot_momentum(sol, scale="log")


@pytest.fixture(scope="module")
def small_basin():
    with pytest.warns(Warning):
        return jaxsleigh.run_basin(jaxsleigh.grid_starts(x="-2:2:4", y=0.5, theta="-2:2:3"), eps=0.3,
                                   t_final=10.0, dt=0.05, run=jaxsleigh.RunOptions(progress=False))


def test_basin_overview_footer_clears_the_histogram_label_and_no_stamp(small_basin):
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from jaxsleigh.plots import basin as bp

    fig = bp.plot_basin(small_basin)
    FigureCanvasAgg(fig)
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    (footer,) = [t for ax in fig.axes for t in ax.texts if t.get_gid() == bp.FOOTER_GID]
    hist_ax = footer.axes
    label = hist_ax.xaxis.label
    assert label.get_text() == r"$T_\varepsilon$ [s]"
    fb, lb = footer.get_window_extent(r), label.get_window_extent(r)
    assert not fb.overlaps(lb), (fb, lb)
    assert fb.y1 <= lb.y0 + 0.5                         # under the label
    assert fb.y0 >= 0 and fb.x1 <= fig.bbox.x1 + 0.5      # inside the figure
    assert "not settled by T" in footer.get_text()
    assert len(_stamp_texts(fig)) == 1 and _stamp_texts(bp.plot_basin(small_basin, stamp=False)) == []
    for fn in (bp.plot_t_eps_distribution, bp.plot_t_eps_scatter, bp.plot_fraction_vs_theta, bp.plot_basin_map):
        assert _stamp_texts(fn(small_basin, stamp=False)) == [], fn.__name__


def _all_texts(fig):
    out = [fig.get_suptitle()] + [t.get_text() for t in fig.texts]
    for ax in fig.axes:
        out += [ax.get_xlabel(), ax.get_ylabel(), ax.get_title()] + [t.get_text() for t in ax.texts]
        leg = ax.get_legend()
        out += [t.get_text() for t in leg.get_texts()] if leg else []
    for leg in fig.legends:
        out += [t.get_text() for t in leg.get_texts()]
    return out


def test_convergence_time_is_one_symbol_everywhere(small_basin):
    """Every basin figure writes the convergence time as mathtext $T_\\varepsilon$, never T_ε or T_eps."""
    from jaxsleigh.plots import basin as bp

    texts = []
    for fn in (bp.plot_basin, bp.plot_basin_map, bp.plot_t_eps_distribution, bp.plot_t_eps_scatter):
        texts += _all_texts(fn(small_basin))
    joined = "\n".join(texts)
    assert "T_ε" not in joined and "T_eps" not in joined
    assert joined.count(r"$T_\varepsilon$") >= 5


def test_reported_wall_time_includes_start_up_and_imports(tmp_path):
    """Besides the command's own time, the command line reports the process's whole wall time: at least
    the command's own (imports and start-up come on top), at most what the caller waited."""
    import re
    import time

    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-m", "jaxsleigh.cli", "simulate", "--ic", "1,1,0.5", "--t-final", "0.1",
                        "--out", str(tmp_path / "r.npz")], capture_output=True, text=True, env=env, timeout=300)
    outer = time.monotonic() - t0
    assert r.returncode == 0, r.stderr
    own = float(re.search(r"([0-9.]+) s wall \(", r.stdout).group(1))
    m = re.search(r"jaxsleigh simulate: ([0-9.]+) s wall in all since the process started \(Python start-up, "
                  r"imports, compilation, computing and writing\)", r.stderr)
    assert m, r.stderr
    total = float(m.group(1))
    assert own < total <= outer + 0.05, (own, total, outer)
    from jaxsleigh.cli.clock import process_elapsed

    secs, origin = process_elapsed()
    assert origin == "since the process started" and secs > 0


def _history(valid, loss):
    n = len(valid)
    return {"loss": np.asarray(loss, float), "valid": np.asarray(valid, bool),
            "best": np.minimum.accumulate(np.where(valid, loss, np.inf)), "grad_norm": np.linspace(1.0, 0.1, n),
            "L": np.tile([1.0, 2.0, 3.0], (n, 1)), "k": np.full(n, 0.5), "D_hat": np.tile(np.eye(2), (n, 1, 1)),
            "probe_attempts": np.linspace(100.0, 200.0, n)}


@pytest.mark.parametrize("valid, loss, top", [
    ([True, False, True, False], [0.8, np.nan, 0.5, 0.9], 0.8),      # non-finite rejected: at the largest valid loss
    ([False, False, False], [np.nan, 2.0, np.inf], 2.0),            # none valid: at the largest finite loss
    ([False, False], [np.nan, np.nan], 1.0),                        # none finite: at 1
])
def test_plot_history_draws_rejected_candidates_even_when_none_is_valid(valid, loss, top):
    """A tuning run whose every candidate was rejected is what one most wants to look at: `plot_history` draws
    it (it failed on numpy's empty reduction before) with the rejected marks at finite heights."""
    from jaxsleigh.plots.tuning import plot_history

    fig = plot_history(_history(valid, loss), probe_budget=150.0)
    ax = fig.axes[0]
    rejected = [ln for ln in ax.get_lines() if ln.get_label().startswith("rejected")]
    assert len(rejected) == 1 and len(fig.axes) == 4
    y = np.asarray(rejected[0].get_ydata(), float)
    expect = np.where(np.isfinite(np.asarray(loss)[~np.asarray(valid)]), np.asarray(loss)[~np.asarray(valid)], top)
    np.testing.assert_array_equal(y, expect)
    assert np.all(np.isfinite(y))
    assert fig._suptitle.get_text() == "Gain tuning"


def test_every_tuning_figure_draws_on_its_own_figure_and_into_given_axes():
    """Each figure of `jaxsleigh.plots.tuning` makes its own figure of as many panels as it draws, draws into as many
    axes given instead (and no other figure), and refuses a wrong number of axes by name."""
    from types import SimpleNamespace

    from jaxsleigh.plots import tuning as tp
    from jaxsleigh.plots.base import new_figure

    n = 4
    effort = {"energy": np.linspace(2.0, 1.0, n), "soft_loss": np.linspace(0.5, 0.2, n), "multiplier": np.ones(n),
              "probe_attempts": np.full(n, 50.0), "probe_active": np.array([False, True, False, False]),
              "valid": np.array([True, False, True, True])}
    search = {"generation": np.arange(n), "feasible": np.array([False, True, True, True]),
              "median_T": np.linspace(30.0, 20.0, n), "median_energy": np.linspace(3.0, 2.0, n),
              "sigma": np.linspace(0.5, 0.1, n)}
    row = SimpleNamespace(median_T=20.0, median_se=1.0, frac_converged=0.9, frac_se=0.05)
    fig_of = {
        "history": (4, lambda axes: tp.plot_history(_history([True] * n, np.linspace(1, 0.5, n)), axes=axes)),
        "effort": (3, lambda axes: tp.plot_effort_history(effort, budget=1.5, probe_budget=100.0, returned=2,
                                                          axes=axes)),
        "search": (3, lambda axes: tp.plot_search_history(search, reference={"median_T": 25.0, "median_energy": 2.5,
                                                                             "energy_budget": 2.5}, axes=axes)),
        "times": (2, lambda axes: tp.plot_convergence_times({"a": np.array([1.0, 2.0, np.inf, np.nan])}, axes=axes)),
        "per plant": (2, lambda axes: tp.plot_per_plant({"paper plant": {"paper": row, "tuned": row}}, axes=axes)),
    }
    for name, (panels, draw) in fig_of.items():
        own = draw(None)
        assert len(own.axes) >= panels, name             # (a twin axis adds one)
        given = new_figure((8.0, 6.0))
        axes = given.subplots(panels, 1)
        assert draw(list(axes)) is given, name
        with pytest.raises(ValueError, match=f"need {panels} axes, got {panels - 1}"):
            draw(list(axes)[:-1])
    front = {"method": "warm", "evaluations": 2, "points": [
        {"evaluation": {"median_energy": e, "median_T_0.05_s": t, "median_se_s": 0.5}} for e, t in ((1.0, 30.0),
                                                                                                  (2.0, 20.0))]}
    ax = new_figure((5.0, 4.0)).add_subplot(1, 1, 1)
    assert tp.plot_front(front, ax=ax) is ax.figure and len(tp.plot_front(front).axes) == 1
