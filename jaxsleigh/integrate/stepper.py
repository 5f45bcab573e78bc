r"""The engine's stepper: RK4 in the w chart, fixed-step or adapted per trajectory.

**Why the w chart.** In ``y = (w, p)`` the closed loop is port-Hamiltonian with
\(H_d = \tfrac12 p^\top M^{-1} p + \tfrac12 w^\top L w\) non-increasing (eq. 15-18), so the state
stays in a bounded set, and the right-hand side is rational in ``w`` without trigonometry. In the
physical chart every evaluation recomputes ``w`` from ``q`` through \(z_3 / \theta^2\), and
float32 rounding of ``q`` is amplified by \(1/\theta^2\) near the singular set.

**Passivity monitor.** The exact closed loop never increases \(H_d\) (eq. 18). A step that
does (beyond rounding and a relative slack of 1e-6) is rejected by the adaptive method and ends
a fixed-step run with status ``UNRELIABLE``. It catches gross RK4 instability (e.g. dt = 0.05
from the paper's start), not small inaccuracies: at dt = 0.01 wrong stiff starts still lose H_d.

**Why adaptive.** Near \(\theta = 0\) the closed loop is stiff: the injected damping
\(k / w_1^2\) and the potential forces \(\sim |w|^2 / w_1\) give Jacobian eigenvalues far
outside RK4's stability region at ``dt = 0.01``. Each trajectory therefore takes classical RK4
steps whose size is chosen from an embedded third-order error estimate that costs no extra
evaluation: with \(k_5 = f(t + h, y_{n+1})\) (which is also the next step's \(k_1\)),
\(\hat y_{n+1} = y_n + h(k_1 + 2k_2 + 2k_3 + k_5)/6\) is third order, so
\(y_{n+1} - \hat y_{n+1} = h (k_4 - k_5) / 6\). A step is rejected (and retried smaller) when
this error exceeds the tolerance, when it produces a non-finite value, or when it would carry
\(w_1 = \theta\) across zero, which the exact flow never does (Lemma 2). Steps never exceed
the base step ``dt`` and are clipped to land exactly on the save times.

**The settled phase.** Close to the target \(k / w_1^2\) makes the \(p_2\) equation stiff, and the pair
\((w_2, p_1)\) oscillates at a frequency \(\sqrt{V_{22}/m}/|w_1|\); both would cap classical RK4's step by
stability long after accuracy allows more. In the w chart the adaptive step is therefore the exponential RK4
of `jaxsleigh.integrate.etd` (the linear term of \(p_2\) and, from 20 rad/s, the oscillation integrated
exactly over the step; classical RK4 on the rest), with a PI controller (`jaxsleigh.integrate.stepsize`).

**Stiff flights.** A start within ~1e-3 rad of the singular set flies off with a huge \(H_d\) and stays stiff for
its whole flight (`jaxsleigh.integrate.stragglers`): explicit steps are held at their stability limit there. With
``implicit`` every step is instead the linearly implicit Rosenbrock step of `jaxsleigh.integrate.rosenbrock`
(second order, L-stable, the same checks, observers and error norm); the ensembles' engine takes it for a lane that
is still flying after `jaxsleigh.integrate.engine.STIFF_AFTER` attempts.

**Fixed shape.** One loop iteration is one attempted step of every trajectory of a batch; a
trajectory that has reached its target time, failed, or used its budget idles. Every step of a
batch heads for the same target time, so nothing is gathered or scattered per step:
`run` is the one loop over time, in four kinds (`Scan`: a fixed number of attempts; `Count`: a traced number, the
segments between which ensembles compact the batch on the host, one program for every horizon; `WhileActive`: until
every lane is done; `Checkpointed`: a bounded number in checkpointed segments, for reverse mode); `run_stops`
walks a grid of stop times with it (the host's decimated trajectories, `jaxsleigh.solve`'s saves, the sampled loop's
periods), and `run_plain` is the fast path's plain fixed-step RK4
(no masks, no summaries).

Time is accumulated with compensated (two-sum) addition, so float32 runs keep time exact to
rounding over ``1e4`` or more steps.
"""
from __future__ import annotations

import functools
from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp

from ..model.charts import chart_for, q_norm2_w  # noqa: F401  (q_norm2_w: re-exported)
from ..model.closed_loop import ClosedLoop
from .observers import DEFAULT_OBSERVERS, StepInfo
from .etd import etd_stages
from .guard import oscillation_guard
from .rk4 import rk4_stages, rk4_steps
from .horizon import FLIGHT_STEP, STIFF_AFTER, default_tolerance
from .rosenbrock import rosenbrock_stages
from ..status import Status
from .stepsize import StepSizeController, error_ratio, next_step

__all__ = ["Controls", "StepState", "init_state", "init_batch", "init_batch_lanes", "is_active", "attempt",
           "run", "Scan", "Count", "WhileActive", "Checkpointed", "run_stops", "run_plain", "integrands", "q_norm2_w",
           "FlightSwitch"]

#: attempts between two refreshes of the oscillation guard (jaxsleigh.integrate.guard)
GUARD_EVERY = 8

# A step that would overshoot the next save time by less than this fraction is stretched onto it,
# so that rounding in t never leaves a tiny last step.
_STRETCH = 1.01


