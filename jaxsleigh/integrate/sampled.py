r"""The sampled-data loop: a digital controller (zero-order hold, delay, noise) on the continuous plant.

At the sampling instants \(t_k = k T_s\), \(k = 0, \dots, K-1\) (\(K = t_\mathrm{final} / T_s\)), the
controller measures

\[ \tilde q_k = q(t_k) + \sigma \xi^q_k, \qquad \tilde v_k = M^{-1} p(t_k) + \sigma \xi^v_k, \qquad
   \xi_k \sim \mathcal N(0, I_5) \text{ keyed by (seed, k)}, \]

computes \(\hat u_k = \mathrm{law}(\tilde q_k, \tilde v_k, t_k)\) once, and the plant (paper eq. 1-2)

\[ \dot q = Q(q) M^{-1} p, \qquad \dot p = (J(p) - D(q, p)) M^{-1} p + u_k^\mathrm{held} \]

receives the held input \(u_k^\mathrm{held} = \hat u_{k-d}\) on \([t_k, t_{k+1})\) (\(\hat u_j = 0\) for
\(j < 0\); ``d = sampler.delay``, kept in a ring buffer of the last \(d\) controls).

**A structure on the solver, not a second solver.** The sample instants are step boundaries (as diffrax's
``jump_ts``) and the held input is part of the closed loop's arguments: on \([t_k, t_{k+1}]\) the library's own
stepper (`jaxsleigh.integrate.stepper.attempt`, the error control and PI step-size policy of
`jaxsleigh.integrate.stepsize`) integrates the plant under the law `HeldInput` \(u = u_k^\mathrm{held}\), smooth
there, and lands exactly on \(t_{k+1}\); at each sample the step's first slope (reused from the previous step's last
one) is recomputed with the new input, and the step size proposed at the end of one period is the first one tried
in the next. So ``rtol`` and ``atol`` (default: those of the continuous loop in the same dtype,
`jaxsleigh.integrate.stepsize.DEFAULT_RTOL`) set the accuracy, and the observers of every run
(`jaxsleigh.integrate.observers`) give the summaries. ``substeps`` only sets the first step tried,
\(T_s / \text{substeps}\). ``StepSizeController(method="rk4")`` takes ``substeps`` fixed classical RK4 steps per
period instead (the loop of earlier versions, \(O(h^4)\), tolerances unused).

**Accuracy** (``tests/test_sampled_accuracy.py``): the paper's law under a zero-order hold at \(T_s = 0.2\) s for
30 s in float64 from \((x, y, \theta) = (1, 1, 0.5)\) at rest ends 1.0e-11 from scipy's DOP853 integrating the same
loop sample by sample (rtol 1e-13, atol 1e-14) at ``rtol=1e-11, atol=1e-12`` (3,715 steps), 1.2e-9 at 1e-10,
4.2e-7 at the defaults (1e-8; 578 steps) and 1.4e-5 at 1e-6; the fixed 20 RK4 substeps per period of earlier
versions (3,000 steps) ended 1.4e-5 from it whatever the tolerances.

**Cost** against that fixed-substep loop, float32, default tolerances, the paper's law, compiled programs
excluded, best of 15 on a shared 2-core x86-64 CPU: 3 starts (those of ``tests/test_actuators.py``),
\(T_s = 0.05\) s for 10 s: 273 steps per start instead of 4,000; 5.3 ms instead of 2.2 ms, a reverse-mode gradient
(``jax.grad`` of the summed ``u_energy`` with respect to the starts) 48 ms instead of 33 ms. 64 starts: 289 steps,
26 ms instead of 22 ms, gradient 108 ms instead of 158 ms. \(T_s = 0.2\) s for 30 s, 64 starts: 387 steps instead
of 3,000, 34 ms instead of 22 ms, gradient 139 ms instead of 122 ms. An attempted step costs more than a fixed
one (the error estimate, the observers' dense output), and each period's attempts are rounded up to a segment of
`SEGMENT`; ``method="rk4"`` through the stepper takes 2.4-3.7x the old loop's time for the same steps.

Summaries, per start:

* ``T_eps``: the start of the last stay in the ball \(|q| \le \epsilon\), located on each step's dense output
  (`jaxsleigh.integrate.observers.ConvergenceTime`); ``inf`` if outside at \(t_\mathrm{final}\).
* ``u_energy`` \(= \int_0^{t_\mathrm{final}} \|u\|^2 dt = \sum_k \|u_k^\mathrm{held}\|^2 T_s\) and ``u_abs_int``
  \(= \sum_k \|u_k^\mathrm{held}\| T_s\) (the steps' quadrature of a held input is exact to rounding);
  ``u_norm_peak`` \(= \max_k \|u_k^\mathrm{held}\|\), ``u_peak`` the largest \(|u_i|\).
* ``min_abs_theta``, ``max_excursion``: \(\min |\theta|\) and \(\max |q|\) over the ends of the accepted steps.
* ``n_steps``, ``n_rejected``: the accepted and rejected attempts; ``t_reached``.
* ``status``: `jaxsleigh.Status.OK`; ``INVALID_INPUT`` for a non-finite start (not integrated); ``NONFINITE`` where
  the law's output became non-finite (e.g. the paper's law on \(\theta = 0\)) or its effort integral overflowed
  (under ``"rk4"`` also the state); ``STEP_UNDERFLOW`` where the adaptive step collapsed; ``BUDGET_EXHAUSTED``
  where a period needed more attempts than its share of ``max_steps`` (tight tolerances, or a state that runs away
  faster and faster: Astolfi's law under measurement noise, whose held force reaches 1e5 N). A row that is not OK
  has NaN summaries and NaN samples from its failing sample on; its state is frozen at the last good one, so nothing
  silently turns NaN.

Everything is one jitted ``lax.scan`` over the samples (the law vmapped over the batch through
`jaxsleigh.model.controller.apply_law`). Each period is a bounded scan of attempts in checkpointed segments of
`SEGMENT` attempts gathered in blocks of `BLOCK` segments, a segment or a block in which no start is active skipped
(`jaxsleigh.integrate.stepper.Checkpointed`), and the period itself is checkpointed: reverse mode (``jax.grad``)
with respect to the starts, the law's and the plant's numbers keeps one carry per sample and recomputes a period's
steps when it needs them. What is differentiated is the scheme along the steps it chose (the step-size choice is
not differentiated, as in `jaxsleigh.integrate.solve`).
"""
from __future__ import annotations

