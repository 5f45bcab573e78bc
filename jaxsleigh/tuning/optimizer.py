r"""The optimiser loop: optax Adam (clipped, warm-up + cosine) with backtracking on invalid candidates,
safety probes, checkpoint/resume and the final check with the accurate engine (see the package
docstring for what makes a candidate valid).

Backtracking is an optax-style wrapper (`backtracking`): its ``update`` takes ``valid=`` as an
extra argument; a valid candidate becomes the new anchor (and the step grows back by ``grow`` up to 1),
an invalid one is replaced by the anchor's step shrunk by ``shrink``. The wrapper's state is a pytree
of arrays, so the whole optimiser can be ``vmap``'ed (one lane per effort budget, see
`jaxsleigh.tuning.pareto`).
"""
from __future__ import annotations

import functools
import math
import time
from typing import Any, Callable, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np
import optax

from ..model.params import Gains, PlantParams, gains_to_dict, load_gains
from ..progress import Progress
from .checkpoint import Checkpoint, TunerCheckpoint, TuningInterrupted, check_resume, tune_settings
from .gradients import GRADIENT_MODES, make_value_and_grad
from .loops import descend
from .objective import LossConfig, loss_record, make_training_set, traced_loss, training_max_step
from .params import D_FLOOR, GainParams, gains_from_params, gains_numpy, merge_params, parse_tune, params_from_gains, \
    split_params
from .probes import check, hardest, probe
from .starts import PlantDistribution, UniformStarts, draw_starts, guard_starts, plant_groups
from ..validate import check_count, check_memory

__all__ = ["CandidateTrack", "TuneConfig", "TuneHistory", "TuneResult", "BacktrackState", "backtracking",
           "make_optimizer", "tune"]


class TuneConfig(NamedTuple):
    """Settings of `tune` that are not the objective's (see `LossConfig` for those).

    Attributes:
      steps: optimiser iterations (each evaluates one candidate).
      batch: training starts; seed: their seed (and the plants' in robust tuning).
      lr: peak learning rate of Adam in the unconstrained coordinates (log-gains).
      clip: global-norm gradient clipping.
      warmup: iterations of linear warm-up; the rate then decays by cosine to ``lr * final_lr``.
      n_attempts: budget of attempted steps per lane (the scan's length).
      segment: attempts per checkpointed segment.
      mode: ``"forward"`` (default, faster for the <= 7 gain parameters) or ``"reverse"`` gradients.
      max_rejections: stop after this many invalid candidates in a row, or once backtracking has
        shrunk the step below ``min_scale`` of the schedule's (the best valid point is then on the
        boundary of the valid set: typically the probe's step budget).
      probe: training starts probed per candidate (those that needed the most steps at the last
        refresh; 0: no probe).
      probe_budget: attempted steps per probe start over ``probe_t_final`` (the engine's default
        budget for 100 s is ~2e5).
      probe_refresh: every this many accepted candidates (and at the first) the whole training
        batch is probed and the probe set re-chosen.
      verify: after the loop, check up to this many of the best valid candidates (best first) with
        the accurate engine (`run_ensemble`, default budget) on all
        training and guard starts over ``probe_t_final``, and return the first whose trajectories
        all end with status OK (0: skip).
    """

    steps: int = 150
    batch: int = 256
    seed: int = 0
    lr: float = 0.05
    clip: float = 1.0
    warmup: int = 5
    final_lr: float = 0.1
    n_attempts: int = 4000
    segment: int = 100
    mode: str = "forward"
    max_rejections: int = 12
    min_scale: float = 1e-3
    probe: int = 16
    probe_budget: int = 100000
    probe_refresh: int = 25
    verify: int = 5


