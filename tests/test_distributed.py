"""Multi-process runs (issue 11): several local CPU processes joined by ``jax.distributed`` write the
same ``.npz``, byte for byte, as one process; a killed process loses only its unfinished chunks and
``--resume`` by another number of processes recomputes exactly those; bad or inconsistent
options and stale checkpoint folders are refused by every process before anything is written; a
2-process ``jaxsleigh sweep`` writes the single-process bytes too.

The processes are real ones (``python -m jaxsleigh.cli basin ...`` on 127.0.0.1, a free port,
``JAX_PLATFORMS=cpu``) with a small workload (200 Monte-Carlo starts, 2 s horizon, chunks of 16).
"""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from jaxsleigh.cli import main
from jaxsleigh.distributed import cluster_env, parse_coordinator

WORK = ["--samples", "200", "--seed", "3", "--t-final", "2", "--chunk-size", "16"]
N_CHUNKS = 13                      # ceil(200 / 16)


def _env():
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONUNBUFFERED="1")
    for k in [k for k in env if k.startswith(("SLURM_", "OMPI_"))]:
        del env[k]                 # never let a CI runner's SLURM job turn these into cluster runs
    return env


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _cmd(out, extra=(), work=None):
    work = ["basin", *WORK] if work is None else work
    return [sys.executable, "-m", "jaxsleigh.cli", *work, "--out", str(out), *extra]


