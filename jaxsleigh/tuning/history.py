"""The optimisation history on disk (``.npz``, one key per `TuneHistory` field), and the one writer of every tuner's
history: equal histories, equal bytes."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .optimizer import TuneHistory
from ..files.npz import write_npz_deterministic
from ..validate import output_file

__all__ = ["save_history", "load_history", "save_arrays", "history_wall", "WALL_COLUMNS"]


def save_history(history: TuneHistory, path, **extra) -> Path:
    """Write the history as ``.npz`` (one key per field, plus ``extra`` arrays)."""
    path = output_file(path, "history file", suffix=".npz")     # not a folder, device or named pipe
    return save_arrays(path, {**history._asdict(), **extra})


#: The columns of a history that hold wall time (the gradient tuner's ``wall``, the search's ``wall_s``): they vary
#: between runs, so a history file leaves them out; a tuner's run records them in its sidecar ``FILE.run.json``
#: (``history``: `history_wall`).
WALL_COLUMNS = ("wall", "wall_s")


def history_wall(history) -> dict:
    """The wall-time columns (`WALL_COLUMNS`) of a history (a `TuneHistory` or a dict of arrays), as lists."""
    arrays = history._asdict() if hasattr(history, "_asdict") else dict(history or {})
    return {k: np.asarray(v, np.float64).tolist() for k, v in arrays.items() if k in WALL_COLUMNS}


def save_arrays(path, arrays: dict) -> Path:
    """Write a history's ``arrays`` (one key each) as an uncompressed ``.npz`` with fixed timestamps, atomically: the
    same history, the same bytes (`jaxsleigh.files.npz.write_npz_deterministic`). Its wall-time columns
    (`WALL_COLUMNS`) are left out: they vary between runs."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_npz_deterministic(path, {k: np.asarray(v) for k, v in arrays.items() if k not in WALL_COLUMNS},
                                   compress=False, stamped=False)


def load_history(path) -> TuneHistory:
    """Read a history written by `save_history`: its wall time per iteration from the history itself (a file of
    jaxsleigh 0.3 kept it there) or from the sidecar of the same name (``HISTORY.run.json``, where the tuner's run
    recorded it when its output has the history's name: ``out.json``, ``out.npz``), else NaN."""
    from ..files.runner import sidecar

    with np.load(path, allow_pickle=False) as z:
        got = {f: z[f] for f in TuneHistory._fields if f in z.files}
    if "wall" not in got:
        side = sidecar(path)
        rows = len(next(iter(got.values())))
        try:
            got["wall"] = np.asarray(json.loads(side.read_text())["history"]["wall"], np.float64)
        except (OSError, ValueError, KeyError, TypeError):
            got["wall"] = np.full(rows, np.nan)
    return TuneHistory(**got)
