"""Chunks that know who they are, runs that own their output, a full disk that says what to do.

A chunk file under another chunk's name is never trusted; two runs never write
the same output (a killed run leaves no stale lock); a full disk names the file and the way on;
a refused resume names the options that differ, with both values, and every hint says what works.
"""
from __future__ import annotations

import errno
import io as _io
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import textwrap
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as hst

import jaxsleigh as js
from jaxsleigh import cli
from jaxsleigh.files.chunks import ChunkStore
from jaxsleigh.cli.common import EXIT_CODES, EXIT_DISK_FULL, EXIT_LOCKED
from jaxsleigh.errors import CheckpointError, DamagedCheckpointWarning, DiskFullError, RunLockedError
from jaxsleigh.files.runlock import RunLock

REPO = Path(__file__).resolve().parents[1]
BASIN = ["--samples", "32", "--t-final", "0.3", "--dt", "0.05", "--chunk-size", "8", "--no-progress"]
KW = dict(t_final=0.3, dt=0.05)
N, CHUNK = 16, 4
FIELDS = ("q", "p", "T_eps", "status", "n_steps", "Hd0", "Hd_final", "min_abs_theta")


def _quiet(**fields):
    """The `jaxsleigh.RunOptions` of these runs (no progress bar)."""
    return js.RunOptions(progress=False, **fields)


def run_cli(argv, capsys):
    rc = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    return rc, out, err


def same(a, b) -> bool:
    return all(np.asarray(getattr(a, f)).tobytes() == np.asarray(getattr(b, f)).tobytes() for f in FIELDS)


# ---------------------------------------------------------------------------------------------
# 1. a chunk under another chunk's name is never trusted
# ---------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The uninterrupted result, its chunk folder, and a folder of the same run with other chunks."""
    ics = js.sample_starts(N, seed=5).ics
    ref = js.run_ensemble(ics, **KW, run=_quiet(chunk_size=CHUNK))
    base = tmp_path_factory.mktemp("chunks")
    js.run_ensemble(ics, **KW, run=_quiet(chunk_size=CHUNK, checkpoint_dir=base / "own"))
    js.run_ensemble(ics, **KW, run=_quiet(chunk_size=2 * CHUNK, checkpoint_dir=base / "wide"))   # other chunk size
    return ics, ref, base


def _strip_identity(path: Path) -> None:
    """Rewrite a chunk as the earlier format wrote it: fingerprint, but no index, rows, digest of the starts or
    content digest."""
    with np.load(path) as z:
        data = {k: z[k] for k in z.files if k not in ("__chunk__", "__starts__", "__digest__")}
    buf = _io.BytesIO()
    np.savez(buf, **data)
    path.write_bytes(buf.getvalue())


