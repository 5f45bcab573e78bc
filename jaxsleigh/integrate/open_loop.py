r"""The plant under a given input: fixed-step RK4 of the open loop with a piecewise-constant \(u(t)\).

The input is held constant on each of \(N\) equal intervals of \([0, T]\), \(u(t) = u_k\) for
\(t \in [k h, (k + 1) h)\), \(h = T / N\), and each interval is integrated with ``substeps`` classical RK4
steps of size \(h / \text{substeps}\). The steps never straddle a jump of \(u\), so RK4 keeps its fourth order
(a step across a jump would be first order). The energy of such an input is exact:
\(\int_0^T |u|^2\,dt = h \sum_k |u_k|^2\).

The vector field is the library's plant (`jaxsleigh.model.plant.open_loop`, paper eq. 1-2) with the
plant's own damping model; this is what `jaxsleigh.studies.optimum` differentiates through. Both functions
are for one trajectory: ``vmap`` them over starts and inputs and ``jit`` at the call site; ``T`` may be
traced (only ``N`` and ``substeps`` fix the program).
"""
from __future__ import annotations

import jax.numpy as jnp

from ..model.plant import open_loop
from .rk4 import rk4_intervals

__all__ = ["plant_field_u", "piecewise_constant_final", "piecewise_constant_path"]


def plant_field_u(t, y, args):
    """The plant's vector field ``f(t, y, (u, params))`` with ``y = (x, y, theta, p1, p2)`` and a held input ``u``."""
    del t
    u, params = args
    qdot, pdot = open_loop(y[:3], y[3:], u, params)
    return jnp.concatenate([qdot, pdot])


def _intervals(y0, u, T, params, substeps: int):
    """``(final, ys)`` of `rk4_intervals` with ``u`` held on each interval."""
    u = jnp.asarray(u, y0.dtype)
    dt = jnp.asarray(T, y0.dtype) / (u.shape[0] * substeps)
    return rk4_intervals(plant_field_u, y0, params, dt=dt, n_intervals=u.shape[0], substeps=substeps, inputs=u)


def piecewise_constant_final(y0, u, T, params, *, substeps: int):
    r"""State at \(T\) of the plant started at ``y0`` (5,) under the input ``u`` (N, 2) held on \(N\) equal
    intervals of \([0, T]\), ``substeps`` RK4 steps per interval."""
    return _intervals(y0, u, T, params, substeps)[0]


def piecewise_constant_path(y0, u, T, params, *, substeps: int):
    """The states at the interval ends, shape (N + 1, 5), ``y0`` first (same integration as
    `piecewise_constant_final`)."""
    _, ys = _intervals(y0, u, T, params, substeps)
    return jnp.concatenate([y0[None], ys])
