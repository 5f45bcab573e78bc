"""Typed warnings and errors of jaxsleigh.

Every problem a user can cause is a ``ValueError`` (or a subclass) whose message says what to
change; the command line prints it as ``jaxsleigh: error: ...`` and exits with code 2. Warnings
are subclasses of `JaxsleighWarning`, so callers (and the command line) recognise them by
type, not by their text::

    with warnings.catch_warnings():
        warnings.simplefilter("error", js.errors.FlaggedStartsWarning)   # make bad rows fatal
"""
from __future__ import annotations

__all__ = ["JaxsleighWarning", "FlaggedStartsWarning", "DamagedCheckpointWarning", "CheckpointError"]


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


class CheckpointError(ValueError):
    """A checkpoint directory cannot be used for this run (it belongs to another run, or its
    manifest is damaged); the message names the file and what to do."""
