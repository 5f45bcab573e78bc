"""Nothing lost, nothing mixed: every way a run could lose or mix results, as a regression test.

Checkpoints that cannot mix runs, damaged files named and recomputed, outputs checked before any
work, an interrupted tuner that keeps its best gains and resumes to the same answer, one bad row
that never stops a batch, and a command line that answers every typed input with a message (exit
code 2), never a traceback.
"""
from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

import jaxsleigh as js
from jaxsleigh import cli
from jaxsleigh import tuning as tu
from jaxsleigh.tuning import optimizer
from jaxsleigh.errors import CheckpointError, DamagedCheckpointWarning, FlaggedStartsWarning
from jaxsleigh.status import Status


def run_cli(argv, capsys):
    rc = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    return rc, out, err


# small and fast: 0.5 s horizon, coarse steps
BASIN = ["--samples", "64", "--t-final", "0.5", "--dt", "0.05", "--chunk-size", "16", "--no-progress"]


# ---------------------------------------------------------------------------------------------
# checkpoints
# ---------------------------------------------------------------------------------------------

def test_resume_without_manifest_never_mixes_runs(tmp_path, capsys):
    """Chunks of a seed-3 run, manifest (the folder's one record) deleted, resumed with seed 4: refused by the chunks'
    own fingerprints."""
    out = tmp_path / "mm.npz"
    rc, _, err = run_cli(["basin", *BASIN, "--seed", "3", "--out", out, "--keep-chunks"], capsys)
    assert rc == 0, err
    chunks = tmp_path / "mm.npz.chunks"
    (chunks / "manifest.json").unlink()
    out.unlink()
    rc, _, err = run_cli(["basin", *BASIN, "--seed", "4", "--resume", "--out", out], capsys)
    assert rc == 2 and "written by a different run" in err and "mm.npz.chunks" in err, err
    assert not out.exists()
    # the original command resumes from its own chunks and gives the same file as a fresh run
    rc, out_text, err = run_cli(["basin", *BASIN, "--seed", "3", "--resume", "--out", out], capsys)
    assert rc == 0 and "4 chunk(s) resumed" in out_text, err
    fresh = tmp_path / "fresh.npz"
    assert run_cli(["basin", *BASIN, "--seed", "3", "--out", fresh], capsys)[0] == 0
    assert out.read_bytes() == fresh.read_bytes()


