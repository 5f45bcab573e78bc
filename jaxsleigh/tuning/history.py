"""The optimisation history on disk (``.npz``, one key per `TuneHistory` field)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .optimizer import TuneHistory
from ..files.npz import atomic_write
from ..validate import output_file

__all__ = ["save_history", "load_history"]


def save_history(history: TuneHistory, path, **extra) -> Path:
    """Write the history as ``.npz`` (one key per field, plus ``extra`` arrays)."""
    path = output_file(path, "history file", suffix=".npz")     # not a folder, device or named pipe
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda f: np.savez(f, **history._asdict(), **{k: np.asarray(v) for k, v in extra.items()}))
    return path


def load_history(path) -> TuneHistory:
    """Read a history written by `save_history`."""
    with np.load(path, allow_pickle=False) as z:
        return TuneHistory(**{f: z[f] for f in TuneHistory._fields})
