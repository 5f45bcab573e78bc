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

from typing import Any, Callable, NamedTuple, Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optax

from ..controllers.actuators import NormSaturation, Sampled, Saturation, is_sampled
from ..model.charts import chart_for, physical_chart_for
from ..model.controller import as_controller, is_paper_law, law_leaf_names, positive_names
from ..integrate.engine import initial_w
from ..model.params import Gains, PlantParams, as_plant
from ..status import Status
from .checkpoint import LawCheckpoint, Checkpoint, TuningInterrupted, check_resume, law_settings
from .loops import descend, step_if
from .optimizer import check_sizes
from .params import TUNABLE, GainParams, gains_from_params, params_from_gains
from .objective import (LaneSummary, LossConfig, loss_from_lanes, soft_convergence, soft_indicator, training_max_step,
                        valid_starts)
from ..controllers.paper import PaperLaw
from ..integrate.sampled import solve_sampled
from ..studies.sampled import plain_sampler, substeps_for

__all__ = ["LawTuneResult", "tune_law", "law_loss", "gain_names", "LawCoordinates", "law_coordinates",
           "InvalidStartingLaw"]


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


class LawCoordinates(NamedTuple):
    r"""A law's tuned parameters as one flat vector \(x\) in which every value is admissible.

    Attributes:
      x0: (n,) float64, the starting law's coordinates.
      law_of: ``x -> law`` (traceable; the leaves not tuned are the starting law's, unchanged).
      names: (n,) what each coordinate is (``"log gamma"``, ``"kp"``, ``"d_chol[1]"``).
    """

    x0: np.ndarray
    law_of: Callable
    names: tuple


def law_coordinates(law, tune: Optional[Sequence[str]] = None, *, dtype=jnp.float32) -> LawCoordinates:
    r"""The unconstrained coordinates the tuners move in.

    * the paper's law (`jaxsleigh.Gains`): `jaxsleigh.tuning.params.GainParams` flattened, \(x = (\log L,
      \log k, c_0, c_1, c_2)\), 7 numbers, \(\hat D = C C^\top + \delta I\) (``tune`` must be ``None``);
    * the paper's law behind actuators (`jaxsleigh.saturate`, `jaxsleigh.controllers.actuators.sampled`): the same
      coordinates of the gains named in ``tune`` (``law.gains.k``, ...; default all three);
    * any other law: the leaves named in ``tune`` (default `gain_names`), each leaf the law declares ``positive``
      as its logarithm (it stays positive), the others as they are.

    ``law_of(x)`` computes in ``dtype``. Raises ``ValueError`` for a positive leaf that is not > 0."""
    if is_paper_law(law):
        if tune is not None:
            raise ValueError("the paper's gains are tuned as a whole here (7 coordinates); tune=None")
        p = params_from_gains(law)
        x0 = np.concatenate([np.ravel(a) for a in p]).astype(np.float64)

        def gains_of(x):
            x = jnp.asarray(x, dtype)
            return gains_from_params(GainParams(x[0:3], x[3], x[4:7]))

        names = ("log L1", "log L2", "log L3", "log k", "d_chol[0]", "d_chol[1]", "d_chol[2]")
        return LawCoordinates(x0, gains_of, names)
    leaves, tree, names, idx = _split(law, tune)
    prefix = _paper_prefix(law)
    if prefix is not None and all(names[i].startswith(prefix) for i in idx):
        return _wrapped_paper_coordinates(leaves, tree, names, idx, prefix, dtype)
    positive = positive_names(law)
    logs = [names[i] in positive for i in idx]             # declared positive: optimised as a logarithm
    parts, labels = [], []
    for i, lg in zip(idx, logs):
        try:
            v = np.asarray(leaves[i], np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"the law's leaf {names[i]!r} is {leaves[i]!r}, not a number: only numeric leaves (gains) "
                             f"can be tuned") from None
        if lg and not np.all(v > 0):
            raise ValueError(f"{names[i]} must be > 0 to be tuned (the law declares it positive), got {leaves[i]!r}")
        parts.append(np.ravel(np.log(v) if lg else v))
        labels += [("log " if lg else "") + names[i] + (f"[{j}]" if v.ndim else "") for j in range(v.size)]
    shapes = [np.shape(leaves[i]) for i in idx]

    def law_of(x):
        x = jnp.asarray(x, dtype)
        full, o = list(leaves), 0
        for i, shape, lg in zip(idx, shapes, logs):
            n = int(np.prod(shape, dtype=int))
            p = x[o:o + n].reshape(shape)
            full[i], o = (jnp.exp(p) if lg else p), o + n
        return jax.tree_util.tree_unflatten(tree, full)

    return LawCoordinates(np.concatenate(parts), law_of, tuple(labels))


