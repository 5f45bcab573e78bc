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

from tuner_runs import FRONT, FRONT_VMAP, GRADIENT, LAW, SEARCH  # noqa: E402  (the smallest run of each mode)


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


#: mode -> (argv, interrupter, writes a history, what Ctrl-C says)
TUNERS = {"gradient": (GRADIENT, _gradient, True, "interrupted after 2 iterations"),
          "search": (SEARCH, _search, True, "interrupted after 2 generations"),
          "law": (LAW, _law, True, "interrupted after 2 steps"),
          "front": (FRONT, _front, False, "interrupted after 1 of 2 points"),
          "front-vmap": (FRONT_VMAP, _front_vmap, False, "interrupted after 2 of 3 iterations; wrote the best "
                                                         "candidate so far of 2 of 2 budgets")}


def _files(root: Path) -> dict:
    """The bytes of every result file under ``root``: all but the sidecars ``*.run.json``."""
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and not p.name.endswith(".run.json")}


@pytest.mark.slow
@pytest.mark.parametrize("mode", sorted(TUNERS))
def test_every_tuner_mode_resumes_to_the_files_of_an_uninterrupted_run(tmp_path, capsys, monkeypatch, mode):
    """The same command, uninterrupted or interrupted and resumed, writes the same bytes (the command line recorded
    in the files is the same: relative names, in two folders); wall time, devices and ``--resume`` are in the
    sidecar ``out.run.json``."""
    argv, interrupt, history, says = TUNERS[mode]
    argv = [*argv, "--out", "out.json", *(["--history", "out.npz"] if history else [])]
    whole, part = tmp_path / "whole", tmp_path / "part"
    for d in (whole, part):
        d.mkdir()
    monkeypatch.chdir(whole)
    rc, out, err = _run(argv, capsys)
    assert rc == 0 and " s" in out, err
    assert "wall_s" not in (whole / "out.json").read_text()
    side = json.loads((whole / "out.run.json").read_text())
    assert side["wall_s"] > 0 and side["devices"] and side["command"][:2] == ["jaxsleigh", "tune"], side
    monkeypatch.chdir(part)
    with pytest.MonkeyPatch.context() as m:
        interrupt(m)
        rc, _, err = _run(argv, capsys)
    assert rc == EXIT_INTERRUPTED and "--resume" in err and says in err, err
    kept = json.loads((part / "out.json").read_text())                       # the best so far, flagged
    assert kept.get("interrupted", kept.get("meta", {}).get("interrupted")) is True
    assert _locks(tmp_path) == []
    rc, _, err = _run(argv, capsys)                                           # never over the progress, silently
    assert rc == 2 and "--resume" in err, err
    rc, _, err = _run([*argv, "--resume"], capsys)
    assert rc == 0, err
    a = json.loads((part / "out.json").read_text())
    assert "interrupted" not in a and "interrupted" not in a.get("meta", {})
    assert not (part / "out.json.ckpt.npz").exists() and _locks(tmp_path) == []
    assert json.loads((part / "out.run.json").read_text())["resumed"] is True
    got, want = _files(part), _files(whole)
    assert sorted(got) == sorted(want)
    for name, b in want.items():                        # the same bytes
        assert got[name] == b, name
    monkeypatch.chdir(whole)                            # and the same command again: the same bytes
    (whole / "out.json").unlink()
    if history:
        (whole / "out.npz").unlink()
    assert _run(argv, capsys)[0] == 0
    assert _files(whole) == want


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


def _ran(side: Path, command: str) -> None:
    """The sidecar ``side`` records what varies between runs: the command, its wall time and devices."""
    run = json.loads(side.read_text())
    assert run["command"][:2] == ["jaxsleigh", command] and run["wall_s"] > 0 and run["devices"], run


def test_simulate_interrupted_while_writing_leaves_no_output_and_the_rerun_writes_the_same(tmp_path, capsys):
    argv = ["simulate", "--ic", "-1,1,0.5", "--ic", "0.5,-1,1", "--t-final", "2", "--no-progress",
            "--out", tmp_path / "s.npz"]
    assert _run(argv, capsys)[0] == 0
    whole = (tmp_path / "s.npz").read_bytes()
    for p in ("s.npz", "s.run.json"):
        (tmp_path / p).unlink()
    with pytest.MonkeyPatch.context() as m:
        _interrupt_writing(m, "s.npz")
        rc, _, err = _run(argv, capsys)
    assert rc == EXIT_INTERRUPTED and "interrupted" in err, err
    assert _left(tmp_path) == []                         # no output, no part of it, no lock
    rc, out, _ = _run(argv, capsys)
    assert rc == 0 and " s wall " in out, out
    assert (tmp_path / "s.npz").read_bytes() == whole    # the same command, the same bytes
    _ran(tmp_path / "s.run.json", "simulate")
    with np.load(tmp_path / "s.npz") as z:
        assert "wall_s" not in str(z["settings_json"]) and "devices" not in str(z["settings_json"])