class Controls(NamedTuple):
    """Traced numbers of the stepper (changing them does not recompile).

    Attributes:
      dt: base step: the fixed step of RK4, the first step tried by the adaptive method.
      max_step: largest adaptive step.
      rtol, atol: tolerances of the adaptive error control (unused by fixed RK4).
      eps: radius of the convergence ball ``|q| <= eps`` for the on-line ``T_eps``.
      max_steps: budget of attempted steps per trajectory.
      safety, factor_min, factor_max: the step-size policy (`jaxsleigh.integrate.stepsize`).
    """

    dt: jax.Array
    max_step: jax.Array
    rtol: jax.Array
    atol: jax.Array
    eps: jax.Array
    max_steps: jax.Array
    safety: jax.Array = 0.9
    factor_min: jax.Array = 0.1
    factor_max: jax.Array = 5.0


def controls(stepsize: StepSizeController, dtype, *, dt, eps, max_steps=None, xp=jnp) -> Controls:
    """The stepper's traced numbers for a run: the policy ``stepsize`` (its defaults resolved for ``dtype`` and the
    base step ``dt``, `StepSizeController.resolved`), the ball's radius ``eps`` and the budget ``max_steps``
    (default: the policy's own, which must then be set: the host's drivers take a policy whose every number is
    resolved, `jaxsleigh.studies.config.SolveConfig.stepsize`).
    ``xp=np`` makes NumPy scalars (a host driver passes them to a compiled step as arguments; made on the device,
    each cast was a program of its own). Every front builds its controls here."""
    ss = stepsize.resolved(dtype, dt)
    if max_steps is None:
        if ss.max_steps is None:
            raise ValueError("controls needs a step budget: give max_steps= or a policy with max_steps set "
                             "(jaxsleigh.integrate.horizon.step_budget)")
        max_steps = ss.max_steps
    dtype = xp.dtype(dtype)
    return Controls(*(xp.asarray(v, dtype) for v in (dt, ss.max_step, ss.rtol, ss.atol, eps)),
                    max_steps=xp.asarray(max_steps, xp.int32),
                    **{k: xp.asarray(getattr(ss, k), dtype) for k in ("safety", "factor_min", "factor_max")})


class StepState(NamedTuple):
    """Carry of one trajectory (batched, every field gets a trailing batch axis)."""

    t: jax.Array          # time, high part
    t_lo: jax.Array       # time, compensation (two-sum)
    y: jax.Array          # (5,) state in the w chart
    k1: jax.Array         # (5,) f(t, y), reused (FSAL)
    h: jax.Array          # proposed next step
    status: jax.Array     # int32 Status
    n_accept: jax.Array   # int32
    n_reject: jax.Array   # int32
    Hd: jax.Array         # closed-loop Hamiltonian H_d(y)
    obs: tuple            # one tuple of arrays per observer (jaxsleigh.integrate.observers)
    quad: jax.Array       # (m,) quadrature rows of the observers, integrated with the RK4 weights
    g1: jax.Array         # (m,) the observers' integrands at y (FSAL, like k1)
    err_prev: jax.Array   # error ratio of the last accepted step (the PI controller's memory)
    guard: tuple = ()     # (cap, atol) of jaxsleigh.integrate.guard in a chart with the pair; () elsewhere
    stiff: jax.Array = False  # bool: the lane steps implicitly (the host's engine.flying, or a traced FlightSwitch)


class FlightSwitch(NamedTuple):
    r"""The implicit switch as a declared policy of a traced loop (``implicit=FlightSwitch()`` in `attempt` / `run`):
    each lane carries its own ``stiff`` flag; a lane still OK after ``after`` attempts at a mean step below
    ``flight`` base steps (scaled for tolerances tighter than the dtype's default as `jaxsleigh.integrate.horizon.
    flight_step` scales it) takes the linearly implicit step from then on, the others the explicit one. It is the
    rule the host's engine applies between segments (`jaxsleigh.integrate.engine.flying`), applied after every
    attempt, so that `jaxsleigh.solve` carries a stiff flight near \(\theta = 0\) as `jaxsleigh.simulate` does.
    Both steps are compiled; one lane runs one of them (``lax.cond``), a batch both (selected per lane)."""

    after: int = STIFF_AFTER
    flight: float = FLIGHT_STEP


def integrands(observers, y, u, dtype):
    """The observers' quadrature integrands at ``y`` under ``u``, stacked in rows (cast to ``dtype``)."""
    rows = [g for o in observers for g in o.integrand(y, u)]
    return jnp.stack(rows).astype(dtype) if rows else jnp.zeros((0,) + y.shape[1:], dtype)


def _needs_fsal(observers) -> bool:
    """Whether some observer needs f(y_new) (dense output) or the control at y_new."""
    return any(o.needs_control or o.n_quad or getattr(o, "needs_dense", False) for o in observers)


def init_state(y0w, status0, args: ClosedLoop, ctl: Controls, t0=0.0, observers=DEFAULT_OBSERVERS) -> StepState:
    """Carry for one trajectory starting at the w-chart state ``y0w`` with status ``status0``.

    A trajectory whose ``status0`` is not OK is never stepped; pass any finite ``y0w`` for it.
    ``observers`` (`jaxsleigh.integrate.observers`) are the on-line summaries carried along.
    """
    dtype = y0w.dtype
    chart = chart_for(args.controller)
    ok = status0 == Status.OK
    # keep an invalid lane's arithmetic finite: it idles, but it is still computed with the batch
    y0w = jnp.where(ok, y0w, jnp.array([1.0, 0.0, 0.0, 0.0, 0.0], dtype))
    t0 = jnp.asarray(t0, dtype)
    k1, u0 = chart.field_and_control(t0, y0w, args)
    g1 = integrands(observers, y0w, u0, dtype)
    return StepState(
        t=t0, t_lo=jnp.zeros((), dtype), y=y0w,
        k1=k1, h=jnp.asarray(ctl.dt, dtype),
        status=jnp.asarray(status0, jnp.int32),
        n_accept=jnp.zeros((), jnp.int32), n_reject=jnp.zeros((), jnp.int32),
        Hd=chart.energy(y0w, args),
        obs=tuple(o.init(t0, y0w, u0, ctl, chart) for o in observers),
        quad=jnp.zeros_like(g1), g1=g1, err_prev=jnp.ones((), dtype),
        guard=_guard_at(chart, t0, y0w, args, ctl), stiff=jnp.zeros((), bool),
    )


