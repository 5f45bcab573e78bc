"""Validation of gains with the accurate engine (`run_ensemble`), never
with the training discretisation: convergence times and their tables."""
from __future__ import annotations

import math
import warnings
from typing import Any, NamedTuple, Optional

import jax.numpy as jnp
import numpy as np

from ..errors import AccuracyWarning
from ..integrate.horizon import make_horizon, reference_max_steps
from ..integrate.stepsize import StepSizeController
from ..model.params import Gains, PlantParams, load_gains, paper_plant
from ..studies.audit import Audit, for_law, without_cost
from ..status import Status
from ..studies.options import RunOptions, SaveAt
from ..model.coordinates import q_to_w
from ..model.plant import velocity_components
from ..model.w_laws import control_w_components
from ..studies.ensemble import run_ensemble

__all__ = ["Validation", "validate", "markdown_table", "validation_dict", "AUDIT_ROWS"]

#: the starts of a validation that its audit re-runs in float64 (all of them for fewer): a law that misreports
#: systematically (the 0.2 ``balanced`` gains: two thirds of the starts more than 5% off) cannot pass 16 rows, and 16
#: cost a quarter of 64 (each is a float64 run at rtol = atol = 1e-10, the dearest part of a validation)
AUDIT_ROWS = 16


class Validation(NamedTuple):
    r"""Hard convergence times measured by `jaxsleigh.studies.ensemble.run_ensemble`.

    Attributes:
      T_eps: (N,) convergence times (inf: not settled by the horizon; nan: failed).
      median_T, median_se: median ``T_eps`` over all starts (inf if half did not settle) and its
        bootstrap standard error.
      frac_converged, frac_se: fraction settled within the horizon, binomial standard error.
      n, n_failed: starts and starts whose status is not OK; status: (N,) codes.
      mean_steps: accepted adaptive steps per trajectory over the horizon (the cost of simulating).
      max_attempts: most attempted steps of one trajectory (the engine's default budget for 100 s
        is 200180; a trajectory that needs more ends with status BUDGET_EXHAUSTED).
      settings: of the ensemble run.
      u_energy: (N,) control energy \(\int_0^T |u|^2 dt\) [N^2 s]; u_norm_peak: (N,) largest
        \(|u|\) [N]; median_energy, median_peak_u: their medians over the starts that did not
        fail; n_crossed: starts that failed or whose theta changed sign (crossed the singular set).
      audit: the accuracy audit of the run at the given settings (`jaxsleigh.studies.audit`); resolved: it failed,
        so every figure above is of the float64 re-run at rtol = atol = 1e-10 (what the gains really do).
    """

    T_eps: np.ndarray
    median_T: float
    median_se: float
    frac_converged: float
    frac_se: float
    n: int
    n_failed: int
    status: np.ndarray
    mean_steps: float
    max_attempts: int
    settings: dict
    u_energy: Optional[np.ndarray] = None
    u_norm_peak: Optional[np.ndarray] = None
    median_energy: float = float("nan")
    median_peak_u: float = float("nan")
    n_crossed: int = 0
    audit: Optional[dict] = None
    resolved: bool = False


def validate(gains, ics, *, plant: Optional[PlantParams] = None, t_final: float = 100.0, eps: float = 0.05,
             x64: bool = False, n_boot: int = 1000, seed: int = 0, progress: Any = None, **ensemble_kw) -> Validation:
    """Measure ``T_eps`` and the control effort of ``gains`` (the paper's law; or any feedback law, a
    `jaxsleigh.model.controller` object) with the accurate engine
    (`run_ensemble`, adaptive RK4, default tolerances), never with the
    training discretisation. The effort comes from the engine's on-line
    `ControlEffort` quadrature (RK4 order) when it reports one; otherwise
    from a second run saving every base step (trapezoid on the saved samples).
    ``ensemble_kw`` go to `run_ensemble` (e.g. ``stepsize=jaxsleigh.StepSizeController(atol=1e-8)``);
    ``progress`` sets the progress bar of ``run`` (`jaxsleigh.RunOptions`).

    Every validation is audited (`jaxsleigh.studies.audit`: `AUDIT_ROWS` of the starts re-run in float64 at
    rtol = atol = 1e-10; ``audit=`` another `jaxsleigh.Audit`, or ``False``). Where the audit fails, the figures are
    those of the whole set re-run at the audit's reference settings (``resolved``): a tuner judged on them cannot be
    fooled by a settled phase that the defaults do not resolve."""
    law = gains if callable(gains) and not isinstance(gains, (Gains, str)) else None
    g = None if law is not None else load_gains(gains)
    kw = dict(ensemble_kw, **({"gains": g} if law is None else {"controller": law}))
    run = kw.pop("run", None) or RunOptions()
    run = run if progress is None else run._replace(progress=progress)
    audit = kw.pop("audit", Audit(rows=min(AUDIT_ROWS, int(np.shape(ics)[0]))))
    with warnings.catch_warnings():           # a failed audit is acted on here: the gains are measured resolved
        warnings.simplefilter("ignore", AccuracyWarning)
        r = run_ensemble(ics, plant=plant, t_final=t_final, eps=eps, x64=x64, run=run._replace(audit=audit), **kw)
    rec = (r.run_info or {}).get("audit")
    resolved = bool(rec and rec.get("rows") and not rec["passed"])
    if resolved:
        # the settings misreport these gains (an unresolved settled phase flatters them): a tuner must see what
        # they really do, so every figure comes from float64 at the audit's reference tolerances
        budget = reference_max_steps(make_horizon(t_final, kw.get("dt", 0.01)))
        ref = for_law(audit, law) if law is not None else audit   # the tolerance at which float64 resolves the law
        kw["stepsize"] = StepSizeController(rtol=ref.rtol, atol=ref.atol, max_steps=budget)
        r = run_ensemble(ics, plant=plant, t_final=t_final, eps=eps, x64=True, run=run._replace(audit=False), **kw)
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
    ok = r.status == Status.OK
    energy, peak = _effort(r, g, ics, plant, t_final, eps, x64, ensemble_kw)
    th0 = np.asarray(r.ics)[:, 2]
    th1 = np.asarray(r.q_final)[:, 2]
    crossed = ~ok | (np.sign(th1) != np.sign(th0)) | ~(np.asarray(r.min_abs_theta) > 0)
    return Validation(T, med, se, frac, math.sqrt(max(frac * (1 - frac), 0.0) / n), n,
                      int(np.sum(~ok)), r.status, float(np.mean(r.n_steps)),
                      int(np.max(r.n_steps + r.n_rejected)), r.settings, energy, peak,
                      float(np.median(energy[ok])) if ok.any() else float("nan"),
                      float(np.median(peak[ok])) if ok.any() else float("nan"), int(np.sum(crossed)), rec, resolved)


