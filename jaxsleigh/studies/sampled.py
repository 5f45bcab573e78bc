r"""The studies' path for a law behind a digital controller (`jaxsleigh.controllers.actuators.Sampled`).

`jaxsleigh.simulate` and `jaxsleigh.run_ensemble` (hence `jaxsleigh.run_basin`) hand a sampled law here: it runs
through `jaxsleigh.integrate.sampled.solve_sampled` (the law once per sample, held; the plant integrated in between
by the library's adaptive RK4 to the run's ``rtol`` and ``atol``, landing on every sample instant, its first step
``period / substeps`` with `substeps_for`; with ``method="rk4"``, ``substeps`` fixed RK4 steps per period) and comes
back in the library's vocabulary (`jaxsleigh.Solution`, `jaxsleigh.EnsembleResult`). What an adaptive run has and a
sampled one has not is NaN: ``Hd`` (the closed loop is no longer port-Hamiltonian).
"""
from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

from ..controllers.actuators import Sampler
from ..integrate.engine import check_ics
from ..integrate.stepsize import StepSizeController
from ..model.controller import PerTrajectory
from ..integrate.sampled import solve_sampled, substeps_for
from ..progress import Progress

__all__ = ["substeps_for", "split_sampled", "sampled_settings", "sampled_solution", "sampled_summaries"]


def plain_sampler(smp) -> Sampler:
    """The sampler's numbers as Python numbers (whole ones as integers): lanes and the tuner hold every leaf as a
    float array."""
    period, delay, noise, seed = (np.asarray(x).reshape(-1)[0].item() for x in smp)
    return Sampler(float(period), int(round(delay)), float(noise), int(round(seed)))


def split_sampled(law):
    """``(held law, Sampler)`` of a sampled law. A sweep's ``PerTrajectory(Sampled(law, sampler))`` gives
    ``PerTrajectory(law)`` and the sampler's numbers, which must be the same on every trajectory (the number of
    samples is part of the compiled loop): ``ValueError`` naming the one that varies."""
    if not isinstance(law, PerTrajectory):
        return law.law, plain_sampler(law.sampler)
    inner = law.law
    for name, x in zip(Sampler._fields, inner.sampler):
        a = np.asarray(x).reshape(-1)
        if not np.all(a == a[0]):
            raise ValueError(f"the sampler's {name} cannot vary per trajectory (a sweep of sampler.{name}): run one "
                             f"sweep per value")
    return PerTrajectory(inner.law), plain_sampler(inner.sampler)


def sampled_settings(cfg) -> dict:
    """The settings of a sampled run: the configuration's, with the method ``"sampled"`` (its steps ``step_method``:
    adaptive to ``rtol`` and ``atol``, or fixed RK4), the sampler, and ``substeps`` (`substeps_for`)."""
    _, smp = split_sampled(cfg.controller)
    s = cfg.settings()
    s.pop("check_passivity", None)               # the held loop has no H_d
    substeps = substeps_for(smp.period, cfg.horizon.dt)
    s.update(method="sampled", step_method=cfg.stepsize.method, sampler=dict(smp._asdict()), substeps=substeps)
    if not cfg.adaptive:                         # fixed RK4: its steps, no tolerances
        for k in ("rtol", "atol", "max_step"):
            s.pop(k, None)
        s["max_steps"] = round(cfg.horizon.t_final / smp.period) * substeps
    return s


def _stepsize(cfg) -> StepSizeController:
    """The step options of a sampled run: the configuration's resolved policy (`jaxsleigh.studies.config.SolveConfig`),
    without a budget for fixed RK4 (its steps per period are ``substeps``)."""
    return cfg.stepsize if cfg.adaptive else cfg.stepsize._replace(max_steps=None)


def _run(cfg, ics5, *, save: bool, args=None):
    plant, law = (cfg.plant, cfg.controller) if args is None else (args.plant, args.controller)
    held, smp = split_sampled(law)
    with jax.enable_x64(cfg.x64):
        r = solve_sampled(held, plant, ics5, t_final=cfg.horizon.t_final, sampler=smp,
                          substeps=substeps_for(smp.period, cfg.horizon.dt), eps=cfg.eps,
                          dtype=jnp.float64 if cfg.x64 else jnp.float32, save=save, stepsize=_stepsize(cfg))
        return jax.tree_util.tree_map(lambda a: None if a is None else np.asarray(a), r)


def sampled_summaries(cfg, ics5, args=None) -> dict:
    """The per-start fields of an `jaxsleigh.EnsembleResult` (``SUMMARY_FIELDS``) for ``ics5`` (N, 5); ``args``: the
    rows' `jaxsleigh.ClosedLoop` when the plant or the law vary per trajectory (a sweep)."""
    r = _run(cfg, ics5, save=False, args=args)
    n = ics5.shape[0]
    nan = np.full(n, np.nan)
    f64 = lambda a: np.asarray(a, np.float64)  # noqa: E731
    return {"q_final": f64(r.q_final), "p_final": f64(r.p_final), "T_eps": f64(r.T_eps),
            "min_abs_theta": f64(r.min_abs_theta), "max_excursion": f64(r.max_excursion), "Hd0": nan, "Hd_final": nan,
            "t_reached": f64(r.t_reached), "n_steps": r.n_steps.astype(np.int64),
            "n_rejected": r.n_rejected.astype(np.int64), "status": r.status.astype(np.int32), "u_peak": f64(r.u_peak),
            "u_norm_peak": f64(r.u_norm_peak), "u_energy": f64(r.u_energy), "u_abs_int": f64(r.u_abs_int)}


def sampled_solution(cfg, ics, progress=None) -> dict:
    """The fields of the `jaxsleigh.Solution` of a sampled law: the state and the held input at every sample
    instant (``save_every`` = 1 sample; the last input is the one held up to the horizon)."""
    ics5, _ = check_ics(ics, cfg.dtype, singular=False)
    t0 = time.perf_counter()
    with Progress(progress, desc="simulate (sampled)") as bar:
        r = _run(cfg, ics5, save=True)
        bar.update(1.0)
    u = np.concatenate([r.u, r.u[:, -1:]], axis=1)
    settings = {**sampled_settings(cfg), "save_every": 1}      # every sample instant
    settings.pop("eps")
    return dict(t=r.t, q=r.q, p=r.p, u=u,
                Hd=np.full(r.q.shape[:2], np.nan), status=r.status.astype(np.int32),
                n_steps=r.n_steps.astype(np.int64), n_rejected=r.n_rejected.astype(np.int64),
                settings=settings, T_eps=r.T_eps, min_abs_theta=r.min_abs_theta, max_excursion=r.max_excursion,
                u_peak=r.u_peak, u_norm_peak=r.u_norm_peak, u_energy=r.u_energy, u_abs_int=r.u_abs_int,
                run_info={"wall_s": time.perf_counter() - t0, "devices": [str(jax.devices()[0])]})
