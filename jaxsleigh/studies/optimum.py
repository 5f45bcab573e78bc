r"""The energy-optimal open-loop control per start: the absolute anchor the feedback laws are measured against.

**Problem.** For a start \(y_0 = (q_0, p_0)\), \(q = (x, y, \theta)\), and a horizon \(T\), find the input of least
energy that brings the plant (`jaxsleigh.model.plant`, paper eq. 1-2, with the plant's own damping: the
paper's Coulomb model by default, the same plant the feedback laws' closed loops integrate) to rest inside the
ball \(|q| \le \epsilon\) by \(T\):

\[ E^*(T) = \min_u \int_0^T |u(t)|^2\,dt \quad\text{s.t.}\quad |q(T)| \le \epsilon, \quad p(T) = 0. \]

**Why "at rest in the ball at T".** A feedback law's \(T_\epsilon\) is the time it *enters the ball and stays*.
An open-loop input that ends at rest (\(p(T) = 0\)) inside the ball and is zero afterwards stays there forever
(at \(p = 0\), \(u = 0\) the plant does not move), so "at rest in the ball at \(T\)" is the open-loop analogue of
\(T_\epsilon \le T\). Numerically the condition is \(|p(T)| \le\) ``p_tol`` (default \(10^{-3}\); under the
Coulomb damping a momentum that small coasts the sleigh by less than \(10^{-3}\,\epsilon\)) and
\(|q(T)| \le \epsilon + \) ``q_tol`` (default \(10^{-6}\)).

**Discretisation.** \(u\) is piecewise constant on \(N\) equal intervals (``intervals``), \(u(t) = u_k\) on
\([k h, (k + 1) h)\), \(h = T / N\), integrated by fixed-step RK4 with steps that never straddle a jump
(`jaxsleigh.integrate.open_loop`). Piecewise constant rather than a spline because (i) every such input is an
admissible input of the continuous problem, so each computed \(E^*_N(T)\) is *achievable* (an upper bound on
the continuous optimum, up to the RK4 error) and refining the grid by halving can only lower it; (ii) the
energy is exact, \(h \sum_k |u_k|^2\); (iii) the stepper keeps its order. The unknowns are scaled,
\(z_k = \sqrt h\, u_k\), so that \(E = |z|^2\) whatever the horizon.

**Solver.** Single shooting, differentiating through the simulator, with an augmented Lagrangian for the
terminal conditions (equalities \(c = p(T)\), inequality \(g = (|q(T)|^2 - \epsilon^2) / (2\epsilon) \le 0\)):

\[ L_\rho(z) = |z|^2 + \lambda^\top c + \tfrac\rho2 |c|^2 + \tfrac1{2\rho}\big(\max(0, \mu + \rho g)^2 - \mu^2\big), \]

minimised in \(z\) by L-BFGS (memory 8, with a parallel backtracking line search; optax's L-BFGS,
whose zoom line search is a sequential loop that every lane of a ``vmap``-ped batch waits out, took 0.8 s per
iteration on 12 problems against 8 ms here) for ``inner`` iterations, then
\(\lambda \leftarrow \lambda + \rho c\), \(\mu \leftarrow \max(0, \mu + \rho g)\), and \(\rho\) grows fourfold where
the violation did not halve, for at most ``outer`` rounds; every problem of a batch (starts x initial guesses, one
batch per horizon) runs at once, ``vmap``-ped. The problem is not convex (the sleigh is nonholonomic), so each problem
starts from ``guesses`` turn-drive-turn manoeuvres (turn towards or away from the origin, drive, turn to
\(\theta = 0\), each with a smooth speed profile, the input from the plant's inverse dynamics), and the best
converged one is kept: the result is the best local optimum found, an upper bound on the global one.

**Status per problem** (`OptimumStatus`, never a silent non-answer): ``CONVERGED`` when the terminal conditions
hold within their tolerances and the Karush-Kuhn-Tucker residual
\(|\nabla_z (|z|^2 + \lambda^\top c + \mu g)| \le\) ``kkt_tol`` \(\cdot \max(2|z|, 10^{-12})\); ``NOT_STATIONARY``
(feasible, not stationary: its energy is still achievable, perhaps not least); ``INFEASIBLE`` (terminal
conditions not met: no energy is claimed, ``energy`` is NaN); ``NONFINITE``; ``INVALID_INPUT``.
"""
from __future__ import annotations

import enum
import functools
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from ..integrate.open_loop import piecewise_constant_final, piecewise_constant_path
from ..integrate.pool import Ladder, padded
from ..model.params import PlantParams, as_plant
from ..model.plant import momentum_rhs
from ..files.checkpoint import run_key
from ..files.chunks import ChunkStore
from ..files.npz import damaged, read_npz, value_problem, write_npz_deterministic
from ..progress import Progress
from .config import plant_to_dict
from .options import RunOptions, study_options, takes_objects
from ..validate import check_count, check_memory, output_file

__all__ = ["OptimumOptions", "OptimumStatus", "OptimumResult", "Gap", "optimum", "initial_guesses", "energy_for_time",
           "time_for_energy", "save_optimum", "load_optimum", "rollout"]


class OptimumStatus(enum.IntEnum):
    CONVERGED = 0
    NOT_STATIONARY = 1
    INFEASIBLE = 2
    NONFINITE = 3
    INVALID_INPUT = 4


STATUS_WORDS = {
    OptimumStatus.CONVERGED: "at rest in the ball at T and stationary (KKT residual within kkt_tol)",
    OptimumStatus.NOT_STATIONARY: ("at rest in the ball at T but not stationary: the energy is achievable, perhaps "
                                   "not least; raise outer/inner iterations"),
    OptimumStatus.INFEASIBLE: ("terminal conditions not met within the iterations (the horizon may be too short for "
                               "the grid, or more iterations are needed); energy is NaN"),
    OptimumStatus.NONFINITE: "the iteration became inf/NaN; energy is NaN",
    OptimumStatus.INVALID_INPUT: "non-finite start or horizon <= 0; not solved, energy is NaN",
}


