r"""Derivative-free search of the gains on the accurate engine's own figures, under an effort budget.

The gradient tuner (`tune`) descends a smooth *surrogate* (the soft time outside the ball, with a
budget on the geometric-mean energy of its training batch, integrated by its own differentiable scan).
What a user reads, and what the ``balanced`` preset promises, are other numbers: the **median hard
convergence time** \(T_{0.05}\) over starts, **percentiles of the control energy** \(\int_0^{100}|u|^2 dt\),
the converged fraction, no start failing or crossing \(\theta = 0\), all measured by the accurate
engine (`jaxsleigh.studies.ensemble.run_ensemble`). `search` optimises exactly those:

\[ \min_{\text{gains}}\ \operatorname{median}_i T_{0.05,i} \quad \text{s.t.}\quad P_q(E) \le E_{max,q}\ (q \in Q),\ \ \text{converged} \ge F_{min},\ \ \text{no start fails or crosses } \theta = 0, \]

on a training batch of starts, by CMA-ES (`jaxsleigh.tuning.cmaes`) in the unconstrained
parametrisation of `GainParams`, with the constraints as an exact penalty

\[ s = \min(\operatorname{median} T, 2 T_f) + \rho\,\big[\textstyle\sum_{q \in Q} \max(0, \log(P_q(E) / E_{max,q})) + \max(0, F_{min} - F) + n_{bad}\big] \]

(\(\rho\) = ``penalty``, large: a feasible candidate always beats an infeasible one that is not
much faster). \(P_q(E)\) is the \(q\)-th percentile of the control energy over the training starts,
\(Q\) = ``energy_percentiles`` (the median alone by default), and \(E_{max,q}\) is ``energy_margin`` times the
reference gains' same percentile on the same
starts (or ``energy_budget``) and \(F_{min}\) their converged fraction plus ``converged_margin``: the
margins leave room for the sampling noise when the result is re-measured on other starts.

**Vectorised over the population.** Every candidate of a generation runs in the same
`run_ensemble` call, its gains as per-lane parameters (`jaxsleigh.model.lanes`): a generation of
\(\lambda\) candidates on \(N\) starts is one compiled ensemble of \(\lambda N\) trajectories, and
changing the gains never recompiles.

**Why not the gradient.** The median of hard times is piecewise constant in the gains and the
converged fraction a step function; the surrogate that makes them differentiable is what the
gradient tuner optimises, and its optimum under an energy budget is a different point (it weighs
every start's time and the geometric-mean energy, not the medians; ``docs/how-to/tuning.md``
gives both results side by side).

**Safety.** The returned gains are the best feasible candidate that also passes the guard starts
(`guard_starts`, \(|\theta_0|\) down to 0.05) over the horizon with the accurate engine; the
``verify`` best feasible candidates are tried in turn. A run is checkpointed after every generation
(``checkpoint=``; the strategy's state, the generator's state, the history, the best candidates) and
resumes to the same result; Ctrl-C raises `TuningInterrupted` with the best so far.
"""
from __future__ import annotations

import hashlib
import json
import math
import time
from pathlib import Path
from typing import Any, NamedTuple, Optional, Sequence

import numpy as np

from ..model.params import Gains, PlantParams, gains as make_gains, gains_to_dict, load_gains
from ..progress import Progress
from ..status import Status
from ..studies.options import RunOptions
from .checkpoint import Checkpoint, TuningInterrupted, checked_state
from .cmaes import CMAState, cma_ask, cma_init, cma_tell
from .loops import ask_tell
from .params import D_FLOOR, params_from_gains, parse_tune
from .starts import UniformStarts, draw_starts, guard_starts
from ..model.lanes import stack_gains
from ..studies.ensemble import run_ensemble
from ..validate import check_count, check_memory

__all__ = ["SearchConfig", "SearchResult", "PopulationFigures", "NoFeasibleCandidate", "evaluate_population", "search",
           "MAX_GENERATIONS", "MAX_POPULATION"]

#: Most generations a search accepts: 100 take about an hour with the default population and batch.
MAX_GENERATIONS = 10_000
#: Most candidates per generation: one generation is one ensemble of population x batch trajectories.
MAX_POPULATION = 4096