def _launch(n, out, extra=(), per_process=None, work=None):
    """Start ``n`` processes of one run; ``per_process(i)`` adds options to process ``i``."""
    port = _port()
    return [subprocess.Popen(_cmd(out, [*extra, "--coordinator", f"127.0.0.1:{port}", "--num-processes", str(n),
                                        "--process-id", str(i), *(per_process(i) if per_process else [])], work),
                             env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            for i in range(n)]


def _wait(procs, timeout=120):
    results = []
    for p in procs:
        try:
            o, e = p.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            for q in procs:
                if q.poll() is None:
                    q.kill()
            raise
        results.append((p.returncode, o, e))
    return results


def _run(n, out, extra=(), work=None):
    res = _wait(_launch(n, out, extra, work=work))
    for i, (rc, o, e) in enumerate(res):
        assert rc == 0, f"process {i} of {n}: exit {rc}\n{o}\n{e[-3000:]}"
    return res


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> bytes:
    """The single-process run's .npz (no distributed options at all)."""
    out = tmp_path_factory.mktemp("single") / "ref.npz"
    r = subprocess.run(_cmd(out), env=_env(), capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    return out.read_bytes()


# ---------------------------------------------------------------------------------------------
# fast: options, no processes started
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("extra, needle", [
    (["--coordinator", "127.0.0.1:1234"], "go together"),
    (["--num-processes", "2", "--process-id", "0"], "missing --coordinator"),
    (["--coordinator", "localhost", "--num-processes", "2", "--process-id", "0"], "HOST:PORT"),
    (["--coordinator", "127.0.0.1:99999", "--num-processes", "2", "--process-id", "0"], "1..65535"),
    (["--coordinator", "127.0.0.1:1234", "--num-processes", "2", "--process-id", "2"], "--process-id must be 0..1"),
    (["--coordinator", "127.0.0.1:1234", "--num-processes", "0", "--process-id", "0"], "--num-processes must be >= 1"),
])
def test_bad_distributed_options_exit_2(tmp_path, capsys, extra, needle):
    rc = main(["basin", *WORK, "--out", str(tmp_path / "x.npz"), *extra])
    assert rc == 2
    assert needle in capsys.readouterr().err
    assert not (tmp_path / "x.npz").exists()


def test_cluster_detection(monkeypatch):
    for k in [k for k in os.environ if k.startswith(("SLURM_", "OMPI_"))]:
        monkeypatch.delenv(k)
    assert cluster_env() is None
    slurm = {"SLURM_JOB_ID": "7", "SLURM_STEP_NODELIST": "n[1-2]", "SLURM_NTASKS": "1", "SLURM_PROCID": "0",
             "SLURM_LOCALID": "0"}
    for k, v in slurm.items():
        monkeypatch.setenv(k, v)
    assert cluster_env() is None                     # one task: a plain single-process run
    monkeypatch.setenv("SLURM_NTASKS", "4")
    assert cluster_env() == "slurm"
    for k in slurm:
        monkeypatch.delenv(k)
    monkeypatch.setenv("OMPI_MCA_orte_hnp_uri", "123.0;tcp://10.0.0.1:5000")
    monkeypatch.setenv("OMPI_COMM_WORLD_SIZE", "2")
    assert cluster_env() == "ompi"


def test_parse_coordinator():
    assert parse_coordinator("10.0.0.1:12345") == "10.0.0.1:12345"
    assert parse_coordinator("[::1]:80") == "[::1]:80"
    for bad in ("10.0.0.1", ":80", "host:port", "a:b:1"):
        with pytest.raises(ValueError, match="HOST:PORT"):
            parse_coordinator(bad)


# ---------------------------------------------------------------------------------------------
# slow: real processes
# ---------------------------------------------------------------------------------------------

@pytest.mark.slow
@pytest.mark.parametrize("n", [2, 3])
def test_processes_write_the_single_process_bytes(tmp_path, reference, n):
    out = tmp_path / "multi.npz"
    res = _run(n, out)
    assert out.read_bytes() == reference
    assert not (tmp_path / "multi.npz.chunks").exists()           # cleaned up as in a single-process run
    info = json.loads((tmp_path / "multi.run.json").read_text())
    assert info["processes"] == n and info["chunks_reused"] == 0
    assert "N = 200" in res[0][1]                                  # process 0 reports the summary
    for rc, o, e in res[1:]:
        assert o == "" and "process 0 writes" in e


#: a small sweep: 3 values of k x 24 starts = 72 rows in 5 chunks of 16
SWEEP = ["sweep", "--param", "k=0.05:0.4:3:log", "--samples", "24", "--seed", "3", "--t-final", "2",
         "--chunk-size", "16", "--no-progress"]


@pytest.mark.slow
def test_sweep_processes_write_the_single_process_bytes(tmp_path, capsys):
    assert main([*SWEEP, "--out", str(tmp_path / "x.npz"), "--coordinator", "127.0.0.1:1234"]) == 2
    assert "go together" in capsys.readouterr().err                # the options of basin, checked alike
    single = tmp_path / "single.npz"
    r = subprocess.run(_cmd(single, work=SWEEP), env=_env(), capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    out = tmp_path / "multi.npz"
    res = _run(2, out, work=SWEEP)
    assert out.read_bytes() == single.read_bytes()
    assert not (tmp_path / "multi.npz.chunks").exists()
    info = json.loads((tmp_path / "multi.run.json").read_text())
    assert info["processes"] == 2 and info["chunks_reused"] == 0
    assert "2 processes" in res[0][1] and "fraction +- s.e." in res[0][1]   # process 0 reports the table
    assert res[1][1] == "" and "process 0 writes" in res[1][2]


def _chunk_index(p: Path) -> int:
    return int(p.stem.split("_")[1])


@pytest.mark.slow
def test_killed_process_then_resume_with_other_count(tmp_path, reference):
    out = tmp_path / "k.npz"
    chunks = tmp_path / "k.npz.chunks"
    procs = _launch(2, out, ["--keep-chunks"])
    try:
        deadline = time.monotonic() + 90
        while not any(_chunk_index(p) % 2 == 1 for p in chunks.glob("chunk_*.npz")):   # process 1's first chunk
            assert time.monotonic() < deadline and procs[1].poll() is None, "process 1 wrote no chunk"
            time.sleep(0.005)
        procs[1].send_signal(signal.SIGKILL)
        # process 0 finishes its share (even chunks), then waits for process 1 at the barrier
        mine = {i for i in range(N_CHUNKS) if i % 2 == 0}
        while not mine <= {_chunk_index(p) for p in chunks.glob("chunk_*.npz")}:
            assert time.monotonic() < deadline, "process 0 did not finish its share after process 1 died"
            time.sleep(0.05)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
            p.communicate()
    assert procs[1].returncode == -signal.SIGKILL
    assert not out.exists()
    before = {p.name: (p.stat().st_ino, p.stat().st_mtime_ns) for p in chunks.glob("chunk_*.npz")}
    lost = N_CHUNKS - len(before)
    assert lost >= 1, "process 1 finished its share before it was killed: nothing to test"
    assert {_chunk_index(Path(n)) % 2 for n in before} >= {0}

    # a fresh run (no --resume) into that folder is refused by every process
    res = _wait(_launch(2, out))
    assert [rc for rc, _, _ in res] == [2, 2]
    assert all("--resume" in e for _, _, e in res)

    # resumed by 3 processes: exactly the lost chunks are computed, the others are not touched
    _run(3, out, ["--resume", "--keep-chunks"])
    assert out.read_bytes() == reference
    after = {p.name: (p.stat().st_ino, p.stat().st_mtime_ns) for p in chunks.glob("chunk_*.npz")}
    assert len(after) == N_CHUNKS
    assert {k: after[k] for k in before} == before
    info = json.loads((tmp_path / "k.run.json").read_text())
    assert info["chunks_reused"] == len(before) and info["processes"] == 3
    assert not list(chunks.glob(".jaxsleigh-process-*"))


@pytest.mark.slow
def test_processes_with_different_options_are_refused_before_any_write(tmp_path):
    out = tmp_path / "d.npz"
    res = _wait(_launch(2, out, per_process=lambda i: ["--eps", "0.1"] if i == 1 else []))
    assert [rc for rc, _, _ in res] == [2, 2]
    assert all("different options" in e for _, _, e in res)
    assert not list((tmp_path / "d.npz.chunks").glob("*")) and not out.exists()