def _effort(r, g, ics, plant, t_final, eps, x64, ensemble_kw) -> tuple[np.ndarray, np.ndarray]:
    """``(energy, peak |u|)`` per start: the engine's observers, else a saved-path quadrature."""
    if getattr(r, "u_energy", None) is not None:
        return np.asarray(r.u_energy, np.float64), np.asarray(r.u_norm_peak, np.float64)
    if g is None:                             # a law's effort is always observed; a run without it reports none
        nan = np.full(np.shape(r.T_eps), np.nan)
        return nan, nan

    p = paper_plant() if plant is None else plant
    kw = {k: v for k, v in ensemble_kw.items() if k not in ("saveat", "run")}
    run = (ensemble_kw.get("run") or RunOptions())._replace(progress=False)
    s = run_ensemble(ics, plant=p, gains=g, t_final=t_final, eps=eps, x64=x64, saveat=SaveAt(every=1), run=run,
                     **kw)
    w = np.asarray(q_to_w(jnp.moveaxis(jnp.asarray(s.q), -1, 0)), np.float64)
    v = velocity_components(np.moveaxis(np.asarray(s.p, np.float64), -1, 0), p)
    u = np.stack([np.asarray(c, np.float64) for c in control_w_components(w, v, g)])
    e = np.sum(u * u, axis=0)
    return np.trapezoid(e, s.t, axis=-1), np.sqrt(e.max(axis=-1))


def markdown_table(rows: dict) -> str:
    """``{name: Validation}`` -> a markdown table: median T_eps, fraction converged, median control
    energy and peak |u|, mean adaptive steps."""
    lines = ["| gains | N | median T_0.05 [s] | converged by horizon | median energy ∫\\|u\\|² dt | "
             "median peak \\|u\\| | mean adaptive steps | status not OK |",
             "|---|---|---|---|---|---|---|---|"]
    for name, v in rows.items():
        lines.append(f"| {name} | {v.n} | {v.median_T:.2f} ± {v.median_se:.2f} | "
                     f"{100 * v.frac_converged:.1f}% ± {100 * v.frac_se:.1f}% | {v.median_energy:.4g} | "
                     f"{v.median_peak_u:.3g} | {v.mean_steps:,.0f} | {v.n_failed} |")
    return "\n".join(lines)


def validation_dict(v: Validation, **extra) -> dict:
    """The figures of a `Validation` as a JSON-ready dict (``extra`` merged in): what a file keeps of them, so its
    audit without what it cost (`jaxsleigh.studies.audit.without_cost`: that varies between runs)."""
    def num(x):
        x = float(x)
        return x if math.isfinite(x) else str(x)

    return {"n": v.n, "median_T_0.05_s": num(v.median_T), "median_se_s": num(v.median_se),
            "frac_converged": v.frac_converged, "frac_se": v.frac_se, "median_energy": num(v.median_energy),
            "median_peak_u": num(v.median_peak_u), "mean_adaptive_steps": v.mean_steps,
            "max_attempts": v.max_attempts, "n_status_not_ok": v.n_failed, "n_crossed_theta0": v.n_crossed,
            "audit": without_cost(v.audit), "resolved_in_float64": v.resolved, **extra}
