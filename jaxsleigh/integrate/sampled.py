r"""The sampled-data loop: a digital controller (zero-order hold, delay, noise) on the continuous plant.

At the sampling instants \(t_k = k T_s\), \(k = 0, \dots, K-1\) (\(K = t_\mathrm{final} / T_s\)), the
controller measures

\[ \tilde q_k = q(t_k) + \sigma \xi^q_k, \qquad \tilde v_k = M^{-1} p(t_k) + \sigma \xi^v_k, \qquad
   \xi_k \sim \mathcal N(0, I_5) \text{ keyed by (seed, k)}, \]

computes \(\hat u_k = \mathrm{law}(\tilde q_k, \tilde v_k, t_k)\) once, and the plant (paper eq. 1-2)

\[ \dot q = Q(q) M^{-1} p, \qquad \dot p = (J(p) - D(q, p)) M^{-1} p + u_k^\mathrm{held} \]

receives the held input \(u_k^\mathrm{held} = \hat u_{k-d}\) on \([t_k, t_{k+1})\) (\(\hat u_j = 0\) for
\(j < 0\); ``d = sampler.delay``, kept in a ring buffer of the last \(d\) controls). With \(u\) constant the
plant is smooth on each interval, so ``substeps`` classical RK4 steps of \(h = T_s / \text{substeps}\)
integrate it to \(O(h^4)\): ``substeps`` is the accuracy knob.

Summaries, per start:

* ``T_eps``: the start of the last stay in the ball \(|q| \le \epsilon\), judged at the RK4 substep points
  (the crossing located by linear interpolation of \(|q|\) inside the substep); ``inf`` if outside at
  \(t_\mathrm{final}\).
* ``u_energy`` \(= \sum_k \|u_k^\mathrm{held}\|^2 T_s = \int_0^{t_\mathrm{final}} \|u\|^2 dt\) (exact for a held
  input); ``u_norm_peak`` \(= \max_k \|u_k^\mathrm{held}\|\).
* ``min_abs_theta``: \(\min |\theta|\) over the substep points.
* ``status``: `jaxsleigh.Status.OK`; ``INVALID_INPUT`` for a non-finite start (not integrated);
  ``NONFINITE`` where the law's output or the state became non-finite (e.g. the paper's law on
  \(\theta = 0\)). A row that is not OK has NaN summaries and NaN samples from its failing sample on; its
  state is frozen at the last good one, so nothing silently turns NaN.

Everything is one jitted ``lax.scan`` over the samples (the law vmapped over the batch through
`jaxsleigh.model.controller.apply_law`), differentiable with respect to the starts, the law's and the
plant's numbers.
"""
from __future__ import annotations

import math
from functools import partial
from typing import Any, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from ..controllers.actuators import check_sampler
from ..controllers.paper import PaperLaw
from ..model.charts import physical_chart_for
from ..model.controller import FunctionLaw, apply_law, is_paper_law
from ..model.params import PlantParams, plant_params
from ..model.plant import open_loop, velocity
from ..status import Status
from .engine import MAX_BASE_STEPS
from .rk4 import rk4_step

__all__ = ["SampledRun", "solve_sampled", "sample_count"]


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
      max_excursion: (N,) largest \\(|q|\\) at the substep points (the names of `jaxsleigh.EnsembleResult`).
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


def _is_concrete(tree) -> bool:
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(tree))


def solve_sampled(law, plant: Optional[PlantParams] = None, ics=None, *, t_final: float, sampler,
                  substeps: int = 20, eps: float = 0.05, dtype=jnp.float32, save: bool = True) -> SampledRun:
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
      substeps: RK4 steps per sampling period (the accuracy knob); eps: radius of the ball of ``T_eps``.
      dtype: ``jnp.float32`` or ``jnp.float64`` (the latter needs ``jax.enable_x64(True)``).
      save: keep the samples (``t``, ``q``, ``p``, ``u``); ``False``: summaries and final states only.

    Returns:
      `SampledRun`.

    Raises:
      ValueError: a bad sampler, horizon, ``substeps``, ``eps``, ``dtype`` or ``ics`` shape.
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
    if isinstance(substeps, (bool, np.bool_)) or not float(substeps).is_integer() or int(substeps) < 1:
        raise ValueError(f"substeps must be an integer >= 1, got {substeps!r}")
    substeps = int(substeps)
    K = sample_count(t_final, period)
    eps = float(eps)
    if not (math.isfinite(eps) and eps > 0):
        raise ValueError(f"eps must be > 0 and finite, got {eps!r}")
    if is_paper_law(law):                        # the paper's gains: the law from measurements, as sampled
        law = PaperLaw(law)
    if not callable(law):
        raise ValueError(f"law must be a feedback law u = law(q, v), got {type(law).__name__}")
    if not (isinstance(law, tuple) or hasattr(law, "tree_flatten")) and jax.tree_util.tree_leaves(law) == [law]:
        law = FunctionLaw(law)                   # a plain function: static
    plant = plant_params() if plant is None else plant

    y0 = jnp.asarray(ics)
    if _is_concrete(y0):
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

    return _solve(law, plant, y0, jnp.asarray(period, dtype), jnp.asarray(noise, dtype),
                  jnp.asarray(seed % 2**32, jnp.uint32), jnp.asarray(eps, dtype), K=K, substeps=substeps, delay=delay,
                  save=bool(save))