OPS = hst.lists(hst.one_of(
    hst.tuples(hst.just("swap"), hst.integers(0, 3), hst.integers(0, 3)),
    hst.tuples(hst.just("copy"), hst.integers(0, 3), hst.integers(0, 3)),
    hst.tuples(hst.just("delete"), hst.integers(0, 3), hst.just(0)),
    hst.tuples(hst.just("old_format"), hst.integers(0, 3), hst.just(0)),
    hst.tuples(hst.just("other_chunk_size"), hst.integers(0, 1), hst.integers(0, 3))), min_size=1, max_size=4)


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(ops=OPS)
def test_shuffled_copied_or_foreign_chunks_give_the_same_result_or_a_named_refusal(runs, ops):
    ics, ref, base = runs
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp) / "ck"
        shutil.copytree(base / "own", d)
        name = lambda i: d / f"chunk_{i:06d}.npz"             # noqa: E731
        for op, i, j in ops:
            if op == "swap" and name(i).exists() and name(j).exists():
                a, b = name(i).read_bytes(), name(j).read_bytes()
                name(i).write_bytes(b), name(j).write_bytes(a)
            elif op == "copy" and i != j and name(i).exists():
                shutil.copyfile(name(i), name(j))
            elif op == "delete":
                name(i).unlink(missing_ok=True)
            elif op == "old_format" and name(i).exists():
                _strip_identity(name(i))
            elif op == "other_chunk_size":
                shutil.copyfile(base / "wide" / f"chunk_{i:06d}.npz", name(j))
        key = json.loads((d / "manifest.json").read_text())["key"]
        missing = {i for i in range(4) if not name(i).exists()}
        foreign, misplaced = [], []
        for f in sorted(d.glob("chunk_*.npz")):
            with np.load(f) as z:
                if str(z["__run_key__"]) != key:
                    foreign.append(f.name)
                elif "__chunk__" not in z.files or int(z["__chunk__"][0]) != int(f.name[6:12]):
                    misplaced.append(f.name)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                res = js.run_ensemble(ics, **KW, run=_quiet(chunk_size=CHUNK, checkpoint_dir=d,
                                                             resume=True))
            except CheckpointError as e:
                assert foreign, f"own chunks refused: {e}"                 # refused only for a foreign chunk
                assert any(f in str(e) for f in foreign) and "different run" in str(e)
                return
        assert not foreign, "a chunk of another run was accepted"
        assert same(res, ref), ops                                         # never a mixed result
        said = " | ".join(str(w.message) for w in caught if isinstance(w.message, DamagedCheckpointWarning))
        for f in misplaced:                                                # every misplaced chunk is named
            assert f in said, (f, said)
        assert res.run_info["chunks_reused"] == 4 - len(missing | {int(f[6:12]) for f in misplaced})


def test_a_swapped_basin_chunk_is_named_and_recomputed(tmp_path, capsys):
    out, fresh = tmp_path / "b.npz", tmp_path / "fresh.npz"
    assert run_cli(["basin", *BASIN, "--out", out, "--keep-chunks"], capsys)[0] == 0
    ck = tmp_path / "b.npz.chunks"
    a, b = (ck / "chunk_000000.npz").read_bytes(), (ck / "chunk_000002.npz").read_bytes()
    (ck / "chunk_000000.npz").write_bytes(b)
    (ck / "chunk_000002.npz").write_bytes(a)
    out.unlink()
    rc, text, err = run_cli(["basin", *BASIN, "--out", out, "--resume"], capsys)
    assert rc == 0, err
    assert "chunk_000000.npz" in err and "chunk_000002.npz" in err and "holds chunk 2" in err, err
    assert "2 chunk(s) resumed" in text
    assert run_cli(["basin", *BASIN, "--out", fresh], capsys)[0] == 0
    assert out.read_bytes() == fresh.read_bytes()


def test_a_chunk_without_its_identity_is_not_trusted(tmp_path):
    ics = js.sample_starts(8, seed=1).ics
    d = tmp_path / "ck"
    js.run_ensemble(ics, **KW, run=_quiet(chunk_size=4, checkpoint_dir=d))
    _strip_identity(d / "chunk_000001.npz")
    with pytest.warns(DamagedCheckpointWarning, match=r"chunk_000001\.npz.*earlier jaxsleigh"):
        res = js.run_ensemble(ics, **KW, run=_quiet(chunk_size=4, checkpoint_dir=d, resume=True))
    assert res.run_info["chunks_reused"] == 1


def test_store_checks_rows_and_starts(tmp_path):
    """Direct: a chunk saved for rows 0-3 is not chunk 0 of rows 0-2, nor of other starts."""
    s = ChunkStore(tmp_path / "ck", "k")
    s.open(resume=False, manifest={})
    try:
        starts = np.arange(20.0).reshape(4, 5)
        s.save(0, {"a": np.zeros(4)}, lo=0, starts=starts)
        assert s.load(0, 4, lo=0, starts=starts) is not None
        with pytest.warns(DamagedCheckpointWarning, match="not chunk 0 \\(rows 4-7\\)"):
            assert s.load(0, 4, lo=4, starts=starts) is None
        with pytest.warns(DamagedCheckpointWarning, match="other starts"):
            assert s.load(0, 4, lo=0, starts=starts + 1) is None
    finally:
        s.close()


