r"""Tuning any feedback law by gradient: the tuner's objective (`jaxsleigh.tuning.objective`) over the
numeric leaves of a user's law ``u = law(q, v)`` (`jaxsleigh.model.controller`), with optax. The leaves a law
declares ``positive`` are optimised as their logarithm, so they stay positive.

The loss is the tuner's: the batch's mean soft convergence time \(S\) (plus the singular-set term for
a law that has one), subject to a budget on the geometric-mean control energy by an augmented
Lagrangian (`jaxsleigh.tuning.objective.loss_from_lanes`). The other leaves are optimised as they are
(unconstrained). The paper's law
has its own tuner with an admissible parametrisation, checkpoints and checks (`jaxsleigh.tuning.tune`).
"""
from __future__ import annotations

from typing import Any, NamedTuple, Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optax

from ..controllers.actuators import is_sampled
from ..model.charts import chart_for
from ..model.controller import as_controller, is_paper_law, law_leaf_names, positive_names
from ..integrate.engine import check_ics, initial_w
from ..model.params import PlantParams, as_plant
from ..status import Status
from .objective import LaneSummary, LossConfig, loss_from_lanes, soft_convergence, soft_indicator

__all__ = ["LawTuneResult", "tune_law", "law_loss", "gain_names"]


class LawTuneResult(NamedTuple):
    """The best valid law found (every lane OK, finite loss) and the history.

    Attributes:
      law: the tuned law (same type as the starting one).
      loss, energy: its loss and geometric-mean energy on the training starts.
      history: ``{"loss": (steps,), "energy": (steps,), "valid": (steps,)}`` per iteration.
    """

    law: Any
    loss: float
    energy: float
    history: dict


def gain_names(law) -> list:
    """The leaves of ``law`` worth tuning (`jaxsleigh.model.controller.law_leaf_names`): its gains, not the plant
    model it carries (``model.m``, ...), an actuator's bound (``u_max``) nor a sampler's numbers (``sampler.*``)."""
    hardware = ("model", "sampler")
    return [n for n in law_leaf_names(law)
            if not (n.split(".")[0] in hardware or any(f".{h}." in f".{n}" for h in hardware) or "u_max" in n)]


def _split(law, tune):
    leaves, tree = jax.tree_util.tree_flatten(law)
    names = list(law_leaf_names(law))
    chosen = gain_names(law) if tune is None else list(tune)
    bad = [n for n in chosen if n not in names]
    if bad or not chosen:
        raise ValueError(f"tune must name parameters of the law ({', '.join(names)}), got {list(tune or [])}")
    return leaves, tree, names, [names.index(n) for n in chosen]


def sampled_lanes(law, y0, plant: PlantParams, cfg: LossConfig) -> LaneSummary:
    r"""The tuner's lane summaries of a law behind a digital controller (`jaxsleigh.controllers.actuators.Sampled`),
    from the sampled-data loop (`jaxsleigh.integrate.sampled.solve_sampled`, RK4 substeps of at most ``cfg.dt``):
    the soft time \(S = \int_0^T \phi\,dt\) by the trapezoid rule on the sample instants, the control energy exact
    for the held input. A lane that failed counts the whole horizon and energy 1 (values only; the candidate is
    then invalid)."""
    from ..integrate.sampled import solve_sampled
    from ..model.charts import PhysicalChart
    from ..studies.sampled import plain_sampler, substeps_for

    smp = plain_sampler(law.sampler)
    r = solve_sampled(law.law, plant, y0, t_final=float(cfg.t_final), sampler=smp, eps=float(cfg.eps),
                      substeps=substeps_for(smp.period, float(cfg.dt)), dtype=y0.dtype)
    ok = r.status == Status.OK
    q = jnp.where(jnp.isfinite(r.q), r.q, 0.0)                              # (N, K+1, 3); no NaN in the gradient
    y = jnp.moveaxis(jnp.concatenate([q, jnp.zeros(q.shape[:2] + (2,), q.dtype)], axis=-1), -1, 0)
    phi = soft_indicator(y, jnp.asarray(cfg.eps, q.dtype), jnp.asarray(cfg.temperature, q.dtype), PhysicalChart())
    soft = smp.period * (jnp.sum(phi, axis=-1) - 0.5 * (phi[..., 0] + phi[..., -1]))
    T = jnp.asarray(cfg.t_final, q.dtype)
    zero = jnp.zeros_like(soft)
    return LaneSummary(soft_time=jnp.where(ok, soft, T), barrier=zero, ok=ok, stopped=jnp.zeros_like(ok), t=zero + T,
                       status=r.status, n_attempts=jnp.zeros_like(r.status), min_abs_theta=r.min_abs_theta,
                       max_excursion=r.max_excursion, u_energy=jnp.where(ok, r.u_energy, 1.0),
                       u_norm_peak=r.u_norm_peak)


