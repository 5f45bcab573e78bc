r"""Observers of the step: on-line summaries of a trajectory, as pluggable pieces.

The stepper (`jaxsleigh.integrate.stepper`) carries, next to the state, one small state per observer and
updates it after every attempted step (only accepted steps count). An observer may also ask for
*quadrature* rows: integrands \(g(y, u)\) that the stepper integrates with the step's own RK4
weights, \(Q_{n+1} = Q_n + \tfrac{h}{6}(g_1 + 2 g_2 + 2 g_3 + g_4)\) over the stage states, i.e.
to the integrator's fourth order (not a post-hoc sum of saved samples).

An observer is a frozen dataclass (hashable: it is a static argument of the jitted stepper; subclass `Observer`
for the defaults below) with

* ``fields``: the names of its results;
* ``n_quad``: how many quadrature rows it needs; ``needs_control``: whether it reads ``u``; ``needs_dense``:
  whether it reads the step's dense output (`hermite`, which needs the derivative at the step's end);
* ``init(t0, y, u, ctl, chart)`` -> tuple of arrays (its state at the start; ``chart``, from
  `jaxsleigh.model.charts`, gives \\(|q|^2\\) and \\(|\\theta|\\) of a state in the chart it is integrated in);
* ``update(state, step, ctl)`` -> state after an attempted step; ``step`` is a `StepInfo`
  (``acc``: the mask of trajectories whose step was accepted; the state, its derivative and the
  control before and after; the step's start time and size, for the step's dense output; the chart);
* ``integrand(y, u)`` -> tuple of ``n_quad`` arrays;
* ``values(state, quad)`` -> dict of JAX arrays (traced: what `jaxsleigh.integrate.solve` returns and differentiates);
* ``results(state, quad)`` -> dict of host NumPy arrays (batch axis first).

Every array broadcasts over a trailing batch axis (``y`` is (5,) or (5, N)). The built-ins:
`ConvergenceTime` (``T_eps``), `ClosestApproach` (``min_abs_theta``),
`Excursion` (``max_excursion``), `ControlEffort` (``u_peak``, ``u_norm_peak``,
``u_energy``, ``u_abs_int``). `DEFAULT_OBSERVERS` are on in every ensemble and simulation.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["StepInfo", "hermite", "Observer", "ConvergenceTime", "ClosestApproach", "Excursion", "ControlEffort",
           "DEFAULT_OBSERVERS",
           "observer_fields", "collect", "collect_values"]


class StepInfo(NamedTuple):
    """What an observer sees of one attempted step (every field broadcasts over the batch)."""

    t: jax.Array          # start of the step
    h: jax.Array          # its size (0 where a lane idles)
    t_new: jax.Array      # its end, compensated (t + h up to rounding)
    y: jax.Array          # (5,) state at the start
    y_new: jax.Array      # (5,) state at the end
    k1: jax.Array         # (5,) f(t, y)
    k5: jax.Array         # (5,) f(t + h, y_new); None without FSAL
    u_new: tuple          # control (u1, u2) at y_new; None if no observer needs it
    acc: jax.Array        # bool: the step was accepted
    chart: object = None  # the chart of the state (jaxsleigh.model.charts): |q|^2 and |theta| of a state


def hermite(step: StepInfo, theta, rows=slice(0, 3)):
    r"""The step's dense output: the cubic Hermite interpolant through ``(y, k1)`` and
    ``(y_new, k5)`` at the fraction ``theta`` of the step (rows ``rows``, default ``w``). RK4 with
    these end-point derivatives is third-order accurate in between (the classical RK4 dense output
    of Hairer, Norsett & Wanner, II.6)."""
    t2, t3 = theta * theta, theta * theta * theta
    h00, h10, h01, h11 = 2 * t3 - 3 * t2 + 1, t3 - 2 * t2 + theta, 3 * t2 - 2 * t3, t3 - t2
    y0, y1, f0, f1 = step.y[rows], step.y_new[rows], step.k1[rows], step.k5[rows]
    return h00 * y0 + h01 * y1 + step.h * (h10 * f0 + h11 * f1)


def _np(a) -> np.ndarray:
    return np.array(np.moveaxis(np.asarray(a, np.float64), -1, 0) if np.ndim(a) > 1 else np.asarray(a, np.float64))


@dataclass(frozen=True)
class Observer:
    """What an observer that does not say otherwise is (subclass it, as the built-ins do): no quadrature rows, no
    control read, no dense output, so no integrand; ``fields``, ``init``, ``update``, ``values`` and ``results`` are
    its own."""

    fields: ClassVar[tuple] = ()
    n_quad: ClassVar[int] = 0
    needs_control: ClassVar[bool] = False
    needs_dense: ClassVar[bool] = False

    def integrand(self, y, u):
        return ()


@dataclass(frozen=True)
class ConvergenceTime(Observer):
    r"""``T_eps``: the start of the last stay in the ball \(|q| \le \epsilon\) (``ctl.eps``), i.e.
    the first time after which the trajectory stays inside (``inf`` while it is outside).

    Located inside each step on the step's dense output (`hermite`): ``samples`` points per
    step tell whether the trajectory left the ball during the step, and ``bisections`` halvings
    locate the last entry, to ``h / (samples 2^bisections)``. So ``T_eps`` keeps its resolution
    however long the steps grow.
    """

    samples: int = 4
    bisections: int = 12

    fields: ClassVar[tuple] = ("T_eps",)
    needs_dense: ClassVar[bool] = True

    def init(self, t0, y, u, ctl, chart):
        inside = chart.q_norm2(y) <= ctl.eps * ctl.eps
        return (jnp.where(inside, t0, jnp.inf).astype(y.dtype),)

    def entry(self, step, ctl):
        """``(inside_end, entered, fraction)``: whether the step ends in the ball, whether the trajectory was
        outside it at some sample of the step, and the fraction of the step at which it last entered."""
        dtype = step.y.dtype
        eps2 = ctl.eps * ctl.eps
        q_norm2 = step.chart.q_norm2
        outside = lambda th: q_norm2(hermite(step, th)) > eps2  # noqa: E731
        inside_end = q_norm2(step.y_new) <= eps2
        # the last sample point (theta = j / samples, j < samples) outside the ball; -1 if none
        last_out = jnp.full(inside_end.shape, -1, jnp.int32)
        for j in range(self.samples):
            th = jnp.asarray(j / self.samples, dtype)
            out_j = (q_norm2(step.y) > eps2) if j == 0 else outside(th)
            last_out = jnp.where(out_j, j, last_out)
        # bisect between that point (outside) and the next one (inside, or the end) for the entry
        lo = last_out.astype(dtype) / self.samples
        hi = jnp.minimum(lo + 1.0 / self.samples, 1.0)

        def bisect(_, bracket):
            lo, hi = bracket
            mid = 0.5 * (lo + hi)
            o = outside(mid)
            return jnp.where(o, mid, lo), jnp.where(o, hi, mid)

        # a loop, not unrolled: the step's program stays small (compile time) for any count
        lo, hi = jax.lax.fori_loop(0, self.bisections, bisect, (lo, hi))
        return inside_end, last_out >= 0, hi

    def update(self, state, step, ctl):
        (t_enter,) = state
        inside_end, entered, hi = self.entry(step, ctl)
        entry = jnp.where(hi >= 1.0, step.t_new, step.t + hi * step.h).astype(t_enter.dtype)
        new = jnp.where(inside_end, jnp.where(entered, entry, t_enter), jnp.inf)
        return (jnp.where(step.acc, new, t_enter).astype(t_enter.dtype),)

    def values(self, state, quad):
        return {"T_eps": state[0]}

    def results(self, state, quad):
        return {"T_eps": _np(state[0])}


@dataclass(frozen=True)
class ClosestApproach(Observer):
    r"""``min_abs_theta``: \(\min_t |\theta(t)|\) over the accepted steps (the singular set)."""

    fields: ClassVar[tuple] = ("min_abs_theta",)

    def init(self, t0, y, u, ctl, chart):
        return (chart.abs_theta(y),)

    def update(self, state, step, ctl):
        return (jnp.where(step.acc, jnp.minimum(state[0], step.chart.abs_theta(step.y_new)), state[0]),)

    def values(self, state, quad):
        return {"min_abs_theta": state[0]}

    def results(self, state, quad):
        return {"min_abs_theta": _np(state[0])}


@dataclass(frozen=True)
class Excursion(Observer):
    r"""``max_excursion``: \(\max_t |q(t)|\) over the accepted steps."""

    fields: ClassVar[tuple] = ("max_excursion",)

    def init(self, t0, y, u, ctl, chart):
        return (chart.q_norm2(y),)

    def update(self, state, step, ctl):
        return (jnp.where(step.acc, jnp.maximum(state[0], step.chart.q_norm2(step.y_new)), state[0]),)

    def values(self, state, quad):
        return {"max_excursion": jnp.sqrt(state[0])}

    def results(self, state, quad):
        return {"max_excursion": np.sqrt(_np(state[0]))}


def _sqrt0(e):
    """\\(\\sqrt{e}\\) of ``e >= 0`` with derivative 0 at ``e = 0`` (a double ``jnp.where``): a law whose force is
    exactly 0 (one at rest at its goal) would otherwise put \\(0 \\cdot \\infty\\) = NaN into a reverse-mode gradient
    through the step loop, where zero cotangents are numbers, not symbols."""
    pos = e > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, e, jnp.ones_like(e))), jnp.zeros_like(e))


@dataclass(frozen=True)
class ControlEffort(Observer):
    r"""Control effort over the horizon, in the paper's units (``u`` is a generalised force: the
    forward force in N and the turning moment in N m):

    * ``u_peak`` (N, 2): \(\max_t |u_i(t)|\) per component, ``u_norm_peak``:
      \(\max_t \|u(t)\|\), both over the accepted steps' end points and the start;
    * ``u_energy``: \(\int_0^T \|u\|^2 dt\) and ``u_abs_int``: \(\int_0^T \|u\| dt\),
      quadrature rows integrated with the step's RK4 weights (fourth order).
    """

    fields: ClassVar[tuple] = ("u_peak", "u_norm_peak", "u_energy", "u_abs_int")
    n_quad: ClassVar[int] = 2
    needs_control: ClassVar[bool] = True

    def init(self, t0, y, u, ctl, chart):
        return (jnp.abs(u[0]), jnp.abs(u[1]), _sqrt0(u[0] * u[0] + u[1] * u[1]))

    def update(self, state, step, ctl):
        new = self.init(step.t_new, step.y_new, step.u_new, ctl, step.chart)
        return tuple(jnp.where(step.acc, jnp.maximum(a, b), a) for a, b in zip(state, new))

    def integrand(self, y, u):
        e = u[0] * u[0] + u[1] * u[1]
        return (e, _sqrt0(e))

    def values(self, state, quad):
        return {"u_peak": jnp.stack([state[0], state[1]], axis=-1), "u_norm_peak": state[2],
                "u_energy": quad[0], "u_abs_int": quad[1]}

    def results(self, state, quad):
        return {"u_peak": np.stack([_np(state[0]), _np(state[1])], axis=-1), "u_norm_peak": _np(state[2]),
                "u_energy": _np(quad[0]), "u_abs_int": _np(quad[1])}


#: The observers of every ensemble, basin study and simulation.
DEFAULT_OBSERVERS = (ConvergenceTime(), ClosestApproach(), Excursion(), ControlEffort())


def observer_fields(observers) -> tuple:
    """The result names of ``observers``, in order."""
    return tuple(f for o in observers for f in o.fields)


def collect_values(observers, obs_state, quad) -> dict:
    """Traced results of every observer of one trajectory (`jaxsleigh.integrate.solve`)."""
    out, row = {}, 0
    for o, st in zip(observers, obs_state):
        out.update(o.values(st, tuple(quad[row + i] for i in range(o.n_quad))))
        row += o.n_quad
    return out


def collect(observers, obs_state, quad) -> dict:
    """Host results of every observer (``obs_state``, ``quad`` from the stepper's final state)."""
    out, row = {}, 0
    for o, st in zip(observers, obs_state):
        out.update(o.results(st, tuple(quad[row + i] for i in range(o.n_quad))))
        row += o.n_quad
    return out