class NoFeasibleCandidate(RuntimeError):
    """`search` finished its generations but no feasible candidate passed (the budget is too tight,
    or every feasible one failed the guard starts).

    Attributes:
      history: the per-generation history (as `SearchResult.history`); reference: the reference's
        figures with the budget and the floor; settings: the run's settings; reason: ``"infeasible"``
        (no candidate met the budget) or ``"guard"`` (feasible ones failed the guard starts).
    """

    def __init__(self, message: str, *, history: dict, reference: dict, settings: dict, reason: str):
        super().__init__(message)
        self.history, self.reference, self.settings, self.reason = history, reference, settings, reason

#: Position of each tunable gain in the flat parameter vector ``(log_L (3), log_k, d_chol (3))``.
_SLICES = {"L": slice(0, 3), "k": slice(3, 4), "D_hat": slice(4, 7)}
_HISTORY = ("generation", "score", "median_T", "median_energy", "frac_converged", "n_bad", "feasible", "sigma",
            "best_score", "wall_s", "median_gap")
#: The columns of ``_HISTORY`` that are not floats, with their types.
_HISTORY_TYPES = {"generation": int, "n_bad": int, "feasible": bool}


class SearchConfig(NamedTuple):
    """Settings of `search`.

    Attributes:
      generations: CMA-ES generations. population: candidates per generation (\\(\\lambda\\)).
      batch: training starts drawn from ``starts`` with ``seed``. seed: of the starts and of the search.
      sigma0: initial step size in the unconstrained parameters (0.5: gains change by ~e^0.5).
      energy_margin: \\(E_{max}\\) = this x the reference gains' median energy on the training starts.
      converged_margin: the converged fraction must be at least the reference's plus this (the hard starts
        are a tail of a few %: a faster median tends to lengthen it, and the margin keeps the result from
        converging fewer starts than the reference on other starts).
      objective: ``"time"``: the median \\(T_{0.05}\\) (the module docstring); ``"gap"``: the median over the starts
        of the time ratio to the optimum, \\(T_{law} / T^*(E_{law})\\) (`jaxsleigh.OptimumResult.gap`: how much
        longer than the earliest rest in the ball that the law's own energy could buy), under the same energy
        budget; it needs ``search(frontier=...)``, whose starts are the training starts. A start whose ratio the
        frontier's horizons only bound (the law spends more than the shortest horizon needs) counts as inf.
      penalty: \\(\\rho\\) of the exact penalty (module docstring).
      t_final: horizon [s] (the validation's 100 s). eps: radius of the ball of \\(T_\\epsilon\\).
      verify: feasible candidates tried against the guard starts, best first.
      energy_percentiles: the percentiles of the control energy over the training starts that must each stay
        within ``energy_margin`` x the reference's same percentile (``(50,)``: the median only). The energy is
        bimodal (starts near theta = 0 carry \\(H_d(0) \\sim \\theta_0^{-4}\\)): a median budget alone lets the
        upper half grow several-fold.
    """

    generations: int = 100
    population: int = 16
    batch: int = 128
    seed: int = 0
    sigma0: float = 0.5
    energy_margin: float = 0.95
    converged_margin: float = 0.02
    penalty: float = 200.0
    t_final: float = 100.0
    eps: float = 0.05
    verify: int = 5
    energy_percentiles: tuple = (50.0,)
    objective: str = "time"


class PopulationFigures(NamedTuple):
    """Figures of each candidate on the training starts (arrays over the candidates): median T_eps
    (failures and unconverged count as inf), median control energy (of the OK starts), converged
    fraction, starts that failed or crossed theta = 0, mean accepted steps; the energy at each of the
    ``percentiles`` asked for, shape (candidates, percentiles) (not one of `SCALAR_FIGURES`); and the median time
    ratio to the optimum (`jaxsleigh.OptimumResult.gap`; a start not settled or beyond the frontier counts as inf;
    NaN without a frontier, ``None`` where not computed)."""

    median_T: np.ndarray
    median_energy: np.ndarray
    frac_converged: np.ndarray
    n_bad: np.ndarray
    mean_steps: np.ndarray
    energy_at: np.ndarray
    median_gap: Optional[np.ndarray] = None


