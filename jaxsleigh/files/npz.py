"""Files: the ``.npz`` written by ``jaxsleigh simulate`` and ``jaxsleigh paper`` (a stable contract)."""
from __future__ import annotations

import ast
import errno
import hashlib
import io as _io
import json
import math
import operator
import os
import zipfile
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from ..errors import DamagedFileError, DiskFullError
from ..status import Status, describe
from ..validate import check_memory, host_label, output_file

__all__ = ["write_npz", "npz_path", "damping_name", "parse_number", "load_ics", "atomic_write", "atomic_write_text",
           "settings_arrays", "write_npz_deterministic", "write_result", "read_result", "read_npz", "npz_kind",
           "NPZ_KINDS", "FIELDS", "check_fields", "DIGEST_KEY", "content_digest", "check_digest", "value_problem",
           "damaged"]


def npz_path(path) -> Path:
    """Where a writer puts ``path``: as given when it ends in ``.npz``, else with ``.npz`` appended.
    (Readers do not append to a name with another extension, see `read_npz`.)"""
    p = Path(path)
    return p if p.suffix == ".npz" else p.with_name(p.name + ".npz")


#: The result files jaxsleigh writes: kind -> (keys that only that kind has, what it is, its reader).
NPZ_KINDS = {
    "basin": (("T_eps", "Hd_final", "valid", "converged"), "a basin result",
              "jaxsleigh.load_basin"),
    "sweep": (("values", "names", "status_counts"), "a sweep result", "jaxsleigh.load_sweep"),
    "simulation": (("t", "q", "u", "Hd"), "a simulation (jaxsleigh simulate / paper)",
                   "jaxsleigh.plots.paper_figures.load_solution"),
    "optimum": (("horizons", "frontier", "kkt"), "a bound on the optimum (jaxsleigh optimum)",
                "jaxsleigh.load_optimum"),
}


def npz_kind(keys) -> Optional[str]:
    """Which of `NPZ_KINDS` a result file with these keys is (``None``: none of them)."""
    keys = set(keys)
    for kind, (marks, _, _) in NPZ_KINDS.items():
        if "settings_json" in keys and all(k in keys for k in marks):
            return kind
    return None


#: What varies between two runs of the same command (wall time, devices, chunks reused): recorded in the run's
#: sidecar ``FILE.run.json`` (`jaxsleigh.files.runner.write_sidecar`), never in its result file, whose bytes
#: depend on the command alone.
RUN_VARIES = ("wall_s", "devices", "chunks_reused")


def steady(run_info: Optional[dict]) -> Optional[dict]:
    """A result's ``run_info`` without what varies between runs (`RUN_VARIES`): what a result file may keep of it
    (``None`` when nothing is left)."""
    kept = {k: v for k, v in (run_info or {}).items() if k not in RUN_VARIES}
    return kept or None


def _npz_to_read(path, what: str) -> Path:
    """The file a reader opens: ``path`` itself when it ends in ``.npz`` or exists; ``path + '.npz'``
    when that exists or ``path`` has no extension (the writers append it); else a ``ValueError``.
    A name with another extension (``run.json``) never becomes ``run.json.npz`` in a message."""
    p = Path(path)
    if p.suffix == ".npz" or p.exists():
        return p
    alt = p.with_name(p.name + ".npz")
    if alt.is_file() or not p.suffix:
        return alt
    raise ValueError(f"{str(path)!r} not found; the path must be a .npz written by jaxsleigh: give the {what}")


