r"""The time-effort Pareto front: the fastest gains for each control-energy budget.

Each point minimises the soft convergence time subject to "geometric-mean control energy of the
training batch <= budget" (`objective`, augmented Lagrangian) and is then
re-evaluated on held-out starts with the accurate engine (`validate`). Two
ways to compute the front (``method``):

* ``"warm"``: the first point is the budget nearest the starting gains' own training energy
  (``config.steps`` iterations from them); then up the front and down from the first point, each
  started from its neighbour's gains and multiplier with ``warm_steps`` iterations;
* ``"vmap"``: every point from the same start, ``config.steps`` iterations, the whole optimiser
  (parameters, optax state with the backtracking wrapper, multiplier) ``jax.vmap``'ed over the budgets:
  one XLA call evaluates every budget's candidate per iteration.

`random_search` is the derivative-free baseline with the same number of objective evaluations.
``experiments/studies/pareto_front.py`` measures which method is faster (see the how-to for the numbers).
"""
from __future__ import annotations

import functools
import json
import math
import time
from pathlib import Path
from typing import Any, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np
import optax

from ..model.params import Gains, PlantParams, gains as make_gains, gains_to_dict, load_gains
from ..progress import Progress
from .objective import LossConfig, loss_record, make_training_set, objective, traced_loss, training_max_step
from .checkpoint import Checkpoint, TunerCheckpoint, TuningInterrupted, check_resume
from .loops import descend
from .optimizer import CandidateTrack, GradientRun, TuneConfig, TuneHistory, check_sizes, prepare_run, tune
from .params import D_FLOOR, GainParams, gains_from_params, gains_numpy, params_from_gains, parse_tune, \
    split_params
from .starts import UniformStarts, draw_starts
from .validation import Validation, validate, validation_dict
from ..files.npz import atomic_write
from ..studies.config import plant_to_dict
from ..validate import check_count

__all__ = ["FrontPoint", "Front", "training_energy", "default_budgets", "budgets_between", "pareto_front",
           "random_search", "evaluate_front",
           "front_dict", "save_front", "load_front", "point_gains", "finished_points", "FRONT_METHODS",
           "MAX_FRONT_POINTS"]

FRONT_METHODS = ("warm", "vmap")
#: Most points a front accepts: each is a whole tuning run (seconds to minutes), and a front is drawn
#: well by a few dozen; 1000 points took about 50 minutes.
MAX_FRONT_POINTS = 100


class FrontPoint(NamedTuple):
    """One point of the front.

    Attributes:
      budget: the training budget \\(E_{max}\\) on the geometric-mean control energy [N^2 s].
      gains: the point's gains (validated).
      train: figures of the optimisation (soft loss, training energy, iteration, probe at the result).
      evaluation: `Validation` on held-out starts (``None`` until
        `evaluate_front`).
      history: the point's `TuneHistory` (``None`` for random search).
    """

    budget: float
    gains: Gains
    train: dict
    evaluation: Optional[Validation] = None
    history: Optional[TuneHistory] = None


class Front(NamedTuple):
    """A computed front: its points (increasing budget), the method, the optimisation's wall time and
    number of objective evaluations, and the settings."""

    points: list
    method: str
    wall_s: float
    evaluations: int
    settings: dict


def training_energy(gains, *, starts=UniformStarts(), config: TuneConfig = TuneConfig(),
                    loss: LossConfig = LossConfig(), plant: Optional[PlantParams] = None, x64: bool = False,
                    d_floor: float = D_FLOOR) -> dict:
    """The training objective at ``gains`` (one evaluation, no gradient): ``{"energy": geometric-mean
    control energy, "soft_loss": f, "valid": bool}`` on the starts the tuner would train on."""
    ics = draw_starts(starts, config.batch, config.seed)
    with jax.enable_x64(bool(x64)):
        dtype, f = _training_value(ics, config, loss, plant, d_floor)
        _, aux = f(GainParams(*(jax.device_put(np.asarray(x, dtype))      # cast on the host: no program for it
                                for x in params_from_gains(gains, d_floor=d_floor))))
    return {"energy": float(aux["energy"]), "soft_loss": float(aux["soft"]), "valid": bool(aux["valid"])}