class TuneHistory(NamedTuple):
    """One row per iteration (NumPy arrays).

    Attributes:
      loss, grad_norm: objective and global norm of its gradient at the candidate.
      L (n, 3), k (n,), D_hat (n, 2, 2): the candidate's gains.
      valid: candidate accepted; best: running best valid loss.
      median_soft: median soft convergence time S of the batch [s];
      median_passage: median first-passage time into the stopping ball (inf: not reached) [s].
      max_attempts: largest number of attempts of a training or guard lane (training integrator);
      probe_attempts: largest number of attempted steps of a probed start over the validation
        horizon (accurate engine; nan: not probed); lr_scale: backtracking factor; wall: [s].
      soft_loss: the objective's time part f (``loss`` is f plus the augmented-Lagrangian terms);
      energy: geometric-mean control energy of the batch (training integration) [N^2 s];
      constraint: g = log(energy / energy_budget) (<= 0: within the budget; -inf without one);
      multiplier: the augmented Lagrangian's lambda at the candidate; feasible: valid and g <= 0;
      probe_active: the integration-cost probe rejected this candidate (the step budget, not the
        objective, would have shaped the answer there).
    """

    loss: np.ndarray
    grad_norm: np.ndarray
    L: np.ndarray
    k: np.ndarray
    D_hat: np.ndarray
    valid: np.ndarray
    best: np.ndarray
    median_soft: np.ndarray
    median_passage: np.ndarray
    max_attempts: np.ndarray
    probe_attempts: np.ndarray
    lr_scale: np.ndarray
    wall: np.ndarray
    soft_loss: np.ndarray
    energy: np.ndarray
    constraint: np.ndarray
    multiplier: np.ndarray
    feasible: np.ndarray
    probe_active: np.ndarray


class TuneResult(NamedTuple):
    """What `tune` returns.

    Attributes:
      gains: the best valid gains found that passed the final check (validated
        `Gains`; frozen gains are the initial ones, bit for bit).
      initial: the starting gains.
      best_loss, initial_loss: objective at ``gains`` and at ``initial``.
      best_iteration: iteration at which ``gains`` was evaluated (``settings["verified_iteration"]``).
      history: `TuneHistory`.
      settings: everything that produced the result (JSON-ready).
    """

    gains: Gains
    initial: Gains
    best_loss: float
    initial_loss: float
    best_iteration: int
    history: TuneHistory
    settings: dict


#: ranks an infeasible candidate (over the effort budget) after every feasible one
_INFEASIBLE = 1e6


class BacktrackState(NamedTuple):
    """State of `backtracking`: the inner state that produced the current parameters, the anchor
    (last valid parameters, the inner state there and their gradient) and the step scale."""

    inner: Any
    last_params: Any
    last_inner: Any
    last_grad: Any
    scale: jax.Array


def backtracking(inner: optax.GradientTransformation, *, grow: float = 1.25, shrink: float = 0.5,
                 max_scale: float = 1.0) -> optax.GradientTransformationExtraArgs:
    """Wrap ``inner`` so that an invalid candidate is never stepped from.

    ``update(grads, state, params, valid=...)``: if ``valid``, ``params`` (with ``grads`` and the inner
    state that produced them) become the anchor and the scale grows by ``grow`` (at most ``max_scale``);
    otherwise the scale shrinks by ``shrink``. Either way the returned updates move ``params`` to
    ``anchor + scale * inner_step(anchor)`` (so a rejected candidate is replaced by a shorter step from the
    last valid point). Pure and traceable: ``valid`` may be a traced boolean, and the wrapper vmaps.
    """

    def init_fn(params):
        st = inner.init(params)
        leaf = jax.tree_util.tree_leaves(params)[0]
        return BacktrackState(st, params, st, jax.tree_util.tree_map(jnp.zeros_like, params),
                              jnp.ones((), jnp.asarray(leaf).dtype))

    def update_fn(updates, state, params=None, *, valid=True, **extra):
        del extra
        valid = jnp.asarray(valid)

        def pick(a, b):
            return jax.tree_util.tree_map(lambda x, y: jnp.where(valid, x, y), a, b)

        anchor = pick(params, state.last_params)
        anchor_inner = pick(state.inner, state.last_inner)
        anchor_grad = pick(updates, state.last_grad)
        scale = jnp.where(valid, jnp.minimum(max_scale, grow * state.scale), shrink * state.scale)
        scale = scale.astype(state.scale.dtype)
        step, inner_new = inner.update(anchor_grad, anchor_inner, anchor)
        new = jax.tree_util.tree_map(lambda p, s: p + scale * s, anchor, step)
        out = jax.tree_util.tree_map(lambda n, p: n - p, new, params)
        return out, BacktrackState(inner_new, anchor, anchor_inner, anchor_grad, scale)

    return optax.GradientTransformationExtraArgs(init_fn, update_fn)


