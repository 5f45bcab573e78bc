"""Checkpoint and resume of the tuners: the optimiser's whole state in one fingerprinted ``.npz``, written
atomically after every iteration by the one class that writes every resumable run's checkpoints, the chunk store's
too (`jaxsleigh.files.checkpoint.Checkpoint`; how each tuner lays out its state in it: `TunerCheckpoint` for the
paper's gains, `LawCheckpoint` for any law, the CMA-ES search's generations), and
`TuningInterrupted` (Ctrl-C keeps the best so far). A checkpoint may also carry the options of the command that
wrote it (`checkpoint_options`), so that a refused resume can name the option first.

A checkpoint is checked before a resume uses it, and refused with a `jaxsleigh.errors.DamagedFileError` naming the
file and what is wrong (the command line prints it and exits with code 2): its content digest (``__digest__``, over
every array's name, dtype, shape and bytes) must match what was written, so any edit or damage after writing is
caught (a checkpoint of jaxsleigh 0.3 or earlier records none and is read with the checks below only); every field
the tuner needs must be there, of the shape and kind of number of the run's state; the parameters (the current ones,
the best and every valid candidate) must be finite; the iteration counter a whole number from 0 to the run's budget
(``steps``; for `tune_law`, the number of steps its history records). A refused checkpoint is never used: the tuner's
state is one file, nothing can be recomputed in its place, so the fix is to delete it and start afresh."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np

from ..files.checkpoint import Checkpoint, refused
from ..model.params import gains_to_dict
from ..model.controller import law_leaf_names
from ..studies.config import plant_to_dict
from .objective import loss_record

__all__ = ["TuningInterrupted", "TunerCheckpoint", "tune_settings", "LawCheckpoint", "law_settings",
           "checkpoint_options", "Checkpoint", "tree_arrays", "tree_from", "track_arrays",
           "restore_track", "check_resume", "refused", "checked_state", "check_counter"]


class TuningInterrupted(KeyboardInterrupt):
    """Ctrl-C during `tune`. ``partial``: a `TuneResult`
    with the best valid gains so far (``None`` if no candidate was valid yet); ``checkpoint``: the file
    to resume from (or ``None``)."""

    def __init__(self, partial, checkpoint):
        super().__init__("tuning interrupted")
        self.partial = partial
        self.checkpoint = checkpoint


def tune_settings(g0, names, config, loss, plant, robust, guard, x64, d_floor, starts) -> dict:
    """Everything that determines a `jaxsleigh.tuning.tune` run but its training starts, as JSON (`Checkpoint.of_run`
    adds those: a checkpoint only resumes the same run)."""
    return {"gains0": gains_to_dict(g0), "names": list(names), "config": config._asdict(),
            "loss": loss_record(loss),
            "plant": None if plant is None else plant_to_dict(plant), "robust": None if robust is None else repr(robust),
            "guard": None if guard is None else np.asarray(guard, np.float64).tolist(), "x64": bool(x64),
            "d_floor": float(d_floor), "starts": repr(starts) if callable(starts) else "array"}


def check_resume(checkpoint, resume: bool, what: str = "tuner checkpoint", run: str = "run") -> None:
    """Refuse ``resume=True`` without a ``checkpoint`` file, and a ``checkpoint`` (``what``) left by an earlier run
    without ``resume=True`` (nothing is written over it); ``run`` names what writes the file."""
    if resume and checkpoint is None:
        raise ValueError(f"resume=True needs checkpoint (the file the interrupted {run} wrote)")
    if checkpoint is not None and not resume and Path(checkpoint).exists():
        raise ValueError(f"{what} {str(Path(checkpoint))!r} exists from an earlier run; pass resume=True (--resume) "
                         "to continue it, or delete it to start afresh")


class _Content(Exception):
    """A field of a checkpoint that is not what the run wrote (its message says how)."""


def checked_state(what: str, path, restore):
    """``restore()`` (which reads a checkpoint's arrays into the run's state), a missing field or one not of the run's
    shape, kind or range (`tree_from`, `check_counter`) turned into the `refused` error naming the file."""
    try:
        return restore()
    except KeyError as e:
        raise refused(what, path, f"it lacks the field {e.args[0]!r}") from None
    except _Content as e:
        raise refused(what, path, str(e)) from None
    except (TypeError, ValueError) as e:
        raise refused(what, path, f"a field cannot be read as the run's state ({type(e).__name__}: {e})") from None


def check_counter(a: dict, name: str, top: int, says: str) -> int:
    """``a[name]`` as an int: a whole number from 0 to ``top`` (``says``: what ``top`` is), else `_Content`."""
    v = np.asarray(a[name])
    if v.ndim != 0 or not np.issubdtype(v.dtype, np.integer):
        raise _Content(f"its iteration counter {name} is {v.dtype} of shape {v.shape}, not a whole number")
    if not 0 <= int(v) <= top:
        raise _Content(f"its iteration counter {name} is {int(v)}, outside 0-{top} ({says})")
    return int(v)


def _finite(prefix: str, x) -> None:
    if not np.all(np.isfinite(np.asarray(x, np.float64))):
        raise _Content(f"its parameters {prefix} are not all finite (NaN or inf); no run writes those")


def tree_arrays(prefix: str, tree) -> dict:
    """``{prefix/i: leaf i}`` of a pytree, for `Checkpoint.write`."""
    return {f"{prefix}/{i}": np.asarray(leaf) for i, leaf in enumerate(jax.tree_util.tree_leaves(tree))}


def tree_from(a: dict, prefix: str, like, finite: bool = False):
    """The pytree shaped (and typed) like ``like`` from the arrays `tree_arrays` wrote; a `KeyError` for a missing
    leaf, `_Content` for one of another shape, one that is not numbers or (``finite``: parameters) is not finite."""
    leaves, tdef = jax.tree_util.tree_flatten(like)
    out = []
    for i, leaf in enumerate(leaves):
        name, want = f"{prefix}/{i}", np.shape(leaf)
        x = np.asarray(a[name])
        if x.dtype.kind not in "biuf":
            raise _Content(f"its field {name!r} holds {x.dtype}, not numbers")
        if x.shape != want:
            raise _Content(f"its field {name!r} has shape {x.shape}, the run's state {want}")
        if finite:
            _finite(repr(name), x)
        out.append(jnp.asarray(x, jnp.asarray(leaf).dtype))
    return jax.tree_util.tree_unflatten(tdef, out)


class TunerCheckpoint:
    """The optimiser's whole state in one ``.npz`` (pytree leaves by position), written atomically.

    The state: the iteration, the current parameters and optax state (which, with the backtracking
    wrapper, holds the last valid point), the `jaxsleigh.tuning.optimizer.CandidateTrack` (`track_arrays`) and the
    tuner's ``extra`` arrays. The vmapped Pareto front keeps a list of tracks, one per budget (``budget{b}/``), its
    parameters batched over the budgets; ``what`` names the file in a refusal.
    """

    def __init__(self, path, stamp: Checkpoint, row_fields, what: str = "tuner checkpoint"):
        self.path, self.stamp, self._row_fields, self.what = Path(path), stamp, tuple(row_fields), what

    def save(self, it, trainable, opt_state, track, **extra) -> None:
        arrays = {"it": np.int64(it), **extra, **tree_arrays("trainable", trainable),
                  **tree_arrays("opt_state", opt_state)}
        for prefix, t in _prefixed(track):
            arrays.update(track_arrays(t, self._row_fields, prefix))
        self.stamp.write(self.path, arrays)

    def load(self, trainable, opt_state, groups, track, budget: Optional[int] = None):
        """``(it, trainable, opt_state, arrays)`` restructured like ``trainable`` / ``opt_state``, ``track`` restored
        (`restore_track`; a list of tracks: like one budget's ``trainable``) and every array read (the ``extra``);
        ``None`` if there is no file. ``budget``: the run's iterations (``steps``), the most ``it`` can be (``None``: no
        bound, for a caller that does not know it). A file that lacks a field, holds one of another shape or kind,
        non-finite parameters or a counter outside ``0..budget`` is refused (`jaxsleigh.errors.DamagedFileError`,
        naming it)."""
        a = self.stamp.read(self.path, self.what)
        if a is None:
            return None

        def restore():
            it = check_counter(a, "it", np.iinfo(np.int64).max if budget is None else int(budget), "the run's steps")
            one = jax.tree_util.tree_map(lambda x: x[0], trainable) if isinstance(track, list) else trainable
            for prefix, t in _prefixed(track):
                restore_track(a, t, one, groups, self._row_fields, prefix)
            return it, tree_from(a, "trainable", trainable, finite=True), tree_from(a, "opt_state", opt_state), a

        return checked_state(self.what, self.path, restore)


def _prefixed(track) -> list:
    """``[(prefix, track)]``: one track at the top, a list of them one per budget (``budget{b}/``)."""
    return [(f"budget{b}/", t) for b, t in enumerate(track)] if isinstance(track, list) else [("", track)]


def track_arrays(track, row_fields, prefix: str = "") -> dict:
    """The arrays of a `jaxsleigh.tuning.optimizer.CandidateTrack` under ``prefix``: its counters and multiplier, the
    best and every valid candidate, the history rows (``row_fields``) and the probe set."""
    p = prefix
    arrays = {f"{p}scalar/rejections": np.float64(track.rejections), f"{p}scalar/n_accepted": np.float64(
        track.n_accepted), f"{p}scalar/multiplier": np.float64(track.lam)}
    if track.best is not None:
        arrays.update({f"{p}best/value": np.float64(track.best[0]), f"{p}best/it": np.int64(track.best[1]),
                       **tree_arrays(f"{p}best/trainable", track.best[2])})
    arrays[f"{p}valid/value"] = np.asarray([v for v, _, _ in track.valid_points], np.float64)
    arrays[f"{p}valid/it"] = np.asarray([i for _, i, _ in track.valid_points], np.int64)
    for j, (_, _, tr) in enumerate(track.valid_points):
        arrays.update(tree_arrays(f"{p}valid/{j}", tr))
    for f in row_fields:
        arrays[f"{p}rows/{f}"] = np.asarray([r[f] for r in track.rows])
    for j, (pstarts, _) in enumerate(track.probes or ()):
        arrays[f"{p}probes/{j}"] = np.asarray(pstarts)
    return arrays


def restore_track(a: dict, track, trainable, groups, row_fields, prefix: str = "") -> None:
    """Set ``track`` to the state `track_arrays` wrote under ``prefix`` (candidates shaped like ``trainable``; the
    probe sets' plants from ``groups``)."""
    p = prefix
    track.best = None
    if f"{p}best/value" in a:
        track.best = (float(a[f"{p}best/value"]), int(a[f"{p}best/it"]),
                      tree_from(a, f"{p}best/trainable", trainable, finite=True))
    track.valid_points = [(float(v), int(i), tree_from(a, f"{p}valid/{j}", trainable, finite=True))
                          for j, (v, i) in enumerate(zip(a[f"{p}valid/value"], a[f"{p}valid/it"]))]
    n_rows = len(a[f"{p}rows/{row_fields[0]}"])
    track.rows = [{f: _scalar(a[f"{p}rows/{f}"][r]) for f in row_fields} for r in range(n_rows)]
    track.probes = None
    if f"{p}probes/0" in a:
        track.probes = [(a[f"{p}probes/{j}"], groups[j][2]) for j in range(len(groups)) if f"{p}probes/{j}" in a]
    track.rejections, track.n_accepted = int(a[f"{p}scalar/rejections"]), int(a[f"{p}scalar/n_accepted"])
    track.lam = float(a[f"{p}scalar/multiplier"])


def _scalar(x):
    x = np.asarray(x)
    if x.ndim:
        return x
    if x.dtype == bool:
        return bool(x)
    return x.item()


def checkpoint_options(path) -> dict | None:
    """The options (``{flag: value}``) a checkpoint was written with, as its writer passed them (``options=``);
    ``None`` for a file without them or one that cannot be read (its loader then says what is wrong)."""
    return Checkpoint.options_of(path)


def law_settings(law, names, plant, loss, lr, x64, n_attempts) -> dict:
    """Everything that determines a `jaxsleigh.tuning.tune_law` run but its training starts (`Checkpoint.of_run` adds those)
    and its number of steps (a resumed run may go on for more), as JSON."""
    leaves = {n: np.asarray(v, np.float64).tolist() for n, v in law_leaf_names(law).items()}
    return {"law": str(jax.tree_util.tree_structure(law)), "leaves": leaves, "tuned": list(names),
            "plant": plant_to_dict(plant), "loss": loss_record(loss), "lr": float(lr),
            "x64": bool(x64), "n_attempts": int(n_attempts)}


class LawCheckpoint:
    """The state of `jaxsleigh.tuning.tune_law`'s Adam descent in one ``.npz``, written atomically after every
    step: the next step, the parameters and optimiser state, the best valid candidate, the history and whether
    the descent stopped (at an invalid candidate)."""

    def __init__(self, path, stamp: Checkpoint):
        self.path, self.stamp, self.what = Path(path), stamp, "tuner checkpoint"

    def save(self, it: int, params, opt_state, best, hist: dict, stopped: bool) -> None:
        arrays = {"it": np.int64(it), "stopped": np.bool_(stopped), "params": np.asarray(params),
                  **tree_arrays("opt_state", opt_state)}
        if best is not None:
            arrays.update({"best/params": np.asarray(best[0]), "best/loss": np.float64(best[1]),
                           "best/energy": np.float64(best[2])})
        for k, v in hist.items():
            arrays[f"hist/{k}"] = np.asarray(v, bool if k == "valid" else np.float64)
        self.stamp.write(self.path, arrays)

    def load(self, params, opt_state):
        """``(it, params, opt_state, best, hist, stopped)`` shaped like ``params`` / ``opt_state``; ``None`` if there is
        no file. Refuses a damaged file or one written with other settings (naming what differs), and one whose
        parameters are not finite or of the run's shape, or whose counter ``it`` is not 0 to the steps its history
        records (`jaxsleigh.errors.DamagedFileError`, naming it)."""
        a = self.stamp.read(self.path)
        if a is None:
            return None
        dtype, shape = jnp.asarray(params).dtype, np.shape(params)

        def vector(name):
            x = np.asarray(a[name])
            if x.dtype.kind not in "biuf" or x.shape != shape:
                raise _Content(f"its field {name!r} is {x.dtype} of shape {x.shape}, the run's parameters {shape}")
            _finite(repr(name), x)
            return jnp.asarray(x, dtype)

        def restore():
            hist = {k.split("/", 1)[1]: [_scalar(x) for x in v] for k, v in a.items() if k.startswith("hist/")}
            it = check_counter(a, "it", len(hist.get("loss", ())), "the steps its history records")
            best = None
            if "best/params" in a:
                best = (vector("best/params"), float(a["best/loss"]), float(a["best/energy"]))
            return it, vector("params"), tree_from(a, "opt_state", opt_state), best, hist, bool(a["stopped"])

        return checked_state(self.what, self.path, restore)