def write_npz(path, sol, *, ics, command: Optional[Sequence[str]] = None) -> Path:
    """Write a `Solution` and the settings that produced it.

    Keys: ``t (T,)``, ``q (N, T, 3)``, ``p (N, T, 2)``, ``u (N, T, 2)``, ``Hd (N, T)``,
    ``status (N,)``, ``n_steps (N,)``, ``n_rejected (N,)``, ``ics (N, 5)``; ``settings_json`` (the
    solution's settings plus ``ics``, ``command`` and the status legend, as JSON) and the scalars
    ``dt, t_final, save_every, method, dtype, gains_L, gains_k, gains_D_hat, params (m, J, l),
    damping``; and the per-trajectory summaries of `Solution.effort` (``u_peak (N, 2)``,
    ``u_norm_peak``, ``u_energy``, ``u_abs_int``, ``T_eps``, ``min_abs_theta``, ``max_excursion``).
    Returns the path written (``.npz`` appended when missing; a name that is, or whose ``.npz`` is, a folder,
    device or named pipe is refused: `jaxsleigh.validate.output_file`).
    """
    path = output_file(path, suffix=".npz")
    path.parent.mkdir(parents=True, exist_ok=True)
    ics = np.asarray(ics, dtype=np.float64)
    if ics.ndim == 1:
        ics = ics[None]
    if ics.shape[1] == 3:
        ics = np.concatenate([ics, np.zeros((ics.shape[0], 2))], axis=1)
    s = dict(sol.settings)
    settings = {**s, "ics": ics.tolist(), "command": list(command) if command is not None else None,
                "status_codes": describe(),
                # what varies between runs (wall time, devices) goes to the run's sidecar FILE.run.json
                "run_info": steady(getattr(sol, "run_info", None))}
    plant, g = s["plant"], s["gains"]
    # a law of the user's own has no paper gains: its record is in settings_json ("controller")
    gains = {} if g is None else {"gains_L": np.asarray(g["L"], dtype=np.float64), "gains_k": np.float64(g["k"]),
                                  "gains_D_hat": np.asarray(g["D_hat"], dtype=np.float64)}
    return write_npz_deterministic(path, dict(
        t=np.asarray(sol.t), q=np.asarray(sol.q), p=np.asarray(sol.p), u=np.asarray(sol.u),
        Hd=np.asarray(sol.Hd), status=np.asarray(sol.status, dtype=np.int32),
        n_steps=np.asarray(sol.n_steps), n_rejected=np.asarray(sol.n_rejected), ics=ics,
        settings_json=np.array(json.dumps(settings)),
        dt=np.float64(s["dt"]), t_final=np.float64(s["t_final"]), save_every=np.int64(s["save_every"]),
        method=np.array(s["method"]), dtype=np.array(s["dtype"]), **gains,
        params=np.array([plant["m"], plant["J"], plant["l"]], dtype=np.float64),
        damping=np.array(damping_name(plant["damping"])),
        **{k: np.asarray(v) for k, v in (getattr(sol, "effort", None) or {}).items()},
    ))


def settings_arrays(s: dict) -> dict:
    """The settings every result file repeats as scalars next to ``settings_json``: ``eps``,
    ``t_final``, ``dt``, ``method``, ``dtype``, ``max_steps``, ``gains_L``, ``gains_k``,
    ``gains_D_hat``, ``params (m, J, l)``, ``damping``."""
    plant, g = s["plant"], s.get("gains")
    # a law of the user's own has no paper gains: its record is in settings_json ("controller")
    gains = {} if g is None else {"gains_L": np.asarray(g["L"], np.float64), "gains_k": np.float64(g["k"]),
                                  "gains_D_hat": np.asarray(g["D_hat"], np.float64)}
    return dict(
        eps=np.float64(s["eps"]), t_final=np.float64(s["t_final"]), dt=np.float64(s["dt"]),
        method=np.array(s["method"]), dtype=np.array(s["dtype"]), max_steps=np.int64(s["max_steps"]),
        **gains, params=np.array([plant["m"], plant["J"], plant["l"]], np.float64),
        damping=np.array(damping_name(plant["damping"])),
    )


def write_result(path, arrays: dict, settings: dict) -> Path:
    """Write a study's result file (``.npz`` appended when missing, its folder made): ``arrays``, then the settings
    as JSON (``settings_json``, with the status legend) and as the scalars of `settings_arrays`; deterministic bytes
    (`write_npz_deterministic`). Returns the path. A name that is, or whose ``.npz`` is, not a regular file (a folder,
    a device, a named pipe) is refused (`jaxsleigh.validate.output_file`)."""
    path = output_file(path, suffix=".npz")
    path.parent.mkdir(parents=True, exist_ok=True)
    doc = json.dumps({**settings, "status_codes": describe()}, sort_keys=True, default=str)
    return write_npz_deterministic(path, {**arrays, "settings_json": np.array(doc), **settings_arrays(settings)})


