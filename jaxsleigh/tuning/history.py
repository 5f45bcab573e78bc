"""The optimisation history on disk (``.npz``, one key per `TuneHistory` field), and the one writer of every tuner's
history: equal histories, equal bytes."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .optimizer import TuneHistory
from ..files.npz import write_npz_deterministic
from ..validate import output_file

__all__ = ["save_history", "load_history", "save_arrays"]


def save_history(history: TuneHistory, path, **extra) -> Path:
    """Write the history as ``.npz`` (one key per field, plus ``extra`` arrays)."""
    path = output_file(path, "history file", suffix=".npz")     # not a folder, device or named pipe
    return save_arrays(path, {**history._asdict(), **extra})


def save_arrays(path, arrays: dict) -> Path:
    """Write a history's ``arrays`` (one key each) as an uncompressed ``.npz`` with fixed timestamps, atomically: the
    same history, the same bytes (`jaxsleigh.files.npz.write_npz_deterministic`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_npz_deterministic(path, {k: np.asarray(v) for k, v in arrays.items()}, compress=False,
                                   stamped=False)


def load_history(path) -> TuneHistory:
    """Read a history written by `save_history`."""
    with np.load(path, allow_pickle=False) as z:
        return TuneHistory(**{f: z[f] for f in TuneHistory._fields})
