"""Chunk checkpoints of long runs: nothing lost when a run is interrupted, nothing mixed on resume.

A `ChunkStore` is a folder of ``chunk_NNNNNN.npz`` files plus a ``manifest.json`` (and, while a chunk's stragglers
still run in a pool shared by many chunks, its work in progress ``pending_NNNNNN.npz``: the states its parts ended
with, from which a killed run resumes with the same bits). Every
chunk carries the fingerprint of the run that wrote it (a hash of the settings and of *all* the
starts) and its own identity (its index, its rows ``[lo, hi)`` and a digest of the starts of those
rows), and is checked on reuse whether or not the manifest exists:

* a chunk of another run (other settings, seed, starts or chunk size) stops the run with a
  `CheckpointError` naming the file and the fix: results are never mixed;
* a chunk under another chunk's name (renamed, copied over another, written with other chunk
  bounds) or a chunk of the earlier format that does not record its index is named in a
  `DamagedCheckpointWarning` and recomputed, as is a damaged one (empty, truncated, corrupt,
  wrong length);
* a chunk's content is checked before it is used: its content digest (``__digest__``, the SHA-256 of every array's
  name, dtype, shape and bytes, `jaxsleigh.files.npz.content_digest`) must match, so a chunk edited by hand (values,
  dtypes, a field replaced by text) or damaged in place is caught, and a chunk that records no digest (jaxsleigh 0.3
  and earlier) is not trusted; its fields must be the run's, with its rows, holding numbers, known status codes of a
  whole-number dtype, ``T_eps`` real (>= 0, inf or NaN) and counts >= 0 (`jaxsleigh.files.npz.value_problem`). A chunk
  that fails is named in a `DamagedCheckpointWarning` and recomputed, never used: recomputing costs one chunk's
  time and gives the bytes of an uninterrupted run, where refusing would stop a long run for a file it can remake;
* a manifest of another run is refused with the settings that differ, by name, with both values;
* while a run works, the folder is locked (`jaxsleigh.files.runlock.RunLock`; by the lock of the run's output,
  which covers its chunk folder, or, for a store used on its own, by a lock in the folder): a second run with other
  settings is refused at once, naming the first;
* files are written atomically (temporary file, fsync, rename): a kill leaves either the complete
  chunk or none, and leftover temporary files are hidden names that are never read as chunks.
"""
from __future__ import annotations

import hashlib
import json
import warnings
import zipfile
from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import CheckpointError, DamagedCheckpointWarning, DamagedFileError
from ..status import Status
from .checkpoint import MANIFEST, Checkpoint, differences, joined, record, recorded
from .npz import value_problem
from .run import Words, refuse_progress
from .runlock import RunLock
from ..validate import writable_dir

__all__ = ["ChunkStore", "starts_digest"]

#: the fingerprint in every checkpoint file's header (`jaxsleigh.files.checkpoint.Checkpoint`); a chunk's also holds
#: ``__chunk__`` (its index and rows ``[index, lo, hi]``) and ``__starts__`` (the digest of the starts of those rows)
_KEY = "__run_key__"

#: Settings that vary between equal runs (never a reason to refuse a checkpoint).
_VOLATILE = {"devices", "wall_s", "chunks_reused"}


def starts_digest(starts) -> str:
    """A short hash of an array of starts (its dtype, shape and bytes)."""
    a = np.ascontiguousarray(starts)
    h = hashlib.sha256(f"{a.dtype.str}{a.shape}".encode())
    h.update(a.tobytes())
    return h.hexdigest()[:32]


#: how a chunk store used on its own names resume (from Python or the command line)
_STORE_WORDS = Words(resume="resume=True (--resume)")


def _afresh(folder: Path) -> str:
    return (f"delete or move {str(folder)!r} (or choose another --out / checkpoint folder) to start afresh")