def test_compare_interrupted_while_drawing_writes_no_record_and_the_rerun_writes_the_same(tmp_path, capsys):
    argv = ["compare", "--controllers", "paper,astolfi", "--samples", "2", "--t-final", "3", "--seed", "1",
            "--audit-rows", "1", "--out", tmp_path / "c.json", "--plot", tmp_path / "c.png"]
    assert _run(argv, capsys)[0] == 0
    whole = {p: (tmp_path / p).read_bytes() for p in ("c.json", "c.png")}
    for p in (*whole, "c.run.json"):
        (tmp_path / p).unlink()
    with pytest.MonkeyPatch.context() as m:
        _interrupt_writing(m, "c.png")                   # every row computed, the figure half written
        rc, _, err = _run(argv, capsys)
    assert rc == EXIT_INTERRUPTED and _left(tmp_path) == [], (err, _left(tmp_path))
    rc, out, _ = _run(argv, capsys)
    assert rc == 0 and " s wall " in out, out
    for p, b in whole.items():                          # the same command, the same bytes
        assert (tmp_path / p).read_bytes() == b, p
    table = json.loads(whole["c.json"])
    assert "run_info" not in table and all(r["audit"]["rows"] == 1 for r in table["rows"])
    assert not any("wall_s" in r["audit"] or "share_of_run" in r["audit"] for r in table["rows"])
    _ran(tmp_path / "c.run.json", "compare")
    cost = json.loads((tmp_path / "c.run.json").read_text())["audit_cost"]   # what the audit cost, this time
    assert sorted(cost) == sorted(f"{law} on {d}" for law in ("paper", "astolfi") for d in ("near", "uniform", "wide"))
    assert all(c["wall_s"] > 0 for c in cost.values()), cost


def test_paper_interrupted_between_its_figures_leaves_no_data_file_and_the_rerun_writes_the_same(tmp_path, capsys):
    """The paper's data file is written last: a folder without it holds no finished run. (Its smallest run: half a
    second of the paper's six starts, every figure drawn.)"""
    out = tmp_path / "p"
    argv = ["paper", "--out", out, "--dt", "0.05", "--t-final", "0.5"]
    assert _run(argv, capsys)[0] == 0
    whole = {p: (out / p).read_bytes() for p in _left(out)}
    for p in whole:
        (out / p).unlink()
    assert "paper.run.json" in whole
    with pytest.MonkeyPatch.context() as m:
        _interrupt_writing(m, "fig4_momentum.png")
        rc, _, err = _run(argv, capsys)
    assert rc == EXIT_INTERRUPTED, err
    assert _left(out) == ["fig2_paths.png", "fig3_configuration.png"]       # no paper.npz, no part, no lock
    assert _run(argv, capsys)[0] == 0
    assert _left(out) == sorted(whole)
    for p, b in whole.items():                          # the same command, the same bytes, but its run record
        if p != "paper.run.json":
            assert (out / p).read_bytes() == b, p
    _ran(out / "paper.run.json", "paper")


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


# ---------------------------------------------------------------------------------------------
# the wall time lives in the sidecar; files that still hold it (jaxsleigh 0.3) load
# ---------------------------------------------------------------------------------------------

def test_a_history_reads_its_wall_time_from_itself_or_its_sidecar_and_an_old_simulate_file_loads(tmp_path):
    from jaxsleigh.files.npz import write_npz_deterministic
    from jaxsleigh.files.runner import sidecar, steady, write_sidecar
    from jaxsleigh.plots.paper_figures import _run_info, load_solution
    from jaxsleigh.tuning import load_history
    from jaxsleigh.tuning.history import save_arrays
    from jaxsleigh.tuning.optimizer import TuneHistory

    rows = {f: np.zeros((2, 3)) if f == "L" else np.arange(2.0) + 1 for f in TuneHistory._fields}
    old = write_npz_deterministic(tmp_path / "old.npz", rows, compress=False, stamped=False)   # wall inside
    np.testing.assert_array_equal(load_history(old).wall, [1.0, 2.0])
    new = save_arrays(tmp_path / "new.npz", rows)
    with np.load(new) as z:
        assert "wall" not in z.files
    assert np.isnan(load_history(new).wall).all()                           # no sidecar: not known
    write_sidecar(new, {"wall_s": 3.0, "history": {"wall": [0.5, 1.5]}})
    assert sidecar(new).name == "new.run.json"
    np.testing.assert_array_equal(load_history(new).wall, [0.5, 1.5])
    assert steady({"wall_s": 1.0, "devices": ["cpu:0"], "audit": {"rows": 0}}) == {"audit": {"rows": 0}}
    assert steady({"wall_s": 1.0, "devices": ["cpu:0"]}) is None

    # a simulate file of 0.3 kept wall time and devices in settings_json["run_info"]: it loads, and names its device
    import jaxsleigh as js
    from jaxsleigh.files.npz import write_npz

    sol = js.simulate(np.array([[1.0, 1.0, 0.5]]), t_final=0.1, dt=0.01,
                      stepsize=js.StepSizeController(method="rk4"), run=js.RunOptions(progress=False))
    path = write_npz(tmp_path / "s.npz", sol, ics=np.array([[1.0, 1.0, 0.5]]))
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files if k != "__digest__"}
    settings = json.loads(str(arrays["settings_json"]))
    assert settings["run_info"] is None                                     # nothing of the run's timing inside
    settings["run_info"] = {"wall_s": 0.25, "devices": ["cpu:0"]}
    arrays["settings_json"] = np.array(json.dumps(settings))
    old_sim = write_npz_deterministic(tmp_path / "old_s.npz", arrays)
    loaded = load_solution(old_sim)
    np.testing.assert_array_equal(loaded.q, sol.q)
    assert _run_info(loaded)["devices"] == ["cpu:0"]
