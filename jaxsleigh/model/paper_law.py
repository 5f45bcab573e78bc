r"""The discontinuous energy-shaping control law (paper eq. 13).

\[ u = -Q_w^\top(w) L w - \hat D \nabla_p H - D_i(w) \nabla_p H, \qquad D_i(w) = \mathrm{diag}(0,\ k / w_1^2) \]

with \(Q_w\) as *derived* in `jaxsleigh.model.coordinates` (the printed eq. 11 is wrong).

The controller only measures the configuration and its rate (paper Remark 1): from
\(\dot q = Q(q) \nabla_p H\) and \(Q^\top Q = I\), \(\nabla_p H = Q(q)^\top \dot q\),
which is Remark 1's \([[z_3, 1], [1, 0]]\,(\dot z_1, \dot z_2)\) written in q. It never reads
the plant's mass matrix or damping.

``gains`` below is a `jaxsleigh.Gains` (fields ``L``, ``k``, ``D_hat``), whose methods call these functions (the
law interface); this module does not import it, so that `jaxsleigh.model.params` can.
"""
from __future__ import annotations

import jax.numpy as jnp

from .coordinates import Q_entries, Q_w_entries, q_to_w
from .smallmat import rmatvec

__all__ = ["potential", "measured_velocity", "damping_injection", "damping_injection_components", "control_w",
           "control_w_components", "control"]


def potential(w, gains):
    """Shaped potential \\(\\tfrac12 w^\\top L w\\) (the second term of \\(H_d\\), eq. 15)."""
    return 0.5 * (gains.L[0] * w[0] ** 2 + gains.L[1] * w[1] ** 2 + gains.L[2] * w[2] ** 2).astype(w.dtype)


def measured_velocity(q, qdot):
    """\\(\\nabla_p H = Q(q)^\\top \\dot q\\) from measurements only (Remark 1, eq. 14)."""
    return jnp.stack(rmatvec(Q_entries(q), qdot))


def damping_injection_components(w, v, gains):
    """\\((\\hat D + D_i(w)) v\\) with \\(D_i = \\mathrm{diag}(0, k / w_1^2)\\) (eq. 13), as a tuple."""
    D = gains.D_hat
    # D_i only acts on the turning rate; k / w1^2 is what keeps theta away from 0 (Lemma 2).
    return (D[0, 0] * v[0] + D[0, 1] * v[1],
            D[1, 0] * v[0] + (D[1, 1] + gains.k / (w[0] * w[0])) * v[1])


def damping_injection(w, v, gains):
    """\\((\\hat D + D_i(w)) v\\) as an array."""
    return jnp.stack(damping_injection_components(w, v, gains)).astype(v.dtype)


def control_w_components(w, v, gains):
    """Control law (eq. 13) on sequences of components (one trajectory or batch-last arrays)."""
    L = gains.L
    force = rmatvec(Q_w_entries(w), (L[0] * w[0], L[1] * w[1], L[2] * w[2]))
    inj = damping_injection_components(w, v, gains)
    return (-force[0] - inj[0], -force[1] - inj[1])


def control_w(w, v, gains):
    """Control law (eq. 13) from the w coordinates and \\(v = \\nabla_p H\\)."""
    return jnp.stack(control_w_components(w, v, gains)).astype(w.dtype)


def control(q, qdot, gains):
    """Control law (eq. 13) as the controller computes it, from measured \\((q, \\dot q)\\)."""
    return control_w(q_to_w(q), measured_velocity(q, qdot), gains)
