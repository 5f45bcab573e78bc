r"""The discontinuous energy-shaping control law (paper eq. 13).

.. math::
    u = -Q_w^\top(w) L w - \hat D \nabla_p H - D_i(w) \nabla_p H, \qquad
    D_i(w) = \mathrm{diag}(0,\ k / w_1^2)

with :math:`Q_w` as *derived* in :mod:`jaxsleigh.coordinates` (the printed eq. 11 is wrong).

The controller only measures the configuration and its rate (paper Remark 1): from
:math:`\dot q = Q(q) \nabla_p H` and :math:`Q^\top Q = I`, :math:`\nabla_p H = Q(q)^\top \dot q`,
which is Remark 1's :math:`[[z_3, 1], [1, 0]]\,(\dot z_1, \dot z_2)` written in q. It never reads
the plant's mass matrix or damping.
"""
from __future__ import annotations

import jax.numpy as jnp

from .coordinates import Q, Q_w, q_to_w
from .params import Gains

__all__ = ["potential", "measured_velocity", "control_w", "control"]


def potential(w, gains: Gains):
    """Shaped potential :math:`\\tfrac12 w^\\top L w` (the second term of :math:`H_d`, eq. 15)."""
    return 0.5 * jnp.sum(jnp.asarray(gains.L, w.dtype) * w * w)


def measured_velocity(q, qdot):
    """:math:`\\nabla_p H = Q(q)^\\top \\dot q` from measurements only (Remark 1, eq. 14)."""
    return Q(q).T @ qdot


def control_w(w, v, gains: Gains):
    """Control law (eq. 13) from the w coordinates and :math:`v = \\nabla_p H`."""
    L = jnp.asarray(gains.L, w.dtype)
    D_hat = jnp.asarray(gains.D_hat, w.dtype)
    k = jnp.asarray(gains.k, w.dtype)
    # D_i only acts on the turning rate; k / w1^2 is what keeps theta away from 0 (Lemma 2).
    d_i = jnp.stack([jnp.zeros_like(w[0]), k / (w[0] * w[0])])
    return -(Q_w(w).T @ (L * w)) - D_hat @ v - d_i * v


def control(q, qdot, gains: Gains):
    """Control law (eq. 13) as the controller computes it, from measured :math:`(q, \\dot q)`."""
    return control_w(q_to_w(q), measured_velocity(q, qdot), gains)
