r"""Tuning on the objective users measure: quantiles of the hard settling time under budgets on quantiles of the
control energy, by gradient (the implicit-function derivative of `jaxsleigh.tuning.event_time`) or by CMA-ES on the
same numbers.

For a law with parameters \(\vartheta\), moved in unconstrained coordinates \(x\) (`jaxsleigh.tuning.law.law_coordinates`:
a leaf declared ``positive`` as its logarithm, the paper's gains as `jaxsleigh.tuning.params.GainParams`) and a batch of
starts,

\[ f(x) = \sum_j a_j\, \frac{Q_{q_j}(T)}{t_f} + \rho \sum_k \max\big(0,\ \log Q_{r_k}(E) - \log E^{max}_k\big)^2
          + \rho\, \max(0,\ s_{min} - \bar s)^2 , \]

\(Q_q\) the \(q\)-quantile over the batch (``jnp.quantile``, linear interpolation), \(T\) the settling time
\(T_{0.05}\) (``t_final`` for a start that did not settle), \(E = \int_0^{t_f} \|u\|^2 dt\), \(\bar s\) the fraction
of starts settled with a smooth stand-in (\(\bar s\) is counted but has no derivative). The budgets
\(E^{max}_k\) are, by default, the reference law's (the paper's gains') own energy quantiles on the same starts:
"no more energy than the paper's at the 25th, 50th, 75th and 90th percentiles". A candidate is *feasible* when
every budget and the settled floor hold and every start ends with status OK; the tuners keep the best feasible one.

The penalty is the \(\lambda = 0\) case of an augmented Lagrangian: with the constraints
\(c_k = \log Q_{r_k}(E) - \log E^{max}_k \le 0\) and \(c_0 = s_{min} - \bar s \le 0\), multipliers
\(\lambda_k \ge 0\) and \(\mu = 2\rho\), each constraint adds

\[ \psi(c, \lambda) = \begin{cases} \lambda c + \tfrac{\mu}{2} c^2, & \lambda + \mu c \ge 0, \\
    -\lambda^2 / (2\mu), & \text{otherwise,} \end{cases} \]

which is \(\rho \max(0, c)^2\) at \(\lambda = 0\). A penalty alone settles where its pull balances the time's,
just outside the budget; `tune_by_gradient` with ``multiplier_every = m`` updates
\(\lambda \leftarrow \max(0, \lambda + \mu c)\) every \(m\) evaluations (the method of multipliers), which moves
that balance onto the budget's edge (each update uses at most a violation of 0.1, `MULTIPLIER_STEP_CAP`). The tuners
rank feasible points by the time term alone.

The simulation budget of a run is counted in trajectory-seconds: starts x horizon per evaluation of \(f\) (a
gradient evaluation also re-simulates each checkpointed segment once on the way back; the study reports wall time
next to it).
"""
from __future__ import annotations

import time
from typing import Any, Callable, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np
import optax

from ..controllers.actuators import is_sampled
from ..integrate.engine import initial_w
from ..integrate.stepsize import StepSizeController
from ..model.charts import chart_for
from ..model.params import PlantParams, as_plant, paper_gains
from ..status import Status
from ..validate import refuses_removed_keywords
from .cmaes import cma_ask, cma_init, cma_tell
from .event_time import settling
from .law import law_coordinates
from .loops import ask_tell, descend, step_if
from .objective import valid_starts

__all__ = ["HardTimeConfig", "HardTimeProblem", "hard_time_problem", "tune_by_gradient", "tune_by_cma", "TuneRun"]


class _HardTimeFields(NamedTuple):
    t_final: float = 100.0
    eps: float = 0.05
    time_quantiles: tuple = (0.5, 0.9)
    time_weights: tuple = (1.0, 0.5)
    energy_quantiles: tuple = (0.25, 0.5, 0.75, 0.9)
    energy_margin: float = 0.95
    settled_margin: float = 0.0
    penalty: float = 10.0
    stepsize: StepSizeController = StepSizeController(max_steps=40_000)
    segment: int = 200


