r"""The Chaplygin sleigh plant in port-Hamiltonian form (paper eq. 1-2).

\[ \dot q = Q(q) \nabla_p H, \qquad \dot p = -Q^\top(q) \nabla_q H + (J(p) - D(q, p)) \nabla_p H + u, \qquad H = \tfrac12 p^\top M^{-1} p \]

Since \(H\) does not depend on \(q\), \(\nabla_q H = 0\). The state of one trajectory
is ``y = (x, y, theta, p1, p2)``; \(\nabla_p H = M^{-1} p = (v, \omega)\) is the forward speed
and the turning rate.
"""
from __future__ import annotations

import jax.numpy as jnp

from .coordinates import Q_entries
from .params import PlantParams
from .smallmat import as_array, matvec

__all__ = [
    "mass_matrix",
    "inverse_mass",
    "hamiltonian",
    "velocity",
    "gyroscopic",
    "gyroscopic_entries",
    "momentum_rhs",
    "momentum_rhs_components",
    "velocity_components",
    "open_loop",
    "open_loop_field",
]


def mass_matrix(params: PlantParams):
    """\\(M = \\mathrm{diag}(m, J + m l^2)\\) (eq. 2)."""
    return jnp.diag(inverse_mass(params) ** -1)


def inverse_mass(params: PlantParams):
    """Diagonal of \\(M^{-1}\\), shape (2,)."""
    m, J, l = params.m, params.J, params.l
    return 1.0 / jnp.stack([jnp.asarray(m), jnp.asarray(J + m * l * l)])


def velocity_components(p, params: PlantParams):
    """\\((v, \\omega) = M^{-1} p\\) as a tuple of components (``p`` a sequence of two)."""
    m, J, l = params.m, params.J, params.l
    return (p[0] / m, p[1] / (J + m * l * l))


def velocity(p, params: PlantParams):
    """\\(\\nabla_p H = M^{-1} p = (v, \\omega)\\)."""
    return jnp.stack(velocity_components(p, params)).astype(p.dtype)


def hamiltonian(p, params: PlantParams):
    """Kinetic energy \\(H = \\tfrac12 p^\\top M^{-1} p\\) (eq. 1)."""
    v = velocity_components(p, params)
    return 0.5 * (p[0] * v[0] + p[1] * v[1])


def gyroscopic_entries(p, params: PlantParams):
    """Rows of \\(J(p)\\) (eq. 2): \\(\\frac{m l}{J + m l^2} p_2 [[0, 1], [-1, 0]]\\)."""
    m, J, l = params.m, params.J, params.l
    a = (m * l / (J + m * l * l)) * p[1]
    return ((0, a), (-a, 0))


def gyroscopic(p, params: PlantParams):
    """\\(J(p)\\), skew-symmetric (eq. 2)."""
    return as_array(gyroscopic_entries(p, params), p[1])


def momentum_rhs_components(q, p, u, params: PlantParams):
    """`momentum_rhs` on sequences of components (one trajectory or batch-last arrays)."""
    v = velocity_components(p, params)
    gyro = matvec(gyroscopic_entries(p, params), v)
    damp = params.damping.force(q, p, v)
    return tuple(g - d + ui for g, d, ui in zip(gyro, damp, u))


def momentum_rhs(q, p, u, params: PlantParams):
    """\\(\\dot p = (J(p) - D(q, p)) \\nabla_p H + u\\) (eq. 1 with \\(\\nabla_q H = 0\\)).

    ``q`` is only passed on to the damping model (the built-in ones ignore it).
    """
    return jnp.stack(momentum_rhs_components(q, p, u, params)).astype(p.dtype)


def open_loop(q, p, u, params: PlantParams):
    """Plant vector field ``(qdot, pdot)`` for a given input ``u`` (eq. 1)."""
    return jnp.stack(matvec(Q_entries(q), velocity(p, params))), momentum_rhs(q, p, u, params)


def open_loop_field(t, y, params: PlantParams):
    """Uncontrolled plant (``u = 0``) as ``f(t, y, args)`` with ``y = (x, y, theta, p1, p2)``."""
    del t
    q, p = y[:3], y[3:]
    qdot, pdot = open_loop(q, p, jnp.zeros_like(p), params)
    return jnp.concatenate([qdot, pdot])