#: The figures of one candidate that a search keeps for its best ones (one number each).
SCALAR_FIGURES = tuple(f for f in PopulationFigures._fields if f != "energy_at")


def _scalars(fig: PopulationFigures, i: int) -> tuple:
    return tuple(math.nan if getattr(fig, k) is None else float(getattr(fig, k)[i]) for k in SCALAR_FIGURES)


class SearchResult(NamedTuple):
    """Result of `search`.

    Attributes:
      gains: the best feasible candidate that passed the guard starts (validated `Gains`).
      initial: the starting gains. figures: dict of the result's training figures (median T, energy,
        converged, n_bad, mean steps). reference: the reference gains' figures on the same starts
        and the budget \\(E_{max}\\) (``energy_budget``) and floor \\(F_{min}\\) (``converged_floor``) derived from them.
      history: dict of arrays, one entry per generation (the generation's best candidate; ``_HISTORY``).
      best_generation: where the returned gains were found (-1: the starting gains, when no feasible
        candidate beat them). settings: everything that made the run.
    """

    gains: Gains
    initial: Gains
    figures: dict
    reference: dict
    history: dict
    best_generation: int
    settings: dict


def evaluate_population(gains_list, ics, *, plant: Optional[PlantParams] = None, t_final: float = 100.0,
                        eps: float = 0.05, x64: bool = False, stepsize=None,
                        percentiles: Sequence[float] = (50.0,), frontier=None) -> PopulationFigures:
    """Run every candidate of ``gains_list`` from every start of ``ics`` in one ensemble (gains as
    per-lane parameters, ``stepsize`` a `jaxsleigh.StepSizeController` or ``None`` for the defaults) and reduce
    per candidate (`PopulationFigures`; the median gap against ``frontier``, a `jaxsleigh.OptimumResult` of the
    same starts, if given)."""
    glist = [load_gains(g) for g in gains_list]
    ics = np.asarray(ics, np.float64)
    P, N = len(glist), ics.shape[0]
    r = run_ensemble(np.tile(ics, (P, 1)), plant=plant, gains=stack_gains([g for g in glist for _ in range(N)]),
                     t_final=t_final, eps=eps, x64=x64, stepsize=stepsize, run=RunOptions(progress=False))
    ok = (r.status == Status.OK).reshape(P, N)
    T = np.where(ok, np.asarray(r.T_eps).reshape(P, N), np.inf)
    T = np.where(np.isnan(T), np.inf, T)
    E = np.asarray(r.u_energy, np.float64).reshape(P, N)
    th0 = np.tile(ics[:, 2], P).reshape(P, N)
    crossed = np.sign(np.asarray(r.q_final)[:, 2].reshape(P, N)) != np.sign(th0)
    med_E = np.array([np.median(E[i][ok[i]]) if ok[i].any() else np.inf for i in range(P)])
    at = np.array([np.percentile(E[i][ok[i]], percentiles) if ok[i].any() else np.full(len(percentiles), np.inf)
                   for i in range(P)]).reshape(P, len(percentiles))
    gap = np.full(P, np.nan)
    if frontier is not None:
        # the ratio's value only: where the frontier's horizons merely bound it (Gap.time_at_least) it is NaN and
        # counts as inf, so that no candidate can buy a small ratio by spending beyond the frontier
        ratio = np.stack([frontier.gap(T[i], E[i]).time for i in range(P)])
        gap = np.median(np.where(np.isnan(ratio), np.inf, ratio), axis=1)
    return PopulationFigures(np.median(T, axis=1), med_E, np.isfinite(T).mean(axis=1),
                             np.sum(~ok | crossed, axis=1), np.asarray(r.n_steps, np.float64).reshape(P, N).mean(1),
                             at, gap)