# ---------------------------------------------------------------------------------------------
# 2. a run owns its output and its chunk folder
# ---------------------------------------------------------------------------------------------

HOLDER = textwrap.dedent("""
    import sys, time
    from jaxsleigh.files.runlock import RunLock
    RunLock(sys.argv[1], sys.argv[2], folder=sys.argv[3] == "folder").acquire()
    print("ready", flush=True)
    time.sleep(120)
""")


def _holder(target, fingerprint, folder=False):
    """A real process that holds the lock on ``target``; returns it once the lock is taken."""
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    p = subprocess.Popen([sys.executable, "-c", HOLDER, str(target), fingerprint, "folder" if folder else "file"],
                         stdout=subprocess.PIPE, env=env, text=True)
    assert p.stdout.readline().strip() == "ready"
    return p


def _kill9(p) -> None:
    os.kill(p.pid, signal.SIGKILL)
    p.wait(timeout=30)
    p.stdout.close()


def test_a_second_run_on_the_same_out_is_refused_and_a_killed_one_leaves_no_stale_lock(tmp_path, capsys):
    out = tmp_path / "b.npz"
    p = _holder(out, "another-run")
    try:
        env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
        second = subprocess.run([sys.executable, "-m", "jaxsleigh.cli", "basin", *BASIN, "--out", str(out)],
                                capture_output=True, text=True, env=env, timeout=300)
        assert second.returncode == EXIT_LOCKED, second.stderr
        assert f"pid {p.pid}" in second.stderr and "another run" in second.stderr
        assert "Traceback" not in second.stderr and not out.exists()
        # the processes of one run (same fingerprint) share it
        with RunLock(out, "another-run"):
            pass
    finally:
        _kill9(p)
    assert list(tmp_path.glob(".b.npz.lock.*")), "the killed holder's lock file is still there (not yet stale)"
    rc, _, err = run_cli(["basin", *BASIN, "--out", out], capsys)      # the killed run holds nothing
    assert rc == 0, err
    assert not list(tmp_path.glob(".b.npz.lock.*")) and not list(tmp_path.glob(".tmplock.*"))


def test_the_library_locks_its_checkpoint_folder(tmp_path):
    d = tmp_path / "ck"
    p = _holder(d, "another-run", folder=True)
    try:
        with pytest.raises(RunLockedError, match=rf"checkpoint folder .*ck.* pid {p.pid}"):
            js.run_ensemble(js.sample_starts(4, seed=1).ics, **KW, run=_quiet(chunk_size=4, checkpoint_dir=d))
        assert not list(d.glob("chunk_*.npz")) and not (d / "manifest.json").exists()
    finally:
        _kill9(p)
    js.run_ensemble(js.sample_starts(4, seed=1).ics, **KW, run=_quiet(chunk_size=4, checkpoint_dir=d))
    assert not list(d.glob(".lock.*"))                                   # stale one removed, own released


def test_locks_in_one_process_share_or_refuse(tmp_path):
    a = RunLock(tmp_path / "o.npz", "one").acquire()
    try:
        with pytest.raises(RunLockedError, match="in this process"):
            RunLock(tmp_path / "o.npz", "two").acquire()
        b = RunLock(tmp_path / "o.npz", "one").acquire()             # nested: shared
        b.release()
        assert list(tmp_path.glob(".o.npz.lock.*"))                   # still held by a
    finally:
        a.release()
    assert not list(tmp_path.glob(".o.npz.lock.*"))
    RunLock(tmp_path / "o.npz", "two").acquire().release()            # free again


