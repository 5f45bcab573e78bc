"""The host runner: a long, chunked run that owns its output file, its chunks computed here or by the workers of a
Dask cluster.

A study that writes its result chunk by chunk (`jaxsleigh.run_basin`, `jaxsleigh.sweep`, or any function that
takes the runner's ``checkpoint_dir``, ``resume`` and ``shard``, e.g. into `jaxsleigh.RunOptions`) runs to one file
``out`` in three steps, the same from Python and from the command line (``jaxsleigh basin``, ``jaxsleigh sweep``
and ``jaxsleigh optimum`` are `run_to_file` with their own checks and printing):

1. **own** ``out`` as every run that writes does (`jaxsleigh.files.run.Run`): one lock next to it, which covers
   ``out.chunks/`` too (another live run on the same file is refused with `jaxsleigh.errors.RunLockedError`, exit code
   5 on the command line), then refuse a chunk folder ``out.chunks/`` that holds the chunks of an earlier run unless
   ``resume=True`` (decided there once: the chunk store does not decide it again); a
   fresh run records its options in the folder's one record file, ``out.chunks/manifest.json``
   (`jaxsleigh.files.checkpoint.record`, next to what the chunk store records there), so that a refused
   resume can name the options that differ;
2. **compute** the chunks: this process does them all, or, with ``workers`` (`Workers`), the workers of a Dask
   cluster do (`jaxsleigh.files.workers.compute_shares`: a dead worker's tasks run again on the others);
3. **assemble**: the result read from the chunks (a missing chunk is computed), saved to ``out`` atomically, a
   sidecar ``out.run.json`` of what varies between runs (wall time, devices, load, workers, the command), the chunk
   folder removed unless ``keep_chunks`` (then marked finished, `FINISHED`: a later run is told it holds a finished
   run).

An interrupted run (Ctrl-C, a killed process, a full disk) keeps its finished chunks; the same call
with ``resume=True`` continues it and writes the same file, byte for byte, with any number of workers or none.

Example, a basin on four worker processes of this machine::

    from jaxsleigh import RunOptions, run_basin, sample_starts, save_basin
    from jaxsleigh.files.runner import Workers, run_to_file

    starts = sample_starts(10**6, seed=1)
    # the runner passes checkpoint_dir, resume and shard: the study puts them into its RunOptions
    done = run_to_file("mc.npz", lambda **kw: run_basin(starts, eps=0.05, run=RunOptions(**kw)), save_basin,
                       options={"samples": 10**6, "seed": 1, "eps": 0.05}, workers=Workers(4))
"""
from __future__ import annotations

import json
import os
import platform
import shutil
import time
from pathlib import Path
from typing import Any, Callable, NamedTuple, Optional

from . import checkpoint
from .checkpoint import differences, recorded
from .npz import RUN_VARIES, atomic_write_text, steady
from .run import PYTHON_WORDS, Run, Words
from .runlock import settings_fingerprint
from .workers import Workers, compute_shares, require_dask
from ..errors import CheckpointError, DiskFullError, RunLockedError
from ..validate import output_file

__all__ = ["Workers", "Words", "PYTHON_WORDS", "Finished", "run_to_file", "run_owned", "own_output", "chunk_dir",
           "FINISHED", "other_command", "sidecar", "write_sidecar", "run_record", "RUN_VARIES", "steady", "options_differ",
           "load_average"]


class Finished(NamedTuple):
    """What `run_to_file` returns: ``result``, ``code`` (what ``finish`` returned; 0 without ``finish``) and the
    files written."""

    result: Any
    code: int
    written: tuple


def chunk_dir(out) -> Path:
    """The checkpoint folder of ``out``: ``FILE.npz.chunks/``."""
    out = Path(out)
    return out.with_name(out.name + ".chunks")


def sidecar(out) -> Path:
    """The run's sidecar next to ``out``: ``FILE.run.json`` (what varies between runs)."""
    out = Path(out)
    return out.with_name(out.stem + ".run.json")


def run_record(command, wall_s: float, devices=None, **more) -> dict:
    """What a single-process run writes in its sidecar (`write_sidecar`): its ``command``, ``wall_s``, the
    ``devices`` it used, the machine's load at the end and its CPU count, then ``more``."""
    return {"command": None if command is None else [str(c) for c in command], "wall_s": wall_s,
            "devices": devices, "loadavg_end": load_average(), "cpu_count": os.cpu_count(), **more}


def write_sidecar(out, record: dict) -> Path:
    """Write the run's sidecar ``FILE.run.json`` next to ``out`` (`sidecar`), atomically: what varies between
    runs of the same command (``wall_s``, ``devices``, the ``command``, ...), kept out of the result file so that
    the same command writes the same bytes. Every command that writes records its run here. Returns its path."""
    side = output_file(sidecar(out), "run record file")
    atomic_write_text(side, json.dumps(record, indent=1, default=str) + "\n")
    return side


def load_average() -> list:
    """The machine's load averages (1, 5, 15 min), recorded next to timings; [] where unknown."""
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:  # pragma: no cover - not on every platform
        return []


def _single_run_id(options: Any = None) -> str:
    """The fingerprint of a single-process run: its options (what defines the result) hashed, so that the same run
    started twice on one output is told "the same run is in progress"; without options, one of its own."""
    if options is None:
        return f"{platform.node()}:{os.getpid()}:{time.time_ns()}"
    return "single:" + settings_fingerprint(options)


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


