r"""The differentiable solve: one trajectory of the closed loop as a pure JAX function.

`solve` integrates one start under any controller (the paper's law, `jaxsleigh.Gains`, in its w
chart; any other law ``u = law(q, v)`` in the physical chart, `jaxsleigh.model.charts`; a digital controller
``sampled(law, period)``, its sample instants step boundaries, `jaxsleigh.integrate.sampled`) with the engine's
own stepper (`jaxsleigh.integrate.stepper.attempt`, the step-size policy of `jaxsleigh.integrate.stepsize`) and
observers (`jaxsleigh.integrate.observers`), and returns the final state and the observers' summaries as JAX
arrays. It runs a fixed number of attempted steps in a ``lax.scan``, so it composes with ``jit``,
``vmap`` (batches of starts, gains or plants), ``jax.grad`` and ``jax.jacfwd``: derivatives of the
final state, of \(\int \|u\|^2 dt\) and of the other summaries with respect to the controller's
parameters, the plant's and the start.

What is differentiated is the discrete scheme along the step sizes it chose (the choice itself is
not differentiated, `jaxsleigh.integrate.stepsize.next_step`); with tight tolerances it converges to the
derivative of the exact flow. ``T_eps`` and the peaks are piecewise smooth in the parameters.

The NumPy fronts (`jaxsleigh.simulate`, `jaxsleigh.run_ensemble`, basins, sweeps) add what a study
needs on top of the same stepper (chunks, checkpoints, devices, batch compaction, files); they are
not traced.
"""
from __future__ import annotations

import functools
from typing import Any, NamedTuple, Optional

import jax
import jax.numpy as jnp

from ..controllers.actuators import Sampled, is_sampled
from ..cores import configure
from ..model.charts import chart_for
from ..model.closed_loop import ClosedLoop
from .observers import DEFAULT_OBSERVERS, collect_values
from ..model.params import is_concrete, paper_plant
from ..status import NO_RESULT, Status
from .sampled import solve_sampled, substeps_for
from .horizon import make_horizon, step_budget
from .saveat import SaveAt
from .stepper import Checkpointed, FlightSwitch, controls, init_state, run, run_stops
from .stepsize import StepSizeController, check_policy
from ..validate import real, refuses_removed_keywords

__all__ = ["solve", "SolveOutput"]


class SolveOutput(NamedTuple):
    r"""What `solve` returns for one start (JAX arrays; vmap adds a leading batch axis), under the names every
    front's result uses.

    Attributes:
      q_final, p_final: final configuration (3,) and momentum (2,) (NaN for a status of
        `jaxsleigh.status.NO_RESULT`, as the summaries).
      status: `jaxsleigh.Status` code (``BUDGET_EXHAUSTED`` when the attempts ran out first).
      t_reached: time reached.
      n_steps, n_rejected: accepted and rejected attempts.
      summaries: the observers' values (``T_eps``, ``u_energy``, ``u_peak``, ...); the standard ones are also
        attributes (`T_eps`, `u_energy`, ...).
      Hd0, Hd_final: the paper's closed-loop energy \(H_d\) at the start and at the end (NaN for a law without
        it, and at the end of a run that did not end OK).
      t, q, p, u: with ``saveat=SaveAt(every=n)``: the save times (K+1,) from 0, and the configuration (K+1, 3),
        momentum (K+1, 2) and input (K+1, 2) there (NaN from where the run stopped); ``None`` without.
    """

    q_final: jax.Array
    p_final: jax.Array
    status: jax.Array
    t_reached: jax.Array
    n_steps: jax.Array
    n_rejected: jax.Array
    summaries: dict
    Hd0: Optional[jax.Array] = None
    Hd_final: Optional[jax.Array] = None
    t: Optional[jax.Array] = None
    q: Optional[jax.Array] = None
    p: Optional[jax.Array] = None
    u: Optional[jax.Array] = None

    def _summary(self, name: str):
        return self.summaries.get(name)

    T_eps = property(lambda self: self._summary("T_eps"), doc="Convergence time (the `ConvergenceTime` observer).")
    u_energy = property(lambda self: self._summary("u_energy"), doc="Control energy \\(\\int \\|u\\|^2 dt\\).")
    u_abs_int = property(lambda self: self._summary("u_abs_int"), doc="\\(\\int \\|u\\| dt\\).")
    u_norm_peak = property(lambda self: self._summary("u_norm_peak"), doc="Largest \\(\\|u\\|\\).")
    min_abs_theta = property(lambda self: self._summary("min_abs_theta"), doc="Closest approach to theta = 0.")
    max_excursion = property(lambda self: self._summary("max_excursion"), doc="Largest \\(|q|\\).")
    #: traced results carry no run record (wall time, devices): the host fronts' ``run_info`` is ``None`` here
    run_info = None

    @property
    def converged(self) -> jax.Array:
        """Ended OK and settled in the ball within the horizon (``T_eps`` finite), as `jaxsleigh.status.converged`."""
        return (self.status == Status.OK) & jnp.isfinite(self.T_eps)


