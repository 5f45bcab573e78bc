"""The host runner: a long, chunked run that owns its output file, in one process or in several.

A study that writes its result chunk by chunk (`jaxsleigh.run_basin`, `jaxsleigh.sweep`, or any function that
takes the runner's ``checkpoint_dir``, ``resume`` and ``shard``, e.g. into `jaxsleigh.RunOptions`) runs to one file
``out`` in four steps, the same from Python and from the command line (``jaxsleigh basin`` and ``jaxsleigh
sweep`` are `run_to_file` with their own checks and printing):

1. **own** ``out`` as every run that writes does (`jaxsleigh.files.run.Run`): one lock next to it, which covers
   ``out.chunks/`` too (another live run on the same file is refused with `jaxsleigh.errors.RunLockedError`, exit code
   5 on the command line), then refuse a chunk folder ``out.chunks/`` that holds the chunks of an earlier run unless
   ``resume=True`` (decided there once: the chunk store does not decide it again); a
   fresh run records its options in the folder's one record file, ``out.chunks/manifest.json``
   (`jaxsleigh.files.checkpoint.record`, next to what the chunk store records there), so that a refused
   resume can name the options that differ;
2. **compute** the chunks: one process does them all; in a multi-process run (`Processes`, or detected
   under SLURM / Open MPI) every process computes the chunks ``i`` with ``i % count == index``
   (`jaxsleigh.files.distributed.run_shared`);
3. **assemble** (process 0, or the only process): the result read from the chunks (a missing chunk is
   computed), saved to ``out`` atomically, a sidecar ``out.run.json`` of what varies between runs (wall
   time, devices, load, processes, the command), the chunk folder removed unless ``keep_chunks`` (then marked
   finished, `FINISHED`: a later run is told it holds a finished run);
4. **leave**: every process gets process 0's result code (`leave`).

An interrupted run (Ctrl-C, a killed process, a full disk) keeps its finished chunks; the same call
with ``resume=True`` continues it and writes the same file, byte for byte, on any number of processes.

Example, a basin over four processes of one machine (start the same script four times, ``I`` = 0..3)::

    from jaxsleigh import RunOptions, run_basin, sample_starts, save_basin
    from jaxsleigh.files.runner import Processes, leave, run_to_file

    starts = sample_starts(10**6, seed=1)
    # the runner passes checkpoint_dir, resume and shard: the study puts them into its RunOptions
    done = run_to_file("mc.npz", lambda **kw: run_basin(starts, eps=0.05, run=RunOptions(**kw)), save_basin,
                       options={"samples": 10**6, "seed": 1, "eps": 0.05},
                       processes=Processes("127.0.0.1:12345", 4, I))
    leave(done)             # every process ends here with process 0's code
"""
from __future__ import annotations

import hashlib
import json
import os
import platform
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, NamedTuple, Optional

from . import checkpoint
from .checkpoint import MANIFEST, differences, recorded
from .distributed import CLUSTER_TIMEOUT_S, EXIT_CLUSTER, run_shared, start
from .npz import atomic_write_text
from .run import PYTHON_WORDS, Run, Words
from .runlock import settings_fingerprint
from .workers import Workers, compute_shares, require_dask
from ..errors import CheckpointError, DiskFullError, RunLockedError
from ..validate import output_file

__all__ = ["Processes", "Workers", "Words", "PYTHON_WORDS", "Finished", "run_to_file", "run_owned", "own_output", "chunk_dir",
           "FINISHED", "other_command", "sidecar", "options_differ", "load_average", "start_processes", "leave"]


@dataclass(frozen=True)
class Processes:
    """A multi-process run: the address ``HOST:PORT`` of process 0's coordinator, the number of processes and
    this process's id (all three, or leave ``processes=None`` for one process, or under SLURM / Open MPI where
    they are detected); ``timeout_s`` is how long a silent process is waited for before the run fails."""

    coordinator: Optional[str] = None
    num_processes: Optional[int] = None
    process_id: Optional[int] = None
    timeout_s: float = CLUSTER_TIMEOUT_S




