"""One run lifecycle for every command that writes: Ctrl-C after the first chunk (or iteration) of every chunked
command and every tuner mode keeps the finished work, and ``--resume`` ends with the bytes of an uninterrupted run;
Ctrl-C while simulate, compare or paper writes leaves no output that claims to be complete, nor a lock, and the rerun
writes what an uninterrupted run writes.
While a chunked run works it holds one lock (next to its output, covering its chunk folder) and its chunk folder one
record file (``manifest.json``: the chunk store's fields and the command's options)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from jaxsleigh.cli import main as cli_main
from jaxsleigh.cli.common import EXIT_INTERRUPTED
from jaxsleigh.files.chunks import ChunkStore

#: the smallest run of every chunked command, in two chunks or more
CHUNKED = {
    "basin": ["basin", "--x", "-2:2:3", "--y", "-1:1:2", "--theta", "0.9", "--eps", "0.31", "--t-final", "5",
              "--dt", "0.05", "--method", "rk4", "--chunk-size", "3", "--no-progress"],
    "sweep": ["sweep", "--param", "k=0.05:0.4:2:log", "--samples", "4", "--seed", "3", "--x", "-1:1", "--y", "-1:1",
              "--theta", "0.3:1.5", "--eps", "0.2", "--t-final", "5", "--dt", "0.05", "--chunk-size", "4",
              "--no-progress"],
    "optimum": ["optimum", "--samples", "2", "--seed", "3", "--horizons", "10", "--intervals", "8", "--chunk-size", "1",
                "--no-progress"],
}


def _run(argv, capsys):
    rc = cli_main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def _locks(root: Path) -> list:
    return sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if ".lock." in p.name)


@pytest.mark.parametrize("command", [pytest.param(c, marks=pytest.mark.slow) if c == "optimum" else c  # optimum: 14 s cold
                                     for c in sorted(CHUNKED)])
def test_every_chunked_command_resumes_to_the_bytes_of_an_uninterrupted_run(tmp_path, capsys, monkeypatch, command):
    argv = CHUNKED[command]
    real, seen, saved = ChunkStore.save, {}, []

    def counted(self, *a, **k):
        saved.append(1)
        return real(self, *a, **k)

    whole = tmp_path / "whole.npz"
    with monkeypatch.context() as m:
        m.setattr(ChunkStore, "save", counted)
        rc, _, err = _run([*argv, "--out", whole], capsys)
    assert rc == 0 and len(saved) >= 2, err
    total = len(saved)
    out = tmp_path / "out.npz"
    chunks = tmp_path / "out.npz.chunks"

    def save(self, *a, **k):                       # Ctrl-C once the first chunk is written
        real(self, *a, **k)
        seen["locks"] = _locks(tmp_path)
        seen["record"] = json.loads((chunks / "manifest.json").read_text())
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(ChunkStore, "save", save)
        rc, _, err = _run([*argv, "--out", out], capsys)
    assert rc == EXIT_INTERRUPTED and "--resume" in err and not out.exists(), err
    assert seen["locks"] == [f".out.npz.lock.{seen['locks'][0].rsplit('.lock.', 1)[1]}"], seen["locks"]  # one lock
    record = seen["record"]
    assert {"key", "options"} <= set(record) and record["options"]["command"] == command, record
    # one record file beside the chunks kept: the first, and any whose stragglers the pool had finished by the
    # interruption (written then); work in progress of the others (pending_*.npz) may be there too
    names = sorted(p.name for p in chunks.iterdir() if not p.name.startswith("pending_"))
    kept = [n for n in names if n.startswith("chunk_")]
    assert names == kept + ["manifest.json"] and kept[0] == "chunk_000000.npz", names
    assert _locks(tmp_path) == []
    rc, _, err = _run([*argv, "--out", out], capsys)                     # never over the chunks, silently
    assert rc == 2 and "--resume" in err, err
    saved.clear()
    with monkeypatch.context() as m:
        m.setattr(ChunkStore, "save", counted)
        rc, _, err = _run([*argv, "--out", out, "--resume"], capsys)
    assert rc == 0 and len(saved) == total - len(kept), err             # the chunks kept are not computed again
    assert out.read_bytes() == whole.read_bytes() and not chunks.exists() and _locks(tmp_path) == []


def test_a_refused_resume_names_the_option_from_the_one_record_and_an_old_options_file_is_read(tmp_path, capsys):
    argv = CHUNKED["basin"]
    out = tmp_path / "b.npz"
    assert _run([*argv, "--out", out, "--keep-chunks"], capsys)[0] == 0
    chunks = tmp_path / "b.npz.chunks"
    assert not (chunks / "options.json").exists()
    out.unlink()
    rc, _, err = _run([*argv[:-1], "--eps", "0.2", "--no-progress", "--out", out, "--resume"], capsys)
    assert rc == 2 and "--eps 0.31 in the checkpoint vs --eps 0.2 now" in err, err
    # a folder of jaxsleigh 0.3 kept its options in options.json: still named
    record = json.loads((chunks / "manifest.json").read_text())
    (chunks / "options.json").write_text(json.dumps(record.pop("options")))
    (chunks / "manifest.json").write_text(json.dumps(record))
    rc, _, err = _run([*argv[:-1], "--eps", "0.2", "--no-progress", "--out", out, "--resume"], capsys)
    assert rc == 2 and "--eps 0.31 in the checkpoint vs --eps 0.2 now" in err, err


# ---------------------------------------------------------------------------------------------
# every tuner mode: Ctrl-C after its first iterations, --resume to an uninterrupted run's files
# ---------------------------------------------------------------------------------------------

from tuner_runs import FRONT, FRONT_VMAP, GRADIENT, LAW, SEARCH, VOLATILE  # noqa: E402  (the smallest run of each mode)


def _after_calls(module, name, n):
    """An interrupter: Ctrl-C in the ``n``-th call of ``module.name`` (the earlier ones done and checkpointed)."""
    def arm(m):
        real, calls = getattr(module, name), []

        def f(*a, **k):
            calls.append(1)
            if len(calls) == n:
                raise KeyboardInterrupt
            return real(*a, **k)
        m.setattr(module, name, f)
    return arm


def _gradient(m):
    from jaxsleigh.tuning import optimizer

    real = optimizer._Bar.update

    def update(self, it, row):
        real(self, it, row)
        if it == 1:
            raise KeyboardInterrupt
    m.setattr(optimizer._Bar, "update", update)


def _law(m):
    from jaxsleigh.tuning import law

    real = law._Descent._step

    def step(self, step_fn, it, *rest):
        if it == 2:
            raise KeyboardInterrupt
        return real(self, step_fn, it, *rest)
    m.setattr(law._Descent, "_step", step)


def _search(m):
    from jaxsleigh.tuning import cma_search

    _after_calls(cma_search, "evaluate_population", 4)(m)


def _front(m):
    from jaxsleigh.tuning import pareto

    _after_calls(pareto, "tune", 2)(m)


def _front_vmap(m):
    from jaxsleigh.tuning import pareto

    _after_calls(pareto, "_assess_candidates", 3)(m)


#: mode -> (argv, interrupter, writes a history, the history's fields that hold wall time, what Ctrl-C says)
TUNERS = {"gradient": (GRADIENT, _gradient, True, ("wall",), "interrupted after 2 iterations"),
          "search": (SEARCH, _search, True, ("wall_s",), "interrupted after 2 generations"),
          "law": (LAW, _law, True, (), "interrupted after 2 steps"),
          "front": (FRONT, _front, False, (), "interrupted after 1 of 2 points"),
          "front-vmap": (FRONT_VMAP, _front_vmap, False, (), "interrupted after 2 of 3 iterations; wrote the best "
                                                             "candidate so far of 2 of 2 budgets")}


def _doc(path) -> dict:
    def strip(d):
        return {k: strip(v) if isinstance(v, dict) else v for k, v in d.items() if k not in VOLATILE}

    return strip(json.loads(Path(path).read_text()))


@pytest.mark.slow
@pytest.mark.parametrize("mode", sorted(TUNERS))
def test_every_tuner_mode_resumes_to_the_files_of_an_uninterrupted_run(tmp_path, capsys, mode):
    argv, interrupt, history, wall, says = TUNERS[mode]
    hist = (lambda p: ["--history", p.with_suffix(".npz")]) if history else (lambda p: [])
    whole, out = tmp_path / "whole.json", tmp_path / "out.json"
    rc, _, err = _run([*argv, "--out", whole, *hist(whole)], capsys)
    assert rc == 0, err
    with pytest.MonkeyPatch.context() as m:
        interrupt(m)
        rc, _, err = _run([*argv, "--out", out, *hist(out)], capsys)
    assert rc == EXIT_INTERRUPTED and "--resume" in err and says in err, err
    kept = json.loads(out.read_text())                                       # the best so far, flagged
    assert kept.get("interrupted", kept.get("meta", {}).get("interrupted")) is True
    assert _locks(tmp_path) == []
    rc, _, err = _run([*argv, "--out", out, *hist(out)], capsys)              # never over the progress, silently
    assert rc == 2 and "--resume" in err, err
    rc, _, err = _run([*argv, "--out", out, *hist(out), "--resume"], capsys)
    assert rc == 0, err
    a = _doc(out)
    assert _doc(whole) == a and "interrupted" not in a and "interrupted" not in a.get("meta", {})
    assert not (tmp_path / "out.json.ckpt.npz").exists() and _locks(tmp_path) == []
    if history:
        a, b = (tmp_path / "whole.npz").read_bytes(), (tmp_path / "out.npz").read_bytes()
        if not wall:                                   # one deterministic writer: the same bytes
            assert a == b
        with np.load(tmp_path / "whole.npz") as za, np.load(tmp_path / "out.npz") as zb:
            assert za.files == zb.files
            for k in za.files:
                if k not in wall:
                    np.testing.assert_array_equal(za[k], zb[k], err_msg=k)


# ---------------------------------------------------------------------------------------------
# simulate, compare, paper: Ctrl-C while they write leaves nothing claimed complete, and the rerun writes what an
# uninterrupted run writes
# ---------------------------------------------------------------------------------------------

def _interrupt_writing(m, name: str):
    """Ctrl-C while the file called ``name`` is written: its bytes are in the temporary file, not yet renamed."""
    from jaxsleigh.files import npz
    from jaxsleigh.plots import base

    real = npz.atomic_write

    def atomic_write(path, write, **k):
        if Path(path).name != name:
            return real(path, write, **k)

        def part(f):
            write(f)
            raise KeyboardInterrupt
        return real(path, part, **k)
    m.setattr(npz, "atomic_write", atomic_write)
    m.setattr(base, "atomic_write", atomic_write)


def _left(root: Path) -> list:
    """Every file under ``root`` (temporary files and locks are hidden names: listed too)."""
    return sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file())


def _same_npz(a: Path, b: bytes) -> None:
    """``a`` holds what the bytes ``b`` hold: the same arrays, the same settings but the run's wall time (and so
    the content digest)."""
    import io

    with np.load(a) as za, np.load(io.BytesIO(b)) as zb:
        assert za.files == zb.files
        for k in za.files:
            if k not in ("settings_json", "__digest__"):         # the digest covers the wall time
                np.testing.assert_array_equal(za[k], zb[k], err_msg=k)
        sa, sb = (json.loads(str(z["settings_json"])) for z in (za, zb))
    for s in (sa, sb):
        s["run_info"].pop("wall_s")
    assert sa == sb


def test_simulate_interrupted_while_writing_leaves_no_output_and_the_rerun_writes_the_same(tmp_path, capsys):
    argv = ["simulate", "--ic", "-1,1,0.5", "--ic", "0.5,-1,1", "--t-final", "2", "--no-progress",
            "--out", tmp_path / "s.npz"]
    assert _run(argv, capsys)[0] == 0
    whole = (tmp_path / "s.npz").read_bytes()
    (tmp_path / "s.npz").unlink()
    with pytest.MonkeyPatch.context() as m:
        _interrupt_writing(m, "s.npz")
        rc, _, err = _run(argv, capsys)
    assert rc == EXIT_INTERRUPTED and "interrupted" in err, err
    assert _left(tmp_path) == []                         # no output, no part of it, no lock
    assert _run(argv, capsys)[0] == 0
    _same_npz(tmp_path / "s.npz", whole)


def test_compare_interrupted_while_drawing_writes_no_record_and_the_rerun_writes_the_same(tmp_path, capsys):
    argv = ["compare", "--controllers", "paper,astolfi", "--samples", "2", "--t-final", "3", "--seed", "1",
            "--out", tmp_path / "c.json", "--plot", tmp_path / "c.png"]
    assert _run(argv, capsys)[0] == 0
    whole = {p: (tmp_path / p).read_bytes() for p in ("c.json", "c.png")}
    for p in whole:
        (tmp_path / p).unlink()
    with pytest.MonkeyPatch.context() as m:
        _interrupt_writing(m, "c.png")                   # every row computed, the figure half written
        rc, _, err = _run(argv, capsys)
    assert rc == EXIT_INTERRUPTED and _left(tmp_path) == [], (err, _left(tmp_path))
    assert _run(argv, capsys)[0] == 0
    assert (tmp_path / "c.png").read_bytes() == whole["c.png"]
    a, b = (json.loads(x) for x in ((tmp_path / "c.json").read_text(), whole["c.json"]))
    for d in (a, b):
        d["run_info"].pop("wall_s")
    assert a == b


def test_paper_interrupted_between_its_figures_leaves_no_data_file_and_the_rerun_writes_the_same(tmp_path, capsys):
    """The paper's data file is written last: a folder without it holds no finished run. (Its smallest run: half a
    second of the paper's six starts, every figure drawn.)"""
    out = tmp_path / "p"
    argv = ["paper", "--out", out, "--dt", "0.05", "--t-final", "0.5"]
    assert _run(argv, capsys)[0] == 0
    whole = {p: (out / p).read_bytes() for p in _left(out)}
    for p in whole:
        (out / p).unlink()
    with pytest.MonkeyPatch.context() as m:
        _interrupt_writing(m, "fig4_momentum.png")
        rc, _, err = _run(argv, capsys)
    assert rc == EXIT_INTERRUPTED, err
    assert _left(out) == ["fig2_paths.png", "fig3_configuration.png"]       # no paper.npz, no part, no lock
    assert _run(argv, capsys)[0] == 0
    assert _left(out) == sorted(whole)
    for p, b in whole.items():
        if p == "paper.npz":
            _same_npz(out / p, b)
        else:
            assert (out / p).read_bytes() == b, p


