"""Every tuner mode owns its output: a run refuses an ``--out`` that another live run writes (exit code 5, naming it),
so does ``simulate``; and every mode (gradient, --search, --pareto, --controller) keeps its progress on Ctrl-C and
resumes with --resume to the file an uninterrupted run writes, to the last bit of every number. The same lifecycle
from Python: `jaxsleigh.tuning.runs`."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from jaxsleigh.cli import main as cli_main
from jaxsleigh.cli.common import EXIT_INTERRUPTED, EXIT_LOCKED
from jaxsleigh.errors import RunLockedError
from jaxsleigh.files.runlock import RunLock

REPO = Path(__file__).resolve().parents[1]

from tuner_runs import FRONT, GRADIENT, LAW, SEARCH, VOLATILE  # noqa: E402  (the smallest run of each mode)


def _run(argv, capsys):
    rc = cli_main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def _doc(path) -> dict:
    """The written JSON without what differs between two runs of the same settings."""
    def strip(d):
        return {k: strip(v) if isinstance(v, dict) else v for k, v in d.items() if k not in VOLATILE}

    return strip(json.loads(Path(path).read_text()))


def _arrays(path, drop=("wall", "wall_s")) -> dict:
    with np.load(path) as z:
        return {k: z[k] for k in z.files if k not in drop}


def _same_arrays(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def _interrupt_and_resume(tmp_path, capsys, argv, interrupt, *, history=True):
    """Run ``argv`` whole, then interrupted (``interrupt(monkeypatch context)`` arms the Ctrl-C) and resumed; returns
    ``(whole output, resumed output, stderr of the interrupted run)``."""
    whole, out = tmp_path / "whole.json", tmp_path / "out.json"
    hist = (lambda p: ["--history", p.with_suffix(".npz")]) if history else (lambda p: [])
    rc, _, err = _run([*argv, "--out", whole, *hist(whole)], capsys)
    assert rc == 0, err
    with pytest.MonkeyPatch.context() as m:
        interrupt(m)
        rc, _, said = _run([*argv, "--out", out, *hist(out)], capsys)
    assert rc == EXIT_INTERRUPTED and "--resume" in said, said
    kept = json.loads(out.read_text())                                       # the best so far, flagged
    assert kept.get("interrupted", kept.get("meta", {}).get("interrupted")) is True
    rc, _, err = _run([*argv, "--out", out, *hist(out)], capsys)              # never over the progress, silently
    assert rc == 2 and "--resume" in err, err
    rc, _, err = _run([*argv, "--out", out, *hist(out), "--resume"], capsys)
    assert rc == 0, err
    assert not (tmp_path / "out.json.ckpt.npz").exists() and not list(tmp_path.glob(".*.lock.*"))
    return whole, out, said


# ---------------------------------------------------------------------------------------------
# 1. Ctrl-C keeps the progress of every mode, and --resume ends where an uninterrupted run ends: one test of every
#    tuner mode, tests/test_interrupt_resume.py
# ---------------------------------------------------------------------------------------------

# ---------------------------------------------------------------------------------------------
# 2. a run owns its --out: another live run on it is refused, exit code 5, naming it
# ---------------------------------------------------------------------------------------------

HOLDER = textwrap.dedent("""
    import sys, time
    from jaxsleigh.files.runlock import RunLock
    RunLock(sys.argv[1], "another-run").acquire()
    print("ready", flush=True)
    time.sleep(120)