class OptimumOptions(NamedTuple):
    """Settings of the discretisation, the terminal tolerances and the solver (see the module's docstring).

    Attributes:
      intervals: N, the intervals on which u is constant.
      max_dt: the largest RK4 step; each interval gets ``ceil(T / (N max_dt))`` steps.
      p_tol: tolerance on |p(T)| (at rest).
      q_tol: tolerance on |q(T)| - eps.
      kkt_tol: relative tolerance on the KKT residual.
      outer, inner: augmented-Lagrangian rounds and L-BFGS iterations per round.
      guesses: initial guesses per problem (1 to 4 turn-drive-turn manoeuvres).
      rho0: the first penalty weight.
    """

    intervals: int = 24
    max_dt: float = 0.1
    p_tol: float = 1e-3
    q_tol: float = 1e-6
    kkt_tol: float = 1e-2
    outer: int = 20
    inner: int = 30
    guesses: int = 2
    rho0: float = 10.0

    def check(self) -> "OptimumOptions":
        """Self, or a ValueError saying what to change."""
        for name in ("intervals", "outer", "inner", "guesses"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"OptimumOptions.{name} must be a whole number >= 1, got {v!r}")
        if self.guesses > 4:
            raise ValueError(f"OptimumOptions.guesses must be 1 to 4, got {self.guesses}")
        for name in ("max_dt", "p_tol", "q_tol", "kkt_tol", "rho0"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float, np.floating)) and math.isfinite(v) and v > 0):
                raise ValueError(f"OptimumOptions.{name} must be a finite number > 0, got {v!r}")
        return self


# --------------------------------------------------------------------------------------------- initial guesses
_PLANS = ((+1, (1 / 3, 1 / 3, 1 / 3)), (-1, (1 / 3, 1 / 3, 1 / 3)), (+1, (0.2, 0.6, 0.2)), (-1, (0.2, 0.6, 0.2)))


def _bump(t, t0, tau, delta):
    """Speed and its derivative of a smooth move by ``delta`` over ``[t0, t0 + tau]``:
    \\(v = \\frac\\delta\\tau (1 - \\cos 2\\pi s)\\), \\(s = (t - t0)/\\tau\\)."""
    s = (t - t0) / tau
    inside = (s >= 0) & (s < 1)
    v = np.where(inside, delta / tau * (1 - np.cos(2 * np.pi * s)), 0.0)
    a = np.where(inside, delta / tau * 2 * np.pi / tau * np.sin(2 * np.pi * s), 0.0)
    return v, a


@jax.jit
def _free_rhs(p, plant):
    """\\(\\dot p\\) at u = 0 for momenta p (2, n) (the turning plan's inverse dynamics)."""
    return jax.vmap(lambda pp: momentum_rhs(None, pp, jnp.zeros(2, pp.dtype), plant), in_axes=1, out_axes=1)(p)


def initial_guesses(start, T: float, intervals: int, plant: Optional[PlantParams] = None, count: int = 4,
                    samples: int = 16) -> np.ndarray:
    r"""``count`` turn-drive-turn inputs (count, N, 2) for one start (5,): turn to face the origin (forward, or
    backward with the sleigh driving in reverse), drive there, turn to \(\theta = 0\); the fractions of \(T\) of
    the three phases are 1/3 each or 0.2/0.6/0.2. Each phase has the speed profile of `_bump`; the input is the
    plant's inverse dynamics \(u = \dot p - \dot p|_{u = 0}\), averaged over each interval."""
    plant = as_plant(plant)
    x, y, th0 = (float(v) for v in start[:3])
    N = int(intervals)
    t = (np.arange(N * samples) + 0.5) * (T / (N * samples))
    Jt = float(plant.J) + float(plant.m) * float(plant.l) ** 2
    out = []
    for sign, (fa, fb, fc) in _PLANS[:count]:
        phi = math.atan2(-sign * y, -sign * x)
        cands = [phi + 2 * math.pi * k for k in (-1, 0, 1)]
        phi = min(cands, key=lambda c: abs(c - th0) + abs(c))
        d = sign * math.hypot(x, y)
        w1, a1 = _bump(t, 0.0, fa * T, phi - th0)
        v, av = _bump(t, fa * T, fb * T, d)
        w3, a3 = _bump(t, (fa + fb) * T, fc * T, -phi)
        w, aw = w1 + w3, a1 + a3
        p = np.stack([float(plant.m) * v, Jt * w])
        pdot = np.stack([float(plant.m) * av, Jt * aw])
        with jax.enable_x64(True):
            free = np.asarray(_free_rhs(p, plant))
        u = (pdot - free).T.reshape(N, samples, 2).mean(axis=1)
        out.append(u)
    return np.stack(out)


# ------------------------------------------------------------------------------------------------- the solver
def _substeps(T: float, intervals: int, max_dt: float) -> int:
    """RK4 steps per interval: ``ceil(T / (intervals max_dt))``, at least 1."""
    return max(1, int(math.ceil(T / (intervals * max_dt) - 1e-9)))


def rollout(start, u, T: float, plant: Optional[PlantParams] = None, *, max_dt: float = 0.1, path: bool = False):
    """The plant from ``start`` (5,) under the piecewise-constant input ``u`` (N, 2) over ``[0, T]`` (float64):
    the final state (5,), or with ``path=True`` the states at the interval ends (N + 1, 5)."""
    plant = as_plant(plant)
    u = np.asarray(u, np.float64)
    fn = piecewise_constant_path if path else piecewise_constant_final
    with jax.enable_x64(True):
        return np.asarray(fn(jnp.asarray(start, jnp.float64), jnp.asarray(u), T, plant,
                             substeps=_substeps(T, u.shape[0], max_dt)))


_ALPHAS = tuple(10.0 ** (-k / 2) for k in range(13))     # 1 down to 1e-6
_MEMORY = 8