# ---------------------------------------------------------------------------------------------
# one lock per run, seen from another process: a chunk store used on its own on the chunk folder of a live run
# ---------------------------------------------------------------------------------------------

_HOLD = """
import sys, time
from pathlib import Path
from jaxsleigh.files.runlock import RunLock
out, chunks = Path(sys.argv[2]), Path(sys.argv[2] + ".chunks")
if sys.argv[1] == "run":
    RunLock(out, "a-run", covers=(chunks,)).acquire()          # a run on out, covering its chunk folder
else:
    RunLock(chunks, "a-store", folder=True).acquire()          # a chunk store used on its own
print("ready", flush=True)
time.sleep(120)
"""


def _hold(kind: str, out: Path):
    import os
    import subprocess
    import sys

    root = str(Path(__file__).resolve().parents[1])
    env = {**os.environ, "PYTHONPATH": root + os.pathsep + os.environ.get("PYTHONPATH", "")}
    p = subprocess.Popen([sys.executable, "-c", _HOLD, kind, str(out)], stdout=subprocess.PIPE, env=env, text=True)
    assert p.stdout.readline().strip() == "ready"
    return p


def _end(p) -> None:
    import signal

    p.send_signal(signal.SIGKILL)
    p.wait(timeout=30)
    p.stdout.close()