def _guard_at(chart, t, y, args, ctl: Controls) -> tuple:
    """The guard's state ``(cap, atol)`` at ``y`` (`jaxsleigh.integrate.guard`); ``()`` in a chart without the pair."""
    g = oscillation_guard(chart, t, y, args, jnp.asarray(ctl.atol, y.dtype), jnp.asarray(ctl.eps, y.dtype))
    return () if g is None else g


def _guard_now(chart, s: "StepState", active, args, ctl: Controls) -> tuple:
    """The guard for this attempt: refreshed at the step's start on a lane's every `GUARD_EVERY`-th attempt, carried
    otherwise. A lane's guard depends on its own attempts only, not on the batch it is in; the refresh runs when some
    lane is due (the lanes of one batch attempt together, so they are due together; under `jax.vmap` too, by
    `any_lane`). Its three forward-mode products (one batched product) cost about a step; every eighth attempt keeps
    them near a tenth of the run."""
    if not s.guard:
        return ()
    due = active & ((s.n_accept + s.n_reject) % GUARD_EVERY == 0)
    return jax.lax.cond(any_lane(due),
                        lambda: tuple(jnp.where(due, new, old)
                                      for new, old in zip(_guard_at(chart, s.t, s.y, args, ctl), s.guard)),
                        lambda: s.guard)


def _stage_quadrature(observers, h, g1, stages, dtype):
    r"""The observers' integrands over a step's stages ``((y2, u2), (y3, u3), (y4, u4))`` with RK4's
    weights: ``(dq, g4)``, the rows' increment and their integrands at the last stage (for the error estimate
    \(h (g_4 - g_5) / 6\) of the rows, as of the state, `_adaptive_outcome`)."""
    g2, g3, g4 = (integrands(observers, yi, ui, dtype) for yi, ui in stages)
    return (h / 6.0) * (g1 + 2.0 * g2 + 2.0 * g3 + g4), g4


def _stages_with_quadrature(t, y, h, args, k1, g1, observers):
    """Classical RK4 from ``k1`` (as `rk4_stages`) that also integrates the
    observers' integrands over the same stages: returns ``(dy, k4, (dq, g4))``."""
    f = chart_for(args.controller).field_and_control
    y2 = y + (0.5 * h) * k1
    k2, u2 = f(t + 0.5 * h, y2, args)
    y3 = y + (0.5 * h) * k2
    k3, u3 = f(t + 0.5 * h, y3, args)
    y4 = y + h * k3
    k4, u4 = f(t + h, y4, args)
    dq, g4 = _stage_quadrature(observers, h, g1, ((y2, u2), (y3, u3), (y4, u4)), y.dtype)
    return (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4), k4, (dq, g4)


def _increment(chart, s: "StepState", h, args, k1, observers, adaptive: bool):
    """One step's increment, last-stage slope, observers' quadrature ``(dq, g4)`` and error estimate (``None``:
    the classical one): the exponential RK4 for the stiff damping when adaptive in a chart that has it
    (`jaxsleigh.integrate.etd`), classical RK4 otherwise."""
    lam = chart.stiff_rate(s.y, args) if adaptive else None
    if lam is not None:
        osc = chart.oscillation(s.y, args)
        dy, k4, error, stages = etd_stages(chart.field_and_control, s.t, s.y, h, args, k1, lam, osc)
        dq = _stage_quadrature(observers, h, s.g1, stages, s.y.dtype) if s.quad.shape[0] else (s.quad, s.quad)
        return dy, k4, dq, error
    if s.quad.shape[0]:
        return (*_stages_with_quadrature(s.t, s.y, h, args, k1, s.g1, observers), None)
    dy, k4 = rk4_stages(chart.field, s.t, s.y, h, args, k1)
    return dy, k4, (s.quad, s.quad), None


def _all_finite(*xs):
    """All components (axis 0) finite: a scalar for one trajectory, (N,) for a batch-last batch."""
    out = jnp.all(jnp.isfinite(xs[0]), axis=0)
    for x in xs[1:]:
        out = out & jnp.all(jnp.isfinite(x), axis=0)
    return out


def _two_sum(a, b):
    s = a + b
    bb = s - a
    return s, (a - (s - bb)) + (b - bb)


@jax.custom_batching.custom_vmap
def any_lane(active):
    """Whether some lane of the batch is ``active``, also across `jax.vmap`: vmapped (a user's ``vmap`` of
    `jaxsleigh.solve`, a tuner's batch of starts), the answer is one for the whole mapped batch, not one per member,
    so a loop's ``cond`` on it stays a branch, skipped once every member is done, rather than a select that runs
    for every member to the end of the static budget. Boolean: nothing to differentiate."""
    return jnp.any(active)


@any_lane.def_vmap
def _any_lane_vmap(axis_size, in_batched, active):
    return jnp.any(active), False


def is_active(s: StepState, target, ctl: Controls):
    """Still stepping towards ``target``: OK, short of it, and within budget."""
    return (s.status == Status.OK) & (s.t < target) & (s.n_accept + s.n_reject < ctl.max_steps)


