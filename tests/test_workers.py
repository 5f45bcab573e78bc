"""Runs whose chunks are computed by the workers of a Dask cluster (``--workers N``): the same ``.npz``, byte for
byte, as one process on 1 and 2 workers; a worker killed mid-run is named (on stderr and in the run's record) and
its chunks are finished by the others; after every process of the run is killed, ``--resume`` computes exactly the
missing chunks; bad options are refused before any work, with a message and exit code 2, never a traceback.

The runs are real ones (``python -m jaxsleigh.cli basin ... --workers N``, ``JAX_PLATFORMS=cpu``) with a small
workload (200 Monte-Carlo starts, 2 s horizon, chunks of 16).
"""
from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from jaxsleigh.cli import main

pytest.importorskip("distributed")

WORK = ["--samples", "200", "--seed", "3", "--t-final", "2", "--chunk-size", "16"]
N_CHUNKS = 13                      # ceil(200 / 16)


def _env():
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONUNBUFFERED="1")
    for k in [k for k in env if k.startswith(("SLURM_", "OMPI_"))]:
        del env[k]
    return env


def _cmd(out, extra=()):
    return [sys.executable, "-m", "jaxsleigh.cli", "basin", *WORK, "--out", str(out), *extra]


def _start(out, extra=()):
    """The driver of a run, in a session of its own (its workers are in it: one signal reaches them all)."""
    return subprocess.Popen(_cmd(out, extra), env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)


def _chunks(folder: Path) -> set:
    return {p.name for p in folder.glob("chunk_*.npz")}


@contextlib.contextmanager
def socket_port():
    """A free TCP port of 127.0.0.1 (free again once the block ends)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        yield s.getsockname()[1]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> bytes:
    """The single-process run's .npz."""
    out = tmp_path_factory.mktemp("single") / "ref.npz"
    r = subprocess.run(_cmd(out), env=_env(), capture_output=True, text=True, timeout=180)
    assert r.returncode == 0, r.stderr
    return out.read_bytes()


# ---------------------------------------------------------------------------------------------
# fast: refused before any work
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("extra, needle", [
    (["--workers", "0"], "--workers"),
    (["--workers", "two"], "--workers"),
    (["--scheduler", "10.0.0.1"], "PROTOCOL://HOST:PORT"),
    (["--workers", "2", "--scheduler", "tcp://127.0.0.1:8786"], "not allowed with argument"),
    (["--workers", "2", "--cluster-timeout", "0"], "--cluster-timeout"),
    (["--coordinator", "127.0.0.1:1234", "--num-processes", "2", "--process-id", "0"], "removed in jaxsleigh 0.4"),
    (["--process-id", "1"], "--workers N"),
    (["--workers", "2", "--samples", "0"], "--samples"),
    (["--workers", "2", "--t-final", "-1"], "--t-final"),
])
def test_bad_options_are_refused_before_any_worker_starts(tmp_path, capsys, extra, needle):
    t0 = time.perf_counter()
    rc = main(["basin", *WORK, "--out", str(tmp_path / "x.npz"), *extra])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert needle in err and "Traceback" not in err
    assert "worker(s)" not in err                     # no cluster was started
    assert not list(tmp_path.iterdir())
    assert time.perf_counter() - t0 < 20


def test_a_missing_dask_names_the_extra_to_install(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)        # import distributed -> ImportError
    rc = main(["basin", *WORK, "--out", str(tmp_path / "x.npz"), "--workers", "2"])
    err = capsys.readouterr().err
    assert rc == 2 and 'pip install "jaxsleigh[cluster]"' in err and "Traceback" not in err
    assert not list(tmp_path.iterdir())