def _lbfgs_direction(g, S, Y, r):
    r"""L-BFGS two-loop recursion on flat vectors: \(d = -H g\) from the pairs ``S``, ``Y`` (m, n) (oldest
    first) and \(r_i = 1 / (y_i^\top s_i)\) (0 for an empty slot), \(H_0 = \gamma I\) scaled by the newest pair."""
    q = g
    alphas = []
    for i in reversed(range(S.shape[0])):
        a = r[i] * (S[i] @ q)
        q = q - a * Y[i]
        alphas.append(a)
    yy = Y[-1] @ Y[-1]
    gamma = jnp.where(r[-1] > 0, 1.0 / jnp.where(r[-1] > 0, r[-1] * yy, 1.0), 0.5)
    q = gamma * q
    for i, a in zip(range(S.shape[0]), reversed(alphas)):
        b = r[i] * (Y[i] @ q)
        q = q + (a - b) * S[i]
    return -q


@functools.lru_cache(maxsize=16)
def _functions(plant, eps: float, substeps: int):
    r"""Jitted, vmapped pieces of the augmented Lagrangian for one program (one number of RK4 substeps).

    The inner minimiser is L-BFGS with a *parallel* backtracking line search: the trial steps `_ALPHAS` are
    evaluated at once (one batched forward simulation) and the longest with Armijo's decrease
    \(L(z + \alpha d) \le L(z) + 10^{-4} \alpha \nabla L^\top d\) is taken (else the best trial if it decreases
    L, else none and the memory is cleared). No sequential line-search loop: every lane of a batch costs the
    same, one gradient and ``len(_ALPHAS)`` forward runs per iteration."""

    def terms(z, y0, T):
        h = T / z.shape[0]
        yT = piecewise_constant_final(y0, z / jnp.sqrt(h), T, plant, substeps=substeps)
        q, p = yT[:3], yT[3:]
        return p, (q @ q - eps * eps) / (2 * eps), yT

    def aug(z, y0, T, lam, mu, rho):
        c, g, _ = terms(z, y0, T)
        return (jnp.sum(z * z) + lam @ c + 0.5 * rho * (c @ c)
                + (jnp.maximum(0.0, mu + rho * g) ** 2 - mu * mu) / (2 * rho))

    def start(z, y0, T, lam, mu, rho):
        f, g = jax.value_and_grad(aug)(z, y0, T, lam, mu, rho)
        n = z.size
        return f, g, jnp.zeros((_MEMORY, n), z.dtype), jnp.zeros((_MEMORY, n), z.dtype), jnp.zeros(_MEMORY, z.dtype)

    def step(z, f, g, S, Y, r, y0, T, lam, mu, rho):
        shape = z.shape
        gf = g.ravel()
        d = _lbfgs_direction(gf, S, Y, r)
        slope = gf @ d
        # no curvature pairs (or not a descent direction): steepest descent scaled to a step of length <= 1
        gn = jnp.sqrt(gf @ gf)
        bad = ~(slope < 0) | ~(r.sum() > 0)
        scale = jnp.minimum(0.5, 1.0 / jnp.maximum(gn, 1e-300))
        d = jnp.where(bad, -gf * scale, d)
        slope = jnp.where(bad, -scale * (gf @ gf), slope)
        alphas = jnp.asarray(_ALPHAS, z.dtype)
        trial = jax.vmap(lambda a: aug(z + a * d.reshape(shape), y0, T, lam, mu, rho))(alphas)
        trial = jnp.where(jnp.isfinite(trial), trial, jnp.inf)
        armijo = trial <= f + 1e-4 * alphas * slope
        k = jnp.where(armijo.any(), jnp.argmax(armijo), jnp.argmin(trial))
        moved = trial[k] < f
        z_new = jnp.where(moved, z + alphas[k] * d.reshape(shape), z)
        f_new, g_new = jax.value_and_grad(aug)(z_new, y0, T, lam, mu, rho)
        s, yv = (z_new - z).ravel(), (g_new - g).ravel()
        sy = s @ yv
        keep = moved & (sy > 1e-12 * jnp.sqrt((s @ s) * (yv @ yv)))
        S2 = jnp.where(keep, jnp.concatenate([S[1:], s[None]]), S)
        Y2 = jnp.where(keep, jnp.concatenate([Y[1:], yv[None]]), Y)
        r2 = jnp.where(keep, jnp.concatenate([r[1:], (1.0 / jnp.where(keep, sy, 1.0))[None]]),
                       jnp.where(moved, r, jnp.zeros_like(r)))
        return z_new, f_new, g_new, S2, Y2, r2

    def lagrangian(z, y0, T, lam, mu):
        c, g, _ = terms(z, y0, T)
        return jnp.sum(z * z) + lam @ c + mu * g

    def measure(z, y0, T, lam, mu):
        c, g, yT = terms(z, y0, T)
        grad = jax.grad(lagrangian)(z, y0, T, lam, mu)
        return c, g, yT, jnp.sqrt(jnp.sum(grad * grad)), jnp.sqrt(jnp.sum(z * z))

    return jax.jit(jax.vmap(start)), jax.jit(jax.vmap(step)), jax.jit(jax.vmap(measure))


#: the optimum's batches: a batch of 128 problems or more shrinks to the next power of two of its working ones
_LADDER = Ladder(floor=1, shrink_from=128)