class Finished(NamedTuple):
    """What `run_to_file` returns: ``result`` (process 0 or the only process; ``None`` elsewhere), ``code``
    (what ``finish`` returned, process 0's in every process; 0 without ``finish``), the files written, and
    ``cluster`` (``None`` for one process), for `leave`."""

    result: Any
    code: int
    written: tuple
    cluster: Any


def chunk_dir(out) -> Path:
    """The checkpoint folder of ``out``: ``FILE.npz.chunks/``."""
    out = Path(out)
    return out.with_name(out.name + ".chunks")


def sidecar(out) -> Path:
    """The run's sidecar next to ``out``: ``FILE.run.json`` (what varies between runs)."""
    out = Path(out)
    return out.with_name(out.stem + ".run.json")


def load_average() -> list:
    """The machine's load averages (1, 5, 15 min), recorded next to timings; [] where unknown."""
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:  # pragma: no cover - not on every platform
        return []


def _single_run_id(options: Any = None) -> str:
    """The fingerprint of a single-process run: its options (what defines the result) hashed, so that the same run
    started twice on one output is told "the same run is in progress"; without options, one of its own. No other
    process shares its output (its lock is not shared)."""
    if options is None:
        return f"{platform.node()}:{os.getpid()}:{time.time_ns()}"
    return "single:" + settings_fingerprint(options)


def _cluster_run_id(processes: Optional[Processes], cluster) -> str:
    """The fingerprint the processes of one run share (their output and chunk folder are one): their
    coordinator (or the SLURM / Open MPI job) and their count."""
    where = (processes.coordinator if processes is not None else None) or os.environ.get(
        "SLURM_JOB_ID") or os.environ.get("OMPI_MCA_orte_hnp_uri", "")
    return hashlib.sha256(json.dumps([where, cluster.count], default=str).encode()).hexdigest()


#: The mark a run leaves in the chunk folder it keeps (``keep_chunks``) once its output is written: the next run
#: is told the folder holds a finished run, not an unfinished one. A run that starts there removes it first.
FINISHED = "finished.json"


def own_output(out, chunks, *, resume: bool, run_id: Optional[str] = None, words: Words = PYTHON_WORDS,
               shared: Optional[bool] = None) -> tuple:
    """Claim ``out`` and its chunk folder for this run, before looking at the folder (`jaxsleigh.files.run.Run`: one
    lock next to ``out``, which covers the folder, whose chunk store shares it; `RunLockedError` names another live
    run), then decide, once for the run and its chunk store, whether the folder's chunks may be used: a folder that
    holds chunks (or a chunk's work in progress) is refused without ``resume``. ``run_id``: the run's fingerprint
    (``None``: one of its own); ``shared``: other processes with the same fingerprint share the output (default: when
    ``run_id`` is given). Returns ``(the claimed Run, the chunk files found)``; the caller releases it."""
    shared = run_id is not None if shared is None else shared
    run = Run(out, run_id or _single_run_id(), resume=resume, words=words, covers=(chunks,), shared=shared).claim()
    try:
        folder = Path(chunks)
        have = sorted(folder.glob("chunk_*.npz")) if folder.is_dir() else []
        pending = sorted(folder.glob("pending_*.npz")) if folder.is_dir() else []
        afresh = f"delete or move that folder (or choose another {words.out})"
        if have and (folder / FINISHED).is_file():
            run.refuse_progress(f"{str(chunks)!r} holds the kept chunks of a finished run for {str(out)!r} (kept "
                                f"after it wrote its output)", then="write the output again from them", afresh=afresh)
        run.refuse_progress(f"{str(chunks)!r} holds the chunks of an earlier, unfinished run for {str(out)!r}"
                            if have or pending else None, afresh=afresh)
    except BaseException:
        run.release()
        raise
    return run, have


