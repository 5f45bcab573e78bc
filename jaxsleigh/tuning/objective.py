r"""The tuner's objective: the soft convergence time integrated differentiably by its own scan over
`jaxsleigh.integrate.stepper.attempt` (see the package docstring for the formulas).

Two kinds of integral ride along one run of the stepper. The control energy \(E = \int \|u\|^2 dt\) is the
engine's own: the `jaxsleigh.integrate.observers.ControlEffort` observer's quadrature row, integrated with each
accepted step's RK4 weights over its stages,

\[ E_{n+1} = E_n + \tfrac{h}{6}\left(g_1 + 2 g_2 + 2 g_3 + g_4\right), \qquad g_j = \|u(y_j)\|^2, \]

and held to the step's tolerances like the state (its embedded estimate is under the same error norm), so that the
tuner's \(E_i\) and \(\max\|u\|\) of a lane are those `jaxsleigh.run_ensemble` and `jaxsleigh.solve` report
for the same steps. The soft time \(S\) and the barrier \(B\) are the objective's own, accumulated by the
trapezoid on the accepted steps from the states at both ends of each (`jaxsleigh.integrate.stepper.run`'s
``accumulate``).
"""
from __future__ import annotations

import functools
from typing import Any, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from ..model.closed_loop import ClosedLoop
from ..integrate.engine import check_ics, initial_w
from ..model.params import PlantParams
from ..status import Status
from ..integrate.observers import ClosestApproach, ControlEffort, Excursion
from ..model.charts import WChart, chart_for
from ..integrate.stepper import Checkpointed, Controls, StepState, controls, init_state, run, starting_step
from ..integrate.stepsize import StepSizeController, check_policy
from ..validate import refuses_removed_keywords

from .params import D_FLOOR, GainParams, gains_from_params, merge_params
from .starts import PlantDistribution, guard_starts, plant_groups

__all__ = ["LossConfig", "LOSS_KEYWORDS", "TRAINING_STEPSIZE", "check_loss_stepsize", "training_max_step",
           "traced_loss", "loss_record",
           "LaneSummary", "TrainingSet", "make_training_set", "valid_starts", "soft_convergence",
           "objective", "loss_from_lanes"]

#: The stepper's observers inside the differentiated objective: only what LaneSummary reports. `ControlEffort` is
#: the engine's (its quadrature rows are under the step's error norm, so the tuner's lanes take the engine's steps).
_OBSERVERS = (ClosestApproach(), Excursion(), ControlEffort())


#: The training integrator of the tuner: the adaptive RK4 at rtol = atol = 1e-5 with steps of at most 0.1 s (ten base
#: steps of 0.01 s; the command line's ``--dt`` sets it to 10 dt).
TRAINING_STEPSIZE = StepSizeController(rtol=1e-5, atol=1e-5, max_step=0.1)


class _LossFields(NamedTuple):
    t_final: float = 30.0
    guard_t_final: float = 10.0
    probe_t_final: float = 100.0
    dt: float = 0.01
    stepsize: StepSizeController = TRAINING_STEPSIZE
    eps: float = 0.05
    temperature: float = 1.0
    stop_fraction: float = 0.5
    theta_barrier: float = 0.02
    barrier_weight: float = 0.1
    guard_weight: float = 0.01
    energy_budget: float = float("inf")
    penalty: float = 10.0
    multiplier: float = 0.0
    dual_step: float = 0.05


#: The keywords `LossConfig` took before jaxsleigh 0.4: ``keyword -> ("stepsize", field)`` of the object that holds it
#: now.
LOSS_KEYWORDS = {k: ("stepsize", k) for k in ("rtol", "atol", "max_step")}