def _solve_batch(y0, T, z0, plant, eps: float, opts: OptimumOptions, substeps: int, progress=None):
    """Augmented Lagrangian on a batch: ``y0`` (B, 5), ``T`` (B,), ``z0`` (B, N, 2), all float64.

    Problems that converge leave the batch: once at most a quarter of a batch of 128 or more is still working, the
    rest continues in a batch of the next power of two (`_LADDER`, padded with copies of a working problem), so that
    a few slow problems do not keep the whole batch busy (each new size compiles once)."""
    try:
        start, step, measure = _functions(plant, eps, substeps)
    except TypeError:                               # a plant with unhashable leaves: compiled afresh
        start, step, measure = _functions.__wrapped__(plant, eps, substeps)
    B = y0.shape[0]
    y0_h, T_h, z_h = np.asarray(y0, np.float64), np.asarray(T, np.float64), np.array(z0, np.float64)
    lam_h, mu_h, rho_h, vp_h = np.zeros((B, 2)), np.zeros(B), np.full(B, float(opts.rho0)), np.full(B, np.inf)
    status_h = np.full(B, int(OptimumStatus.INFEASIBLE), np.int32)
    yT_h, kkt_h, zn_h = np.full((B, 5), np.nan), np.full(B, np.nan), np.full(B, np.nan)
    active, size, fresh, rho_before = np.arange(B), B, True, None   # rho_before: the penalty weights of the last pass
    for k in range(opts.outer):
        if k == 0 or _LADDER.shrinks(size, active.size):
            size = B if k == 0 else _LADDER.size(active.size)
            lanes = padded(active, size)
            z, y0j, Tj = z_h[lanes], y0_h[lanes], T_h[lanes]
            lam, mu, rho, vp = lam_h[lanes], mu_h[lanes], rho_h[lanes], vp_h[lanes]
            fresh = True
        f, g, S0, Y0, r0 = start(z, y0j, Tj, lam, mu, rho)
        if fresh:
            S, Y, r = S0, Y0, r0
            fresh = False
        else:                       # keep the curvature pairs where the penalty weight did not change
            r = np.where((rho == rho_before)[:, None], np.asarray(r), 0.0)
        rho_before = rho.copy()
        for _ in range(opts.inner):
            z, f, g, S, Y, r = step(z, f, g, S, Y, r, y0j, Tj, lam, mu, rho)
        # the multipliers' update is host work (NumPy, the same float64 operations one by one): on the device each
        # operation compiled a program of its own per batch size
        c, gq = (np.asarray(a) for a in measure(z, y0j, Tj, lam, mu)[:2])
        lam = lam + rho[:, None] * c
        mu = np.maximum(0.0, mu + rho * gq)
        viol = np.maximum(np.linalg.norm(c, axis=1), np.maximum(gq, 0.0))
        rho = np.where(viol > 0.5 * vp, np.minimum(rho * 4.0, 1e8), rho)
        vp = np.minimum(viol, vp)
        c, gq, yT, kkt, zn = (np.asarray(a) for a in measure(z, y0j, Tj, lam, mu))
        st = _status(c, gq, kkt, zn, yT, eps, opts)
        n = active.size
        z_h[active], lam_h[active], mu_h[active] = np.asarray(z)[:n], np.asarray(lam)[:n], np.asarray(mu)[:n]
        rho_h[active], vp_h[active], status_h[active] = rho[:n], vp[:n], st[:n]
        yT_h[active], kkt_h[active], zn_h[active] = yT[:n], kkt[:n], zn[:n]
        if progress is not None:
            progress((k + 1) / opts.outer, float(np.mean(status_h == OptimumStatus.CONVERGED)))
        keep = st[:n] != OptimumStatus.CONVERGED
        if not keep.any():
            break
        if not keep.all():          # the working problems move to the front; the batch keeps its size until it shrinks
            order = padded(np.flatnonzero(keep), size)
            z, y0j, Tj, lam, mu, S, Y, r = (np.asarray(a)[order] for a in (z, y0j, Tj, lam, mu, S, Y, r))
            rho, vp, rho_before = rho[order], vp[order], rho_before[order]
            active = active[keep]
    return z_h, status_h, yT_h, kkt_h / np.maximum(2 * zn_h, 1e-12), lam_h, mu_h


def _status(c, g, kkt, zn, yT, eps, opts):
    qn = np.linalg.norm(yT[:, :3], axis=1)
    pn = np.linalg.norm(c, axis=1)
    finite = np.isfinite(yT).all(axis=1) & np.isfinite(kkt) & np.isfinite(zn)
    feasible = (pn <= opts.p_tol) & (qn <= eps + opts.q_tol)
    stationary = kkt <= opts.kkt_tol * np.maximum(2 * zn, 1e-12)
    return np.where(~finite, OptimumStatus.NONFINITE,
                    np.where(~feasible, OptimumStatus.INFEASIBLE,
                             np.where(stationary, OptimumStatus.CONVERGED, OptimumStatus.NOT_STATIONARY))).astype(
        np.int32)


# ------------------------------------------------------------------------------------------------ the result
class Gap(NamedTuple):
    r"""A law's distance from the optimum per start (`OptimumResult.gap`): ``time`` \(T_{law} / T^*(E_{law})\),
    ``energy`` \(E_{law} / E^*(T_{law})\), values only where the frontier's solved horizons cover the law (NaN
    elsewhere), and where each was a bound rather than a value (``time_where`` -1: a lower bound, the law's energy
    exceeds the shortest horizon's; ``energy_where`` +1: a lower bound, the law is slower than the longest horizon;
    0: interpolated). ``time_at_least`` / ``energy_at_least``: the lower bound where the ratio is one (never below
    1, the ratio's physical limit; NaN elsewhere). A bound is never a value: a search that minimised it as one drove
    a gain to 1317 to spend more energy than the shortest horizon needs and report a time ratio of 0.17."""

    time: np.ndarray
    energy: np.ndarray
    time_where: np.ndarray
    energy_where: np.ndarray
    time_at_least: Optional[np.ndarray] = None
    energy_at_least: Optional[np.ndarray] = None


