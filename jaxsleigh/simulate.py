"""Simulate the closed loop from one or many initial conditions and keep decimated trajectories.

:func:`simulate` is the entry point for figures and for inspecting a few trajectories; for large
batches with summaries only, see :mod:`jaxsleigh.ensemble`.
"""
from __future__ import annotations

import time
from typing import Any, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from .closed_loop import ClosedLoop, closed_loop_hamiltonian_w
from .control import control_w
from .coordinates import w_to_q
from .engine import METHODS, check_ics, default_max_steps, drive_saving, initial_w, make_horizon
from .params import Gains, PlantParams, gains_to_dict, paper_gains, paper_plant
from .plant import velocity
from .progress import Progress

__all__ = ["Solution", "simulate", "DEFAULT_RTOL", "DEFAULT_ATOL"]

# Tolerances of the adaptive method, per dtype (chosen from measured accuracy, see README).
DEFAULT_RTOL = {"float32": 1e-6, "float64": 1e-8}
DEFAULT_ATOL = {"float32": 1e-6, "float64": 1e-8}
# Largest adaptive step, in base steps: at 0.1 s the adaptive method needs ~1300 steps per 100 s
# on typical starts (against 10^4 fixed steps) with final-state errors ~1e-6 (float32).
MAX_STEP_FACTOR = 10


class Solution(NamedTuple):
    """Decimated closed-loop trajectories.

    Attributes:
      t: (T,) saved times (0 included).
      q: (N, T, 3) configuration ``(x, y, theta)``.
      p: (N, T, 2) momentum.
      u: (N, T, 2) control.
      Hd: (N, T) closed-loop Hamiltonian.
      status: (N,) :class:`~jaxsleigh.status.Status` codes.
      n_steps: (N,) accepted steps; ``n_rejected``: (N,) rejected attempts.
      settings: what produced it (plant, gains, horizon, method, dtype, tolerances).
    """

    t: np.ndarray
    q: np.ndarray
    p: np.ndarray
    u: np.ndarray
    Hd: np.ndarray
    status: np.ndarray
    n_steps: np.ndarray
    n_rejected: np.ndarray
    settings: dict


@jax.jit
def _outputs(yw, args: ClosedLoop):
    """(w, p) trajectories -> q, u, Hd (vmapped over batch and time)."""

    def one(y):
        w, p = y[:3], y[3:]
        return w_to_q(w), control_w(w, velocity(p, args.plant), args.gains), closed_loop_hamiltonian_w(y, args)

    return jax.vmap(jax.vmap(one))(yw)


def plant_to_dict(plant: PlantParams) -> dict:
    d = plant.damping
    return {"m": float(plant.m), "J": float(plant.J), "l": float(plant.l),
            "damping": type(d).__name__, "damping_params": {k: float(v) for k, v in d._asdict().items()}
            if hasattr(d, "_asdict") else repr(d)}


def simulate(ics, *, plant: Optional[PlantParams] = None, gains: Optional[Gains] = None,
             t_final: float = 100.0, dt: float = 0.01, save_every: int = 10,
             method: str = "adaptive", rtol: Optional[float] = None, atol: Optional[float] = None,
             max_step: Optional[float] = None, max_steps: Optional[int] = None, x64: bool = False,
             progress: Any = None) -> Solution:
    """Simulate the closed loop (plant eq. 1 + control law eq. 13).

    Args:
      ics: ``(3,)``, ``(5,)``, ``(N, 3)`` or ``(N, 5)``: ``(x, y, theta[, p1, p2])``.
      plant, gains: defaults are the paper's (m = 2, J = 1, l = 1, Coulomb; L = diag(2, .5, .8),
        k = 0.1, D_hat = diag(4, 8)).
      t_final, dt: horizon and base step (``t_final`` a multiple of ``dt``).
      save_every: keep every ``save_every``-th base step (the saved grid is uniform in time).
      method: ``"adaptive"`` (default: RK4 with per-trajectory error control, starting at ``dt``;
        accurate near theta = 0) or ``"rk4"`` (classical fixed-step RK4 at ``dt``).
      rtol, atol: tolerances of ``"adaptive"`` (defaults per dtype, see ``DEFAULT_RTOL``).
      max_step: largest adaptive step (default ``10 * dt``; steps also never pass a save time).
      max_steps: budget of attempted steps per trajectory (default: 20x the base steps when
        adaptive); a trajectory that runs out gets status ``BUDGET_EXHAUSTED``.
      x64: compute in float64 (default float32).
      progress: ``True`` for a progress bar, ``False``/``None`` for none (auto on a terminal).

    Returns:
      :class:`Solution`, as NumPy arrays.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    horizon = make_horizon(t_final, dt, save_every)
    ics5, status0 = check_ics(ics)
    plant = paper_plant() if plant is None else plant
    gains = paper_gains() if gains is None else gains
    adaptive = method == "adaptive"
    with jax.enable_x64(bool(x64)):
        dtype = jnp.zeros(()).dtype
        rtol = DEFAULT_RTOL[dtype.name] if rtol is None else float(rtol)
        atol = DEFAULT_ATOL[dtype.name] if atol is None else float(atol)
        if not (rtol > 0 and atol > 0):
            raise ValueError(f"rtol and atol must be > 0, got {rtol}, {atol}")
        max_steps = default_max_steps(horizon, adaptive) if max_steps is None else int(max_steps)
        max_step = MAX_STEP_FACTOR * horizon.dt if max_step is None else float(max_step)
        if not max_step > 0:
            raise ValueError(f"max_step must be > 0, got {max_step}")
        if max_steps < horizon.n_steps:
            raise ValueError(f"max_steps={max_steps} is below the {horizon.n_steps} base steps of the horizon")
        args = ClosedLoop(plant, gains)
        y0w = initial_w(ics5, status0, dtype)
        t_start = time.perf_counter()
        with Progress(progress, desc="simulate") as bar:
            final, ys = drive_saving(y0w, status0, args, horizon, adaptive=adaptive, rtol=rtol, atol=atol,
                                     eps=0.05, max_steps=max_steps, max_step=max_step,
                                     progress=bar)
        yw = np.concatenate([np.asarray(y0w)[:, None], ys], axis=1)
        bad = status0 != 0
        yw[bad] = np.nan
        q, u, Hd = (np.array(a) for a in _outputs(jnp.asarray(yw), args))
    settings = {
        "plant": plant_to_dict(plant), "gains": gains_to_dict(gains),
        "t_final": horizon.t_final, "dt": horizon.dt, "save_every": horizon.save_every,
        "method": method, "rtol": rtol, "atol": atol, "max_step": max_step, "max_steps": max_steps,
        "dtype": dtype.name, "wall_s": time.perf_counter() - t_start,
    }
    # restore the exact initial state (the w chart round trip rounds it in float32)
    q[:, 0] = np.where(bad[:, None], np.nan, ics5[:, :3])
    return Solution(t=horizon.t(), q=q, p=yw[..., 3:], u=u, Hd=Hd, status=np.asarray(final.status),
                    n_steps=np.asarray(final.n_accept), n_rejected=np.asarray(final.n_reject),
                    settings=settings)
