"""Host-side driver of the stepper: input checks, the segment loop, batch compaction.

The jitted kernel is ``vmap(run_segment)`` over a batch of trajectories. The driver calls it
repeatedly until every trajectory is done (or out of budget). When few trajectories remain
active, it gathers them into a smaller batch (a power of two, so few shapes get compiled): the
cost then follows the sum of the steps each trajectory needs, not the batch's maximum.
"""
from __future__ import annotations

import functools
import math
import warnings
from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from .closed_loop import ClosedLoop, state_to_w
from .status import Status
from .stepper import Controls, StepState, init_state, run_segment

__all__ = ["Horizon", "check_ics", "make_horizon", "initial_w", "drive", "working_dtype", "default_max_steps", "METHODS"]

METHODS = ("adaptive", "rk4")


def working_dtype():
    """float64 where x64 is enabled (``jax.enable_x64``), else float32."""
    return jnp.zeros(()).dtype


class Horizon(NamedTuple):
    """Time grid of a run: ``n_steps`` base steps of ``dt``, saved every ``save_every``."""

    t_final: float
    dt: float
    n_steps: int
    save_every: int

    @property
    def n_out(self) -> int:
        return self.n_steps // self.save_every

    def save_times(self) -> np.ndarray:
        """Save times after t = 0, float64, shape (n_out,)."""
        return self.dt * self.save_every * np.arange(1, self.n_out + 1, dtype=np.float64)

    def t(self) -> np.ndarray:
        """Saved times including t = 0, shape (n_out + 1,)."""
        return np.concatenate([[0.0], self.save_times()])


def make_horizon(t_final, dt, save_every=None) -> Horizon:
    """Validated horizon; ``save_every=None`` saves the final state only."""
    try:
        t_final, dt = float(t_final), float(dt)
    except (TypeError, ValueError):
        raise ValueError(f"t_final and dt must be numbers, got {t_final!r}, {dt!r}") from None
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a finite number > 0, got {dt}")
    if not (math.isfinite(t_final) and t_final > 0):
        raise ValueError(f"t_final must be a finite number > 0, got {t_final}")
    n_steps = int(round(t_final / dt))
    if n_steps < 1 or abs(n_steps * dt - t_final) > 1e-9 * max(1.0, t_final):
        raise ValueError(f"t_final={t_final} must be a whole multiple of dt={dt} "
                         f"(e.g. dt={t_final / max(1, n_steps)})")
    if save_every is None:
        save_every = n_steps
    if int(save_every) != save_every or save_every < 1:
        raise ValueError(f"save_every must be a whole number >= 1, got {save_every}")
    save_every = int(save_every)
    if n_steps % save_every:
        raise ValueError(f"the number of steps t_final/dt = {n_steps} must be a multiple of "
                         f"save_every = {save_every}")
    return Horizon(t_final, dt, n_steps, save_every)


def check_ics(ics) -> tuple[np.ndarray, np.ndarray]:
    """Validate initial conditions; returns ``(ics (N, 5) float64, status0 (N,) int32)``.

    ``ics`` is ``(3,)``/``(5,)`` for one start or ``(N, 3)``/``(N, 5)`` for many: ``(x, y, theta)``
    with zero momentum, or ``(x, y, theta, p1, p2)``. Starts on the singular set ``theta = 0`` or
    with non-finite entries are flagged (not integrated); if *every* start is bad this raises,
    and a single bad start raises with a message that says what to change.
    """
    arr = np.asarray(ics, dtype=np.float64) if not isinstance(ics, np.ndarray) else ics.astype(np.float64)
    if arr.ndim == 1:
        arr = arr[None]
    if arr.ndim != 2 or arr.shape[1] not in (3, 5) or arr.shape[0] == 0:
        raise ValueError(f"initial conditions must have shape (3,), (5,), (N, 3) or (N, 5) "
                         f"[(x, y, theta) or (x, y, theta, p1, p2)], got {np.shape(ics)}")
    if arr.shape[1] == 3:
        arr = np.concatenate([arr, np.zeros((arr.shape[0], 2))], axis=1)
    status = np.zeros(arr.shape[0], np.int32)
    finite = np.all(np.isfinite(arr), axis=1)
    status[~finite] = Status.INVALID_INPUT
    status[finite & (arr[:, 2] == 0.0)] = Status.SINGULAR_START
    bad = np.flatnonzero(status)
    if bad.size:
        first = int(bad[0])
        why = ("theta0 = 0 is on the singular set where the control law is undefined; "
               "start with theta0 != 0 (e.g. 1e-3)" if status[first] == Status.SINGULAR_START
               else "it has a non-finite entry")
        msg = f"initial condition {first} {arr[first].tolist()} is invalid: {why}"
        if bad.size == arr.shape[0]:
            if arr.shape[0] == 1:
                raise ValueError(msg)
            raise ValueError(f"all {arr.shape[0]} initial conditions are invalid; first: {msg}")
        warnings.warn(f"{bad.size} of {arr.shape[0]} initial conditions are invalid and are flagged "
                      f"in `status` (outputs NaN), not integrated; first: {msg}", stacklevel=3)
    return arr, status