@dataclass
class OptimumResult:
    """Per start and horizon, the least-energy input found and how it ends.

    Attributes (S starts, H horizons, N intervals):
      starts (S, 5), horizons (H,), eps.
      energy (S, H): \\(E^*_N(T)\\), \\(\\int_0^T |u|^2 dt\\) (NaN unless the status is CONVERGED or NOT_STATIONARY).
      u (S, H, N, 2): the input on each interval.
      status (S, H): `OptimumStatus` codes.
      q_final (S, H, 3), p_final (S, H, 2): the state at T (float64 RK4 of the plant).
      kkt (S, H): the relative KKT residual; guess (S, H): which initial guess won.
      settings: the options and the plant, as recorded in files.
    """

    starts: np.ndarray
    horizons: np.ndarray
    eps: float
    energy: np.ndarray
    u: np.ndarray
    status: np.ndarray
    q_final: np.ndarray
    p_final: np.ndarray
    kkt: np.ndarray
    guess: np.ndarray
    settings: dict = field(default_factory=dict)
    run_info: dict = field(default_factory=dict)

    @property
    def certified(self) -> np.ndarray:
        """(S, H) bool: the optimiser converged to a certified local optimum (status ``CONVERGED``; a start's
        ``converged`` in every trajectory result means settled, another quantity)."""
        return self.status == OptimumStatus.CONVERGED

    def frontier(self) -> np.ndarray:
        """\\(E^*(T)\\) made non-increasing in T (S, H): a start that can be at rest at \\(T\\) can arrive at
        \\(T' > T\\) and wait with u = 0, so the least energy never grows with the horizon; each entry is the
        least achieved energy at this or any shorter horizon (NaN until one is solved)."""
        e = np.where(self.status <= OptimumStatus.NOT_STATIONARY, self.energy, np.inf)
        env = np.minimum.accumulate(e, axis=1)
        return np.where(np.isfinite(env), env, np.nan)

    def time_for_energy(self, energy) -> tuple:
        """\\(T^*(E)\\) per start for energies (S,): see `time_for_energy`."""
        return time_for_energy(self.horizons, self.frontier(), energy)

    def energy_for_time(self, T) -> tuple:
        """\\(E^*(T)\\) per start for horizons (S,): see `energy_for_time`."""
        return energy_for_time(self.horizons, self.frontier(), T)

    def gap(self, T_law, E_law) -> "Gap":
        r"""How far a law's runs from these starts are from the optimum: per start, the **time ratio**
        \(T_{law} / T^*(E_{law})\) (how much longer than the earliest rest in the ball that the law's energy could
        buy) and the **energy ratio** \(E_{law} / E^*(T_{law})\) (how much more energy than rest in the ball as
        early as the law needs). Both are \(\ge 1\) up to the grid's and the solver's error, since the optimum is
        the least over every input and a law's run is one of them.

        Outside the solved horizons the ratios are *bounds*, never values: ``time`` / ``energy`` are NaN there, the
        bound is in ``time_at_least`` / ``energy_at_least`` and the case in ``time_where`` / ``energy_where`` (as
        `time_for_energy` / `energy_for_time`): where \(E_{law} > E^*(T_{min})\), \(T^* < T_{min}\) and the time
        ratio is at least \(\max(1, T_{law} / T_{min})\) (``-1``); where \(T_{law} > T_{max}\) the energy ratio is
        at least \(\max(1, E_{law} / E^*(T_{max}))\) (``+1``); where the law's energy buys no solved horizon
        (``+1``) or nothing was solved (``2``) the time ratio is unknown (NaN, no bound). A start the law did not
        settle (``T_law`` NaN or inf) has NaN ratios. To judge a law on such starts, solve the frontier at
        horizons that cover its times and energies.

        Args:
          T_law, E_law: (S,) the law's \(T_\epsilon\) (of this result's ``eps``) and control energy per start.
        """
        T_law = np.broadcast_to(np.asarray(T_law, float), self.starts.shape[:1])
        E_law = np.broadcast_to(np.asarray(E_law, float), self.starts.shape[:1])
        fr = self.frontier()
        T_star, wT = time_for_energy(self.horizons, fr, E_law)
        E_star, wE = energy_for_time(self.horizons, fr, T_law)
        last = np.array([f[np.isfinite(f)][-1] if np.isfinite(f).any() else np.nan for f in fr])
        ok = np.isfinite(T_law) & np.isfinite(E_law)
        first = np.array([h[np.isfinite(f)][0] if np.isfinite(f).any() else np.nan
                          for h, f in zip(np.broadcast_to(self.horizons, fr.shape), fr)])
        with np.errstate(invalid="ignore", divide="ignore"):
            t = np.where(wT == 0, T_law / T_star, np.nan)
            e = np.where(wE == 0, E_law / E_star, np.nan)
            # a bound is at least the ratio's physical limit, 1: the optimum is the least over every input
            t_low = np.where(wT == -1, np.maximum(T_law / first, 1.0), np.nan)
            e_low = np.where(wE == 1, np.maximum(E_law / last, 1.0), np.nan)
        nan = np.nan
        return Gap(np.where(ok, t, nan), np.where(ok, e, nan), wT, wE, np.where(ok, t_low, nan),
                   np.where(ok, e_low, nan))

    def counts(self) -> dict:
        return {s.name.lower(): int(np.sum(self.status == s)) for s in OptimumStatus}

    def __repr__(self) -> str:
        # a summary, not every array (print(result) of many starts dumped u, energy, ... whole): `describe`'s lines
        # (at most 8 horizons), eps and the arrays' shapes
        lines = self.describe().splitlines()
        if len(lines) > 9:
            lines = lines[:9] + [f"  ... and {len(lines) - 9} more horizons (describe() lists them all)"]
        arrays = ", ".join(f"{f} {tuple(np.shape(getattr(self, f)))}"
                           for f in ("starts", "horizons", "energy", "u", "status", "q_final", "p_final", "kkt",
                                     "guess"))
        return "\n".join([f"OptimumResult({lines[0]}", *lines[1:], f"  eps = {self.eps:g}",
                          f"  arrays: {arrays})"])

    def describe(self) -> str:
        """A few lines: how many problems converged, and the median E*(T) per horizon."""
        lines = [f"{self.status.size} problems ({self.starts.shape[0]} starts x {self.horizons.size} horizons): "
                 + ", ".join(f"{n} {k.replace('_', ' ')}" for k, n in self.counts().items() if n)]
        for j, T in enumerate(self.horizons):
            e = self.energy[:, j][np.isfinite(self.energy[:, j])]
            med = f"{np.median(e):.4g}" if e.size else "none solved"
            lines.append(f"  T = {T:g}: median E* = {med} ({int(np.sum(self.certified[:, j]))} certified)")
        return "\n".join(lines)


def _per_start(horizons, frontier, x, lookup, unknown: int) -> tuple:
    """``(values, where)`` per start: ``lookup(h, e, x_i) -> (value, where)`` on the start's solved horizons ``h``
    and frontier values ``e`` (``x`` broadcast to the starts); NaN with ``where`` 2 when nothing was solved, and
    ``unknown`` for a non-finite ``x_i``."""
    horizons = np.asarray(horizons, float)
    frontier = np.atleast_2d(frontier)
    x = np.broadcast_to(np.asarray(x, float), frontier.shape[:1])
    out = np.full(x.shape, np.nan)
    where = np.zeros(x.shape, np.int8)
    for i in range(x.size):
        ok = np.isfinite(frontier[i])
        if not ok.any() or not np.isfinite(x[i]):
            where[i] = 2 if not ok.any() else unknown
        else:
            out[i], where[i] = lookup(horizons[ok], frontier[i][ok], x[i])
    return out, where