def _training_value(ics, config: TuneConfig, loss: LossConfig, plant, d_floor: float) -> tuple:
    """``(dtype, f)`` in the current precision: ``f(theta) -> (value, aux)``, the training objective without a
    budget on the starts ``ics`` at the `GainParams` ``theta`` (one evaluation, no gradient)."""
    dtype = jnp.result_type(float)             # the working precision, without compiling a zero for it
    data = make_training_set(ics, plant=plant, seed=config.seed + 1, dtype=dtype)
    cfg = traced_loss(loss._replace(energy_budget=float("inf"), multiplier=0.0), dtype)
    f = _value(config.n_attempts, config.segment, d_floor)
    return dtype, lambda theta: f(*split_params(theta, None), data, cfg)


@functools.lru_cache(maxsize=8)
def _value(n_attempts, segment, d_floor):
    return jax.jit(lambda tr, fr, d, c: objective(tr, fr, d, c, n_attempts=int(n_attempts), segment=int(segment),
                                                  d_floor=float(d_floor)))


def default_budgets(n: int, *, below: float = 4.0, above: float = 2.0, **kw) -> np.ndarray:
    """``n`` budgets from the paper's gains' training energy / ``below`` to ``tuned``'s x ``above``
    (``kw``: as `training_energy`)."""
    lo = training_energy("paper", **kw)["energy"] / below
    hi = training_energy("tuned", **kw)["energy"] * above
    return budgets_between(lo, hi, n)


def budgets_between(lo: float, hi: float, n: int) -> np.ndarray:
    """``n`` budgets spaced geometrically from ``lo`` to ``hi`` (energies span decades)."""
    if not (0 < lo < hi) or n < 1:
        raise ValueError(f"need 0 < lo < hi and n >= 1, got lo={lo}, hi={hi}, n={n}")
    return np.geomspace(lo, hi, int(n)) if n > 1 else np.array([math.sqrt(lo * hi)])