import functools
import math
from typing import Any, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from ..controllers.actuators import check_sampler
from ..controllers.paper import measured_law
from ..model.charts import PhysicalChart, physical_chart_for
from ..model.closed_loop import ClosedLoop
from ..model.controller import FunctionLaw, PerTrajectory, apply_law
from ..model.params import PlantParams, is_concrete, plant_params
from ..model.plant import velocity
from ..status import Status
from .horizon import MAX_BASE_STEPS, attempt_budget
from .observers import DEFAULT_OBSERVERS, collect_values
from .stepper import Controls, StepState, controls, init_state, integrands, run_stops
from .stepsize import StepSizeController, check_policy
from ..validate import real, refuses_removed_keywords, whole

__all__ = ["SampledRun", "HeldInput", "held_input_type", "solve_sampled", "sample_count", "substeps_for", "SEGMENT",
           "SAMPLED_KEYWORDS",
           "BLOCK"]

#: Attempts per checkpointed segment of a period (adaptive): a period costs its attempts rounded up to this.
SEGMENT = 4
#: Segments per block: a block in which no start is active is skipped at once (forward and in reverse mode).
BLOCK = 8

#: The observers of the sampled loop: those of every run.
OBSERVERS = DEFAULT_OBSERVERS


class SampledRun(NamedTuple):
    """Result of `solve_sampled` (JAX arrays; first axis the start).

    Attributes:
      t: (K+1,) sampling instants \\(t_k = k T_s\\), ``t_final`` included.
      q, p: (N, K+1, 3), (N, K+1, 2) the state at the sampling instants (NaN from a row's failure on).
      u: (N, K, 2) the input held on \\([t_k, t_{k+1})\\) (zero before the first delayed control).
      (``t``, ``q``, ``p``, ``u`` are ``None`` with ``save=False``: summaries only, memory independent of K.)
      q_final, p_final: (N, 3), (N, 2) state at ``t_final``.
      T_eps, u_energy, u_norm_peak, min_abs_theta: (N,) summaries (see the module).
      status: (N,) int32 `jaxsleigh.Status` codes.
      u_peak: (N, 2) largest \\(|u_i|\\) held; u_abs_int: (N,) \\(\\int \\|u\\| dt = \\sum_k \\|u_k\\| T_s\\);
      max_excursion: (N,) largest \\(|q|\\) at the ends of the steps (the names of `jaxsleigh.EnsembleResult`).
      n_steps, n_rejected: (N,) int32 accepted and rejected attempted steps.
      t_reached: (N,) the time integrated to (``t_final`` for a row that is OK; NaN for one not integrated).
      summaries: every observer's values by name (those above, and those of observers given to `solve_sampled`).
    """

    t: Any
    q: Any
    p: Any
    u: Any
    q_final: Any
    p_final: Any
    T_eps: Any
    u_energy: Any
    u_norm_peak: Any
    min_abs_theta: Any
    status: Any
    u_peak: Any = None
    u_abs_int: Any = None
    max_excursion: Any = None
    n_steps: Any = None
    n_rejected: Any = None
    t_reached: Any = None
    summaries: Any = None


