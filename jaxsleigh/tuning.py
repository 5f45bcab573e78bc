r"""Differentiable tuning of the controller's gains: objective, parametrisation, gradients, optimiser.

**Objective.** The hard convergence time :math:`T_\epsilon` (first time after which
:math:`|q| \le \epsilon` holds) is piecewise constant in the gains. Its smooth surrogate is the time
a trajectory spends outside the ball, weighted by a soft indicator that is exactly zero inside it:

.. math::
    S = \int_0^{T} \phi\big(\log(|q(t)| / \epsilon) / \tau\big)\,dt, \qquad
    \phi(u) = 1 - e^{-u^2}\ (u > 0), \quad \phi(u) = 0\ (u \le 0),

averaged over a batch of starts (``tau`` is the temperature: the band
:math:`\epsilon < |q| \lesssim \epsilon e^{2\tau}` where the indicator rises). A lane stops once
:math:`|q| \le` ``stop_fraction`` :math:`\cdot\,\epsilon`: after that the closed loop only gets stiffer
(the injected damping :math:`k / w_1^2` grows without bound as :math:`\theta \to 0`), and since
:math:`\phi = 0` there the stopped integral has the same value and exact gradient as the full one as
long as the trajectory stays in the ball (validation with the accurate engine checks that it does).

**Numerical safety.** Lanes are integrated in the w chart by the engine's adaptive RK4
(:func:`jaxsleigh.stepper.attempt`: steps that cross :math:`\theta = 0`, go non-finite or increase
:math:`H_d` are rejected and retried smaller) with a fixed budget of attempts per lane, as one
differentiable ``lax.scan``. A lane that does not reach its horizon within the budget (too stiff)
or fails is charged the rest of the horizon and makes the candidate *invalid*. A differentiable
term keeps unconverged trajectories away from the singular set, where the loop is stiff:

.. math:: B = \int_0^{T} \phi(\cdot)\, \max\big(0, \log(\theta_b / |\theta|)\big)^2\,dt .

**Integration cost.** Faster convergence has a price after convergence: as :math:`\theta \to 0` the
closed loop's eigenvalues grow like :math:`k / \theta^2` and :math:`\sqrt{L} / \theta`, and with stronger
gains :math:`\theta` gets small sooner, so the steps needed for a fixed horizon grow quickly (left
alone, the optimiser drives the gains up until 100 s need ~10^5 adaptive steps and the engine's
default budget runs out). Each candidate is therefore also *probed*: the training starts that need
the most steps (an active set, re-found every ``probe_refresh`` accepted candidates by running the
whole training batch) are integrated over the validation horizon (100 s) by the accurate engine
with a budget of ``probe_budget`` attempted steps each (half the engine's default); a start that
needs more makes the candidate invalid. In effect the tuner minimises the soft convergence time
subject to "every training start needs at most ``probe_budget`` steps for 100 s".

The optimiser loop (:func:`tune`) rejects every invalid candidate (non-OK lane, non-finite loss or
gradient, on the training batch and on a *guard* set of starts with :math:`|\theta_0|` down to
0.05, failed probe), backtracks to the last valid point with a halved step, and returns the best
valid gains that also pass a final check with the accurate engine over the validation horizon.

**Parametrisation** (always admissible, see :class:`GainParams`):
:math:`L = e^{\ell}`, :math:`k = e^{\kappa}`, :math:`\hat D = C C^\top + \delta I` with
:math:`C = \begin{bmatrix} e^{c_0} & 0 \\ c_1 & e^{c_2} \end{bmatrix}`.

**Gradients** go through the integrator (the adaptive step sizes are ``stop_gradient``'ed in the
stepper, so this is the exact derivative of the discrete map with its step sequence frozen):
reverse mode with ``jax.checkpoint`` over segments of the scan (memory grows with the number of
segments plus one segment's residuals, not with the number of steps) or forward mode
(``jax.jacfwd``, one tangent per free parameter, memory independent of the number of steps).
``experiments/bench_gradients.py`` measures both: for the 7 gain parameters, 10^4 steps and 256
starts (float32, 2 CPU cores), forward mode took 2.0 s and 0.4 MB of XLA temporaries against
3.2 s and 20 MB for checkpointed reverse mode (5.3 s and 1.8 GB without checkpointing), so
forward mode is the default. Reverse mode's cost does not grow with the number of parameters;
it wins from roughly a dozen of them.
"""
from __future__ import annotations

import functools
import math
import sys
import time
from pathlib import Path
from typing import Any, Callable, NamedTuple, Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.flatten_util import ravel_pytree

from .closed_loop import ClosedLoop
from .damping import CoulombDamping, NoDamping, ViscousDamping
from .engine import check_ics, initial_w
from .params import Gains, PlantParams, gains as make_gains, gains_to_dict, load_gains, paper_plant
from .status import Status
from .stepper import Controls, StepState, attempt, init_state, is_active, q_norm2_w

__all__ = [
    "GainParams", "TUNABLE", "D_FLOOR", "params_from_gains", "gains_from_params", "parse_tune", "split_params",
    "merge_params",
    "UniformStarts", "guard_starts", "sample_starts",
    "PlantDistribution", "sample_plants", "validation_plants",
    "LossConfig", "LaneSummary", "TrainingSet", "make_training_set", "soft_convergence", "objective",
    "make_value_and_grad", "GRADIENT_MODES",
    "TuneConfig", "TuneHistory", "TuneResult", "TuningInterrupted", "make_optimizer", "tune", "save_history",
    "load_history",
    "Validation", "validate", "markdown_table",
]

#: Gains that can be tuned, each mapped to its unconstrained field of :class:`GainParams`.
TUNABLE = {"L": "log_L", "k": "log_k", "D_hat": "d_chol"}
#: Floor :math:`\delta` of :math:`\hat D = C C^\top + \delta I` (its smallest eigenvalue is >= this).
D_FLOOR = 1e-3
GRADIENT_MODES = ("reverse", "forward")


# ---------------------------------------------------------------------------------------------
# parametrisation
# ---------------------------------------------------------------------------------------------

class GainParams(NamedTuple):
    r"""Unconstrained coordinates of :class:`~jaxsleigh.params.Gains`; every value is admissible.

    .. math:: L = \mathrm{diag}(e^{\ell_1}, e^{\ell_2}, e^{\ell_3}),\quad k = e^{\kappa},\quad
              \hat D = C C^\top + \delta I,\ C = \begin{bmatrix} e^{c_0} & 0\\ c_1 & e^{c_2}\end{bmatrix}

    Attributes:
      log_L: (3,) :math:`\ell`.
      log_k: () :math:`\kappa`.
      d_chol: (3,) :math:`(c_0, c_1, c_2)`; the floor :math:`\delta` is not a parameter.
    """

    log_L: Any
    log_k: Any
    d_chol: Any


