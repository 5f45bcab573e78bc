r"""Gradients of the objective through the integrator: reverse mode over checkpointed segments of the
scan, or forward mode (``jax.jacfwd``, one tangent per free parameter; the default for the <= 7 gain
parameters, see the package docstring for the measurements).
"""
from __future__ import annotations

import functools

import jax
from jax.flatten_util import ravel_pytree

from .objective import objective
from .params import D_FLOOR

__all__ = ["GRADIENT_MODES", "make_value_and_grad"]

GRADIENT_MODES = ("reverse", "forward")


def make_value_and_grad(*, mode: str = "forward", n_attempts: int, segment: int = 100, adaptive: bool = True,
                        d_floor: float = D_FLOOR):
    """A jitted ``f(trainable, frozen, data, cfg) -> ((loss, aux), grad)`` of `objective`.

    ``mode="reverse"``: ``jax.value_and_grad`` through the checkpointed scan;
    ``mode="forward"``: ``jax.jacfwd`` over the flattened trainable parameters (one tangent each).
    The same settings return the same (cached) function, whether a default is given or left out, so a second tuning
    run with the same shapes does not recompile.
    """
    if mode not in GRADIENT_MODES:
        raise ValueError(f"mode must be one of {GRADIENT_MODES}, got {mode!r}")
    return _value_and_grad(mode, int(n_attempts), int(segment), bool(adaptive), float(d_floor))


@functools.lru_cache(maxsize=32)
def _value_and_grad(mode: str, n_attempts: int, segment: int, adaptive: bool, d_floor: float):
    """`make_value_and_grad` for settings in one normal form (the cache's key)."""
    loss = functools.partial(objective, n_attempts=n_attempts, segment=segment, adaptive=adaptive, d_floor=d_floor)
    if mode == "reverse":
        return jax.jit(jax.value_and_grad(loss, has_aux=True))

    def forward(trainable, frozen, data, cfg):
        flat, unravel = ravel_pytree(trainable)

        def f(v):
            value, aux = loss(unravel(v), frozen, data, cfg)
            return value, (value, aux)

        jac, (value, aux) = jax.jacfwd(f, has_aux=True)(flat)
        return (value, aux), unravel(jac)

    return jax.jit(forward)