class LossConfig(_LossFields):
    r"""Numbers of the objective and of its integrator (leaves: changing them does not recompile).

    Attributes:
      t_final: training horizon [s] of the main batch.
      guard_t_final: horizon [s] of the guard starts (their danger is early, near theta = 0).
      probe_t_final: horizon [s] of the integration-cost probe and of the final check (the
        validation horizon).
      dt: base (first) step, as `jaxsleigh.solve`'s ``dt``.
      stepsize: `jaxsleigh.StepSizeController` of the training integrator (default `TRAINING_STEPSIZE`: rtol = atol
        = 1e-5, ``max_step`` 0.1 s); its numbers are leaves of the config like the others, its ``method``,
        ``check_passivity`` and ``max_steps`` static (`jaxsleigh.integrate.stepsize.STATIC_FIELDS`). The attempts per
        lane are the tuner's (`TuneConfig.n_attempts`); ``method`` must be ``"adaptive"``, and ``max_steps`` unset.
      eps: radius of the ball ``|q| <= eps``.
      temperature: width ``tau`` of the soft indicator in ``log |q|``.
      stop_fraction: a lane stops once ``|q| <= stop_fraction * eps``.
      theta_barrier, barrier_weight: the singular-set term ``B`` (module docstring) and its weight.
      guard_weight: weight of the guard starts' soft time in the loss.
      energy_budget: \(E_{max}\), the budget on the batch's geometric-mean control energy
        \(\exp(\overline{\log E_i})\), \(E_i = \int |u|^2 dt\) over the lane's integration
        [N^2 s, (N m)^2 s]; ``inf`` (default): no budget, the plain soft convergence time.
      penalty: \(\rho\) of the augmented Lagrangian; multiplier: its \(\lambda \ge 0\)
        (updated by the optimiser loop, see `objective`); dual_step: the loop's step
        \(\eta\) of the multiplier, \(\lambda \leftarrow \max(0, \lambda + \eta g)\).

    ``LossConfig(rtol=...)``, ``atol=``, ``max_step=`` (before jaxsleigh 0.4) are a ``TypeError`` naming
    ``stepsize=jaxsleigh.StepSizeController(...)``.
    """

    __slots__ = ()
    __new__ = refuses_removed_keywords(LOSS_KEYWORDS, {"stepsize": frozenset(StepSizeController._fields)},
                                       "LossConfig's rtol=, atol= and max_step= were removed in jaxsleigh 0.4",
                                       name="LossConfig")(_LossFields.__new__)


def check_loss_stepsize(loss: LossConfig) -> StepSizeController:
    """The training integrator's policy of ``loss``, checked (`jaxsleigh.integrate.stepsize.check_policy`, named
    ``loss.stepsize``): adaptive, and without a ``max_steps`` (the attempts per lane are `TuneConfig.n_attempts`,
    the length of the differentiated scan)."""
    ss = check_policy(loss.stepsize, "loss.stepsize")
    if ss.method != "adaptive":
        raise ValueError(f"loss.stepsize.method must be 'adaptive' (the tuner differentiates the adaptive RK4), got "
                         f"{ss.method!r}")
    if ss.max_steps is not None:
        raise ValueError("loss.stepsize.max_steps is not used by the tuner: its attempts per lane are "
                         "TuneConfig.n_attempts (--n-attempts); leave max_steps unset")
    return ss


def training_max_step(loss: LossConfig) -> float:
    """The largest step of the training integrator: ``loss.stepsize.max_step``, by default
    (`jaxsleigh.integrate.stepsize.MAX_STEP_FACTOR`) 100 base steps ``loss.dt``; the policy checked first
    (`check_loss_stepsize`). What the size check of a gradient run reads (`jaxsleigh.tuning.optimizer.check_sizes`)."""
    return float(check_loss_stepsize(loss).resolved("float32", float(loss.dt)).max_step)


def traced_loss(loss: LossConfig, dtype) -> LossConfig:
    """``loss`` with every number (its step policy's too, `jaxsleigh.integrate.stepsize.STATIC_FIELDS` aside) an
    array of ``dtype``: the leaves a compiled objective takes, so that changing them does not recompile."""
    return jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype), loss)


def loss_record(loss: LossConfig) -> dict:
    """``loss`` as JSON numbers, one key per number, the step policy's ``max_step``, ``rtol`` and ``atol`` in its
    place (``None`` where unset) and any other field of the policy only where it differs from its default: the
    record of the settings files and checkpoints (a tuner's checkpoint written before the policy was an object
    resumes)."""
    out = {}
    for k, v in loss._asdict().items():
        if k != "stepsize":
            out[k] = float(v)
            continue
        base = StepSizeController()
        for f in ("max_step", "rtol", "atol"):
            out[f] = None if getattr(v, f) is None else float(getattr(v, f))
        for f in v._fields:
            if f not in ("max_step", "rtol", "atol") and getattr(v, f) != getattr(base, f):
                value = getattr(v, f)
                out[f] = value if isinstance(value, (str, bool, int)) or value is None else float(value)
    return out