def gains_from_params(theta: GainParams, *, d_floor: float = D_FLOOR) -> Gains:
    """Map unconstrained parameters to gains: ``L > 0``, ``k > 0``, ``D_hat`` symmetric with
    eigenvalues ``>= d_floor`` for every finite ``theta`` (traceable)."""
    L = jnp.exp(theta.log_L)
    k = jnp.exp(theta.log_k)
    c = theta.d_chol
    a, b, d = jnp.exp(c[0]), c[1], jnp.exp(c[2])
    D = jnp.stack([jnp.stack([a * a + d_floor, a * b]), jnp.stack([a * b, b * b + d * d + d_floor])])
    return Gains(L, k, D)


def params_from_gains(g, *, d_floor: float = D_FLOOR) -> GainParams:
    """Inverse of :func:`gains_from_params` (eager, float64 NumPy); ``g`` may be gains or a preset
    name / JSON path. Raises if ``D_hat - d_floor I`` is not positive definite."""
    g = load_gains(g)
    D = np.asarray(g.D_hat, dtype=np.float64) - d_floor * np.eye(2)
    try:
        C = np.linalg.cholesky(D)
    except np.linalg.LinAlgError:
        raise ValueError(f"D_hat = {np.asarray(g.D_hat).tolist()} has an eigenvalue below the floor "
                         f"{d_floor}; use a larger D_hat or a smaller d_floor") from None
    return GainParams(np.log(np.asarray(g.L, dtype=np.float64)), np.float64(np.log(float(g.k))),
                      np.array([np.log(C[0, 0]), C[1, 0], np.log(C[1, 1])]))


def parse_tune(spec) -> tuple[str, ...]:
    """``'L,k'`` / ``('L', 'D_hat')`` / ``None`` (all) -> a tuple of names from :data:`TUNABLE`."""
    if spec is None:
        return tuple(TUNABLE)
    names = [s.strip() for s in (spec.split(",") if isinstance(spec, str) else spec)]
    names = [s for s in names if s]
    bad = [s for s in names if s not in TUNABLE]
    if bad or not names:
        raise ValueError(f"gains to tune must be a non-empty subset of {', '.join(TUNABLE)} "
                         f"(e.g. 'L,k'), got {spec!r}")
    return tuple(s for s in TUNABLE if s in names)


def split_params(theta: GainParams, tune) -> tuple[dict, GainParams]:
    """``(trainable, frozen)``: a dict of the tuned fields and the whole parameter tuple."""
    names = parse_tune(tune)
    return {TUNABLE[n]: theta._asdict()[TUNABLE[n]] for n in names}, theta


def merge_params(trainable: dict, frozen: GainParams) -> GainParams:
    """The parameters with the tuned fields taken from ``trainable`` and the rest from ``frozen``."""
    return frozen._replace(**trainable)


# ---------------------------------------------------------------------------------------------
# starts and plants
# ---------------------------------------------------------------------------------------------

class UniformStarts(NamedTuple):
    """Starts with ``x, y`` uniform in ``(-xy, xy)``, ``|theta0|`` uniform in ``(theta_min, theta_max)``
    with a random sign and zero momentum (the issue's "typical starts")."""

    xy: float = 3.0
    theta_min: float = 0.3
    theta_max: float = math.pi

    def __call__(self, rng: np.random.Generator, n: int) -> np.ndarray:
        xy = rng.uniform(-self.xy, self.xy, size=(n, 2))
        th = rng.choice([-1.0, 1.0], size=n) * rng.uniform(self.theta_min, self.theta_max, size=n)
        return np.column_stack([xy, th])