def _record_options(chunks, options: dict, resume: bool) -> None:
    """A fresh run records its options in the chunk folder's record (``manifest.json``; after the checks: a refused
    run writes nothing); a resumed run keeps those of the run it continues (once its chunk store has recorded its key
    there: before, a refused resume may have written them)."""
    old = recorded(chunks)
    if not resume or (old is not None and ("options" not in old or "key" not in old)):
        checkpoint.record(chunks, {"options": options}, fresh=not resume)


def _recorded_options(chunks) -> Optional[dict]:
    """The options the chunk folder's record holds (``None``: none, or a record that cannot be read)."""
    old = (recorded(chunks) or {}).get("options")
    return old if isinstance(old, dict) else None


def options_differ(chunks, options: dict, words: Words = PYTHON_WORDS) -> str:
    """``'seed=3 in the checkpoint vs seed=4 now; ...'`` from the chunk folder's record; '' if unknown."""
    old = _recorded_options(chunks)
    if old is None:
        return ""
    keys = {*old, *options}
    return "; ".join(differences({k: old.get(k) for k in keys}, {k: options.get(k) for k in keys}, show=words.shown,
                                 flat=True))


def other_command(chunks, options: dict, words: Words = PYTHON_WORDS) -> Optional[CheckpointError]:
    """The refusal of a chunk folder that another command made (its record holds another ``"command"`` than
    ``options``'): one line naming it, instead of every option that differs; ``None`` otherwise (also where either
    does not record a command)."""
    old = _recorded_options(chunks)
    then, now = (old or {}).get("command"), options.get("command")
    if not then or not now or then == now:
        return None
    return CheckpointError(f"{str(chunks)!r} holds the chunks of a 'jaxsleigh {then}' run, not of 'jaxsleigh {now}': "
                           f"continue it with 'jaxsleigh {then}' and its options with {words.resume}, or delete or "
                           f"move that folder (or choose another {words.out}) to start afresh")


def _explained(e, chunks, options: dict, words: Words):
    """A full disk or a refused checkpoint told with what to do (where the finished chunks are, which options
    differ from the interrupted run's); ``None`` where there is nothing to add."""
    if isinstance(e, DiskFullError):
        if words.resume != PYTHON_WORDS.resume and "(resume=True)" in str(e):
            return DiskFullError(e.errno, str(e).replace(" (resume=True)", ""), path=e.path)
        if chunks is None or words.resume in str(e) or "resume=True" in str(e):
            return None
        return DiskFullError(e.errno, f"{e}; the finished chunks are kept in {str(chunks)!r}: once there is space, "
                                      f"{words.again} with {words.resume} continues", path=e.path)
    if isinstance(e, RunLockedError):
        return None
    other = other_command(chunks, options, words) if chunks is not None else None
    if other is not None:
        return other
    why = options_differ(chunks, options, words) if chunks is not None else ""
    if not why:
        return None
    return CheckpointError(f"{why}: {str(chunks)!r} holds the chunks of a run with other options; to continue it, "
                           f"give its options with {words.resume}, or delete or move {str(chunks)!r} (or choose "
                           f"another {words.out}) to start afresh")


def start_processes(processes: Optional[Processes]):
    """Join the processes of a multi-process run (`jaxsleigh.files.distributed.start`): its `Cluster`, or
    ``None`` for one process. Call it before any JAX computation in this process."""
    p = processes or Processes()
    return start(p.coordinator, p.num_processes, p.process_id, timeout_s=p.timeout_s or CLUSTER_TIMEOUT_S)