def make_optimizer(lr: float, steps: int, *, clip: float = 1.0, warmup: int = 5, final_lr: float = 0.1):
    """Adam with global-norm clipping and a warm-up + cosine-decay schedule, wrapped in `backtracking`."""
    schedule = optax.warmup_cosine_decay_schedule(init_value=0.1 * lr, peak_value=lr,
                                                  warmup_steps=max(1, min(warmup, steps - 1)),
                                                  decay_steps=max(2, steps), end_value=final_lr * lr)
    return backtracking(optax.chain(optax.clip_by_global_norm(clip), optax.adam(schedule)))


def optimizer_step(opt, trainable, opt_state, grad, valid):
    """One step of the optimiser ``opt`` (`make_optimizer`): ``(trainable, opt_state)`` after ``grad``; with
    ``valid`` False the backtracking wrapper redoes the last valid step, half as long."""
    updates, opt_state = opt.update(grad, opt_state, trainable, valid=valid)
    return optax.apply_updates(trainable, updates), opt_state


@functools.lru_cache(maxsize=16)
def _optimizer_and_step(lr: float, steps: int, clip: float, warmup: int, final_lr: float):
    """One optimiser and its jitted step per setting. The optimiser is the step's static argument: a new
    one per call of `tune` (each point of a Pareto front) compiled and kept a new executable each time,
    so memory grew with every point."""
    return (make_optimizer(lr, steps, clip=clip, warmup=warmup, final_lr=final_lr),
            jax.jit(optimizer_step, static_argnums=0))


class _Bar:
    """The tuner's progress: the library's `Progress` counting iterations,
    with the loss in its postfix (``enabled=None``: on a terminal)."""

    def __init__(self, enabled, total):
        self._total = max(1, int(total))
        self._bar = Progress(enabled, desc="tune")

    def skip(self, n):
        """Count ``n`` iterations done by an earlier (resumed) run."""
        if n:
            self._bar.update(n / self._total)

    def update(self, it, row):
        self._bar.postfix(loss=f"{row['loss']:.4f}", best=f"{row['best']:.4f}", ok="yes" if row["valid"] else "no")
        self._bar.update((it + 1) / self._total)

    def __enter__(self):
        self._bar.__enter__()
        return self

    def __exit__(self, *exc):
        return self._bar.__exit__(*exc)


def _validate_number(name, v, *, integer=False, positive=True):
    try:
        x = int(v) if integer else float(v)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {v!r}") from None
    if integer and x != v:
        raise ValueError(f"{name} must be a whole number, got {v!r}")
    if not math.isfinite(x) or (positive and x <= 0):
        raise ValueError(f"{name} must be a finite number > 0, got {v!r}")
    return x


class TuneContext(NamedTuple):
    """What the candidate bookkeeping of one tuning run needs to know (fixed for the run)."""

    config: Any
    loss: Any
    ics: Any
    groups: Any
    frozen: Any
    d_floor: float
    g0: Any
    names: tuple
    x64: bool

    def checks(self, guard=None) -> list:
        """The final check's ``(starts, plant)``: the training starts of each plant group, then the ``guard`` starts
        (default `guard_starts`; none if empty) on the first group's plant."""
        guard = guard_starts() if guard is None else np.asarray(guard, dtype=np.float64)
        return ([(self.ics[idx], p0) for idx, _, p0 in self.groups]
                + ([(guard, self.groups[0][2])] if guard.size else []))


