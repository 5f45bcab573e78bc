"""Eager checks of what users pass in: one place, the same messages for the API and the command line.

Every function raises ``ValueError`` with a message that names the argument (``name``: the Python
keyword, or the command-line flag when the command line calls it) and says what to write instead.
Numbers that are really something else (``True``, a complex number, a string) are refused, not
converted.
"""
from __future__ import annotations

import functools
import inspect
import math
import numbers
import os
import platform
import stat
from pathlib import Path
from typing import Optional

import numpy as np

__all__ = ["INT32_MAX", "refuses_removed_keywords", "real", "whole", "check_memory", "check_count", "writable_path",
           "writable_dir", "output_file", "not_a_file", "host_label"]

#: The largest step budget the engine's int32 counters hold.
INT32_MAX = 2**31 - 1


def _example(name: str, example) -> str:
    if example is None:
        return ""
    return f" (e.g. {name} {example})" if name.startswith("-") else f" (e.g. {name}={example})"


def real(name: str, value, *, positive: bool = False, nonnegative: bool = False, example=None,
         maximum: Optional[float] = None) -> float:
    """A finite real number (a Python or NumPy int/float; not a bool, complex or string)."""
    ex = _example(name, example)
    if not isinstance(value, (np.ndarray, numbers.Real, str)) and getattr(value, "shape", None) == () \
            and hasattr(value, "__array__"):
        try:                                   # a concrete 0-d jax.Array is a number too
            value = np.asarray(value)
        except Exception:                      # noqa: BLE001 - a tracer: refused below, by its type
            pass
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real) or isinstance(value, str):
        if isinstance(value, np.ndarray) and value.ndim == 0 and np.issubdtype(value.dtype, np.number) \
                and not np.issubdtype(value.dtype, np.complexfloating) and value.dtype != bool:
            value = value.item()
        else:
            raise ValueError(f"{name} must be a real number, got {value!r}{ex}")
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {v}{ex}")
    if positive and not v > 0:
        raise ValueError(f"{name} must be > 0, got {v:g}{ex}")
    if nonnegative and v < 0:
        raise ValueError(f"{name} must be >= 0, got {v:g}{ex}")
    if maximum is not None and v > maximum:
        raise ValueError(f"{name} must be <= {maximum:g}, got {v:g}{ex}")
    return v


def whole(name: str, value, *, minimum: int = 1, maximum: int = INT32_MAX, example=None) -> int:
    """A whole number in ``[minimum, maximum]`` (``1.0`` is accepted, ``1.5`` and ``True`` are not)."""
    ex = _example(name, example)
    if isinstance(value, (bool, np.bool_)) or isinstance(value, str) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name} must be a whole number, got {value!r}{ex}")
    if isinstance(value, numbers.Integral):
        v = int(value)
    else:
        f = float(value)
        if not (math.isfinite(f) and f == int(f)):
            raise ValueError(f"{name} must be a whole number, got {value!r}{ex}")
        v = int(f)
    if v < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {v}{ex}")
    if v > maximum:
        raise ValueError(f"{name} must be <= {maximum}, got {v}{ex}")
    return v


def _available_bytes() -> Optional[int]:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):  # pragma: no cover - not on every platform
        return None


#: Host memory a run keeps per start (the start, the per-start results, and their copy in the file).
BYTES_PER_START = 400


def check_memory(n: int, what: str, *, bytes_per_start: int = BYTES_PER_START, fraction: float = 0.8,
                 unit: str = "starts", fix: Optional[str] = None) -> None:
    """Refuse, before any work, a run whose per-item inputs and results would not fit in memory.

    Args:
      n: how many items (starts, rows, values) the run would hold; any size, also one that no array could.
      what: names the input in the message (the Python keyword or the command-line flag).
      bytes_per_start: host memory one item needs.
      unit, fix: what an item is, and what to do instead (the defaults speak of starts).
    """
    need = int(n) * bytes_per_start
    have = _available_bytes()
    if have is not None and need > fraction * have:
        if fix is None:
            fix = "use fewer starts (a coarser grid, fewer --samples) or split the study into several runs"
        for_what = " for the starts and their results" if unit == "starts" else ""
        raise ValueError(f"{what}: {int(n):,} {unit} need about {need / 2**30:,.1f} GiB of host memory{for_what}, "
                         f"more than the {have / 2**30:,.1f} GiB available; {fix}")


def check_count(what: str, n: int, *, maximum: int, reason: str, fix: str) -> int:
    """Refuse a count that costs time rather than memory (points of a front, generations) above a sane
    ``maximum``; the message names ``what`` (keyword or flag), the count, the bound and ``reason``."""
    if int(n) > maximum:
        raise ValueError(f"{what} {int(n):,} is more than the {maximum:,} allowed: {reason}; {fix}")
    return int(n)


def host_label() -> str:
    """This host's name as a file-name component (other characters than letters, digits, - and _ as ``_``; at most
    64): with the pid, it keeps apart the files of processes on hosts that share a folder."""
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in platform.node())[:64]