def _score(fig: PopulationFigures, i: int, e_max, f_min: float, cfg: SearchConfig) -> tuple[float, bool]:
    """The penalised score of candidate ``i`` and whether it is feasible; ``e_max``: the budget at each of
    ``cfg.energy_percentiles`` (the module docstring's \\(E_{max}\\), one per percentile)."""
    viol = sum(max(0.0, math.log(max(e, 1e-300) / b)) if math.isfinite(e) else 1e3
               for e, b in zip(fig.energy_at[i], np.atleast_1d(e_max)))
    viol += max(0.0, f_min - fig.frac_converged[i]) + float(fig.n_bad[i])
    if cfg.objective == "gap":
        # a ratio, ~1-10 where the laws are (the penalty's scale suits it as it suits seconds); capped as time is
        t = min(float(fig.median_gap[i]), 100.0)
    else:
        t = min(float(fig.median_T[i]), 2.0 * cfg.t_final)
    return t + cfg.penalty * viol, viol == 0.0


def _to_gains(x_full, d_floor, g0: Gains, names) -> Gains:
    """`gains_from_params` in float64 NumPy; the gains not in ``names`` are ``g0``'s, bit for bit."""
    x = np.asarray(x_full, np.float64)
    a, b, d = math.exp(x[4]), x[5], math.exp(x[6])
    D = np.array([[a * a + d_floor, a * b], [a * b, b * b + d * d + d_floor]])
    return make_gains(np.exp(x[:3]) if "L" in names else g0.L, math.exp(x[3]) if "k" in names else g0.k,
                      D if "D_hat" in names else g0.D_hat)


def _save(path: Path, stamp: Checkpoint, state: CMAState, rng, hist: list, top: list) -> None:
    arrays = {"rng": np.array(json.dumps(rng.bit_generator.state)),
              **{f"cma/{f}": np.asarray(v) for f, v in state._asdict().items()},
              **{f"hist/{f}": np.asarray([h.get(f, math.nan) for h in hist], np.float64) for f in _HISTORY}}
    arrays["top/score"] = np.asarray([t[0] for t in top], np.float64)
    arrays["top/generation"] = np.asarray([t[1] for t in top], np.int64)
    arrays["top/x"] = np.asarray([t[2] for t in top], np.float64).reshape(len(top), state.mean.size)
    arrays["top/figures"] = np.asarray([t[3] for t in top], np.float64).reshape(len(top), len(SCALAR_FIGURES))
    stamp.write(path, arrays)


def search(gains0="paper", *, starts=UniformStarts(), config: SearchConfig = SearchConfig(), reference="paper",
           energy_budget: Optional[float] = None, tune=None, plant: Optional[PlantParams] = None, x64: bool = False,
           d_floor: float = D_FLOOR, stepsize=None, progress: Any = None, checkpoint=None,
           resume: bool = False, options: Optional[dict] = None, frontier=None) -> SearchResult:
    """The fastest gains (median T_eps on ``config.batch`` training starts) whose median control energy
    is at most ``energy_budget`` (default: ``config.energy_margin`` x the ``reference`` gains' on the
    same starts), with no fewer converged than ``reference`` and no start failing or crossing
    theta = 0, by CMA-ES from ``gains0`` over the gains named in ``tune`` (default all; module
    docstring). ``checkpoint``: a ``.npz`` written after every generation; ``resume=True`` continues
    from it (also with more ``generations`` than the run that wrote it: the first ones are identical); ``options`` are
    recorded in it as they are (the command line's, `jaxsleigh.tuning.checkpoint.checkpoint_options`). Raises `TuningInterrupted` on Ctrl-C (``partial``: the best so far, or ``None``) and
    ``RuntimeError`` if no feasible candidate passes the guard starts. ``stepsize``: the engine's
    `jaxsleigh.StepSizeController` for every run (``None``: the defaults). Control energy spent after settling
    needs a tighter absolute tolerance than the float32 default to be resolved (``atol=1e-8``:
    docs/evidence/settled-phase.md); a search on the defaults can reward gains for energy that float32 does not see.
    ``frontier``: with ``config.objective="gap"``, the `jaxsleigh.OptimumResult` of the training starts (its
    ``starts`` replace ``starts`` and ``config.batch``; its ``eps`` must be ``config.eps``): the search minimises the
    median time ratio to that optimum instead of the median time."""
    pcts = _checked_search_inputs(config, energy_budget)
    names, g0 = parse_tune(tune), load_gains(gains0)
    space = _Space(np.concatenate([np.ravel(p) for p in params_from_gains(g0, d_floor=d_floor)]),
                   np.concatenate([np.arange(7)[_SLICES[n]] for n in names]), d_floor, g0, names)
    ics = _training_starts(starts, config, frontier)
    ev = _Evaluator(ics, plant, config.t_final, config.eps, x64, stepsize, pcts, frontier)
    guard = guard_starts()
    settings, stamp = _search_settings(config, space, ev, reference, energy_budget, starts, options)
    ckpt = None if checkpoint is None else Path(checkpoint)
    # the reference and the start in one ensemble; the start is candidate "generation -1"
    ref = ev.evaluate([reference, space.g0])
    budget = _budget(ref, energy_budget, config, pcts)
    run = _start(space, ref, budget, config, ckpt if resume else None, stamp)
    try:
        _generations(run, space, ev, budget, config, ckpt, stamp, progress)
    except KeyboardInterrupt:
        # the best feasible candidate so far, unchecked
        raise TuningInterrupted(_result(run, space, budget, settings, run.top[0]) if run.top else None, ckpt) from None
    return _verified(run, space, ev, guard, budget, settings)