class CandidateTrack:
    """The tuner's bookkeeping of one optimisation run, shared by `tune` and the vmapped Pareto front.

    After every gradient evaluation `assess` decides whether the candidate is valid (every lane OK and
    finite, then the integration-cost probe), records its row of the history, keeps the best candidate
    (feasible ones by their soft loss, infeasible ones after them by their violation) and takes the dual
    step of the augmented Lagrangian, \\(\\lambda \\leftarrow \\max(0, \\lambda + \\eta g)\\).
    """

    def __init__(self, lam: float, budgeted: bool):
        self.lam, self.budgeted = float(lam), bool(budgeted)
        self.probes, self.n_accepted, self.rejections = None, 0, 0
        self.best, self.valid_points, self.rows = None, [], []

    def assess(self, it: int, value: float, gnorm: float, valid: bool, trainable, aux, scale: float, ctx: TuneContext,
               wall: float, invalid_start: Callable) -> bool:
        """Record candidate ``it``; returns whether it is valid. ``invalid_start(aux, value, gnorm, probe_attempts)``
        gives the message raised when the very first candidate is not valid."""
        config = ctx.config
        probe_attempts, probed = float("nan"), valid
        if valid and config.probe:
            g = gains_numpy(trainable, ctx.frozen, ctx.d_floor, ctx.g0, ctx.names)
            refresh = self.probes is None or self.n_accepted % max(1, int(config.probe_refresh)) == 0
            sets = [(ctx.ics[idx], p0) for idx, _, p0 in ctx.groups] if refresh else self.probes
            valid, attempts = probe(g, sets, float(ctx.loss.probe_t_final), int(config.probe_budget), ctx.x64)
            probe_attempts = float(max(a.max() for a in attempts))
            if refresh and valid:
                self.probes = hardest(sets, attempts, int(config.probe))
        row = _row(value, gnorm, valid, trainable, ctx.frozen, aux, scale, ctx.d_floor, wall)
        row.update(probe_attempts=probe_attempts, probe_active=bool(probed and config.probe and not valid),
                   multiplier=self.lam, feasible=bool(valid and row["constraint"] <= 0))
        if valid:
            self.rejections = 0
            # feasible candidates rank by f; infeasible ones after them, by their violation
            score = row["soft_loss"] if row["feasible"] else _INFEASIBLE + row["constraint"]
            if self.best is None or score < self.best[0]:
                self.best = (score, it, trainable)
            self.valid_points.append((score, it, trainable))
            self.n_accepted += 1
            if self.budgeted:         # dual step of the augmented Lagrangian
                self.lam = max(0.0, self.lam + float(ctx.loss.dual_step) * row["constraint"])
        else:
            if self.n_accepted == 0:
                raise ValueError(invalid_start(aux, value, gnorm, probe_attempts))
            self.rejections += 1      # backtrack: the optimiser redoes the last valid step, half as long
        row["best"] = self.best[0]
        self.rows.append(row)
        return valid

    def history(self) -> "TuneHistory":
        return TuneHistory(**{f: np.asarray([r[f] for r in self.rows]) for f in TuneHistory._fields})

    def verify(self, ctx: TuneContext, checks, n: int):
        """The best of the ``n`` best valid candidates that passes the accurate engine's check on ``checks``
        (``n = 0``: the best, unchecked). Returns ``(candidate, gains, probe_at_result, why)``; ``candidate``
        is ``None`` when none passed (``why`` says why the last one failed)."""
        why = ""
        for cand in sorted(self.valid_points, key=lambda p: p[0])[:max(1, int(n))]:
            with jax.enable_x64(bool(ctx.x64)):
                g = gains_numpy(cand[2], ctx.frozen, ctx.d_floor, ctx.g0, ctx.names)
            if not n:
                return cand, g, None, ""
            attempts = []
            why = check(g, checks, float(ctx.loss.probe_t_final), ctx.x64, attempts)
            if not why:
                most = int(max(a.max() for a in attempts[:len(ctx.groups)]))
                pa = {"max_attempts_training_starts": most, "probe_budget": int(ctx.config.probe_budget),
                      "active": bool(ctx.config.probe) and most > int(ctx.config.probe_budget)}
                return cand, g, pa, ""
        return None, None, None, why


