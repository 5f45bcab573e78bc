"""Chunk checkpoints of long runs: nothing lost when a run is interrupted, nothing mixed on resume.

A `ChunkStore` is a folder of ``chunk_NNNNNN.npz`` files plus a ``manifest.json``. Every
chunk carries the fingerprint of the run that wrote it (a hash of the settings and of *all* the
starts) and is checked on reuse whether or not the manifest exists:

* a chunk of another run (other settings, seed, starts or chunk size) stops the run with a
  `CheckpointError` naming the file and the fix: results are never mixed;
* a damaged chunk (empty, truncated, corrupt, wrong length) is named in a
  `DamagedCheckpointWarning` and recomputed;
* files are written atomically (temporary file, fsync, rename): a kill leaves either the complete
  chunk or none, and leftover temporary files are hidden names that are never read as chunks.
"""
from __future__ import annotations

import io
import json
import warnings
import zipfile
from pathlib import Path
from typing import Optional

import numpy as np

from .errors import CheckpointError, DamagedCheckpointWarning
from .io import atomic_write, atomic_write_text

__all__ = ["ChunkStore"]

_KEY = "__run_key__"


class ChunkStore:
    """Chunks of one run in ``folder``, identified by the run's fingerprint ``key``."""

    def __init__(self, folder, key: str):
        self.folder = Path(folder)
        self.key = str(key)

    @property
    def manifest(self) -> Path:
        return self.folder / "manifest.json"

    def path(self, index: int) -> Path:
        return self.folder / f"chunk_{index:06d}.npz"

    def chunks(self) -> list[Path]:
        """The finished chunk files (temporary files are never listed)."""
        return sorted(self.folder.glob("chunk_*.npz"))

    def open(self, *, resume: bool, manifest: dict) -> None:
        """Create the folder and write the manifest; refuse a folder that holds another run's work.

        Without ``resume`` a folder that already holds chunks is refused (they would be
        overwritten); with it, a manifest of another run is refused, a damaged manifest is
        replaced (the chunks identify themselves).
        """
        from .validate import writable_dir

        writable_dir(self.folder, what="checkpoint folder")
        have = self.chunks()
        if have and not resume:
            raise CheckpointError(f"checkpoint {str(self.folder)!r} already holds {len(have)} chunk(s) of an "
                                  "earlier run; pass resume=True (--resume) to continue it, or delete that "
                                  "folder to start afresh")
        if resume and self.manifest.exists():
            try:
                old = json.loads(self.manifest.read_text())
                old_key = old.get("key") if isinstance(old, dict) else None
            except (json.JSONDecodeError, UnicodeDecodeError, OSError) as e:
                warnings.warn(DamagedCheckpointWarning(
                    f"checkpoint manifest {str(self.manifest)!r} is damaged ({e}); it is rewritten and every "
                    "chunk is checked on its own"), stacklevel=3)
                old_key = self.key
            if old_key != self.key:
                raise CheckpointError(f"checkpoint {str(self.folder)!r} was made with other settings or initial "
                                      "conditions than this run; rerun the original command with --resume, or "
                                      "delete that folder (or drop --resume) to start afresh")
        if resume:
            for path in have:                 # before anything is written: never adopt another run's folder
                key = self._key_of(path)
                if key is not None and key != self.key:
                    raise self._foreign(path)
        atomic_write_text(self.manifest, json.dumps({"key": self.key, **manifest}, indent=1, default=str) + "\n")

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
            f"mixed: rerun the command that made it with --resume, or delete {str(self.folder)!r} to start afresh")

    def save(self, index: int, arrays: dict) -> Path:
        """Write chunk ``index`` atomically, tagged with the run's fingerprint."""
        def write(f):
            np.savez(f, **arrays, **{_KEY: np.array(self.key)})

        return atomic_write(self.path(index), write)

    def load(self, index: int, rows: int, fields=None) -> Optional[dict]:
        """Chunk ``index`` if it exists, belongs to this run and holds ``rows`` rows; ``None`` if it
        is missing or damaged (then it is recomputed); `CheckpointError` if another run
        wrote it. ``fields``: the names the chunk must hold (all of them, no others)."""
        path = self.path(index)
        if not path.exists():
            return None
        try:
            raw = path.read_bytes()
            with np.load(io.BytesIO(raw), allow_pickle=False) as z:
                data = {k: z[k] for k in z.files}
        except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError) as e:
            self._damaged(path, f"{type(e).__name__}: {e}" if str(e) else type(e).__name__)
            return None
        key = data.pop(_KEY, None)
        if key is None or str(key) != self.key:
            raise self._foreign(path)
        if fields is not None and set(data) != set(fields):
            self._damaged(path, f"holds fields {sorted(data)}, expected {sorted(fields)}")
            return None
        if not data or any(np.ndim(v) < 1 or np.shape(v)[0] != rows for v in data.values()):
            self._damaged(path, f"expected {rows} rows per field")
            return None
        return data

    @staticmethod
    def _damaged(path: Path, why: str) -> None:
        warnings.warn(DamagedCheckpointWarning(
            f"checkpoint chunk {str(path)!r} is damaged ({why}); recomputing it"), stacklevel=4)