def run_owned(check: Callable[[], dict], assemble: Callable[[dict], int], *, recorded: dict, resume: bool,
              words: Words = PYTHON_WORDS) -> int:
    """Run a chunked job; returns ``assemble``'s code.

    ``check()`` validates and owns the output (`own_output`), returning a state dict with ``"chunks"`` and
    ``"lock"``; ``assemble(state)`` computes the chunks, reads them and writes the output. ``recorded`` is what a
    fresh run records for a later resume to compare. The lock is released however the run ends; a full disk or a
    refused resume is told with what to do.
    """
    state: dict = {}
    try:
        state = check()
        _record_options(state["chunks"], recorded, resume)
        return int(assemble(state))
    except (DiskFullError, CheckpointError) as e:
        better = _explained(e, state.get("chunks"), recorded, words)
        if better is None:
            raise
        raise better from None
    finally:
        lock = state.get("lock")
        if lock is not None:
            lock.release()


def run_to_file(out, study: Callable[..., Any], save: Callable[[Path, Any], Any], *, options: Optional[dict] = None,
                resume: bool = False, keep_chunks: bool = False, workers: Optional[Workers] = None,
                check: Optional[Callable[[], None]] = None, finish: Optional[Callable[..., int]] = None,
                info: Optional[Callable[[Any], dict]] = None, command: Optional[list] = None,
                words: Words = PYTHON_WORDS) -> Finished:
    """Run ``study(checkpoint_dir=, resume=, shard=)`` chunk by chunk into the file ``out`` (steps 1-3 of the
    module's docstring); ``save(out, result)`` writes the result.

    Args:
      options: what defines the result (JSON-able; recorded for a later resume).
      resume: continue from the chunks of an interrupted run with the same options.
      keep_chunks: keep ``out.chunks/`` after ``out`` is written.
      workers: compute the chunks on the workers of a Dask cluster (`Workers`, `jaxsleigh.files.workers`); this
        process checks, owns the output and writes it. ``None``: this process computes them.
      check: validates the input before anything is written or claimed (raise ``ValueError``).
      finish: ``finish(result, written, record) -> code`` (after the sidecar, before the chunks are removed;
        ``record``: the sidecar's dict, with ``wall_s``, ``chunks_reused`` and, with ``workers``, ``workers`` and
        ``lost_workers``): e.g. a figure (append its path to ``written``) and a summary; its code is returned.
      info: ``info(result) -> dict`` added to the sidecar.
      command: the command line recorded in the sidecar.

    Returns a `Finished`. An ``out`` that is not a regular file (a folder, a device such as ``/dev/full``, a named pipe), or whose ``.npz`` (which jaxsleigh's
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
        if not isinstance(workers, Workers):
            raise ValueError(f"workers must be a jaxsleigh.files.runner.Workers (e.g. Workers(4)), got {workers!r}")
        require_dask()
        run_id = f"workers:{_single_run_id()}"  # the workers share this run's lock: a fingerprint of its own
    else:
        run_id = _single_run_id([str(out), options])
    t0, load_start, kept = time.perf_counter(), load_average(), {}

    def owned() -> dict:
        if check is not None:
            check()
        chunks.mkdir(parents=True, exist_ok=True)
        lock, have = own_output(out, chunks, resume=resume, run_id=run_id, words=words, shared=workers is not None)
        other = other_command(chunks, options, words) if resume else None
        if other is not None:                   # another command's folder: said in one line, before any work
            lock.release()
            raise other
        (chunks / FINISHED).unlink(missing_ok=True)       # this run is not finished until it says so
        return {"chunks": chunks, "lock": lock, "had": len(have)}

    def assemble(state):
        lost = None
        if workers is not None:                 # the workers compute the chunks, this process assembles them
            lost = compute_shares(workers, study, out=out, chunks=chunks, run_id=run_id)
        result = study(checkpoint_dir=chunks, resume=resume or workers is not None, shard=None)
        written = [str(save(out, result))]
        run_info = getattr(result, "run_info", None) or {}
        reused = state["had"] if workers is not None else int(run_info.get("chunks_reused") or 0)
        record = {"command": command, "wall_s": time.perf_counter() - t0, "devices": run_info.get("devices"),
                  "chunks_reused": reused, "loadavg_start": load_start, "loadavg_end": load_average(),
                  "cpu_count": os.cpu_count(),
                  **({"workers": workers.count or workers.scheduler, "lost_workers": lost} if lost is not None
                     else {}),
                  **(info(result) if info is not None else {})}
        written.append(str(write_sidecar(out, record)))
        code = int(finish(result, written, record)) if finish is not None else 0
        if not keep_chunks:                     # after the figure: a full disk there leaves resume to finish
            shutil.rmtree(chunks, ignore_errors=True)
        else:
            atomic_write_text(chunks / FINISHED, json.dumps({"out": str(out), "written": written}, indent=1) + "\n")
        kept.update(result=result, written=tuple(written))
        return code

    code = run_owned(owned, assemble, recorded={k: v for k, v in options.items() if k not in _NOT_RECORDED},
                     resume=resume, words=words)
    return Finished(kept.get("result"), code, kept.get("written", ()))


#: Options that do not change the chunks (left out of the checkpoint's recorded options).
_NOT_RECORDED = {"out", "plot", "resume", "keep_chunks", "audit_rows"}