def tune(gains0="paper", *, starts=UniformStarts(), config: TuneConfig = TuneConfig(),
         loss: LossConfig = LossConfig(), tune=None, plant: Optional[PlantParams] = None,
         robust: Optional[PlantDistribution] = None, guard=None, x64: bool = False,
         d_floor: float = D_FLOOR, progress: Any = None, callback: Optional[Callable] = None,
         checkpoint=None, resume: bool = False, options: Optional[dict] = None) -> TuneResult:
    """Tune the gains by gradient descent on the soft convergence time.

    Args:
      gains0: starting gains (``Gains``, a preset name or a JSON path).
      starts: the distribution of training starts: a sampler ``(rng, n) -> (n, 3|5)`` (default
        `UniformStarts`: ``|x|, |y| <= 3``, ``|theta0|`` in ``(0.3, pi)``) or a fixed array.
      config: `TuneConfig` (iterations, batch, seed, learning rate, budgets, gradient mode).
      loss: `LossConfig` (horizon, tolerances, eps, temperature, penalty weights).
      tune: the gains to tune, a subset of ``"L", "k", "D_hat"`` (``"L,k"``); the rest stay frozen.
      plant: the plant (default: the paper's); robust: a `PlantDistribution` to average the
        objective over sampled plants instead.
      guard: guard starts (default `guard_starts`, ``|theta0|`` in {0.05, 0.1} at the corners).
      x64: compute in float64 (default float32).
      progress: progress bar (``None``: on a terminal); callback: ``callback(i, row_dict)`` per iteration.
      checkpoint: a file (``.npz``) where the optimiser's whole state is written, atomically, after
        every iteration; ``resume=True`` continues from it (the run's settings must be the same:
        they are fingerprinted) and ends with the result an uninterrupted run would have given.
      options: recorded in the checkpoint as they are (the command line's options,
        `jaxsleigh.tuning.checkpoint.checkpoint_options`).

    Returns:
      `TuneResult` whose ``gains`` are the best *valid* candidate (every training and guard
      lane reached its horizon or the ball with status OK, loss and gradient finite, the probed
      starts within ``probe_budget`` steps for 100 s) that also passed the final check with the
      accurate engine on all training and guard starts over ``loss.probe_t_final``.

    Raises:
      ValueError: bad settings, or starting gains that are not a valid candidate (the message
        says which check failed and what to change).
      RuntimeError: no candidate passed the final check.
      TuningInterrupted: Ctrl-C during the loop; its ``partial`` is a `TuneResult` with the
        best valid gains so far (not re-checked with the accurate engine) and the history.
    """
    names, steps, batch = _checked_tune_inputs(tune, config, loss, starts)
    check_resume(checkpoint, resume)
    g0 = load_gains(gains0)
    ics = draw_starts(starts, batch, config.seed)
    t_start = time.perf_counter()
    with jax.enable_x64(bool(x64)):
        run, trainable, opt_state = prepare_run(g0, names, ics, steps, config, loss, plant, robust, guard, x64, d_floor)
        ctx = run.ctx
        track = CandidateTrack(float(loss.multiplier), math.isfinite(float(loss.energy_budget)))
        store = None if checkpoint is None else TunerCheckpoint(checkpoint, Checkpoint.of_run(
            tune_settings(g0, names, config, loss, plant, robust, guard, x64, d_floor, starts), ics, options),
            TuneHistory._fields)
        saved = store.load(trainable, opt_state, ctx.groups, track, steps) if store is not None and resume else None
        it0, trainable, opt_state = (0, trainable, opt_state) if saved is None else saved[:3]
        try:
            _iterate(run, track, trainable, opt_state, it0, steps, store, progress, callback, t_start)
        except KeyboardInterrupt:
            raise TuningInterrupted(_interrupted(track, ctx), None if store is None else store.path) from None
        history = track.history()
    best, best_gains, verified, probe_at_result = _final_check(track, ctx, guard)
    settings = _tune_settings(run, track, robust, starts, t_start, verified, probe_at_result)
    return TuneResult(best_gains, g0, float(best[0]), float(track.rows[0]["loss"]), int(best[1]), history, settings)


def _checked_tune_inputs(tune, config: TuneConfig, loss: LossConfig, starts=None) -> tuple:
    """The gains to tune, the steps and the batch; refuses bad settings (ValueError, in a fixed order), and sizes
    that cannot be run (`check_sizes`)."""
    names = parse_tune(tune)
    steps = _validate_number("steps", config.steps, integer=True)
    batch = _validate_number("batch", config.batch, integer=True)
    _validate_number("lr", config.lr)
    _validate_number("t_final", loss.t_final)
    _validate_number("dt", loss.dt)
    if config.mode not in GRADIENT_MODES:
        raise ValueError(f"mode must be one of {GRADIENT_MODES}, got {config.mode!r}")
    rows = len(starts) if isinstance(starts, np.ndarray) and starts.ndim == 2 else batch
    check_sizes(steps, rows, loss.t_final, training_max_step(loss), config.n_attempts)
    return names, steps, batch


#: Host memory one training start takes in a gradient run: 17 KB measured (``jaxsleigh tune --steps 1``, peak
#: resident memory of 1,000 against 16,000 starts, forward mode, float32), rounded up.
BYTES_PER_TRAINING_START = 20_000
#: The most optimiser steps of one run: the bound of the search's generations (a run continues with ``resume``).
MAX_STEPS = 10_000
#: What `check_sizes` calls each setting: the Python keywords (the command line passes its flags).
SIZE_KEYWORDS = {"steps": "steps", "batch": "batch", "t_final": "t_final", "max_step": "max_step",
                 "n_attempts": "n_attempts"}


