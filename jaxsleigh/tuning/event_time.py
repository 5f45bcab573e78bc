r"""The hard settling time and its gradient, by the implicit function theorem.

\(T_\epsilon\) is the last entry into the ball \(|q| \le \epsilon\) (`jaxsleigh.integrate.observers.ConvergenceTime`):
a root of \(F(T, \vartheta) = |q(T; \vartheta)|^2 - \epsilon^2\) in which \(F\) falls through zero. Where
\(\partial_T F = \tfrac{d}{dt}|q|^2 < 0\) at the root, the implicit function theorem gives

\[ \frac{dT}{d\vartheta} = -\frac{\partial_\vartheta |q(T; \vartheta)|^2}{\tfrac{d}{dt}|q|^2\big|_{t = T}} . \]

Both derivatives are read off the step in which the entry happened: the engine's dense output (the cubic Hermite
interpolant of the accepted RK4 step, `jaxsleigh.integrate.observers.hermite`) at the entry's fraction of that step
gives \(|q(T)|^2\) and its time derivative, and the sensitivity \(\partial_\vartheta y\) of the step's end points
is carried through the adaptive RK4 by forward mode (``jax.jvp`` / ``jax.jacfwd`` through the engine's
``while_loop``; what is differentiated is the discrete scheme along the steps it chose). `settling` returns

\[ \tilde T = T + \frac{\mathrm{sg}(|q|^2) - |q|^2}{\mathrm{sg}(\tfrac{d}{dt}|q|^2)} \]

(``sg`` = ``jax.lax.stop_gradient``): its value is \(T\) exactly and its derivative the formula above. A start that
never settles (or settled at the start) has \(\tilde T = T\) with a zero derivative. Quantiles of \(\tilde T\) over a
batch (``jnp.quantile``) are then differentiable where the hard quantile is: between switches of the lane that
holds it. tests/test_event_time.py checks the derivative of the median against finite differences of the hard
median.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, NamedTuple, Optional

import jax
import jax.numpy as jnp

from ..integrate.observers import ControlEffort, ConvergenceTime, hermite
from ..integrate.horizon import step_budget
from ..integrate.stepper import Checkpointed, WhileActive, controls, run
from ..integrate.stepsize import StepSizeController, check_policy
from ..model.closed_loop import ClosedLoop
from ..status import Status
from ..validate import refuses_removed_keywords
from .objective import _initial_states

__all__ = ["EntryState", "Settling", "settling", "SETTLING_KEYWORDS"]


@dataclass(frozen=True)
class EntryState(ConvergenceTime):
    r"""`ConvergenceTime` that also keeps \(|q|^2\) and \(\tfrac{d}{dt}|q|^2\) at the last entry, from the step's
    dense output, with whatever tangents the step's end points carry."""

    fields: ClassVar[tuple] = ("T_eps", "entry_q2", "entry_rate")

    def init(self, t0, y, u, ctl, chart):
        (t,) = super().init(t0, y, u, ctl, chart)
        return t, chart.q_norm2(y), jnp.full_like(t, -1.0)

    def update(self, state, step, ctl):
        t_enter, q2, rate = state
        inside_end, entered, hi = self.entry(step, ctl)
        th = jax.lax.stop_gradient(hi)
        q2_new, dq2 = jax.jvp(lambda f: step.chart.q_norm2(hermite(step, f)), (th,), (jnp.ones_like(th),))
        h = jnp.where(step.h > 0, step.h, 1.0)
        entry = jnp.where(hi >= 1.0, step.t_new, step.t + hi * step.h).astype(t_enter.dtype)
        t_new = jnp.where(inside_end, jnp.where(entered, entry, t_enter), jnp.inf)
        took = step.acc & inside_end & entered
        return (jnp.where(step.acc, t_new, t_enter).astype(t_enter.dtype), jnp.where(took, q2_new, q2),
                jnp.where(took, dq2 / h, rate))

    def values(self, state, quad):
        return {"T_eps": state[0], "entry_q2": state[1], "entry_rate": state[2]}

    def results(self, state, quad):
        raise NotImplementedError("EntryState is for traced use (jaxsleigh.tuning.event_time.settling)")