class LaneSummary(NamedTuple):
    r"""Per-lane results of `soft_convergence` (arrays over the batch).

    Attributes:
      soft_time: \(S\) plus the rest of the horizon for lanes that failed [s].
      barrier: the singular-set term \(B\) [s].
      ok: reached the horizon or stopped in the ball, with status OK.
      stopped: stopped in the ball (``|q| <= stop_fraction * eps``).
      t_reached: time reached; for stopped lanes the first passage into the stopping ball.
      status, n_attempts, min_abs_theta, max_excursion: as the stepper reports them.
      u_energy: control energy \(\int |u|^2 dt\) over the lane's integration [N^2 s], differentiable: the
        engine's `jaxsleigh.integrate.observers.ControlEffort` quadrature (each accepted step's RK4 weights over
        its stages); u_norm_peak: largest \(|u|\) at the start and the accepted steps' ends [N] (the names, and
        the values for the same steps, of `jaxsleigh.EnsembleResult`).
    """

    soft_time: jax.Array
    barrier: jax.Array
    ok: jax.Array
    stopped: jax.Array
    t_reached: jax.Array
    status: jax.Array
    n_attempts: jax.Array
    min_abs_theta: jax.Array
    max_excursion: jax.Array
    u_energy: Any = None
    u_norm_peak: Any = None


def soft_indicator(y, eps, tau, chart=WChart()):
    """\\(\\phi(\\log(|q|/\\epsilon)/\\tau)\\), zero inside the ball, from a state in ``chart``."""
    q2 = chart.q_norm2(y)
    u = jnp.maximum(0.5 * (jnp.log(q2 + 1e-30) - 2.0 * jnp.log(eps)) / tau, 0.0)
    return -jnp.expm1(-u * u)


def _near_singular(y, theta_b, chart=WChart()):
    # |w1| = |theta|; the paper's loop is stiff (eigenvalues ~ k / theta^2) and fragile close to it.
    # A law without the singular set pays no barrier.
    if not chart.singular:
        return jnp.zeros(y.shape[1:], y.dtype)
    return jnp.square(jnp.maximum(jnp.log(theta_b) - jnp.log(chart.abs_theta(y) + 1e-30), 0.0))


def soft_convergence(gains, y0w, plant: PlantParams, cfg: LossConfig, *, t_final=None,
                     n_attempts: int, segment: int = 100, adaptive: bool = True) -> LaneSummary:
    r"""Integrate a batch from the w-chart starts ``y0w`` (N, 5) and accumulate the soft convergence
    time \(S\) and the singular-set term \(B\) along it, differentiably.

    ``n_attempts`` attempted steps per lane (static) run as ``ceil(n_attempts / segment)``
    checkpointed segments; a segment in which no lane is active is skipped. ``plant`` leaves may be
    arrays over the batch (robust tuning). ``t_final`` (a scalar or one horizon per lane)
    overrides ``cfg.t_final``.

    ``adaptive=False`` takes fixed RK4 steps of ``cfg.dt`` (for checks). Adaptive lanes start with
    a step of at most \(0.01\,\|y_0\|/\|f(y_0)\|\) (scaled by the
    tolerances, as in Hairer's starting-step rule): from ``|theta0| = 0.05`` a first trial step of
    ``dt`` overflows float32, and although the stepper rejects it, in reverse mode the discarded
    infinities turn the gradient into NaN. The adaptive controller grows the step back within a
    few steps.
    """
    n, dtype = y0w.shape[0], y0w.dtype
    args, ctl, terms = _soft_setup(gains, plant, cfg, t_final, n_attempts, dtype)
    s0 = _initial_states(y0w, args, ctl, adaptive)
    s, soft, bar = _integrate_soft(s0, n, dtype, args, ctl, terms, n_attempts=n_attempts, segment=segment,
                                   adaptive=adaptive)
    return _lane_summary(s, soft, bar, terms)