def sample_starts(starts, n: int, seed: int) -> np.ndarray:
    """``n`` starts ``(n, 3|5)`` from ``starts``: a sampler ``(rng, n) -> array`` (e.g.
    :class:`UniformStarts`) or a fixed array (whose first ``n`` rows are used)."""
    if callable(starts):
        arr = np.asarray(starts(np.random.default_rng(seed), int(n)), dtype=np.float64)
    else:
        arr = np.asarray(starts, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[0] < n:
            raise ValueError(f"a fixed set of starts needs at least {n} rows of (x, y, theta[, p1, p2]), "
                             f"got shape {arr.shape}")
        arr = arr[:n]
    check_ics(arr)
    return arr


def guard_starts(theta0: Sequence[float] = (0.05, 0.1), xy: float = 3.0) -> np.ndarray:
    """Hard starts near the singular set: ``(+-xy, +-xy)`` corners, each with ``+-theta0`` of each
    size (signs alternate). They carry huge ``H_d(0)`` and are stiff; the tuner requires them to
    stay integrable (status OK, finite loss and gradient)."""
    rows = []
    for j, th in enumerate(theta0):
        for i, (sx, sy) in enumerate(((1, 1), (-1, 1), (1, -1), (-1, -1))):
            rows.append((sx * xy, sy * xy, (-1) ** (i + j) * th))
    return np.asarray(rows, dtype=np.float64)


class PlantDistribution(NamedTuple):
    """Plants for robust tuning: ``m, J, l`` log-uniform in the ranges; lanes are spread evenly over
    the damping models in ``dampings``, each with a scale log-uniform in ``damping_scale``
    (Coulomb's ``scale``; viscous ``c1, c2``; ``'none'`` has no parameter)."""

    m: tuple = (1.0, 4.0)
    J: tuple = (0.5, 2.0)
    l: tuple = (0.5, 1.5)
    dampings: tuple = ("coulomb", "viscous", "none")
    damping_scale: tuple = (0.5, 2.0)


def _log_uniform(rng, lo_hi, n):
    lo, hi = lo_hi
    return np.exp(rng.uniform(np.log(lo), np.log(hi), size=n))


def sample_plants(dist: PlantDistribution, n: int, seed: int) -> list[tuple[np.ndarray, PlantParams]]:
    """``[(lane_indices, plant), ...]``: one group per damping model, whose ``PlantParams`` leaves are
    arrays over the group's lanes (the stepper broadcasts them along the batch axis)."""
    rng = np.random.default_rng(seed)
    kinds = tuple(dist.dampings)
    if not kinds:
        raise ValueError("PlantDistribution.dampings must name at least one damping model")
    out = []
    for j, kind in enumerate(kinds):
        idx = np.arange(j, n, len(kinds))
        if idx.size == 0:
            continue
        m, J, l = (_log_uniform(rng, r, idx.size) for r in (dist.m, dist.J, dist.l))
        s = _log_uniform(rng, dist.damping_scale, idx.size)
        if kind == "coulomb":
            damping = CoulombDamping(0.1, s)
        elif kind == "viscous":
            damping = ViscousDamping(s, _log_uniform(rng, dist.damping_scale, idx.size))
        elif kind == "none":
            damping = NoDamping()
        else:
            raise ValueError(f"unknown damping {kind!r}; use coulomb, viscous or none")
        out.append((idx, PlantParams(m, J, l, damping)))
    return out


def validation_plants() -> dict[str, PlantParams]:
    """Named plants for the per-plant validation table (paper's plant first)."""
    from .params import plant_params

    return {
        "paper (m 2, J 1, l 1, Coulomb)": plant_params(2.0, 1.0, 1.0, "coulomb"),
        "heavy (m 4, J 2, l 1, Coulomb)": plant_params(4.0, 2.0, 1.0, "coulomb"),
        "light (m 1, J 0.5, l 0.5, Coulomb)": plant_params(1.0, 0.5, 0.5, "coulomb"),
        "long (m 2, J 1, l 1.5, Coulomb x2)": plant_params(2.0, 1.0, 1.5, CoulombDamping(0.1, 2.0)),
        "paper inertia, viscous": plant_params(2.0, 1.0, 1.0, "viscous"),
        "paper inertia, no damping": plant_params(2.0, 1.0, 1.0, "none"),
    }


# ---------------------------------------------------------------------------------------------
# the objective
# ---------------------------------------------------------------------------------------------

class LossConfig(NamedTuple):
    """Numbers of the objective and of its integrator (leaves: changing them does not recompile).

    Attributes:
      t_final: training horizon [s] of the main batch.
      guard_t_final: horizon [s] of the guard starts (their danger is early, near theta = 0).
      probe_t_final: horizon [s] of the integration-cost probe and of the final check (the
        validation horizon).
      dt: base (first) step; max_step: largest step; rtol, atol: tolerances of the adaptive RK4.
      eps: radius of the ball ``|q| <= eps``.
      temperature: width ``tau`` of the soft indicator in ``log |q|``.
      stop_fraction: a lane stops once ``|q| <= stop_fraction * eps``.
      theta_barrier, barrier_weight: the singular-set term ``B`` (module docstring) and its weight.
      guard_weight: weight of the guard starts' soft time in the loss.
    """

    t_final: float = 30.0
    guard_t_final: float = 10.0
    probe_t_final: float = 100.0
    dt: float = 0.01
    max_step: float = 0.1
    rtol: float = 1e-5
    atol: float = 1e-5
    eps: float = 0.05
    temperature: float = 1.0
    stop_fraction: float = 0.5
    theta_barrier: float = 0.02
    barrier_weight: float = 0.1
    guard_weight: float = 0.01


class LaneSummary(NamedTuple):
    """Per-lane results of :func:`soft_convergence` (arrays over the batch).

    Attributes:
      soft_time: :math:`S` plus the rest of the horizon for lanes that failed [s].
      barrier: the singular-set term :math:`B` [s].
      ok: reached the horizon or stopped in the ball, with status OK.
      stopped: stopped in the ball (``|q| <= stop_fraction * eps``).
      t: time reached; for stopped lanes the first passage into the stopping ball.
      status, n_attempts, min_abs_theta, max_q: as the stepper reports them.
    """

    soft_time: jax.Array
    barrier: jax.Array
    ok: jax.Array
    stopped: jax.Array
    t: jax.Array
    status: jax.Array
    n_attempts: jax.Array
    min_abs_theta: jax.Array
    max_q: jax.Array


def _soft_indicator(y, eps, tau):
    """:math:`\\phi(\\log(|q|/\\epsilon)/\\tau)`, zero inside the ball, from a w-chart state."""
    q2 = q_norm2_w(y[:3])
    u = jnp.maximum(0.5 * (jnp.log(q2 + 1e-30) - 2.0 * jnp.log(eps)) / tau, 0.0)
    return -jnp.expm1(-u * u)


def _near_singular(y, theta_b):
    # |w1| = |theta|; the loop is stiff (eigenvalues ~ k / theta^2) and fragile close to it
    return jnp.square(jnp.maximum(jnp.log(theta_b) - jnp.log(jnp.abs(y[0]) + 1e-30), 0.0))


def _plant_axes(plant: PlantParams):
    return jax.tree_util.tree_map(lambda x: 0 if np.ndim(x) >= 1 else None, plant)


def _cast_plant(plant: PlantParams, dtype):
    return jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), plant)