def energy_for_time(horizons, frontier, T) -> tuple:
    r"""\(E^*(T)\) between solved horizons: per start, piecewise linear in \((\log T, \log E)\) through the
    solved points of the non-increasing ``frontier`` (S, H). Returns ``(E, where)`` with ``where`` = 0 inside
    the solved horizons, -1 for \(T\) below the shortest (E is then NaN: \(E^*(T) \ge E^*(T_{min})\), the
    caller may use that bound), +1 above the longest (E NaN; \(E^*(T) \le E^*(T_{max})\))."""
    def lookup(h, e, t):
        if t < h[0] - 1e-12:
            return np.nan, -1
        if t > h[-1] + 1e-12:
            return np.nan, 1
        return np.exp(np.interp(np.log(t), np.log(h), np.log(e))), 0     # piecewise linear in (log T, log E)

    return _per_start(horizons, frontier, T, lookup, unknown=0)


def time_for_energy(horizons, frontier, energy) -> tuple:
    r"""\(T^*(E)\), the shortest horizon at which energy \(E\) suffices: the inverse of the non-increasing
    frontier, piecewise linear in \((\log E, \log T)\) between solved points (flat stretches, where a longer
    horizon saves nothing, give their shortest horizon). Returns ``(T, where)``: ``where`` = 0 inside,
    -1 when \(E\) exceeds \(E^*\) at the shortest solved horizon (\(T^* \le T_{min}\); T NaN), +1 when \(E\) is
    below \(E^*\) at the longest (\(T^* > T_{max}\), or no horizon suffices; T NaN), 2 when nothing was solved."""
    def lookup(h, e, E):
        if E > e[0]:
            return np.nan, -1
        if E < e[-1]:
            return np.nan, 1
        # first solved horizon whose frontier is at or below E, then interpolate within the step before it
        j = int(np.argmax(e <= E))
        if j == 0 or e[j - 1] == e[j]:
            return h[j], 0
        s = (np.log(E) - np.log(e[j - 1])) / (np.log(e[j]) - np.log(e[j - 1]))
        return float(np.exp(np.log(h[j - 1]) + s * (np.log(h[j]) - np.log(h[j - 1])))), 0

    return _per_start(horizons, frontier, energy, lookup, unknown=2)