def _training_starts(starts, config: SearchConfig, frontier) -> np.ndarray:
    """The training starts: ``config.batch`` drawn from ``starts``, or the frontier's own for the gap objective."""
    if config.objective not in ("time", "gap"):
        raise ValueError(f"search: objective must be 'time' or 'gap', got {config.objective!r}")
    if config.objective == "time":
        if frontier is not None:
            raise ValueError("search: a frontier is used by objective='gap' only; set it, or drop the frontier")
        return draw_starts(starts, config.batch, config.seed)
    if frontier is None or not hasattr(frontier, "gap"):
        raise ValueError("search: objective='gap' needs frontier=, the jaxsleigh.optimum result of the training "
                         f"starts (jaxsleigh.optimum(starts, horizons)), got {type(frontier).__name__}")
    if not math.isclose(float(frontier.eps), float(config.eps)):
        raise ValueError(f"search: the frontier was solved for the ball eps = {frontier.eps:g}, the search measures "
                         f"T_eps for eps = {config.eps:g}; solve it for the same ball")
    if not np.isfinite(frontier.frontier()).any():
        raise ValueError("search: the frontier has no solved problem (every status is INFEASIBLE or worse); "
                         "solve it with more iterations or longer horizons")
    return np.asarray(frontier.starts, np.float64)


def _checked_search_inputs(config: SearchConfig, energy_budget: Optional[float]) -> tuple:
    """Refuse a bad ``config`` or ``energy_budget`` (ValueError, in a fixed order); returns the energy
    percentiles as floats."""
    for name in ("generations", "population", "batch", "verify"):
        v = getattr(config, name)
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < (2 if name == "population" else 1):
            raise ValueError(f"search: {name} must be a whole number >= {2 if name == 'population' else 1}, got {v!r}")
    check_count("search: generations", config.generations, maximum=MAX_GENERATIONS,
                reason="each generation runs the whole population on the training starts over 100 s (100 take "
                       "about an hour)", fix="search in stages (resume the same run with more generations)")
    check_count("search: population", config.population, maximum=MAX_POPULATION,
                reason="a generation is one ensemble of population x batch trajectories",
                fix="use a smaller population (CMA-ES needs about 4 + 3 ln(7) ~ 10)")
    check_memory(int(config.population) * int(config.batch), "search: population x batch",
                 unit="trajectories per generation", fix="use a smaller population or batch")
    if not (isinstance(config.converged_margin, (int, float, np.floating)) and 0 <= config.converged_margin < 1):
        raise ValueError(f"search: converged_margin must be in [0, 1), got {config.converged_margin!r}")
    for name in ("sigma0", "energy_margin", "penalty", "t_final", "eps"):
        v = getattr(config, name)
        if not (isinstance(v, (int, float, np.floating)) and math.isfinite(v) and v > 0):
            raise ValueError(f"search: {name} must be a finite number > 0, got {v!r}")
    if energy_budget is not None and not (math.isfinite(energy_budget) and energy_budget > 0):
        raise ValueError(f"search: energy_budget must be a finite number > 0, got {energy_budget!r}")
    pcts = config.energy_percentiles
    if not (isinstance(pcts, (tuple, list)) and pcts and len(set(pcts)) == len(pcts) and all(
            isinstance(q, (int, float, np.integer, np.floating)) and not isinstance(q, bool) and 0 < q < 100
            for q in pcts)):
        raise ValueError(f"search: energy_percentiles must be distinct percentiles in (0, 100), e.g. (50, 75, 90), "
                         f"got {pcts!r}")
    if energy_budget is not None and tuple(pcts) != (50.0,):
        raise ValueError("search: energy_budget is a budget on the median; with other energy_percentiles the budgets "
                         "are energy_margin x the reference's")
    return tuple(float(q) for q in pcts)