def test_a_dead_runs_lock_probed_by_another_newcomer_is_still_stale(tmp_path):
    """Two processes of a resumed run start together and both find the lock file a killed run left: one
    of them holding it while it probes must not make it look live to the other (a probe once held it
    exclusively, and the other newcomer was refused, named the dead run)."""
    import fcntl
    dead = tmp_path / f".o.npz.lock.elsewhere.{os.getpid() + 1}"
    dead.write_text(json.dumps({"fingerprint": "the-killed-run", "host": "elsewhere", "pid": 1}) + "\n")
    fd = os.open(dead, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)                # the other newcomer, mid-probe
        with RunLock(tmp_path / "o.npz", "the-resumed-run"):
            assert not dead.exists()                                   # taken for what it is: stale
    finally:
        os.close(fd)
    assert not list(tmp_path.glob(".o.npz.lock.*"))


# ---------------------------------------------------------------------------------------------
# 3. a full disk names the file and the way on
# ---------------------------------------------------------------------------------------------

def _full_when(monkeypatch, part: str):
    """Make the atomic writer's writes to files whose name contains ``part`` fail with ENOSPC."""
    import builtins

    import jaxsleigh.files.npz as jio

    real = builtins.open

    class Full(_io.RawIOBase):
        def writable(self):
            return True

        def write(self, b):
            raise OSError(errno.ENOSPC, "No space left on device")

    def fake_open(path, mode="r", *a, **k):
        if "w" in mode and part in Path(path).name:
            real(path, mode).close()                  # the temporary file exists, as in real life
            return _io.BufferedWriter(Full())
        return real(path, mode, *a, **k)

    monkeypatch.setattr(jio, "open", fake_open, raising=False)


def test_atomic_write_on_a_full_disk_names_the_file(tmp_path, monkeypatch):
    from jaxsleigh.files.npz import atomic_write

    def write(f):
        raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(DiskFullError, match=r"x\.bin.*no space left.*free some space") as info:
        atomic_write(tmp_path / "x.bin", write, when_full="--resume continues")
    assert info.value.errno == errno.ENOSPC and "--resume continues" in str(info.value)
    assert not list(tmp_path.iterdir())                                # no temporary file left
    with pytest.raises(DiskFullError, match="quota"):
        atomic_write(tmp_path / "y.bin", lambda f: (_ for _ in ()).throw(OSError(errno.EDQUOT, "Disk quota")))


@pytest.mark.parametrize("part", ["chunk_000001", "b.npz."])
def test_a_full_disk_exits_4_naming_the_file_and_resume_continues(tmp_path, capsys, monkeypatch, part):
    out, fresh = tmp_path / "b.npz", tmp_path / "fresh.npz"
    with monkeypatch.context() as m:
        _full_when(m, part)
        rc, _, err = run_cli(["basin", *BASIN, "--out", out], capsys)
    assert rc == EXIT_DISK_FULL, err
    named = "chunk_000001.npz" if part.startswith("chunk") else "b.npz"
    assert named in err and "no space left" in err and "--resume" in err and "Errno" not in err, err
    assert "resume=True" not in err, err                 # the command line's words, not Python's
    assert not out.exists() and (tmp_path / "b.npz.chunks" / "chunk_000000.npz").exists()
    rc, _, err = run_cli(["basin", *BASIN, "--out", out, "--resume"], capsys)
    assert rc == 0, err
    assert run_cli(["basin", *BASIN, "--out", fresh], capsys)[0] == 0
    assert out.read_bytes() == fresh.read_bytes()


def test_exit_codes_of_the_typed_errors_are_documented():
    assert DiskFullError.exit_code == EXIT_DISK_FULL and RunLockedError.exit_code == EXIT_LOCKED
    assert EXIT_DISK_FULL in EXIT_CODES and EXIT_LOCKED in EXIT_CODES
    doc = (REPO / "docs" / "reliability.md").read_text()
    assert f"exit code {EXIT_DISK_FULL}" in doc and f"exit code {EXIT_LOCKED}" in doc