class Settling(NamedTuple):
    r"""Per-start results of `settling` (arrays over the batch).

    Attributes:
      T: the settling time \(\tilde T\) with the implicit-function derivative (value: ``T_eps``; ``t_final`` where
        the start did not settle, with a zero derivative) [s].
      settled: ``T_eps <= t_final`` and status OK.
      u_energy: \(\int_0^{t_f} \|u\|^2 dt\), differentiable (the engine's fourth-order quadrature).
      u_norm_peak: \(\max \|u\|\) at the steps' ends.
      status: `jaxsleigh.Status` codes; n_steps: accepted steps.
    """

    T: jax.Array
    settled: jax.Array
    u_energy: jax.Array
    u_norm_peak: jax.Array
    status: jax.Array
    n_steps: jax.Array


_OBSERVERS = (EntryState(), ControlEffort())


#: The keywords `settling` took before jaxsleigh 0.4: ``keyword -> ("stepsize", field)`` of the object that holds it
#: now.
SETTLING_KEYWORDS = {k: ("stepsize", k) for k in ("rtol", "atol", "max_steps")}


@refuses_removed_keywords(SETTLING_KEYWORDS, {"stepsize": frozenset(StepSizeController._fields)},
                          "settling's rtol=, atol= and max_steps= were removed in jaxsleigh 0.4")
def settling(controller, y0w, plant, *, t_final: float = 100.0, eps: float = 0.05, dt: float = 0.01,
             stepsize: Optional[StepSizeController] = None, reverse: bool = False, segment: int = 200) -> Settling:
    r"""Integrate the chart starts ``y0w`` (N, 5) under ``controller`` to ``t_final`` with the engine's adaptive
    stepper and return `Settling`. Traced code (``jit`` it).

    ``dt`` is the base step (the first step tried), as in `jaxsleigh.solve`. ``stepsize``: the
    `jaxsleigh.StepSizeController` of the adaptive steps (static; checked and resolved as `jaxsleigh.solve` does:
    tolerances per dtype by default; ``method`` must be ``"adaptive"``). Its ``max_steps`` is the budget of attempted
    steps per start (a start that needs more ends ``BUDGET_EXHAUSTED``, not settled); by default the budget of every
    front (`jaxsleigh.integrate.horizon.step_budget`: \(20\,(t_{final}/dt + 9)\) attempts in float32,
    \(30\,(t_{final}/dt + 9)\) in float64), which needs ``t_final`` and ``dt`` concrete.

    ``reverse=False`` (static) steps in a ``while_loop``: differentiate in forward mode (``jax.jvp``,
    ``jax.jacfwd``, one tangent per parameter). ``reverse=True`` steps in checkpointed segments of ``segment``
    attempts (`jaxsleigh.integrate.stepper.Checkpointed`): ``jax.grad`` too, whose cost does not grow with the
    number of parameters (the budget is then the number of attempts the segments hold, a static number)."""
    ss = check_policy(stepsize)
    if ss.method != "adaptive":
        raise ValueError(f"settling steps with the adaptive method (its entry time is read off the adaptive step's "
                         f"dense output): stepsize.method must be 'adaptive', got {ss.method!r}")
    dtype = y0w.dtype
    max_steps = step_budget(ss, t_final, dt, dtype)
    ctl = controls(ss, dtype, dt=dt, eps=eps, max_steps=max_steps)
    args = ClosedLoop(plant, controller)
    s = _initial_states(y0w, args, ctl, True, _OBSERVERS)
    T_end = jnp.asarray(t_final, dtype)
    if reverse:
        s = run(s, T_end, args, ctl, Checkpointed(max_steps, int(segment)), adaptive=True, observers=_OBSERVERS)
    else:
        s = run(s, T_end, args, ctl, WhileActive(), adaptive=True, observers=_OBSERVERS)
    (t_hard, q2, rate), (_, _, peak) = s.obs
    ok = (s.status == Status.OK) & (s.t >= T_end)
    settled = ok & (t_hard <= T_end)
    moving = settled & (t_hard > 0) & (rate < 0)
    safe_rate = jnp.where(moving, jax.lax.stop_gradient(rate), -1.0)
    correction = jnp.where(moving, (jax.lax.stop_gradient(q2) - q2) / safe_rate, 0.0)
    T = jnp.where(settled, jax.lax.stop_gradient(t_hard) + correction, T_end)
    return Settling(T=T, settled=settled, u_energy=s.quad[0], u_norm_peak=peak, status=s.status, n_steps=s.n_accept)
