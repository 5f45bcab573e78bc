"""The Python API's rough edges and the command line's late refusals.

* every loader says what kind of result file it got and which function reads it, and never
  speaks of ``run.json.npz``;
* the NumPy-returning fronts refuse JAX tracers with a ``TypeError`` that names the input and the
  differentiable path;
* ``print(result)`` shows a summary, not every array;
* ``--plot`` (and the other outputs) are checked before any work, naming the flag.

Results are built from arrays and written by the real writers (``save_basin``, ``save_sweep``,
``write_npz``), so no test here integrates anything.
"""
from __future__ import annotations

import importlib
import json
import re
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import jaxsleigh as js
from jaxsleigh import cli
from jaxsleigh.studies.basin import BasinResult, array_starts, load_basin, save_basin
from jaxsleigh.studies.config import solve_config
from jaxsleigh.studies.ensemble import EnsembleResult
from jaxsleigh.files.npz import write_npz
from jaxsleigh.plots.paper_figures import load_solution
from jaxsleigh.studies.simulate import Solution
from jaxsleigh.status import Status
from jaxsleigh.studies.sweep import SweepResult, load_sweep, parse_param, save_sweep

ROOT = Path(__file__).resolve().parents[1]


def run_cli(argv, capsys):
    rc = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    return rc, out, err


# ---------------------------------------------------------------------------------------------
# results made from arrays
# ---------------------------------------------------------------------------------------------

def _settings() -> dict:
    return solve_config(t_final=2.0, dt=0.05, stepsize=js.StepSizeController(method="rk4")).settings()


def _per_start(status, T_eps, Hd0=None, u_energy=None):
    status = np.asarray(status, np.int32)
    n = status.shape[0]
    T_eps = np.asarray(T_eps, np.float64)
    return dict(status=status, T_eps=T_eps, Hd0=np.arange(n, dtype=np.float64) if Hd0 is None else Hd0,
                u_energy=np.ones(n) if u_energy is None else u_energy, n=n)


def fake_ensemble(status, T_eps, Hd0=None, u_energy=None) -> EnsembleResult:
    d = _per_start(status, T_eps, Hd0, u_energy)
    n, z = d["n"], np.zeros(d["n"])
    return EnsembleResult(ics=np.ones((n, 5)), q_final=np.zeros((n, 3)), p_final=np.zeros((n, 2)), T_eps=d["T_eps"],
                          min_abs_theta=z, max_excursion=z, Hd0=d["Hd0"], Hd_final=z, t_reached=z,
                          n_steps=np.zeros(n, np.int64), n_rejected=np.zeros(n, np.int64), status=d["status"],
                          u_peak=np.zeros((n, 2)), u_norm_peak=z, u_energy=d["u_energy"], u_abs_int=z,
                          settings={**_settings(), "chunk_size": 16})


def fake_basin(status, T_eps, Hd0=None, u_energy=None) -> BasinResult:
    d = _per_start(status, T_eps, Hd0, u_energy)
    n, z = d["n"], np.zeros(d["n"])
    starts = array_starts(np.column_stack([np.ones(n), np.ones(n), np.full(n, 0.5)]))
    return BasinResult(starts=starts, ics=np.ones((n, 5)), T_eps=d["T_eps"], status=d["status"], Hd0=d["Hd0"],
                       Hd_final=z, min_abs_theta=z, max_excursion=z, n_steps=np.zeros(n, np.int64),
                       n_rejected=np.zeros(n, np.int64), q_final=np.zeros((n, 3)), p_final=np.zeros((n, 2)),
                       settings={**_settings(), "starts": starts.spec}, u_peak=np.zeros((n, 2)), u_norm_peak=z,
                       u_energy=d["u_energy"], u_abs_int=z)


