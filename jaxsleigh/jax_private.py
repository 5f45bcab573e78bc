"""The one place jaxsleigh reads a private name of JAX (and replaces none).

JAX's multi-controller runtime has no public accessor for its distributed client, whose key-value store and
barriers `jaxsleigh.files.distributed` uses to coordinate the processes of one run. It is read here, and
``tests/test_import.py`` fails when JAX moves it.
"""
from __future__ import annotations

__all__ = ["distributed_client"]


def distributed_client():
    """The client of ``jax.distributed`` in this process (``None`` before ``jax.distributed.initialize``):
    ``jax._src.distributed.global_state.client``."""
    from jax._src import distributed

    return distributed.global_state.client
