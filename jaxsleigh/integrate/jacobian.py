r"""Columns of a field's Jacobian by forward mode, as one batched product.

The linearly implicit step (`jaxsleigh.integrate.rosenbrock`) needs every column of
\(J = \partial f / \partial y\) and \(\partial f / \partial t\); the settled oscillation's guard
(`jaxsleigh.integrate.guard`) three of them. Written as one `jax.jvp` per direction, a traced program holds one copy
of the field's derivative per column (and its transpose per column under reverse mode); one `jax.linearize` pushed
through ``vmap`` over the unit directions holds one batched copy, and gives the same values (every operation of the
field is elementwise over the directions: the engine's runs and the golden runs are the same bytes).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["jacobian_columns"]


def jacobian_columns(f, t, y, rows=None, with_time=False):
    r"""The columns \(J e_j\), ``j`` in ``rows`` (default: every component), of the Jacobian of ``f(t, y)`` in ``y``
    at ``(t, y)``, ``y`` of shape ``(n,)`` or batch-last ``(n, N)``, and with ``with_time`` also
    \(\partial f / \partial t\): ``(dfdt or None, [J e_j, ...])``, every entry of ``y``'s shape."""
    t = jnp.asarray(t, y.dtype)
    rows = tuple(range(y.shape[0])) if rows is None else tuple(rows)
    _, lin = jax.linearize(f, t, y)
    dy = jnp.zeros((len(rows),) + y.shape, y.dtype)
    for i, j in enumerate(rows):
        dy = dy.at[i, j].set(1.0)
    dt = jnp.zeros((len(rows),) + t.shape, y.dtype)
    if with_time:
        dy = jnp.concatenate([jnp.zeros((1,) + y.shape, y.dtype), dy])
        dt = jnp.concatenate([jnp.ones((1,) + t.shape, y.dtype), dt])
    out = jax.vmap(lin)(dt, dy)
    cols = [out[i + with_time] for i in range(len(rows))]
    return (out[0] if with_time else None), cols