def fake_sweep(n_starts: int = 3) -> SweepResult:
    axis = parse_param("k=0.1:0.2:2")
    P, N = 2, n_starts
    starts = array_starts(np.column_stack([np.ones(N), np.ones(N), np.full(N, 0.5)]))
    status = np.zeros((P, N), np.int32)
    status[1, 0] = int(Status.SINGULAR_START)
    T = np.full((P, N), 3.0)
    T[0, 0] = np.inf
    settings = {**_settings(), "starts": starts.spec,
                "sweep": {"names": ["k"], "axes": [axis.spec()], "n_values": P, "n_starts": N}}
    return SweepResult(names=("k",), values=axis.values()[:, None], grid_shape=(P,), axes=(axis,), starts=starts,
                       ics=np.ones((N, 5)), T_eps=T, status=status, n_steps=np.zeros((P, N), np.int64),
                       min_abs_theta=np.zeros((P, N)), Hd0=np.ones((P, N)), u_energy=np.ones((P, N)),
                       settings=settings)


def fake_solution(n: int = 2, T: int = 5) -> Solution:
    s = {**_settings(), "save_every": 1}
    s.pop("eps")
    return Solution(t=np.linspace(0, 1, T), q=np.zeros((n, T, 3)), p=np.zeros((n, T, 2)), u=np.zeros((n, T, 2)),
                    Hd=np.ones((n, T)), status=np.zeros(n, np.int32), n_steps=np.ones(n, np.int64),
                    n_rejected=np.zeros(n, np.int64), settings=s,
                    T_eps=np.full(n, 0.5), u_energy=np.ones(n))


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """One file of each kind, written by the library's writers."""
    d = tmp_path_factory.mktemp("files")
    return {"basin": save_basin(d / "b.npz", fake_basin([0, 0, 1], [1.0, np.inf, np.nan])),
            "sweep": save_sweep(d / "s.npz", fake_sweep()),
            "simulation": write_npz(d / "r.npz", fake_solution(), ics=np.ones((2, 3)))}


# ---------------------------------------------------------------------------------------------
# 1. loaders name the kind of file they got and the function that reads it
# ---------------------------------------------------------------------------------------------

LOADERS = {"basin": (load_basin, "jaxsleigh.load_basin", "a basin result"),
           "sweep": (load_sweep, "jaxsleigh.load_sweep", "a sweep result"),
           "simulation": (load_solution, "jaxsleigh.plots.paper_figures.load_solution", "a simulation")}


@pytest.mark.parametrize("loader", LOADERS)
@pytest.mark.parametrize("kind", LOADERS)
def test_each_loader_names_the_kind_of_file_it_got_and_its_reader(files, loader, kind):
    load = LOADERS[loader][0]
    if loader == kind:
        back = load(files[kind])
        assert np.asarray(back.status).size > 0
        return
    _, reader, name = LOADERS[kind]
    with pytest.raises(ValueError) as e:
        load(files[kind])
    msg = str(e.value)
    assert name in msg and f"read it with {reader}" in msg and str(files[kind]) in msg, msg


@pytest.mark.parametrize("suffix", [".json", ".txt", ".npy", ".csv"])
@pytest.mark.parametrize("exists", [True, False])
@pytest.mark.parametrize("load", [load_basin, load_sweep, load_solution])
def test_loaders_never_append_npz_to_another_extension(tmp_path, suffix, exists, load):
    p = tmp_path / f"result{suffix}"
    if exists:
        if suffix == ".npy":
            np.save(p, np.zeros(3))
        else:
            p.write_text(json.dumps({"L": [1, 2, 3]}))
    with pytest.raises(ValueError) as e:
        load(p)
    msg = str(e.value)
    assert f"result{suffix}.npz" not in msg and repr(str(p)) in msg, msg
    assert ".npz written by jaxsleigh" in msg, msg


def test_a_name_without_extension_still_finds_what_the_writer_wrote(tmp_path):
    # the writers append .npz to a bare name; the loaders look for it there
    save_basin(tmp_path / "plain", fake_basin([0], [1.0]))
    assert (tmp_path / "plain.npz").is_file()
    assert load_basin(tmp_path / "plain").status.tolist() == [0]
    with pytest.raises(ValueError, match=r"not found"):
        load_basin(tmp_path / "absent")


