"""The one place jaxsleigh reads private names of JAX (and replaces none).

JAX's multi-controller runtime has no public accessor for its distributed client, whose key-value store and
barriers `jaxsleigh.files.distributed` uses to coordinate the processes of one run; and its persistent cache does
not say how it names an entry's access-time file, which `jaxsleigh.cache` writes for entries an unbounded cache
kept without one. Both are read here, and ``tests/test_import.py`` fails when JAX moves them.
"""
from __future__ import annotations

__all__ = ["distributed_client", "cache_entry_suffixes"]


def cache_entry_suffixes() -> tuple:
    """``(entry, access time)``: the suffixes of the two files of one entry of JAX's persistent cache
    (``jax._src.lru_cache``: ``"-cache"``, ``"-atime"``)."""
    from jax._src import lru_cache

    return lru_cache._CACHE_SUFFIX, lru_cache._ATIME_SUFFIX


def distributed_client():
    """The client of ``jax.distributed`` in this process (``None`` before ``jax.distributed.initialize``):
    ``jax._src.distributed.global_state.client``."""
    from jax._src import distributed

    return distributed.global_state.client