def read_result(path, what: str, required=(), *, kind: str) -> tuple[dict, dict]:
    """``(arrays, settings)`` of a file written by `write_result` (`read_npz`'s checks and messages; the settings
    without the status legend)."""
    data = read_npz(path, what, ("settings_json",) + tuple(required), kind=kind)
    settings = json.loads(str(data["settings_json"]))
    settings.pop("status_codes", None)
    return data, settings


#: The key of the content digest in every file `write_npz_deterministic` writes (results and checkpoints alike).
DIGEST_KEY = "__digest__"


def content_digest(arrays: dict) -> str:
    """The SHA-256 (hex) of a file's arrays as they are written: for each name in sorted order (`DIGEST_KEY` left
    out) the name, the dtype (``<f8``), the shape and the bytes (C order). Equal arrays, equal digest; a value, a
    dtype, a shape or a name changed, another digest."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        if name == DIGEST_KEY:
            continue
        a = np.asanyarray(arrays[name])
        h.update(f"{name}\0{a.dtype.str}\0{a.shape}\0".encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def damaged(path, problem: str, fix: str = "write it again") -> DamagedFileError:
    """The `DamagedFileError` of ``path``: its name, ``problem`` and ``fix``."""
    return DamagedFileError(f"{str(path)!r}: {problem}; {fix}", path=path, problem=problem)


def check_digest(path, data: dict, fix: str = "write it again") -> bool:
    """Verify the content digest of a file's arrays ``data`` (as read) and take it out of ``data``: ``True`` when it
    matches, ``False`` when the file records none (written by an earlier jaxsleigh, or by hand); a `DamagedFileError`
    naming the file when it does not match (the file was edited or damaged after it was written) or is no digest."""
    if DIGEST_KEY not in data:
        return False
    rec = data.pop(DIGEST_KEY)
    if rec.ndim != 0 or not np.issubdtype(rec.dtype, np.str_) or len(str(rec)) != 64:
        raise damaged(path, f"its content digest ({DIGEST_KEY}) is not a SHA-256 but {rec.dtype} of shape "
                            f"{rec.shape}: the file was edited or damaged after jaxsleigh wrote it", fix)
    got = content_digest(data)
    if str(rec) != got:
        raise damaged(path, f"its contents do not match the digest recorded when jaxsleigh wrote it (sha256 "
                            f"{str(rec)[:12]}..., its arrays now give {got[:12]}...): it was edited or damaged after "
                            f"it was written", fix)
    return True


def value_problem(data: dict, codes=tuple(Status)) -> Optional[str]:
    """What is wrong with the values of a file's per-start arrays, in words (``None``: nothing): every field holds
    numbers or booleans (no text, no objects); ``status`` whole numbers among ``codes`` (`jaxsleigh.status.Status`);
    ``T_eps`` real numbers >= 0, ``inf`` (not settled) or NaN (not integrated); ``n_steps`` and ``n_rejected`` whole
    numbers >= 0. Used on checkpoint chunks (`jaxsleigh.files.chunks.ChunkStore.load`) and, text fields left out,
    on result files (`check_fields`)."""
    for name, a in data.items():
        a = np.asarray(a)
        if a.dtype.kind not in "biuf":
            return f"field {name} holds {a.dtype}, not numbers"
    if "status" in data:
        a = np.asarray(data["status"])
        if not np.issubdtype(a.dtype, np.integer):
            return f"field status holds {a.dtype}, not whole-number status codes"
        known = [int(c) for c in codes]
        bad = np.setdiff1d(np.unique(a), np.asarray(known))
        if bad.size:
            return (f"field status holds {bad.size} unknown status code(s) ({', '.join(map(str, bad[:5].tolist()))}"
                    f"{', ...' if bad.size > 5 else ''}; the codes are {min(known)}-{max(known)})")
    if "T_eps" in data:
        a = np.asarray(data["T_eps"])
        if not np.issubdtype(a.dtype, np.floating):
            return f"field T_eps holds {a.dtype}, not real numbers (seconds, inf or NaN)"
        if np.any(a < 0):
            return "field T_eps holds negative times"
    for name in ("n_steps", "n_rejected"):
        if name in data:
            a = np.asarray(data[name])
            if not np.issubdtype(a.dtype, np.integer):
                return f"field {name} holds {a.dtype}, not whole numbers"
            if np.any(a < 0):
                return f"field {name} holds negative counts"
    return None


#: Version of the result files' layout, written into every result file as ``format_version``. 1: files of
#: jaxsleigh 0.1 (no ``format_version`` key), still read; 2: the same arrays, versioned.
FORMAT_VERSION = 2


def write_npz_deterministic(path, arrays: dict, *, compress: bool = True, when_full: str = "",
                            stamped: bool = True) -> Path:
    """Like ``np.savez_compressed`` but with fixed zip timestamps (equal inputs, equal bytes),
    written atomically (:func:`atomic_write`); the file carries ``format_version`` (`FORMAT_VERSION`) and, last,
    ``__digest__`` (`DIGEST_KEY`): the `content_digest` of every other array, which every reader verifies
    (`check_digest`): a file edited or damaged after it was written is refused (a checkpoint chunk recomputed).
    Compressed at zlib's level 1: a 10^5-start basin's 16.6 MB of arrays in 0.4 s instead of 1.4 s at the default
    level 6, for a file 6% larger; ``compress=False`` stores them as they are (checkpoints, written often).
    ``when_full``: as in `atomic_write`; ``stamped=False``: the arrays alone, without ``format_version`` and
    ``__digest__`` (a tuner's history, which readers take as plain ``numpy.load`` arrays)."""
    if stamped:
        arrays = {"format_version": np.int64(FORMAT_VERSION), **arrays}
        arrays[DIGEST_KEY] = np.array(content_digest(arrays))

    def write(f):
        method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
        with zipfile.ZipFile(f, "w", compression=method) as zf:
            for key, val in arrays.items():
                buf = _io.BytesIO()
                np.lib.format.write_array(buf, np.asanyarray(val), allow_pickle=False)
                info = zipfile.ZipInfo(key + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
                info.compress_type = method
                info._compresslevel = 1 if compress else None    # writestr takes a ZipInfo's level, not the file's
                info.external_attr = 0o644 << 16
                zf.writestr(info, buf.getvalue())

    return atomic_write(path, write, when_full=when_full)


def _a(what: str) -> str:
    """``what`` with its article: "a basin file", "an optimum file"."""
    return ("an " if what[:1].lower() in "aeiou" else "a ") + what


def read_npz(path, what: str, required=(), *, kind: Optional[str] = None, check=None) -> dict:
    """Every array of an ``.npz`` result file; ``ValueError`` naming the file if it cannot be read
    or lacks a ``required`` key (``what``: e.g. ``"basin file (written by jaxsleigh basin / save_basin)"``).

    ``kind`` (a key of `NPZ_KINDS`): the file must be that kind of result; a result of another
    kind is refused with its name and the function that reads it ("x.npz is a sweep result; read it
    with jaxsleigh.load_sweep").

    What is read is checked before it is used, each failure a `jaxsleigh.errors.DamagedFileError` (a ``ValueError``)
    naming the file and what is wrong: the file is a zip archive of arrays (a JSON, text or ``.npy`` file is named as
    such); for a ``kind``, `check_fields`: every field's kind of number, shape and values; ``check(path, data)``: a
    reader's own checks of the values (they name the field a hand edit broke); last, its content digest
    (``__digest__``, `check_digest`) matches its arrays, which catches any edit the field checks let through (files
    of jaxsleigh 0.3 and earlier record none and are read without it).
    """
    p = _npz_to_read(path, what)
    if p.is_dir():
        raise ValueError(f"{str(p)!r} is a folder; the path must be a .npz written by jaxsleigh: give the {what}")
    fix = f"the path must be a .npz written by jaxsleigh: give the {what}"
    not_zip = _not_a_zip(p)
    if not_zip:
        problem = f"it is {not_zip}, not an .npz archive"
        raise DamagedFileError(f"cannot read {str(p)!r}: {problem}; {fix}", path=p, problem=problem)
    try:
        z = np.load(p, allow_pickle=False)
        if not hasattr(z, "files"):            # a .npy array, not an archive of named arrays
            raise ValueError("a single .npy array, not a .npz archive")
        with z:
            data = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise ValueError(f"{str(p)!r} not found; give the {what}") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise ValueError(f"cannot read {str(p)!r} ({type(e).__name__}: {e}); the path must be a .npz written by "
                         f"jaxsleigh: give the {what}") from None
    version = _format_version(p, data)
    if version > FORMAT_VERSION:
        raise ValueError(f"{str(p)!r} was written by a newer jaxsleigh (result format {version}); this one reads "
                         f"formats up to {FORMAT_VERSION}: upgrade jaxsleigh to read it")
    found = npz_kind(data)
    if kind is not None and found is not None and found != kind:
        _, name, reader = NPZ_KINDS[found]
        raise ValueError(f"{str(p)!r} is {name}, not {_a(what)}; read it with {reader}")
    missing = [k for k in required if k not in data]
    if missing:
        keys = ", ".join(sorted(data)[:12]) + (", ..." if len(data) > 12 else "")
        raise ValueError(f"{str(p)!r} is not {_a(what)}: it lacks {', '.join(missing)} (its keys: {keys or 'none'})")
    if kind is not None:
        check_fields(p, data, kind)
    if check is not None:
        check(p, data)
    check_digest(p, data, "write it again (rerun the command that made it)")
    return data


def _not_a_zip(p: Path) -> str:
    """What ``p`` is in words when it is not a zip archive (an ``.npz``): ``"a JSON file"``, ``"text"``, ``"a single
    .npy array"``, ``"an empty file"``, ``"not a zip archive"``; ``""`` when it is one (or cannot be opened: the
    reader then says why)."""
    try:
        with open(p, "rb") as f:
            head = f.read(512)
    except OSError:
        return ""
    if head[:2] == b"PK":
        return ""
    if not head:
        return "an empty file"
    if head.startswith(b"\x93NUMPY"):
        return "a single .npy array"
    try:
        text = head.decode("utf-8").lstrip()
    except UnicodeDecodeError:
        return "not a zip archive"
    return "a JSON file" if text[:1] in "{[" and text else "text"


def _format_version(p: Path, data: dict) -> int:
    """The file's ``format_version`` (1 when absent: a file of jaxsleigh 0.1); ``ValueError`` naming the file and
    the field when it is not a whole number >= 1."""
    if "format_version" not in data:
        return 1
    v = data["format_version"]
    if v.ndim != 0 or not np.issubdtype(v.dtype, np.integer) or int(v) < 1:
        shown = v.tolist() if v.size <= 4 else f"an array of shape {v.shape}"
        raise ValueError(f"{str(p)!r}: field format_version must be a whole number >= 1 (the result format; this "
                         f"jaxsleigh writes {FORMAT_VERSION}), got {shown!r} ({v.dtype}); the file is damaged or was "
                         f"not written by jaxsleigh: write it again")
    return int(v)


# what each field of a result file holds: (kind of number, shape). Kinds: "int" whole numbers, "real" real
# numbers (whole ones too), "text" strings. A shape names its axes (the same name, the same length across the
# file's fields) or fixes them (3; (3, 5): one of these).
_N, _P, _T = "N", "P", "T"
_START = {"T_eps": ("real", (_N,)), "status": ("int", (_N,)), "Hd0": ("real", (_N,)), "Hd_final": ("real", (_N,)),
          "min_abs_theta": ("real", (_N,)), "max_excursion": ("real", (_N,)), "n_steps": ("int", (_N,)),
          "n_rejected": ("int", (_N,)), "q_final": ("real", (_N, 3)), "p_final": ("real", (_N, 2)),
          "ics": ("real", (_N, (3, 5))), "u_peak": ("real", (_N, 2)), "u_norm_peak": ("real", (_N,)),
          "u_energy": ("real", (_N,)), "u_abs_int": ("real", (_N,)), "settings_json": ("text", ())}
FIELDS = {
    "basin": _START,
    "sweep": {"names": ("text", ("n",)), "values": ("real", (_P, "n")), "grid_shape": ("int", ("g",)),
              "ics": ("real", (_N, (3, 5))), "T_eps": ("real", (_P, _N)), "status": ("int", (_P, _N)),
              "n_steps": ("int", (_P, _N)), "min_abs_theta": ("real", (_P, _N)), "Hd0": ("real", (_P, _N)),
              "u_energy": ("real", (_P, _N)), "u_abs_int": ("real", (_P, _N)), "u_norm_peak": ("real", (_P, _N)),
              "settings_json": ("text", ())},
    "simulation": {"t": ("real", (_T,)), "q": ("real", (_N, _T, 3)), "p": ("real", (_N, _T, 2)),
                   "u": ("real", (_N, _T, 2)), "Hd": ("real", (_N, _T)), "status": ("int", (_N,)),
                   "n_steps": ("int", (_N,)), "n_rejected": ("int", (_N,)), "ics": ("real", (_N, (3, 5))),
                   "T_eps": ("real", (_N,)), "settings_json": ("text", ())},
    "optimum": {"starts": ("real", ("S", 5)), "horizons": ("real", ("H",)), "eps": ("real", ()),
                "energy": ("real", ("S", "H")), "frontier": ("real", ("S", "H")), "u": ("real", ("S", "H", "I", 2)),
                "status": ("int", ("S", "H")), "q_final": ("real", ("S", "H", 3)), "p_final": ("real", ("S", "H", 2)),
                "kkt": ("real", ("S", "H")), "guess": ("int", ("S", "H")), "settings_json": ("text", ())},
}
#: The status codes a result file of each kind may hold (an optimum's, `jaxsleigh.studies.optimum.OptimumStatus`, are
#: checked by `jaxsleigh.load_optimum`).
STATUS_CODES = {"basin": tuple(Status), "sweep": tuple(Status), "simulation": tuple(Status)}
_KIND_TEST = {"int": lambda d: np.issubdtype(d, np.integer),
              "real": lambda d: np.issubdtype(d, np.integer) or np.issubdtype(d, np.floating),
              "text": lambda d: np.issubdtype(d, np.str_)}
_KIND_WORDS = {"int": "whole numbers", "real": "real numbers", "text": "text"}


def check_fields(p, data: dict, kind: str) -> None:
    """Every field of `FIELDS` [kind] that ``data`` holds has its kind of number and its shape, fields that share an
    axis agree on its length, and the per-start fields hold values a run writes (`value_problem`: known status codes,
    ``T_eps`` >= 0, inf or NaN, counts >= 0; the status codes of `STATUS_CODES` [kind]); else a
    `jaxsleigh.errors.DamagedFileError` (a ``ValueError``) naming the file and the field."""
    sizes: dict = {}
    for name, (num, shape) in FIELDS.get(kind, {}).items():
        if name not in data:
            continue
        a = data[name]
        if not _KIND_TEST[num](a.dtype):
            raise damaged(p, f"field {name} must hold {_KIND_WORDS[num]}, but it holds {a.dtype}",
                          "the file is damaged or was not written by jaxsleigh: write it again")
        _check_shape(p, name, a.shape, shape, sizes)
    codes = STATUS_CODES.get(kind)
    if codes is not None:
        per_start = {k: data[k] for k in ("status", "T_eps", "n_steps", "n_rejected") if k in data}
        why = value_problem(per_start, codes)
        if why:
            raise damaged(p, why, "the file is damaged or was not written by jaxsleigh: write it again")


def _check_shape(p, name: str, got: tuple, want: tuple, sizes: dict) -> None:
    """``got`` against the named / fixed axes ``want``; ``sizes`` holds each named axis's length (and the field
    that set it) across the file."""
    def wanted() -> str:
        return "(" + ", ".join(str(w) if not isinstance(w, tuple) else " or ".join(map(str, w)) for w in want) \
            + ("," if len(want) == 1 else "") + ")"

    what = f"field {name} has shape {tuple(got)}, expected {wanted()}"
    bad = f"{str(p)!r}: {what}"
    if len(got) != len(want):
        raise DamagedFileError(f"{bad}; the file is damaged or was not written by jaxsleigh: write it again", path=p,
                               problem=what)
    for n, w in zip(got, want):
        if isinstance(w, int) and n != w or isinstance(w, tuple) and n not in w:
            raise DamagedFileError(f"{bad}; the file is damaged or was not written by jaxsleigh: write it again",
                                   path=p, problem=what)
        if isinstance(w, str):
            if w in sizes and sizes[w][0] != n:
                raise DamagedFileError(f"{bad} with {w} = {sizes[w][0]} as in field {sizes[w][1]} (shape "
                                       f"{sizes[w][2]}); the file is truncated or damaged: write it again", path=p,
                                       problem=what)
            sizes.setdefault(w, (n, name, tuple(got)))


def damping_name(class_name: str) -> str:
    return {"CoulombDamping": "coulomb", "ViscousDamping": "viscous", "NoDamping": "none"}.get(
        class_name, class_name)


_BINOPS = {ast.Add: operator.add, ast.Sub: operator.sub, ast.Mult: operator.mul, ast.Div: operator.truediv}
_NAMES = {"pi": math.pi, "nan": math.nan, "inf": math.inf}


def parse_number(text: str) -> float:
    """A float from ``'0.39'``, ``'-pi/8'``, ``'3*pi/4'``, ``'1e-3'`` (numbers, pi, + - * /)."""

    def ev(node):
        if isinstance(node, ast.Expression):
            return ev(node.body)
        if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)) \
                and not isinstance(node.value, bool):
            return float(node.value)
        if isinstance(node, ast.Name) and node.id.lower() in _NAMES:
            return _NAMES[node.id.lower()]
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
            v = ev(node.operand)
            return -v if isinstance(node.op, ast.USub) else v
        if isinstance(node, ast.BinOp) and type(node.op) in _BINOPS:
            return _BINOPS[type(node.op)](ev(node.left), ev(node.right))
        raise ValueError

    text = text.strip()
    try:
        return float(text)
    except ValueError:
        pass
    try:
        return ev(ast.parse(text, mode="eval"))
    except (SyntaxError, ValueError, ZeroDivisionError, RecursionError, OverflowError):
        raise ValueError(f"{text!r} is not a number") from None