# ------------------------------------------------------------------------------------------------ the front door
def _as_starts(starts) -> np.ndarray:
    try:
        a = np.asarray(starts, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError("starts must be numbers: an array (S, 3) [x, y, theta] or (S, 5) [x, y, theta, p1, p2]")
    if a.ndim == 1:
        a = a[None]
    if a.ndim != 2 or a.shape[1] not in (3, 5) or a.shape[0] == 0:
        raise ValueError(f"starts must have shape (S, 3) [x, y, theta] or (S, 5) [x, y, theta, p1, p2] with S >= 1, "
                         f"got {a.shape}")
    if a.shape[1] == 3:
        a = np.concatenate([a, np.zeros((a.shape[0], 2))], axis=1)
    return a


def as_horizons(horizons) -> np.ndarray:
    """``horizons`` as a 1-D float64 array of strictly increasing, finite horizons > 0 (else ``ValueError``)."""
    try:
        h = np.atleast_1d(np.asarray(horizons, dtype=np.float64))
    except (TypeError, ValueError):
        raise ValueError(f"horizons must be numbers, e.g. (5, 10, 20, 40), got {horizons!r}") from None
    if h.ndim != 1 or h.size == 0 or not np.all(np.isfinite(h)) or np.any(h <= 0):
        raise ValueError(f"horizons must be finite numbers > 0, e.g. (5, 10, 20, 40), got {np.asarray(horizons).tolist()}")
    if np.any(np.diff(h) <= 0):
        raise ValueError(f"horizons must increase strictly, e.g. (5, 10, 20, 40), got {h.tolist()}")
    return h


def _fields(n, H, N):
    return {"energy": (n, H), "u": (n, H, N, 2), "status": (n, H), "q_final": (n, H, 3), "p_final": (n, H, 2),
            "kkt": (n, H), "guess": (n, H)}


def _solve_starts(starts, horizons, plant, eps, opts, progress=None):
    """All horizons for a block of starts: arrays of `_fields`."""
    S, H, N, K = starts.shape[0], horizons.size, opts.intervals, opts.guesses
    out = {k: np.full(shape, np.nan) for k, shape in _fields(S, H, N).items()}
    out["status"] = np.full((S, H), int(OptimumStatus.INVALID_INPUT), np.int32)
    out["guess"] = np.full((S, H), -1, np.int32)
    valid = np.isfinite(starts).all(axis=1)
    idx = np.flatnonzero(valid)
    if idx.size == 0:
        return out
    with jax.enable_x64(True):
        for j, T in enumerate(horizons):
            sub = _substeps(float(T), opts.intervals, opts.max_dt)
            h = T / N
            z0 = np.stack([initial_guesses(starts[i], float(T), N, plant, K) for i in idx]) * math.sqrt(h)
            B = idx.size * K
            y0 = np.repeat(starts[idx], K, axis=0)
            report = None if progress is None else (lambda f, c, j=j: progress((j + f) / H, c))
            z, status, yT, kkt, _, _ = _solve_batch(y0, np.full(B, T), z0.reshape(B, N, 2), plant, eps, opts, sub,
                                                    report)
            energy = np.sum(z.reshape(B, -1) ** 2, axis=1)
            rank = np.where(status <= OptimumStatus.NOT_STATIONARY, status * 1e300 + energy,
                            np.inf).reshape(-1, K)
            # best: converged before not-stationary, then least energy; if none is feasible, the least violation
            viol = (np.linalg.norm(yT[:, 3:], axis=1) + np.maximum(np.linalg.norm(yT[:, :3], axis=1) - eps, 0)
                    ).reshape(-1, K)
            best = np.where(np.isfinite(rank).any(axis=1), np.argmin(np.where(np.isfinite(rank), rank, np.inf),
                                                                     axis=1),
                            np.argmin(np.where(np.isfinite(viol), viol, np.inf), axis=1))
            pick = np.arange(idx.size) * K + best
            st = status[pick]
            out["status"][idx, j] = st
            out["energy"][idx, j] = np.where(st <= OptimumStatus.NOT_STATIONARY, energy[pick], np.nan)
            out["u"][idx, j] = z[pick] / math.sqrt(h)
            out["q_final"][idx, j] = yT[pick, :3]
            out["p_final"][idx, j] = yT[pick, 3:]
            out["kkt"][idx, j] = kkt[pick]
            out["guess"][idx, j] = best
    return out


def _settings(plant, eps, opts, horizons) -> dict:
    return {"eps": float(eps), "horizons": [float(h) for h in horizons], "options": opts._asdict(),
            "plant": plant_to_dict(plant),
            "dtype": "float64"}


#: Starts solved (and checkpointed) at once when ``run.chunk_size`` is ``None``.
OPTIMUM_CHUNK = 64

#: Host memory the reverse pass of one problem keeps per RK4 step (float64; XLA's memory analysis of the compiled
#: value-and-gradient measured 534 bytes).
BYTES_PER_RK4_STEP = 540
#: The most RK4 steps of one problem's iterations: steps of one simulation x outer x inner (an L-BFGS iteration runs 14
#: simulations: the gradient and 13 trial steps). 256 starts x 4 horizons with 2 guesses (750 steps x 600 iterations
#: per start and guess) took 501 s on 2 CPU cores: 2.2 us per step and iteration of one guess, so 600,000,000 (a
#: horizon of 100,000 s with the default 20 x 30 iterations) take about 45 minutes per start and horizon with 2 guesses.
MAX_PROBLEM_STEPS = 600_000_000

#: The names `check_sizes` gives in its messages: the Python keywords (the command line passes its flags).
KEYWORDS = {"starts": "starts", "horizons": "horizons", "intervals": "options.intervals",
            "guesses": "options.guesses", "outer": "options.outer", "inner": "options.inner",
            "chunk_size": "run.chunk_size"}


def check_sizes(n_starts: int, horizons, opts: OptimumOptions, chunk_size: int, names: dict | None = None) -> None:
    r"""Refuse, before any work, a run that would not fit in memory or would take days (`ValueError` naming what to
    change: ``names`` maps `KEYWORDS`' keys to the keywords or flags).

    * results: per start \(8 \cdot 2 H (2N + 9)\) bytes (energy, u, status, final state, KKT, guess, kept per chunk
      and concatenated), \(H\) horizons of \(N\) intervals;
    * the gradient: \(B \cdot N \lceil T_{max} / (N\,\Delta t_{max}) \rceil\) RK4 steps of
      `BYTES_PER_RK4_STEP`, \(B\) = min(chunk, S) x guesses problems solved at once;
    * time: at most `MAX_PROBLEM_STEPS` RK4 steps x iterations for one problem (steps x outer x inner).
    """
    w = {**KEYWORDS, **(names or {})}
    h = np.asarray(horizons, np.float64)
    H, N, K = h.size, int(opts.intervals), int(opts.guesses)
    check_memory(n_starts, w["starts"], bytes_per_start=40 + 16 * H * (2 * N + 9),
                 fix=f"give fewer starts{'' if w['starts'] == 'starts' else ' (' + w['starts'] + ')'}, fewer "
                     f"{w['horizons']} or fewer {w['intervals']}, or split the starts into several runs")
    longest = float(h.max())
    steps = N * _substeps(longest, N, float(opts.max_dt))
    lanes = min(int(chunk_size), int(n_starts)) * K
    check_memory(lanes * steps, f"{w['horizons']} up to {longest:g} s", bytes_per_start=BYTES_PER_RK4_STEP,
                 unit=f"RK4 steps held for the gradient ({lanes:,} problems at once x {steps:,} steps of at most "
                      f"{float(opts.max_dt):g} s)",
                 fix=f"use shorter {w['horizons']}, or solve fewer problems at once (a smaller {w['chunk_size']}, "
                     f"{w['guesses']} 1)")
    outer, inner = int(opts.outer), int(opts.inner)
    check_count(f"{w['horizons']} up to {longest:g} s ({steps:,} RK4 steps) x {w['outer']} {outer:,} x {w['inner']} "
                f"{inner:,}: the steps of one problem's iterations", steps * outer * inner, maximum=MAX_PROBLEM_STEPS,
                reason="every iteration runs 14 simulations, and 600,000,000 take about 45 minutes per start and "
                       "horizon on 2 CPU cores",
                fix=f"use shorter {w['horizons']} or fewer iterations ({w['outer']}, {w['inner']})")


@takes_objects
def optimum(starts, horizons=(5.0, 10.0, 20.0, 40.0), *, plant: Optional[PlantParams] = None, eps: float = 0.05,
            options: Optional[OptimumOptions] = None, run: Optional[RunOptions] = None) -> Optional[OptimumResult]:
    r"""The energy-optimal frontier: per start and horizon \(T\), the least-energy piecewise-constant input that
    brings the plant to rest in the ball \(|q| \le \epsilon\) by \(T\) (module docstring: problem, grid, solver,
    statuses). Always float64.

    Args:
      starts: (S, 3) ``[x, y, theta]`` at rest, or (S, 5) with the momentum ``[p1, p2]``.
      horizons: increasing horizons \(T > 0\) [s].
      plant: `jaxsleigh.PlantParams` (the paper's, Coulomb damping, by default: what the laws' runs use).
      eps: radius of the terminal ball (that of the laws' \(T_\epsilon\)).
      options: `OptimumOptions`.
      run: `jaxsleigh.RunOptions`: ``chunk_size``, the starts solved (and checkpointed) at once (``None``: 64);
        ``progress``, a progress bar on stderr (``None``: on a terminal); ``checkpoint_dir``, ``resume`` and
        ``shard``, the chunk files of an interrupted run to continue and a process's share ``(index, count)`` of
        the chunks (then ``None`` is returned), as `jaxsleigh.files.runner.run_to_file` passes them. Its other
        fields (``segment``, ``devices``, ``cores``, ``audit``) do not apply and must keep their defaults.

    Returns:
      `OptimumResult`; its ``frontier()``, ``time_for_energy(E)`` and ``energy_for_time(T)`` give \(E^*(T)\)
      and its inverse.

    Raises:
      TypeError: a loose ``chunk_size=``, ``progress=``, ``checkpoint_dir=``, ``resume=`` or ``shard=`` (they are
        ``run``'s fields now).
      ValueError: a bad input or option, naming it.
    """
    plant = as_plant(plant)
    starts = _as_starts(starts)
    horizons = as_horizons(horizons)
    eps = float(eps)
    if not (math.isfinite(eps) and eps > 0):
        raise ValueError(f"eps must be a finite number > 0 (the ball's radius), got {eps}")
    opts = (options or OptimumOptions()).check()
    run = study_options("optimum", run=run).run
    chunk_size = OPTIMUM_CHUNK if run.chunk_size is None else run.chunk_size
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, (int, np.integer)) or chunk_size < 1:
        raise ValueError(f"chunk_size must be a whole number >= 1, got {chunk_size!r}")
    check_sizes(starts.shape[0], horizons, opts, chunk_size)
    settings = _settings(plant, eps, opts, horizons)
    S, H, N = starts.shape[0], horizons.size, opts.intervals
    bounds = [(lo, min(lo + chunk_size, S)) for lo in range(0, S, chunk_size)]
    shard = run.shard
    mine = range(len(bounds)) if shard is None else [i for i in range(len(bounds)) if i % shard[1] == shard[0]]
    key = run_key({"settings": settings, "chunk_size": chunk_size}, starts)
    store = ChunkStore(run.checkpoint_dir, key) if run.checkpoint_dir is not None else None
    parts, reused = {}, 0
    try:
        if store is not None:
            store.open(resume=run.resume, manifest={"settings": settings, "chunk_size": chunk_size, "starts": S})
        with Progress(run.progress, desc="optimum") as bar:
            for n, i in enumerate(mine):
                lo, hi = bounds[i]
                fields = _fields(hi - lo, H, N)
                got = (store.load(i, hi - lo, list(fields), lo=lo, starts=starts[lo:hi], codes=tuple(OptimumStatus))
                       if store is not None else None)
                if got is None:
                    rep = lambda f, c, n=n: (bar.update((n + f) / len(mine)), bar.postfix(converged=f"{c:.0%}"))  # noqa: E731
                    got = _solve_starts(starts[lo:hi], horizons, plant, eps, opts, rep)
                    if store is not None:
                        store.save(i, got, lo=lo, starts=starts[lo:hi])
                else:
                    reused += 1
                parts[i] = got
                bar.update((n + 1) / len(mine))
    finally:
        if store is not None:
            store.close()
    if shard is not None:
        return None
    arrays = {k: np.concatenate([parts[i][k] for i in range(len(bounds))]) for k in _fields(0, H, N)}
    arrays.update(status=arrays["status"].astype(np.int32), guess=arrays["guess"].astype(np.int32))
    return OptimumResult(starts=starts, horizons=horizons, eps=eps, **arrays, settings=settings,
                         run_info={"chunks_reused": reused})


