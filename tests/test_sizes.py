"""Slice H2: every size a user gives is checked up front (the memory it needs, or a sane maximum for
what costs time), and the tuner's long runs keep their work when interrupted.

The memory checks are made deterministic by fixing the host memory the checks see
(``jaxsleigh.validate._available_bytes``)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import jaxsleigh.cli as cli
import jaxsleigh.validate as validate
from jaxsleigh.studies.sweep import param_grid, parse_param, sweep

GiB = 2**30


@pytest.fixture
def four_gib(monkeypatch):
    """The checks see 4 GiB of available host memory, whatever the machine has."""
    monkeypatch.setattr(validate, "_available_bytes", lambda: 4 * GiB)


# ---------------------------------------------------------------------------------------------
# sweep: values, value sets and rows are counted before anything is built
# ---------------------------------------------------------------------------------------------

def test_sweep_refuses_too_many_values_before_materialising_them(four_gib, monkeypatch):
    def no_materialising(*a, **k):
        raise AssertionError("values were materialised before the size check")

    monkeypatch.setattr(np, "linspace", no_materialising)
    with pytest.raises(ValueError, match=r"--param k=0:1:1e9: 1,000,000,000 values need about 238\.4 GiB .*"
                                         r"4\.0 GiB available; use fewer values"):
        parse_param("k=0:1:1e9")
    with pytest.raises(ValueError, match="P = inf must be a whole number"):
        parse_param("k=0.1:1:inf")


def test_sweep_refuses_a_grid_before_itertools_product(four_gib, monkeypatch):
    import itertools

    def no_product(*a, **k):
        raise AssertionError("itertools.product ran before the size check")

    a, b = parse_param("k=0.1:1:100000"), parse_param("m=1:2:100000")     # each fits on its own
    monkeypatch.setattr(itertools, "product", no_product)
    with pytest.raises(ValueError, match=r"--param k=0\.1:1:100000 x --param m=1:2:100000: 10,000,000,000 value "
                                         r"sets need about .* GiB"):
        param_grid([a, b])


def test_sweep_refuses_values_times_starts_naming_both(four_gib):
    starts = np.tile([[1.0, 1.0, 0.5]], (1000, 1))
    with pytest.raises(ValueError, match=r"sweep: 10,000,000 rows \(10,000 values x 1,000 starts\) need about "
                                         r"5\.2 GiB .* fewer starts"):
        sweep(starts, ["k=0.1:1:10000"], t_final=1.0)
    with pytest.raises(ValueError, match=r"rows \(10,000 values x 1,000 starts\)"):
        sweep(starts, {"k": np.linspace(0.1, 1, 10000)}, t_final=1.0)


@pytest.mark.parametrize("argv, flag", [
    (["--param", "k=0.01:1:1e7", "--samples", "256"], "jaxsleigh sweep: 2,560,000,000 rows"),
    (["--param", "k=0:1:1e9"], "--param k=0:1:1e9: 1,000,000,000 values"),
    (["--param", "k=0.1:1:1e5", "--param", "m=1:2:1e5"], "10,000,000,000 values x 256 starts"),
])
def test_cli_sweep_refuses_huge_sizes_with_exit_2(four_gib, tmp_path, capsys, argv, flag):
    out = tmp_path / "s.npz"
    rc = cli.main(["sweep", *argv, "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and flag in err and "GiB of host memory" in err and "Traceback" not in err
    assert not out.exists() and not (tmp_path / "s.npz.chunks").exists()


# ---------------------------------------------------------------------------------------------
# .npy starts: the header is checked against the file before anything is allocated
# ---------------------------------------------------------------------------------------------

def _forge(path, shape, descr, version, payload: bytes):
    header = {"descr": descr, "fortran_order": False, "shape": tuple(shape)}
    with open(path, "wb") as f:
        (np.lib.format.write_array_header_1_0 if version == 1 else np.lib.format.write_array_header_2_0)(f, header)
        f.write(payload)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(rows=st.integers(0, 10**12), cols=st.sampled_from([3, 5, 7]), descr=st.sampled_from(["<f8", "<f4", "<i8", "|u1"]),
       version=st.sampled_from([1, 2]), payload=st.binary(max_size=64))
def test_load_ics_checks_a_forged_header_against_the_file(tmp_path, rows, cols, descr, version, payload):
    from jaxsleigh.files.npz import load_ics

    path = tmp_path / "forged.npy"
    _forge(path, (rows, cols), descr, version, payload)
    need = rows * cols * np.dtype(descr).itemsize
    if need > len(payload):
        with pytest.raises(ValueError, match=r"forged\.npy'.*header claims an array of shape .* only "
                                             rf"{len(payload):,} bytes follow it"):
            load_ics(path)
    elif rows >= 1 and cols in (3, 5):
        assert load_ics(path).shape == (rows, cols)
    else:
        with pytest.raises(ValueError, match=r"forged\.npy"):
            load_ics(path)


@pytest.mark.parametrize("cmd", [["basin"], ["sweep", "--param", "k=0.1:1:2"]])
def test_cli_refuses_a_forged_ics_header_with_exit_2(tmp_path, capsys, cmd):
    path = tmp_path / "huge.npy"
    _forge(path, (10**10, 3), "<f8", 1, b"\x00" * 24)
    rc = cli.main([*cmd, "--ics", str(path), "--out", str(tmp_path / "o.npz"), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and "huge.npy" in err and "only 24 bytes follow it" in err and "Traceback" not in err


# ---------------------------------------------------------------------------------------------
# tune --search: bounded sizes; no feasible candidate keeps the history and exits 3
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv, msg", [
    (["--steps", "1000000"], "--steps (generations of --search) 1,000,000 is more than the 10,000 allowed"),
    (["--population", "100000"], "--population 100,000 is more than the 4,096 allowed"),
    (["--population", "4000", "--batch", "1000000"], "--population x --batch: 4,000,000,000 trajectories"),
])
def test_cli_search_bounds_population_and_generations(four_gib, tmp_path, capsys, argv, msg):
    rc = cli.main(["tune", "--search", "--out", str(tmp_path / "g.json"), "--no-progress", *argv])
    err = capsys.readouterr().err
    assert rc == 2 and msg in err and "Traceback" not in err
    assert not (tmp_path / "g.json").exists()


def test_search_bounds_its_sizes_in_python():
    from jaxsleigh import tuning as tu

    with pytest.raises(ValueError, match=r"search: generations 20,000 is more than the 10,000 allowed"):
        tu.search(config=tu.SearchConfig(generations=20_000))
    with pytest.raises(ValueError, match=r"search: population 5,000 is more than the 4,096 allowed"):
        tu.search(config=tu.SearchConfig(population=5_000))


def test_cli_search_without_a_feasible_candidate_writes_its_history_and_exits_3(tmp_path, capsys):
    out, hist = tmp_path / "g.json", tmp_path / "h.npz"
    rc = cli.main(["tune", "--search", "--out", str(out), "--steps", "1", "--batch", "4", "--population", "2",
                   "--energy-margin", "0.001", "--history", str(hist), "--validate", "0", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 3, err
    assert "--energy-margin" in err and "--steps" in err and "energy_margin" not in err and "Traceback" not in err
    assert not out.exists()
    with np.load(hist) as z:
        assert len(z["generation"]) == 1 and not z["feasible"].any()
    assert (tmp_path / "g.json.ckpt.npz").exists()          # more generations resume the finished run


# ---------------------------------------------------------------------------------------------
# tune --pareto: bounded count; Ctrl-C keeps the finished points, --resume continues
# ---------------------------------------------------------------------------------------------

def test_cli_pareto_bounds_the_number_of_points(tmp_path, capsys):
    rc = cli.main(["tune", "--pareto", "1000", "--out", str(tmp_path / "f.json"), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and "--pareto 1,000 is more than the 100 allowed" in err and "50 minutes" in err
    assert not (tmp_path / "f.json").exists()
    from jaxsleigh import tuning as tu

    with pytest.raises(ValueError, match="the number of budgets 101 is more than the 100 allowed"):
        tu.pareto_front(np.geomspace(1, 100, 101))


FRONT = ["tune", "--pareto", "3", "--steps", "2", "--warm-steps", "1", "--batch", "4", "--t-final", "10",
         "--n-attempts", "1500", "--tune", "L,k", "--validate", "0", "--budgets", "5:50", "--no-progress"]


def test_cli_pareto_interrupted_keeps_the_finished_points_and_resumes(tmp_path, capsys, monkeypatch):
    import json

    from jaxsleigh.tuning import pareto

    out = tmp_path / "front.json"
    real, calls = pareto.tune, []

    def ctrl_c_at_the_second_point(*a, **k):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(pareto, "tune", ctrl_c_at_the_second_point)
    rc = cli.main([*FRONT, "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 130 and "interrupted after 1 of 3 points" in err and "--resume" in err
    doc = json.loads(out.read_text())
    assert doc["interrupted"] is True and len(doc["points"]) == 1
    first = doc["points"][0]
    # without --resume the partial front is not overwritten
    assert cli.main([*FRONT, "--out", str(out)]) == 2 and "add --resume" in capsys.readouterr().err
    monkeypatch.setattr(pareto, "tune", real)
    calls.clear()
    rc = cli.main([*FRONT, "--out", str(out), "--resume"])
    assert rc == 0, capsys.readouterr().err
    doc = json.loads(out.read_text())
    assert "interrupted" not in doc and len(doc["points"]) == 3
    kept = [p for p in doc["points"] if p["budget"] == first["budget"]][0]
    assert kept["L"] == first["L"] and kept["k"] == first["k"] and kept["train"] == first["train"]
    # the resumed front is the front an uninterrupted run computes
    assert cli.main([*FRONT, "--out", str(tmp_path / "whole.json")]) == 0
    whole = json.loads((tmp_path / "whole.json").read_text())
    assert [(p["L"], p["k"]) for p in whole["points"]] == [(p["L"], p["k"]) for p in doc["points"]]


def test_a_front_compiles_the_optimiser_step_once_per_setting_not_per_point():
    import jax

    from jaxsleigh import tuning as tu
    from jaxsleigh.tuning import optimizer

    compiled = jax.jit(optimizer.optimizer_step, static_argnums=0)._cache_size   # jit's cache of the step (shared)
    optimizer._optimizer_and_step.cache_clear()
    before = compiled()
    cfg = tu.TuneConfig(steps=2, batch=4, lr=0.2, warmup=1, seed=1, n_attempts=1500, probe=2, verify=1)
    front = tu.pareto_front([5.0, 12.0, 25.0, 50.0], config=cfg, loss=tu.LossConfig(t_final=10.0), warm_steps=1,
                            tune_names="L,k", progress=False)
    assert len(front.points) == 4
    info = optimizer._optimizer_and_step.cache_info()
    # the first point (2 steps) and the three warm ones (1 step): two settings, two compiled steps; a new
    # optimiser per point added a compiled step (kept for good) per point, and memory grew with the points
    assert info.currsize == 2 and info.hits == 2
    assert compiled() - before == 2


# ---------------------------------------------------------------------------------------------
# optimum, tune, bench, simulate: every size is estimated before any work, on the command line and in Python
# ---------------------------------------------------------------------------------------------

def _no_work(monkeypatch, target, name):
    def refused(*a, **k):
        raise AssertionError(f"{name} ran before the size check")

    monkeypatch.setattr(target, name, refused)


@pytest.mark.parametrize("argv, msg", [
    (["--samples", "4", "--horizons", "1e9"],
     ("--horizons up to 1e+09 s: 80,000,000,064 RK4 steps held for the gradient (8 problems at once x "
      "10,000,000,008 steps of at most 0.1 s) need about 40,233.1 GiB of host memory, more than the 4.0 GiB "
      "available")),
    (["--samples", "1000000000"], "--samples: 1,000,000,000 starts need about 3,434.7 GiB"),
    (["--samples", "4", "--horizons", "5,1e12"], "--horizons up to 1e+12 s: 80,000,000,000,064 RK4 steps"),
    (["--samples", "1", "--guesses", "1", "--horizons", "1e4", "--inner", "100000"],
     ("--horizons up to 10000 s (100,008 RK4 steps) x --outer 20 x --inner 100,000: the steps of one problem's "
      "iterations 200,016,000,000 is more than the 600,000,000 allowed")),
    (["--samples", "4", "--inner", "100000"], "--inner 100,000: the steps of one problem's iterations 816,000,000"),
])
def test_cli_optimum_refuses_sizes_before_drawing_or_solving(four_gib, tmp_path, capsys, monkeypatch, argv, msg):
    from jaxsleigh.studies import optimum
    from jaxsleigh.tuning.starts import UniformStarts

    _no_work(monkeypatch, optimum, "_solve_starts")
    _no_work(monkeypatch, UniformStarts, "__call__")
    out = tmp_path / "opt.npz"
    rc = cli.main(["optimum", *argv, "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and msg in err and "Traceback" not in err, err
    assert not out.exists() and not (tmp_path / "opt.npz.chunks").exists()


def test_optimum_refuses_sizes_in_python(four_gib, monkeypatch):
    import jaxsleigh as js
    from jaxsleigh.studies import optimum

    _no_work(monkeypatch, optimum, "_solve_starts")
    start = np.array([[1.0, 1.0, 0.5]])
    with pytest.raises(ValueError, match=r"^horizons up to 1e\+09 s: 20,000,000,016 RK4 steps held for the gradient "
                                         r".* use shorter horizons, or solve fewer problems at once \(a smaller "
                                         r"run.chunk_size, options.guesses 1\)"):
        js.optimum(start, horizons=(5.0, 1e9))
    with pytest.raises(ValueError, match=r"^starts: 100,000 starts need about .* GiB .* give fewer starts, fewer "
                                         r"horizons or fewer options.intervals"):
        js.optimum(np.tile(start, (100_000, 1)), horizons=np.arange(1.0, 101.0),
                   options=js.OptimumOptions(intervals=4096))
    with pytest.raises(ValueError, match=r"options.inner 100,000: the steps of one problem's iterations .* more than "
                                         r"the 600,000,000 allowed"):
        js.optimum(start, options=js.OptimumOptions(inner=100_000))


@pytest.mark.parametrize("argv, msg", [
    (["--batch", "1000000000"], ("--batch: 1,000,000,000 training starts need about 18,626.5 GiB of host memory, "
                                 "more than the 4.0 GiB available; use a smaller --batch")),
    (["--batch", "1099511627776"], "--batch must be <= 2147483646"),
    (["--validate", "1000000000"], "--validate: 1,000,000,000 starts need about 372.5 GiB"),
    (["--search", "--validate", "10000000000"], "--validate must be <= 2147483646"),
    (["--search", "--validate", "20000000"], "--validate: 20,000,000 starts need about 7.5 GiB"),
    (["--t-final", "1e9"], ("--t-final 1e+09 s needs at least 10,000,000,000 steps of at most the step cap "
                            "(10 x --dt) 0.1 s, more than the 4,000 attempted steps a start may take (--n-attempts)")),
    (["--t-final", "1e12", "--n-attempts", "5000"], "use --t-final 500 or less, or raise --n-attempts"),
    (["--steps", "100000000"], "--steps 100,000,000 is more than the 10,000 allowed"),
    (["--steps", "20000", "--controller", "sontag"], "--steps 20,000 is more than the 10,000 allowed"),
    (["--pareto", "3", "--warm-steps", "100000000"], "--warm-steps 100,000,000 is more than the 10,000 allowed"),
    (["--pareto", "50", "--front-method", "vmap", "--batch", "100000"],
     "--batch x --pareto: 5,000,000 training starts need about 93.1 GiB"),
])
def test_cli_tune_refuses_sizes_before_tuning(four_gib, tmp_path, capsys, monkeypatch, argv, msg):
    from jaxsleigh.tuning import cma_search, optimizer, pareto
    from jaxsleigh.tuning.starts import UniformStarts

    for module, name in ((optimizer, "prepare_run"), (UniformStarts, "__call__"), (cma_search, "search"),
                         (pareto, "training_energy")):
        _no_work(monkeypatch, module, name)
    out = tmp_path / "g.json"
    rc = cli.main(["tune", *argv, "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and msg in err and "Traceback" not in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_tuners_refuse_sizes_in_python(four_gib, tmp_path, monkeypatch):
    from jaxsleigh import tuning as tu
    from jaxsleigh.tuning import optimizer
    from jaxsleigh.tuning.runs import HeldOut, tune_run
    from jaxsleigh.tuning.starts import UniformStarts

    _no_work(monkeypatch, optimizer, "prepare_run")
    _no_work(monkeypatch, UniformStarts, "__call__")
    with pytest.raises(ValueError, match=r"^steps 20,000 is more than the 10,000 allowed"):
        tu.tune(config=tu.TuneConfig(steps=20_000))
    with pytest.raises(ValueError, match=r"^batch: 1,000,000,000 training starts need about 18,626\.5 GiB"):
        tu.tune(config=tu.TuneConfig(batch=10**9))
    with pytest.raises(ValueError, match=r"^t_final 1e\+09 s needs at least 10,000,000,000 steps of at most max_step "
                                         r"0\.1 s, more than the 4,000 attempted steps a start may take \(n_attempts\)"):
        tu.tune(loss=tu.LossConfig(t_final=1e9))
    with pytest.raises(ValueError, match=r"^t_final 1e\+12 s"):
        tu.pareto_front(3, loss=tu.LossConfig(t_final=1e12))
    with pytest.raises(ValueError, match=r"^warm_steps 100,000,000 is more than the 10,000 allowed"):
        tu.pareto_front(3, warm_steps=10**8)
    with pytest.raises(ValueError, match=r"^held_out.n: 1,000,000,000 starts need about 372\.5 GiB"):
        tune_run(tmp_path / "g.json", config=tu.TuneConfig(steps=1, batch=2), held_out=HeldOut(n=10**9))
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("argv, msg", [
    (["--n-ics", "1000000000"], "--n-ics: 1,000,000,000 starts need about 1,862.6 GiB"),
    (["--n-ics", "100000", "--t-final", "10000"],
     ("--n-ics 100,000 x 1,000,000 base steps (--t-final / --dt): the trajectory-steps 100,000,000,000 is more "
      "than the 10,485,760,000 allowed")),
])
def test_bench_refuses_sizes_before_drawing_the_workload(four_gib, capsys, monkeypatch, argv, msg):
    from jaxsleigh.studies import bench

    _no_work(monkeypatch, bench, "workload")
    rc = cli.main(["bench", *argv])
    err = capsys.readouterr().err
    assert rc == 2 and msg in err and "Traceback" not in err and "compiling" not in err, err
    with pytest.raises(ValueError, match=r"^n_ics: 1,000,000,000 starts"):
        bench.bench(n_ics=10**9)


def test_simulate_refuses_saved_points_that_do_not_fit(four_gib, tmp_path, capsys, monkeypatch):
    import jaxsleigh as js
    from jaxsleigh.studies import simulate

    _no_work(monkeypatch, simulate, "drive_saving")
    starts = np.tile([[1.0, 1.0, 0.5]], (1000, 1))
    np.save(tmp_path / "ics.npy", starts)
    out = tmp_path / "run.npz"
    rc = cli.main(["simulate", "--ics", str(tmp_path / "ics.npy"), "--t-final", "4e5", "--save-every", "1",
                   "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err, err
    assert ("--ics x --t-final / --save-every: 40,000,001,000 saved points (1,000 starts x 40,000,001 points each) "
            "need about 7,152.6 GiB of host memory, more than the 4.0 GiB available; save fewer points (a larger "
            "--save-every, a shorter --t-final) or simulate fewer starts") in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ics.npy"]
    with pytest.raises(ValueError, match=r"^ics x t_final / saveat.every: 4,000,001,000 saved points"):
        js.simulate(starts, t_final=4e5)
    with pytest.raises(ValueError, match=r"^ics x t_final / saveat.every: 40,000,001 saved points \(1 start x"):
        js.simulate(starts[0], t_final=4e5, saveat=js.SaveAt(every=1))


@pytest.mark.parametrize("argv, msg", [
    (["--samples", "1000000000000"], "--samples: 1,000,000,000,000 starts need about"),
    (["--x=-3:3:100000", "--theta=-3:3:100000"], "--x -3:3:100000 x --theta -3:3:100000: 10,000,000,000 starts"),
])
def test_cli_basin_names_the_flag_of_a_size_that_does_not_fit(four_gib, tmp_path, capsys, argv, msg):
    """The command line's refusal names the flags a user typed, not the Python function behind them."""
    out = tmp_path / "b.npz"
    rc = cli.main(["basin", *argv, "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and msg in err and "_starts" not in err and "Traceback" not in err, err
    assert not out.exists()