#: The keywords `solve` took before jaxsleigh 0.4: ``keyword -> ("stepsize", field)`` of the object that holds it now.
SOLVE_KEYWORDS = {"method": ("stepsize", "method"), "max_attempts": ("stepsize", "max_steps")}


@refuses_removed_keywords(SOLVE_KEYWORDS, {"stepsize": frozenset(StepSizeController._fields)},
                          "solve's method= and max_attempts= were removed in jaxsleigh 0.4")
def solve(controller, y0, *, plant=None, t_final: float = 100.0, dt: float = 0.01,
          stepsize: Optional[StepSizeController] = None, eps: float = 0.05, observers: Any = DEFAULT_OBSERVERS,
          saveat: Optional[SaveAt] = None) -> SolveOutput:
    r"""Integrate one start ``y0`` ((3,) or (5,), physical state) to ``t_final`` under ``controller``.

    Args:
      controller: `jaxsleigh.Gains` (the paper's law) or any law ``u = law(q, v)`` (`jaxsleigh.model.controller`),
        possibly behind actuator pieces; a digital controller ``sampled(law, period, ...)``
        (`jaxsleigh.controllers.actuators.sampled`) runs the sampled-data loop on the same stepper, its sample
        instants step boundaries (``t_final`` a whole number of periods; the sampler's numbers, ``t_final`` and
        ``dt`` concrete; the noise is keyed by ``(seed, k)``, so starts vmapped together see the same draws).
      y0: ``(x, y, theta)`` (zero momentum) or ``(x, y, theta, p1, p2)``; its dtype sets the precision.
      plant: `jaxsleigh.PlantParams` (default: the paper's).
      t_final, dt: horizon and base step (the fixed step of ``"rk4"``, the first step of ``"adaptive"``).
      stepsize: `jaxsleigh.StepSizeController`, static (a constant of the traced function, or a static
        argument of ``jit``; its numbers may also be traced): ``method`` ``"adaptive"`` or ``"rk4"``, the
        adaptive policy (tolerances per dtype by default), ``check_passivity``, and ``max_steps``, the most
        attempted steps (default: the budget of every front, `jaxsleigh.integrate.horizon.default_max_steps`: the
        base steps \(t_{final}/dt\) plus the saves and 8 for ``"rk4"``, 20x that in float32 and 30x in float64 for
        ``"adaptive"``); a start that needs more ends ``BUDGET_EXHAUSTED`` (its summaries are then up to
        ``t_reached``). The attempts run in checkpointed segments, and a segment after the lane is done is
        skipped (under ``vmap``, once every start of the batch is done: `jaxsleigh.integrate.stepper.any_lane`),
        so a large budget costs nothing it does not use; the program's static length is the budget rounded up to a
        power of four, at least 4^9 (`loop_length`), so every default horizon up to 131 s (float32) shares one
        compiled program. A
        stiff flight near \(\theta = 0\) moves to the implicit step of `jaxsleigh.integrate.rosenbrock` by the
        flight rule of every front (`jaxsleigh.integrate.stepper.FlightSwitch`): from ``(1.9, -0.04, 2e-4)`` in
        float32 `solve` carries it to 100 s as `jaxsleigh.simulate` does.
      eps: radius of the ball of ``T_eps``.
      observers: the summaries to carry (static).
      saveat: `jaxsleigh.SaveAt`: ``SaveAt(every=n)`` also returns the trajectory at \(t_j = j\,n\,dt\) (``t``, ``q``,
        ``p``, ``u``; ``t_final`` a whole number of save intervals, ``t_final``, ``dt`` concrete). The steps land on
        the save times and ``max_steps`` is shared evenly between the save intervals (as between a sampled loop's
        periods), a stretch of the scan in which the lane is done skipped; the results differ from a run without
        saving within the tolerances. Under a sampled law the samples are saved: ``n dt`` must be the period.

    Returns:
      `SolveOutput` (its ``t``, ``q``, ``p``, ``u`` ``None`` without ``saveat``). Concrete settings are checked
      here (``t_final``, ``dt``, ``eps`` finite and positive, a controller given); the gains and plant are not (they
      may be traced): validate them with `jaxsleigh.gains` /
      `jaxsleigh.plant_params` first. A start that cannot be integrated is reported as data, as in every
      front: non-finite ``INVALID_INPUT``, ``theta0 = 0`` under a law singular there ``SINGULAR_START``, one
      whose chart state, vector field, H_d or effort integrand \(|u|^2\) overflows the precision
      ``OUT_OF_RANGE``; its outputs are NaN. So are those of a run that failed while stepping (``NONFINITE``,
      ``STEP_UNDERFLOW``, ...: `jaxsleigh.status.NO_RESULT`): final state and summaries NaN, never its start nor
      the integrals up to the failure.
    """
    ss = check_policy(stepsize)
    configure()              # a run begins: one JAX CPU device per core, if JAX has not started (jaxsleigh.cores)
    y0 = _checked_start(controller, y0, t_final=t_final, dt=dt, eps=eps)
    every, observers = _save_every(saveat), tuple(observers)
    if is_sampled(controller):
        return _solve_held(controller, y0, plant, t_final, dt, ss, eps, observers, every)
    dtype = y0.dtype
    adaptive = ss.method == "adaptive"
    max_attempts = step_budget(ss, t_final, dt, dtype, save_every=every, flags={"save_every": "saveat.every"})
    args = ClosedLoop(paper_plant() if plant is None else plant, controller)
    ctl = controls(ss, dtype, dt=dt, eps=eps, max_steps=max_attempts)
    how = dict(adaptive=adaptive, monitor=bool(ss.check_passivity), observers=observers,
               implicit=FlightSwitch() if adaptive else False)
    if every is None:
        return _scan(y0, jnp.asarray(t_final, dtype), args, ctl, loop_length(int(max_attempts)), **how)
    if not is_concrete((t_final, dt)):
        raise ValueError("with saveat, t_final and dt must be concrete (they set the number of saves)")
    return _run_saving(y0, args, ctl, float(t_final), float(dt), every, int(max_attempts), **how)