class HeldInput(NamedTuple):
    r"""The input held by the zero-order hold, as a law: \(u = \mathrm{law}(q, v) = u_k^\mathrm{held}\) whatever is
    measured. Wrapped in `jaxsleigh.model.controller.PerTrajectory` it holds one input per start (``u`` of shape
    (2, N)). Its class attribute ``chart`` is the physical chart with the sampled law's heading convention
    (`held_input_type`), which the observers measure \(|q|\) and \(|\theta|\) in."""

    u: Any

    chart = PhysicalChart()

    def __call__(self, q, v, *t):
        return jnp.asarray(self.u)


@functools.lru_cache(maxsize=None)
def held_input_type(chart: PhysicalChart) -> type:
    """`HeldInput` in ``chart`` (a subclass that declares it; one per chart, so compiled programs are reused)."""
    if chart == HeldInput.chart:
        return HeldInput
    return type("HeldInput", (HeldInput,), {"chart": chart, "__slots__": ()})


def sample_count(t_final, period) -> int:
    """The number of samples ``K = t_final / period``; ``ValueError`` unless ``t_final`` is a positive, finite, whole
    number of periods."""
    try:
        t_final = float(t_final)
    except (TypeError, ValueError):
        raise ValueError(f"t_final must be a number of seconds, got {t_final!r}") from None
    if not (math.isfinite(t_final) and t_final > 0):
        raise ValueError(f"t_final must be > 0 and finite, got {t_final!r}")
    ratio = t_final / period
    if not ratio <= MAX_BASE_STEPS + 0.5:             # inf for a subnormal period: refused, not an OverflowError
        raise ValueError(f"t_final / period = {ratio:.3g} samples is more than one run can take "
                         f"({MAX_BASE_STEPS:.0e}); use a longer sampling period or a shorter t_final")
    K = int(round(ratio))
    if K < 1 or abs(K * period - t_final) > 1e-6 * max(1.0, t_final):     # float32's rounding of a period allowed
        raise ValueError(f"t_final = {t_final} must be a whole number of sampling periods "
                         f"(period = {period}): t_final / period = {t_final / period:.6g}")
    return K


def substeps_for(period: float, dt: float) -> int:
    """``substeps`` of a sampling period for a base step ``dt``: the first step tried is ``period / substeps``, at
    most ``dt`` and at most a quarter period (the fixed RK4 steps per period with ``method="rk4"``)."""
    return max(4, math.ceil(period / dt - 1e-9))