""")


@pytest.fixture
def holder():
    """``holder(path)``: a real process that holds the lock on ``path`` until the test ends."""
    procs = []

    def hold(path):
        env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
        p = subprocess.Popen([sys.executable, "-c", HOLDER, str(path)], stdout=subprocess.PIPE, env=env, text=True)
        procs.append(p)
        assert p.stdout.readline().strip() == "ready"
        return p

    yield hold
    for p in procs:
        os.kill(p.pid, signal.SIGKILL)
        p.wait(timeout=30)
        p.stdout.close()


@pytest.mark.parametrize("argv", [GRADIENT, SEARCH, FRONT, LAW], ids=["gradient", "search", "pareto", "controller"])
def test_every_tuner_mode_refuses_an_out_that_another_run_holds(tmp_path, capsys, argv):
    out = tmp_path / "g.json"
    with RunLock(out, "another-run"):
        rc, _, err = _run([*argv, "--out", out], capsys)
    assert rc == EXIT_LOCKED and "in use by another run" in err and f"pid {os.getpid()}" in err, err
    assert "choose another --out" in err and "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == []          # nothing written, the lock given back


def test_a_second_tune_is_refused_while_another_process_writes_its_out(tmp_path, capsys, holder):
    out = tmp_path / "g.json"
    p = holder(out)
    rc, _, err = _run([*GRADIENT, "--out", out], capsys)
    assert rc == EXIT_LOCKED and f"pid {p.pid}" in err and "another run" in err, err
    assert not out.exists() and not (tmp_path / "g.json.ckpt.npz").exists()


@pytest.mark.parametrize("given", ["run.npz", "run"])
def test_simulate_refuses_an_out_that_another_process_writes(tmp_path, capsys, holder, given):
    p = holder(tmp_path / "run.npz")                      # --out run writes run.npz: the same file
    rc, _, err = _run(["simulate", "--ic", "1,1,0.5", "--t-final", "0.1", "--out", tmp_path / given], capsys)
    assert rc == EXIT_LOCKED and f"pid {p.pid}" in err and "choose another --out" in err, err
    assert not (tmp_path / "run.npz").exists()


def test_simulate_gives_its_out_back_when_it_ends(tmp_path, capsys):
    out = tmp_path / "run.npz"
    for _ in range(2):                                    # the second run is not refused by the first's lock
        rc, _, err = _run(["simulate", "--ic", "1,1,0.5", "--t-final", "0.1", "--out", out], capsys)
        assert rc == 0, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.npz", "run.run.json"]   # and its sidecar
    with RunLock(out, "another-run"):
        rc, _, err = _run(["simulate", "--ic", "1,1,0.5", "--t-final", "0.1", "--out", out], capsys)
    assert rc == EXIT_LOCKED and "in use by another run" in err, err


# ---------------------------------------------------------------------------------------------
# 3. the same lifecycle from Python, in its own terms
# ---------------------------------------------------------------------------------------------

def test_the_library_run_refuses_a_held_out_a_stale_checkpoint_and_other_options(tmp_path):
    from jaxsleigh.tuning import TuneConfig
    from jaxsleigh.tuning.runs import TuningRun, tune_run

    out = tmp_path / "g.json"
    with RunLock(out, "another-run"):
        with pytest.raises(RunLockedError, match="in use by another run"):
            tune_run(out, config=TuneConfig(steps=1, batch=2))
    run = TuningRun(out, options={"seed": 0, "steps": 3})
    np.savez(run.checkpoint, options=np.array(json.dumps({"seed": 0, "steps": 2})))
    with pytest.raises(ValueError, match=r"interrupted tuning run .*add resume=True"):
        tune_run(run, config=TuneConfig(steps=1, batch=2))
    with pytest.raises(ValueError, match=r"^steps=2 in the checkpoint vs steps=3 now: "):
        tune_run(TuningRun(out, options={"seed": 0, "steps": 3}, resume=True), config=TuneConfig(steps=1, batch=2))
    np.savez(run.checkpoint, options=np.array(json.dumps({"--seed": 1})))       # as earlier versions named them
    with pytest.raises(ValueError, match=r"^seed=1 in the checkpoint vs seed=0 now: "):
        tune_run(TuningRun(out, options={"seed": 0}, resume=True), config=TuneConfig(steps=1, batch=2))
    run.checkpoint.unlink()
    with pytest.raises(ValueError, match="resume=True: no checkpoint"):
        tune_run(TuningRun(out, resume=True), config=TuneConfig(steps=1, batch=2))
    assert sorted(p.name for p in tmp_path.iterdir()) == []


@pytest.mark.parametrize("argv, name, folder", [(["compare", "--samples", "2", "--t-final", "5"], "c.json", False),
                                                (["paper"], "paper", True)], ids=["compare", "paper"])
def test_compare_and_paper_refuse_an_out_that_another_run_holds(tmp_path, capsys, argv, name, folder):
    """Every command that writes owns its --out: compare's table and paper's folder too (nothing computed)."""
    out = tmp_path / name
    with RunLock(out, "another-run", folder=folder):
        rc, _, err = _run([*argv, "--out", out], capsys)
    assert rc == EXIT_LOCKED and "in use by another run" in err and "choose another --out" in err, err
    assert "Traceback" not in err and not (out / "paper.npz").exists() and not out.is_file()