class _SoftTerms(NamedTuple):
    """The constants of the soft-time integrand, in the batch's dtype: the chart of the gains, the horizon
    ``T``, the ball radius ``eps``, the temperature ``tau``, the barrier angle ``theta_b`` and the squared
    stopping radius ``r_stop2``."""

    chart: Any
    T: jax.Array
    eps: jax.Array
    tau: jax.Array
    theta_b: jax.Array
    r_stop2: jax.Array


def _soft_setup(gains, plant, cfg: LossConfig, t_final, n_attempts, dtype):
    """The closed loop, the stepper's controls and the integrand's `_SoftTerms` of `soft_convergence`."""
    plant = jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), plant)
    chart = chart_for(gains)
    gains = jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), gains)
    args = ClosedLoop(plant, gains)
    ctl = controls(cfg.stepsize, dtype, dt=cfg.dt, eps=cfg.eps, max_steps=n_attempts)
    T = jnp.asarray(cfg.t_final if t_final is None else t_final, dtype)
    eps, tau = jnp.asarray(cfg.eps, dtype), jnp.asarray(cfg.temperature, dtype)
    theta_b = jnp.asarray(cfg.theta_barrier, dtype)
    r_stop2 = jnp.square(jnp.asarray(cfg.stop_fraction, dtype) * eps)
    return args, ctl, _SoftTerms(chart, T, eps, tau, theta_b, r_stop2)


def _initial_states(y0w, args: ClosedLoop, ctl: Controls, adaptive: bool, observers=_OBSERVERS) -> StepState:
    """The batch's stepper states (batch-last) at the starts ``y0w`` with ``observers``, with the starting step when
    adaptive (`soft_convergence`; `jaxsleigh.tuning.event_time.settling`)."""
    n = y0w.shape[0]
    plant_axes = jax.tree_util.tree_map(lambda x: 0 if np.ndim(x) >= 1 else None, args.plant)   # per lane or shared
    in_axes = (0, 0, ClosedLoop(plant_axes, None), None)
    s0 = jax.vmap(functools.partial(init_state, observers=observers), in_axes=in_axes,
                  out_axes=-1)(y0w, jnp.zeros(n, jnp.int32), args, ctl)
    if adaptive:
        s0 = starting_step(s0, ctl)
    return s0


def _target_of(s: StepState, terms: _SoftTerms):
    """Each lane's target time: ``T``, or its own time once in the stopping ball (a stopped lane idles)."""
    stop = jax.lax.stop_gradient(terms.chart.q_norm2(s.y) <= terms.r_stop2)
    return jnp.where(stop, s.t, terms.T)


def _soft_and_barrier(soft, bar, h, y0, y1, terms: _SoftTerms):
    """``S`` and ``B`` advanced by the trapezoid over a step of length ``h`` from ``y0`` to ``y1``."""
    eps, tau, theta_b, chart = terms.eps, terms.tau, terms.theta_b, terms.chart
    phi0, phi1 = soft_indicator(y0, eps, tau, chart), soft_indicator(y1, eps, tau, chart)
    soft = soft + h * 0.5 * (phi0 + phi1)
    bar = bar + h * 0.5 * (phi0 * _near_singular(y0, theta_b, chart) + phi1 * _near_singular(y1, theta_b, chart))
    return soft, bar


def _integrate_soft(s0, n, dtype, args: ClosedLoop, ctl: Controls, terms: _SoftTerms, *, n_attempts: int,
                    segment: int, adaptive: bool):
    """The checkpointed segments of `soft_convergence` (`jaxsleigh.integrate.stepper.Checkpointed`, a lane
    idling once in the stopping ball): ``(state, S, B)``; the control energy is the state's quadrature row of
    `ControlEffort` (`_lane_summary`)."""
    def accumulate(acc, s, s_new):
        soft, bar = acc
        h = (s_new.t - s.t) + (s_new.t_lo - s.t_lo)       # 0 unless accepted; no gradient (times are fixed)
        return _soft_and_barrier(soft, bar, h, s.y, s_new.y, terms)

    zeros = jnp.zeros(n, dtype)
    s, (soft, bar) = run(s0, lambda s: _target_of(s, terms), args, ctl, Checkpointed(n_attempts, segment),
                         adaptive=adaptive, observers=_OBSERVERS, accumulate=accumulate, acc=(zeros, zeros))
    return s, soft, bar