class _Space(NamedTuple):
    """What a search moves: the flat parameters ``full0`` of the starting gains ``g0``, of which those at
    ``free`` (the gains in ``names``) are the candidate vector."""

    full0: np.ndarray
    free: np.ndarray
    d_floor: float
    g0: Gains
    names: tuple

    def gains(self, x) -> Gains:
        """The gains of candidate vector ``x`` (the untuned ones are ``g0``'s, bit for bit)."""
        v = self.full0.copy()
        v[self.free] = x
        return _to_gains(v, self.d_floor, self.g0, self.names)


class _Evaluator(NamedTuple):
    """The training starts and the engine's settings that every candidate of a search is run with."""

    ics: np.ndarray
    plant: Optional[PlantParams]
    t_final: float
    eps: float
    x64: bool
    stepsize: Any
    pcts: tuple
    frontier: Any = None

    def evaluate(self, gains_list) -> PopulationFigures:
        """`evaluate_population` of ``gains_list`` on the training starts."""
        return evaluate_population(gains_list, self.ics, plant=self.plant, t_final=self.t_final, eps=self.eps,
                                   x64=self.x64, stepsize=self.stepsize, percentiles=self.pcts,
                                   frontier=self.frontier)


def _search_settings(config: SearchConfig, space: _Space, ev: _Evaluator, reference, energy_budget: Optional[float],
                     starts, options: Optional[dict]) -> tuple[dict, Checkpoint]:
    """The run's settings (as recorded in its result) and the `Checkpoint` a checkpoint must match."""
    settings = {"config": config._asdict(), "gains0": gains_to_dict(space.g0),
                "reference": gains_to_dict(load_gains(reference)), "energy_budget": energy_budget,
                "tuned": list(space.names), "x64": bool(ev.x64), "d_floor": float(space.d_floor),
                "starts": repr(starts) if callable(starts) else "array",
                "plant": None if ev.plant is None else repr(ev.plant), "method": "CMA-ES on the accurate engine"}
    if ev.stepsize is not None:            # (left out otherwise: the fingerprints of earlier runs hold)
        settings["stepsize"] = ev.stepsize._asdict()
    if ev.frontier is not None:                # its starts are the training starts: config.batch is not used
        settings["starts"] = "the frontier's"
        settings["config"] = {**settings["config"], "batch": int(np.shape(ev.ics)[0])}
        digest = hashlib.sha256(np.ascontiguousarray(ev.frontier.frontier()).tobytes()).hexdigest()
        settings["frontier"] = {"horizons": [float(h) for h in ev.frontier.horizons], "sha256": digest}
    # the generation count is left out: a finished or interrupted run can be resumed for more generations
    # (a generation does not depend on how many follow it)
    # (the percentiles are left out at their default: the fingerprints of earlier runs hold)
    # (and so is the objective at "time")
    stamped = {**settings, "config": {k: v for k, v in config._asdict().items() if k != "generations"
                                      and not (k == "energy_percentiles" and ev.pcts == (50.0,))
                                      and not (k == "objective" and v == "time")}}
    return settings, Checkpoint.of_run(stamped, ev.ics, options)