class HardTimeConfig(_HardTimeFields):
    """Numbers of the hard-time objective (module docstring).

    Attributes:
      t_final, eps: horizon [s] and ball radius of \\(T_\\epsilon\\).
      time_quantiles, time_weights: the \\(q_j\\) and \\(a_j\\).
      energy_quantiles: the \\(r_k\\); energy_margin: the budgets are ``margin x`` the reference's quantiles.
      settled_margin: the floor \\(s_{min}\\) is the reference's settled fraction minus this.
      penalty: \\(\\rho\\).
      stepsize: the `jaxsleigh.StepSizeController` of `jaxsleigh.tuning.event_time.settling` (adaptive, tolerances per
        dtype); its ``max_steps`` is the attempts per start (default 40,000, 4x the base steps of 100 s: the
        reverse-mode gradient stores a checkpoint per segment of them; ``None``: every front's budget,
        `jaxsleigh.integrate.horizon.step_budget`). segment: checkpointed segment length.

    ``HardTimeConfig(max_steps=...)`` (before jaxsleigh 0.4) is a ``TypeError`` naming
    ``stepsize=jaxsleigh.StepSizeController(max_steps=...)``.
    """

    __slots__ = ()
    __new__ = refuses_removed_keywords({"max_steps": ("stepsize", "max_steps")},
                                       {"stepsize": frozenset(StepSizeController._fields)},
                                       "HardTimeConfig's max_steps= was removed in jaxsleigh 0.4",
                                       name="HardTimeConfig")(_HardTimeFields.__new__)


class HardTimeProblem(NamedTuple):
    """A law family, its starts and budgets, ready to evaluate: ``value(x, lam=0)`` and ``value_and_grad(x, lam=0)``
    of the objective in the law's coordinates ``x`` (flat, float) with multipliers ``lam`` (one per energy quantile,
    then the settled floor; module docstring), ``law_of(x)`` the law, ``x0`` the start."""

    x0: np.ndarray
    law_of: Callable
    value: Callable
    value_and_grad: Callable
    budgets: np.ndarray
    settled_floor: float
    n: int
    cfg: HardTimeConfig


def _figures(r, cfg: HardTimeConfig):
    T = r.T
    tq = jnp.stack([jnp.quantile(T, q) for q in cfg.time_quantiles])
    eq = jnp.stack([jnp.quantile(r.u_energy, q) for q in cfg.energy_quantiles])
    return tq, eq, jnp.mean(r.settled.astype(T.dtype)), jnp.sum(r.status != Status.OK)


def _mu(cfg: HardTimeConfig) -> float:
    """\\(\\mu = 2\\rho\\): the augmented Lagrangian's quadratic weight, and the multipliers' step (module docstring)."""
    return 2.0 * cfg.penalty


def _no_multipliers(cfg: HardTimeConfig) -> np.ndarray:
    """Zero multipliers: one per energy quantile, then the settled floor (the order of the objective's constraints)."""
    return np.zeros(len(cfg.energy_quantiles) + 1)


def hard_time_problem(law, starts, *, reference=None, plant: Optional[PlantParams] = None,
                      cfg: HardTimeConfig = HardTimeConfig(), dtype=jnp.float32) -> HardTimeProblem:
    """The objective of ``law``'s gains on ``starts`` (N, 3|5), the budgets from ``reference`` (default: the paper's
    gains) on the same starts. ``law`` is any law the engine integrates without a sampler (the paper's `Gains`, a
    `ShapedGains`, a literature law of `jaxsleigh.controllers`), moved in its coordinates
    (`jaxsleigh.tuning.law.law_coordinates`: the paper's gains in their 7 admissible numbers, another law's positive
    gains in logarithm)."""
    if is_sampled(law):
        raise ValueError("hard_time_problem tunes a law the adaptive engine integrates; a sampled law "
                         "(jaxsleigh.controllers.actuators.Sampled) is tuned by jaxsleigh.tuning.tune_law")
    ics5, status0 = valid_starts(starts, name="training start")
    plant = jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), as_plant(plant))
    coords = law_coordinates(law, dtype=dtype)
    ref = paper_gains() if reference is None else reference
    y0_law, y0_ref = (initial_w(ics5, status0, dtype, chart_for(c)) for c in (law, ref))    # each in its own chart

    def run(c, y0w):
        return settling(c, y0w, plant, t_final=cfg.t_final, eps=cfg.eps,
                        stepsize=cfg.stepsize, reverse=True, segment=cfg.segment)

    # the budgets: the reference's energy quantiles times energy_margin; the floor: its settled fraction minus
    # settled_margin
    _, eq_ref, s_ref, _ = jax.jit(lambda c: _figures(run(c, y0_ref), cfg))(
        jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), ref))
    budgets = np.asarray(eq_ref, np.float64) * cfg.energy_margin
    floor = float(s_ref) - cfg.settled_margin
    objective = _objective(lambda x: run(coords.law_of(x), y0_law), budgets, floor, cfg, dtype)
    lam0 = _no_multipliers(cfg)
    value_lam = jax.jit(objective)
    vg_lam = jax.jit(jax.value_and_grad(objective, has_aux=True))

    def value(x, lam=lam0):
        return value_lam(x, lam)

    def value_and_grad(x, lam=lam0):
        return vg_lam(x, lam)

    return HardTimeProblem(coords.x0, coords.law_of, value, value_and_grad, budgets, floor, int(ics5.shape[0]), cfg)