def _lane_summary(s: StepState, soft, bar, terms: _SoftTerms) -> LaneSummary:
    """The `LaneSummary` of the final states ``s`` (their observers: ``_OBSERVERS``) and the accumulated ``S``,
    ``B``."""
    T = terms.T
    stopped = terms.chart.q_norm2(s.y) <= terms.r_stop2
    ok = (s.status == Status.OK) & (stopped | (s.t >= T))
    # a failed lane counts as never converging for the rest of the horizon (value only)
    soft = soft + jax.lax.stop_gradient(jnp.where(ok, 0.0, jnp.maximum(T - s.t, 0.0)))
    (min_abs_theta,), (max_q2,), (_, _, u_norm_peak) = s.obs
    return LaneSummary(soft, bar, ok, stopped, s.t, s.status, s.n_accept + s.n_reject, min_abs_theta,
                       jnp.sqrt(max_q2), u_energy=s.quad[0], u_norm_peak=u_norm_peak)


class TrainingSet(NamedTuple):
    """Starts of the objective, mapped to the w chart.

    Attributes:
      groups: ``((y0w (n_g, 5), plant), ...)``, one per plant group (one for a single plant).
      guard: (n_guard, 5) w-chart guard starts. They run as extra lanes of the first group's scan
        (one compiled integrator) with their own horizon, on the plant of that group's first lane
        (the paper's plant when tuning for a single plant).
    """

    groups: tuple
    guard: Any


def make_training_set(ics, *, plant: Optional[PlantParams] = None, robust: Optional[PlantDistribution] = None,
                      guard=None, seed: int = 0, dtype=None) -> TrainingSet:
    """Validate the starts and map them to the w chart (float64 then ``dtype``, default: working dtype).

    With ``robust`` the lanes are spread over plants sampled from it (``seed``), else all use
    ``plant`` (default: the paper's). ``guard`` defaults to `guard_starts`; pass an empty
    array for none.
    """
    dtype = jnp.zeros(()).dtype if dtype is None else dtype
    ics5, status0 = valid_starts(ics)
    guard = guard_starts() if guard is None else np.asarray(guard, dtype=np.float64)
    guard_w = initial_w(*valid_starts(guard, "guard starts"), dtype) if guard.size else jnp.zeros((0, 5), dtype)
    groups = tuple((initial_w(ics5[idx], status0[idx], dtype), p)
                   for idx, p, _ in plant_groups(ics5.shape[0], plant, robust, seed))
    return TrainingSet(groups, guard_w)


def valid_starts(starts, what: str = "training starts", why: str = "finite, theta0 != 0", **check) -> tuple:
    """``(ics5, status)`` of ``starts`` (`jaxsleigh.integrate.engine.check_ics`, ``check`` its keywords), refusing any
    start that is not valid (``ValueError``: "``what`` must all be valid (``why``)")."""
    ics5, status = check_ics(starts, **check)
    if np.any(status != Status.OK):
        raise ValueError(f"{what} must all be valid ({why})")
    return ics5, status


