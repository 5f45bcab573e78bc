r"""Charts the engine integrates in: where a controller's state lives and what the stepper checks there.

A chart is a small static object (hashable: part of the compiled program) that tells the stepper

* ``field_and_control(t, y, args)``: the closed-loop vector field in the chart and the control it applies;
* ``energy(y, args)``: a function that never increases along the exact flow (the passivity monitor), or
  ``has_energy = False``;
* ``singular``: whether the law has a singular set the flow never crosses (then a step that crosses it is
  rejected, and starts on it are flagged);
* ``q_norm2(y)``, ``abs_theta(y)``: \(|q|^2\) and \(|\theta|\) of a chart state (for the observers);
* ``to_chart`` / ``from_chart``: the physical state ``(x, y, theta, p1, p2)`` to and from the chart.

`WChart` is the paper's law, or another energy-shaping law of `jaxsleigh.model.w_laws`, in its w chart (eq. 15:
port-Hamiltonian, \(H_d\) non-increasing, no trigonometry, the singular set \(w_1 = \theta = 0\));
`PhysicalChart` is any other law ``u = law(q, v)``
in the physical state; with ``heading_modulo=True`` it measures the heading modulo \(2\pi\) (for a law that steers
\(\theta\) to 0 modulo \(2\pi\), e.g. `jaxsleigh.controllers.aicardi.AicardiLaw`). `chart_for` picks the chart of a
controller.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import math

import jax.numpy as jnp

from .closed_loop import (closed_loop_hamiltonian_w, state_from_w, state_to_w, vector_field_law_control,
                          vector_field_w_control)
from .coordinates import f_w_inv
from .w_laws import is_w_law, stiff_coeff, w2_stiffness

__all__ = ["WChart", "PhysicalChart", "chart_for", "q_norm2_w", "heading_mod_2pi", "physical_chart_for"]


def heading_mod_2pi(theta):
    r"""\(\theta - 2\pi\,\mathrm{round}(\theta / 2\pi) \in [-\pi, \pi]\): the heading's distance to the nearest
    multiple of \(2\pi\), signed (derivative 1 away from odd multiples of \(\pi\))."""
    two_pi = 2.0 * math.pi
    return theta - two_pi * jnp.round(theta / two_pi)


def q_norm2_w(w):
    """\\(|q|^2\\) from ``w`` without trigonometry: \\(f_z\\) only rotates (x, y), so
    \\(|q| = |z| = |f_w^{-1}(w)|\\)."""
    z = f_w_inv(w)
    return z[0] * z[0] + z[1] * z[1] + z[2] * z[2]


@dataclass(frozen=True)
class WChart:
    """A w-chart law (the paper's eq. 13, or `jaxsleigh.model.shaped_law.ShapedGains`) in the chart
    ``y = (w1, w2, w3, p1, p2)`` (eq. 15)."""

    name: ClassVar[str] = "w"
    singular: ClassVar[bool] = True
    has_energy: ClassVar[bool] = True

    def field_and_control(self, t, y, args):
        return vector_field_w_control(t, y, args)

    def field(self, t, y, args):
        return vector_field_w_control(t, y, args)[0]

    def energy(self, y, args):
        return closed_loop_hamiltonian_w(y, args)

    def q_norm2(self, y):
        return q_norm2_w(y[:3])

    def abs_theta(self, y):
        return jnp.abs(y[0])

    def crossed(self, y, y_new):
        return jnp.sign(y_new[0]) != jnp.sign(y[0])

    def stiff_rate(self, y, args):
        """The rate \\(\\lambda = -(\\hat D_{22} + k / w_1^2) / (J + m l^2) \\le 0\\) of the linear term
        \\(\\lambda p_2\\) of the \\(p_2\\) equation that the injected damping puts there (stiff near
        \\(\\theta = 0\\); `jaxsleigh.integrate.etd`), or ``None`` for a law without the paper's ``k`` and
        ``D_hat``."""
        pl = args.plant
        c = stiff_coeff((y[0], y[1], y[2]), args.controller)
        if c is None:
            return None
        lam = -c / (pl.J + pl.m * pl.l * pl.l)
        return jnp.minimum(lam, 0.0).astype(y.dtype)

    def oscillation(self, y, args):
        r"""The coefficients \((a, b)\) of the linear pair \(\dot w_2 = a p_1 + \ldots\),
        \(\dot p_1 = -b w_2 + \ldots\): \(a = 1 / (m w_1)\), \(b = V_{22} / w_1\) (`w2_stiffness`), an
        oscillation of frequency \(\sqrt{ab} = \sqrt{V_{22} / m} / |w_1|\), stiff near \(\theta = 0\)
        (`jaxsleigh.integrate.etd`); ``None`` for a law that does not give \(V_{22}\)."""
        v22 = w2_stiffness((y[0], y[1], y[2]), args.controller)
        if v22 is None:
            return None
        inv = 1.0 / y[0]
        return (inv / args.plant.m).astype(y.dtype), (inv * v22).astype(y.dtype)

    def to_chart(self, y):
        return state_to_w(y)

    def from_chart(self, y):
        return state_from_w(y)


@dataclass(frozen=True)
class PhysicalChart:
    r"""Any law ``u = law(q, v)`` in the physical state ``y = (x, y, theta, p1, p2)``: no singular set, no
    known non-increasing energy (the passivity monitor is off).

    ``heading_modulo``: measure the heading modulo \(2\pi\) in \(|q|\) and \(|\theta|\) (`heading_mod_2pi`), so
    that \(T_\epsilon\) counts a start that reaches the goal with \(\theta = \pm 2\pi\) (the same physical pose) as
    settled. For a law that sees the heading only through wrapped angles and so steers it to 0 modulo \(2\pi\); a
    law declares it with the class attribute ``chart = PhysicalChart(heading_modulo=True)``. The state itself (and
    ``q_final``) keeps \(\theta\) as integrated."""

    heading_modulo: bool = False

    name: ClassVar[str] = "q"
    singular: ClassVar[bool] = False
    has_energy: ClassVar[bool] = False

    def field_and_control(self, t, y, args):
        return vector_field_law_control(t, y, args)

    def field(self, t, y, args):
        return vector_field_law_control(t, y, args)[0]

    def energy(self, y, args):
        return jnp.zeros(y.shape[1:], y.dtype)

    def heading(self, y):
        r"""\(\theta\) as the chart measures it: modulo \(2\pi\) with ``heading_modulo``, else as integrated."""
        return heading_mod_2pi(y[2]) if self.heading_modulo else y[2]

    def q_norm2(self, y):
        th = self.heading(y)
        return y[0] * y[0] + y[1] * y[1] + th * th

    def abs_theta(self, y):
        return jnp.abs(self.heading(y))

    def crossed(self, y, y_new):
        return jnp.zeros(y.shape[1:], bool)

    def stiff_rate(self, y, args):
        return None                      # no injected k / theta^2 damping: classical RK4

    def oscillation(self, y, args):
        return None

    def to_chart(self, y):
        return y

    def from_chart(self, y):
        return y


def chart_for(controller):
    """The chart a controller is integrated in: its own ``chart`` attribute if it declares one, the w chart
    for a w-chart law (`jaxsleigh.model.w_laws`: the paper's `jaxsleigh.Gains`, `ShapedGains`), else the physical chart.
    An actuator piece that holds its law in a field ``law`` (saturation, sampling) is in the physical chart with the
    heading convention of the law it wraps."""
    declared = getattr(type(controller), "chart", None)
    if declared is not None:
        return declared
    if is_w_law(controller):
        return WChart()
    inner = getattr(controller, "law", None)
    if inner is not None:
        wrapped = chart_for(inner)
        if isinstance(wrapped, PhysicalChart):
            return wrapped
    return PhysicalChart()


def physical_chart_for(controller) -> PhysicalChart:
    """The physical chart with ``controller``'s heading convention, for a loop that runs in the physical state
    whatever chart the law would have in the adaptive engine (the sampled-data loop)."""
    chart = chart_for(controller)
    return chart if isinstance(chart, PhysicalChart) else PhysicalChart()