def writable_dir(path, what: str = "output folder") -> Path:
    """Create ``path`` (a folder) if needed and check that files can be written in it."""
    d = Path(path)
    if d.exists() and not d.is_dir():
        raise ValueError(f"the {what} {str(d)!r} exists and is not a folder; choose another path")
    try:
        d.mkdir(parents=True, exist_ok=True)
        probe = d / f".jaxsleigh-write-test-{host_label()}-{os.getpid()}"   # unique across hosts sharing d
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise ValueError(f"cannot write into the {what} {str(d)!r} ({e.strerror or e}); choose a writable "
                         f"location") from None
    return d


def not_a_file(path) -> Optional[str]:
    """What ``path`` is when it exists and is not a regular file, in words ("a folder", "a named pipe (FIFO)",
    "a character device", ...; a symbolic link is followed, so a link to ``/dev/null`` is a character
    device); ``None`` when it is a regular file or does not exist. Only looks (``stat``): never opens it."""
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):              # absent, a dangling link, a name the system refuses
        return None
    if stat.S_ISREG(mode):
        return None
    for test, words in ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a named pipe (FIFO)"),
                        (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                        (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return words
    return "not a regular file"                # pragma: no cover - door, port, ...


def output_file(path, what: str = "output file", *, suffix: Optional[str] = None) -> Path:
    """The file a writer writes for the name ``path``, refused if writing it would replace or open something
    that is not a regular file.

    ``suffix`` (``".npz"``): the extension the writer appends to a name without it; then the name as given is
    checked too (``--out /dev/full`` is refused, not written as ``/dev/full.npz``). A name that exists and is a
    folder, a device (``/dev/full``, ``/dev/null``), a named pipe or a socket raises ``ValueError`` naming the
    path and what it is. Only looks at the names (nothing is created or opened); returns the name written.
    """
    given = Path(path)
    written = given if suffix is None or given.suffix == suffix else given.with_name(given.name + suffix)
    for p in dict.fromkeys((given, written)):
        kind = not_a_file(p)
        if kind is None:
            continue
        if kind == "a folder":
            raise ValueError(f"the {what} {str(p)!r} is a folder; give a file name (e.g. {str(p / 'out')!r})")
        also = f" (the file written would be {str(written)!r})" if p != written else ""
        raise ValueError(f"the {what} {str(p)!r} is {kind}, not a regular file{also}; jaxsleigh writes its "
                         f"outputs to regular files only: give the name of a file")
    return written


def writable_path(path, what: str = "output file", *, suffix: Optional[str] = None) -> Path:
    """Check, before any work, that ``path`` can be written: not a folder, device, named pipe or socket
    (`output_file`; with ``suffix``, neither the name given nor the name with ``suffix`` appended), its
    folder created if needed and writable, the file itself writable if it exists. Returns the name written
    (``path``, or with ``suffix`` appended)."""
    p = output_file(path, what, suffix=suffix)
    writable_dir(p.parent if str(p.parent) else Path("."), what=f"folder of the {what}")
    if p.exists() and not os.access(p, os.W_OK):
        raise ValueError(f"the {what} {str(p)!r} exists and is not writable; choose another path")
    return p


#: The class each option parameter of a front takes, by the parameter's name (what a refusal names).
OPTION_CLASSES = {"stepsize": "StepSizeController", "saveat": "SaveAt", "run": "RunOptions"}


def refuses_removed_keywords(removed: dict, uses: dict, since: str, name: str = ""):
    """A decorator: a keyword of ``removed`` (``keyword -> (parameter, field)`` of the option object that holds it
    now) given to the decorated front is a ``TypeError`` naming that object and field, e.g. ``run_basin() got an
    unexpected keyword argument 'rtol': pass stepsize=jaxsleigh.StepSizeController(rtol=...)``, or saying that the
    front has no use for it (a field not in ``uses``, ``parameter -> fields``); ``since`` ends the message (which
    keywords, removed when). Any other unexpected keyword gets Python's own ``TypeError``; the signature, name and
    docstring are the front's. ``name``: what the message calls the front (default: its ``__name__``; a class's
    ``__new__`` gives the class's name)."""
    def decorate(front):
        params = inspect.signature(front).parameters
        label = name or front.__name__

        @functools.wraps(front)
        def call(*args, **kwargs):
            given = [k for k in kwargs if k in removed and k not in params]
            if not given:
                return front(*args, **kwargs)
            fields, unused = {}, []
            for key in given:
                home, field = removed[key]
                if field in uses.get(home, ()):
                    fields.setdefault(home, []).append(field)
                else:
                    unused.append(f"jaxsleigh.{OPTION_CLASSES[home]}.{field}")
            objects = [f"{h}=jaxsleigh.{OPTION_CLASSES[h]}({', '.join(f + '=...' for f in fields[h])})"
                       for h in OPTION_CLASSES if h in fields]
            says = ["pass " + ", ".join(objects)] if objects else []
            if unused:
                says.append(f"{label}() has no use for {', '.join(unused)}")
            got = "an unexpected keyword argument" if len(given) == 1 else "unexpected keyword arguments"
            raise TypeError(f"{label}() got {got} {', '.join(repr(k) for k in given)}: {'; '.join(says)} ({since})")

        return call

    return decorate