#: attempts per checkpointed segment of `solve` without saving (`stepper.Checkpointed`, one level: a second level of
#: blocks made the program with the flight switch 1.5x slower to compile). A lone start skips the segments after it
#: is done: the README's gradient ran in 0.12 s against 2.7 s for a plain scan of the whole budget
SEGMENT = 256


#: the shortest static loop of `solve` (attempts): 4^9, the default float32 budget of a 131 s horizon at ``dt = 0.01``
MIN_LOOP = 4 ** 9


def loop_length(max_attempts: int) -> int:
    """The static length of `solve`'s loop for a budget of ``max_attempts``: the next power of four, at least
    `MIN_LOOP`. Each lane still stops at its own budget (``ctl.max_steps``, a traced number), and the segments after
    every lane is done are skipped (`jaxsleigh.integrate.stepper.any_lane`, also under ``vmap``), so the rounding costs
    a check per skipped segment (the README's gradient over 10 s ran as fast with 1,024 segments as with 256) and,
    in reverse mode, the carry it keeps per segment (1,024 of them per lane up to `MIN_LOOP`). In return, budgets
    within the same power of four share one compiled program: in float32 at ``dt = 0.01`` every default horizon up to
    131 s (in float64, up to 87 s; then 87-349 s)."""
    return max(MIN_LOOP, 1 << (2 * -(-max(int(max_attempts) - 1, 1).bit_length() // 2)))


@functools.partial(jax.jit, static_argnames=("n", "adaptive", "monitor", "observers", "implicit"))
def _scan(y0, t_final, args, ctl, n: int, **how) -> SolveOutput:
    """`solve` of the physical start ``y0`` to ``t_final`` without saving, as one jitted program: the start in the
    law's chart, `run` of at most ``n`` attempted steps in checkpointed segments (those after the lane is done
    skipped), the output. A second `solve` of the same law, shapes and options compiles nothing, and `jax.grad` of a
    `solve` outside ``jit`` differentiates this one program (traced op by op around the loop, the chart's maps and the
    output compiled some 130 small programs, and a second gradient took 0.16 s where it takes 0.05 s)."""
    chart = chart_for(args.controller)
    yc, status0 = _start_in_chart(y0, chart, args)
    s0 = init_state(yc, status0, args, ctl, observers=how["observers"])
    s = run(s0, t_final, args, ctl, Checkpointed(n, min(SEGMENT, n)), **how)
    return _output(s, s0, status0, chart, t_final, how["observers"], {})


def _checked_start(controller, y0, **numbers) -> jax.Array:
    """``y0`` as a (5,) floating array (a (3,) start gets zero momentum), after checking the concrete settings of a
    `solve` call: a controller given, ``numbers`` (``t_final``, ``dt``, ``eps``) finite and > 0 (a traced one is
    checked where it is concrete), the start's shape."""
    if controller is None or not (callable(controller) or hasattr(controller, "L")):
        raise ValueError(f"controller must be jaxsleigh.Gains (the paper's law) or a law u = law(q, v), "
                         f"got {type(controller).__name__}")
    for name, value in numbers.items():
        if is_concrete(value):
            real(name, value, positive=True)
    y0 = jnp.asarray(y0)
    if not jnp.issubdtype(y0.dtype, jnp.floating):
        y0 = y0.astype(jnp.zeros(()).dtype)
    if y0.shape == (3,):
        y0 = jnp.concatenate([y0, jnp.zeros(2, y0.dtype)])
    if y0.shape != (5,):
        raise ValueError(f"y0 must have shape (3,) or (5,) (one start; vmap for many), got {y0.shape}")
    return y0


def _output(s, s0, status0, chart, t_final, observers, traj: dict) -> SolveOutput:
    r"""The `SolveOutput` of the stepper's last state ``s`` (first ``s0``): a lane still OK short of ``t_final`` ran
    out of budget; a start that could not be integrated (``status0`` not OK) or a run that failed (a status of
    `jaxsleigh.status.NO_RESULT`: ``STEP_UNDERFLOW``, ``NONFINITE``, ...) has NaN final state and summaries (not
    its start, not the integrals up to the failure), and \(H_d\) is NaN under a law without it."""
    status = jnp.where((s.status == Status.OK) & (s.t < jnp.asarray(t_final, s.t.dtype)), Status.BUDGET_EXHAUSTED,
                       s.status)
    valid, energy = status0 == Status.OK, chart.has_energy
    ran = valid & ~jnp.isin(status, jnp.asarray([int(c) for c in NO_RESULT], status.dtype))
    y = jnp.where(ran, chart.from_chart(s.y), jnp.nan)
    summaries = jax.tree_util.tree_map(lambda v: jnp.where(ran, v, jnp.nan),
                                       collect_values(observers, s.obs, s.quad))
    return SolveOutput(q_final=y[:3], p_final=y[3:], status=status, t_reached=s.t, n_steps=s.n_accept,
                       n_rejected=s.n_reject, summaries=summaries,
                       Hd0=jnp.where(valid & energy, s0.Hd, jnp.nan),
                       Hd_final=jnp.where(valid & energy & (status == Status.OK), s.Hd, jnp.nan), **traj)


#: attempts per checkpointed segment, and segments per block, of a save interval (`stepper.Checkpointed`)
SAVE_SEGMENT, SAVE_BLOCK = 8, 8


def _save_every(saveat) -> Optional[int]:
    """``saveat.every`` checked (``None``: no trajectory): a whole number >= 1, with summaries."""
    if saveat is None:
        return None
    if not isinstance(saveat, SaveAt):
        raise ValueError(f"saveat must be a jaxsleigh.SaveAt, got {type(saveat).__name__}")
    if not saveat.summaries:
        raise ValueError("solve always carries its summaries: SaveAt(summaries=False) is the fronts' plain fixed-step "
                         "path (jaxsleigh.run_ensemble)")
    if saveat.every is None:
        return None
    e = saveat.every
    if isinstance(e, bool) or not isinstance(e, int) and not (isinstance(e, float) and e.is_integer()) or e < 1:
        raise ValueError(f"saveat.every must be a whole number of base steps >= 1, got {e!r}")
    return int(e)


@functools.partial(jax.jit, static_argnames=("t_final", "dt", "every", "max_attempts", "adaptive", "monitor",
                                             "observers", "implicit"))
def _run_saving(y0, args, ctl, t_final: float, dt: float, every: int, max_attempts: int, **how) -> SolveOutput:
    """`solve` of the physical start ``y0`` with the trajectory (``t``, ``q``, ``p``, ``u``) at the save times of
    ``every`` base steps, as one jitted program (as `_scan`): `jaxsleigh.integrate.stepper.run_stops` through them,
    each interval at most its share of ``max_attempts`` attempts. A state the lane did not reach (it stopped, or its
    share ran out: ``BUDGET_EXHAUSTED``) is NaN."""
    horizon = make_horizon(t_final, dt, every, flags={"save_every": "saveat.every"})
    chart = chart_for(args.controller)
    yc, status0 = _start_in_chart(y0, chart, args)
    s0 = init_state(yc, status0, args, ctl, observers=how["observers"])
    dtype = s0.y.dtype

    def record(s, a, target, extra):
        good = s.status == Status.OK
        y = jnp.where(good, chart.from_chart(s.y), jnp.nan)
        return y, jnp.where(good, jnp.stack(chart.field_and_control(s.t, s.y, a)[1]), jnp.nan)

    s, (ys, us) = run_stops(s0, jnp.asarray(horizon.save_times(), dtype), args, ctl,
                            share=-(-max_attempts // horizon.n_out), segment=SAVE_SEGMENT, block=SAVE_BLOCK,
                            record=record, **how)
    ok0 = status0 == Status.OK
    y_first = jnp.where(ok0, y0, jnp.nan)
    u_first = jnp.where(ok0, jnp.stack(chart.field_and_control(s0.t, s0.y, args)[1]), jnp.nan)
    ys, us = jnp.concatenate([y_first[None], ys]), jnp.concatenate([u_first[None], us])
    traj = dict(t=jnp.asarray(horizon.t(), dtype), q=ys[:, :3], p=ys[:, 3:], u=us)
    return _output(s, s0, status0, chart, t_final, how["observers"], traj)


def _solve_held(controller, y0, plant, t_final, dt, ss: StepSizeController, eps, observers, every) -> SolveOutput:
    """`solve` under a `jaxsleigh.controllers.actuators.Sampled` law: the sample instants are step boundaries of the
    same stepper and the held input is state (`jaxsleigh.integrate.sampled`), so the tolerances, the observers and the
    gradients work as for any law. One start is a batch of one of `jaxsleigh.integrate.sampled.solve_sampled`, its
    first step ``period / substeps`` (`jaxsleigh.integrate.sampled.substeps_for` of ``dt``). The held loop has no
    \\(H_d\\): ``Hd0`` and ``Hd_final`` are NaN. Saving keeps the samples: ``t``, ``q``, ``p`` at the K+1 sample
    instants, ``u`` (K, 2) the input held on each period."""
    if not isinstance(controller, Sampled):
        raise ValueError("solve integrates one start: a sampled law with per-trajectory numbers (PerTrajectory) runs "
                         "in jaxsleigh.run_ensemble; to solve many starts, vmap solve over them")
    if not is_concrete((controller.sampler, t_final, dt)):
        raise ValueError("under a sampled law, the sampler's numbers, t_final and dt must be concrete (they set the "
                         "number of samples of the compiled loop): differentiate or vmap with respect to the law's "
                         "parameters, e.g. lambda gains: solve(sampled(gains, 0.2), y0)")
    period = float(controller.sampler.period)
    if every is not None and abs(every * float(dt) - period) > 1e-9 * period:
        raise ValueError(f"under a sampled law solve saves the samples: saveat.every * dt ({every} * {float(dt):g}) "
                         f"must be the sampling period {period:g}")
    out = solve_sampled(controller.law, paper_plant() if plant is None else plant, y0[None], t_final=t_final,
                        sampler=controller.sampler, substeps=substeps_for(period, float(dt)), eps=eps, dtype=y0.dtype,
                        save=every is not None, stepsize=ss, observers=observers)
    traj = {} if every is None else dict(t=out.t, q=out.q[0], p=out.p[0], u=out.u[0])
    nan = jnp.full((), jnp.nan, y0.dtype)
    return SolveOutput(q_final=out.q_final[0], p_final=out.p_final[0], status=out.status[0],
                       t_reached=out.t_reached[0], n_steps=out.n_steps[0], n_rejected=out.n_rejected[0],
                       summaries={k: v[0] for k, v in out.summaries.items()}, Hd0=nan, Hd_final=nan, **traj)


def _overflows_at(chart, y, args) -> jax.Array:
    r"""Whether the chart's vector field, its H_d or the effort integrand \(|u|^2\) is infinite at the chart state
    ``y`` (finite): an overflow of the dtype, which no step can resolve (a NaN is the law's, not an overflow, and
    ends the run ``NONFINITE``)."""
    f, u = chart.field_and_control(jnp.zeros((), y.dtype), y, args)
    u2 = u[0] * u[0] + u[1] * u[1]
    inf = jnp.any(jnp.isinf(f)) | jnp.isinf(u2)
    return inf | jnp.isinf(chart.energy(y, args)) if chart.has_energy else inf


def _start_in_chart(y0: jax.Array, chart, args) -> tuple[jax.Array, jax.Array]:
    r"""``y0`` in ``chart`` and its starting status, traced (``y0`` may be a tracer under ``grad``/``vmap``):
    ``INVALID_INPUT`` for a non-finite start, ``SINGULAR_START`` for ``theta0 = 0`` in a chart singular there,
    ``OUT_OF_RANGE`` where the chart's state, its vector field, H_d or the effort integrand \(|u|^2\) overflows
    the dtype (`_overflows_at`: in float32 from ``theta0 = 1e-7``, whose \(|u|^2 \sim 10^{41}\), or from
    ``x = y = 1e30``, whose H_d overflows). Such a start is replaced by a harmless
    placeholder, which is never stepped (its status is not OK), so no NaN reaches the step or its gradient."""
    placeholder = jnp.asarray([1.0, 0.0, 1.0, 0.0, 0.0], y0.dtype)
    finite = jnp.all(jnp.isfinite(y0))
    singular = bool(chart.singular) & (y0[2] == 0)
    status = jnp.where(~finite, Status.INVALID_INPUT, jnp.where(singular, Status.SINGULAR_START, Status.OK))
    probe = chart.to_chart(jax.lax.stop_gradient(jnp.where(status == Status.OK, y0, placeholder)))
    status = jnp.where((status == Status.OK) & ~jnp.all(jnp.isfinite(probe)), Status.OUT_OF_RANGE, status)
    status = jnp.where((status == Status.OK) & _overflows_at(chart, probe, args), Status.OUT_OF_RANGE, status)
    # mapped again from the start or the placeholder: an overflowing start's inf never meets the gradient
    return chart.to_chart(jnp.where(status == Status.OK, y0, placeholder)), status.astype(jnp.int32)