def check_sizes(steps: int, batch: int, t_final: float, max_step: float, n_attempts: int, *,
                names: dict | None = None) -> None:
    r"""Refuse, before any work, sizes a gradient run cannot honour (`ValueError` naming what to change; ``names``
    maps `SIZE_KEYWORDS` to the keywords or flags):

    * ``steps`` above `MAX_STEPS` (each step integrates the whole batch);
    * ``batch`` starts of `BYTES_PER_TRAINING_START` bytes more than the host memory (`check_memory`);
    * a horizon the step budget cannot reach, \(\lceil t_{final} / \Delta t_{max} 
ceil > n_{attempts}\): a start
      that has not converged runs out of attempts before ``t_final``, and the loss, the soft time divided by
      ``t_final``, no longer measures the horizon (at ``t_final = 1e9`` it is flat: the starting gains come back).
    """
    w = {**SIZE_KEYWORDS, **(names or {})}
    check_count(w["steps"], int(steps), maximum=MAX_STEPS,
                reason="each step integrates the whole training batch (the search's generations have the same bound)",
                fix=f"use {MAX_STEPS:,} or fewer (the learning rate's schedule spans them all)")
    check_memory(int(batch), w["batch"], bytes_per_start=BYTES_PER_TRAINING_START, unit="training starts",
                 fix=f"use a smaller {w['batch']} (256 is the default)")
    ratio = float(t_final) / float(max_step)
    if not math.isfinite(ratio):                  # a subnormal step: no budget reaches the horizon
        raise ValueError(f"{w['max_step']} {float(max_step):g} s is too small to reach {w['t_final']} "
                         f"{float(t_final):g} s in any number of steps; use a larger one")
    need = math.ceil(ratio - 1e-9)
    if need > int(n_attempts):
        raise ValueError(f"{w['t_final']} {float(t_final):g} s needs at least {need:,} steps of at most "
                         f"{w['max_step']} {float(max_step):g} s, more than the {int(n_attempts):,} attempted steps a "
                         f"start may take ({w['n_attempts']}): a start that has not converged would stop short of the "
                         f"horizon, and the loss (the soft time over {w['t_final']}) would not measure it; use "
                         f"{w['t_final']} {int(n_attempts) * float(max_step):g} or less, or raise {w['n_attempts']} "
                         f"to {need:,}")


class GradientRun(NamedTuple):
    """The fixed parts of one gradient run, built in its precision: the training set, the objective's settings, the
    value-and-gradient function, the optimiser's jitted step ``step(trainable, opt_state, grad, valid)`` and the
    `TuneContext` (the vmapped Pareto front's function and step are vmapped over its budgets)."""

    data: Any
    cfg: LossConfig
    dtype: Any
    vg: Callable
    step: Callable
    ctx: TuneContext

    def descent_step(self, trainable, opt_state, out, valid):
        """The step piece of `descend`: the backtracking optimiser's step with the candidate's gradient (``out[1]``)
        and whether it was valid (per lane in the vmapped front)."""
        return self.step(trainable, opt_state, out[1], np.asarray(valid))    # (jnp.asarray compiles a copy)


def host_norm(tree) -> float:
    """`optax.tree.norm` of a pytree of real arrays, on the host: the same operations in the same order and dtype
    (each leaf's squares summed in order, the leaves' sums added in order, the square root), the same bits, without
    the ten or so programs that compiled, one per operation and shape."""
    leaves = [np.asarray(leaf) for leaf in jax.tree_util.tree_leaves(tree)]
    total = 0
    for a in leaves:
        s = a.dtype.type(0)
        for x in np.square(a).ravel():
            s = s + x
        total = total + s
    return float(np.sqrt(np.asarray(total, np.result_type(*(a.dtype for a in leaves)))))


