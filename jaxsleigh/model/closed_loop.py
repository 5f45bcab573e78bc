r"""The closed loop: the plant (eq. 1) driven by the control law (eq. 13), composed once.

Two charts of the same system, both as ``f(t, y, args)`` with ``args = ClosedLoop(plant, gains)``:

* `vector_field` in the physical state ``y = (x, y, theta, p1, p2)``;
* `vector_field_w` in ``y = (w1, w2, w3, p1, p2)``, the paper's eq. 15 chart. There the
  closed loop is port-Hamiltonian with \(H_d = \tfrac12 p^\top M^{-1} p + \tfrac12 w^\top L w\)
  and \(D_d = D + \hat D + D_i\) (eq. 15-16), so ``w`` stays in the bounded set
  \(H_d \le H_d(0)\) and the right-hand side needs no trigonometry. The ensemble engine
  integrates in this chart. Another energy-shaping law (`jaxsleigh.ShapedGains`) replaces
  \(\tfrac12 w^\top L w\) by its own potential \(V(w)\) here (`jaxsleigh.model.w_laws`).

Along either, \(\dot H_d = -\nabla_p H^\top D_d \nabla_p H \le 0\) (eq. 18).
"""
from __future__ import annotations

from typing import Any, NamedTuple

import jax.numpy as jnp

from .controller import apply_law
from .damping import BUILTIN_DAMPINGS
from .paper_law import control
from .w_laws import control_w_components, injection_components, potential
from .coordinates import Q_entries, Q_w_entries, q_to_w, w_to_q
from .smallmat import matvec
from .params import Gains, PlantParams
from .plant import hamiltonian, momentum_rhs, momentum_rhs_components, velocity, velocity_components

__all__ = [
    "ClosedLoop",
    "vector_field",
    "vector_field_w",
    "vector_field_w_control",
    "vector_field_w_components",
    "vector_field_law_control",
    "closed_loop_hamiltonian",
    "closed_loop_hamiltonian_w",
    "dissipation_w",
    "state_to_w",
    "state_from_w",
]


class ClosedLoop(NamedTuple):
    """``args`` of the closed-loop vector fields: the plant and the controller.

    ``controller`` is the paper's law (`Gains`) or any law ``u = law(q, v)``
    (`jaxsleigh.model.controller`); ``gains`` is the same field under the paper's name.
    """

    plant: PlantParams
    controller: Any

    @property
    def gains(self) -> Gains:
        return self.controller


def vector_field(t, y, args: ClosedLoop):
    """Closed loop in the physical state ``y = (x, y, theta, p1, p2)``.

    The controller sees only ``(q, qdot)``; the plant's own equations produce ``pdot``.
    """
    del t
    q, p = y[:3], y[3:]
    qdot = jnp.stack(matvec(Q_entries(q), velocity(p, args.plant)))
    u = control(q, qdot, args.gains)
    return jnp.concatenate([qdot, momentum_rhs(q, p, u, args.plant)])


def vector_field_w(t, y, args: ClosedLoop):
    """Closed loop in the chart ``y = (w1, w2, w3, p1, p2)`` (eq. 10 + eq. 13 = eq. 15).

    Written on components, so ``y`` may be one state (5,) or a batch-last array (5, N).
    """
    return vector_field_w_control(t, y, args)[0]


def vector_field_w_control(t, y, args: ClosedLoop):
    """`vector_field_w` and the control ``u`` (a tuple of two components) it applies: the
    observers of control effort read ``u`` without a second evaluation of the law."""
    del t
    ydot, u = vector_field_w_components(y, args)
    return jnp.stack(ydot).astype(y.dtype), u


def vector_field_w_components(y, args: ClosedLoop):
    r"""`vector_field_w_control` on components: ``y`` a sequence of the five components
    \((w_1, w_2, w_3, p_1, p_2)\) (scalars or batch-last arrays); returns the five components of
    \(\dot y\) (a tuple) and ``u``. It builds no array of them, so a kernel that holds each component
    on its own (`jaxsleigh.integrate.gpu_plain`) can call it. \(q\) (from `w_to_q`) is formed only for a
    damping model that reads it (the built-in ones do not)."""
    w, p = (y[0], y[1], y[2]), (y[3], y[4])
    v = velocity_components(p, args.plant)
    u = control_w_components(w, v, args.controller)
    q = None if isinstance(args.plant.damping, BUILTIN_DAMPINGS) else w_to_q(jnp.stack(w))
    wdot = matvec(Q_w_entries(w), v)
    pdot = momentum_rhs_components(q, p, u, args.plant)
    return wdot + pdot, u


def vector_field_law_control(t, y, args: ClosedLoop):
    """Closed loop of any law ``u = law(q, v)`` in the physical state ``y = (x, y, theta, p1, p2)``, and
    the control it applies (a tuple of two components). Written on components: ``y`` may be one
    state (5,) or a batch-last array (5, N) (the law is then vmapped over the batch)."""
    q, p = y[:3], (y[3], y[4])
    v = velocity_components(p, args.plant)
    qdot = matvec(Q_entries(q), v)
    u = apply_law(args.controller, q, jnp.stack(v), t)
    pdot = momentum_rhs_components(q, p, u, args.plant)
    return jnp.stack(qdot + pdot).astype(y.dtype), u


def closed_loop_hamiltonian(y, args: ClosedLoop):
    """\\(H_d(q, p) = \\tfrac12 p^\\top M^{-1} p + V(w(q))\\), \\(V = \\tfrac12 w^\\top L w\\) for the paper's law
    (eq. 15), the law's own potential for another w-chart law (`jaxsleigh.model.w_laws`)."""
    return hamiltonian(y[3:], args.plant) + potential(q_to_w(y[:3]), args.controller)


def closed_loop_hamiltonian_w(y, args: ClosedLoop):
    """\\(H_d\\) of a w-chart state ``(w, p)``."""
    return hamiltonian(y[3:], args.plant) + potential(y[:3], args.controller)


def dissipation_w(y, args: ClosedLoop):
    """\\(-\\nabla_p H^\\top D_d \\nabla_p H\\) (eq. 18), the exact value of \\(\\dot H_d\\)."""
    w, p = y[:3], y[3:]
    v = velocity_components(p, args.plant)
    d = args.plant.damping.force(w_to_q(w), p, v)
    inj = injection_components(w, v, args.controller)
    return -(v[0] * (d[0] + inj[0]) + v[1] * (d[1] + inj[1]))


def state_to_w(y):
    """``(q, p) -> (w, p)``."""
    return jnp.concatenate([q_to_w(y[:3]), y[3:]])


def state_from_w(y):
    """``(w, p) -> (q, p)``."""
    return jnp.concatenate([w_to_q(y[:3]), y[3:]])
