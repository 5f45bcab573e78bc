"""One run lifecycle for everything that writes: every command (simulate, basin, sweep, optimum, tune, compare, paper)
and every Python run of a study or a tuner that owns an output lives the same five steps, through `Run`:

1. **claim** the output: one lock next to it (`jaxsleigh.files.runlock.RunLock`), which covers the folders the run
   writes besides it (a chunked run's ``OUT.chunks/``), under one fingerprint (the run's settings hashed, so that the
   same run started twice is told it is in progress; another live run is refused with
   `jaxsleigh.errors.RunLockedError`, exit code 5 on the command line);
2. **own** what it writes: nothing of it is written by another run meanwhile;
3. **decide** whether to resume, in one place (`Run.refuse_progress`): the kept progress of an interrupted run
   (chunks, a tuner's checkpoint, an interrupted front) is never written over without ``resume``, and ``resume``
   without any progress is refused; both refusals say what to do, in the caller's words (`Words`);
4. **finish** atomically: every file is written under a temporary name and renamed (`jaxsleigh.files.npz.atomic_write`,
   which every saver uses), and the file that says the run finished (a result, a record, ``paper.npz``) last, so an
   interrupted run never leaves a partial file, nor one that claims a finished run;
5. **release** the lock however the run ends (its return, an error, Ctrl-C): a ``with`` block.

What differs between the runs stays with them: a chunked run's chunks and processes (`jaxsleigh.files.runner`), a
tuner's checkpoint and history (`jaxsleigh.tuning.runs.TuningRun`, a `Run`), a command's flags
(`jaxsleigh.cli.common.claim_output`).
"""
from __future__ import annotations

import uuid
from pathlib import Path
from typing import Callable, NamedTuple, Optional

from .runlock import RunLock, settings_fingerprint

__all__ = ["Run", "refuse_progress", "Words", "PYTHON_WORDS", "COMMAND_WORDS"]


class Words(NamedTuple):
    """How a run's messages name the caller's options: Python's keywords by default, the flags on the
    command line (``resume='--resume'``, ``out='--out'``, ``option=lambda k: '--' + k.replace('_', '-')``)."""

    resume: str = "resume=True"
    out: str = "out"
    option: Callable[[str], str] = lambda k: f"{k}="
    again: str = "the same call"

    def shown(self, name: str, value) -> str:
        """An option with its value as the caller writes it: ``'seed=3'``, ``'--seed 3'``, ``'--x64'``, ``'no
        --plot'`` (unset or off), a list's values one after the other."""
        flag = self.option(name)
        if value is None or value is False:
            return f"no {flag.rstrip('=')}"
        if value is True:
            return flag.rstrip("=")
        v = " ".join(map(str, value)) if isinstance(value, list) else value
        return f"{flag}{v}" if flag.endswith("=") else f"{flag} {v}"


PYTHON_WORDS = Words()

#: How the command line's messages name its options.
COMMAND_WORDS = Words(resume="--resume", out="--out", option=lambda k: "--" + k.replace("_", "-"),
                      again="the same command")


class Run:
    """A run's claim on its output ``out`` (a file, or a ``folder``), held from `claim` (or ``with``) to `release`.

    Args:
      out: what the run writes.
      fingerprint: identifies the run to its lock; ``settings``: what defines the run, hashed into it instead
        (`jaxsleigh.files.runlock.settings_fingerprint`); neither: a fingerprint of its own (no run is the same).
      resume: continue the kept progress of an interrupted run (`refuse_progress`).
      words: how the refusals name ``resume``, ``out`` and the options.
      folder: ``out`` is a folder (the lock goes inside it).
      covers: folders the run writes besides ``out`` (a chunked run's chunks), held by the same lock.
      shared: other processes with the same fingerprint share the output (the processes of one run).
    """

    def __init__(self, out, fingerprint: Optional[str] = None, *, settings=None, resume: bool = False,
                 words: Words = PYTHON_WORDS, folder: bool = False, covers=(), shared: bool = False):
        self.out = Path(out)
        if fingerprint is None:
            fingerprint = uuid.uuid4().hex if settings is None else settings_fingerprint(settings)
        self.run_id = str(fingerprint)
        self.resume = bool(resume)
        self.words = words
        self.folder = bool(folder)
        self.covers = tuple(covers)
        self.shared = bool(shared)
        self._lock: Optional[RunLock] = None

    # -- claim / release ----------------------------------------------------------------------

    def claim(self) -> "Run":
        """Take the one lock of the run (next to ``out``, or in it for a folder; covering ``covers``);
        `jaxsleigh.errors.RunLockedError` names another live run that holds it. Claiming twice is claiming once."""
        if self._lock is None:
            what = "output folder" if self.folder else "output"
            self._lock = RunLock(self.out, self.run_id, folder=self.folder, what=what,
                                 hint=f"choose another {self.words.out}", shared=self.shared,
                                 covers=self.covers).acquire()
        return self

    def release(self) -> None:
        """Give the output back. Safe to call twice."""
        lock, self._lock = self._lock, None
        if lock is not None:
            lock.release()

    @property
    def claimed(self) -> bool:
        return self._lock is not None

    def __enter__(self) -> "Run":
        return self.claim()

    def __exit__(self, *exc) -> None:
        self.release()

    # -- the one resume decision ----------------------------------------------------------------

    def refuse_progress(self, kept: Optional[str], *, then: str = "continue it", afresh: Optional[str] = None,
                        missing: Optional[str] = None, error: type = ValueError) -> None:
        """The one resume decision (`refuse_progress`) for this run's ``resume`` and ``words``."""
        refuse_progress(kept, resume=self.resume, words=self.words, then=then, afresh=afresh, missing=missing,
                        error=error)


def refuse_progress(kept: Optional[str], *, resume: bool, words: Words = PYTHON_WORDS, then: str = "continue it",
                    afresh: Optional[str] = None, missing: Optional[str] = None, error: type = ValueError) -> None:
    """Whether a run may go on over what an earlier run kept, decided in one place for every run (a `Run`, and a
    chunk store used on its own).

    ``kept``: what an interrupted run left (``"'out.npz.chunks' holds the chunks of an earlier, unfinished run for
    'out.npz'"``; ``None``: nothing). Kept progress without ``resume`` is refused (nothing is written over it), saying
    to add ``resume`` to ``then`` or, ``afresh`` (default: delete it, or choose another output), to start afresh; with
    ``missing`` (why there is nothing to continue) ``resume`` without kept progress is refused too. Raises ``error`` (a
    ``ValueError``, exit code 2 on the command line)."""
    flag = words.resume
    if kept and not resume:
        afresh = afresh or f"delete it (or choose another {words.out})"
        raise error(f"{kept}; add {flag} (with the same options) to {then}, or {afresh} to start afresh")
    if resume and not kept and missing is not None:
        raise error(f"{flag}: {missing}; run without {flag}")