class _Budget(NamedTuple):
    """The constraints of a search: the energy budget at each percentile (``e_max``), the floor of the
    converged fraction (``f_min``), and the reference's figures with both (``reference``)."""

    e_max: np.ndarray
    f_min: float
    reference: dict


def _budget(ref: PopulationFigures, energy_budget: Optional[float], config: SearchConfig, pcts: tuple) -> _Budget:
    """The budgets and the floor from the reference's figures (candidate 0 of ``ref``)."""
    e_max = (np.array([float(energy_budget)]) if energy_budget is not None
             else config.energy_margin * np.asarray(ref.energy_at[0], np.float64))
    f_min = min(1.0, float(ref.frac_converged[0]) + config.converged_margin)
    reference_figs = {"median_T": float(ref.median_T[0]), "median_energy": float(ref.median_energy[0]),
                      "frac_converged": float(ref.frac_converged[0]), "n_bad": int(ref.n_bad[0]),
                      "mean_steps": float(ref.mean_steps[0]),
                      "energy_budget": float(e_max[pcts.index(50.0)]) if 50.0 in pcts else math.nan,
                      "converged_floor": f_min}
    if ref.median_gap is not None and np.isfinite(ref.median_gap[0]):
        reference_figs["median_gap"] = float(ref.median_gap[0])
    if pcts != (50.0,):
        reference_figs["energy_budgets"] = {f"p{q:g}": float(b) for q, b in zip(pcts, e_max)}
    return _Budget(e_max, f_min, reference_figs)


class _SearchState:
    """A search under way: the strategy's ``state``, the generator ``rng``, the ``hist`` rows, the best
    feasible candidates ``top`` ((score, generation, x, figures), best first) and the clock's origin ``t0``."""

    def __init__(self, state: CMAState, rng, hist: list, top: list, t0: float):
        self.state, self.rng, self.hist, self.top, self.t0 = state, rng, hist, top, t0

    def history(self) -> dict:
        """The history as arrays, one entry per generation (``_HISTORY``)."""
        return {k: np.asarray([h[k] for h in self.hist]) for k in _HISTORY}


def _start(space: _Space, ref: PopulationFigures, budget: _Budget, config: SearchConfig,
           resume_from: Optional[Path], stamp: Checkpoint) -> _SearchState:
    """A fresh run from the starting gains (candidate 1 of ``ref``, kept if feasible), or the one
    checkpointed at ``resume_from`` if that file exists."""
    rng = np.random.default_rng(config.seed)
    state, hist, top = cma_init(space.full0[space.free], config.sigma0), [], []
    s0, feasible0 = _score(ref, 1, budget.e_max, budget.f_min, config)
    if feasible0:
        top.append((float(s0), -1, space.full0[space.free].copy(), _scalars(ref, 1)))
    if resume_from is not None and resume_from.exists():
        a = stamp.read(resume_from, what="search checkpoint")

        def restore():
            rng.bit_generator.state = json.loads(str(a["rng"]))
            state = CMAState(*(a[f"cma/{f}"] for f in CMAState._fields))
            # the types of a fresh row (the checkpoint keeps every column as float64): a resumed search writes
            # the history of an uninterrupted one, byte for byte
            hist = [{f: _HISTORY_TYPES.get(f, float)(a[f"hist/{f}"][i].item()) for f in _HISTORY if f"hist/{f}" in a}
                    for i in range(len(a["hist/generation"]))]
            top = [(float(s), int(g), x, tuple(f)) for s, g, x, f in
                   zip(a["top/score"], a["top/generation"], a["top/x"], a["top/figures"])]
            return state, hist, top

        state, hist, top = checked_state("search checkpoint", resume_from, restore)
    return _SearchState(state, rng, hist, top, time.perf_counter() - (hist[-1]["wall_s"] if hist else 0.0))