def _paper_prefix(law) -> Optional[str]:
    """The path (``"law.gains."``) of the paper's gains inside actuators (saturation, digital controller) around the
    paper's law; ``None`` for any other law."""
    prefix = ""
    while isinstance(law, (Saturation, NormSaturation, Sampled)):
        law, prefix = law.law, prefix + "law."
    return prefix + "gains." if isinstance(law, PaperLaw) else None


def _wrapped_paper_coordinates(leaves, tree, names, idx, prefix: str, dtype) -> LawCoordinates:
    """The paper's gains behind an actuator in the paper's admissible coordinates (`GainParams`: log L, log k and
    the Cholesky factor of D_hat - floor), so that every candidate has L, k > 0 and D_hat symmetric positive
    definite; only the gains in ``idx`` move."""
    fields = ("L", "k", "D_hat")
    at = {f: names.index(prefix + f) for f in fields}
    p0 = params_from_gains(Gains(*(np.asarray(leaves[at[f]], np.float64) for f in fields)))
    chosen = [f for f in fields if at[f] in idx]
    starts = [np.asarray(getattr(p0, TUNABLE[f])) for f in chosen]

    def law_of(x):
        x = jnp.asarray(x, dtype)
        vals, o = {c: jnp.asarray(np.asarray(v), dtype) for c, v in p0._asdict().items()}, 0
        for f, v in zip(chosen, starts):            # the tuned ones from x, in order
            vals[TUNABLE[f]], o = x[o:o + v.size].reshape(v.shape), o + v.size
        g = gains_from_params(GainParams(**vals))
        full = list(leaves)
        for f in chosen:
            full[at[f]] = getattr(g, f)
        return jax.tree_util.tree_unflatten(tree, full)

    labels = [TUNABLE[f] + (f"[{j}]" if v.ndim else "") for f, v in zip(chosen, starts) for j in range(v.size)]
    return LawCoordinates(np.concatenate([np.ravel(v) for v in starts]), law_of, tuple(labels))


def _host_law(start, law, tune):
    """``law`` with its tuned leaves as float64 NumPy arrays and every other leaf ``start``'s own, bit for bit."""
    leaves, tree, _, idx = _split(start, tune)
    new = jax.tree_util.tree_leaves(law)
    final = list(leaves)
    for i in idx:
        final[i] = np.asarray(new[i], np.float64)
    return jax.tree_util.tree_unflatten(tree, final)


