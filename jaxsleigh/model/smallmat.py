"""Small matrices as nested tuples of entries, applied without building arrays.

XLA on CPU runs ``(3, 2) @ (2,)`` products of stacked arrays many times slower than the same
arithmetic written out, and cannot drop multiplications by structural zeros (``0 * nan`` is
``nan``). Each matrix of the paper is therefore defined once as a tuple of rows whose entries are
arrays or the Python literals ``0``/``1``; `as_array` builds the matrix (for tests and
display), `matvec` and `rmatvec` apply it, skipping the literals.
"""
from __future__ import annotations

import jax.numpy as jnp

__all__ = ["as_array", "matvec", "rmatvec"]


def _scaled(e, x):
    if isinstance(e, (int, float)) and not isinstance(e, bool):
        if e == 0:
            return None
        if e == 1:
            return x
    return e * x


def _sum(terms, like):
    terms = [t for t in terms if t is not None]
    if not terms:
        return jnp.zeros_like(like)
    out = terms[0]
    for t in terms[1:]:
        out = out + t
    return out


def as_array(rows, like):
    """The matrix as an array (entries broadcast to the shape/dtype of ``like``)."""
    z = jnp.zeros_like(like)
    return jnp.stack([jnp.stack([z + e for e in row]) for row in rows])


def matvec(rows, x):
    """``A @ x`` for ``A`` given by rows of entries and ``x`` a sequence of components; returns a tuple."""
    return tuple(_sum([_scaled(e, xj) for e, xj in zip(row, x)], x[0]) for row in rows)


def rmatvec(rows, x):
    """``A.T @ x``; returns a tuple."""
    cols = list(zip(*rows))
    return tuple(_sum([_scaled(e, xi) for e, xi in zip(col, x)], x[0]) for col in cols)