class _Trial(NamedTuple):
    """A trial step of `attempt`, not yet judged (every array broadcasts over a trailing batch axis)."""

    h: jax.Array          # its size (0 where a lane idles)
    hit: jax.Array        # bool: it lands on the target
    k1: jax.Array         # (5,) f(t, y)
    dy: jax.Array         # (5,) the increment, y_new - y
    k4: jax.Array         # (5,) the last stage's slope
    dq: jax.Array         # (m,) the observers' quadrature rows over the step
    g4: jax.Array         # (m,) their integrands at the last stage
    g5: jax.Array         # (m,) their integrands at y_new (FSAL, the next step's g1); g4 without FSAL
    error: object         # the exponential RK4's error estimate, a function of (y_new, k5); None: the classical one
    y_new: jax.Array      # (5,) the state at its end
    k5: jax.Array         # (5,) f(t + h, y_new) (FSAL); without FSAL the carried k1, unchanged
    u_new: tuple          # the control at y_new; None without FSAL
    error_q: object = None  # the quadrature rows' error estimate; None: the classical h (g4 - g5) / 6


def _step_towards(s: StepState, target, active):
    """``(h, hit)``: the step to try towards ``target`` (the proposed ``s.h``, or the rest of the way when that is
    at most `_STRETCH` times it) and whether it lands there."""
    remaining = (target - s.t) - s.t_lo
    hit = remaining <= _STRETCH * s.h
    h = jnp.where(hit, remaining, s.h)
    # an idle lane still computes (the whole batch steps together); give it a harmless step
    return jnp.where(active, h, jnp.zeros_like(h)), hit


def _trial_step(chart, s: StepState, target, active, args, observers, *, adaptive: bool, fsal: bool) -> _Trial:
    """The step from ``s`` towards ``target``. With ``fsal`` (static) ``k1`` is the carried f(y) and f(y_new) is
    evaluated at the end (the next step's ``k1``); without it ``k1`` is recomputed and f(y_new) is not."""
    h, hit = _step_towards(s, target, active)
    k1 = s.k1 if fsal else chart.field(s.t, s.y, args)
    dy, k4, (dq, g4), error = _increment(chart, s, h, args, k1, observers, adaptive)
    y_new = s.y + dy
    k5, u_new = chart.field_and_control(s.t + h, y_new, args) if fsal else (s.k1, None)
    g5 = integrands(observers, y_new, u_new, s.y.dtype) if s.quad.shape[0] else g4
    return _Trial(h, hit, k1, dy, k4, dq, g4, g5, error, y_new, k5, u_new)


def _implicit_trial(chart, s: StepState, target, active, args, observers) -> _Trial:
    """The linearly implicit trial step of `jaxsleigh.integrate.rosenbrock` from ``s`` towards ``target``, with the
    observers' rows by Simpson's rule over the step's midpoint stage (their difference from the trapezoid rule as
    their error) and that stage's slope in the place of RK4's ``k4`` (the error's rounding floor)."""
    h, hit = _step_towards(s, target, active)
    dy, k5, u_new, e, (y_mid, u_mid, f_mid) = rosenbrock_stages(chart.field_and_control, s.t, s.y, h, args, s.k1)
    y_new = s.y + dy
    if s.quad.shape[0]:
        g_mid = integrands(observers, y_mid, u_mid, s.y.dtype)
        g5 = integrands(observers, y_new, u_new, s.y.dtype)
        dq = (h / 6.0) * (s.g1 + 4.0 * g_mid + g5)
        e_q = dq - (0.5 * h) * (s.g1 + g5)
    else:
        g_mid = g5 = dq = e_q = s.quad
    return _Trial(h, hit, s.k1, dy, f_mid, dq, g_mid, g5, lambda *_: e, y_new, k5, u_new, error_q=e_q)


def _judge(chart, s: StepState, trial: _Trial, args, *, adaptive: bool, monitor: bool):
    """``(finite, crossed, rose, Hd_new)`` of a trial step: its end (adaptive: and f there) finite, ``w_1``
    carried across zero, H_d increased (never with the monitor off or in a chart without H_d), H_d at its end."""
    finite = _all_finite(trial.y_new, trial.k5) if adaptive else _all_finite(trial.y_new)
    crossed = chart.crossed(s.y, trial.y_new)
    # Passivity monitor: the exact flow never increases H_d (eq. 18); a step that does (beyond
    # rounding and a 1e-6 relative slack) is wrong, typically unstable RK4 near theta = 0.
    Hd_new = chart.energy(trial.y_new, args)
    rose = Hd_new > s.Hd * (1.0 + 1e-6 + 64.0 * jnp.finfo(s.y.dtype).eps)
    if not (monitor and chart.has_energy):
        rose = jnp.zeros_like(rose)
    return finite, crossed, rose, Hd_new