def test_a_study_that_cannot_be_sent_to_the_workers_is_refused_before_they_start(tmp_path, capsys):
    import threading

    from jaxsleigh.files.runner import Workers, run_to_file

    lock = threading.Lock()                            # a lock does not pickle

    def study(**kw):
        with lock:
            return None

    with pytest.raises(ValueError, match="cannot be sent to the workers"):
        run_to_file(tmp_path / "x.npz", study, lambda out, res: out, workers=Workers(2))
    assert "worker(s)" not in capsys.readouterr().err and not (tmp_path / "x.npz").exists()


def test_a_scheduler_that_does_not_answer_is_said_with_exit_6(tmp_path, capsys):
    with socket_port() as port:                        # a port where nothing listens
        pass
    rc = main(["basin", *WORK, "--out", str(tmp_path / "x.npz"), "--scheduler", f"tcp://127.0.0.1:{port}",
               "--cluster-timeout", "2"])
    err = capsys.readouterr().err
    assert rc == 6, err
    assert f"no Dask worker at the Dask cluster at tcp://127.0.0.1:{port} within 2 s" in err
    assert "Traceback" not in err and not (tmp_path / "x.npz").exists()


# ---------------------------------------------------------------------------------------------
# real runs
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("n", [1, 2])
def test_workers_write_the_single_process_bytes(tmp_path, reference, n):
    out = tmp_path / "w.npz"
    r = subprocess.run(_cmd(out, ["--workers", str(n)]), env=_env(), capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert out.read_bytes() == reference
    record = json.loads((tmp_path / "w.run.json").read_text())
    assert record["workers"] == n and record["lost_workers"] == []
    assert not (tmp_path / "w.npz.chunks").exists()


#: a small sweep: 3 values of k x 24 starts = 72 rows in 5 chunks of 16
SWEEP = ["sweep", "--param", "k=0.05:0.4:3:log", "--samples", "24", "--seed", "3", "--t-final", "2",
         "--chunk-size", "16", "--no-progress"]


def test_a_sweep_on_workers_writes_the_single_process_bytes(tmp_path):
    runs = {}
    for name, extra in (("single", []), ("workers", ["--workers", "2"])):
        out = tmp_path / f"{name}.npz"
        r = subprocess.run([sys.executable, "-m", "jaxsleigh.cli", *SWEEP, "--out", str(out), *extra], env=_env(),
                           capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr[-3000:]
        runs[name] = (out.read_bytes(), r.stdout)
    assert runs["workers"][0] == runs["single"][0]
    assert "2 workers" in runs["workers"][1] and "fraction +- s.e." in runs["workers"][1]


def _worker_pids(p, deadline) -> list:
    """The pids the driver names in its line ``N worker(s): tcp://... (pid P), ...``."""
    while time.monotonic() < deadline:
        line = p.stderr.readline()
        assert line or p.poll() is None, "the driver ended before naming its workers"
        if "worker(s): " in line:
            return [int(x) for x in re.findall(r"\(pid (\d+)\)", line)]
    raise AssertionError("the driver never named its workers")


def test_a_killed_worker_is_named_and_the_others_finish_its_chunks(tmp_path, reference):
    out, chunks = tmp_path / "k.npz", tmp_path / "k.npz.chunks"
    p = _start(out, ["--workers", "2"])
    try:
        deadline = time.monotonic() + 240
        pids = _worker_pids(p, deadline)
        assert len(pids) == 2
        while not _chunks(chunks):                    # mid-run: the first chunk is written
            assert time.monotonic() < deadline and p.poll() is None, "no chunk was written"
            time.sleep(0.01)
        os.kill(pids[1], signal.SIGKILL)
        rest, err = p.communicate(timeout=240)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.communicate()
    assert p.returncode == 0, err[-3000:]
    assert re.search(rf"worker tcp://\S+ \(pid {pids[1]}\) was lost", err), err[-3000:]
    assert out.read_bytes() == reference
    record = json.loads((tmp_path / "k.run.json").read_text())
    assert any(f"(pid {pids[1]})" in w for w in record["lost_workers"])


def test_after_every_process_is_killed_resume_computes_exactly_the_missing_chunks(tmp_path, reference, capsys):
    out, chunks = tmp_path / "a.npz", tmp_path / "a.npz.chunks"
    p = _start(out, ["--workers", "2", "--keep-chunks"])
    try:
        deadline = time.monotonic() + 240
        pids = _worker_pids(p, deadline)
        while len(_chunks(chunks)) < 2:
            assert time.monotonic() < deadline and p.poll() is None, "fewer than 2 chunks were written"
            time.sleep(0.01)
        os.killpg(p.pid, signal.SIGKILL)              # the driver and every worker
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
        p.communicate()
    t = time.monotonic()
    while any(_alive(q) for q in pids) and time.monotonic() - t < 10:
        time.sleep(0.1)
    assert not any(_alive(q) for q in pids)
    assert not out.exists()
    before = {n: (chunks / n).stat().st_mtime_ns for n in _chunks(chunks)}
    assert 2 <= len(before) < N_CHUNKS, "the run finished before it was killed: nothing to test"

    # without --resume the kept chunks are refused, before any worker starts (in this process, as the bad options
    # above: the refusal needs no Python start-up of its own)
    capsys.readouterr()
    rc = main(_cmd(out, ["--workers", "2"])[3:])
    err = capsys.readouterr().err
    assert rc == 2 and "--resume" in err and "worker(s)" not in err and "Traceback" not in err
    assert not out.exists() and {n: (chunks / n).stat().st_mtime_ns for n in _chunks(chunks)} == before

    r = subprocess.run(_cmd(out, ["--workers", "2", "--resume", "--keep-chunks"]), env=_env(), capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert out.read_bytes() == reference
    after = {n: (chunks / n).stat().st_mtime_ns for n in _chunks(chunks)}
    assert len(after) == N_CHUNKS
    assert {n: after[n] for n in before} == before     # the kept chunks were not computed again
    assert json.loads((tmp_path / "a.run.json").read_text())["chunks_reused"] == len(before)


#: a Python program that runs the basin of WORK on Dask workers with the library's runner (no command line)
PYTHON_BASIN = textwrap.dedent("""
    import sys
    from jaxsleigh import RunOptions, run_basin, sample_starts, save_basin
    from jaxsleigh.files.runner import Workers, run_to_file

    if __name__ == "__main__":            # the local workers start by importing this file anew
        out, n = sys.argv[1], int(sys.argv[2])
        starts = sample_starts(200, seed=3)
        done = run_to_file(out, lambda **kw: run_basin(starts, t_final=2.0,
                                                       run=RunOptions(chunk_size=16, progress=False, **kw)),
                           save_basin, options={"samples": 200, "seed": 3, "t_final": 2.0}, workers=Workers(n))
        print("fraction", float(done.result.fraction))
""")


def test_a_python_program_runs_a_basin_on_workers_with_the_library_runner(tmp_path, reference):
    script = tmp_path / "basin_run.py"
    script.write_text(PYTHON_BASIN)
    out = tmp_path / "py.npz"
    r = subprocess.run([sys.executable, str(script), str(out), "2"], env=_env(), capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "fraction" in r.stdout
    assert out.read_bytes() == reference                                # the command line's bytes, one process
    info = json.loads((tmp_path / "py.run.json").read_text())
    assert info["workers"] == 2 and info["lost_workers"] == [] and info["command"] is None
    assert not (tmp_path / "py.npz.chunks").exists()


def test_the_library_runner_owns_its_output_and_resumes_with_python_words(tmp_path):
    """One process: a second run on a file whose chunks an interrupted run left is refused in Python's words
    (resume=True), continued with resume=True, and its options compared with the interrupted run's."""
    from jaxsleigh import RunOptions, run_basin, sample_starts, save_basin
    from jaxsleigh.errors import CheckpointError
    from jaxsleigh.files.runner import chunk_dir, run_to_file

    starts, out = sample_starts(40, seed=1), tmp_path / "b.npz"

    def run(t_final, interrupt=False, **resume):
        def study(**kw):
            if interrupt:                      # the run is interrupted after its chunks are written
                run_basin(starts, t_final=t_final, run=RunOptions(chunk_size=16, progress=False,
                                                                 checkpoint_dir=kw["checkpoint_dir"], resume=False))
                raise KeyboardInterrupt
            return run_basin(starts, t_final=t_final, run=RunOptions(chunk_size=16, progress=False, **kw))
        return run_to_file(out, study, save_basin, options={"t_final": t_final}, **resume)

    with pytest.raises(KeyboardInterrupt):
        run(1.0, interrupt=True)
    assert not out.exists() and any(chunk_dir(out).glob("chunk_*.npz"))
    with pytest.raises(ValueError, match=r"add resume=True"):
        run(1.0)
    with pytest.raises(CheckpointError, match=r"t_final=1.0 in the checkpoint vs t_final=2.0 now"):
        run(2.0, resume=True)
    done = run(1.0, resume=True)
    assert out.exists() and done.code == 0 and done.result.status.size == 40
    assert json.loads((tmp_path / "b.run.json").read_text())["chunks_reused"] >= 1
    assert not chunk_dir(out).exists()


def _dask(*args):
    """``dask scheduler ...`` or ``dask worker ...`` in a session of its own (stopped with `_stop`)."""
    dask = Path(sys.executable).with_name("dask")
    return subprocess.Popen([str(dask), *args], env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)


def _stop(*procs):
    for p in procs:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
        p.wait()


def test_on_a_scheduler_whose_workers_all_die_the_run_stops_with_exit_6_and_resume_finishes(tmp_path, reference):
    """``--scheduler``: the workers of a running Dask cluster compute the chunks; when every one of them dies the
    command says so after ``--cluster-timeout`` (exit code 6, the chunks kept), and ``--resume`` on a new worker
    computes exactly the missing chunks."""
    with socket_port() as port:
        pass
    address = f"tcp://127.0.0.1:{port}"
    scheduler = _dask("scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard")
    workers = [_dask("worker", address, "--nthreads", "1", "--no-nanny", "--no-dashboard") for _ in range(2)]
    out, chunks = tmp_path / "s.npz", tmp_path / "s.npz.chunks"
    try:
        p = _start(out, ["--scheduler", address, "--cluster-timeout", "5", "--keep-chunks"])
        try:
            deadline = time.monotonic() + 240
            while len(_chunks(chunks)) < 2:
                assert time.monotonic() < deadline and p.poll() is None, "fewer than 2 chunks were written"
                time.sleep(0.01)
            _stop(*workers)
            _, err = p.communicate(timeout=120)
        finally:
            _stop(p)
        assert p.returncode == 6, err[-3000:]
        assert "was lost" in err and "no Dask worker left for 5 s" in err and "--resume" in err, err[-3000:]
        assert not out.exists()
        before = {n: (chunks / n).stat().st_mtime_ns for n in _chunks(chunks)}
        assert 2 <= len(before) < N_CHUNKS, "the run finished before its workers were killed: nothing to test"

        workers = [_dask("worker", address, "--nthreads", "1", "--no-nanny", "--no-dashboard")]
        r = subprocess.run(_cmd(out, ["--scheduler", address, "--resume", "--keep-chunks"]), env=_env(),
                           capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr[-3000:]
        assert out.read_bytes() == reference
        after = {n: (chunks / n).stat().st_mtime_ns for n in _chunks(chunks)}
        assert len(after) == N_CHUNKS and {n: after[n] for n in before} == before
        record = json.loads((tmp_path / "s.run.json").read_text())
        assert record["workers"] == address and record["chunks_reused"] == len(before)
    finally:
        _stop(scheduler, *workers)