def test_an_npz_of_another_program_is_refused_with_what_it_lacks(tmp_path):
    np.savez(tmp_path / "other.npz", a=np.zeros(2), T_eps=np.zeros(2))
    for load, what in ((load_basin, "basin file"), (load_sweep, "sweep file"), (load_solution, "simulation file")):
        with pytest.raises(ValueError, match=rf"is not a {what}.*lacks .*its keys: T_eps, a"):
            load(tmp_path / "other.npz")


# ---------------------------------------------------------------------------------------------
# 2. the NumPy fronts refuse tracers, naming the input and the differentiable path
# ---------------------------------------------------------------------------------------------

ICS = np.array([[1.0, 1.0, 0.5]])
G = js.paper_gains()
P = js.paper_plant()
FRONTS = {
    "simulate": lambda **kw: js.simulate(kw.pop("ics", ICS), **kw, run=js.RunOptions(progress=False)),
    "run_ensemble": lambda **kw: js.run_ensemble(kw.pop("ics", ICS), **kw, run=js.RunOptions(progress=False)),
    "run_basin": lambda **kw: js.run_basin(kw.pop("ics", ICS), **kw, run=js.RunOptions(progress=False)),
    "sweep": lambda **kw: js.sweep(kw.pop("ics", ICS), {"l1": [1.0, 2.0]}, **kw, run=js.RunOptions(progress=False)),
}
# input name in the message -> keyword arguments built from the traced scalar x
INPUTS = {
    "gains.k": lambda x: {"gains": G._replace(k=x)},
    "gains.L": lambda x: {"gains": G._replace(L=G.L * x)},
    "plant.m": lambda x: {"plant": P._replace(m=x)},
    "t_final": lambda x: {"t_final": x},
    "eps": lambda x: {"eps": x},
    "ics": lambda x: {"ics": jnp.array([[1.0, 1.0, 0.5]]) * x},
}
TRANSFORMS = {"jit": jax.jit, "grad": jax.grad, "vmap": lambda f: (lambda x: jax.vmap(f)(jnp.stack([x, x])))}


@pytest.fixture
def no_work(monkeypatch):
    """Any integration fails the test: the refusal must come first."""
    def fail(*a, **k):
        raise AssertionError("work started before the tracer was refused")

    for mod, name in [("jaxsleigh.studies.simulate", "drive_saving"), ("jaxsleigh.studies.ensemble", "drive_final"),
                      ("jaxsleigh.studies.ensemble", "drive_saving"), ("jaxsleigh.studies.ensemble", "drive_plain")]:
        monkeypatch.setattr(importlib.import_module(mod), name, fail)


# no_work's patches hold for every example (they are never undone in between, on purpose)
@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(front=st.sampled_from(sorted(FRONTS)), where=st.sampled_from(sorted(INPUTS)),
       transform=st.sampled_from(sorted(TRANSFORMS)))
def test_fronts_refuse_tracers_naming_the_input_and_the_differentiable_path(no_work, front, where, transform):
    if front == "simulate" and where == "eps":
        where = "t_final"                      # simulate has no eps

    def f(x):
        out = FRONTS[front](**INPUTS[where](x))
        return jnp.sum(jnp.asarray(out.status))

    with pytest.raises(TypeError) as e:
        TRANSFORMS[transform](f)(jnp.float32(0.1))
    msg = str(e.value)
    if where == "ics" and front in ("run_basin", "sweep"):
        where = "starts"                       # their first argument's name
    assert msg.startswith(f"{front}() got a JAX tracer in {where}"), msg
    assert "neither jittable nor differentiable" in msg
    assert "jaxsleigh.solve" in msg


def test_the_differentiable_path_named_in_the_message_exists():
    from jaxsleigh import tuning
    from jaxsleigh.studies.config import DIFFERENTIABLE_PATHS

    for name in re.findall(r"jaxsleigh\.tuning\.(\w+)", DIFFERENTIABLE_PATHS):
        assert callable(getattr(tuning, name)), name
    assert "jaxsleigh.solve " in DIFFERENTIABLE_PATHS and callable(js.solve)