def _adaptive_outcome(s: StepState, trial: _Trial, active, finite, crossed, rose, ctl: Controls, guard=None,
                      implicit: bool = False):
    """``(ok, h_next, status, err)`` of an adaptive step: good and within tolerance (error ratio ``err``), the next
    step to try, and where a rejected step leaves a vanishing next step ``NONFINITE`` if that step's end, the field
    there or its error estimate was not finite (the field is NaN or overflows where the run is, or the effort
    integrand does), else ``STEP_UNDERFLOW``. ``guard``: the
    `jaxsleigh.integrate.guard` of the step's start, ``(cap, atol)``: the largest next step and the state's
    absolute tolerance there. ``implicit``: the step was the second-order Rosenbrock step (the next one from the
    error's power -1/3)."""
    h, y_new, k5 = trial.h, trial.y_new, trial.k5
    # the error measure and the step-size policy: jaxsleigh.integrate.stepsize; the observers' quadrature rows
    # (the effort integrals) are under the same norm as the state, with their own embedded estimate
    err = error_ratio(h, s.y, y_new, trial.k4, k5, ctl if guard is None else ctl._replace(atol=guard[1]),
                      e=None if trial.error is None else trial.error(y_new, k5))
    if s.quad.shape[0]:
        err = jnp.maximum(err, error_ratio(h, s.quad, s.quad + trial.dq, trial.g4, trial.g5, ctl, e=trial.error_q))
    good = finite & ~crossed & ~rose
    # a NaN ratio (an overflowing estimate: inf - inf) is a failed step, not a step size: NaN there made every
    # later step NaN and burnt the lane's whole budget in rejections
    overflow = jnp.isnan(err)
    err = jnp.where(good & ~overflow, err, jnp.inf)
    ok = good & (err <= 1.0)
    h_next = next_step(h, err, ctl, order=2) if implicit else next_step(h, err, ctl, err_prev=s.err_prev)
    h_next = jnp.where(ok & trial.hit, jnp.maximum(h_next, s.h), h_next)
    h_next = jnp.minimum(h_next, ctl.max_step if guard is None else jnp.minimum(ctl.max_step, guard[0]))
    # compensated time keeps tiny steps meaningful in float32 too; starts near theta = 0
    # need h ~ 1e-8 s at first from theta0 = 1e-2 (|dp/dt| ~ 1e12) and
    # need h ~ 1e-12 s at first from theta0 = 1e-3 (Jacobian eigenvalues ~ 1e10 i)
    # a step that shrank to nothing because the field is not finite there (a law returning NaN, an overflow) or its
    # error estimate overflows (the effort integrand |u|^2 beyond the dtype) is a diverging run, NONFINITE: only a
    # finite trial rejected for its error is a step-size underflow
    status = jnp.where(active & ~ok & (h_next < 1e-18 * ctl.dt),
                       jnp.where(finite & ~overflow, Status.STEP_UNDERFLOW, Status.NONFINITE), s.status)
    return ok, h_next, status, err


def _fixed_outcome(s: StepState, active, finite, crossed, rose):
    """``(ok, h_next, status, None)`` of a fixed step: the step stays ``s.h``, and a bad step ends the run with
    the status of its first failed check."""
    ok = finite & ~crossed & ~rose
    status = jnp.where(active & ~finite, Status.NONFINITE,
                       jnp.where(active & crossed, Status.CROSSED_SINGULAR,
                                 jnp.where(active & rose, Status.UNRELIABLE, s.status)))
    return ok, s.h, status, None


def _advance_time(s: StepState, trial: _Trial, target):
    """``(t_new, t_lo_new)`` at the step's end: the compensated (two-sum) ``t + h``, exactly ``target`` on a hit."""
    t_hi, t_err = _two_sum(s.t, trial.h)
    t_new = jnp.where(trial.hit, target, t_hi)
    return t_new, jnp.where(trial.hit, jnp.zeros_like(s.t_lo), s.t_lo + t_err)


def _quadrature_after(observers, s: StepState, trial: _Trial, acc):
    """``(quad, g1)``: the observers' quadrature rows and integrands, advanced where the step was accepted."""
    if not s.quad.shape[0]:
        return s.quad, s.g1
    return jnp.where(acc, s.quad + trial.dq, s.quad), jnp.where(acc, trial.g5, s.g1)


def attempt(s: StepState, target, args: ClosedLoop, ctl: Controls, *, adaptive: bool,
            monitor: bool = True, observers=DEFAULT_OBSERVERS, implicit: bool = False) -> StepState:
    """One attempted step towards the time ``target`` (a no-op once there, failed or out of
    budget). A step that reaches ``target`` lands on it exactly. ``monitor`` (static) turns the
    passivity monitor on; off, fixed RK4 runs ~2x faster on CPU but a step that increases
    H_d goes unnoticed. ``observers`` (static, `jaxsleigh.integrate.observers`) are updated after
    every accepted step; their quadrature rows are integrated with the step's RK4 weights.

    ``implicit`` (static; adaptive only): the step is the linearly implicit Rosenbrock step of
    `jaxsleigh.integrate.rosenbrock` instead (for a stiff flight near the singular set, which the explicit step
    crosses only at its stability limit; `jaxsleigh.integrate.engine.STIFF_AFTER`).

    ``implicit=FlightSwitch(...)`` (adaptive): each lane's ``stiff`` flag chooses, and the flight rule sets it
    (`FlightSwitch`).

    Written for one trajectory (``y`` of shape (5,)) but every operation broadcasts over a
    trailing batch axis, so it also steps a batch-last batch (``y`` (5, N), scalars (N,))."""
    if isinstance(implicit, FlightSwitch):
        return _switched_attempt(s, target, args, ctl, adaptive=adaptive, monitor=monitor, observers=observers,
                                 switch=implicit)
    chart = chart_for(args.controller)
    dtype = s.y.dtype
    target = jnp.asarray(target, dtype)
    active = is_active(s, target, ctl)
    # Without observers of the control or of the dense output, fixed steps recompute k1 = f(y)
    # (no FSAL): carrying f(y_new) across steps ran ~2x slower on XLA:CPU there, and fixed RK4
    # needs no fifth evaluation for an error estimate. Those observers need f(y_new) anyway.
    fsal = adaptive or _needs_fsal(observers)
    implicit = implicit and adaptive
    trial = (_implicit_trial(chart, s, target, active, args, observers) if implicit
             else _trial_step(chart, s, target, active, args, observers, adaptive=adaptive, fsal=fsal))
    finite, crossed, rose, Hd_new = _judge(chart, s, trial, args, adaptive=adaptive, monitor=monitor)
    if adaptive:
        # a weakly damped settled oscillation is resolved, whatever its amplitude (jaxsleigh.integrate.guard)
        guard = _guard_now(chart, s, active, args, ctl)
        ok, h_next, status, err = _adaptive_outcome(s, trial, active, finite, crossed, rose, ctl, guard or None,
                                                    implicit)
    else:
        ok, h_next, status, err = _fixed_outcome(s, active, finite, crossed, rose)
    acc, rej = active & ok, active & ~ok
    t_new, t_lo_new = _advance_time(s, trial, target)
    info = StepInfo(t=s.t, h=trial.h, t_new=t_new + t_lo_new, y=s.y, y_new=trial.y_new, k1=trial.k1,
                    k5=trial.k5 if fsal else None, u_new=trial.u_new, acc=acc, chart=chart)
    quad, g1 = _quadrature_after(observers, s, trial, acc)
    if quad.shape[0]:
        # a diverging law can keep the state finite while its effort integral overflows (|u| ~ 1e19 in float32):
        # the run ends there, NONFINITE, instead of reporting OK with an infinite energy
        status = jnp.where(acc & ~_all_finite(quad), Status.NONFINITE, status)
    return StepState(
        t=jnp.where(acc, t_new, s.t), t_lo=jnp.where(acc, t_lo_new, s.t_lo),
        y=s.y + jnp.where(acc, trial.dy, jnp.zeros_like(trial.dy)), k1=jnp.where(acc, trial.k5, s.k1),
        h=jnp.where(active, h_next, s.h).astype(dtype), status=status.astype(jnp.int32),
        n_accept=s.n_accept + acc.astype(jnp.int32), n_reject=s.n_reject + rej.astype(jnp.int32),
        Hd=jnp.where(acc, Hd_new, s.Hd),
        obs=tuple(o.update(st, info, ctl) for o, st in zip(observers, s.obs)),
        quad=quad, g1=g1,
        err_prev=jnp.where(acc, jnp.maximum(err, 1e-4), s.err_prev).astype(dtype) if adaptive else s.err_prev,
        guard=guard if adaptive else s.guard, stiff=s.stiff,
    )


