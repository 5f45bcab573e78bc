"""What every resumable run keeps on disk, in one place: its checkpoint files, its record and how a resume that does
not match them is told what differs.

* `Checkpoint`: one class writes and reads every checkpoint file, a chunk of a basin, sweep or optimum and the whole
  state of every tuner: the run's arrays next to a header (the run's fingerprint ``key``, the ``settings`` it hashes,
  the command's ``options``, and what the caller adds: a chunk's index and rows), uncompressed with fixed timestamps
  (equal state, equal bytes), written atomically, the content digest last (``__digest__``), verified on reading.
* `record` / `recorded`: a chunk folder's one record file, ``manifest.json``: the chunk store's fields (its key,
  rows, chunk size, settings) and the runner's ``options``, each writer adding its own fields and keeping the
  other's. A folder of jaxsleigh 0.3 recorded the options in ``options.json``; they are read from there.
* `differences`: the one routine that says how a record of a checkpoint differs from this run's, leaf by leaf with
  both values; every refused resume says it in these words.
"""
from __future__ import annotations

import hashlib
import io
import json
import zipfile
from pathlib import Path
from typing import Callable, NamedTuple, Optional

import numpy as np

from ..errors import DamagedFileError
from .npz import DIGEST_KEY, atomic_write_text, check_digest, write_npz_deterministic

__all__ = ["Checkpoint", "run_key", "differences", "joined", "record", "recorded", "refused", "MANIFEST"]

#: the one record file of a chunk folder
MANIFEST = "manifest.json"
#: where jaxsleigh 0.3 recorded a chunk folder's options (read, never written)
_LEGACY_OPTIONS = "options.json"


def run_key(settings, starts=None) -> str:
    """The fingerprint of a resumable run: a SHA-256 of ``settings`` (as sorted JSON, values that JSON cannot write
    as their ``str``) followed by the bytes of ``starts`` as given (cast them first to key on a dtype)."""
    h = hashlib.sha256(json.dumps(settings, sort_keys=True, default=str).encode())
    if starts is not None:
        h.update(np.ascontiguousarray(starts).tobytes())
    return h.hexdigest()


class Checkpoint(NamedTuple):
    """What identifies a resumable run's checkpoint files and writes them: ``key`` (the run's fingerprint),
    ``settings`` (what the key hashes, as JSON: a refused resume names what differs) and ``options`` (the command's,
    if given, so that a refusal can name a flag)."""

    key: str
    settings: Optional[dict] = None
    options: Optional[dict] = None

    @classmethod
    def of(cls, key: str, settings: Optional[dict], options: Optional[dict] = None) -> "Checkpoint":
        """The settings as JSON reads them back (tuples become lists), so that a refusal compares like with like."""
        return cls(str(key), json.loads(json.dumps(settings or {}, sort_keys=True, default=str)), options)

    @classmethod
    def of_run(cls, settings: dict, ics, options: Optional[dict] = None) -> "Checkpoint":
        """The checkpoint of a run of ``settings`` on the starts ``ics``: the key a SHA-256 of the settings (as sorted
        JSON) and the starts' float64 bytes; the settings recorded with a digest of the starts (``ics``), so that a
        refusal says "other initial conditions"."""
        a = np.ascontiguousarray(ics, np.float64)
        return cls.of(run_key(settings, a), {**settings, "ics": hashlib.sha256(a.tobytes()).hexdigest()[:16]}, options)

    def write(self, path, arrays: dict, *, when_full: str = "", **header) -> Path:
        """``arrays`` and the header (the key, the settings and options where known, and ``header``'s entries, e.g. a
        chunk's ``chunk`` and ``starts``; ``None`` left out) as ``__name__`` arrays, atomically, deterministic bytes
        (``when_full``: what continues the work once a full disk has space)."""
        head = {"run_key": self.key, "settings": None if self.settings is None else json.dumps(self.settings, sort_keys=True),
                "options": None if self.options is None else json.dumps(self.options, sort_keys=True, default=str),
                **header}
        named = {f"__{k}__": np.asarray(v) for k, v in head.items() if v is not None}
        return write_npz_deterministic(Path(path), {**arrays, **named}, compress=False, when_full=when_full)

    @staticmethod
    def read_file(path) -> tuple:
        """``(arrays, header)`` of a checkpoint file, the header by name (``run_key``, ``chunk``, ``starts``,
        ``settings``, ``options`` and ``digest``, the content digest verified; no ``digest`` for a file that records
        none, written by jaxsleigh 0.3 or earlier); raises what `numpy.load` raises for a damaged file and a
        `jaxsleigh.errors.DamagedFileError` naming it when its contents do not match its digest."""
        with np.load(io.BytesIO(Path(path).read_bytes()), allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
        digest = data.get(DIGEST_KEY)
        if not check_digest(path, data, "delete it and start afresh (without --resume)"):
            digest = None
        data.pop("format_version", None)
        if digest is not None:
            data[DIGEST_KEY] = digest
        return data, {k[2:-2]: data.pop(k) for k in list(data) if k.startswith("__") and k.endswith("__")}

    def read(self, path, what: str = "checkpoint") -> Optional[dict]:
        """The arrays of the checkpoint file ``path`` (``what`` names it in a refusal), ``None`` if there is no file;
        a `refused` error for a file whose contents do not match its digest, a ``ValueError`` for a damaged file or
        one written by a run with other settings than this one's (naming what differs). A file of the earlier layout
        (``key``, ``settings``, ``options`` among the arrays) is read the same way."""
        path = Path(path)
        if not path.exists():
            return None
        try:
            a, head = self.read_file(path)
        except DamagedFileError as e:
            raise refused(what, path, e.problem) from None
        except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError) as e:
            raise ValueError(f"{what} {str(path)!r} is damaged ({type(e).__name__}: {e}); delete it "
                             "and start afresh (without --resume)") from None
        if not head:
            head = {"run_key" if k == "key" else k: a.pop(k) for k in ("key", "settings", "options") if k in a}
        if str(head.get("run_key")) != self.key:
            try:
                old = json.loads(str(head["settings"])) if "settings" in head else {}
            except ValueError:
                old = {}
            # 'config.steps 4 in the checkpoint vs 8 now; ...'; nothing when either side is unknown
            why = joined(differences(old, self.settings, said={"ics": "other initial conditions"})
                         ) if old and self.settings else ""
            raise ValueError(f"{what} {str(path)!r} was written by a run with other settings"
                             + (f" ({why})" if why else "") + "; rerun that command with --resume, or delete "
                             "or move the checkpoint (or choose another --out) to start afresh")
        return a

    @classmethod
    def options_of(cls, path) -> Optional[dict]:
        """The options (``{name: value}``) the checkpoint file ``path`` was written with; ``None`` for a file without
        them or one that cannot be read (its reader then says what is wrong)."""
        try:
            a, head = cls.read_file(path)
            text = head.get("options", a.get("options"))
            doc = None if text is None else json.loads(str(text))
        except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError):
            return None
        return doc if isinstance(doc, dict) else None