def law_loss(law, y0, plant: PlantParams, cfg: LossConfig, *, n_attempts: int, adaptive: bool = True):
    """``(loss, aux)`` of ``law`` on the chart starts ``y0`` (N, 5): the tuner's objective without guard starts (for a
    sampled law, on the sampled-data loop: `sampled_lanes`)."""
    if is_sampled(law):
        lanes = sampled_lanes(law, y0, plant, cfg)
    else:
        lanes = soft_convergence(law, y0, plant, cfg, n_attempts=n_attempts, adaptive=adaptive)
    return loss_from_lanes(lanes, None, cfg)


def tune_law(law, starts, *, tune: Optional[Sequence[str]] = None, plant: Optional[PlantParams] = None,
             loss: LossConfig = LossConfig(), steps: int = 50, lr: float = 0.05, x64: bool = False,
             n_attempts: Optional[int] = None) -> LawTuneResult:
    """Tune the numeric leaves of ``law`` (all, or those named in ``tune``) by Adam on the tuner's objective.

    Args:
      law: any feedback law ``u = law(q, v)`` (`jaxsleigh.model.controller`).
      starts: training starts ``(N, 3)`` or ``(N, 5)``.
      tune: names of the leaves to tune (`jaxsleigh.model.controller.law_leaf_names`); default `gain_names`: every
        leaf but the plant model the law carries and an actuator's bound.
      plant: the plant (default: the paper's); loss: `LossConfig` (horizon, tolerances, energy budget).
      steps, lr: Adam iterations and learning rate; x64: float64.
      n_attempts: attempted steps per start (default 4x the base steps of ``loss.t_final``).
    """
    if is_paper_law(law):
        raise ValueError("the paper's law has its own tuner with admissible gains: jaxsleigh.tuning.tune")
    law = as_controller(law)
    for name, v, ok in (("steps", steps, isinstance(steps, int) and steps >= 1),
                        ("lr", lr, isinstance(lr, (int, float)) and np.isfinite(lr) and lr > 0)):
        if not ok:
            raise ValueError(f"{name} must be a positive {'whole ' if name == 'steps' else ''}number, got {v!r}")
    chart = chart_for(law)
    ics5, status0 = check_ics(starts, singular=chart.singular, name="training start")
    if np.any(status0 != Status.OK):
        raise ValueError("training starts must all be valid (finite; theta0 != 0 for a law with that singular set)")
    plant = as_plant(plant)
    n_attempts = int(4 * round(loss.t_final / loss.dt) + 8) if n_attempts is None else int(n_attempts)
    with jax.enable_x64(bool(x64)):
        dtype = jnp.zeros(()).dtype
        y0 = initial_w(ics5, status0, dtype, chart)          # the law's chart, mapped in float64
        leaves, tree, names, idx = _split(law, tune)
        positive = positive_names(law)
        logs = [names[i] in positive for i in idx]        # declared positive: optimised as a logarithm
        for i, lg in zip(idx, logs):
            if lg and not np.all(np.asarray(leaves[i], np.float64) > 0):
                raise ValueError(f"{names[i]} must be > 0 to be tuned (the law declares it positive), got {leaves[i]!r}")
        params = [jnp.log(jnp.asarray(leaves[i], dtype)) if lg else jnp.asarray(leaves[i], dtype)
                  for i, lg in zip(idx, logs)]

        def value_of(p, lg):
            return jnp.exp(p) if lg else p

        def rebuild(ps):
            full = [np.asarray(x, dtype) for x in leaves]          # constants (concrete under jit)
            for i, p, lg in zip(idx, ps, logs):
                full[i] = value_of(p, lg)
            return jax.tree_util.tree_unflatten(tree, full)

        def f(ps):
            return law_loss(rebuild(ps), y0, plant, loss, n_attempts=n_attempts)

        step_fn = jax.jit(jax.value_and_grad(f, has_aux=True))
        opt = optax.adam(lr)
        state = opt.init(params)
        best, hist = None, {"loss": [], "energy": [], "valid": []}
        for _ in range(steps):
            (value, aux), grads = step_fn(params)
            valid = bool(aux["valid"]) and all(bool(jnp.all(jnp.isfinite(g))) for g in grads)
            hist["loss"].append(float(value))
            hist["energy"].append(float(aux["energy"]))
            hist["valid"].append(valid)
            if valid and (best is None or float(value) < best[1]):
                best = (params, float(value), float(aux["energy"]))
            if not valid:
                break
            updates, state = opt.update(grads, state, params)
            params = optax.apply_updates(params, updates)
        if best is None:
            raise ValueError("the starting law is not a valid candidate (a training start failed or the loss is not "
                             "finite); check it with jaxsleigh.run_ensemble(starts, controller=law)")
        final = list(leaves)
        for i, p, lg in zip(idx, best[0], logs):
            final[i] = np.asarray(value_of(p, lg), np.float64)
        tuned = jax.tree_util.tree_unflatten(tree, final)
    return LawTuneResult(tuned, best[1], best[2], {k: np.asarray(v) for k, v in hist.items()})