def _objective(run_law, budgets, floor: float, cfg: HardTimeConfig, dtype):
    """The objective ``(x, lam) -> (f, aux)`` of the module docstring (``run_law(x)``: the settling run of the law
    at ``x``): the weighted time quantiles plus the augmented-Lagrangian terms \\(\\psi(c, \\lambda)\\) of the
    energy budgets and the settled floor."""
    lb = jnp.log(jnp.asarray(budgets, dtype))
    weights = jnp.asarray(cfg.time_weights, dtype)

    mu = _mu(cfg)

    def objective(x, lam):
        r = run_law(x)
        tq, eq, settled, n_bad = _figures(r, cfg)
        c = jnp.concatenate([jnp.log(eq) - lb, (floor - settled)[None]])
        lam = jnp.asarray(lam, dtype)
        psi = jnp.where(lam + mu * c >= 0, lam * c + 0.5 * mu * c * c, -lam * lam / (2.0 * mu))
        time_term = jnp.sum(weights * tq) / cfg.t_final
        f = time_term + jnp.sum(psi)
        feasible = (n_bad == 0) & jnp.all(c[:-1] <= 1e-6) & (c[-1] <= 0)      # within rounding of the budgets
        aux = {"T_quantiles": tq, "energy_quantiles": eq, "settled": settled, "n_bad": n_bad, "feasible": feasible,
               "mean_steps": jnp.mean(r.n_steps.astype(dtype)), "time_term": time_term, "constraints": c}
        return f, aux

    return objective


class TuneRun(NamedTuple):
    """A tuner's record: the best feasible ``x`` (or ``None``), its value (the time term: no budget is active there)
    and figures, and the history (one row per evaluation: ``value``, ``feasible``, ``trajectory_seconds`` so far,
    ``wall_s`` so far, the point ``x``, and the multipliers ``lam`` where a run updates them)."""

    x: Any
    value: float
    figures: dict
    history: list


def _host(aux) -> dict:
    return {k: np.asarray(v, np.float64).tolist() for k, v in aux.items()}


class _Record:
    """The tuners' shared bookkeeping: one history row per evaluation (trajectory-seconds and wall time so far), the
    progress callback, and the best feasible point."""

    def __init__(self, problem: HardTimeProblem, progress: Optional[Callable]):
        self.problem, self.progress = problem, progress
        self.best, self.history, self.t0 = None, [], time.perf_counter()

    def add(self, x, f, aux) -> float:
        f = float(f)
        feas = bool(aux["feasible"]) and np.isfinite(f)
        score = float(aux.get("time_term", f))           # a feasible point's value without the multipliers' terms
        n = len(self.history) + 1
        row = {"value": f, "feasible": feas, "trajectory_seconds": n * self.problem.n * self.problem.cfg.t_final,
               "wall_s": time.perf_counter() - self.t0, "x": np.asarray(x, np.float64).tolist(), **_host(aux)}
        self.history.append(row)
        if self.progress:
            self.progress(n - 1, row)
        if feas and (self.best is None or score < self.best[1]):
            self.best = (np.asarray(x, np.float64), score, _host(aux))
        return f

    def result(self) -> TuneRun:
        return TuneRun(*(self.best if self.best else (None, float("inf"), {})), self.history)


