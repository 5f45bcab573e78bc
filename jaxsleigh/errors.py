"""Typed warnings and errors of jaxsleigh.

Every problem a user can cause is a ``ValueError`` (or a subclass) whose message says what to
change; the command line prints it as ``jaxsleigh: error: ...`` and exits with code 2. Warnings
are subclasses of `JaxsleighWarning`, so callers (and the command line) recognise them by
type, not by their text::

    with warnings.catch_warnings():
        warnings.simplefilter("error", js.errors.FlaggedStartsWarning)   # make bad rows fatal
"""
from __future__ import annotations

__all__ = ["JaxsleighWarning", "FlaggedStartsWarning", "DamagedCheckpointWarning", "AccuracyWarning", "CheckpointError",
           "RunLockedError", "RunLockWarning", "DiskFullError", "DamagedFileError"]


class JaxsleighWarning(UserWarning):
    """Base class of jaxsleigh's warnings."""


class FlaggedStartsWarning(JaxsleighWarning):
    """Some rows of a batch of initial conditions were flagged (status 1, 2 or 8) and not integrated.

    Attributes:
      rows: indices of the flagged rows (all of them).
      status: their status codes.
    """

    def __init__(self, message: str, rows=(), status=()):
        super().__init__(message)
        self.rows = list(rows)
        self.status = list(status)


class DamagedCheckpointWarning(JaxsleighWarning):
    """A checkpoint chunk could not be read (truncated, empty, corrupt) and is recomputed."""


class AccuracyWarning(JaxsleighWarning):
    """The accuracy audit (`jaxsleigh.studies.audit`) found the result's rows off their float64 reference by more
    than its thresholds: the energy, ``T_eps`` or final states it reports are not to be trusted at these settings."""


class CheckpointError(ValueError):
    """A checkpoint directory cannot be used for this run (it belongs to another run, or its
    manifest is damaged); the message names the file and what to do."""


class DamagedFileError(ValueError):
    """A file jaxsleigh wrote and reads back (a result, a checkpoint chunk, a tuner's checkpoint, a frontier) does not
    hold what it wrote: its content digest does not match (it was edited or damaged after it was written), a field is
    missing, of another dtype or shape, or holds values no run writes (an unknown status code, a non-finite parameter,
    an iteration counter past the run's budget, decreasing horizons). The message names the file and what is wrong;
    the command line prints it and exits with code 2. A damaged checkpoint *chunk* is not refused but recomputed (with
    a `DamagedCheckpointWarning` naming it).

    Attributes:
      path: the file.
      problem: what is wrong with it, in words.
    """

    def __init__(self, message: str, path=None, problem: str = ""):
        super().__init__(message)
        self.path = path
        self.problem = problem


class RunLockedError(CheckpointError):
    """Another run (another process, with other settings) is writing the same output file or
    checkpoint folder; the message names it (host, pid, start time). The command line exits with
    code 5 (`jaxsleigh.cli.common.EXIT_LOCKED`).

    Attributes:
      path: the output file or folder that is in use.
      holder: what the other run recorded in its lock file (host, pid, started, ...).
    """

    exit_code = 5

    def __init__(self, message: str, path=None, holder=None):
        super().__init__(message)
        self.path = path
        self.holder = dict(holder or {})


class RunLockWarning(JaxsleighWarning):
    """An output could not be locked (the filesystem has no ``flock``): two runs writing it are not
    kept apart."""


class DiskFullError(OSError):
    """A file could not be written because its disk (or the user's quota) is full; the message names
    the file and what to do. The command line exits with code 4 (`jaxsleigh.cli.common.EXIT_DISK_FULL`).

    Attributes:
      path: the file being written.
    """

    exit_code = 4

    def __init__(self, errno_: int, message: str, path=None):
        super().__init__(errno_, message)
        self.path = path

    def __str__(self) -> str:   # the message alone, not "[Errno 28] ..."
        return str(self.strerror)
