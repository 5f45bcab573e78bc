r"""Controllers compared on the same plant, the same starts and the same measures.

`compare` runs each law from each distribution of starts and returns one row per (law, distribution)
with the measures a reviewer asks for, judged on the whole distribution and not its median alone
(control energy is bimodal: starts near \(\theta = 0\) and far ones dominate it):

* ``median_T``, ``p90_T``: median and 90th percentile of \(T_\varepsilon\) (``inf`` when more than that share
  did not settle);
* ``settled``: the fraction settled within the horizon (status OK and \(T_\varepsilon\) finite);
* ``energy_p50``, ``energy_p75``, ``energy_p90``: percentiles of \(\int_0^T \|u\|^2 dt\) over the starts
  that ran (not only the settled ones: a law that spends and fails is charged);
* ``u_peak_p50``, ``u_peak_max``: median and largest \(\max_t \|u(t)\|\);
* ``min_abs_theta``: the closest approach to \(\theta = 0\) over all starts; ``failed``: starts whose
  integration did not reach the horizon.

Actuators: ``saturation`` clips each component, \(|u_i| \le U\) (`jaxsleigh.controllers.actuators.Saturation`);
``sampler`` runs the sampled-data loop (zero-order hold, delay, noise:
`jaxsleigh.integrate.sampled.solve_sampled`) instead of the continuous one. Under either, the paper's law is
evaluated from the measured q and v (`jaxsleigh.controllers.paper.PaperLaw`), as a digital controller would.
"""
from __future__ import annotations

from typing import Any, Mapping, Optional

import numpy as np

from ..controllers.actuators import sampled, saturate
from ..status import Status, converged

__all__ = ["START_DISTRIBUTIONS", "draw_compare_starts", "compare", "METRICS"]

#: The held-out start distributions (name -> description): near the singular set, the training box, and
#: a wider box with momentum.
START_DISTRIBUTIONS = {
    "near": "|x|, |y| <= 3, 0.05 <= |theta0| <= 0.3, at rest",
    "uniform": "|x|, |y| <= 3, 0.3 <= |theta0| <= pi, at rest",
    "wide": "|x|, |y| <= 4, 0.2 <= |theta0| <= pi, momentum p1, p2 ~ N(0, 1)",
}

#: The columns of a row, in order.
METRICS = ("median_T", "p90_T", "settled", "energy_p50", "energy_p75", "energy_p90", "u_peak_p50", "u_peak_max",
           "min_abs_theta", "failed")


def draw_compare_starts(name: str, n: int, seed: int) -> np.ndarray:
    """``n`` starts ``(n, 5)`` of the distribution ``name`` (`START_DISTRIBUTIONS`), from ``seed`` (the same
    seed gives the same starts; each distribution draws from its own stream)."""
    if name not in START_DISTRIBUTIONS:
        raise ValueError(f"unknown start distribution {name!r}; choose from {', '.join(START_DISTRIBUTIONS)}")
    rng = np.random.default_rng([int(seed), list(START_DISTRIBUTIONS).index(name)])
    box, lo, hi = {"near": (3.0, 0.05, 0.3), "uniform": (3.0, 0.3, np.pi), "wide": (4.0, 0.2, np.pi)}[name]
    xy = rng.uniform(-box, box, (n, 2))
    th = rng.uniform(lo, hi, n) * rng.choice([-1.0, 1.0], n)
    p = rng.normal(0.0, 1.0, (n, 2)) if name == "wide" else np.zeros((n, 2))
    return np.column_stack([xy, th, p])


def _pct(a, q) -> float:
    """The ``q``-th percentile of the non-NaN values, taken as an order statistic (no interpolation, so that
    ``inf`` entries give ``inf`` when they reach the percentile, never ``inf - inf = nan``)."""
    a = np.asarray(a, np.float64)
    a = a[~np.isnan(a)]
    return float(np.percentile(a, q, method="inverted_cdf")) if a.size else float("nan")


def _row(T_eps, status, energy, u_peak, min_theta) -> dict:
    status = np.asarray(status)
    ran = status == Status.OK
    T = np.where(ran, np.asarray(T_eps, np.float64), np.inf)     # a failed start never settled
    ok = converged(status, np.asarray(T_eps, np.float64))
    return {"median_T": _pct(T, 50), "p90_T": _pct(T, 90), "settled": float(np.mean(ok)),
            "energy_p50": _pct(np.where(ran, energy, np.nan), 50),
            "energy_p75": _pct(np.where(ran, energy, np.nan), 75),
            "energy_p90": _pct(np.where(ran, energy, np.nan), 90),
            "u_peak_p50": _pct(np.where(ran, u_peak, np.nan), 50),
            "u_peak_max": float(np.nanmax(np.where(ran, u_peak, np.nan))) if ran.any() else float("nan"),
            "min_abs_theta": float(np.nanmin(min_theta)) if np.isfinite(min_theta).any() else float("nan"),
            "failed": int(np.sum(~ran))}


def compare(laws: Mapping[str, Any], starts: Mapping[str, np.ndarray], *, plant=None, t_final: float = 100.0,
            eps: float = 0.05, saturation: Optional[float] = None, sampler=None, x64: bool = False,
            substeps: int = 20, stepsize=None) -> list:
    """One row per (law, start set): ``{"controller", "starts", "n", **METRICS}`` (module docstring).

    Args:
      laws: name -> law (`jaxsleigh.Gains` for the paper's law, or any ``u = law(q, v)``).
      starts: name -> ``(N, 3)`` or ``(N, 5)`` starts (e.g. `draw_compare_starts`).
      plant: the simulated plant (default the paper's; its leaves may vary per start, a trailing axis of N,
        for unknown plants); the literature's laws carry their own, fixed, model of it.
      saturation: ``U`` to clip each component of ``u`` to ``[-U, U]``; sampler: a
        `jaxsleigh.controllers.actuators.Sampler` for the sampled-data loop (``t_final`` a whole number of
        periods; ``substeps`` RK4 steps per period).
      stepsize: a `jaxsleigh.StepSizeController` for every run (``None``: the defaults). Effort spent after settling
        by the paper's law under small k needs ``atol=1e-8`` in float32 (docs/evidence/settled-phase.md).
    """
    from .ensemble import run_ensemble

    rows = []
    for name, law in laws.items():
        law = law if saturation is None else saturate(law, saturation)
        dt = 0.01
        if sampler is not None:                    # the sampled-data loop: substeps of period / substeps
            law, dt = sampled(law, *sampler), sampler.period / substeps
        for sname, ics in starts.items():
            ics = np.asarray(ics, np.float64)
            r = run_ensemble(ics, plant=plant, controller=law, t_final=t_final, dt=dt, eps=eps, x64=x64,
                             stepsize=stepsize, progress=False)
            row = _row(r.T_eps, r.status, r.u_energy, r.u_norm_peak, r.min_abs_theta)
            rows.append({"controller": name, "starts": sname, "n": int(ics.shape[0]), **row})
    return rows