def _field(y, u, plant):
    """Plant vector field with a held input, one trajectory ``y`` (5,)."""
    qdot, pdot = open_loop(y[:3], y[3:], u, plant)
    return jnp.concatenate([qdot, pdot]).astype(y.dtype)


def _qnorm(y, chart):
    """\\(|q|\\) per row of a batch ``y`` (N, 5), the heading measured as the law's chart measures it
    (`jaxsleigh.model.charts.PhysicalChart`: modulo \\(2\\pi\\) for a law that declares so)."""
    return jnp.sqrt(chart.q_norm2(y.T))


def _row_axes(plant):
    """vmap axes of a plant over the rows: a leaf with a trailing axis (one value per start) maps over it."""
    return jax.tree_util.tree_map(lambda x: -1 if jnp.ndim(x) >= 1 else None, plant)


def _control(law, plant, y, buf, status, k, key0, noise, period, delay: int):
    """Sample ``k``: measure (with noise), evaluate the law once, and return the input held on
    \\([t_k, t_{k+1})\\) (the one computed ``delay`` samples ago) and the updated ring buffer."""
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


def _hold(step, y, u, t_enter, min_th, tk, h, eps, substeps: int, chart):
    """The plant over one period with ``u`` held: ``substeps`` RK4 steps of ``h``, tracking the entry time into
    the ball (linear interpolation of \\(|q|\\) inside a substep), \\(\\min |\\theta|\\) and whether every value stayed
    finite, and \\(\\max |q|\\). Returns ``(y_new, t_enter, min_th, finite, max_q)``."""
    dtype = y.dtype

    def sub(c, j):
        yy, t_in, mth, fin, mq = c
        y_new = step(yy, u)
        fin = fin & jnp.all(jnp.isfinite(y_new), axis=1)
        r0, r1 = _qnorm(yy, chart), _qnorm(y_new, chart)
        t0 = tk + j.astype(dtype) * h
        inside = r1 <= eps
        s = jnp.clip((r0 - eps) / jnp.where(r0 > r1, r0 - r1, jnp.ones_like(r0)), 0.0, 1.0)
        entry = jnp.where(r0 > eps, t0 + s * h, t_in)
        t_in = jnp.where(inside, entry, jnp.inf).astype(dtype)
        mth = jnp.minimum(mth, chart.abs_theta(y_new.T))
        return (y_new, t_in, mth, fin, jnp.maximum(mq, r1)), None

    fin0 = jnp.all(jnp.isfinite(u), axis=1)
    return jax.lax.scan(sub, (y, t_enter, min_th, fin0, _qnorm(y, chart)), jnp.arange(substeps))[0]


class _Carry(NamedTuple):
    """What the loop carries from sample to sample, per row: the state, the ring buffer of delayed controls, the
    status, and the running summaries."""

    y: Any
    buf: Any
    status: Any
    t_enter: Any
    min_th: Any
    energy: Any
    peak: Any
    peak_c: Any
    abs_int: Any
    max_q: Any


def _start(y0, eps, chart, delay: int):
    """The first carry and the mask of valid starts: a non-finite start is ``INVALID_INPUT`` and replaced by zeros
    (never step a bad start); ``T_eps`` is 0 for a start already in the ball. Returns ``(valid, carry0)``."""
    dtype = y0.dtype
    N = y0.shape[0]
    valid = jnp.all(jnp.isfinite(y0), axis=1)
    y0 = jnp.where(valid[:, None], y0, jnp.zeros_like(y0))     # never step a bad start
    status0 = jnp.where(valid, int(Status.OK), int(Status.INVALID_INPUT)).astype(jnp.int32)
    t_enter0 = jnp.where(_qnorm(y0, chart) <= eps, jnp.zeros((), dtype), jnp.inf).astype(dtype)
    buf0 = jnp.zeros((max(delay, 1), N, 2), dtype)
    zeros = jnp.zeros((N,), dtype)
    return valid, _Carry(y0, buf0, status0, t_enter0, chart.abs_theta(y0.T), zeros, zeros, jnp.zeros((N, 2), dtype),
                         zeros, _qnorm(y0, chart))


