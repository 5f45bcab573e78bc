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
* while a run works, it holds a lock in the folder (`jaxsleigh.files.runlock.RunLock`): a second run
  with other settings is refused at once, naming the first;
* files are written atomically (temporary file, fsync, rename): a kill leaves either the complete
  chunk or none, and leftover temporary files are hidden names that are never read as chunks.
"""
from __future__ import annotations

import hashlib
import io
import json
import warnings
import zipfile
from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import CheckpointError, DamagedCheckpointWarning, DamagedFileError
from ..status import Status
from .npz import DIGEST_KEY, atomic_write_text, check_digest, value_problem, write_npz_deterministic
from .runlock import RunLock
from ..validate import writable_dir

__all__ = ["ChunkStore", "write_checkpoint", "read_checkpoint_file", "run_key", "starts_digest", "setting_differences",
           "joined"]

#: the fingerprint in every checkpoint file's header (`write_checkpoint`); a chunk's also holds ``__chunk__`` (its
#: index and rows ``[index, lo, hi]``) and ``__starts__`` (the digest of the starts of those rows)
_KEY = "__run_key__"

#: Settings that vary between equal runs (never a reason to refuse a checkpoint).
_VOLATILE = {"devices", "wall_s", "chunks_reused"}


def write_checkpoint(path, arrays: dict, *, key: str, when_full: str = "", **header) -> Path:
    """One checkpoint file, the layout of every resumable run's (the chunk store's chunks and work in progress, every
    tuner's state): ``arrays`` next to a header, the run's fingerprint ``key`` and the ``header`` entries given
    (``chunk``, ``starts``, ``settings``, ``options``; ``None`` left out), stored as ``__key__``-style names;
    uncompressed, with fixed timestamps (equal state, equal bytes), written atomically (``when_full``: what continues
    the work once a full disk has space); last, the content digest of all of it (``__digest__``,
    `jaxsleigh.files.npz.content_digest`), which `read_checkpoint_file` verifies."""
    head = {f"__{k}__": np.asarray(v) for k, v in header.items() if v is not None}
    return write_npz_deterministic(path, {**arrays, _KEY: np.array(key), **head}, compress=False, when_full=when_full)


def read_checkpoint_file(path) -> tuple:
    """``(arrays, header)`` of a checkpoint file (`write_checkpoint`), the header by name (``run_key``, ``chunk``,
    ``starts``, ``settings``, ``options`` and ``digest``, the content digest verified; no ``digest`` for a file that
    records none, written by jaxsleigh 0.3 or earlier); raises what `numpy.load` raises for a damaged file and a
    `jaxsleigh.errors.DamagedFileError` naming it when its contents do not match its digest (edited or damaged after
    it was written)."""
    with np.load(io.BytesIO(Path(path).read_bytes()), allow_pickle=False) as z:
        data = {k: z[k] for k in z.files}
    digest = data.get(DIGEST_KEY)
    if not check_digest(path, data, "delete it and start afresh (without --resume)"):
        digest = None
    data.pop("format_version", None)
    if digest is not None:
        data[DIGEST_KEY] = digest
    return data, {k[2:-2]: data.pop(k) for k in list(data) if k.startswith("__") and k.endswith("__")}


def starts_digest(starts) -> str:
    """A short hash of an array of starts (its dtype, shape and bytes)."""
    a = np.ascontiguousarray(starts)
    h = hashlib.sha256(f"{a.dtype.str}{a.shape}".encode())
    h.update(a.tobytes())
    return h.hexdigest()[:32]


def run_key(settings: dict, starts) -> str:
    """The fingerprint of a resumable run: a SHA-256 of ``settings`` (as sorted JSON, values that JSON cannot
    write as their ``str``) followed by the starts' bytes, as given (cast them first to key on a dtype)."""
    h = hashlib.sha256(json.dumps(settings, sort_keys=True, default=str).encode())
    h.update(np.ascontiguousarray(starts).tobytes())
    return h.hexdigest()


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
        return self.folder / "manifest.json"

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
        locked (`jaxsleigh.files.runlock.RunLock`) until `close`.
        """
        writable_dir(self.folder, what="checkpoint folder")
        self._lock = RunLock(self.folder, self.key, folder=True, what="checkpoint folder",
                             hint="choose another --out / checkpoint folder").acquire()
        try:
            self._check(resume, manifest)
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

    def _check(self, resume: bool, manifest: dict) -> None:
        have = self.chunks() + sorted(self.folder.glob("pending_*.npz"))
        if have and not resume:
            raise CheckpointError(f"checkpoint {str(self.folder)!r} already holds {len(have)} chunk(s) of an "
                                  f"earlier run; pass resume=True (--resume) with the same settings to continue "
                                  f"it, or {_afresh(self.folder)}")
        new = {"key": self.key, **manifest}
        if resume and self.manifest.exists():
            try:
                old = json.loads(self.manifest.read_text())
                old_key = old.get("key") if isinstance(old, dict) else None
            except (json.JSONDecodeError, UnicodeDecodeError, OSError) as e:
                warnings.warn(DamagedCheckpointWarning(
                    f"checkpoint manifest {str(self.manifest)!r} is damaged ({e}); it is rewritten and every "
                    "chunk is checked on its own"), stacklevel=4)
                old, old_key = None, self.key
            if old_key != self.key:
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
        atomic_write_text(self.manifest, json.dumps(new, indent=1, default=str) + "\n", when_full=self._when_full())

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
        return write_checkpoint(path, arrays, key=self.key, when_full=self._when_full(),
                                chunk=np.array([index, lo, lo + len(starts)], np.int64), starts=starts_digest(starts))

    def _read(self, path: Path, index: int, rows: int, lo: int, starts) -> Optional[dict]:
        """The arrays of ``path`` if it is there, of this run, and chunk ``index``'s (rows ``[lo, lo + rows)`` of
        ``starts``); ``None`` (with a `DamagedCheckpointWarning` saying why) if it is missing, damaged or another
        chunk's; `CheckpointError` if another run wrote it."""
        if not path.exists():
            return None
        try:
            data, head = read_checkpoint_file(path)
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