class ChunkStore:
    """Chunks of one run in ``folder``, identified by the run's fingerprint ``key``."""

    def __init__(self, folder, key: str):
        self.folder = Path(folder)
        self.key = str(key)
        self._lock = None

    @property
    def manifest(self) -> Path:
        return self.folder / MANIFEST

    def path(self, index: int) -> Path:
        return self.folder / f"chunk_{index:06d}.npz"

    def chunks(self) -> list[Path]:
        """The finished chunk files (temporary files are never listed)."""
        return sorted(self.folder.glob("chunk_*.npz"))

    def open(self, *, resume: bool, manifest: dict) -> None:
        """Create the folder, lock it and write the manifest; refuse a folder that holds another
        run's work or that another run is writing.

        Without ``resume`` a folder that already holds chunks is refused (they would be
        overwritten); with it, a manifest of another run is refused (naming the settings that
        differ), a damaged manifest is replaced (the chunks identify themselves). The folder stays
        locked (`jaxsleigh.files.runlock.RunLock`) until `close`: by the lock of the run that owns an output and
        covers this folder (`RunLock.over`, one lock per run), else by a lock of its own.
        """
        writable_dir(self.folder, what="checkpoint folder")
        covered = RunLock.over(self.folder)
        self._lock = covered or RunLock(self.folder, self.key, folder=True, what="checkpoint folder",
                                        hint="choose another --out / checkpoint folder").acquire()
        try:
            self._check(resume, manifest, decided=covered is not None)
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        """Release the folder's lock (the chunks stay). Safe to call twice."""
        lock, self._lock = self._lock, None
        if lock is not None:
            lock.release()

    def __enter__(self) -> "ChunkStore":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _check(self, resume: bool, manifest: dict, decided: bool = False) -> None:
        have = self.chunks() + sorted(self.folder.glob("pending_*.npz"))
        if not decided:            # a run that covers the folder decided it when it claimed its output
            refuse_progress(f"checkpoint {str(self.folder)!r} already holds {len(have)} chunk(s) of an earlier run"
                            if have else None, resume=resume, words=_STORE_WORDS, error=CheckpointError,
                            afresh=f"delete or move {str(self.folder)!r} (or choose another --out / checkpoint folder)")
        new = {"key": self.key, **manifest}
        old = recorded(self.folder) if resume and self.manifest.exists() else {}
        if old is None:
            warnings.warn(DamagedCheckpointWarning(
                f"checkpoint manifest {str(self.manifest)!r} is damaged; it is rewritten and every chunk is checked "
                "on its own"), stacklevel=4)
        elif "key" in old and old["key"] != self.key:     # a record without a key: the runner's options only
            why = _differences(old, json.loads(json.dumps(new, default=str)))
            raise CheckpointError(f"checkpoint {str(self.folder)!r} was made with other settings or initial "
                                  f"conditions than this run"
                                  + ("" if why.startswith("other settings") else f" ({why})")
                                  + f"; rerun the original command with --resume, or {_afresh(self.folder)}")
        if resume:
            for path in have:                 # before anything is written: never adopt another run's folder
                key = self._key_of(path)
                if key is not None and key != self.key:
                    raise self._foreign(path)
        record(self.folder, new, when_full=self._when_full())

    def _when_full(self) -> str:
        return (f"the finished chunks are kept in {str(self.folder)!r}: once there is space, the same command "
                f"with --resume (resume=True) continues")

    @staticmethod
    def _key_of(path: Path) -> Optional[str]:
        """The fingerprint stored in a chunk ('' for a chunk without one), ``None`` if unreadable."""
        try:
            with np.load(path, allow_pickle=False) as z:
                return str(z[_KEY]) if _KEY in z.files else ""
        except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError):
            return None

    def _foreign(self, path: Path) -> CheckpointError:
        return CheckpointError(
            f"checkpoint chunk {str(path)!r} was written by a different run (other settings, seed, starts or "
            f"chunk size, or jaxsleigh 0.1, whose chunks carry no fingerprint); results of two runs are never "
            f"mixed: rerun the command that made it with --resume, or {_afresh(self.folder)}")

    def save(self, index: int, arrays: dict, *, lo: int, starts) -> Path:
        """Write chunk ``index`` atomically, tagged with the run's fingerprint and its identity: its
        index, its rows ``[lo, lo + len(starts))`` and the digest of their ``starts``."""
        return self._write(self.path(index), index, arrays, lo, starts)

    def load(self, index: int, rows: int, fields=None, *, lo: int, starts, codes=tuple(Status)) -> Optional[dict]:
        """Chunk ``index`` if it exists, belongs to this run and is this very chunk (index, rows
        ``[lo, lo + rows)``, digest of ``starts``) with ``rows`` rows, its content digest verified and its values
        those a run writes (`jaxsleigh.files.npz.value_problem`; ``codes``: the status codes its ``status`` may
        hold); ``None`` if it is missing, damaged, edited or another chunk under this one's name (then it is
        recomputed, with a `DamagedCheckpointWarning`); `CheckpointError` if another run wrote it. ``fields``: the
        names the chunk must hold (all of them, no others)."""
        path = self.path(index)
        data = self._read(path, index, rows, lo, starts)
        if data is None:
            return None
        if fields is not None and set(data) != set(fields):
            self._damaged(path, f"holds fields {sorted(data)}, expected {sorted(fields)}")
            return None
        if not data or any(np.ndim(v) < 1 or np.shape(v)[0] != rows for v in data.values()):
            self._damaged(path, f"expected {rows} rows per field")
            return None
        why = value_problem(data, codes)
        if why:
            self._damaged(path, why)
            return None
        return data

    def pending_path(self, index: int) -> Path:
        return self.folder / f"pending_{index:06d}.npz"

    def save_pending(self, index: int, arrays: dict, *, lo: int, starts) -> Path:
        """Write chunk ``index``'s work in progress (its parts' states, whose stragglers are still running elsewhere)
        atomically, tagged as `save` tags a chunk: a run killed before the chunk ends resumes from it."""
        return self._write(self.pending_path(index), index, arrays, lo, starts)

    def load_pending(self, index: int, rows: int, *, lo: int, starts) -> Optional[dict]:
        """Chunk ``index``'s work in progress (`save_pending`) if it is there, of this run and of this chunk; ``None``
        otherwise (a damaged one is named in a `DamagedCheckpointWarning` and the chunk recomputed)."""
        return self._read(self.pending_path(index), index, rows, lo, starts)

    def _write(self, path: Path, index: int, arrays: dict, lo: int, starts) -> Path:
        return Checkpoint(self.key).write(path, arrays, when_full=self._when_full(),
                                          chunk=np.array([index, lo, lo + len(starts)], np.int64),
                                          starts=starts_digest(starts))

    def _read(self, path: Path, index: int, rows: int, lo: int, starts) -> Optional[dict]:
        """The arrays of ``path`` if it is there, of this run, and chunk ``index``'s (rows ``[lo, lo + rows)`` of
        ``starts``); ``None`` (with a `DamagedCheckpointWarning` saying why) if it is missing, damaged or another
        chunk's; `CheckpointError` if another run wrote it."""
        if not path.exists():
            return None
        try:
            data, head = Checkpoint.read_file(path)
        except DamagedFileError as e:
            self._damaged(path, e.problem)
            return None
        except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError) as e:
            self._damaged(path, f"{type(e).__name__}: {e}" if str(e) else type(e).__name__)
            return None
        key, ident, digest = head.get("run_key"), head.get("chunk"), head.get("starts")
        if key is None or str(key) != self.key:
            raise self._foreign(path)
        if ident is None or digest is None:
            self._damaged(path, "it was written by an earlier jaxsleigh that does not record which chunk it is, "
                                "so it cannot be trusted under this name")
            return None
        got = np.asarray(ident).ravel().tolist()
        if got != [index, lo, lo + rows]:
            what = (f"chunk {got[0]} (rows {got[1]}-{got[2] - 1})" if len(got) == 3 else f"identity {got}")
            self._damaged(path, f"it holds {what}, not chunk {index} (rows {lo}-{lo + rows - 1}): it was renamed, "
                                f"copied over another chunk or written with other chunk bounds")
            return None
        if str(digest) != starts_digest(starts):
            self._damaged(path, f"its rows {lo}-{lo + rows - 1} were computed from other starts")
            return None
        if "digest" not in head:
            self._damaged(path, "it records no content digest (written by jaxsleigh 0.3 or earlier, or rewritten by "
                                "hand), so what it holds cannot be checked")
            return None
        return data

    def drop_pending(self, index: int) -> None:
        """Remove chunk ``index``'s work in progress (once the chunk itself is written)."""
        try:
            self.pending_path(index).unlink()
        except FileNotFoundError:
            pass

    @staticmethod
    def _damaged(path: Path, why: str) -> None:
        warnings.warn(DamagedCheckpointWarning(
            f"checkpoint chunk {str(path)!r} is damaged ({why}); recomputing it"), stacklevel=4)


def _differences(old, new: dict, limit: int = 6) -> str:
    """The settings in which two manifests differ, by name with both values (checkpoint vs this run)."""
    if not isinstance(old, dict):
        return "its manifest is not a run's manifest"
    diffs = []
    o_set, n_set = old.get("settings"), new.get("settings")
    if isinstance(o_set, dict) and isinstance(n_set, dict):
        for k in sorted(set(o_set) | set(n_set)):
            if k in _VOLATILE or o_set.get(k) == n_set.get(k):
                continue
            diffs.extend(differences(o_set.get(k, "(unset)"), n_set.get(k, "(unset)"), k))
    if old.get("n") != new.get("n"):
        diffs.append(f"{old.get('n')} starts in the checkpoint vs {new.get('n')} now")
    elif "starts" in old and old.get("starts") != new.get("starts"):
        diffs.append("other initial conditions (e.g. another --seed, grid or --ics file)")
    if old.get("chunk") != new.get("chunk") and not any(d.startswith("chunk_size") for d in diffs):
        diffs.append(f"chunks of {old.get('chunk')} rows in the checkpoint vs {new.get('chunk')} now")
    return joined(diffs, limit) if diffs else "other settings or initial conditions"