def _switched_attempt(s: StepState, target, args: ClosedLoop, ctl: Controls, *, adaptive: bool, monitor: bool,
                      observers, switch: FlightSwitch) -> StepState:
    """`attempt` under a `FlightSwitch`: the lane's own ``stiff`` flag picks the explicit or the implicit step (one
    lane: ``lax.cond``; a batch: both, selected per lane), then the flight rule may set the flag."""
    how = dict(adaptive=adaptive, monitor=monitor, observers=observers)
    if not adaptive:
        return attempt(s, target, args, ctl, implicit=False, **how)
    if jnp.ndim(s.stiff) == 0:
        new = jax.lax.cond(s.stiff, lambda c: attempt(c, target, args, ctl, implicit=True, **how),
                           lambda c: attempt(c, target, args, ctl, implicit=False, **how), s)
    else:
        explicit = attempt(s, target, args, ctl, implicit=False, **how)
        implicit = attempt(s, target, args, ctl, implicit=True, **how)
        new = jax.tree_util.tree_map(lambda a, b: jnp.where(s.stiff, b, a), explicit, implicit)
    n = new.n_accept + new.n_reject
    dtype = new.y.dtype
    # the flight bar of jaxsleigh.integrate.horizon.flight_step, with the tolerances traced
    bar = switch.flight * jnp.minimum(1.0, jnp.minimum(ctl.rtol, ctl.atol) / default_tolerance(dtype)) ** 0.2
    flies = (new.status == Status.OK) & (n >= switch.after) & (new.t < bar * ctl.dt * n.astype(dtype))
    return new._replace(stiff=jnp.logical_or(new.stiff, flies))


def init_batch(y0w, status0, args: ClosedLoop, ctl: Controls, t0=0.0, observers=DEFAULT_OBSERVERS) -> StepState:
    """`init_state` for a batch ``y0w`` of shape (N, 5); the result is batch-last."""
    init = functools.partial(init_state, observers=observers)
    return jax.vmap(init, in_axes=(0, 0, None, None, None), out_axes=-1)(y0w, status0, args, ctl, t0)


@functools.partial(jax.jit, static_argnames=("observers",))
def init_batch_lanes(y0w, status0, args: ClosedLoop, ctl: Controls, observers=None) -> StepState:
    """`init_batch` with canonical per-lane ``args`` (every leaf's last axis is the
    batch, `jaxsleigh.model.lanes.broadcast_lanes`): the result is batch-last."""
    init = functools.partial(init_state, observers=DEFAULT_OBSERVERS if observers is None else observers)
    axes = jax.tree_util.tree_map(lambda _: -1, args)
    return jax.vmap(init, in_axes=(0, 0, axes, None, None), out_axes=-1)(y0w, status0, args, ctl, 0.0)


def _batched_attempt(adaptive: bool, monitor: bool = True, observers=DEFAULT_OBSERVERS, implicit: bool = False):
    # attempt() broadcasts over the trailing batch axis; applying it to the batch directly keeps
    # XLA in the (5, N) layout. vmap(in_axes=-1) made it transpose to (N, 5) and re-derive the
    # step inside every per-field fusion: 3x slower on CPU (measured, 4096 trajectories).
    return functools.partial(attempt, adaptive=adaptive, monitor=monitor, observers=observers, implicit=implicit)