def test_concrete_jax_arrays_are_not_tracers(no_work):
    # a jax.Array of concrete numbers is an ordinary input: the front gets past the check (to the work)
    with pytest.raises(AssertionError, match="work started"):
        js.simulate(jnp.array([1.0, 1.0, 0.5]), gains=G._replace(k=jnp.float32(0.1)), t_final=1.0,
                    run=js.RunOptions(progress=False))


# ---------------------------------------------------------------------------------------------
# 3. print(result) is a summary
# ---------------------------------------------------------------------------------------------

status_codes = st.sampled_from([int(Status.OK)] * 4 + [int(Status.SINGULAR_START), int(Status.NONFINITE)])


@settings(max_examples=15, deadline=None)
@given(data=st.lists(st.tuples(status_codes, st.one_of(st.floats(0.5, 90.0), st.just(np.inf))),
                     min_size=1, max_size=40),
       make=st.sampled_from(["ensemble", "basin"]))
def test_repr_of_a_result_is_its_summary(data, make):
    status = np.array([s for s, _ in data], np.int32)
    T = np.array([t if s == 0 else np.nan for s, t in data])
    res = (fake_ensemble if make == "ensemble" else fake_basin)(status, T)
    text = repr(res)
    assert str(res) == text and len(text.splitlines()) <= 8
    conv = (status == 0) & np.isfinite(T)
    valid = status != int(Status.SINGULAR_START)
    assert f"N = {status.size}" in text
    assert f"{conv.sum()}/{valid.sum()} valid" in text
    for code in np.unique(status):
        assert f"{(status == code).sum()} {Status(int(code)).name.lower()}" in text
    if conv.any():
        assert f"T_eps median {np.median(T[conv]):.4g} s" in text
    else:
        assert "none converged" in text
    assert f"H_d(0) [J]: {'p10' if valid.any() else 'none'}" in text    # of the integrated starts
    assert "float32, rk4, t_final = 2 s, dt = 0.05 s, eps = 0.05" in text
    assert "k = 0.1" in text and f"T_eps ({status.size},)" in text


def test_repr_stays_short_for_a_large_result():
    n = 200_000
    rng = np.random.default_rng(0)
    res = fake_ensemble(np.zeros(n, np.int32), rng.uniform(1, 50, n), Hd0=rng.uniform(0, 10, n))
    text = repr(res)
    assert len(text) < 1500 and "N = 200000" in text and "= 1.0000" in text
    q = re.search(r"H_d\(0\) \[J\]: p10 ([\d.]+), median ([\d.]+), p90 ([\d.]+)", text)
    assert q and np.allclose([float(v) for v in q.groups()], [1.0, 5.0, 9.0], atol=0.05), text  # uniform(0, 10)


def test_repr_of_a_sweep_and_a_solution_are_summaries():
    text = repr(fake_sweep())
    assert text.startswith("SweepResult(N = 6 rows = 2 value sets x 3 starts; swept k 0.1..0.2: 5 ok, 1 singular_start")
    assert "4/5 valid" in text and "per value set: min 0.6667, max 1.0000" in text and "T_eps (2, 3)" in text
    sol_text = repr(fake_solution(n=3, T=7))
    assert sol_text.startswith("Solution(N = 3 trajectories, 7 saved times: 3 ok")
    assert "3/3 valid" in sol_text and "T_eps median 0.5 s" in sol_text and "q (3, 7, 3)" in sol_text
    assert len(sol_text.splitlines()) <= 8


# ---------------------------------------------------------------------------------------------
# 4. --plot and the other outputs are refused before any work, naming the flag
# ---------------------------------------------------------------------------------------------

BASIN = ["basin", "--samples", "8", "--t-final", "0.5", "--dt", "0.05", "--no-progress"]
SWEEP = ["sweep", "--param", "k=0.1:0.2:2", "--samples", "4", "--t-final", "0.5", "--dt", "0.05", "--no-progress"]
PARETO = ["tune", "--pareto", "2", "--steps", "1", "--batch", "4", "--no-progress"]