def run_owned(check: Callable[[], dict], compute: Callable[[dict, tuple], None], assemble: Callable[[dict, bool], int],
              *, cluster, options: dict, recorded: dict, resume: bool, prepare=None, shared_dirs=None,
              words: Words = PYTHON_WORDS) -> int:
    """Run a chunked job in one process (``cluster=None``) or in every process of ``cluster``; returns
    ``assemble``'s code (process 0's, in every process).

    ``check()`` validates and owns the output (`own_output`), returning a state dict with ``"chunks"`` and
    ``"lock"``; ``compute(state, (index, count))`` writes a process's share of the chunks; ``assemble(state,
    multi)`` (process 0) reads them and writes the output; ``prepare(state)`` (process 0, before anyone
    computes) and ``shared_dirs(state)`` as in `jaxsleigh.files.distributed.run_shared`. ``options`` must be
    equal in every process; ``recorded`` is what a fresh run records for a later resume to compare. The
    lock is released however the run ends; a full disk or a refused resume is told with what to do.
    """
    held: dict = {}

    def checked():
        held["state"] = state = check()
        return state

    def prepared(state):
        if prepare is not None:
            prepare(state)
        _record_options(state["chunks"], recorded, resume)

    try:
        if cluster is None:
            state = checked()
            _record_options(state["chunks"], recorded, resume)
            return int(assemble(state, False))
        return run_shared(cluster, check=checked, compute=compute, assemble=lambda state: assemble(state, True),
                          prepare=prepared, shared_dirs=shared_dirs or (lambda state: []), options=options)
    except (DiskFullError, CheckpointError) as e:
        better = _explained(e, (held.get("state") or {}).get("chunks"), recorded, words)
        if better is None:
            raise
        raise better from None
    finally:
        lock = (held.get("state") or {}).get("lock")
        if lock is not None:
            lock.release()