def initial_w(ics5: np.ndarray, status0: np.ndarray, dtype) -> jax.Array:
    """Map validated physical starts to the w chart, in float64 then cast to ``dtype``."""
    safe = np.where(status0[:, None] == 0, ics5, np.array([1.0, 0.0, 1.0, 0.0, 0.0]))
    with jax.enable_x64(True):
        yw = np.asarray(jax.vmap(state_to_w)(jnp.asarray(safe, jnp.float64)))
    if np.any(~np.isfinite(yw[status0 == 0])):
        raise ValueError("an initial condition overflows the w chart (|theta0| too small for this "
                         "precision); use |theta0| >= 1e-150")
    return jnp.asarray(yw, dtype)


@functools.partial(jax.jit, static_argnames=("n_out",))
def _init_batch(y0w, status0, args, ctl, n_out):
    return jax.vmap(init_state, in_axes=(0, 0, None, None, None))(y0w, status0, args, ctl, n_out)


@functools.partial(jax.jit, static_argnames=("n_attempts", "adaptive"), donate_argnums=(0,))
def _segment_batch(state, args, save_times, ctl, n_attempts, adaptive):
    seg = functools.partial(run_segment, n_attempts=n_attempts, adaptive=adaptive)
    return jax.vmap(seg, in_axes=(0, None, None, None))(state, args, save_times, ctl)


def _active(state: StepState, n_out: int, max_steps: int) -> np.ndarray:
    return np.asarray((state.status == Status.OK) & (state.j < n_out)
                      & (state.n_accept + state.n_reject < max_steps))


def _bucket(n: int) -> int:
    return 1 << max(0, (n - 1).bit_length())


def drive(y0w, status0, args: ClosedLoop, horizon: Horizon, *, adaptive: bool, rtol: float, atol: float,
          eps: float, max_steps: int, segment: int = 1024, compact: bool = True,
          progress=None, sharding=None) -> StepState:
    """Run the stepper on a batch until every trajectory is done or out of budget.

    Returns the final :class:`~jaxsleigh.stepper.StepState` (batched, as NumPy arrays) with
    trajectories that ran out of budget marked ``BUDGET_EXHAUSTED``. ``progress`` is an object
    with ``update(fraction_done)`` or ``None``. ``sharding`` places the batch on devices.
    """
    dtype = y0w.dtype
    n = y0w.shape[0]
    n_out = horizon.n_out
    save_times = jnp.asarray(horizon.save_times(), dtype)
    ctl = Controls(*(jnp.asarray(v, dtype) for v in (horizon.dt, rtol, atol, eps)),
                   max_steps=jnp.asarray(max_steps, jnp.int32))
    status0 = jnp.asarray(status0, jnp.int32)
    if sharding is not None:
        y0w, status0 = jax.device_put((y0w, status0), sharding)
    state = _init_batch(y0w, status0, args, ctl, n_out)
    idx = np.arange(n)                       # rows of the current batch in the full batch
    full = None                              # the full batch, filled as lanes are compacted away
    used = 0
    while True:
        act = _active(state, n_out, max_steps)
        if progress is not None:
            t_now = np.asarray(state.t, np.float64)
            done_frac = float(np.mean(np.where(act, t_now / horizon.t_final, 1.0)))
            progress.update((n - idx.size + done_frac * idx.size) / n)
        if not act.any() or used >= max_steps:
            break
        if compact and idx.size > 64 and act.sum() <= idx.size // 4:
            keep = np.flatnonzero(act)
            size = _bucket(max(keep.size, 64))
            pad = np.concatenate([keep, np.repeat(keep[:1], size - keep.size)])
            host = jax.tree_util.tree_map(np.asarray, state)
            if full is None:
                full = host
            else:
                full = jax.tree_util.tree_map(lambda f, h: _scatter(f, idx, h), full, host)
            # padded duplicates of the first lane recompute it; only the first copy is written back
            state = jax.tree_util.tree_map(lambda a: jnp.asarray(a[pad]), host)
            if sharding is not None:
                state = jax.device_put(state, sharding)
            idx = np.concatenate([idx[keep], np.full(size - keep.size, -1)])
        state = _segment_batch(state, args, save_times, ctl, segment, adaptive)
        used += segment
    host = jax.tree_util.tree_map(np.asarray, state)
    full = host if full is None else jax.tree_util.tree_map(lambda f, h: _scatter(f, idx, h), full, host)
    status = np.array(full.status)
    left = (status == Status.OK) & (full.j < n_out)
    status[left] = Status.BUDGET_EXHAUSTED
    return full._replace(status=status)


def _scatter(full: np.ndarray, idx: np.ndarray, part: np.ndarray) -> np.ndarray:
    out = np.array(full)
    real = idx >= 0
    out[idx[real]] = part[real]
    return out


def default_max_steps(horizon: Horizon, adaptive: bool) -> int:
    """Per-trajectory budget of attempted steps: the base steps, plus 20x room when adaptive."""
    base = horizon.n_steps + horizon.n_out + 8
    return 20 * base if adaptive else base
