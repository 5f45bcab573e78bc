"""Open-loop damping models ``D(q, p)`` of the plant (paper eq. 1, Sec. 5).

Each model is a small frozen pytree whose numeric fields are leaves (so ``grad`` and ``vmap``
work over them) and whose *kind* is its Python class (a static choice). Every model exposes

``matrix(q, p) -> (2, 2)``: the symmetric positive semi-definite damping matrix ``D(q, p)``;
``force(q, p, v) -> tuple``: the components of ``D(q, p) v``, with ``p`` and ``v`` given as
sequences of two components (arrays of any common shape: one trajectory or a batch). Written
out for the diagonal models, which is much faster on CPU than a small matrix product.

The controller never reads these (paper Remark 2); only the simulated plant does.
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

__all__ = [
    "CoulombDamping",
    "ViscousDamping",
    "NoDamping",
    "CustomDamping",
    "BUILTIN_DAMPINGS",
    "damping_from_name",
    "as_damping",
]


class CoulombDamping(NamedTuple):
    r"""Smoothed Coulomb friction of the paper's simulation (Sec. 5).

    \[ D(p) = c\,\mathrm{diag}\big(1/\sqrt{\epsilon + p_1^2},\ 1/\sqrt{\epsilon + p_2^2}\big) \]

    The paper uses (eq. 31) \(\epsilon = 0.1\), \(c = 1\).
    """

    eps: float = 0.1
    scale: float = 1.0

    def matrix(self, q, p):
        del q
        return jnp.diag(self.scale * jax.lax.rsqrt(self.eps + p * p))

    def force(self, q, p, v):
        del q
        return tuple(self.scale * jax.lax.rsqrt(self.eps + pi * pi) * vi for pi, vi in zip(p, v))


class ViscousDamping(NamedTuple):
    r"""Linear viscous friction \(D = \mathrm{diag}(c_1, c_2)\)."""

    c1: float = 1.0
    c2: float = 1.0

    def matrix(self, q, p):
        del q
        return jnp.diag(jnp.stack([jnp.asarray(self.c1), jnp.asarray(self.c2)]).astype(p.dtype))

    def force(self, q, p, v):
        del q, p
        return (self.c1 * v[0], self.c2 * v[1])


class NoDamping(NamedTuple):
    """No open-loop damping, \\(D = 0\\) (with ``u = 0`` the plant then conserves ``H``)."""

    def matrix(self, q, p):
        del q
        return jnp.zeros((2, 2), p.dtype)

    def force(self, q, p, v):
        del q, p
        return (jnp.zeros_like(v[0]), jnp.zeros_like(v[1]))


@jax.tree_util.register_pytree_node_class
class CustomDamping:
    """A user's damping ``fn(q, p) -> (2, 2)`` array; ``fn`` is static (part of the tree structure).

    ``fn`` must be a pure JAX function returning a symmetric positive semi-definite matrix;
    otherwise the closed-loop Hamiltonian can increase. Use a module-level function (not a fresh
    lambda per call) so that jitted simulations are not recompiled.
    """

    def __init__(self, fn: Callable):
        if not callable(fn):
            raise TypeError(f"CustomDamping needs a callable fn(q, p) -> (2, 2) array, got {fn!r}")
        self.fn = fn

    def matrix(self, q, p):
        return jnp.asarray(self.fn(q, p), p.dtype)

    def force(self, q, p, v):
        p, v = jnp.stack(list(p)), jnp.stack(list(v))
        if p.ndim == 1:
            return tuple(self.matrix(q, p) @ v)
        # batch-last components: apply per trajectory
        out = jax.vmap(lambda qq, pp, vv: self.matrix(qq, pp) @ vv, in_axes=-1, out_axes=-1)(q, p, v)
        return (out[0], out[1])

    def tree_flatten(self):
        return (), self.fn

    @classmethod
    def tree_unflatten(cls, fn, children):
        del children
        return cls(fn)

    def __eq__(self, other):
        return isinstance(other, CustomDamping) and other.fn is self.fn

    def __hash__(self):
        return hash(self.fn)

    def __repr__(self):
        return f"CustomDamping({getattr(self.fn, '__name__', self.fn)!r})"


#: the built-in models: elementwise in (p, v), none of them reads q (a `CustomDamping` may)
BUILTIN_DAMPINGS = (CoulombDamping, ViscousDamping, NoDamping)


def damping_from_name(name: str):
    """``'coulomb'`` (the paper's), ``'viscous'`` or ``'none'`` -> a damping model with defaults."""
    table = {"coulomb": CoulombDamping(), "viscous": ViscousDamping(), "none": NoDamping()}
    try:
        return table[name]
    except KeyError:
        raise ValueError(f"unknown damping {name!r}: choose one of {sorted(table)}") from None


def as_damping(d):
    """A damping model from a model (as it is), a name (`damping_from_name`) or a callable ``D(q, p) -> (2, 2)``
    (wrapped in `CustomDamping`); ``ValueError`` for anything else."""
    if isinstance(d, str):
        return damping_from_name(d)
    if isinstance(d, (*BUILTIN_DAMPINGS, CustomDamping)):
        return d
    if callable(d):
        return CustomDamping(d)
    raise ValueError(f"damping must be a damping model, a name or a callable, got {d!r}")
