"""The one place jaxsleigh reads private names of JAX (and replaces none).

JAX's persistent cache does not say how it names an entry's access-time file, which `jaxsleigh.cache` writes for
entries an unbounded cache kept without one. It is read here, and ``tests/test_import.py`` fails when JAX moves it.
"""
from __future__ import annotations

__all__ = ["cache_entry_suffixes"]


def cache_entry_suffixes() -> tuple:
    """``(entry, access time)``: the suffixes of the two files of one entry of JAX's persistent cache
    (``jax._src.lru_cache``: ``"-cache"``, ``"-atime"``)."""
    from jax._src import lru_cache

    return lru_cache._CACHE_SUFFIX, lru_cache._ATIME_SUFFIX