# ---------------------------------------------------------------------------------------------
# 4, 5. refusals name what differs, with both values; hints say the one thing that works
# ---------------------------------------------------------------------------------------------

def test_a_refused_resume_names_the_setting_and_both_values(tmp_path):
    ics = js.sample_starts(8, seed=1).ics
    d = tmp_path / "ck"
    js.run_ensemble(ics, **KW, run=_quiet(chunk_size=4, checkpoint_dir=d))
    with pytest.raises(CheckpointError, match=r"t_final 0\.3 in the checkpoint vs 0\.2 now") as info:
        js.run_ensemble(ics, **{**KW, "t_final": 0.2}, run=_quiet(chunk_size=4, checkpoint_dir=d, resume=True))
    assert "{" not in str(info.value) and "drop --resume" not in str(info.value)
    with pytest.raises(CheckpointError, match="other initial conditions"):
        js.run_ensemble(ics + 0.1, **KW, run=_quiet(chunk_size=4, checkpoint_dir=d, resume=True))
    # the step policy's safety and factor limits decide the chunks too: another value is refused, not reused
    with pytest.raises(CheckpointError, match=r"safety"):
        js.run_ensemble(ics, **KW, stepsize=js.StepSizeController(safety=0.8),
                        run=_quiet(chunk_size=4, checkpoint_dir=d, resume=True))


def test_cli_refusals_name_the_option_and_never_suggest_what_is_refused(tmp_path, capsys):
    out = tmp_path / "b.npz"
    assert run_cli(["basin", *BASIN, "--seed", "3", "--out", out, "--keep-chunks"], capsys)[0] == 0
    out.unlink()
    rc, _, err = run_cli(["basin", *BASIN, "--seed", "7", "--out", out, "--resume"], capsys)
    assert rc == 2 and "--seed 3 in the checkpoint vs --seed 7 now" in err, err
    assert "{" not in err and "drop --resume" not in err and "delete or move" in err
    rc, _, err = run_cli(["basin", *BASIN, "--seed", "7", "--out", out], capsys)   # without --resume
    assert rc == 2 and "--resume" in err and "delete or move" in err and "another --out" in err, err
    assert "drop --resume" not in err
    assert not out.exists()


def test_a_refused_resume_of_a_controller_names_the_flag_first_without_dictionaries(tmp_path, capsys):
    out = tmp_path / "b.npz"
    law = ["--controller", "astolfi", "--sample-period", "0.1"]
    assert run_cli(["basin", *BASIN, *law, "--saturation", "2", "--out", out, "--keep-chunks"], capsys)[0] == 0
    out.unlink()
    rc, _, err = run_cli(["basin", *BASIN, *law, "--saturation", "3", "--out", out, "--resume"], capsys)
    line = err.strip().splitlines()
    assert rc == 2 and len(line) == 1, err
    assert line[0].startswith("jaxsleigh: error: --saturation 2.0 in the checkpoint vs --saturation 3.0 now: "), err
    assert "{" not in err and "'type'" not in err and "delete or move" in err


def test_a_refused_resume_from_python_names_the_leaf_of_a_law_that_differs(tmp_path):
    from jaxsleigh.controllers.actuators import saturate
    from jaxsleigh.controllers.registry import make_controller

    ics = js.sample_starts(4, seed=1).ics
    d = tmp_path / "ck"
    js.run_ensemble(ics, controller=saturate(make_controller("astolfi"), 2.0), **KW,
                    run=_quiet(chunk_size=2, checkpoint_dir=d))
    with pytest.raises(CheckpointError, match=r"controller\.u_max 2\.0 in the checkpoint vs 3\.0 now") as info:
        js.run_ensemble(ics, controller=saturate(make_controller("astolfi"), 3.0), **KW,
                        run=_quiet(chunk_size=2, checkpoint_dir=d, resume=True))
    assert "{" not in str(info.value)