def sampled_lanes(law, y0, plant: PlantParams, cfg: LossConfig) -> LaneSummary:
    r"""The tuner's lane summaries of a law behind a digital controller (`jaxsleigh.controllers.actuators.Sampled`),
    from the sampled-data loop (`jaxsleigh.integrate.sampled.solve_sampled`, the adaptive RK4 at the loss's ``rtol`` and
    ``atol`` between the sample instants):
    the soft time \(S = \int_0^T \phi\,dt\) by the trapezoid rule on the sample instants, the control energy exact
    for the held input. A lane that failed counts the whole horizon and energy 1 (values only; the candidate is
    then invalid)."""
    smp = plain_sampler(law.sampler)
    r = solve_sampled(law.law, plant, y0, t_final=float(cfg.t_final), sampler=smp, eps=float(cfg.eps),
                      substeps=substeps_for(smp.period, float(cfg.dt)), dtype=y0.dtype,
                      stepsize=jax.tree_util.tree_map(float, cfg.stepsize))
    ok = r.status == Status.OK
    q = jnp.where(jnp.isfinite(r.q), r.q, 0.0)                              # (N, K+1, 3); no NaN in the gradient
    y = jnp.moveaxis(jnp.concatenate([q, jnp.zeros(q.shape[:2] + (2,), q.dtype)], axis=-1), -1, 0)
    phi = soft_indicator(y, jnp.asarray(cfg.eps, q.dtype), jnp.asarray(cfg.temperature, q.dtype),
                         physical_chart_for(law.law))
    soft = smp.period * (jnp.sum(phi, axis=-1) - 0.5 * (phi[..., 0] + phi[..., -1]))
    T = jnp.asarray(cfg.t_final, q.dtype)
    zero = jnp.zeros_like(soft)
    return LaneSummary(soft_time=jnp.where(ok, soft, T), barrier=zero, ok=ok, stopped=jnp.zeros_like(ok), t_reached=zero + T,
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


def law_attempts(loss: LossConfig, n_attempts: int | None = None) -> int:
    """The attempted steps each start may take: ``n_attempts``, by default ``4 t_final / dt + 8``."""
    return int(4 * round(loss.t_final / loss.dt) + 8) if n_attempts is None else int(n_attempts)


def tune_law(law, starts, *, tune: Optional[Sequence[str]] = None, plant: Optional[PlantParams] = None,
             loss: LossConfig = LossConfig(), steps: int = 50, lr: float = 0.05, x64: bool = False,
             n_attempts: Optional[int] = None, checkpoint=None, resume: bool = False,
             callback: Optional[Callable] = None, options: Optional[dict] = None) -> LawTuneResult:
    """Tune the numeric leaves of ``law`` (all, or those named in ``tune``) by Adam on the tuner's objective.

    Args:
      law: any feedback law ``u = law(q, v)`` (`jaxsleigh.model.controller`).
      starts: training starts ``(N, 3)`` or ``(N, 5)``.
      tune: names of the leaves to tune (`jaxsleigh.model.controller.law_leaf_names`); default `gain_names`: every
        leaf but the plant model the law carries and an actuator's bound.
      plant: the plant (default: the paper's); loss: `LossConfig` (horizon, tolerances, energy budget).
      steps, lr: Adam iterations and learning rate; x64: float64.
      n_attempts: attempted steps per start (default 4x the base steps of ``loss.t_final``).
      checkpoint: a file (``.npz``) where the descent's whole state is written, atomically, after every step;
        ``resume=True`` continues from it (the settings must be the same, they are fingerprinted; a larger ``steps``
        goes on where the run stopped) and ends with the result an uninterrupted run would have given.
      callback: ``callback(i, row)`` after step ``i`` (``row``: its ``loss``, ``energy``, ``valid``).
      options: recorded in the checkpoint as they are (the command line's options, `checkpoint_options`).

    Raises:
      `InvalidStartingLaw` (a ``ValueError``): the starting law is not a valid candidate.
      `TuningInterrupted`: Ctrl-C during the descent; its ``partial`` is a `LawTuneResult` with the best valid
        law so far (``None`` if there is none yet).
    """
    if is_paper_law(law):
        raise ValueError("the paper's law has its own tuner with admissible gains: jaxsleigh.tuning.tune")
    law = as_controller(law)
    for name, v, ok in (("steps", steps, isinstance(steps, int) and steps >= 1),
                        ("lr", lr, isinstance(lr, (int, float)) and np.isfinite(lr) and lr > 0)):
        if not ok:
            raise ValueError(f"{name} must be a positive {'whole ' if name == 'steps' else ''}number, got {v!r}")
    chart = chart_for(law)
    ics5, status0 = valid_starts(starts, why="finite; theta0 != 0 for a law with that singular set",
                                 singular=chart.singular, name="training start")
    check_resume(checkpoint, resume)
    plant = as_plant(plant)
    n_attempts = law_attempts(loss, n_attempts)
    check_sizes(steps, ics5.shape[0], loss.t_final, training_max_step(loss), n_attempts)
    with jax.enable_x64(bool(x64)):
        dtype = jnp.zeros(()).dtype
        y0 = initial_w(ics5, status0, dtype, chart)          # the law's chart, mapped in float64
        coords = law_coordinates(law, tune, dtype=dtype)
        store = None if checkpoint is None else LawCheckpoint(checkpoint, Checkpoint.of_run(
            law_settings(law, coords.names, plant, loss, lr, x64, n_attempts), ics5, options))

        value_and_grad = _law_value_and_grad(law, tune, coords, dtype, n_attempts, loss)

        def result(best, hist):
            tuned = _host_law(law, coords.law_of(best[0]), tune)
            return LawTuneResult(tuned, best[1], best[2], {k: np.asarray(v) for k, v in hist.items()})

        descent = _Descent(optax.adam(lr), jnp.asarray(coords.x0, dtype), store, callback)
        try:
            _adam_descent(descent, lambda x: value_and_grad(x, y0, plant, loss), steps)
        except KeyboardInterrupt:
            partial = None if descent.best is None else result(descent.best, descent.hist)
            raise TuningInterrupted(partial, None if store is None else store.path) from None
        if descent.best is None:
            raise InvalidStartingLaw("the starting law is not a valid candidate (a training start failed or the loss "
                                     "is not finite); check it with jaxsleigh.run_ensemble(starts, controller=law)")
        return result(descent.best, descent.hist)


#: `_law_value_and_grad`'s jitted functions, by what their programs hold as constants (at most `_KEPT` of them)
_VALUE_AND_GRAD: dict = {}
_KEPT = 16


def _law_value_and_grad(law, tune, coords: LawCoordinates, dtype, n_attempts: int, loss: LossConfig):
    """The jitted ``(x, y0, plant, loss) -> ((loss, aux), grad)`` of `law_loss` in ``coords``, the same function for
    every call whose program would be the same: the law's structure, the leaves it does not tune (constants of
    ``coords.law_of``), ``tune``, the dtype and ``n_attempts``, and for a sampled law the loss settings (its sampler's
    loop takes them as Python numbers). The starts, the plant, the loss (otherwise) and the tuned leaves' values are
    arguments, so a second `tune_law` with other starts, starting gains or tolerances compiles nothing (each call
    compiled its objective again: 12.5 s for Aicardi's law); another horizon changes the default ``n_attempts`` and
    compiles. A law whose fixed leaves are not arrays of numbers gets a function of its own."""
    leaves, tree, _, idx = _split(law, tune)
    sampled = is_sampled(law)
    try:
        fixed = tuple((np.asarray(v).dtype.str, np.shape(v), np.asarray(v).tobytes())
                      for i, v in enumerate(leaves) if i not in idx)
        key = (tree, tuple(idx), np.dtype(dtype).str, int(n_attempts), loss if sampled else None, fixed)
        hash(key)
    except (TypeError, ValueError):
        key = None
    if key is not None and key in _VALUE_AND_GRAD:
        return _VALUE_AND_GRAD[key]

    def f(x, y0, plant, cfg):
        return law_loss(coords.law_of(x), y0, plant, loss if sampled else cfg, n_attempts=n_attempts)

    fn = jax.jit(jax.value_and_grad(f, has_aux=True))
    if key is not None:
        if len(_VALUE_AND_GRAD) >= _KEPT:
            _VALUE_AND_GRAD.pop(next(iter(_VALUE_AND_GRAD)))
        _VALUE_AND_GRAD[key] = fn
    return fn


class InvalidStartingLaw(ValueError):
    """`tune_law`'s starting law is not a valid candidate (a training start failed or the loss is not finite)."""


def _adam_descent(descent: "_Descent", step_fn, steps: int) -> None:
    """The work of `tune_law`: ``descent``'s steps ``descent.it`` to ``steps`` by `descend` (none once stopped);
    ``step_fn(params) -> ((loss, aux), grads)``."""
    descent.params, descent.state, descent.stopped = descend(
        lambda it, params: descent._step(step_fn, it, params), descent.observe, step_if(descent.opt), descent.params,
        descent.state, steps=steps, start=descent.it, stopped=descent.stopped, stop=lambda p, s, valid: not valid,
        save=descent.save, report=descent.report)


class _Descent:
    """The pieces `tune_law` gives `descend`: Adam from ``params``, stopping at the first invalid candidate,
    checkpointed after every step (``store``).

    ``best`` is ``(params, loss, energy)`` of the lowest-loss valid candidate (``None`` while none was valid),
    ``hist`` the per-step lists ``loss``, ``energy``, ``valid``. With a ``store`` holding an earlier run's state
    the descent continues from it, so that an interrupted and resumed run ends where an uninterrupted one does.
    """

    def __init__(self, opt, params, store: Optional[LawCheckpoint], callback: Optional[Callable]):
        self.opt, self.store, self.callback = opt, store, callback
        self.params, self.state = params, opt.init(params)
        self.best, self.hist, self.it, self.stopped = None, {"loss": [], "energy": [], "valid": []}, 0, False
        self.row = None
        saved = None if store is None else store.load(self.params, self.state)
        if saved is not None:
            self.it, self.params, self.state, self.best, self.hist, self.stopped = saved

    def _step(self, step_fn, it: int, params):
        """Evaluate candidate ``it``: ``((loss, aux), grads)``."""
        return step_fn(params)

    def observe(self, it: int, params, state, out) -> bool:
        """Record candidate ``it`` (its row of the history; the best valid one); returns whether it is valid (every
        lane OK, finite gradient)."""
        (value, aux), grads = out
        valid = bool(aux["valid"]) and bool(jnp.all(jnp.isfinite(grads)))
        self.row = row = {"loss": float(value), "energy": float(aux["energy"]), "valid": valid}
        for k, v in row.items():
            self.hist[k].append(v)
        if valid and (self.best is None or row["loss"] < self.best[1]):
            self.best = (params, row["loss"], row["energy"])
        return valid

    def save(self, it: int, params, state, stopped: bool) -> None:
        """The state step ``it`` starts from, in the checkpoint."""
        self.it, self.stopped = it, stopped
        if self.store is not None:
            self.store.save(it, params, state, self.best, self.hist, stopped)

    def report(self, it: int, valid: bool) -> None:
        if self.callback is not None:
            self.callback(it, self.row)