def test_a_chunk_store_on_its_own_is_refused_the_chunk_folder_of_a_live_run_in_another_process(tmp_path):
    from jaxsleigh.errors import RunLockedError
    from jaxsleigh.files.runlock import RunLock

    out = tmp_path / "out.npz"
    chunks = tmp_path / "out.npz.chunks"
    p = _hold("run", out)
    try:
        assert _locks(tmp_path) == [f".out.npz.lock.{_locks(tmp_path)[0].rsplit('.lock.', 1)[1]}"]   # one lock
        store = ChunkStore(chunks, "another-key")
        with pytest.raises(RunLockedError, match="checkpoint folder .* is being written by another run"):
            store.open(resume=False, manifest={})
        assert [q.name for q in chunks.iterdir()] == [q.name for q in chunks.glob(".covered.*")]   # nothing written
    finally:
        _end(p)
    store.open(resume=False, manifest={})                  # the run is gone: its mark is stale, never in the way
    store.close()
    p = _hold("store", out)                                 # and the other way round
    try:
        with pytest.raises(RunLockedError, match="checkpoint folder .* is being written by another run"):
            RunLock(out, "a-run", covers=(chunks,)).acquire()
        assert _locks(tmp_path) == [f"out.npz.chunks/{_locks(tmp_path)[0].rsplit('/', 1)[1]}"]
    finally:
        _end(p)