def load_ics(path, *, hint: str = "") -> np.ndarray:
    """Initial conditions from a ``.npy`` (or ``.txt``/``.csv``) file: float64 (N, 3) or (N, 5).

    Raises ``ValueError`` with a message naming the fix; ``hint`` names the command's alternative.
    """
    p = Path(path)
    fix = "save them with numpy.save as a real float array of shape (N, 3) or (N, 5)"
    if not p.is_file():
        what = "is a folder" if p.is_dir() else "not found"
        raise ValueError(f"initial-conditions file {str(path)!r} {what}; give an existing .npy file of "
                         f"shape (N, 3) or (N, 5)" + (f", or {hint}" if hint else ""))
    text = p.suffix.lower() in (".txt", ".csv")
    if text:
        fix = ("write one start per line as 3 or 5 numbers (x, y, theta[, p1, p2]), after at most one header line "
               "of names")
    try:
        if text:
            arr = _load_table(p)
        else:
            with open(p, "rb") as f:
                magic = f.read(6)
            if magic != b"\x93NUMPY":
                kind = "an empty file" if not magic else (
                    "text (a CSV or text table? name it .csv or .txt)" if _looks_like_text(p) else "not a .npy file")
                raise ValueError(f"{str(path)!r} is {kind}, not a NumPy .npy file; {fix}")
            _check_npy_header(p, str(path), fix)
            arr = np.load(p, allow_pickle=False)
    except ValueError as e:
        if str(e).startswith(repr(str(path))):
            raise
        raise ValueError(f"could not read initial conditions from {str(path)!r} ({e}); {fix}") from None
    except (OSError, EOFError) as e:
        raise ValueError(f"could not read initial conditions from {str(path)!r} ({type(e).__name__}: {e}); "
                         f"{fix}") from None
    if not isinstance(arr, np.ndarray) or arr.dtype == bool or not np.issubdtype(arr.dtype, np.number):
        raise ValueError(f"{str(path)!r} must hold a numeric array of shape (N, 3) or (N, 5)")
    if np.iscomplexobj(arr):
        raise ValueError(f"{str(path)!r} holds complex numbers (dtype {arr.dtype}); initial conditions are real: "
                         f"{fix}")
    if arr.ndim != 2 or arr.shape[1] not in (3, 5) or arr.shape[0] == 0:
        raise ValueError(f"{str(path)!r} holds an array of shape {arr.shape}; initial conditions must have "
                         f"shape (N, 3) [x, y, theta] or (N, 5) [x, y, theta, p1, p2] with N >= 1")
    return arr.astype(np.float64)


