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
  integration did not reach the horizon, and ``failed_statuses`` how many of them ended with each status, by name;
* ``per_start``: ``{"T_eps": [...], "energy": [...]}``, each start's \(T_\varepsilon\) (``inf``: did not settle
  or failed) and energy (``nan``: failed), in the order of the starts (what the ECDF figure draws,
  `jaxsleigh.plots.compare.plot_compare_ecdf`). `json_ready` writes ``inf`` and ``nan`` as ``null``.

**Equal effort.** `compare` takes the laws as they are given; `jaxsleigh.tuning.tune_to_budget` tunes the
literature's laws to one energy budget first, so that they are compared at equal effort.

Actuators: ``saturation`` clips each component, \(|u_i| \le U\) (`jaxsleigh.controllers.actuators.Saturation`);
``sampler`` runs the sampled-data loop (zero-order hold, delay, noise:
`jaxsleigh.integrate.sampled.solve_sampled`) instead of the continuous one. Under either, the paper's law is
evaluated from the measured q and v (`jaxsleigh.controllers.paper.PaperLaw`), as a digital controller would.
"""
from __future__ import annotations

import math
from typing import Any, Mapping, Optional

import numpy as np

from ..controllers.actuators import sampled, saturate
from ..status import Status, converged
from .ensemble import run_ensemble
from .options import RunOptions
from ..integrate.engine import MAX_BASE_STEPS

__all__ = ["START_DISTRIBUTIONS", "draw_compare_starts", "compare", "METRICS", "BASE_STEP", "SUBSTEPS", "base_step",
           "check_horizon", "json_ready"]

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
    E = np.where(ran, np.asarray(energy, np.float64), np.nan)   # a failed start's energy is not defined
    return {"median_T": _pct(T, 50), "p90_T": _pct(T, 90), "settled": float(np.mean(ok)),
            "energy_p50": _pct(E, 50), "energy_p75": _pct(E, 75), "energy_p90": _pct(E, 90),
            "u_peak_p50": _pct(np.where(ran, u_peak, np.nan), 50),
            "u_peak_max": float(np.nanmax(np.where(ran, u_peak, np.nan))) if ran.any() else float("nan"),
            "min_abs_theta": float(np.nanmin(min_theta)) if np.isfinite(min_theta).any() else float("nan"),
            "failed": int(np.sum(~ran)),
            # how many ended with each status other than OK, by name ({"nonfinite": 16}): what failed them
            "failed_statuses": {Status(int(c)).name.lower(): int(k)
                                for c, k in zip(*np.unique(status[~ran], return_counts=True))},
            "per_start": {"T_eps": [float(t) if k else math.inf for t, k in zip(T, ok)],
                          "energy": [float(e) for e in E]}}


#: The base step [s] of `compare`'s continuous loop (the adaptive method starts with it and grows it).
BASE_STEP = 0.01

#: ``substeps`` of `compare`'s sampled-data loop: its first step is a period / SUBSTEPS (the adaptive RK4 then
#: chooses its steps to the tolerances; fixed RK4 steps per period with ``method="rk4"``).
SUBSTEPS = 20


def base_step(sampler=None, substeps: int = SUBSTEPS) -> float:
    """The base step [s] `compare` integrates with: `BASE_STEP`, or under ``sampler`` the RK4 substep
    ``period / substeps``."""
    return BASE_STEP if sampler is None else sampler.period / substeps


def check_horizon(t_final: float, sampler=None, substeps: int = SUBSTEPS, *, flag: str = "t_final") -> float:
    r"""The base step of `compare` (`base_step`) after checking that the horizon fits one run:
    \(T / \Delta t \le\) `jaxsleigh.integrate.engine.MAX_BASE_STEPS`. Raises ``ValueError`` naming ``flag``
    (the caller's name for the horizon) and the longest horizon allowed."""
    dt = base_step(sampler, substeps)
    longest = MAX_BASE_STEPS * dt
    if not float(t_final) <= longest * (1 + 1e-12):
        where = (f"with the sample period {sampler.period:g} s and {substeps} RK4 substeps per period" if sampler
                 else f"from a base step of {dt:g} s")
        raise ValueError(f"{flag} {float(t_final):g} s is longer than one comparison can integrate: at most "
                         f"{longest:g} s ({MAX_BASE_STEPS:.0e} steps {where}); use a shorter {flag}")
    return dt


def compare(laws: Mapping[str, Any], starts: Mapping[str, np.ndarray], *, plant=None, t_final: float = 100.0,
            eps: float = 0.05, saturation: Optional[float] = None, sampler=None, x64: bool = False,
            substeps: int = SUBSTEPS, stepsize=None, audit=None) -> list:
    """One row per (law, start set): ``{"controller", "starts", "n", **METRICS, "per_start"}`` (module docstring).

    Args:
      laws: name -> law (`jaxsleigh.Gains` for the paper's law, or any ``u = law(q, v)``).
      starts: name -> ``(N, 3)`` or ``(N, 5)`` starts (e.g. `draw_compare_starts`).
      plant: the simulated plant (default the paper's; its leaves may vary per start, a trailing axis of N,
        for unknown plants); the literature's laws carry their own, fixed, model of it.
      saturation: ``U`` to clip each component of ``u`` to ``[-U, U]``; sampler: a
        `jaxsleigh.controllers.actuators.Sampler` for the sampled-data loop (``t_final`` a whole number of
        periods; the plant integrated to the tolerances between the samples).
      stepsize: a `jaxsleigh.StepSizeController` for every run (``None``: the defaults). Effort spent after settling
        by the paper's law under small k needs ``atol=1e-8`` in float32 (docs/evidence/settled-phase.md).
      audit: the accuracy audit of every run, as in `jaxsleigh.run_ensemble` (its record is the row's ``audit``).
    """
    dt = check_horizon(t_final, sampler, substeps)
    rows = []
    for name, law in laws.items():
        law = law if saturation is None else saturate(law, saturation)
        if sampler is not None:                    # the sampled-data loop: substeps of period / substeps
            law = sampled(law, *sampler)
        for sname, ics in starts.items():
            ics = np.asarray(ics, np.float64)
            r = run_ensemble(ics, plant=plant, controller=law, t_final=t_final, dt=dt, eps=eps, x64=x64,
                             stepsize=stepsize, run=RunOptions(progress=False, audit=audit))
            row = _row(r.T_eps, r.status, r.u_energy, r.u_norm_peak, r.min_abs_theta)
            rows.append({"controller": name, "starts": sname, "n": int(ics.shape[0]), **row,
                         "audit": r.run_info.get("audit")})
    return rows


def json_ready(obj):
    """``obj`` with what strict JSON cannot hold replaced: ``inf`` and ``nan`` (did not settle, not defined)
    become ``None`` (``null``), NumPy scalars and arrays become numbers and lists, tuples lists. Write it with
    ``json.dumps(..., allow_nan=False)``."""
    if isinstance(obj, dict):
        return {str(k): json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_ready(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    return obj