def prepare_run(g0, names, ics, steps, config: TuneConfig, loss: LossConfig, plant, robust, guard, x64, d_floor,
                lanes: int = 0) -> tuple:
    """Build the run (`GradientRun`, in the current precision) and the starting ``(trainable, opt_state)``. With
    ``lanes`` > 0 (the vmapped Pareto front: one lane per energy budget) the parameters are broadcast over the lanes,
    and the objective (its energy budget and multiplier mapped) and the step are jitted and vmapped."""
    dtype = jnp.result_type(float)             # the working precision, without compiling a zero for it
    data = make_training_set(ics, plant=plant, robust=robust, guard=guard, seed=config.seed + 1, dtype=dtype)
    cfg = traced_loss(loss, dtype)
    # cast on the host (jnp.asarray of float64 NumPy to float32 compiles a conversion per shape)
    theta = GainParams(*(jax.device_put(np.asarray(x, dtype)) for x in params_from_gains(g0, d_floor=d_floor)))
    trainable, frozen = split_params(theta, names)
    vg = make_value_and_grad(mode=config.mode, n_attempts=config.n_attempts, segment=config.segment,
                             d_floor=d_floor)
    ctx = TuneContext(config, loss, ics, plant_groups(ics.shape[0], plant, robust, config.seed + 1), frozen, d_floor,
                      g0, names, x64)
    if not lanes:
        opt, step = _optimizer_and_step(float(config.lr), int(steps), float(config.clip), int(config.warmup),
                                        float(config.final_lr))
        return GradientRun(data, cfg, dtype, vg, functools.partial(step, opt), ctx), trainable, opt.init(trainable)
    trainable = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (lanes,) + jnp.shape(x)), trainable)
    cfg_axes = LossConfig(*([None] * len(LossConfig._fields)))._replace(energy_budget=0, multiplier=0)
    opt = make_optimizer(config.lr, steps, clip=config.clip, warmup=config.warmup, final_lr=config.final_lr)
    stepb = jax.jit(jax.vmap(lambda tr, st, gr, v: optimizer_step(opt, tr, st, gr, v)))
    vgb = jax.jit(jax.vmap(vg, in_axes=(0, None, None, cfg_axes)))
    return GradientRun(data, cfg, dtype, vgb, stepb, ctx), trainable, jax.vmap(opt.init)(trainable)


def _iterate(run: GradientRun, track: CandidateTrack, trainable, opt_state, it0: int, steps: int, store, progress: Any,
             callback: Optional[Callable], t_start: float) -> None:
    """Iterations ``it0`` to ``steps`` (or until backtracking gives up) of `descend`, each checkpointed, reported and
    passed to ``callback``; ``track`` records them."""
    config = run.ctx.config

    def evaluate(it, trainable):
        cfg = run.cfg._replace(multiplier=jnp.asarray(track.lam, run.dtype))       # the multiplier's latest step
        return run.vg(trainable, run.ctx.frozen, run.data, cfg)

    def observe(it, trainable, opt_state, out) -> bool:
        (value, aux), grad = out
        value, gnorm = float(value), host_norm(grad)
        return track.assess(it, value, gnorm, bool(aux["valid"]) and math.isfinite(gnorm), trainable, aux,
                            float(opt_state.scale), run.ctx, time.perf_counter() - t_start,
                            lambda a, v, gn, pa: _invalid_start_message(a, v, gn, pa, config))

    def stop(trainable, opt_state, valid) -> bool:
        """Backtracking gives up: too many invalid candidates in a row, or a step shrunk below ``min_scale``."""
        return track.rejections >= config.max_rejections or float(opt_state.scale) < config.min_scale

    def save(it, trainable, opt_state, stopped) -> None:
        # a run that stopped is saved as finished: its resume does nothing more
        store.save(steps if stopped else it, trainable, opt_state, track)

    with _Bar(progress, steps) as bar:
        bar.skip(it0)

        def report(it, valid) -> None:
            row = track.rows[-1]
            bar.update(it, row)
            if callback is not None:
                callback(it, row)

        descend(evaluate, observe, run.descent_step, trainable, opt_state, steps=steps, start=it0, stop=stop,
                save=None if store is None else save, report=report)


def _interrupted(track: CandidateTrack, ctx: TuneContext) -> Optional[TuneResult]:
    """The `TuneResult` a Ctrl-C carries: the best valid candidate so far, not re-checked (``None``: none yet)."""
    if track.best is None:
        return None
    return TuneResult(gains_numpy(track.best[2], ctx.frozen, ctx.d_floor, ctx.g0, ctx.names), ctx.g0,
                      float(track.best[0]), float(track.rows[0]["loss"]), int(track.best[1]), track.history(),
                      {"interrupted": True, "verified_iteration": None, "iterations_run": len(track.rows),
                       "dtype": "float64" if ctx.x64 else "float32", "tuned": list(ctx.names),
                       "loss": loss_record(ctx.loss),
                       "method": "interrupted; best valid candidate so far, not re-checked"})