def _load_table(p: Path) -> np.ndarray:
    """A ``.csv`` (commas) or ``.txt`` (blanks) table of numbers, ``ndmin=2``; a first line that is not numbers
    (a header of names, ``x,y,theta``) is skipped, with the blank or comment lines before it."""
    delimiter = "," if p.suffix.lower() == ".csv" else None
    with open(p, encoding="utf-8", errors="replace") as f:
        lineno, first = next(((i, line) for i, line in enumerate(f, 1)
                              if line.strip() and not line.lstrip().startswith("#")), (0, ""))
    skip = 0
    if first:
        try:
            [float(x) for x in first.split(delimiter) if x.strip()]
        except ValueError:
            skip = lineno           # np.loadtxt(skiprows=...) counts every line up to the header
    return np.loadtxt(p, delimiter=delimiter, ndmin=2, skiprows=skip)


def _check_npy_header(p: Path, name: str, fix: str) -> None:
    """Read only the ``.npy`` header and refuse, before any allocation, an array the file cannot hold
    (a header claiming more bytes than follow it: forged, truncated) or that would not fit in memory."""
    fmt = np.lib.format
    with open(p, "rb") as f:
        version = fmt.read_magic(f)
        if version == (1, 0):
            shape, _, dtype = fmt.read_array_header_1_0(f)
        elif version == (2, 0):
            shape, _, dtype = fmt.read_array_header_2_0(f)
        else:                       # (3, 0): a utf-8 header, read by NumPy's own reader
            shape, _, dtype = fmt._read_array_header(f, version)
        offset = f.tell()
    size = p.stat().st_size - offset
    if dtype.hasobject:
        raise ValueError(f"{name!r} holds Python objects (dtype {dtype}), not numbers; {fix}")
    need = math.prod(int(n) for n in shape) * dtype.itemsize
    if need > size:
        raise ValueError(f"{name!r}: its header claims an array of shape {tuple(shape)} ({dtype}, {need:,} bytes) "
                         f"but only {size:,} bytes follow it; the file is truncated or damaged: write it again "
                         f"({fix})")
    rows = int(shape[0]) if len(shape) else 1
    check_memory(rows, repr(name),
                 fix="split the starts into several files and runs")


