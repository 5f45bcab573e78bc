r"""The engine's stepper: RK4 in the w chart, fixed-step or adapted per trajectory.

**Why the w chart.** In ``y = (w, p)`` the closed loop is port-Hamiltonian with
:math:`H_d = \tfrac12 p^\top M^{-1} p + \tfrac12 w^\top L w` non-increasing (eq. 15-18), so the state
stays in a bounded set, and the right-hand side is rational in ``w`` without trigonometry. In the
physical chart every evaluation recomputes ``w`` from ``q`` through :math:`z_3 / \theta^2`, and
float32 rounding of ``q`` is amplified by :math:`1/\theta^2` near the singular set.

**Why adaptive.** Near :math:`\theta = 0` the closed loop is stiff: the injected damping
:math:`k / w_1^2` and the potential forces :math:`\sim |w|^2 / w_1` give Jacobian eigenvalues far
outside RK4's stability region at ``dt = 0.01``. Each trajectory therefore takes classical RK4
steps whose size is chosen from an embedded third-order error estimate that costs no extra
evaluation: with :math:`k_5 = f(t + h, y_{n+1})` (which is also the next step's :math:`k_1`),
:math:`\hat y_{n+1} = y_n + h(k_1 + 2k_2 + 2k_3 + k_5)/6` is third order, so
:math:`y_{n+1} - \hat y_{n+1} = h (k_4 - k_5) / 6`. A step is rejected (and retried smaller) when
this error exceeds the tolerance, when it produces a non-finite value, or when it would carry
:math:`w_1 = \theta` across zero, which the exact flow never does (Lemma 2). Steps never exceed
the base step ``dt`` and are clipped to land exactly on the save times.

**Fixed shape.** One ``lax.scan`` iteration is one attempted step of every trajectory; a
trajectory that has reached the horizon, failed, or used its budget idles. :func:`run_segment`
runs a fixed number of attempts; callers loop over segments (and may compact the batch).

Time is accumulated with compensated (two-sum) addition, so float32 runs keep time exact to
rounding over ``1e4`` or more steps.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .closed_loop import ClosedLoop, vector_field_w
from .coordinates import f_w_inv
from .rk4 import rk4_stages
from .status import Status

__all__ = ["Controls", "StepState", "init_state", "attempt", "run_segment", "q_norm_w"]

# A step that would overshoot the next save time by less than this fraction is stretched onto it,
# so that rounding in t never leaves a tiny last step.
_STRETCH = 1.01


class Controls(NamedTuple):
    """Traced numbers of the stepper (changing them does not recompile).

    Attributes:
      dt: base (and largest) step.
      rtol, atol: tolerances of the adaptive error control (unused by fixed RK4).
      eps: radius of the convergence ball ``|q| <= eps`` for the on-line ``T_eps``.
      max_steps: budget of attempted steps per trajectory.
    """

    dt: jax.Array
    rtol: jax.Array
    atol: jax.Array
    eps: jax.Array
    max_steps: jax.Array


class StepState(NamedTuple):
    """Carry of one trajectory (``vmap`` adds a leading batch axis to every field)."""

    t: jax.Array          # time, high part
    t_lo: jax.Array       # time, compensation
    y: jax.Array          # (5,) state in the w chart
    k1: jax.Array         # (5,) f(t, y), reused (FSAL)
    h: jax.Array          # proposed next step
    status: jax.Array     # int32 Status
    n_accept: jax.Array   # int32
    n_reject: jax.Array   # int32
    j: jax.Array          # int32 index of the next save time
    buf: jax.Array        # (n_out, 5) states at the save times, NaN until reached
    t_enter: jax.Array    # start of the current stay in |q| <= eps (inf while outside)
    min_abs_theta: jax.Array
    max_q: jax.Array


def q_norm_w(w):
    """:math:`|q|` from ``w`` without trigonometry: :math:`f_z` is a rotation of (x, y), so
    :math:`|q| = |z| = |f_w^{-1}(w)|`."""
    z = f_w_inv(w)
    return jnp.sqrt(jnp.sum(z * z))


def init_state(y0w, status0, args: ClosedLoop, ctl: Controls, n_out: int, t0=0.0) -> StepState:
    """Carry for one trajectory starting at the w-chart state ``y0w`` with status ``status0``.

    A trajectory whose ``status0`` is not OK is never stepped; pass any finite ``y0w`` for it.
    """
    dtype = y0w.dtype
    ok = status0 == Status.OK
    # keep an invalid lane's arithmetic finite: it idles, but its lanes still run through vmap
    y0w = jnp.where(ok, y0w, jnp.array([1.0, 0.0, 0.0, 0.0, 0.0], dtype))
    qn = q_norm_w(y0w[:3])
    t0 = jnp.asarray(t0, dtype)
    return StepState(
        t=t0, t_lo=jnp.zeros((), dtype), y=y0w,
        k1=vector_field_w(t0, y0w, args), h=jnp.asarray(ctl.dt, dtype),
        status=jnp.asarray(status0, jnp.int32),
        n_accept=jnp.zeros((), jnp.int32), n_reject=jnp.zeros((), jnp.int32),
        j=jnp.zeros((), jnp.int32), buf=jnp.full((n_out, 5), jnp.nan, dtype),
        t_enter=jnp.where(qn <= ctl.eps, t0, jnp.inf).astype(dtype),
        min_abs_theta=jnp.abs(y0w[0]), max_q=qn,
    )


def _two_sum(a, b):
    s = a + b
    bb = s - a
    return s, (a - (s - bb)) + (b - bb)


def attempt(s: StepState, args: ClosedLoop, save_times, ctl: Controls, *, adaptive: bool) -> StepState:
    """One attempted step of one trajectory (a no-op once it is done or failed)."""
    f = vector_field_w
    dtype = s.y.dtype
    n_out = save_times.shape[0]
    active = (s.status == Status.OK) & (s.j < n_out) & (s.n_accept + s.n_reject < ctl.max_steps)
    target = save_times[jnp.minimum(s.j, n_out - 1)].astype(dtype)
    remaining = (target - s.t) - s.t_lo
    hit = remaining <= _STRETCH * s.h
    h = jnp.where(hit, remaining, s.h)
    # an idle lane still computes (vmap); give it a harmless step
    h = jnp.where(active, h, jnp.zeros_like(h))

    y_new, k4 = rk4_stages(f, s.t, s.y, h, args, s.k1)
    k5 = f(s.t + h, y_new, args)
    finite = jnp.all(jnp.isfinite(y_new)) & jnp.all(jnp.isfinite(k5))
    crossed = jnp.sign(y_new[0]) != jnp.sign(s.y[0])
    status = s.status
    if adaptive:
        scale = ctl.atol + ctl.rtol * jnp.maximum(jnp.abs(s.y), jnp.abs(y_new))
        err = jnp.max(jnp.abs((h / 6.0) * (k4 - k5)) / scale)
        good = finite & ~crossed
        err = jnp.where(good, err, jnp.inf)
        ok = good & (err <= 1.0)
        # the error estimate is O(h^4); the controller's choice is not differentiated
        fac = jax.lax.stop_gradient(jnp.clip(0.9 * err ** -0.25, 0.2, 5.0))
        h_next = h * fac
        h_next = jnp.where(ok & hit, jnp.maximum(h_next, s.h), h_next)
        h_next = jnp.minimum(h_next, ctl.dt)
        floor = 1e-9 * ctl.dt if dtype == jnp.float64 else 1e-6 * ctl.dt
        status = jnp.where(active & ~ok & (h_next < floor), Status.STEP_UNDERFLOW, status)
    else:
        ok = finite & ~crossed
        h_next = s.h
        status = jnp.where(active & ~finite, Status.NONFINITE,
                           jnp.where(active & crossed, Status.CROSSED_SINGULAR, status))
    acc = active & ok
    rej = active & ~ok

    t_hi, t_err = _two_sum(s.t, h)
    t_new = jnp.where(hit, target, t_hi)
    t_lo_new = jnp.where(hit, jnp.zeros_like(s.t_lo), s.t_lo + t_err)
    y_keep = jnp.where(acc, y_new, s.y)
    qn = q_norm_w(y_keep[:3])
    inside = qn <= ctl.eps
    save = acc & hit
    j_idx = jnp.minimum(s.j, n_out - 1)
    buf = s.buf.at[j_idx].set(jnp.where(save, y_new, s.buf[j_idx]))
    return StepState(
        t=jnp.where(acc, t_new, s.t),
        t_lo=jnp.where(acc, t_lo_new, s.t_lo),
        y=y_keep,
        k1=jnp.where(acc, k5, s.k1),
        h=jnp.where(active, h_next, s.h).astype(dtype),
        status=status.astype(jnp.int32),
        n_accept=s.n_accept + acc.astype(jnp.int32),
        n_reject=s.n_reject + rej.astype(jnp.int32),
        j=s.j + save.astype(jnp.int32),
        buf=buf,
        t_enter=jnp.where(acc, jnp.where(inside, jnp.minimum(s.t_enter, t_new), jnp.inf), s.t_enter).astype(dtype),
        min_abs_theta=jnp.where(acc, jnp.minimum(s.min_abs_theta, jnp.abs(y_new[0])), s.min_abs_theta),
        max_q=jnp.where(acc, jnp.maximum(s.max_q, qn), s.max_q),
    )


def run_segment(s: StepState, args: ClosedLoop, save_times, ctl: Controls, *, n_attempts: int,
                adaptive: bool, unroll: int = 1) -> StepState:
    """``n_attempts`` attempted steps of one trajectory (``vmap`` it; ``jit`` at the call site)."""

    def body(c, _):
        return attempt(c, args, save_times, ctl, adaptive=adaptive), None

    s, _ = jax.lax.scan(body, s, None, length=n_attempts, unroll=unroll)
    return s