def _final_check(track: CandidateTrack, ctx: TuneContext, guard) -> tuple:
    """``(best, best_gains, verified_iteration, probe_at_result)``: the best valid candidate, or with ``config.verify``
    the best that passes the accurate engine on the training and guard starts (RuntimeError if none does)."""
    n = int(ctx.config.verify)
    cand, g, probe_at_result, why = track.verify(ctx, ctx.checks(guard) if n else [], n)
    if cand is None:
        raise RuntimeError(f"none of the {min(len(track.valid_points), n)} best valid candidates passed the check "
                           f"with the accurate engine over {float(ctx.loss.probe_t_final):g} s on the training and "
                           f"guard starts (last: {why}); tune with a smaller learning rate, fewer steps or a smaller "
                           f"probe_budget")
    return cand, g, cand[1] if n else None, probe_at_result


def _tune_settings(run: GradientRun, track: CandidateTrack, robust, starts, t_start: float, verified,
                   probe_at_result) -> dict:
    """Everything that produced the result (`TuneResult.settings`)."""
    ctx = run.ctx
    config, loss, x64 = ctx.config, ctx.loss, ctx.x64
    rows, lam, budgeted = track.rows, track.lam, track.budgeted
    return {
        "method": "gradient descent (optax Adam, clipped, warm-up + cosine, backtracking) on the soft convergence "
                  "time" + (f" subject to a geometric-mean control energy <= {float(loss.energy_budget):.4g} "
                            "(augmented Lagrangian)" if budgeted else "") +
                  ", adaptive RK4 in the w chart, gradients through the integrator",
        "tuned": list(ctx.names), "initial_gains": gains_to_dict(ctx.g0), "config": config._asdict(),
        "loss": loss_record(loss), "x64": bool(x64),
        "dtype": "float64" if x64 else "float32", "robust": None if robust is None else robust._asdict(),
        "starts": repr(starts) if callable(starts) else "fixed array", "n_guard": int(run.data.guard.shape[0]),
        "iterations_run": len(rows), "wall_s": time.perf_counter() - t_start, "d_floor": ctx.d_floor,
        "verified_iteration": verified, "probe_at_result": probe_at_result,
        "energy_budget": float(loss.energy_budget), "final_multiplier": lam,
    }


def _row(value, gnorm, valid, trainable, frozen, aux, scale, d_floor, wall) -> dict:
    g = gains_from_params(merge_params(trainable, frozen), d_floor=d_floor)
    lanes = aux["lanes"]
    att = np.asarray(lanes.n_attempts)
    if aux["guard"] is not None:
        att = np.concatenate([att, np.asarray(aux["guard"].n_attempts)])
    passage = np.where(np.asarray(lanes.stopped), np.asarray(lanes.t_reached, np.float64), np.inf)
    return {"loss": value, "grad_norm": gnorm, "L": np.asarray(g.L, np.float64), "k": float(g.k),
            "probe_attempts": float("nan"),
            "D_hat": np.asarray(g.D_hat, np.float64), "valid": valid,
            "median_soft": float(np.median(np.asarray(lanes.soft_time, np.float64))),
            "median_passage": float(np.median(passage)), "max_attempts": int(att.max()),
            "lr_scale": scale, "wall": wall, "soft_loss": float(aux["soft"]), "energy": float(aux["energy"]),
            "constraint": float(aux["constraint"]), "multiplier": float("nan"), "feasible": False,
            "probe_active": False}


def _invalid_start_message(aux, value, gnorm, probe_attempts, config) -> str:
    lanes, guard = aux["lanes"], aux["guard"]
    n_bad = int(np.sum(~np.asarray(lanes.ok)))
    g_bad = 0 if guard is None else int(np.sum(~np.asarray(guard.ok)))
    if n_bad or g_bad or not (math.isfinite(value) and math.isfinite(gnorm)):
        return (f"the starting gains are not a valid candidate (loss {value}, gradient norm {gnorm}, "
                f"{n_bad} training and {g_bad} guard lanes failed or ran out of their step budget); "
                f"raise n_attempts, shorten t_final or start from other gains")
    return (f"the starting gains fail the integration-cost probe: a training start needs more than "
            f"probe_budget = {config.probe_budget} attempted steps to simulate the validation horizon (it "
            f"stopped after {probe_attempts:.0f} without reaching it); raise probe_budget (the paper's gains need "
            f"about 1,400 per 100 s, the engine's default budget is 200,180) or start from other gains")