def soft_convergence(gains: Gains, y0w, plant: PlantParams, cfg: LossConfig, *, t_final=None,
                     n_attempts: int, segment: int = 100, adaptive: bool = True) -> LaneSummary:
    r"""Integrate a batch from the w-chart starts ``y0w`` (N, 5) and accumulate the soft convergence
    time :math:`S` and the singular-set term :math:`B` along it, differentiably.

    ``n_attempts`` attempted steps per lane (static) run as ``ceil(n_attempts / segment)``
    checkpointed segments; a segment in which no lane is active is skipped. ``plant`` leaves may be
    arrays over the batch (robust tuning). ``t_final`` (a scalar or one horizon per lane)
    overrides ``cfg.t_final``.

    ``adaptive=False`` takes fixed RK4 steps of ``cfg.dt`` (for checks). Adaptive lanes start with
    a step of at most :math:`0.01\,\|y_0\|/\|f(y_0)\|` (scaled by the
    tolerances, as in Hairer's starting-step rule): from ``|theta0| = 0.05`` a first trial step of
    ``dt`` overflows float32, and although the stepper rejects it, in reverse mode the discarded
    infinities turn the gradient into NaN. The adaptive controller grows the step back within a
    few steps.
    """
    dtype = y0w.dtype
    n = y0w.shape[0]
    plant = _cast_plant(plant, dtype)
    gains = Gains(*(jnp.asarray(x, dtype) for x in gains))
    args = ClosedLoop(plant, gains)
    ctl = Controls(*(jnp.asarray(v, dtype) for v in (cfg.dt, cfg.max_step, cfg.rtol, cfg.atol, cfg.eps)),
                   max_steps=jnp.asarray(n_attempts, jnp.int32))
    T = jnp.asarray(cfg.t_final if t_final is None else t_final, dtype)
    eps, tau = jnp.asarray(cfg.eps, dtype), jnp.asarray(cfg.temperature, dtype)
    theta_b = jnp.asarray(cfg.theta_barrier, dtype)
    r_stop2 = jnp.square(jnp.asarray(cfg.stop_fraction, dtype) * eps)
    in_axes = (0, 0, ClosedLoop(_plant_axes(plant), None), None)
    s0 = jax.vmap(init_state, in_axes=in_axes, out_axes=-1)(y0w, jnp.zeros(n, jnp.int32), args, ctl)
    if adaptive:
        sc = ctl.atol + ctl.rtol * jnp.abs(s0.y)
        d0 = jnp.sqrt(jnp.mean(jnp.square(s0.y / sc), axis=0))
        d1 = jnp.sqrt(jnp.mean(jnp.square(s0.k1 / sc), axis=0))
        h0 = jax.lax.stop_gradient(jnp.where(d1 > 0, 0.01 * d0 / jnp.maximum(d1, 1e-30), s0.h))
        s0 = s0._replace(h=jnp.clip(h0, 1e-6 * ctl.dt, s0.h).astype(dtype))

    def target_of(s: StepState):
        # a lane in the stopping ball idles: its target is where it is
        stop = jax.lax.stop_gradient(q_norm2_w(s.y[:3]) <= r_stop2)
        return jnp.where(stop, s.t, T)

    def body(carry, _):
        s, soft, bar = carry
        s_new = attempt(s, target_of(s), args, ctl, adaptive=adaptive)
        h = (s_new.t - s.t) + (s_new.t_lo - s.t_lo)       # 0 unless accepted; no gradient (times are fixed)
        phi0, phi1 = _soft_indicator(s.y, eps, tau), _soft_indicator(s_new.y, eps, tau)
        soft = soft + h * 0.5 * (phi0 + phi1)
        bar = bar + h * 0.5 * (phi0 * _near_singular(s.y, theta_b) + phi1 * _near_singular(s_new.y, theta_b))
        return (s_new, soft, bar), None

    @functools.partial(jax.checkpoint, prevent_cse=False)
    def run_segment(carry):
        return jax.lax.scan(body, carry, None, length=segment)[0]

    def outer(carry, _):
        s = carry[0]
        busy = jnp.any(is_active(s, target_of(s), ctl))
        return jax.lax.cond(busy, run_segment, lambda c: c, carry), None

    zeros = jnp.zeros(n, dtype)
    (s, soft, bar), _ = jax.lax.scan(outer, (s0, zeros, zeros), None, length=-(-int(n_attempts) // segment))
    stopped = q_norm2_w(s.y[:3]) <= r_stop2
    ok = (s.status == Status.OK) & (stopped | (s.t >= T))
    # a failed lane counts as never converging for the rest of the horizon (value only)
    soft = soft + jax.lax.stop_gradient(jnp.where(ok, 0.0, jnp.maximum(T - s.t, 0.0)))
    return LaneSummary(soft, bar, ok, stopped, s.t, s.status, s.n_accept + s.n_reject, s.min_abs_theta,
                       jnp.sqrt(s.max_q2))


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
    ``plant`` (default: the paper's). ``guard`` defaults to :func:`guard_starts`; pass an empty
    array for none.
    """
    dtype = jnp.zeros(()).dtype if dtype is None else dtype
    ics5, status0 = check_ics(ics)
    if np.any(status0 != Status.OK):
        raise ValueError("training starts must all be valid (finite, theta0 != 0)")
    guard = guard_starts() if guard is None else np.asarray(guard, dtype=np.float64)
    if guard.size:
        g5, gs = check_ics(guard)
        if np.any(gs != Status.OK):
            raise ValueError("guard starts must all be valid (finite, theta0 != 0)")
        guard_w = initial_w(g5, gs, dtype)
    else:
        guard_w = jnp.zeros((0, 5), dtype)
    groups = tuple((initial_w(ics5[idx], status0[idx], dtype), p)
                   for idx, p, _ in _plant_groups(ics5.shape[0], plant, robust, seed))
    return TrainingSet(groups, guard_w)


def _first_lane(plant: PlantParams) -> PlantParams:
    return jax.tree_util.tree_map(lambda x: x[0] if np.ndim(x) >= 1 else x, plant)


def _plant_groups(n: int, plant, robust, seed) -> list:
    """``[(lane indices, group plant, plant of its first lane), ...]`` (one group for one plant)."""
    if robust is None:
        plant = paper_plant() if plant is None else plant
        return [(np.arange(n), plant, plant)]
    return [(idx, p, _first_lane(p)) for idx, p in sample_plants(robust, n, seed)]


def objective(trainable: dict, frozen: GainParams, data: TrainingSet, cfg: LossConfig, *, n_attempts: int,
              segment: int = 100, adaptive: bool = True, d_floor: float = D_FLOOR):
    r"""The scalar loss and its diagnostics.

    .. math:: \mathcal{L} = \frac{1}{N T}\sum_i (S_i + w_B B_i)
              + \frac{w_g}{N_g T_g}\sum_{j \in \text{guard}} S_j

    Returns ``(loss, aux)`` with ``aux = {"lanes": LaneSummary over the main batch, "guard":
    LaneSummary over the guard starts (or None), "valid": every lane OK and the loss finite}``.
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
    T = jnp.asarray(cfg.t_final, lanes.soft_time.dtype)
    loss = jnp.mean(lanes.soft_time + cfg.barrier_weight * lanes.barrier) / T
    valid = jnp.all(lanes.ok)
    if guard is not None:
        loss = loss + cfg.guard_weight * jnp.mean(guard.soft_time) / jnp.asarray(cfg.guard_t_final, T.dtype)
        valid = valid & jnp.all(guard.ok)
    valid = valid & jnp.isfinite(loss)
    return loss, {"lanes": lanes, "guard": guard, "valid": valid}


@functools.lru_cache(maxsize=32)
def make_value_and_grad(*, mode: str = "forward", n_attempts: int, segment: int = 100, adaptive: bool = True,
                        d_floor: float = D_FLOOR):
    """A jitted ``f(trainable, frozen, data, cfg) -> ((loss, aux), grad)`` of :func:`objective`.

    ``mode="reverse"``: ``jax.value_and_grad`` through the checkpointed scan;
    ``mode="forward"``: ``jax.jacfwd`` over the flattened trainable parameters (one tangent each).
    The same settings return the same (cached) function, so a second tuning run with the same
    shapes does not recompile.
    """
    if mode not in GRADIENT_MODES:
        raise ValueError(f"mode must be one of {GRADIENT_MODES}, got {mode!r}")
    loss = functools.partial(objective, n_attempts=int(n_attempts), segment=int(segment), adaptive=bool(adaptive),
                             d_floor=float(d_floor))
    if mode == "reverse":
        return jax.jit(jax.value_and_grad(loss, has_aux=True))

    def forward(trainable, frozen, data, cfg):
        flat, unravel = ravel_pytree(trainable)

        def f(v):
            value, aux = loss(unravel(v), frozen, data, cfg)
            return value, (value, aux)

        jac, (value, aux) = jax.jacfwd(f, has_aux=True)(flat)
        return (value, aux), unravel(jac)

    return jax.jit(forward)


# ---------------------------------------------------------------------------------------------
# the optimiser loop
# ---------------------------------------------------------------------------------------------

class TuneConfig(NamedTuple):
    """Settings of :func:`tune` that are not the objective's (see :class:`LossConfig` for those).

    Attributes:
      steps: optimiser iterations (each evaluates one candidate).
      batch: training starts; seed: their seed (and the plants' in robust tuning).
      lr: peak learning rate of Adam in the unconstrained coordinates (log-gains).
      clip: global-norm gradient clipping.
      warmup: iterations of linear warm-up; the rate then decays by cosine to ``lr * final_lr``.
      n_attempts: budget of attempted steps per lane (the scan's length).
      segment: attempts per checkpointed segment.
      mode: ``"forward"`` (default, faster for the <= 7 gain parameters) or ``"reverse"`` gradients.
      max_rejections: stop after this many invalid candidates in a row, or once backtracking has
        shrunk the step below ``min_scale`` of the schedule's (the best valid point is then on the
        boundary of the valid set: typically the probe's step budget).
      probe: training starts probed per candidate (those that needed the most steps at the last
        refresh; 0: no probe).
      probe_budget: attempted steps per probe start over ``probe_t_final`` (the engine's default
        budget for 100 s is ~2e5).
      probe_refresh: every this many accepted candidates (and at the first) the whole training
        batch is probed and the probe set re-chosen.
      verify: after the loop, check up to this many of the best valid candidates (best first) with
        the accurate engine (:func:`~jaxsleigh.ensemble.run_ensemble`, default budget) on all
        training and guard starts over ``probe_t_final``, and return the first whose trajectories
        all end with status OK (0: skip).
    """

    steps: int = 150
    batch: int = 256
    seed: int = 0
    lr: float = 0.05
    clip: float = 1.0
    warmup: int = 5
    final_lr: float = 0.1
    n_attempts: int = 4000
    segment: int = 100
    mode: str = "forward"
    max_rejections: int = 12
    min_scale: float = 1e-3
    probe: int = 16
    probe_budget: int = 100000
    probe_refresh: int = 25
    verify: int = 5


class TuneHistory(NamedTuple):
    """One row per iteration (NumPy arrays).

    Attributes:
      loss, grad_norm: objective and global norm of its gradient at the candidate.
      L (n, 3), k (n,), D_hat (n, 2, 2): the candidate's gains.
      valid: candidate accepted; best: running best valid loss.
      median_soft: median soft convergence time S of the batch [s];
      median_passage: median first-passage time into the stopping ball (inf: not reached) [s].
      max_attempts: largest number of attempts of a training or guard lane (training integrator);
      probe_attempts: largest number of attempted steps of a probed start over the validation
        horizon (accurate engine; nan: not probed); lr_scale: backtracking factor; wall: [s].
    """

    loss: np.ndarray
    grad_norm: np.ndarray
    L: np.ndarray
    k: np.ndarray
    D_hat: np.ndarray
    valid: np.ndarray
    best: np.ndarray
    median_soft: np.ndarray
    median_passage: np.ndarray
    max_attempts: np.ndarray
    probe_attempts: np.ndarray
    lr_scale: np.ndarray
    wall: np.ndarray


class TuneResult(NamedTuple):
    """What :func:`tune` returns.

    Attributes:
      gains: the best valid gains found that passed the final check (validated
        :class:`~jaxsleigh.params.Gains`; frozen gains are the initial ones, bit for bit).
      initial: the starting gains.
      best_loss, initial_loss: objective at ``gains`` and at ``initial``.
      best_iteration: iteration at which ``gains`` was evaluated (``settings["verified_iteration"]``).
      history: :class:`TuneHistory`.
      settings: everything that produced the result (JSON-ready).
    """

    gains: Gains
    initial: Gains
    best_loss: float
    initial_loss: float
    best_iteration: int
    history: TuneHistory
    settings: dict


def make_optimizer(lr: float, steps: int, *, clip: float = 1.0, warmup: int = 5, final_lr: float = 0.1):
    """Adam with global-norm clipping and a warm-up + cosine-decay schedule."""
    schedule = optax.warmup_cosine_decay_schedule(init_value=0.1 * lr, peak_value=lr,
                                                  warmup_steps=max(1, min(warmup, steps - 1)),
                                                  decay_steps=max(2, steps), end_value=final_lr * lr)
    return optax.chain(optax.clip_by_global_norm(clip), optax.adam(schedule))


def _gains_numpy(trainable, frozen, d_floor, initial: Gains, names) -> Gains:
    """Validated float64 gains; frozen gains are the initial ones, bit for bit."""
    g = gains_from_params(merge_params(trainable, frozen), d_floor=d_floor)
    D = np.asarray(g.D_hat, dtype=np.float64)
    return make_gains(np.asarray(g.L, dtype=np.float64) if "L" in names else initial.L,
                      float(g.k) if "k" in names else initial.k,
                      0.5 * (D + D.T) if "D_hat" in names else initial.D_hat)


def _validate_number(name, v, *, integer=False, positive=True):
    try:
        x = int(v) if integer else float(v)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {v!r}") from None
    if integer and x != v:
        raise ValueError(f"{name} must be a whole number, got {v!r}")
    if not math.isfinite(x) or (positive and x <= 0):
        raise ValueError(f"{name} must be a finite number > 0, got {v!r}")
    return x


def tune(gains0="paper", *, starts=UniformStarts(), config: TuneConfig = TuneConfig(),
         loss: LossConfig = LossConfig(), tune=None, plant: Optional[PlantParams] = None,
         robust: Optional[PlantDistribution] = None, guard=None, x64: bool = False,
         d_floor: float = D_FLOOR, progress: Any = None, callback: Optional[Callable] = None,
         checkpoint=None, resume: bool = False) -> TuneResult:
    """Tune the gains by gradient descent on the soft convergence time.

    Args:
      gains0: starting gains (``Gains``, a preset name or a JSON path).
      starts: the distribution of training starts: a sampler ``(rng, n) -> (n, 3|5)`` (default
        :class:`UniformStarts`: ``|x|, |y| <= 3``, ``|theta0|`` in ``(0.3, pi)``) or a fixed array.
      config: :class:`TuneConfig` (iterations, batch, seed, learning rate, budgets, gradient mode).
      loss: :class:`LossConfig` (horizon, tolerances, eps, temperature, penalty weights).
      tune: the gains to tune, a subset of ``"L", "k", "D_hat"`` (``"L,k"``); the rest stay frozen.
      plant: the plant (default: the paper's); robust: a :class:`PlantDistribution` to average the
        objective over sampled plants instead.
      guard: guard starts (default :func:`guard_starts`, ``|theta0|`` in {0.05, 0.1} at the corners).
      x64: compute in float64 (default float32).
      progress: progress bar (``None``: on a terminal); callback: ``callback(i, row_dict)`` per iteration.
      checkpoint: a file (``.npz``) where the optimiser's whole state is written, atomically, after
        every iteration; ``resume=True`` continues from it (the run's settings must be the same:
        they are fingerprinted) and ends with the result an uninterrupted run would have given.

    Returns:
      :class:`TuneResult` whose ``gains`` are the best *valid* candidate (every training and guard
      lane reached its horizon or the ball with status OK, loss and gradient finite, the probed
      starts within ``probe_budget`` steps for 100 s) that also passed the final check with the
      accurate engine on all training and guard starts over ``loss.probe_t_final``.

    Raises:
      ValueError: bad settings, or starting gains that are not a valid candidate (the message
        says which check failed and what to change).
      RuntimeError: no candidate passed the final check.
      TuningInterrupted: Ctrl-C during the loop; its ``partial`` is a :class:`TuneResult` with the
        best valid gains so far (not re-checked with the accurate engine) and the history.
    """
    names = parse_tune(tune)
    steps = _validate_number("steps", config.steps, integer=True)
    batch = _validate_number("batch", config.batch, integer=True)
    _validate_number("lr", config.lr)
    _validate_number("t_final", loss.t_final)
    _validate_number("dt", loss.dt)
    if config.mode not in GRADIENT_MODES:
        raise ValueError(f"mode must be one of {GRADIENT_MODES}, got {config.mode!r}")
    g0 = load_gains(gains0)
    ics = sample_starts(starts, batch, config.seed)
    theta0 = params_from_gains(g0, d_floor=d_floor)
    t_start = time.perf_counter()
    with jax.enable_x64(bool(x64)):
        dtype = jnp.zeros(()).dtype
        data = make_training_set(ics, plant=plant, robust=robust, guard=guard, seed=config.seed + 1, dtype=dtype)
        cfg = LossConfig(*(jnp.asarray(v, dtype) for v in loss))
        theta = GainParams(*(jnp.asarray(x, dtype) for x in theta0))
        trainable, frozen = split_params(theta, names)
        vg = make_value_and_grad(mode=config.mode, n_attempts=config.n_attempts, segment=config.segment,
                                 d_floor=d_floor)
        opt = make_optimizer(config.lr, steps, clip=config.clip, warmup=config.warmup, final_lr=config.final_lr)
        opt_state = opt.init(trainable)
        apply = jax.jit(_apply_update, static_argnums=0)
        groups = _plant_groups(ics.shape[0], plant, robust, config.seed + 1)
        probes, n_accepted = None, 0
        rows, best, last_valid, valid_points = [], None, None, []
        scale, rejections, it0 = 1.0, 0, 0
        store = None
        if checkpoint is not None:
            store = _TunerCheckpoint(checkpoint, _tune_fingerprint(g0, names, config, loss, plant, robust, guard,
                                                                    x64, d_floor, starts, ics))
            if resume:
                st = store.load(trainable, opt_state, groups)
                if st is not None:
                    (trainable, opt_state, last_valid, best, valid_points, rows, scale, rejections,
                     n_accepted, probes, it0) = st
            elif store.path.exists():
                raise ValueError(f"tuner checkpoint {str(store.path)!r} exists from an earlier run; pass "
                                 "resume=True (--resume) to continue it, or delete it to start afresh")
        if checkpoint is None and resume:
            raise ValueError("resume=True needs checkpoint (the file the interrupted run wrote)")
        try:
            with _Bar(progress, steps) as bar:
                bar.skip(it0)
                for it in range(it0, steps):
                    (value, aux), grad = vg(trainable, frozen, data, cfg)
                    value = float(value)
                    gnorm = float(optax.tree.norm(grad))
                    valid = bool(aux["valid"]) and math.isfinite(gnorm)
                    probe_attempts = float("nan")
                    if valid and config.probe:
                        g = _gains_numpy(trainable, frozen, d_floor, g0, names)
                        refresh = probes is None or n_accepted % max(1, int(config.probe_refresh)) == 0
                        sets = [(ics[idx], p0) for idx, _, p0 in groups] if refresh else probes
                        valid, attempts = _probe(g, sets, float(loss.probe_t_final), int(config.probe_budget), x64)
                        probe_attempts = float(max(a.max() for a in attempts))
                        if refresh and valid:
                            probes = _hardest(sets, attempts, int(config.probe))
                    row = _row(value, gnorm, valid, trainable, frozen, aux, scale, d_floor, time.perf_counter() - t_start)
                    row["probe_attempts"] = probe_attempts
                    if valid:
                        rejections = 0
                        if best is None or value < best[0]:
                            best = (value, it, trainable)
                        valid_points.append((value, it, trainable))
                        n_accepted += 1
                        last_valid = (trainable, opt_state, grad)
                        scale = min(1.0, 1.25 * scale)
                    else:
                        if last_valid is None:
                            raise ValueError(_invalid_start_message(aux, value, gnorm, probe_attempts, config))
                        # backtrack: redo the last valid step, half as long
                        rejections += 1
                        scale *= 0.5
                    trainable, opt_state = apply(opt, *last_valid, jnp.asarray(scale, dtype))
                    row["best"] = best[0]
                    rows.append(row)
                    stop = rejections >= config.max_rejections or scale < config.min_scale
                    if store is not None:
                        store.save(it + 1 if not stop else steps, trainable, opt_state, last_valid, best,
                                   valid_points, rows, scale, rejections, n_accepted, probes, groups)
                    bar.update(it, row)
                    if callback is not None:
                        callback(it, row)
                    if stop:
                        break
        except KeyboardInterrupt:
            partial = None
            if best is not None:
                history = TuneHistory(**{f: np.asarray([r[f] for r in rows]) for f in TuneHistory._fields})
                partial = TuneResult(_gains_numpy(best[2], frozen, d_floor, g0, names), g0, float(best[0]),
                                     float(rows[0]["loss"]), int(best[1]), history,
                                     {"interrupted": True, "verified_iteration": None, "iterations_run": len(rows),
                                      "dtype": "float64" if x64 else "float32", "tuned": list(names),
                                      "loss": {k: float(v) for k, v in loss._asdict().items()},
                                      "method": "interrupted; best valid candidate so far, not re-checked"})
            raise TuningInterrupted(partial, None if store is None else store.path) from None
        history = TuneHistory(**{f: np.asarray([r[f] for r in rows]) for f in TuneHistory._fields})
        best_gains = _gains_numpy(best[2], frozen, d_floor, g0, names)
    verified = None
    if config.verify:
        guard_ics = guard_starts() if guard is None else np.asarray(guard, dtype=np.float64)
        checks = [(ics[idx], p0) for idx, _, p0 in groups]
        if guard_ics.size:
            checks.append((guard_ics, groups[0][2]))
        why = ""
        for value, it, tr in sorted(valid_points, key=lambda p: p[0])[:int(config.verify)]:
            with jax.enable_x64(bool(x64)):
                g = _gains_numpy(tr, frozen, d_floor, g0, names)
            why = _check(g, checks, float(loss.probe_t_final), x64)
            if not why:
                best, best_gains, verified = (value, it, tr), g, it
                break
        if verified is None:
            raise RuntimeError(f"none of the {min(len(valid_points), int(config.verify))} best valid candidates "
                               f"passed the check with the accurate engine over {float(loss.probe_t_final):g} s on "
                               f"the training and guard starts (last: {why}); tune with a smaller learning rate, "
                               f"fewer steps or a smaller probe_budget")
    settings = {
        "method": "gradient descent (optax Adam, clipped, warm-up + cosine) on the soft convergence time, "
                  "adaptive RK4 in the w chart, gradients through the integrator",
        "tuned": list(names), "initial_gains": gains_to_dict(g0), "config": config._asdict(),
        "loss": {k: float(v) for k, v in loss._asdict().items()}, "x64": bool(x64),
        "dtype": "float64" if x64 else "float32", "robust": None if robust is None else robust._asdict(),
        "starts": repr(starts) if callable(starts) else "fixed array", "n_guard": int(data.guard.shape[0]),
        "iterations_run": len(rows), "wall_s": time.perf_counter() - t_start, "d_floor": d_floor,
        "verified_iteration": verified,
    }
    return TuneResult(best_gains, g0, float(best[0]), float(rows[0]["loss"]), int(best[1]), history, settings)


def _probe(g: Gains, sets, horizon: float, budget: int, x64) -> tuple:
    """Integrate every ``(starts, plant)`` of ``sets`` over ``horizon`` with the accurate engine and
    ``budget`` attempts per start. Returns ``(all OK, [attempts per start of each set])``."""
    from .ensemble import run_ensemble

    ok, attempts = True, []
    for starts, plant in sets:
        r = run_ensemble(starts, plant=plant, gains=g, t_final=horizon, x64=x64, max_steps=budget, progress=False)
        attempts.append(np.asarray(r.n_steps + r.n_rejected))
        ok = ok and bool(np.all(r.status == Status.OK))
    return ok, attempts


def _hardest(sets, attempts, probe: int) -> list:
    """The ``probe`` starts that needed the most attempts, shared among the sets by size."""
    n = sum(s.shape[0] for s, _ in sets)
    out = []
    for (starts, plant), a in zip(sets, attempts):
        k = max(1, int(math.ceil(probe * starts.shape[0] / n)))
        out.append((starts[np.argsort(-a, kind="stable")[:k]], plant))
    return out


def _check(g: Gains, checks, horizon: float, x64) -> str:
    """Empty if every start of every ``(starts, plant)`` ends with status OK after ``horizon``
    seconds of the accurate engine (default budget), else what went wrong."""
    from .ensemble import run_ensemble

    for starts, plant in checks:
        r = run_ensemble(starts, plant=plant, gains=g, t_final=horizon, x64=x64, progress=False)
        bad = r.status != Status.OK
        if np.any(bad):
            codes = ", ".join(f"{int(np.sum(r.status == c))} {Status(c).name.lower()}" for c in np.unique(r.status[bad]))
            return f"{int(bad.sum())} of {bad.size} starts failed: {codes}"
    return ""


def _apply_update(opt, trainable, opt_state, grad, scale):
    updates, opt_state = opt.update(grad, opt_state, trainable)
    updates = jax.tree_util.tree_map(lambda u: scale * u, updates)
    return optax.apply_updates(trainable, updates), opt_state


def _row(value, gnorm, valid, trainable, frozen, aux, scale, d_floor, wall) -> dict:
    g = gains_from_params(merge_params(trainable, frozen), d_floor=d_floor)
    lanes = aux["lanes"]
    att = np.asarray(lanes.n_attempts)
    if aux["guard"] is not None:
        att = np.concatenate([att, np.asarray(aux["guard"].n_attempts)])
    passage = np.where(np.asarray(lanes.stopped), np.asarray(lanes.t, np.float64), np.inf)
    return {"loss": value, "grad_norm": gnorm, "L": np.asarray(g.L, np.float64), "k": float(g.k),
            "probe_attempts": float("nan"),
            "D_hat": np.asarray(g.D_hat, np.float64), "valid": valid,
            "median_soft": float(np.median(np.asarray(lanes.soft_time, np.float64))),
            "median_passage": float(np.median(passage)), "max_attempts": int(att.max()),
            "lr_scale": scale, "wall": wall}


def _invalid_start_message(aux, value, gnorm, probe_attempts, config) -> str:
    lanes, guard = aux["lanes"], aux["guard"]
    n_bad = int(np.sum(~np.asarray(lanes.ok)))
    g_bad = 0 if guard is None else int(np.sum(~np.asarray(guard.ok)))
    if n_bad or g_bad or not (math.isfinite(value) and math.isfinite(gnorm)):
        return (f"the starting gains are not a valid candidate (loss {value}, gradient norm {gnorm}, "
                f"{n_bad} training and {g_bad} guard lanes failed or ran out of their step budget); "
                f"raise n_attempts, shorten t_final or start from other gains")
    return (f"the starting gains fail the integration-cost probe: a training start needs more than "
            f"probe_budget = {config.probe_budget} attempted steps to simulate the validation horizon (it "
            f"stopped after {probe_attempts:.0f} without reaching it); raise probe_budget (the paper's gains need "
            f"about 1,400 per 100 s, the engine's default budget is 200,180) or start from other gains")


class _Bar:
    """tqdm bar with the loss in its postfix (``enabled=None``: on a terminal)."""

    def __init__(self, enabled, total):
        self._bar = None
        if enabled is None:
            enabled = sys.stderr.isatty()
        if enabled:
            from tqdm.auto import tqdm

            self._bar = tqdm(total=total, desc="tune", unit="it")

    def skip(self, n):
        """Count ``n`` iterations done by an earlier (resumed) run."""
        if self._bar is not None and n:
            self._bar.update(n)

    def update(self, it, row):
        if self._bar is not None:
            self._bar.set_postfix(loss=f"{row['loss']:.4f}", best=f"{row['best']:.4f}",
                                  ok="yes" if row["valid"] else "no", refresh=False)
            self._bar.update(1)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if self._bar is not None:
            self._bar.close()
        return False


class TuningInterrupted(KeyboardInterrupt):
    """Ctrl-C during :func:`tune`. ``partial``: a :class:`TuneResult` with the best valid gains so far
    (``None`` if no candidate was valid yet); ``checkpoint``: the file to resume from (or ``None``)."""

    def __init__(self, partial, checkpoint):
        super().__init__("tuning interrupted")
        self.partial = partial
        self.checkpoint = checkpoint


def _tune_fingerprint(g0, names, config, loss, plant, robust, guard, x64, d_floor, starts, ics) -> str:
    import hashlib
    import json

    from .config import plant_to_dict

    doc = {"gains0": gains_to_dict(g0), "names": list(names), "config": config._asdict(),
           "loss": {k: float(v) for k, v in loss._asdict().items()},
           "plant": None if plant is None else plant_to_dict(plant), "robust": None if robust is None else repr(robust),
           "guard": None if guard is None else np.asarray(guard, np.float64).tolist(), "x64": bool(x64),
           "d_floor": float(d_floor), "starts": repr(starts) if callable(starts) else "array"}
    h = hashlib.sha256(json.dumps(doc, sort_keys=True, default=str).encode())
    h.update(np.ascontiguousarray(ics, np.float64).tobytes())
    return h.hexdigest()


class _TunerCheckpoint:
    """The optimiser's whole state in one ``.npz`` (pytree leaves by position), written atomically."""

    _ROW_FIELDS = TuneHistory._fields

    def __init__(self, path, key: str):
        self.path = Path(path)
        self.key = key

    def save(self, it, trainable, opt_state, last_valid, best, valid_points, rows, scale, rejections,
             n_accepted, probes, groups) -> None:
        from .io import atomic_write

        arrays = {"key": np.array(self.key), "it": np.int64(it), "scale": np.float64(scale),
                  "rejections": np.int64(rejections), "n_accepted": np.int64(n_accepted)}

        def put(prefix, tree):
            for i, leaf in enumerate(jax.tree_util.tree_leaves(tree)):
                arrays[f"{prefix}/{i}"] = np.asarray(leaf)

        put("trainable", trainable)
        put("opt_state", opt_state)
        if last_valid is not None:
            put("last_valid/trainable", last_valid[0])
            put("last_valid/opt_state", last_valid[1])
            put("last_valid/grad", last_valid[2])
        if best is not None:
            arrays["best/value"], arrays["best/it"] = np.float64(best[0]), np.int64(best[1])
            put("best/trainable", best[2])
        arrays["valid/value"] = np.asarray([v for v, _, _ in valid_points], np.float64)
        arrays["valid/it"] = np.asarray([i for _, i, _ in valid_points], np.int64)
        for j, (_, _, tr) in enumerate(valid_points):
            put(f"valid/{j}", tr)
        for f in self._ROW_FIELDS:
            arrays[f"rows/{f}"] = np.asarray([r[f] for r in rows])
        if probes is not None:
            for j, (pstarts, _) in enumerate(probes):
                arrays[f"probes/{j}"] = np.asarray(pstarts)
        atomic_write(self.path, lambda fh: np.savez(fh, **arrays))

    def load(self, trainable, opt_state, groups):
        """The saved state, restructured like ``trainable`` / ``opt_state``; ``None`` if no file."""
        import zipfile

        if not self.path.exists():
            return None
        try:
            with np.load(self.path, allow_pickle=False) as z:
                a = {k: z[k] for k in z.files}
        except (zipfile.BadZipFile, EOFError, OSError, ValueError) as e:
            raise ValueError(f"tuner checkpoint {str(self.path)!r} is damaged ({type(e).__name__}: {e}); delete it "
                             "and start afresh (without --resume)") from None
        if str(a.get("key")) != self.key:
            raise ValueError(f"tuner checkpoint {str(self.path)!r} was written by a run with other settings; rerun "
                             "that command with --resume, or delete the checkpoint to start afresh")

        def get(prefix, like):
            leaves, tdef = jax.tree_util.tree_flatten(like)
            return jax.tree_util.tree_unflatten(
                tdef, [jnp.asarray(a[f"{prefix}/{i}"], jnp.asarray(l).dtype) for i, l in enumerate(leaves)])

        last_valid = None
        if "last_valid/trainable/0" in a:
            last_valid = (get("last_valid/trainable", trainable), get("last_valid/opt_state", opt_state),
                          get("last_valid/grad", trainable))
        best = None
        if "best/value" in a:
            best = (float(a["best/value"]), int(a["best/it"]), get("best/trainable", trainable))
        valid_points = [(float(v), int(i), get(f"valid/{j}", trainable))
                        for j, (v, i) in enumerate(zip(a["valid/value"], a["valid/it"]))]
        n_rows = len(a[f"rows/{self._ROW_FIELDS[0]}"])
        rows = [{f: _scalar(a[f"rows/{f}"][r]) for f in self._ROW_FIELDS} for r in range(n_rows)]
        probes = None
        if "probes/0" in a:
            probes = [(a[f"probes/{j}"], groups[j][2]) for j in range(len(groups)) if f"probes/{j}" in a]
        return (get("trainable", trainable), get("opt_state", opt_state), last_valid, best, valid_points, rows,
                float(a["scale"]), int(a["rejections"]), int(a["n_accepted"]), probes, int(a["it"]))


def _scalar(x):
    x = np.asarray(x)
    if x.ndim:
        return x
    if x.dtype == bool:
        return bool(x)
    return x.item()


def save_history(history: TuneHistory, path, **extra) -> Path:
    """Write the history as ``.npz`` (one key per field, plus ``extra`` arrays)."""
    from .io import atomic_write

    path = Path(path)
    if path.suffix != ".npz":
        path = path.with_name(path.name + ".npz")
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda f: np.savez(f, **history._asdict(), **{k: np.asarray(v) for k, v in extra.items()}))
    return path


def load_history(path) -> TuneHistory:
    """Read a history written by :func:`save_history`."""
    with np.load(path, allow_pickle=False) as z:
        return TuneHistory(**{f: z[f] for f in TuneHistory._fields})


# ---------------------------------------------------------------------------------------------
# validation with the accurate engine
# ---------------------------------------------------------------------------------------------

class Validation(NamedTuple):
    """Hard convergence times measured by :func:`jaxsleigh.ensemble.run_ensemble`.

    Attributes:
      T_eps: (N,) convergence times (inf: not settled by the horizon; nan: failed).
      median, median_se: median ``T_eps`` over all starts (inf if half did not settle) and its
        bootstrap standard error.
      frac_converged, frac_se: fraction settled within the horizon, binomial standard error.
      n, n_failed: starts and starts whose status is not OK; status: (N,) codes.
      mean_steps: accepted adaptive steps per trajectory over the horizon (the cost of simulating).
      max_attempts: most attempted steps of one trajectory (the engine's default budget for 100 s
        is 200180; a trajectory that needs more ends with status BUDGET_EXHAUSTED).
      settings: of the ensemble run.
    """

    T_eps: np.ndarray
    median: float
    median_se: float
    frac_converged: float
    frac_se: float
    n: int
    n_failed: int
    status: np.ndarray
    mean_steps: float
    max_attempts: int
    settings: dict


def validate(gains, ics, *, plant: Optional[PlantParams] = None, t_final: float = 100.0, eps: float = 0.05,
             x64: bool = False, n_boot: int = 1000, seed: int = 0, progress: Any = None, **ensemble_kw) -> Validation:
    """Measure ``T_eps`` with the accurate engine (:func:`~jaxsleigh.ensemble.run_ensemble`,
    adaptive RK4, default tolerances), never with the training discretisation."""
    from .ensemble import run_ensemble

    r = run_ensemble(ics, plant=plant, gains=load_gains(gains), t_final=t_final, eps=eps, x64=x64,
                     progress=progress, **ensemble_kw)
    T = np.where(r.status == Status.OK, r.T_eps, np.nan)
    n = T.size
    conv = np.isfinite(T)
    frac = float(conv.mean())
    # failures count as not converged (inf) in the median
    Tm = np.where(np.isnan(T), np.inf, T)
    med = float(np.median(Tm))
    rng = np.random.default_rng(seed)
    boots = np.median(Tm[rng.integers(0, n, size=(n_boot, n))], axis=1)
    se = float(np.std(boots)) if np.all(np.isfinite(boots)) else float("nan")
    return Validation(T, med, se, frac, math.sqrt(max(frac * (1 - frac), 0.0) / n), n,
                      int(np.sum(r.status != Status.OK)), r.status, float(np.mean(r.n_steps)),
                      int(np.max(r.n_steps + r.n_rejected)), r.settings)


def markdown_table(rows: dict) -> str:
    """``{name: Validation}`` -> a markdown table of median T_eps and fraction converged."""
    lines = ["| gains | N | median T_0.05 [s] | converged by horizon | status not OK |",
             "|---|---|---|---|---|"]
    for name, v in rows.items():
        lines.append(f"| {name} | {v.n} | {v.median:.2f} ± {v.median_se:.2f} | "
                     f"{100 * v.frac_converged:.1f}% ± {100 * v.frac_se:.1f}% | {v.n_failed} |")
    return "\n".join(lines)