def _generations(run: _SearchState, space: _Space, ev: _Evaluator, budget: _Budget, config: SearchConfig,
                 ckpt: Optional[Path], stamp: Checkpoint, progress: Any) -> None:
    """The remaining generations of ``run`` (updated in place) by `ask_tell`, each checkpointed and reported."""

    def evaluate(state, xs):
        """The candidates' penalised scores, in one ensemble; with their figures and feasibility."""
        figs = ev.evaluate([space.gains(x) for x in xs])
        scored = [_score(figs, i, budget.e_max, budget.f_min, config) for i in range(len(xs))]
        return np.array([s for s, _ in scored]), (figs, scored)

    def save(state) -> None:
        _save(ckpt, stamp, run.state, run.rng, run.hist, run.top)

    with Progress(progress, desc="search (CMA-ES)") as bar:
        def report(state) -> None:
            bar.update(int(state.generation) / config.generations)
            bar.postfix(median_T=f"{run.top[0][3][0]:.2f}" if run.top else "-", sigma=f"{float(run.state.sigma):.3f}")

        ask_tell(run.state, lambda state: cma_ask(state, run.rng, config.population), evaluate, cma_tell,
                 done=lambda state: int(state.generation) >= config.generations,
                 observe=lambda state, xs, scores, info: _record(run, state, xs, scores, *info, config),
                 save=None if ckpt is None else save, report=report)


def _record(run: _SearchState, state: CMAState, xs, scores, figs: PopulationFigures, scored: list,
            config: SearchConfig) -> None:
    """A generation told: the strategy's new ``state`` in ``run``, the best feasible candidates kept, and the
    generation's row (its best candidate) appended to the history."""
    run.state, gen = state, int(state.generation) - 1
    for i, (s, feas) in enumerate(scored):
        if feas:
            run.top.append((float(s), gen, np.asarray(xs[i]), _scalars(figs, i)))
    run.top = sorted(run.top, key=lambda t: (t[0], t[1]))[:max(1, int(config.verify))]
    b = int(np.argmin(scores))
    run.hist.append({"generation": gen, "score": float(scores[b]), "median_T": float(figs.median_T[b]),
                     "median_energy": float(figs.median_energy[b]), "frac_converged": float(figs.frac_converged[b]),
                     "n_bad": int(figs.n_bad[b]), "feasible": bool(scored[b][1]), "sigma": float(run.state.sigma),
                     "best_score": run.top[0][0] if run.top else math.inf, "wall_s": time.perf_counter() - run.t0,
                     "median_gap": math.nan if figs.median_gap is None else float(figs.median_gap[b])})


def _verified(run: _SearchState, space: _Space, ev: _Evaluator, guard, budget: _Budget, settings: dict) -> SearchResult:
    """The best of the kept candidates that passes the guard starts; raises `NoFeasibleCandidate` if none does."""
    why = []
    for cand in run.top:
        r = run_ensemble(guard, plant=ev.plant, gains=space.gains(cand[2]), t_final=ev.t_final, x64=ev.x64,
                         stepsize=ev.stepsize, run=RunOptions(progress=False))
        bad = (r.status != Status.OK) | (np.sign(np.asarray(r.q_final)[:, 2]) != np.sign(guard[:, 2]))
        if not bad.any():
            return _result(run, space, budget, settings, cand)
        why.append(f"generation {cand[1]}: guard starts {int(bad.sum())} of {bad.size} failed or crossed theta = 0")
    # the history is kept on the error: a caller (the command line) writes it, so the run is not lost
    budgets = ", ".join(f"{b:.4g} at the {q:g}th percentile" for q, b in zip(ev.pcts, budget.e_max))
    raise NoFeasibleCandidate(
        "search: no feasible candidate" + (" passed the guard starts (" + "; ".join(why) + ")" if why
                                           else f" (energy <= {budgets} with converged >= {budget.f_min:.3f}); raise "
                                                "the budget (energy_margin / energy_budget) or the generations"),
        history=run.history(), reference=budget.reference, settings={**settings, "generations_run": len(run.hist)},
        reason="guard" if why else "infeasible")


def _result(run: _SearchState, space: _Space, budget: _Budget, settings: dict, cand) -> SearchResult:
    """The result of the kept candidate ``cand`` (``(score, generation, x, figures)``)."""
    _, gen, x, f = cand
    return SearchResult(space.gains(x), space.g0, dict(zip(SCALAR_FIGURES, (float(v) for v in f))),
                        budget.reference, run.history(), int(gen), {**settings, "generations_run": len(run.hist)})