def _leaves(value, prefix: str = "") -> dict:
    """``{path: value}`` of the numbers and texts in nested dicts (a controller's record: its type and params)."""
    if not isinstance(value, dict):
        return {prefix: value}
    out = {}
    for k, v in value.items():
        key = str(k) if k != "params" else ""
        out.update(_leaves(v, f"{prefix}.{key}".strip(".").replace("..", ".") if key else prefix))
    return out


def setting_differences(name: str, old, new, *, said: Optional[dict] = None) -> list:
    """``['controller.u_max 2.0 in the checkpoint vs 3.0 now']``: how a setting of a checkpoint differs from this run's,
    leaf by leaf when it is a record (never a whole dict); ``said`` gives the words for a leaf whose values mean
    nothing to a reader (``{"ics": "other initial conditions"}``). Every resumable run refuses in these words."""
    if not (isinstance(old, dict) and isinstance(new, dict)):
        return [f"{name} {old!r} in the checkpoint vs {new!r} now"]
    a, b = _leaves(old), _leaves(new)
    out = []
    for k in sorted(set(a) | set(b), key=str):
        if a.get(k) != b.get(k):
            label = ".".join(part for part in (name, str(k).lstrip(".")) if part)
            out.append((said or {}).get(k) or f"{label} {a.get(k, '(unset)')!r} in the checkpoint vs "
                                              f"{b.get(k, '(unset)')!r} now")
    return out


def joined(diffs: list, limit: int = 6) -> str:
    """The first ``limit`` differences, and how many more."""
    more = f" and {len(diffs) - limit} more" if len(diffs) > limit else ""
    return "; ".join(diffs[:limit]) + more


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
            diffs.extend(setting_differences(k, o_set.get(k, "(unset)"), n_set.get(k, "(unset)")))
    if old.get("n") != new.get("n"):
        diffs.append(f"{old.get('n')} starts in the checkpoint vs {new.get('n')} now")
    elif "starts" in old and old.get("starts") != new.get("starts"):
        diffs.append("other initial conditions (e.g. another --seed, grid or --ics file)")
    if old.get("chunk") != new.get("chunk") and not any(d.startswith("chunk_size") for d in diffs):
        diffs.append(f"chunks of {old.get('chunk')} rows in the checkpoint vs {new.get('chunk')} now")
    return joined(diffs, limit) if diffs else "other settings or initial conditions"