def refused(what: str, path, problem: str) -> DamagedFileError:
    """The `DamagedFileError` of a checkpoint (``what``) at ``path`` that is not what its run wrote: the file,
    ``problem`` and the fix (the state of a tuner is one file: nothing can be recomputed in its place)."""
    return DamagedFileError(f"{what} {str(path)!r} cannot be resumed: {problem}; delete it and start afresh (without "
                            f"--resume)", path=Path(path), problem=problem)


def _leaves(value, prefix: str = "") -> dict:
    """``{path: value}`` of the numbers and texts in nested dicts (a controller's record: its type and params)."""
    if not isinstance(value, dict):
        return {prefix: value}
    out = {}
    for k, v in value.items():
        key = str(k) if k != "params" else ""
        out.update(_leaves(v, f"{prefix}.{key}".strip(".").replace("..", ".") if key else prefix))
    return out


def differences(old, new, name: str = "", *, said: Optional[dict] = None,
                show: Optional[Callable[[str, object], str]] = None, sort: bool = True, flat: bool = False) -> list:
    """``['controller.u_max 2.0 in the checkpoint vs 3.0 now']``: how the record ``old`` of a checkpoint differs from
    this run's ``new``, leaf by leaf when they are records (never a whole dict), under ``name``.

    ``said``: the words for a leaf whose values mean nothing to a reader (``{"ics": "other initial conditions"}``);
    ``show(label, value)``: how a leaf is named with its value on both sides (the command line's flags: ``'--seed 3
    in the checkpoint vs --seed 4 now'``); ``sort``: leaves by name (else in ``new``'s order, then ``old``'s);
    ``flat``: the records' entries compared as they are (an option's value), not leaf by leaf."""
    if not (isinstance(old, dict) and isinstance(new, dict)):
        a, b = {"": old}, {"": new}
    else:
        a, b = (dict(old), dict(new)) if flat else (_leaves(old), _leaves(new))
    keys = list(dict.fromkeys([*b, *a]))
    out = []
    for k in (sorted(keys, key=str) if sort else keys):
        if a.get(k) == b.get(k):
            continue
        label = ".".join(part for part in (name, str(k).lstrip(".")) if part)
        if (said or {}).get(k):
            out.append(said[k])
        elif show is not None:
            out.append(f"{show(label, a.get(k))} in the checkpoint vs {show(label, b.get(k))} now")
        else:
            out.append(f"{label} {a.get(k, '(unset)')!r} in the checkpoint vs {b.get(k, '(unset)')!r} now")
    return out


def joined(diffs: list, limit: int = 6) -> str:
    """The first ``limit`` differences, and how many more."""
    more = f" and {len(diffs) - limit} more" if len(diffs) > limit else ""
    return "; ".join(diffs[:limit]) + more


def recorded(folder) -> Optional[dict]:
    """The record of the chunk folder ``folder`` (``manifest.json``), with the ``options`` of a folder of jaxsleigh
    0.3 (``options.json``) where it records none; ``{}`` without one, ``None`` for one that cannot be read."""
    folder = Path(folder)
    try:
        doc = json.loads((folder / MANIFEST).read_text())
    except FileNotFoundError:
        doc = {}
    except (OSError, ValueError, UnicodeDecodeError):
        return None
    if not isinstance(doc, dict):
        return None
    if "options" not in doc:
        try:
            old = json.loads((folder / _LEGACY_OPTIONS).read_text())
        except (OSError, ValueError, UnicodeDecodeError):
            old = None
        if isinstance(old, dict):
            doc = {**doc, "options": old}
    return doc


def record(folder, fields: dict, *, fresh: bool = False, when_full: str = "") -> None:
    """Write ``fields`` into ``folder``'s record (``manifest.json``), keeping the fields another writer put there
    (``fresh``: none of them; a record that cannot be read is replaced), atomically."""
    folder = Path(folder)
    old = {} if fresh else (recorded(folder) or {})
    atomic_write_text(folder / MANIFEST, json.dumps({**old, **fields}, indent=1, sort_keys=True, default=str) + "\n",
                      when_full=when_full)
    if fresh:
        (folder / _LEGACY_OPTIONS).unlink(missing_ok=True)