def _rk4_rows(plant, h):
    """``step(y, u)``: one RK4 step of ``h`` of every row of ``y`` (N, 5) with its held input ``u`` (N, 2) (a plant
    leaf with one value per start mapped with the rows)."""
    rows = jax.vmap(lambda y, u, pl: rk4_step(lambda t, yy, a: _field(yy, a, pl), 0.0, y, h, u),
                    in_axes=(0, 0, _row_axes(plant)))

    def step(y, u):
        return rows(y, u, plant)

    return step


def _advance(carry: _Carry, u, held, period):
    """Take one period into the carry: ``held`` is `_hold`'s ``(y_new, t_enter, min_th, finite, max_q)`` with ``u``
    held. A row that was OK and stayed finite moves on and adds the period's effort (\\(\\|u\\|^2 T_s\\),
    \\(\\|u\\| T_s\\), the peaks); one that became non-finite is ``NONFINITE``. Returns ``(carry, good)``."""
    y_new, t_new, mth_new, fin, mq_new = held
    ok = carry.status == int(Status.OK)
    good = ok & fin
    status = jnp.where(ok & ~fin, int(Status.NONFINITE), carry.status).astype(jnp.int32)
    # a failed row is frozen at its last good state (no inf/NaN carried on)
    y = jnp.where(good[:, None], y_new, carry.y)
    t_enter = jnp.where(good, t_new, carry.t_enter)
    min_th = jnp.where(good, mth_new, carry.min_th)
    un2 = jnp.sum(u * u, axis=1)
    energy = jnp.where(good, carry.energy + un2 * period, carry.energy)
    peak = jnp.where(good, jnp.maximum(carry.peak, jnp.sqrt(un2)), carry.peak)
    peak_c = jnp.where(good[:, None], jnp.maximum(carry.peak_c, jnp.abs(u)), carry.peak_c)
    abs_int = jnp.where(good, carry.abs_int + jnp.sqrt(un2) * period, carry.abs_int)
    max_q = jnp.where(good, jnp.maximum(carry.max_q, mq_new), carry.max_q)
    return _Carry(y, carry.buf, status, t_enter, min_th, energy, peak, peak_c, abs_int, max_q), good


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


def _finish(carry: _Carry, valid, y0, saved, period, K: int, save: bool) -> SampledRun:
    """The `SampledRun` of the final carry: a row that is not OK has NaN summaries and final state."""
    y = carry.y
    ok = carry.status == int(Status.OK)
    nanN = jnp.full((y.shape[0],), jnp.nan, y.dtype)
    y_fin = _nan_unless(ok[:, None], y)
    t = q = p = u = None
    if save:
        t, q, p, u = _samples(saved, valid, y0, period, K)
    return SampledRun(
        t=t, q=q, p=p, u=u,
        q_final=y_fin[:, :3], p_final=y_fin[:, 3:],
        T_eps=jnp.where(ok, carry.t_enter, nanN), u_energy=jnp.where(ok, carry.energy, nanN),
        u_norm_peak=jnp.where(ok, carry.peak, nanN), min_abs_theta=jnp.where(ok, carry.min_th, nanN),
        status=carry.status, u_peak=_nan_unless(ok[:, None], carry.peak_c),
        u_abs_int=jnp.where(ok, carry.abs_int, nanN), max_excursion=jnp.where(ok, carry.max_q, nanN))


@partial(jax.jit, static_argnames=("K", "substeps", "delay", "save"))
def _solve(law, plant, y0, period, noise, seed, eps, *, K, substeps, delay, save=True):
    """`solve_sampled` on checked inputs: one ``lax.scan`` over the ``K`` samples (measure and hold, `_control`;
    the plant over the period, `_hold`; the carry moved on, `_advance`), then the run (`_finish`)."""
    dtype = y0.dtype
    h = period / substeps
    eps_ = eps.astype(dtype)
    key0 = jax.random.PRNGKey(seed)
    chart = physical_chart_for(law)
    valid, carry0 = _start(y0, eps_, chart, delay)
    step = _rk4_rows(plant, h)

    def sample(carry, k):
        u, buf = _control(law, plant, carry.y, carry.buf, carry.status, k, key0, noise, period, delay)
        held = _hold(step, carry.y, u, carry.t_enter, carry.min_th, k.astype(dtype) * period, h, eps_, substeps,
                     chart)
        carry, good = _advance(carry._replace(buf=buf), u, held, period)
        if not save:
            return carry, None
        return carry, (_nan_unless(good[:, None], carry.y), _nan_unless(good[:, None], u))

    carry, saved = jax.lax.scan(sample, carry0, jnp.arange(K))
    return _finish(carry, valid, carry0.y, saved, period, K, save)