def objective(trainable: dict, frozen: GainParams, data: TrainingSet, cfg: LossConfig, *, n_attempts: int,
              segment: int = 100, adaptive: bool = True, d_floor: float = D_FLOOR):
    r"""The scalar loss and its diagnostics: the soft convergence time subject to an effort budget.

    \[ f = \frac{1}{N T}\sum_i (S_i + w_B B_i) + \frac{w_g}{N_g T_g}\sum_{j \in \text{guard}} S_j, \qquad g = \frac1N \sum_i \log E_i - \log E_{max} \le 0, \]

    \[ \mathcal{L} = f + \lambda \bar g + \tfrac{\rho}{2} \bar g^2, \qquad \bar g = \max(g, -\lambda / \rho) \]

    (the augmented Lagrangian of the inequality in Rockafellar's form: it equals
    \(f - \lambda^2 / 2\rho\) where the budget is slack, and its gradient is continuous).
    \(E_i = \int |u|^2 dt\) is integrated in the same run as \(S_i\) by the engine's quadrature (the
    `ControlEffort` observer: each accepted step's RK4 weights over its stages, the module docstring),
    differentiable; \(S_i\) and \(B_i\) by the trapezoid on the accepted steps. With
    ``cfg.energy_budget = inf`` and ``multiplier = 0``, \(\mathcal{L} = f\) exactly (the unconstrained objective).

    **Why a budget, not a weighted sum.** Time alone is ill-posed (larger gains are faster until the
    integrator breaks), and the question users ask is "how fast for this much effort": a budget in
    the units they budget in (control energy, the paper's gains' as the reference) answers it
    directly and reaches the non-convex parts of the front that a weighted sum
    \(f + w \log E\) cannot. The budget is on the geometric mean (log-energies span two decades
    between the paper's gains and ``tuned``; the mean of logs is smooth, scale-free and close to the
    log of the median that validation reports). The multiplier is the optimiser loop's dual state
    (`tune`: \(\lambda \leftarrow \max(0, \lambda + \eta g)\) after each
    valid candidate, \(\eta\) = ``dual_step``) and a leaf of ``cfg``: it changes without
    recompiling, and it vmaps over budgets.

    Returns ``(loss, aux)`` with ``aux = {"lanes": LaneSummary over the main batch, "guard":
    LaneSummary over the guard starts (or None), "valid": every lane OK and f finite, "soft": f,
    "energy": the geometric-mean energy, "constraint": g}``.
    ``adaptive=False`` integrates with fixed RK4 steps of ``cfg.dt`` instead (for checks: its
    gradient is the exact derivative of the discrete objective).
    """
    g = gains_from_params(merge_params(trainable, frozen), d_floor=d_floor)
    n_guard = data.guard.shape[0]
    parts = []
    for j, (y0w, plant) in enumerate(data.groups):
        n = y0w.shape[0]
        horizon = jnp.full(n, cfg.t_final, y0w.dtype)
        if j == 0 and n_guard:
            # guard lanes ride along in the first group's scan, on its first lane's plant (_first_lane)
            y0w = jnp.concatenate([y0w, data.guard.astype(y0w.dtype)])
            plant = jax.tree_util.tree_map(
                lambda x: jnp.concatenate([x, jnp.repeat(x[:1], n_guard)]) if np.ndim(x) >= 1 else x, plant)
            horizon = jnp.concatenate([horizon, jnp.full(n_guard, cfg.guard_t_final, y0w.dtype)])
        parts.append(soft_convergence(g, y0w, plant, cfg, t_final=horizon, n_attempts=n_attempts,
                                      segment=segment, adaptive=adaptive))
    guard = None
    if n_guard:
        n0 = data.groups[0][0].shape[0]
        guard = jax.tree_util.tree_map(lambda x: x[n0:], parts[0])
        parts[0] = jax.tree_util.tree_map(lambda x: x[:n0], parts[0])
    lanes = jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs), *parts) if len(parts) > 1 else parts[0]
    return loss_from_lanes(lanes, guard, cfg)


def loss_from_lanes(lanes: LaneSummary, guard: Optional[LaneSummary], cfg: LossConfig):
    """The loss of `objective` from the lanes' summaries (the formulas there): ``(loss, aux)``."""
    T = jnp.asarray(cfg.t_final, lanes.soft_time.dtype)
    loss = jnp.mean(lanes.soft_time + cfg.barrier_weight * lanes.barrier) / T
    valid = jnp.all(lanes.ok)
    if guard is not None:
        loss = loss + cfg.guard_weight * jnp.mean(guard.soft_time) / jnp.asarray(cfg.guard_t_final, T.dtype)
        valid = valid & jnp.all(guard.ok)
    valid = valid & jnp.isfinite(loss)
    # the effort budget: g = mean_i log E_i - log E_max <= 0 (the geometric mean, a smooth stand-in for
    # the median that validation reports), by an augmented Lagrangian (Rockafellar's form for an inequality)
    log_e = jnp.mean(jnp.log(lanes.u_energy + 1e-12))
    g_c = log_e - jnp.log(jnp.asarray(cfg.energy_budget, log_e.dtype))
    lam = jnp.asarray(cfg.multiplier, log_e.dtype)
    rho = jnp.asarray(cfg.penalty, log_e.dtype)
    g_s = jnp.maximum(g_c, -lam / rho)
    total = loss + lam * g_s + 0.5 * rho * g_s * g_s
    return total, {"lanes": lanes, "guard": guard, "valid": valid, "soft": loss, "energy": jnp.exp(log_e),
                   "constraint": g_c}