def _looks_like_text(p: Path) -> bool:
    with open(p, "rb") as f:
        head = f.read(512)
    try:
        head.decode("ascii")
    except UnicodeDecodeError:
        return False
    return True


# ---------------------------------------------------------------------------------------------
# atomic writes: a file is either complete or absent, never half-written
# ---------------------------------------------------------------------------------------------

def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:  # pragma: no cover - not every platform opens folders
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover
        pass
    finally:
        os.close(fd)


#: errno values that mean "the disk (or the quota) is full": reported as `DiskFullError`.
_FULL = tuple(e for e in (getattr(errno, "ENOSPC", None), getattr(errno, "EDQUOT", None)) if e is not None)


def atomic_write(path, write, *, when_full: str = "") -> Path:
    """Write ``path`` through ``write(file_object)`` into a temporary file in the same folder,
    flush it to disk (fsync) and rename it into place: readers see the old file or the complete
    new one, also after a crash or a kill.

    A full disk or quota (ENOSPC, EDQUOT) raises `jaxsleigh.errors.DiskFullError` naming the
    file; ``when_full`` is appended to its message (what continues the work once there is space).
    A ``path`` that exists and is not a regular file (a folder, a device such as ``/dev/full``, a named pipe)
    is refused with a ``ValueError`` before anything is written: the rename would replace it.
    """
    path = output_file(path)
    # a hidden name that no glob of finished files ("chunk_*.npz", "*.json") matches; the host name
    # keeps two processes of a multi-host run (same pid, shared folder) apart
    tmp = path.with_name(f".{path.name}.{host_label()}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as e:
        try:
            tmp.unlink()
        except OSError:
            pass
        if isinstance(e, OSError) and e.errno in _FULL:
            what = "no space left on the device" if e.errno == errno.ENOSPC else "the disk quota is exceeded"
            raise DiskFullError(e.errno, f"could not write {str(path)!r}: {what} ({os.strerror(e.errno)}); free some "
                                         f"space there (or choose another location) and run the command again"
                                + (f"; {when_full}" if when_full else ""), path=path) from None
        raise
    _fsync_dir(path.parent)
    return path


def atomic_write_text(path, text: str, *, when_full: str = "") -> Path:
    """`atomic_write` of a UTF-8 text."""
    return atomic_write(path, lambda f: f.write(text.encode("utf-8")), when_full=when_full)