@pytest.fixture
def no_cli_work(monkeypatch):
    def fail(*a, **k):
        raise AssertionError("work started before the outputs were checked")

    for mod, name in [("jaxsleigh.studies.simulate", "drive_saving"), ("jaxsleigh.studies.ensemble", "drive_final"),
                      ("jaxsleigh.tuning.optimizer", "make_training_set"), ("jaxsleigh.tuning", "pareto_front")]:
        m = importlib.import_module(mod)
        if hasattr(m, name):
            monkeypatch.setattr(m, name, fail)


@pytest.mark.parametrize("cmd", [BASIN, SWEEP, PARETO])
@pytest.mark.parametrize("plot,why", [("fig.txt", "the extension .txt"), ("fig", "no extension"),
                                      ("fig.npz", "the extension .npz")])
def test_plot_with_no_figure_format_is_refused_before_any_work(tmp_path, capsys, no_cli_work, cmd, plot, why):
    out = tmp_path / ("o.json" if cmd is PARETO else "o.npz")
    rc, _, err = run_cli([*cmd, "--out", out, "--plot", tmp_path / plot], capsys)
    assert rc == 2, err
    assert f"--plot {str(tmp_path / plot)!r} has {why}" in err and ".png" in err and ".pdf" in err, err
    assert not out.exists() and list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("cmd", [BASIN, SWEEP])
def test_unwritable_plot_and_out_name_their_flag(tmp_path, capsys, no_cli_work, cmd):
    bad = tmp_path / "a_file"
    bad.write_text("x")
    rc, _, err = run_cli([*cmd, "--out", tmp_path / "o.npz", "--plot", bad / "f.png"], capsys)
    assert rc == 2 and "--plot file" in err and "a_file" in err, err
    rc, _, err = run_cli([*cmd, "--out", bad / "o.npz"], capsys)
    assert rc == 2 and "--out file" in err and "a_file" in err, err
    rc, _, err = run_cli(["simulate", "--ic", "1,1,0.5", "--out", bad / "r.npz"], capsys)
    assert rc == 2 and "--out file" in err and "a_file" in err, err


def test_tune_plot_that_would_be_ignored_is_refused(tmp_path, capsys, no_cli_work):
    rc, _, err = run_cli(["tune", "--steps", "1", "--out", tmp_path / "g.json", "--plot", tmp_path / "f.png"], capsys)
    assert rc == 2 and "--plot draws the Pareto front; add --pareto N" in err, err
    rc, _, err = run_cli([*PARETO, "--validate", "0", "--out", tmp_path / "f.json", "--plot", tmp_path / "f.png"],
                         capsys)
    assert rc == 2 and "--plot draws the front validated" in err, err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("suffix", [".png", ".PDF", ".svg"])
def test_figure_formats_matplotlib_writes_are_accepted(tmp_path, suffix):
    from jaxsleigh.cli.common import check_figure

    assert check_figure(tmp_path / "sub" / f"f{suffix}") == tmp_path / "sub" / f"f{suffix}"


def test_result_files_carry_a_format_version_and_old_files_still_load(tmp_path):
    """Version 2 files name their format; a file of 0.1 (no version) loads as before; a newer one is refused."""
    from jaxsleigh.files.npz import FORMAT_VERSION

    res = js.run_basin(js.grid_starts(x=(-1, 1, 2), y=(-1, 1, 2), theta=0.4), t_final=1.0,
                       run=js.RunOptions(progress=False))
    path = js.save_basin(tmp_path / "b.npz", res)
    with np.load(path) as z:
        data = {k: z[k] for k in z.files}
    assert int(data.pop("format_version")) == FORMAT_VERSION == 2
    data.pop("__digest__")                                      # the content digest came in 0.4
    np.savez(tmp_path / "v1.npz", **data)                       # as jaxsleigh 0.1 wrote it
    np.testing.assert_array_equal(js.load_basin(tmp_path / "v1.npz").T_eps, res.T_eps)
    np.savez(tmp_path / "v9.npz", **data, format_version=np.int64(9))
    with pytest.raises(ValueError, match="newer jaxsleigh .result format 9.*upgrade"):
        js.load_basin(tmp_path / "v9.npz")