def starting_step(s: StepState, ctl: Controls) -> StepState:
    r"""``s`` (batch-last) with each lane's first step at most \(0.01\,\|y_0\| / \|f(y_0)\|\) in the tolerances'
    norm (Hairer's starting-step rule), no less than \(10^{-6}\) ``dt``; no derivative flows through the choice.
    From near \(\theta = 0\) a first trial step of ``dt`` overflows float32: the stepper rejects it, but in reverse
    mode the discarded infinities turn the gradient into NaN (differentiated runs start this way)."""
    sc = ctl.atol + ctl.rtol * jnp.abs(s.y)
    d0 = jnp.sqrt(jnp.mean(jnp.square(s.y / sc), axis=0))
    d1 = jnp.sqrt(jnp.mean(jnp.square(s.k1 / sc), axis=0))
    h0 = jax.lax.stop_gradient(jnp.where(d1 > 0, 0.01 * d0 / jnp.maximum(d1, 1e-30), s.h))
    return s._replace(h=jnp.clip(h0, 1e-6 * ctl.dt, s.h).astype(s.y.dtype))


class Scan(NamedTuple):
    """``n`` attempts, all of them (no test of the batch): the fronts' segments, between which the host checks the
    batch (`jaxsleigh.integrate.engine`). Differentiable in both modes, at a memory of ``n`` steps in reverse mode."""

    n: int
    unroll: int = 1

    def __call__(self, body, busy, carry):
        return jax.lax.scan(lambda c, _: (body(c), None), carry, None, length=int(self.n), unroll=self.unroll)[0]


class Count(NamedTuple):
    """``n`` attempts, all of them, with ``n`` traced (a ``fori_loop``): one compiled program for every segment length,
    so a new horizon, whose first segment is shorter, compiles nothing new. Forward mode only: the engine's segments
    (`jaxsleigh.integrate.engine`), which step every lane as `Scan` does (the same body, bitwise)."""

    n: object

    def __call__(self, body, busy, carry):
        return jax.lax.fori_loop(0, self.n, lambda i, c: body(c), carry)


class WhileActive(NamedTuple):
    """Until no lane is active (a ``while_loop``): as many attempts as the stiffest lane needs, forward mode only."""

    def __call__(self, body, busy, carry):
        return jax.lax.while_loop(busy, body, carry)