def test_a_refused_tuner_checkpoint_names_the_setting_and_both_values(tmp_path):
    from jaxsleigh import tuning as tu
    from jaxsleigh.tuning.checkpoint import Checkpoint, TunerCheckpoint, tune_settings
    from jaxsleigh.tuning.optimizer import CandidateTrack

    g0, ics = js.gains(), js.sample_starts(4, seed=1).ics
    settings = lambda steps: tune_settings(g0, ("L",), tu.TuneConfig(steps=steps), tu.LossConfig(), None, None,  # noqa
                                           None, False, 0.0, None)
    key = lambda steps: Checkpoint.of_run(settings(steps), ics)  # noqa
    path = tmp_path / "t.ckpt.npz"
    TunerCheckpoint(path, key(4), ("loss",)).save(0, {"a": np.zeros(1)}, (), CandidateTrack(0.0, False))
    with pytest.raises(ValueError, match=r"config\.steps 4 in the checkpoint vs 8 now") as info:
        TunerCheckpoint(path, key(8), ("loss",)).load({"a": np.zeros(1)}, (), [], CandidateTrack(0.0, False))
    assert "{" not in str(info.value) and "delete or move" in str(info.value)
    other = Checkpoint.of_run(settings(4), ics + 1.0)
    with pytest.raises(ValueError, match=r"other settings \(other initial conditions\);"):   # not two digests
        TunerCheckpoint(path, other, ("loss",)).load({"a": np.zeros(1)}, (), [], CandidateTrack(0.0, False))


def test_every_resumable_run_writes_one_checkpoint_layout(tmp_path):
    """A basin's chunk and a tuner's state are written by one class (`jaxsleigh.files.checkpoint.Checkpoint`): the run's arrays
    and a header under ``__name__`` keys, the fingerprint first; the same state gives the same bytes; a tuner file of
    the earlier layout (``key``/``settings`` among the arrays) still resumes."""
    from jaxsleigh import tuning as tu
    from jaxsleigh.tuning.checkpoint import Checkpoint, TunerCheckpoint, tune_settings
    from jaxsleigh.tuning.optimizer import CandidateTrack

    s = ChunkStore(tmp_path / "ck", "k")
    s.open(resume=False, manifest={})
    try:
        starts = np.arange(20.0).reshape(4, 5)
        chunk = s.save(0, {"a": np.arange(4.0)}, lo=0, starts=starts)
    finally:
        s.close()
    g0, ics = js.gains(), js.sample_starts(4, seed=1).ics
    stamp = Checkpoint.of_run(tune_settings(g0, ("L",), tu.TuneConfig(steps=4), tu.LossConfig(), None, None, None,
                                            False, 0.0, None), ics, {"--steps": 4})
    key = stamp.key
    tuner = tmp_path / "t.ckpt.npz"
    ck = TunerCheckpoint(tuner, stamp, ("loss",))
    ck.save(3, {"a": np.ones(1)}, (), CandidateTrack(0.0, False))
    first = tuner.read_bytes()
    ck.save(3, {"a": np.ones(1)}, (), CandidateTrack(0.0, False))
    assert tuner.read_bytes() == first
    (arrays_c, head_c), (arrays_t, head_t) = Checkpoint.read_file(chunk), Checkpoint.read_file(tuner)
    assert set(head_c) == {"run_key", "chunk", "starts", "digest"} and str(head_c["run_key"]) == "k"
    assert set(head_t) == {"run_key", "settings", "options", "digest"} and str(head_t["run_key"]) == key
    assert set(arrays_c) == {"a"} and not any(k.startswith("__") or k in ("key", "settings") for k in arrays_t)
    # the earlier layout: the header's entries among the arrays, without underscores
    np.savez(tuner, key=np.array(key), settings=head_t["settings"], **arrays_t)
    assert TunerCheckpoint(tuner, stamp._replace(options=None), ("loss",)).load({"a": np.zeros(1)}, (), [], CandidateTrack(0.0, False))[0] == 3