def _period_budget(ss: StepSizeController, K: int, substeps: int, dtype) -> int:
    """Attempted steps per period and start (static). Fixed RK4 takes ``substeps``. Adaptive: ``max_steps`` (per start,
    over the run) shared evenly between the ``K`` periods; by default the rule of every budget,
    `jaxsleigh.integrate.horizon.attempt_budget` (20 in float32, 30 in float64 times the base steps), of the
    ``substeps`` of a period."""
    adaptive = ss.method == "adaptive"
    m = ss.max_steps
    if m is None:
        return attempt_budget(substeps, adaptive=adaptive, dtype=jnp.dtype(dtype))
    if not adaptive and int(m) < K * substeps:
        raise ValueError(f"max_steps {int(m)} is below the {K * substeps} steps fixed RK4 takes ({substeps} per "
                         f"period over {K} periods); raise it to at least {K * substeps}")
    return -(-int(m) // K) if adaptive else substeps


#: The keywords `solve_sampled` took before jaxsleigh 0.4: ``keyword -> ("stepsize", field)`` of the object that
#: holds it now.
SAMPLED_KEYWORDS = {"rtol": ("stepsize", "rtol"), "atol": ("stepsize", "atol")}


@refuses_removed_keywords(SAMPLED_KEYWORDS, {"stepsize": frozenset(StepSizeController._fields)},
                          "solve_sampled's rtol= and atol= were removed in jaxsleigh 0.4")
def solve_sampled(law, plant: Optional[PlantParams] = None, ics=None, *, t_final: float, sampler,
                  substeps: int = 20, eps: float = 0.05, dtype=jnp.float32, save: bool = True,
                  stepsize: Optional[StepSizeController] = None, observers: tuple = OBSERVERS) -> SampledRun:
    """Integrate the sampled-data closed loop (module docstring) from a batch of starts.

    Args:
      law: a controller ``u = law(q, v)`` (or time-varying ``law(q, v, t)``, or a `PerTrajectory` law), e.g.
        `jaxsleigh.controllers.paper.PaperLaw`, possibly wrapped in actuator pieces; `jaxsleigh.Gains` runs as
        ``PaperLaw(gains)``.
      plant: `jaxsleigh.PlantParams` (default: the paper's, ``jaxsleigh.plant_params()``); a leaf may carry one
        value per start (a trailing axis of size N), as in the studies' per-trajectory parameters.
      ics: ``(N, 5)`` starts ``(x, y, theta, p1, p2)``, or ``(N, 3)`` with zero momentum (a single start
        ``(5,)``/``(3,)`` is a batch of one).
      t_final: horizon [s], a whole number of sampling periods.
      sampler: `jaxsleigh.controllers.actuators.Sampler` (period, delay, noise, seed).
      substeps: the base step of the sampled loop as a fraction of the period, ``dt = period / substeps``:
        the first step tried in each period (adaptive), the fixed RK4 steps per period with
        ``stepsize=StepSizeController(method="rk4")``. It is the sampled loop's ``dt`` (`jaxsleigh.solve` takes
        ``dt`` and converts it, `substeps_for`), not a field of the step policy: a whole number of steps per period
        keeps the fixed steps on the sample instants whatever the period, and the policy (tolerances, budget) is the
        same object every front takes. eps: radius of the ball of ``T_eps``.
      dtype: ``jnp.float32`` or ``jnp.float64`` (the latter needs ``jax.enable_x64(True)``).
      save: keep the samples (``t``, ``q``, ``p``, ``u``); ``False``: summaries and final states only.
      stepsize: `jaxsleigh.StepSizeController`: ``method`` (``"adaptive"``, or ``"rk4"``: fixed steps), the
        tolerances (default: the continuous loop's in ``dtype``, 1e-6 in float32, 1e-8 in float64), ``safety``, ``factor_min``, ``factor_max``, ``max_step`` (default: 100 base steps, as in the
        continuous loop; the steps never cross a sample instant) and ``max_steps``
        (attempted steps per start over the run, shared evenly between the periods; default 20 (float32) or 30
        (float64) times ``substeps`` per period, as the continuous loop's 20x or 30x its base steps).
        ``check_passivity`` does not apply (the held loop has no \\(H_d\\)).
      observers: the summaries to carry (static; default those of every run): `SampledRun.summaries` holds all of
        their values by name, and the standard ones are also its fields.

    Returns:
      `SampledRun`.

    Raises:
      ValueError: a bad sampler, horizon, ``substeps``, ``eps``, ``dtype``, ``ics`` shape or step option.
    """
    period, delay, noise, seed = check_sampler(sampler)
    if ics is None:
        raise ValueError("ics (the starts, (N, 5) or (N, 3)) is required")
    dtype = jnp.dtype(dtype)
    if dtype not in (jnp.dtype(jnp.float32), jnp.dtype(jnp.float64)):
        raise ValueError(f"dtype must be float32 or float64, got {dtype}")
    if jax.dtypes.canonicalize_dtype(dtype) != dtype:
        raise ValueError(f"dtype {dtype} needs 64-bit JAX: run inside `with jax.enable_x64(True):` "
                         f"(or set jax.config.update('jax_enable_x64', True))")
    substeps = whole("substeps", substeps)
    K = sample_count(t_final, period)
    eps = real("eps", eps, positive=True)
    ss = check_policy(stepsize)
    # the stepper's traced numbers after checking those given: the first step tried is T_s / substeps; the budget is
    # set per period (_period_budget)
    ctl = controls(ss, dtype, dt=period / substeps, eps=eps, max_steps=0)
    budget = _period_budget(ss, K, substeps, dtype)
    law = measured_law(law)                      # the paper's gains: the law from measurements, as sampled
    if not callable(law):
        raise ValueError(f"law must be a feedback law u = law(q, v), got {type(law).__name__}")
    if not (isinstance(law, tuple) or hasattr(law, "tree_flatten")) and jax.tree_util.tree_leaves(law) == [law]:
        law = FunctionLaw(law)                   # a plain function: static
    plant = plant_params() if plant is None else plant

    y0 = jnp.asarray(ics)
    if is_concrete(y0):
        y0 = jnp.asarray(np.asarray(ics, dtype=np.float64), dtype)
    else:
        y0 = y0.astype(dtype)
    if y0.ndim == 1:
        y0 = y0[None]
    if y0.ndim != 2 or y0.shape[1] not in (3, 5) or y0.shape[0] < 1:
        raise ValueError(f"ics must have shape (N, 5) (x, y, theta, p1, p2) or (N, 3) (x, y, theta), got "
                         f"{tuple(jnp.shape(ics))}")
    if y0.shape[1] == 3:
        y0 = jnp.concatenate([y0, jnp.zeros((y0.shape[0], 2), dtype)], axis=1)

    adaptive = ss.method == "adaptive"
    return _solve(law, plant, y0, jnp.asarray(period, dtype), jnp.asarray(noise, dtype),
                  jnp.asarray(seed % 2**32, jnp.uint32), ctl, K=K, delay=delay, save=bool(save), adaptive=adaptive,
                  budget=budget, segment=SEGMENT if adaptive else budget, observers=tuple(observers))


def _row_axes(plant):
    """vmap axes of a plant over the rows: a leaf with a trailing axis (one value per start) maps over it."""
    return jax.tree_util.tree_map(lambda x: -1 if jnp.ndim(x) >= 1 else None, plant)


def _control(law, plant, y, buf, status, k, key0, noise, period, delay: int):
    """Sample ``k`` of the rows ``y`` (N, 5): measure (with noise), evaluate the law once, and return the input held
    on \\([t_k, t_{k+1})\\) (the one computed ``delay`` samples ago) and the updated ring buffer."""
    dtype = y.dtype
    v = jax.vmap(lambda p, pl: velocity(p, pl), in_axes=(0, _row_axes(plant)))(y[:, 3:], plant)
    z = jax.random.normal(jax.random.fold_in(key0, k), (y.shape[0], 5), dtype)
    q_meas = y[:, :3] + noise * z[:, :3]
    v_meas = v + noise * z[:, 3:]
    # a row that is not OK is frozen: the law sees a fixed harmless point there (no inf in the program)
    ok_k = (status == int(Status.OK))[:, None]
    q_meas = jnp.where(ok_k, q_meas, jnp.asarray([1.0, 0.5, 0.3], dtype))
    v_meas = jnp.where(ok_k, v_meas, jnp.zeros((), dtype))
    u1, u2 = apply_law(law, q_meas.T, v_meas.T, k.astype(dtype) * period)
    u_new = jnp.stack([u1, u2], axis=1).astype(dtype)
    if not delay:
        return u_new, buf
    return buf[0], jnp.concatenate([buf[1:], u_new[None]], axis=0)


def _held_loop(plant, held: type, u) -> ClosedLoop:
    """The closed loop of a period: the plant under the inputs ``u`` (N, 2) held, one per start."""
    return ClosedLoop(plant, PerTrajectory(held(u.T)))


def _hold(s: StepState, u, plant, held: type, observers):
    """The stepper's state ``s`` (batch-last) made ready for a period with ``u`` (N, 2) held: a row whose input is not
    finite becomes ``NONFINITE`` (and idles, its input set to 0 so that no inf enters the program); the first slope
    ``k1`` and the observers' integrands ``g1``, carried from the previous step's end under the previous input, are
    recomputed under ``u``. Returns ``(s, args, u)``."""
    dtype = s.y.dtype
    finite = jnp.all(jnp.isfinite(u), axis=1)
    status = jnp.where((s.status == int(Status.OK)) & ~finite, int(Status.NONFINITE), s.status).astype(jnp.int32)
    u = jnp.where(finite[:, None], u, jnp.zeros((), dtype))
    args = _held_loop(plant, held, u)
    k1, u_at = held.chart.field_and_control(s.t, s.y, args)
    return s._replace(status=status, k1=k1, g1=integrands(observers, s.y, u_at, dtype)), args, u


def _start(y0, plant, ctl: Controls, held: type, observers):
    """The mask of valid starts and the stepper's batch-last state at t = 0 with no input yet (`_hold` puts the first
    one in): a non-finite start is ``INVALID_INPUT`` and replaced by zeros (never stepped). ``T_eps`` is 0 for a
    start already in the ball."""
    valid = jnp.all(jnp.isfinite(y0), axis=1)
    y0 = jnp.where(valid[:, None], y0, jnp.zeros_like(y0))
    status0 = jnp.where(valid, int(Status.OK), int(Status.INVALID_INPUT)).astype(jnp.int32)
    zero = jnp.zeros((2,), y0.dtype)

    def one(y, st, pl):
        return init_state(y, st, ClosedLoop(pl, held(zero)), ctl, 0.0, observers)

    return valid, jax.vmap(one, in_axes=(0, 0, _row_axes(plant)), out_axes=-1)(y0, status0, plant)


def _nan_unless(mask, x):
    """``x`` where ``mask``, NaN elsewhere."""
    return jnp.where(mask, x, jnp.full_like(x, jnp.nan))


def _samples(saved, valid, y0, period, K: int):
    """``(t, q, p, u)`` of a saved run: the instants, the state at them (the start first, NaN for an invalid one)
    and the held inputs, the start on the first axis."""
    ys, us = saved
    y_first = _nan_unless(valid[:, None], y0)
    traj = jnp.concatenate([y_first[:, None], jnp.swapaxes(ys, 0, 1)], axis=1)       # (N, K+1, 5)
    return jnp.arange(K + 1, dtype=y0.dtype) * period, traj[:, :, :3], traj[:, :, 3:], jnp.swapaxes(us, 0, 1)


def _finish(s: StepState, valid, y0, saved, period, K: int, save: bool, observers) -> SampledRun:
    """The `SampledRun` of the stepper's final state: a row that is not OK has NaN summaries and final state."""
    ok = s.status == int(Status.OK)
    y_fin = _nan_unless(ok[:, None], s.y.T)
    values = {k: _nan_unless(ok.reshape(ok.shape + (1,) * (jnp.ndim(v) - 1)), v)        # a row's values: first axis
              for k, v in collect_values(observers, s.obs, s.quad).items()}
    t = q = p = u = None
    if save:
        t, q, p, u = _samples(saved, valid, y0, period, K)
    named = {k: values.get(k) for k in ("T_eps", "u_energy", "u_norm_peak", "min_abs_theta", "u_peak", "u_abs_int",
                                        "max_excursion")}
    return SampledRun(
        t=t, q=q, p=p, u=u, q_final=y_fin[:, :3], p_final=y_fin[:, 3:], status=s.status, n_steps=s.n_accept,
        n_rejected=s.n_reject, summaries=values, **named,
        t_reached=_nan_unless(valid, s.t))


@functools.partial(jax.jit, static_argnames=("K", "delay", "save", "adaptive", "budget", "segment", "observers"))
def _solve(law, plant, y0, period, noise, seed, ctl, *, K, delay, save, adaptive, budget, segment,
           observers=OBSERVERS):
    """`solve_sampled` on checked inputs: one ``lax.scan`` over the ``K`` samples; in each, measure and hold
    (`_control`, `_hold`), then step to the next sample instant in at most ``budget`` attempts, ``segment`` at a
    time (`jaxsleigh.integrate.stepper.Checkpointed`); then the run (`_finish`)."""
    dtype = y0.dtype
    key0 = jax.random.PRNGKey(seed)
    held = held_input_type(physical_chart_for(law))
    valid, s0 = _start(y0, plant, ctl, held, observers)
    buf0 = jnp.zeros((max(delay, 1), y0.shape[0], 2), dtype)

    def sample(s, extra, k):                      # at t_k: measure, evaluate the law, hold its input
        u, buf = _control(law, plant, s.y.T, extra[0], s.status, k, key0, noise, period, delay)
        s, args, u = _hold(s, u, plant, held, observers)
        return s, args, (buf, u)

    def record(s, args, target, extra):
        good = (s.status == int(Status.OK))[:, None]
        return (_nan_unless(good, s.y.T), _nan_unless(good, extra[1])) if save else None

    stops = (jnp.arange(K) + 1).astype(dtype) * period
    s, _, saved = run_stops(s0, stops, None, ctl, adaptive=adaptive, monitor=False, observers=observers,
                            share=budget, segment=segment, block=BLOCK, hook=sample,
                            extra=(buf0, jnp.zeros((y0.shape[0], 2), dtype)), record=record)
    return _finish(s, valid, y0, saved, period, K, save, observers)
