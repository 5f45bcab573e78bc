"""JAX's persistent compilation cache for jaxsleigh: compile once per machine, not once per process.

``import jaxsleigh`` turns it on (the command line and Python sessions alike; ``JAXSLEIGH_NO_COMPILE_CACHE=1``
keeps it off); `enable_compilation_cache` moves it to another folder. Both use the same folder
(`compilation_cache_dir`), so a program compiled by one is reused by the other.
"""
from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Optional, Union

__all__ = ["compilation_cache_dir", "enable_compilation_cache"]


def compilation_cache_dir() -> Optional[Path]:
    """Where compiled programs are kept between processes: ``$JAXSLEIGH_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/jaxsleigh/jax`` (``~/.cache/jaxsleigh/jax``); ``None`` when turned off with
    ``JAXSLEIGH_NO_COMPILE_CACHE=1`` (or ``--no-compile-cache``)."""
    if os.environ.get("JAXSLEIGH_NO_COMPILE_CACHE", "").strip() not in ("", "0"):
        return None
    if os.environ.get("JAXSLEIGH_CACHE_DIR"):
        return Path(os.environ["JAXSLEIGH_CACHE_DIR"])
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "jaxsleigh" / "jax"


def enable_compilation_cache(path: Union[str, os.PathLike, None] = None) -> Optional[Path]:
    """Turn on JAX's persistent compilation cache for this process: a later process (a Python
    session or the command line) compiles nothing that was compiled before.

    Call it once, before the first simulation (JAX reads the setting when it first compiles).

    Args:
      path: the cache folder. Default: the command line's (`compilation_cache_dir`:
        ``$JAXSLEIGH_CACHE_DIR``, else ``~/.cache/jaxsleigh/jax``), or none at all when
        ``JAXSLEIGH_NO_COMPILE_CACHE=1``; a default folder that cannot be created leaves the cache
        off (JAX then compiles as usual).

    Returns:
      The folder in use, or ``None`` when the cache stays off.

    Raises:
      ValueError: ``path`` was given but is empty, a file, or cannot be created.
    """
    if path is None:
        d = compilation_cache_dir()
        if d is None:
            return None
        try:
            d.mkdir(parents=True, exist_ok=True)
        except OSError:
            return None
    else:
        if not isinstance(path, (str, os.PathLike)) or not str(path).strip():
            raise ValueError(f"path must be a folder for the compilation cache (or None for the default), "
                             f"got {path!r}")
        d = Path(path).expanduser()
        try:
            d.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            what = "is a file" if d.is_file() else f"cannot be created ({e.strerror or e})"
            raise ValueError(f"path {str(d)!r} {what}; give a writable folder for the compilation cache, "
                             "or path=None for the default") from None
    import jax

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        jax.config.update("jax_compilation_cache_dir", str(d))
        # cache every program: the sleigh's are small and quick to compile, but many
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return d