def save_optimum(path, res: OptimumResult) -> Path:
    """Write an `OptimumResult` to ``path`` (``.npz`` appended when missing, its folder made; deterministic bytes);
    returns the path. A name that is, or whose ``.npz`` is, not a regular file (a folder, a device, a named pipe) is
    refused (`jaxsleigh.validate.output_file`)."""
    path = output_file(path, suffix=".npz")
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {"starts": res.starts, "horizons": res.horizons, "eps": np.float64(res.eps), "energy": res.energy,
              "frontier": res.frontier(), "u": res.u, "status": res.status, "q_final": res.q_final,
              "p_final": res.p_final, "kkt": res.kkt, "guess": res.guess,
              "settings_json": np.array(json.dumps(res.settings, sort_keys=True)), "kind": np.array("optimum")}
    return write_npz_deterministic(path, arrays)


def _check_values(p, d: dict) -> None:
    """The values of an optimum file: ``status`` known `OptimumStatus` codes, ``horizons`` finite, > 0 and strictly
    increasing (as `optimum` and the command line require them), ``eps`` finite and > 0; else a `DamagedFileError`
    naming the file and the field."""
    fix = "the file is damaged or was not written by jaxsleigh: write it again (jaxsleigh optimum --out)"
    why = value_problem({"status": d["status"]}, tuple(OptimumStatus))
    if why:
        raise damaged(p, why, fix)
    h = d["horizons"]
    if not (np.all(np.isfinite(h)) and np.all(h > 0) and np.all(np.diff(h) > 0)):
        raise damaged(p, f"field horizons must be finite, > 0 and strictly increasing, got {h.tolist()}", fix)
    if not (np.isfinite(d["eps"]) and d["eps"] > 0):
        raise damaged(p, f"field eps must be finite and > 0, got {d['eps'].tolist()}", fix)


def load_optimum(path) -> OptimumResult:
    """Read a file written by `save_optimum` (or ``jaxsleigh optimum``); a ``ValueError`` naming the file when it
    cannot be read or is another kind of result, a `jaxsleigh.errors.DamagedFileError` (a ``ValueError``) naming it and
    the field when what it holds is not what `save_optimum` writes: the checks of `jaxsleigh.files.npz.read_npz` (the
    kinds and shapes of `jaxsleigh.files.npz.FIELDS` ``["optimum"]``, the content digest) and the values
    (`_check_values`)."""
    d = read_npz(path, "optimum file (written by jaxsleigh optimum / save_optimum)",
                 ("starts", "horizons", "eps", "energy", "u", "status", "q_final", "p_final", "kkt", "guess",
                  "settings_json"), kind="optimum", check=_check_values)
    return OptimumResult(starts=d["starts"], horizons=d["horizons"], eps=float(d["eps"]), energy=d["energy"],
                         u=d["u"], status=d["status"], q_final=d["q_final"], p_final=d["p_final"], kkt=d["kkt"],
                         guess=d["guess"], settings=json.loads(str(d["settings_json"])))
