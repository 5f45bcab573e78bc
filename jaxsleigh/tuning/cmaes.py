r"""CMA-ES (Hansen's covariance matrix adaptation evolution strategy), ask / tell, in NumPy.

A derivative-free minimiser for a handful of parameters whose objective is not differentiable (the
median of hard convergence times, with constraints). One generation draws \(\lambda\) candidates
\(x_i = m + \sigma B D z_i\), \(z_i \sim N(0, I)\), \(C = B D^2 B^\top\); `tell` moves the mean to
the weighted mean of the best \(\mu = \lambda / 2\) and adapts \(C\) (rank-one and rank-\(\mu\)
updates) and the step size \(\sigma\) (cumulative step-size adaptation), with the default
constants of Hansen, "The CMA Evolution Strategy: A Tutorial" (arXiv:1604.00772, 2016), Table 1.

The state is a NamedTuple of NumPy arrays (saved and restored by the search's checkpoint); the
random numbers come from the caller's ``numpy.random.Generator``, so a run is reproducible from its
seed and resumable from a saved generator state.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

__all__ = ["CMAState", "cma_init", "cma_ask", "cma_tell", "default_population"]


class CMAState(NamedTuple):
    """The strategy's state (float64 NumPy arrays).

    Attributes:
      mean: (n,) \\(m\\). sigma: () step size. cov: (n, n) \\(C\\).
      path_c, path_s: (n,) evolution paths \\(p_c\\), \\(p_\\sigma\\). generation: () completed generations.
    """

    mean: np.ndarray
    sigma: np.ndarray
    cov: np.ndarray
    path_c: np.ndarray
    path_s: np.ndarray
    generation: np.ndarray


def default_population(n: int) -> int:
    """Hansen's default \\(\\lambda = 4 + \\lfloor 3 \\ln n \\rfloor\\)."""
    return 4 + int(3 * math.log(n))


def cma_init(x0, sigma0: float) -> CMAState:
    """Start at ``x0`` with step size ``sigma0`` and \\(C = I\\)."""
    x0 = np.asarray(x0, np.float64).ravel()
    n = x0.size
    if n < 1 or not np.all(np.isfinite(x0)) or not (sigma0 > 0 and math.isfinite(sigma0)):
        raise ValueError(f"CMA-ES needs a finite start and sigma0 > 0, got x0={x0.tolist()}, sigma0={sigma0}")
    return CMAState(x0.copy(), np.float64(sigma0), np.eye(n), np.zeros(n), np.zeros(n), np.int64(0))


def _weights(lam: int):
    mu = lam // 2
    w = math.log(mu + 0.5) - np.log(np.arange(1, mu + 1))
    w = w / w.sum()
    return mu, w, 1.0 / np.sum(w * w)


def _eig(cov):
    d2, B = np.linalg.eigh(0.5 * (cov + cov.T))
    return np.sqrt(np.maximum(d2, 1e-30)), B


def cma_ask(state: CMAState, rng: np.random.Generator, population: int) -> tuple[np.ndarray, np.ndarray]:
    """``(x, y)``: ``population`` candidates (λ, n) and their steps \\(y_i = B D z_i\\) (λ, n),
    \\(x_i = m + \\sigma y_i\\)."""
    d, B = _eig(state.cov)
    z = rng.standard_normal((int(population), state.mean.size))
    y = (z * d) @ B.T
    return state.mean + state.sigma * y, y


def cma_tell(state: CMAState, y: np.ndarray, scores) -> CMAState:
    """The next state from the steps ``y`` of `cma_ask` and their ``scores`` (lower is better;
    ties keep the order of ``y``)."""
    y = np.asarray(y, np.float64)
    lam, n = y.shape
    mu, w, mueff = _weights(lam)
    cc = (4 + mueff / n) / (n + 4 + 2 * mueff / n)
    cs = (mueff + 2) / (n + mueff + 5)
    c1 = 2 / ((n + 1.3) ** 2 + mueff)
    cmu = min(1 - c1, 2 * (mueff - 2 + 1 / mueff) / ((n + 2) ** 2 + mueff))
    damps = 1 + 2 * max(0.0, math.sqrt((mueff - 1) / (n + 1)) - 1) + cs
    chi_n = math.sqrt(n) * (1 - 1 / (4 * n) + 1 / (21 * n * n))
    order = np.argsort(np.asarray(scores, np.float64), kind="stable")
    ysel = y[order[:mu]]
    yw = w @ ysel
    d, B = _eig(state.cov)
    c_inv_sqrt = (B / d) @ B.T
    g = int(state.generation) + 1
    ps = (1 - cs) * state.path_s + math.sqrt(cs * (2 - cs) * mueff) * (c_inv_sqrt @ yw)
    hsig = float(np.linalg.norm(ps) / math.sqrt(1 - (1 - cs) ** (2 * g)) / chi_n < 1.4 + 2 / (n + 1))
    pc = (1 - cc) * state.path_c + hsig * math.sqrt(cc * (2 - cc) * mueff) * yw
    cov = ((1 - c1 - cmu) * state.cov + c1 * (np.outer(pc, pc) + (1 - hsig) * cc * (2 - cc) * state.cov)
           + cmu * (ysel.T * w) @ ysel)
    sigma = state.sigma * math.exp((cs / damps) * (np.linalg.norm(ps) / chi_n - 1))
    return CMAState(state.mean + state.sigma * yw, np.float64(sigma), 0.5 * (cov + cov.T), pc, ps, np.int64(g))