def test_damaged_chunks_are_named_and_recomputed(tmp_path):
    ics = js.sample_starts(48, seed=1).ics
    kw, run = dict(t_final=0.5, dt=0.05), js.RunOptions(chunk_size=16, progress=False)
    ref = js.run_ensemble(ics, **kw, run=run)
    d = tmp_path / "ck"
    js.run_ensemble(ics, **kw, run=run._replace(checkpoint_dir=d))
    raw = (d / "chunk_000000.npz").read_bytes()
    (d / "chunk_000000.npz").write_bytes(raw[: len(raw) // 2])          # truncated
    (d / "chunk_000001.npz").write_bytes(b"")                           # empty
    (d / "manifest.json").write_text("{not json")                       # corrupt manifest
    (d / ".chunk_000002.npz.999.tmp").write_bytes(b"leftover")          # a killed write's leftover
    with pytest.warns(DamagedCheckpointWarning) as record:
        res = js.run_ensemble(ics, **kw, run=run._replace(checkpoint_dir=d, resume=True))
    text = " | ".join(str(w.message) for w in record)
    assert "chunk_000000.npz" in text and "chunk_000001.npz" in text and "manifest.json" in text
    assert res.run_info["chunks_reused"] == 1                           # only chunk 2 was sound
    for f in ("T_eps", "q", "status", "n_steps"):
        np.testing.assert_array_equal(getattr(res, f), getattr(ref, f))
    assert json.loads((d / "manifest.json").read_text())["n"] == 48     # rewritten


def test_a_chunk_of_another_run_stops_the_api_too(tmp_path):
    kw, run = dict(t_final=0.5, dt=0.05), js.RunOptions(chunk_size=16, progress=False)
    d = tmp_path / "ck"
    js.run_ensemble(js.sample_starts(32, seed=1).ics, **kw, run=run._replace(checkpoint_dir=d))
    (d / "manifest.json").unlink()
    with pytest.raises(CheckpointError, match="chunk_000000.npz.*different run"):
        js.run_ensemble(js.sample_starts(32, seed=2).ics, **kw, run=run._replace(checkpoint_dir=d, resume=True))
    with pytest.raises(CheckpointError, match="resume=True"):          # and never overwritten silently
        js.run_ensemble(js.sample_starts(32, seed=2).ics, **kw, run=run._replace(checkpoint_dir=d))
    with pytest.raises(ValueError, match="needs checkpoint_dir"):
        js.run_ensemble(js.sample_starts(32, seed=2).ics, **kw, run=run._replace(resume=True))


# ---------------------------------------------------------------------------------------------
# outputs checked before the work
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("cmd", [
    ["simulate", "--ic", "1,1,0.5", "--t-final", "0.1", "--out", "{bad}/run.npz"],
    ["tune", "--steps", "1", "--out", "{bad}/g.json"],
    ["tune", "--steps", "1", "--out", "{ok}/g.json", "--history", "{bad}/h.npz"],
    ["basin", *BASIN, "--out", "{bad}/b.npz"],
    ["basin", *BASIN, "--out", "{ok}/b.npz", "--plot", "{bad}/b.png"],
    ["paper", "--out", "{bad}/paper"],
    ["bench", "--cache", "{bad}/cache"],
])
def test_unwritable_outputs_are_refused_before_any_work(tmp_path, capsys, monkeypatch, cmd):
    """'{bad}' is a regular file, so nothing can be created under it (true even for root)."""
    bad = tmp_path / "a_file"
    bad.write_text("x")
    import importlib

    def no_work(*a, **k):
        raise AssertionError("work started before the outputs were checked")

    for mod, name in [("jaxsleigh.studies.simulate", "drive_saving"), ("jaxsleigh.studies.ensemble", "drive_final"),
                      ("jaxsleigh.tuning.optimizer", "make_training_set"), ("jaxsleigh.plots.paper_run", "simulate"),
                      ("jaxsleigh.studies.bench", "run_ensemble")]:
        monkeypatch.setattr(importlib.import_module(mod), name, no_work)
    argv = [a.format(bad=bad, ok=tmp_path) for a in cmd]
    rc, _, err = run_cli(argv, capsys)
    assert rc == 2 and "a_file" in err, err


def test_output_folders_are_created(tmp_path, capsys):
    out = tmp_path / "new" / "deeper" / "run.npz"
    rc, _, err = run_cli(["simulate", "--ic", "1,1,0.5", "--t-final", "0.1", "--out", out], capsys)
    assert rc == 0 and out.exists(), err


# ---------------------------------------------------------------------------------------------
# the tuner: interrupted, it keeps its best gains; resumed, it ends where it would have
# ---------------------------------------------------------------------------------------------

TUNE = dict(config=tu.TuneConfig(steps=4, batch=24, n_attempts=2000, probe=0, verify=0),
            loss=tu.LossConfig(t_final=15.0), tune="L,k", progress=False)


def test_interrupted_tuning_resumes_to_the_same_answer(tmp_path):
    full = tu.tune("paper", **TUNE)
    ck = tmp_path / "tune.ckpt.npz"

    def stop_at_2(i, row):
        if i == 1:
            raise KeyboardInterrupt

    with pytest.raises(tu.TuningInterrupted) as info:
        tu.tune("paper", checkpoint=ck, callback=stop_at_2, **TUNE)
    part = info.value.partial
    assert part is not None and part.settings["interrupted"] and len(part.history.loss) == 2
    js.gains(part.gains.L, part.gains.k, part.gains.D_hat)             # valid gains
    with pytest.raises(ValueError, match="resume"):                     # never restarted over it silently
        tu.tune("paper", checkpoint=ck, **TUNE)
    resumed = tu.tune("paper", checkpoint=ck, resume=True, **TUNE)
    np.testing.assert_array_equal(resumed.history.loss, full.history.loss)
    np.testing.assert_array_equal(resumed.gains.L, full.gains.L)
    assert resumed.best_iteration == full.best_iteration
    with pytest.raises(ValueError, match="other settings"):
        tu.tune("paper", checkpoint=ck, resume=True, **{**TUNE, "tune": "L"})


def test_ctrl_c_in_tune_writes_the_best_gains_and_history(tmp_path, capsys, monkeypatch):
    calls = {"n": 0}
    real = optimizer._Bar.update

    def interrupt_second(self, it, row):
        calls["n"] += 1
        real(self, it, row)
        if calls["n"] == 2:
            raise KeyboardInterrupt

    monkeypatch.setattr(optimizer._Bar, "update", interrupt_second)
    out, hist = tmp_path / "g.json", tmp_path / "h.npz"
    argv = ["tune", "--out", out, "--history", hist, "--steps", "3", "--batch", "24", "--n-attempts", "2000",
            "--t-final", "15", "--tune", "L,k", "--validate", "0", "--probe-budget", "100000", "--no-progress"]
    rc, _, err = run_cli(argv, capsys)
    assert rc == 130 and "--resume" in err, err
    d = json.loads(out.read_text())
    assert d["meta"]["interrupted"] is True and len(d["L"]) == 3
    assert len(tu.load_history(hist).loss) == 2
    assert (tmp_path / "g.json.ckpt.npz").exists()
    rc, _, err = run_cli(argv, capsys)                                  # without --resume: refused
    assert rc == 2 and "--resume" in err
    monkeypatch.setattr(optimizer._Bar, "update", real)
    rc, out_text, err = run_cli([*argv, "--resume"], capsys)
    assert rc == 0, err
    d = json.loads(out.read_text())
    assert "interrupted" not in d["meta"] and d["meta"]["iterations_run"] == 3
    assert not (tmp_path / "g.json.ckpt.npz").exists()


# ---------------------------------------------------------------------------------------------
# one bad row never stops the batch
# ---------------------------------------------------------------------------------------------

def test_one_unrepresentable_row_is_flagged_and_named(tmp_path, capsys):
    ics = np.array([[1.0, 1.0, 0.5], [1.0, 1.0, 1e-200], [-1.0, 2.0, 1.0]])
    with pytest.warns(FlaggedStartsWarning, match=r"row 1 \(status 8 out_of_range") as rec:
        sol = js.simulate(ics, t_final=0.5, saveat=js.SaveAt(every=10))
    assert rec[0].message.rows == [1]
    assert sol.status.tolist() == [0, Status.OUT_OF_RANGE, 0]
    assert np.all(np.isnan(sol.q[1])) and np.all(np.isfinite(sol.q[[0, 2]]))
    with pytest.warns(FlaggedStartsWarning):
        res = js.run_ensemble(ics, t_final=0.5, run=js.RunOptions(progress=False))
    assert res.status.tolist() == [0, Status.OUT_OF_RANGE, 0] and np.isnan(res.T_eps[1])
    np.save(tmp_path / "s.npy", ics)
    rc, out, err = run_cli(["simulate", "--ics", tmp_path / "s.npy", "--t-final", "0.5", "--out",
                            tmp_path / "r.npz"], capsys)
    assert rc == 0 and "row 1" in err and "2 integrated, 1 out_of_range" in out, err
    rc, out, err = run_cli(["basin", "--ics", tmp_path / "s.npy", "--t-final", "0.5", "--out", tmp_path / "b.npz",
                            "--no-progress"], capsys)
    assert rc == 0 and "row 1" in err and "left out of the fraction" in err, err


def test_an_out_of_range_start_is_named_by_what_overflows_and_why():
    """A start far from the origin overflows float32 through its H_d (~|q|^2), not through a small theta0; the
    message said "|theta0| is so small" for (1e30, 1e30, 0.5). It names the quantities that overflow and the
    coordinates that make them; a start near theta = 0 is still named by its theta0."""
    with pytest.raises(ValueError, match="invalid") as far:
        js.simulate([1e30, 1e30, 0.5], t_final=0.5)
    text = str(far.value)
    assert "theta0" not in text and "H_d" in text and "|x| = 1e+30, |y| = 1e+30" in text and "x64" in text
    with pytest.warns(FlaggedStartsWarning) as rec:
        js.simulate([[1.0, 1.0, 0.5], [1.0, 1.0, 1e-30]], t_final=0.5, saveat=js.SaveAt(every=10))
    text = str(rec[0].message)
    assert "|theta0| = 1e-30 is so close to theta = 0" in text and "|x|" not in text


def test_the_plain_region_needs_no_compiled_check(monkeypatch):
    """`_representable` skips its float64 program for starts with |theta0| >= 1e-2 and |x|, |y|, |p| <= 1e2: every
    corner of that region (and random points in it) passes the full check in float32, so skipping it changes no
    status; a start outside the region still gets the full check."""
    import itertools

    from jaxsleigh.integrate import engine

    r, th = engine._PLAIN_REACH, engine._PLAIN_THETA
    corners = [(x, y, t, p1, p2) for x, y, p1, p2 in itertools.product((-r, r, 0.0), repeat=4)
               for t in (-th, th, -np.pi, np.pi)]
    rng = np.random.default_rng(0)
    inside = np.vstack([corners, np.column_stack([rng.uniform(-r, r, (500, 2)),
                                                  rng.choice([-1, 1], 500) * rng.uniform(th, np.pi, 500),
                                                  rng.uniform(-r, r, (500, 2))])])
    assert np.all(engine._representable(inside, np.float32))
    monkeypatch.setattr(engine, "_PLAIN_THETA", np.inf)                # force the compiled check everywhere
    assert np.all(engine._representable(inside, np.float32))
    monkeypatch.undo()
    outside = np.array([[1.0, 1.0, 1e-30, 0.0, 0.0], [1.0, 1.0, 0.5, 0.0, 0.0], [1e3, 0.0, 1e-3, 0.0, 0.0]])
    assert engine._representable(outside, np.float32).tolist() == [False, True, True]


def test_float32_underflow_hints_at_x64():
    with pytest.warns(FlaggedStartsWarning, match="x64"):
        sol = js.simulate([[1, 1, 0.5], [1, 1, 1e-30]], t_final=0.5, saveat=js.SaveAt(every=10))
    assert sol.status[1] == Status.OUT_OF_RANGE
    sol = js.simulate([[1, 1, 0.5], [1, 1, 1e-30]], t_final=0.01, dt=0.01, x64=True,
                      stepsize=js.StepSizeController(max_steps=50), saveat=js.SaveAt(every=1))
    assert sol.status[1] != Status.OUT_OF_RANGE                        # representable in float64


def test_no_trajectory_ok_exits_3(tmp_path, capsys):
    rc, out, err = run_cli(["simulate", "--ic", "1,1,1e-3", "--t-final", "1", "--max-steps", "20", "--out",
                            tmp_path / "r.npz"], capsys)
    assert rc == 3 and "1 budget_exhausted" in out and "no trajectory ended OK" in err


# ---------------------------------------------------------------------------------------------
# the Python API is as strict as the command line
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("kw, match", [
    (dict(gains=js.Gains(np.array([-1.0, 1.0, 1.0]), -0.1, np.eye(2))), "L must be finite and > 0"),
    (dict(gains=js.Gains(np.array([1.0, 1.0, 1.0]), -0.1, np.eye(2))), "k must be > 0"),
    (dict(gains=js.Gains(np.array([1.0, 1.0, 1.0]), True, np.eye(2))), "real"),
    (dict(gains="no_such_preset"), "not found.*'tuned'"),
    (dict(plant=js.PlantParams(m=-2.0)), "mass m must be > 0"),
    (dict(plant=js.PlantParams(m=np.nan)), "m must be finite"),
    (dict(stepsize=js.StepSizeController(rtol=-1)), "rtol must be > 0"),
    (dict(stepsize=js.StepSizeController(max_step=-1)), "max_step must be > 0"),
    (dict(stepsize=js.StepSizeController(max_steps=3_000_000_000)), "max_steps must be <="),
    (dict(stepsize=js.StepSizeController(max_steps=1.5)), "max_steps must be a whole number"),
    (dict(t_final=1e300, dt=1e290), "t_final must be <="),
    (dict(t_final=1e6, dt=1e-5), "more than one run can take"),
    (dict(x64="yes"), "x64 must be True or False"),
])
@pytest.mark.parametrize("entry", ["simulate", "run_ensemble"])
def test_api_validates_eagerly(entry, kw, match):
    fn = getattr(js, entry)
    with pytest.raises(ValueError, match=match):
        fn([[1.0, 1.0, 0.5], [2.0, 1.0, 1.0]], **{"t_final": 0.5, **kw})


@pytest.mark.parametrize("kw, match", [(dict(run=js.RunOptions(chunk_size=1.5)), "chunk_size must be a whole number"),
                                       (dict(run=js.RunOptions(chunk_size=0)), "chunk_size must be >= 1"),
                                       (dict(eps=True), "eps must be a real number")])
def test_run_ensemble_options(kw, match):
    with pytest.raises(ValueError, match=match):
        js.run_ensemble([[1.0, 1.0, 0.5]], t_final=0.5, **kw)


def test_preset_names_work_wherever_gains_do():
    a = js.simulate([1.0, 1.0, 0.5], t_final=0.5, gains="tuned")
    b = js.simulate([1.0, 1.0, 0.5], t_final=0.5, gains=js.load_gains("tuned"))
    np.testing.assert_array_equal(a.q, b.q)
    assert a.settings["gains"]["L"][0] > 10


# ---------------------------------------------------------------------------------------------
# quietly accepted nonsense, refused
# ---------------------------------------------------------------------------------------------

def test_gains_files_are_read_strictly(tmp_path):
    p = tmp_path / "g.json"
    p.write_text(json.dumps({"k": 0.2}))
    with pytest.raises(ValueError, match="lacks L, D_hat"):
        js.load_gains(p)
    p.write_text(json.dumps({"L": [1, 1, 1], "k": True, "D_hat": [1, 1]}))
    with pytest.raises(ValueError, match="k must be a real number, got True"):
        js.load_gains(p)
    p.write_text(json.dumps({"L": [1, "2", 1], "k": 0.1, "D_hat": [1, 1]}))
    with pytest.raises(ValueError, match="L must hold real numbers"):
        js.load_gains(p)
    with pytest.raises(ValueError, match="is a folder"):
        js.load_gains(tmp_path)


def test_start_files_are_read_strictly(tmp_path, capsys):
    np.save(tmp_path / "c.npy", np.ones((2, 3)) * (1 + 1j))
    (tmp_path / "t.npy").write_text("1,1,0.5\n2,2,1\n")
    (tmp_path / "e.npy").write_bytes(b"")
    for name, msg in [("c.npy", "complex"), ("t.npy", "name it .csv"), ("e.npy", "empty file")]:
        with warnings.catch_warnings():
            warnings.simplefilter("error")                         # no NumPy warning on the way
            rc, _, err = run_cli(["simulate", "--ics", tmp_path / name, "--out", tmp_path / "x.npz"], capsys)
        assert rc == 2 and msg in err and name in err, err


# ---------------------------------------------------------------------------------------------
# the command line: messages, never tracebacks
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv, expect", [
    (["simulate", "--ic", "1,1,1", "--max-steps", "3000000000"], "--max-steps must be <="),
    (["simulate", "--ic", "1,1,1", "--t-final", "1e300", "--dt", "1e290", "--out", "{tmp}/x.npz"],
     "--t-final must be <="),
    (["simulate", "--ic", "1,1,1", "--t-final", "1e7", "--dt", "1e-3", "--out", "{tmp}/x.npz"],
     "more than one run can take"),
    (["bench", "--dt", "0"], "--dt must be a finite number > 0"),
    (["bench", "--repeats", "0"], "--repeats must be >= 1"),
    (["bench", "--n-ics", "-5"], "--n-ics must be >= 1"),
    (["basin", "--x", "2:2:5", "--out", "{tmp}/b.npz"], "hold --x fixed write one value (e.g. --x 2)"),
    (["basin", "--samples", "10", "--seed", "-1", "--out", "{tmp}/b.npz"], "--seed must be >= 0"),
    (["tune", "--seed", "-1", "--out", "{tmp}/g.json"], "--seed must be >= 0"),
    (["tune", "--validate", "-1", "--out", "{tmp}/g.json"], "--validate must be >= 0"),
    (["basin", "--x", "-3:3:1e9", "--y", "-3:3:1e9", "--out", "{tmp}/b.npz"], "GiB"),
    (["basin", "--samples", "100000000000", "--out", "{tmp}/b.npz"], "GiB"),
])
def test_typed_input_gives_a_message_not_a_traceback(tmp_path, capsys, argv, expect):
    rc, _, err = run_cli([a.format(tmp=tmp_path) for a in argv], capsys)
    assert rc == 2 and err.startswith("jaxsleigh: error: ") and expect in err, err


def test_probe_budget_message_says_what_happened(tmp_path, capsys):
    rc, _, err = run_cli(["tune", "--out", tmp_path / "g.json", "--steps", "1", "--batch", "8", "--t-final", "5",
                          "--probe-budget", "1", "--validate", "0", "--no-progress"], capsys)
    assert rc == 2 and "--probe-budget 1" in err and "(got 1)" not in err and "stopped after" in err, err


# ---------------------------------------------------------------------------------------------
# compile once per machine: the command line's persistent compilation cache
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("off", [False, True])
def test_command_line_fills_the_compilation_cache_unless_turned_off(tmp_path, off):
    import os
    import subprocess
    import sys

    cache = tmp_path / "cache"
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "JAXSLEIGH_CACHE_DIR": str(cache)}
    if off:
        env["JAXSLEIGH_NO_COMPILE_CACHE"] = "1"
    r = subprocess.run([sys.executable, "-m", "jaxsleigh.cli", "simulate", "--ic", "1,1,0.5", "--t-final", "0.1",
                        "--out", str(tmp_path / "r.npz")], env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    entries = list(cache.rglob("*")) if cache.exists() else []
    assert (len(entries) == 0) if off else (len(entries) >= 3), entries