def run_to_file(out, study: Callable[..., Any], save: Callable[[Path, Any], Any], *, options: Optional[dict] = None,
                resume: bool = False, keep_chunks: bool = False, processes: Optional[Processes] = None,
                check: Optional[Callable[[], None]] = None, finish: Optional[Callable[..., int]] = None,
                info: Optional[Callable[[Any], dict]] = None, command: Optional[list] = None,
                words: Words = PYTHON_WORDS, cluster=None, workers: Optional[Workers] = None) -> Finished:
    """Run ``study(checkpoint_dir=, resume=, shard=)`` chunk by chunk into the file ``out`` (steps 1-4 of the
    module's docstring); ``save(out, result)`` writes the result.

    Args:
      options: what defines the result (JSON-able; equal in every process; recorded for a later resume).
      resume: continue from the chunks of an interrupted run with the same options.
      keep_chunks: keep ``out.chunks/`` after ``out`` is written.
      processes: a multi-process run (`Processes`); ``None``: one process, or SLURM / Open MPI detected.
      check: validates the input before anything is written or claimed (raise ``ValueError``).
      finish: ``finish(result, written, record) -> code`` (process 0, after the sidecar, before the chunks
        are removed; ``record``: the sidecar's dict, with ``wall_s``, ``chunks_reused`` and, for several
        processes, ``processes``): e.g. a figure (append its path to ``written``) and a summary; its code is
        every process's.
      info: ``info(result) -> dict`` added to the sidecar.
      command: the command line recorded in the sidecar.
      cluster: the cluster already joined (`start_processes`) for ``processes``.
      workers: compute the chunks on the workers of a Dask cluster (`jaxsleigh.files.workers`); this process
        checks, owns the output and writes it. Not with ``processes``.

    Returns a `Finished`; in a multi-process run end every process with `leave`. An ``out`` that is not a
    regular file (a folder, a device such as ``/dev/full``, a named pipe), or whose ``.npz`` (which jaxsleigh's
    savers append to a name without it) or sidecar is, is refused with a ``ValueError`` before any work
    (`jaxsleigh.validate.output_file`).
    """
    out = Path(out)
    chunks, side = chunk_dir(out), sidecar(out)
    what = "output file" if words.out == PYTHON_WORDS.out else f"{words.out} file"
    output_file(out, what, suffix=".npz")
    output_file(side, "run record file")
    options = json.loads(json.dumps(options or {}, default=str))
    if workers is not None:
        if processes is not None or cluster is not None:
            raise ValueError("workers (a Dask cluster) and processes (jax.distributed) are two ways to share a run: "
                             "give one")
        require_dask()
    elif cluster is None:
        cluster = start_processes(processes)
    run_id = _cluster_run_id(processes, cluster) if cluster is not None else _single_run_id([str(out), options])
    if workers is not None:                     # the workers share the driver's lock: a fingerprint of this run
        run_id = f"workers:{_single_run_id()}"
    t0, load_start, kept = time.perf_counter(), load_average(), {}

    def owned() -> dict:
        if check is not None:
            check()
        chunks.mkdir(parents=True, exist_ok=True)
        lock, have = own_output(out, chunks, resume=resume, run_id=run_id, words=words,
                                shared=cluster is not None or workers is not None)
        other = other_command(chunks, options, words) if resume else None
        if other is not None:                   # another command's folder: said in one line, before any work
            lock.release()
            raise other
        (chunks / FINISHED).unlink(missing_ok=True)       # this run is not finished until it says so
        return {"chunks": chunks, "lock": lock, "had": len(have)}

    def compute(state, shard):
        study(checkpoint_dir=chunks, resume=True, shard=shard)

    def assemble(state, multi):
        lost = None
        if workers is not None:                 # the workers compute the chunks, this process assembles them
            lost = compute_shares(workers, study, out=out, chunks=chunks, run_id=run_id)
        result = study(checkpoint_dir=chunks, resume=resume or multi or workers is not None, shard=None)
        written = [str(save(out, result))]
        run_info = getattr(result, "run_info", None) or {}
        reused = state["had"] if multi or workers is not None else int(run_info.get("chunks_reused") or 0)
        record = {"command": command, "wall_s": time.perf_counter() - t0, "devices": run_info.get("devices"),
                  "chunks_reused": reused, "loadavg_start": load_start, "loadavg_end": load_average(),
                  "cpu_count": os.cpu_count(), **({"processes": cluster.count} if multi else {}),
                  **({"workers": workers.count or workers.scheduler, "lost_workers": lost} if lost is not None
                     else {}),
                  **(info(result) if info is not None else {})}
        atomic_write_text(side, json.dumps(record, indent=1, default=str) + "\n")
        written.append(str(side))
        code = int(finish(result, written, record)) if finish is not None else 0
        if not keep_chunks:                     # after the figure: a full disk there leaves resume to finish
            shutil.rmtree(chunks, ignore_errors=True)
        else:
            atomic_write_text(chunks / FINISHED, json.dumps({"out": str(out), "written": written}, indent=1) + "\n")
        kept.update(result=result, written=tuple(written))
        return code

    def prepare(state):                         # a fresh multi-process run: no stale manifest
        if not resume:
            (chunks / MANIFEST).unlink(missing_ok=True)

    code = run_owned(owned, compute, assemble, cluster=cluster, options=options,
                     recorded={k: v for k, v in options.items() if k not in _NOT_RECORDED}, resume=resume,
                     prepare=prepare, shared_dirs=lambda state: [chunks], words=words)
    return Finished(kept.get("result"), code, kept.get("written", ()), cluster)


#: Options that do not change the chunks (left out of the checkpoint's recorded options).
_NOT_RECORDED = {"out", "plot", "resume", "keep_chunks", "audit_rows"}


def leave(done: Finished) -> int:
    """End a run: stop this process's heartbeat and return its code; in a multi-process run whose processes
    have process 0's result, exit the process at once with it (JAX's shutdown would wait at its barrier
    for a process that died, then abort; every file is written, atomically, already)."""
    cluster = done.cluster
    if cluster is None:
        return done.code
    if done.code == EXIT_CLUSTER or cluster.synced:
        cluster.stop()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(done.code)
    cluster.stop()
    return done.code