def pareto_front(budgets, *, method: str = "warm", gains0="paper", starts=UniformStarts(),
                 config: TuneConfig = TuneConfig(), loss: LossConfig = LossConfig(), warm_steps: Optional[int] = None,
                 tune_names=None, plant: Optional[PlantParams] = None, x64: bool = False,
                 d_floor: float = D_FLOOR, progress: Any = None, on_point=None, done: Optional[dict] = None,
                 checkpoint=None, resume: bool = False, options: Optional[dict] = None) -> Front:
    """Tune one set of gains per energy budget (``budgets``, sorted increasing) with ``method``
    (``"warm"`` or ``"vmap"``, module docstring). The same training starts (``starts``,
    ``config.seed``) serve every point. Returns a `Front` whose points are not yet evaluated
    on held-out starts (`evaluate_front`).

    Args:
      on_point: ``"warm"``: called with the `Front` of the points finished so far after each point
        (e.g. to write it, so that nothing finished is lost).
      done: ``"warm"``: ``{budget index: FrontPoint}`` finished by an interrupted run with the same
        settings (`finished_points`); they are kept, not recomputed.
      checkpoint: ``"vmap"``: a file for the whole vmapped optimiser's state (every budget's parameters, optax
        state, multiplier and candidates), written atomically after every iteration in the layout of every
        resumable run (`jaxsleigh.tuning.checkpoint.Checkpoint`); ``resume=True`` continues from it to the front an
        uninterrupted run computes, bit for bit, and refuses one written with other settings (naming them);
        ``options`` (the command's) are recorded in it.

    Raises:
      TuningInterrupted: Ctrl-C; its ``partial`` is the `Front` of the finished points (``"vmap"``: each budget's
        best valid candidate so far, not re-checked; ``None`` if none).
    """
    budgets = _checked_budgets(method, budgets)
    # the vmapped front runs every budget's batch at once
    check_sizes(config.steps, int(config.batch) * (budgets.size if method == "vmap" else 1), loss.t_final,
                training_max_step(loss), config.n_attempts)
    if method != "vmap" and (checkpoint is not None or resume):
        raise ValueError("checkpoint and resume are the vmapped front's; a warm front keeps its finished points "
                         "(on_point) and continues from them (done)")
    check_resume(checkpoint, resume, "front checkpoint", "front")
    t0 = time.perf_counter()
    if method == "warm":
        warm_steps = max(1, config.steps // 2) if warm_steps is None else int(warm_steps)
        check_sizes(warm_steps, config.batch, loss.t_final, training_max_step(loss), config.n_attempts,
                    names={"steps": "warm_steps"})
    settings = front_settings(method, budgets, config, loss, warm_steps, x64, gains0, tune_names, starts)
    if method == "warm":
        points, evals = _front_warm(budgets, t0, warm_steps, on_point, done, settings, gains0=gains0, starts=starts,
                                    config=config, loss=loss, tune_names=tune_names, plant=plant, x64=x64,
                                    d_floor=d_floor, progress=progress)
    else:
        points, evals = _front_vmap(budgets, gains0, starts, config, loss, tune_names, plant, x64, d_floor, progress,
                                    checkpoint, resume, settings, options)
    return Front(points, method, time.perf_counter() - t0, evals, settings)


def _checked_budgets(method, budgets) -> np.ndarray:
    """``budgets`` sorted increasing as float64, after checking ``method``, their values and their number."""
    if method not in FRONT_METHODS:
        raise ValueError(f"method must be one of {FRONT_METHODS}, got {method!r}")
    budgets = np.sort(np.asarray(budgets, np.float64).ravel())
    if budgets.size == 0 or not np.all(np.isfinite(budgets)) or np.any(budgets <= 0):
        raise ValueError(f"budgets must be finite and > 0, got {budgets.tolist()}")
    check_count("pareto_front: the number of budgets", budgets.size, maximum=MAX_FRONT_POINTS,
                reason="every point is a whole tuning run (seconds to minutes each)",
                fix="compute fewer points, or several fronts over narrower budget ranges")
    return budgets


def _front_warm(budgets, t0, warm_steps, on_point, done, settings, *, gains0, starts, config, loss, tune_names, plant,
                x64, d_floor, progress):
    """``(points, evaluations)`` of the ``"warm"`` chain (`pareto_front`); ``t0``: the front's start time, ``settings``
    its `front_settings`."""
    # the chain starts at the budget nearest the starting gains' own energy (gains0 is feasible
    # there, nothing to undo), goes up the front, then down from its first point
    e0 = training_energy(gains0, starts=starts, config=config, loss=loss, plant=plant, x64=x64,
                         d_floor=d_floor)["energy"]
    j0 = int(np.argmin(np.abs(np.log(budgets) - math.log(e0))))
    order = list(range(j0, budgets.size)) + list(range(j0 - 1, -1, -1))
    found = dict(done or {})
    evals = 1 + sum(int(p.train.get("iterations_run", 0)) for p in found.values())

    def so_far():
        return Front([found[j] for j in sorted(found)], "warm", time.perf_counter() - t0, evals, settings)

    try:
        for j in order:
            if j in found:                     # finished by the interrupted run this one resumes
                continue
            # from the neighbouring point (its gains and multiplier, warm_steps iterations), or from gains0 with
            # config.steps iterations when there is none
            src = found.get(j - 1 if j > j0 else j + 1)
            g, lam = (gains0, float(loss.multiplier)) if src is None else (src.gains, src.train["final_multiplier"])
            res = tune(g, starts=starts, config=config if src is None else config._replace(steps=warm_steps, warmup=1),
                       loss=loss._replace(energy_budget=float(budgets[j]), multiplier=lam), tune=tune_names,
                       plant=plant, x64=x64, d_floor=d_floor, progress=progress)
            evals += res.settings["iterations_run"]
            found[j] = _point(budgets[j], res.gains, res.history, res.best_iteration, res.settings)
            if on_point is not None:
                on_point(so_far())
    except KeyboardInterrupt:
        raise TuningInterrupted(so_far() if found else None, None) from None
    return [found[j] for j in range(budgets.size)], evals


def front_settings(method, budgets, config, loss, warm_steps, x64, gains0, tune_names, starts) -> dict:
    """What determines a front (recorded in its file; a resume or a checkpoint must match it)."""
    return {"method": method, "budgets": budgets.tolist(), "config": config._asdict(),
            "loss": {k: v for k, v in loss_record(loss).items() if k != "energy_budget"},
            "warm_steps": warm_steps if method == "warm" else None, "x64": bool(x64),
            "gains0": gains_to_dict(load_gains(gains0)), "tuned": list(parse_tune(tune_names)),
            "starts": repr(starts) if callable(starts) else "fixed array"}


def finished_points(doc: dict, front_settings: dict) -> dict:
    """``{budget index: FrontPoint}`` of an interrupted front's document (`front_dict` with
    ``interrupted``), for ``pareto_front(done=...)``; ``ValueError`` if it was computed with other
    settings than ``front_settings`` (those of the run that would resume it)."""
    same = _as_json(front_settings)
    if doc.get("settings") != same:
        diff = sorted(k for k in set(same) | set(doc.get("settings") or {})
                      if (doc.get("settings") or {}).get(k) != same.get(k))
        raise ValueError(f"the interrupted front was computed with other settings ({', '.join(diff)}); rerun its "
                         f"command with --resume, or delete it to start afresh")
    budgets = same["budgets"]
    out = {}
    for p in doc.get("points", []):
        j = int(np.argmin(np.abs(np.log(budgets) - math.log(p["budget"]))))
        out[j] = FrontPoint(float(budgets[j]), point_gains(p), dict(p["train"]), None, None)
    return out


def _point(budget, gains, history, it, settings) -> FrontPoint:
    train = {"best_iteration": int(it), "soft_loss": float(history.soft_loss[it]),
             "training_energy": float(history.energy[it]), "constraint": float(history.constraint[it]),
             "feasible": bool(history.feasible[it]), "iterations_run": int(len(history.loss)),
             "probe_at_result": settings.get("probe_at_result"),
             "probe_active_iterations": int(np.sum(history.probe_active)),
             "final_multiplier": float(settings.get("final_multiplier", float("nan")))}
    return FrontPoint(float(budget), gains, train, None, history)


def _front_vmap(budgets, gains0, starts, config, loss, tune_names, plant, x64, d_floor, progress, checkpoint=None,
                resume: bool = False, settings: Optional[dict] = None, options: Optional[dict] = None):
    """The whole optimiser vmapped over budgets (same safety contract as `tune`), checkpointed after every iteration
    in ``checkpoint`` (``None``: none; a `TunerCheckpoint` whose fingerprint hashes the training starts, the front's
    ``settings``, the plant and the parameters' floor, with the command's ``options``) and continued from it with
    ``resume``."""
    ics = draw_starts(starts, config.batch, config.seed)
    nb = budgets.size
    t0 = time.perf_counter()
    with jax.enable_x64(bool(x64)):
        base, trainable, opt_state = prepare_run(load_gains(gains0), parse_tune(tune_names), ics, config.steps, config,
                                              loss, plant, None, None, x64, d_floor, lanes=nb)
        tracks = [CandidateTrack(float(loss.multiplier), True) for _ in range(nb)]
        store = None if checkpoint is None else TunerCheckpoint(checkpoint, Checkpoint.of_run(_as_json(
            {**settings, "plant": None if plant is None else plant_to_dict(plant), "d_floor": float(d_floor)}), ics,
            options), TuneHistory._fields, "front checkpoint")
        run = _VmapRun(budgets, tracks, base, np.ones(nb, bool), store)
        it0, evals = 0, 0
        saved = (store.load(trainable, opt_state, base.ctx.groups, tracks, config.steps)
                 if store is not None and resume else None)
        if saved is not None:
            it0, trainable, opt_state, a = saved
            run.alive[:], evals = a["alive"], int(a["evals"])
        try:
            evals = _vmap_iterations(run, it0, evals, trainable, opt_state, progress)
        except KeyboardInterrupt:
            raise TuningInterrupted(_vmap_so_far(run, settings, time.perf_counter() - t0),
                                    None if store is None else store.path) from None
    return _verified_points(budgets, tracks, base.ctx), evals


def _vmap_so_far(run: "_VmapRun", settings: Optional[dict], wall: float) -> Optional["Front"]:
    """The `Front` a Ctrl-C of the vmapped front carries: each budget's best valid candidate so far, not re-checked
    (``None``: no budget has one)."""
    ctx, points = run.base.ctx, []
    for b, track in enumerate(run.tracks):
        if track.best is not None:
            g = gains_numpy(track.best[2], ctx.frozen, ctx.d_floor, ctx.g0, ctx.names)
            points.append(_point(run.budgets[b], g, track.history(), track.best[1], {"probe_at_result": None}))
    done = max((len(t.rows) for t in run.tracks), default=0)
    return Front(points, "vmap", wall, 0, {**(settings or {}), "iterations_run": done}) if points else None


class _VmapRun(NamedTuple):
    """One vmapped front run (`_front_vmap`): the budgets and each one's `CandidateTrack`, the run's fixed parts
    (``base``, `jaxsleigh.tuning.optimizer.GradientRun`: its objective and step vmapped over the budgets), which
    budgets are still alive (updated in place) and the checkpoint."""

    budgets: np.ndarray
    tracks: list
    base: GradientRun
    alive: np.ndarray
    store: Optional[TunerCheckpoint] = None


def _vmap_iterations(run: _VmapRun, it0: int, evals: int, trainable, opt_state, progress) -> int:
    """Run the vmapped optimiser from iteration ``it0`` (``evals`` objective evaluations so far; the budgets'
    parameters and optax state) until ``config.steps`` iterations or every budget's track stops; the tracks record
    each candidate, and the state is checkpointed after every iteration (``run.store``). Returns the number of
    objective evaluations (of budgets still alive). The loop is `descend`; a budget whose backtracking gave up stays
    in the vmapped batch (its candidates are no longer assessed), and the run stops once every budget has."""
    base, alive = run.base, run.alive
    config = base.ctx.config
    t_start = time.perf_counter()

    def evaluate(it, trainable):
        nonlocal evals
        lam = np.array([t.lam for t in run.tracks])
        c = base.cfg._replace(energy_budget=jnp.asarray(run.budgets, base.dtype),
                              multiplier=jnp.asarray(lam, base.dtype))
        out = base.vg(trainable, base.ctx.frozen, base.data, c)          # ((values, aux), grads)
        evals += int(alive.sum())
        return out

    def stop(trainable, opt_state, ok) -> bool:
        """A budget stops where its backtracking gives up; the run, once every budget has."""
        rej = np.array([t.rejections for t in run.tracks])
        alive[:] = alive & (rej < config.max_rejections) & (np.asarray(opt_state.scale) >= config.min_scale)
        return not alive.any()

    def save(it, trainable, opt_state, stopped) -> None:
        run.store.save(it, trainable, opt_state, run.tracks, evals=np.int64(evals), alive=np.asarray(alive))

    with Progress(progress, desc=f"front (vmap x{run.budgets.size})") as bar:
        def report(it, ok) -> None:
            bar.update((it + 1) / config.steps)
            bar.postfix(feasible=int(sum(t.rows[-1]["feasible"] for t in run.tracks if t.rows)))

        def observe(it, trainable, opt_state, out):
            return _assess_candidates(run, it, out, trainable, opt_state, t_start)

        descend(evaluate, observe, base.descent_step, trainable, opt_state, steps=config.steps, start=it0,
                stopped=not alive.any(), stop=stop, save=None if run.store is None else save, report=report)
    return evals


def _assess_candidates(run: _VmapRun, it, out, trainable, opt_state, t_start):
    """``ok`` (per budget) after each alive budget's track has assessed its candidate of iteration ``it``
    (``out``: the budgets' ``((values, aux), grads)`` from ``run.base.vg``); a stopped budget's is ``False``."""
    (values, aux), grads = out
    gn = np.asarray(jax.vmap(optax.tree.norm)(grads))
    ok = np.asarray(aux["valid"]) & np.isfinite(gn)
    scales = np.asarray(opt_state.scale)
    for b, track in enumerate(run.tracks):
        if not run.alive[b]:
            ok[b] = False
            continue
        tr_b = jax.tree_util.tree_map(lambda x: x[b], trainable)
        aux_b = jax.tree_util.tree_map(lambda x: x[b], aux)
        ok[b] = track.assess(it, float(values[b]), float(gn[b]), bool(ok[b]), tr_b, aux_b, float(scales[b]),
                             run.base.ctx, time.perf_counter() - t_start,
                             lambda *_, b=b: f"the starting gains are not a valid candidate for budget "
                                             f"{run.budgets[b]:.4g}")
    return ok


def _verified_points(budgets, tracks, ctx) -> list:
    """Each budget's `FrontPoint`: its best candidate that passes the final check on the training and guard
    starts (``RuntimeError`` if none does)."""
    points, checks = [], ctx.checks()
    for b, track in enumerate(tracks):
        cand, g, pa, _ = track.verify(ctx, checks, int(ctx.config.verify))
        if cand is None:
            raise RuntimeError(f"no candidate for budget {budgets[b]:.4g} passed the final check")
        points.append(_point(budgets[b], g, track.history(), cand[1], {"probe_at_result": pa}))
    return points


def random_search(budgets, n_evals: int, *, starts=UniformStarts(), config: TuneConfig = TuneConfig(),
                  loss: LossConfig = LossConfig(), box=None, seed: int = 0, plant: Optional[PlantParams] = None,
                  x64: bool = False, d_floor: float = D_FLOOR, progress: Any = None) -> Front:
    """The derivative-free baseline: ``n_evals`` gains drawn log-uniformly in ``box`` (default: each
    unconstrained parameter over the span of the paper's and ``tuned``'s, widened by 1 on each side),
    each scored by the same training objective (value only, same starts and integrator); per budget
    the valid candidate with the lowest soft time whose training energy is within it."""
    budgets = np.sort(np.asarray(budgets, np.float64).ravel())
    ics = draw_starts(starts, config.batch, config.seed)
    a = np.concatenate([np.ravel(x) for x in params_from_gains("paper", d_floor=d_floor)])
    b = np.concatenate([np.ravel(x) for x in params_from_gains("tuned", d_floor=d_floor)])
    lo, hi = (np.minimum(a, b) - 1.0, np.maximum(a, b) + 1.0) if box is None else map(np.asarray, box)
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    cands = []
    with jax.enable_x64(bool(x64)):
        dtype, f = _training_value(ics, config, loss, plant, d_floor)
        with Progress(progress, desc="random search") as bar:
            for i in range(int(n_evals)):
                v = rng.uniform(lo, hi)
                _, aux = f(GainParams(jnp.asarray(v[:3], dtype), jnp.asarray(v[3], dtype), jnp.asarray(v[4:], dtype)))
                if bool(aux["valid"]):
                    cands.append((float(aux["soft"]), float(aux["energy"]), v))
                bar.update((i + 1) / n_evals)
    points = []
    for bgt in budgets:
        ok = [c for c in cands if c[1] <= bgt]
        if not ok:
            continue
        soft, energy, v = min(ok, key=lambda c: c[0])
        g = gains_from_params(GainParams(v[:3], v[3], v[4:]), d_floor=d_floor)
        g = make_gains(np.asarray(g.L, np.float64), float(g.k), np.asarray(g.D_hat, np.float64))
        points.append(FrontPoint(float(bgt), g, {"soft_loss": soft, "training_energy": energy, "feasible": True}))
    return Front(points, "random", time.perf_counter() - t0, int(n_evals),
                 {"n_evals": int(n_evals), "valid": len(cands),
                  "box": [np.asarray(lo).tolist(), np.asarray(hi).tolist()],
                  "seed": seed, "budgets": budgets.tolist()})


def evaluate_front(front: Front, ics, *, plant: Optional[PlantParams] = None, x64: bool = False,
                   t_final: float = 100.0, **ensemble_kw) -> Front:
    """Re-evaluate every point on held-out starts ``ics`` with the accurate engine (median T_0.05 and
    its s.e., converged fraction, median energy and peak |u|, mean adaptive steps); ``ensemble_kw``
    go to `validate` (e.g. ``stepsize=StepSizeController(atol=1e-8)``, which resolves the energy spent
    after settling in float32)."""
    pts = [p._replace(evaluation=validate(p.gains, ics, plant=plant, x64=x64, t_final=t_final, **ensemble_kw))
           for p in front.points]
    return front._replace(points=pts)


def front_dict(front: Front, *, references: Optional[dict] = None, **meta) -> dict:
    """The JSON document of a front: per point the gains (the gains-file format: ``L``, ``k``,
    ``D_hat``), the budget, the training figures and the held-out evaluation; ``references``
    (``{name: Validation}``, e.g. paper / tuned) and ``meta`` alongside. Not the wall time, which varies between
    runs: a run that writes a front records it in its sidecar ``FILE.run.json``."""
    def pdict(p: FrontPoint) -> dict:
        d = {**gains_to_dict(p.gains), "budget": p.budget, "train": p.train}
        if p.evaluation is not None:
            d["evaluation"] = validation_dict(p.evaluation)
        return d

    return _as_json(
        {"method": front.method, "evaluations": front.evaluations,
         "settings": front.settings, "points": [pdict(p) for p in front.points],
         "references": {k: validation_dict(v) for k, v in (references or {}).items()}, **meta})


def save_front(front: Front, path, *, references: Optional[dict] = None, **meta) -> Path:
    """Write `front_dict` as JSON (atomically); each point loads with ``jaxsleigh.load_gains``
    after `point_gains`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(front_dict(front, references=references, **meta), indent=2)
    atomic_write(path, lambda fh: fh.write(text.encode()))
    return path


def point_gains(point: dict) -> Gains:
    """The gains of one point of a front document."""
    return make_gains(point["L"], point["k"], point["D_hat"])


def _as_json(doc):
    """``doc`` as its JSON reads it back: NumPy numbers as numbers, arrays as lists, anything else JSON cannot write
    as its ``str``."""
    def default(x):
        if isinstance(x, (np.floating, np.integer)):
            return x.item()
        return x.tolist() if isinstance(x, np.ndarray) else str(x)

    return json.loads(json.dumps(doc, default=default))


def load_front(path) -> dict:
    """Read a ``front.json`` (a dict; each point's gains load with ``jaxsleigh.load_gains(point)``)."""
    return json.loads(Path(path).read_text())