#: The largest violation a multiplier update uses: \(\lambda \leftarrow \max(0, \lambda + \mu \min(c, 0.1))\). Far
#: outside a budget the first-order update overshoots (one Aicardi run from its defaults, 30x over the budget, got
#: \(\lambda \approx 50\) at its first update and was then pushed far inside every budget).
MULTIPLIER_STEP_CAP = 0.1


def tune_by_gradient(problem: HardTimeProblem, *, steps: int = 40, lr: float = 0.05, b1: float = 0.5, x0=None,
                     multiplier_every: int = 0, progress: Optional[Callable] = None) -> TuneRun:
    """Adam on \\(f\\) from ``x0`` (default ``problem.x0``); keeps the best feasible iterate. A non-finite gradient
    stops the run (each row says ``gradient_finite``). ``b1`` is Adam's momentum: lower than optax's 0.9 by default, because a
    budget's penalty switches on abruptly and momentum then carries the iterate far past the budget's edge (a first
    run with 0.9 lost its way after 7 steps: docs/evidence/shaped-energy.md). ``multiplier_every = m > 0`` runs the
    method of multipliers (module docstring): after every ``m``-th evaluation the multipliers move by
    \\(\\lambda \\leftarrow \\max(0, \\lambda + \\mu \\min(c, 0.1))\\) with that evaluation's constraints (the cap:
    `MULTIPLIER_STEP_CAP`); 0 keeps the penalty."""
    if not (isinstance(multiplier_every, int) and multiplier_every >= 0):
        raise ValueError(f"multiplier_every must be a whole number >= 0, got {multiplier_every!r}")
    x = jnp.asarray(problem.x0 if x0 is None else x0)
    opt = optax.adam(lr, b1=b1)
    rec = _Record(problem, progress)
    mult = _Multipliers(problem.cfg, multiplier_every)

    def observe(i, x, state, out) -> bool:
        (f, aux), g = out
        rec.add(x, f, aux)
        rec.history[-1]["lam"] = mult.lam.tolist()
        mult.update(i, aux)
        rec.history[-1]["gradient_finite"] = finite = bool(jnp.all(jnp.isfinite(g)))
        return finite

    descend(lambda i, x: problem.value_and_grad(x, mult.lam), observe, step_if(opt), x, opt.init(x), steps=steps,
            stop=lambda x, state, finite: not finite)     # said in the history, not hidden: the run stops there
    return rec.result()


class _Multipliers:
    r"""The method of multipliers of `tune_by_gradient`: after every ``every``-th evaluation (none with
    ``every = 0``: the penalty alone), \(\lambda \leftarrow \max(0, \lambda + \mu \min(c, 0.1))\) with that
    evaluation's constraints \(c\) (the cap: `MULTIPLIER_STEP_CAP`)."""

    def __init__(self, cfg: HardTimeConfig, every: int):
        self.cfg, self.every, self.lam = cfg, int(every), _no_multipliers(cfg)

    def update(self, i: int, aux) -> None:
        """The update after evaluation ``i`` (0-based), whose figures ``aux`` hold the constraints."""
        if self.every and (i + 1) % self.every == 0:
            c = np.minimum(np.asarray(aux["constraints"], np.float64), MULTIPLIER_STEP_CAP)
            self.lam = np.maximum(0.0, self.lam + _mu(self.cfg) * c)


def tune_by_cma(problem: HardTimeProblem, *, evaluations: int = 120, population: int = 12, sigma0: float = 0.3,
                seed: int = 0, x0=None, progress: Optional[Callable] = None) -> TuneRun:
    """CMA-ES (`jaxsleigh.tuning.cmaes`) on the same \\(f\\) (values only), ``evaluations`` in all; keeps the best
    feasible candidate."""
    rng = np.random.default_rng(seed)
    rec = _Record(problem, progress)

    def evaluate(state, xs):
        # the last generation may be cut short by the budget: it is then not told, and the run ends
        scores = []
        for x in xs[: evaluations - len(rec.history)]:
            f = rec.add(x, *problem.value(jnp.asarray(x)))
            scores.append(f if np.isfinite(f) else 1e6)
        return np.asarray(scores), None

    ask_tell(cma_init(np.asarray(problem.x0 if x0 is None else x0, np.float64), sigma0),
             lambda state: cma_ask(state, rng, population), evaluate, cma_tell,
             done=lambda state: len(rec.history) >= evaluations)
    return rec.result()