class Checkpointed(NamedTuple):
    """At most ``n`` attempts (static), in checkpointed segments of ``segment`` attempts, a segment in which no lane is
    active skipped (one test of the batch); with ``block``, the segments gathered in checkpointed blocks of ``block``
    segments, skipped alike. Differentiable in reverse mode (``jax.grad``) at a memory of one segment's steps (and one
    block's segment ends): the tuners' objectives, `jaxsleigh.solve`'s save intervals, the sampled loop's periods."""

    n: int
    segment: int = 200
    block: Optional[int] = None

    def __call__(self, body, busy, carry):
        segment, n = int(self.segment), int(self.n)

        def skipped(inner, length):       # a scan of checkpointed `inner`, each skipped when no lane is active
            inner = functools.partial(jax.checkpoint, prevent_cse=False)(inner)
            return lambda c: jax.lax.scan(lambda c, _: (jax.lax.cond(busy(c), inner, lambda c: c, c), None), c, None,
                                          length=length)[0]

        def segments(length):
            return skipped(lambda c: Scan(segment)(body, busy, c), length)

        if self.block is None or n <= segment * int(self.block):
            return segments(-(-n // segment))(carry)
        return skipped(segments(int(self.block)), -(-n // (segment * int(self.block))))(carry)


def run(s: StepState, target, args: ClosedLoop, ctl: Controls, loop, *, adaptive: bool, monitor: bool = True,
        observers=DEFAULT_OBSERVERS, accumulate=None, acc=None, implicit: bool = False):
    """The stepper's one loop over time: attempted steps of a batch (batch-last) towards ``target``, as ``loop``
    says (`Scan`: a fixed number; `Count`: a traced number, forward only; `WhileActive`: until no lane is active;
    `Checkpointed`: at most a number, in checkpointed segments, for reverse mode). A lane that has reached its
    target, failed or used its budget (``ctl.max_steps``) idles.

    ``s`` is batch-*last* (every field has the batch as its trailing axis): the loop carries structure-of-arrays
    state and `attempt` broadcasts over that axis. On CPU this layout ran ~3x faster than ``vmap`` of a whole scan
    (whose carry is batch-first). ``jit`` at the call site.

    ``target`` is a time (per lane or shared) or a function of the state giving each lane's target at each attempt
    (e.g. its own time once it has stopped, so that it idles). With ``accumulate(acc, s, s_new) -> acc``, a pytree
    ``acc`` is carried and advanced after every attempt from the states before and after it (integrals that need
    both ends of a step, such as the tuner's soft convergence time); the result is then ``(s, acc)``.
    ``implicit``: `attempt`'s linearly implicit step instead of the explicit one."""
    step = _batched_attempt(adaptive, monitor, observers, implicit)

    def target_of(c):
        return target(c) if callable(target) else jnp.asarray(target, c.y.dtype)

    def body(carry):
        c, a = carry
        c_new = step(c, target_of(c), args, ctl)
        return c_new, (a if accumulate is None else accumulate(a, c, c_new))

    def busy(carry):
        return any_lane(is_active(carry[0], target_of(carry[0]), ctl))

    out, acc = loop(body, busy, (s, acc))
    return out if accumulate is None else (out, acc)


def _reached(c: StepState, args, target, extra):
    """`run_stops`' default record of a stop: each lane's state where it got there, NaN elsewhere."""
    return jnp.where(c.t >= target.astype(c.t.dtype), c.y, jnp.nan)


def run_stops(s: StepState, stops, args: ClosedLoop, ctl: Controls, *, adaptive: bool, monitor: bool = True,
              observers=DEFAULT_OBSERVERS, implicit=False, share: Optional[int] = None, segment: int = 8,
              block: Optional[int] = 8, hook=None, extra=None, record=_reached):
    r"""The stepper's one walk through stop times: from each stop \(t_k\) of ``stops`` (shape (K,)) to the next,
    `run` the batch to it, and ``record`` it there; returns ``(state, records)``, the records stacked on a first axis
    of K (``(state, extra, records)`` when ``extra`` is given).

    ``share``: ``None``: each stop is run to until no lane is active (`WhileActive`, forward mode: the host's
    decimated trajectories). A number: at most ``share`` attempts per interval (its share of the run's budget), in
    checkpointed segments of ``segment`` attempts gathered in blocks of ``block`` (`Checkpointed`), each interval
    checkpointed as a whole, so reverse mode holds one interval's steps; a lane still OK short of the stop ends
    ``BUDGET_EXHAUSTED`` (`jaxsleigh.solve`'s saves, the sampled loop's periods).

    ``hook(s, extra, k) -> (s, args, extra)`` runs at each stop before the batch steps on, with the carried pytree
    ``extra``: a sampled law measures there and holds its input over the interval (`jaxsleigh.integrate.sampled`),
    returning the closed loop of the held input; without it every interval runs under ``args``.
    ``record(s, args, target, extra)`` gives a stop's record (default: the state where the lane got there, NaN
    where it did not). ``implicit`` as in `attempt`."""
    how = dict(adaptive=adaptive, monitor=monitor, observers=observers, implicit=implicit)

    def interval(carry, xs):
        c, ex = carry
        k, target = xs
        a = args
        if hook is not None:
            c, a, ex = hook(c, ex, k)
        if share is None:
            c = run(c, target, a, ctl, WhileActive(), **how)
        else:
            per = ctl._replace(max_steps=c.n_accept + c.n_reject + share)
            c = run(c, target, a, per, Checkpointed(share, min(segment, share), block), **how)
            short = (c.status == int(Status.OK)) & (c.t < target)
            c = c._replace(status=jnp.where(short, int(Status.BUDGET_EXHAUSTED), c.status).astype(c.status.dtype))
        return (c, ex), record(c, a, target, ex)

    body = interval if share is None else functools.partial(jax.checkpoint, prevent_cse=False)(interval)
    (s, extra_out), records = jax.lax.scan(body, (s, extra), (jnp.arange(jnp.shape(stops)[0]), stops))
    return (s, records) if extra is None else (s, extra_out, records)


# Trajectories per cache block of the plain fixed-step path (run_plain). Measured on a 2-core
# AVX-512 x86 (XLA:CPU, jax 0.10, 4096 starts x 10^4 steps, float32, one device): per CPU second,
# 256 -> 9.4e7 trajectory-steps, 128 -> 7.8e7, 64 -> 7.1e7, 512 -> 2.6e7 (XLA splits the step's
# loops of 512 or more lanes over its threads and pays a synchronisation per loop, 7 per step),
# whole batch (4096) -> 2.9e7-3.8e7. A block's state and RK4 stages (~40 KiB) stay in L1.
PLAIN_BLOCK = 256


def _plain_scan(y, args: ClosedLoop, dt, n_steps: int, unroll: int = 1):
    """``n_steps`` classical RK4 steps of a batch-last state ``y`` (5, B), all lanes at once (`rk4_steps`)."""
    return rk4_steps(chart_for(args.controller).field, y, args, dt=dt, n_steps=n_steps, unroll=unroll)


def run_plain(y, args: ClosedLoop, dt, *, n_steps: int, unroll: int = 1, block: int | None = PLAIN_BLOCK):
    """Plain classical RK4 on a batch-last w-chart state ``y`` (5, N): ``n_steps`` steps of ``dt``,
    nothing else (no masks, no summaries, no status). The fast path behind
    ``run_ensemble(stepsize=StepSizeController(method="rk4", check_passivity=False), saveat=SaveAt(summaries=False))``,
    which judges each trajectory at the end.

    The batch is cut into cache blocks of ``block`` trajectories (the C reference's structure,
    ``jaxsleigh/studies/c_reference/rk4_w.c``): each block takes all ``n_steps`` steps while its state
    stays in L1, then the next block (``lax.map`` over blocks, ``lax.scan`` over steps). Every
    lane takes the same operations as with ``block=None`` (one scan over the whole batch, the
    earlier form), and the final states agree with it to float32 rounding (``tests/test_fast_path.py``;
    bit for bit on XLA:CPU for batches of a multiple of 8 until the specialised kernel let LLVM
    contract and reassociate, `jaxsleigh.integrate.engine.PLAIN_CPU_OPTIONS`). Blocks always have the
    same shape, so a start's result does not depend on the batch it is in. A last partial block is
    padded with a harmless state and dropped again.
    """
    n = y.shape[-1]
    if block is None or n <= block:
        return _plain_scan(y, args, dt, n_steps, unroll)
    n_blocks = -(-n // block)
    pad = n_blocks * block - n
    if pad:
        filler = jnp.zeros((y.shape[0], pad), y.dtype).at[0].set(1.0)   # w1 = 1, at rest
        y = jnp.concatenate([y, filler], axis=1)
    yb = y.reshape(y.shape[0], n_blocks, block).transpose(1, 0, 2)      # (n_blocks, 5, block)
    yb = jax.lax.map(lambda b: _plain_scan(b, args, dt, n_steps, unroll), yb)
    return yb.transpose(1, 0, 2).reshape(y.shape[0], n_blocks * block)[:, :n]
