r"""The time grid of a run and its step budget: one rule for every door, traced or not.

* `Horizon` / `make_horizon`: ``t_final`` in whole base steps ``dt``, saved every ``save_every`` of them.
* `attempt_budget`: the one step-budget rule, attempts = a factor of the step and tolerance class times base steps
  (1 for fixed RK4, `BUDGET_FACTOR` adaptive, `REFERENCE_FACTOR` for a float64 reference at tight tolerances),
  capped for the engine's int32 counters. Its callers only say what the base steps are: `default_max_steps`, the
  attempted steps a trajectory may take (`jaxsleigh.solve`, `jaxsleigh.simulate` and the ensembles take it);
  `reference_max_steps`, the budget of a float64 reference run (the accuracy audit, a validation re-run at its
  settings); the sampled loop's budget per period (`jaxsleigh.integrate.sampled`). `step_budget` is a step
  policy's budget, its own ``max_steps`` or `default_max_steps`, for a traced door (`jaxsleigh.solve`,
  `jaxsleigh.tuning.event_time.settling`).
* The flight rule (`STIFF_AFTER`, `FLIGHT_STEP`, `flight_step`): when a lane still in a stiff flight near
  \(\theta = 0\) moves to the linearly implicit step of `jaxsleigh.integrate.rosenbrock`. The host's engine reads
  it between segments (`jaxsleigh.integrate.engine.flying`); the traced loop of `jaxsleigh.solve` after every attempt
  (`jaxsleigh.integrate.stepper.FlightSwitch`).

This module sits below both the stepper and the host's engine, so that the traced door does not import the host's.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ..model.params import is_concrete
from .stepsize import DEFAULT_ATOL, DEFAULT_RTOL, StepSizeController

__all__ = ["Horizon", "MAX_BASE_STEPS", "make_horizon", "BUDGET_FACTOR", "attempt_budget", "default_max_steps",
           "step_budget", "reference_max_steps", "REFERENCE_FACTOR", "MAX_ATTEMPTS", "REFERENCE_MAX_ATTEMPTS",
           "STIFF_AFTER",
           "FLIGHT_STEP", "flight_step", "default_tolerance"]


class Horizon(NamedTuple):
    """Time grid of a run: ``n_steps`` base steps of ``dt``, saved every ``save_every``."""

    t_final: float
    dt: float
    n_steps: int
    save_every: int

    @property
    def n_out(self) -> int:
        return self.n_steps // self.save_every

    def save_times(self) -> np.ndarray:
        """Save times after t = 0, float64, shape (n_out,)."""
        return self.dt * self.save_every * np.arange(1, self.n_out + 1, dtype=np.float64)

    def t(self) -> np.ndarray:
        """Saved times including t = 0, shape (n_out + 1,)."""
        return np.concatenate([[0.0], self.save_times()])


#: Most base steps (t_final / dt) of one run: the step budget (30x that at most, adaptive) must fit the
#: engine's int32 counters.
MAX_BASE_STEPS = 50_000_000


def make_horizon(t_final, dt, save_every=None, *, flags=None) -> Horizon:
    """Validated horizon; ``save_every=None`` saves the final state only. ``flags`` maps the
    keywords ``t_final``, ``dt``, ``save_every`` to the names used in messages (command-line flags)."""
    f = (lambda n: (flags or {}).get(n, n))
    try:
        t_final, dt = float(t_final), float(dt)
    except (TypeError, ValueError):
        raise ValueError(f"{f('t_final')} and {f('dt')} must be numbers, got {t_final!r}, {dt!r}") from None
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"{f('dt')} must be a finite number > 0, got {dt}")
    if not (math.isfinite(t_final) and t_final > 0):
        raise ValueError(f"{f('t_final')} must be a finite number > 0, got {t_final}")
    ratio = t_final / dt
    if not ratio <= MAX_BASE_STEPS + 0.5:
        raise ValueError(f"{f('t_final')} / {f('dt')} = {ratio:.3g} base steps is more than one run can take "
                         f"({MAX_BASE_STEPS:.0e}); use a larger {f('dt')} (the adaptive method grows its step "
                         f"by itself) or a shorter {f('t_final')}")
    n_steps = int(round(ratio))
    if n_steps < 1 or abs(n_steps * dt - t_final) > 1e-9 * max(1.0, t_final):
        raise ValueError(f"{f('t_final')} {t_final:g} must be a whole multiple of {f('dt')} {dt:g} "
                         f"(e.g. {f('t_final')} {max(1, n_steps) * dt:g} or {f('dt')} {t_final / max(1, n_steps):g})")
    if save_every is None:
        save_every = n_steps
    if isinstance(save_every, bool) or int(save_every) != save_every or save_every < 1:
        raise ValueError(f"{f('save_every')} must be a whole number >= 1, got {save_every}")
    save_every = int(save_every)
    if n_steps % save_every:
        raise ValueError(f"the {n_steps} base steps ({f('t_final')} / {f('dt')}) are not a multiple of "
                         f"{f('save_every')} {save_every}; use a {f('save_every')} that divides {n_steps} (e.g. 1)")
    return Horizon(t_final, dt, n_steps, save_every)


#: room of the adaptive budget, in base steps, per dtype: float64's 100x tighter tolerances need ~20% more
#: attempts than 20x out of the stiffest starts (theta0 = 1e-2 took 25,387 attempts for a 10 s run's 1,008 base
#: steps; python experiments/performance/engine_defaults.py)
BUDGET_FACTOR = {"float32": 20, "float64": 30}

#: attempts per base step of a float64 reference run at the audit's tight tolerances (`reference_max_steps`)
REFERENCE_FACTOR = 100

#: most attempts of one trajectory: the engine counts them in int32 (a reference run's budget stops at 2e9)
MAX_ATTEMPTS = 2**31 - 2
REFERENCE_MAX_ATTEMPTS = 2_000_000_000


def attempt_budget(base_steps: int, *, adaptive: bool, dtype="float32", reference: bool = False) -> int:
    r"""The step-budget rule, from which every default budget of the library comes: a trajectory may attempt
    \(f \cdot b\) steps for \(b\) = ``base_steps``, with the factor \(f\) of its step and tolerance class,

    * fixed-step RK4 (``adaptive=False``): 1, its base steps;
    * adaptive at the dtype's default tolerances: `BUDGET_FACTOR`, 20 in float32 and 30 in float64;
    * ``reference``: a float64 reference run at tolerances far tighter than the dtype's default (the accuracy
      audit's re-run, `jaxsleigh.studies.audit`, and `jaxsleigh.tuning.validate`'s): `REFERENCE_FACTOR`, 100,

    at most `MAX_ATTEMPTS` (`REFERENCE_MAX_ATTEMPTS` for a reference run), for the engine's int32 counters. The base
    steps are the caller's: a run's \(n + n_{out} + 8\) (`default_max_steps`), a reference run's \(n + 10\)
    (`reference_max_steps`), a sampling period's ``substeps`` (`jaxsleigh.integrate.sampled`), for \(n\) =
    ``t_final / dt`` base steps and \(n_{out}\) saves."""
    if reference:
        return min(REFERENCE_FACTOR * base_steps, REFERENCE_MAX_ATTEMPTS)
    factor = BUDGET_FACTOR.get(np.dtype(dtype).name, 30) if adaptive else 1
    return min(factor * base_steps, MAX_ATTEMPTS)


def default_max_steps(horizon: Horizon, adaptive: bool, dtype="float32") -> int:
    """Per-trajectory budget of attempted steps: `attempt_budget` of the base steps plus the saves and 8 of room,
    times `BUDGET_FACTOR` when adaptive. A start that uses it up (one near theta = 0 that does not settle) ends
    ``BUDGET_EXHAUSTED``."""
    return attempt_budget(horizon.n_steps + horizon.n_out + 8, adaptive=adaptive, dtype=dtype)


def reference_max_steps(horizon: Horizon) -> int:
    r"""The budget of a float64 reference run at tight tolerances (the accuracy audit's re-run of some rows,
    `jaxsleigh.studies.audit`, and a validation re-run at the audit's settings, `jaxsleigh.tuning.validate`):
    `attempt_budget` with ``reference=True``, \(100\,(n + 10) = 100\,n + 1000\) attempts for \(n = t_{final}/dt\)
    base steps, at most 2e9. Larger than `default_max_steps` (30x in float64), for tolerances far tighter than the
    dtype's default."""
    return attempt_budget(horizon.n_steps + 10, adaptive=True, dtype="float64", reference=True)


def step_budget(stepsize: StepSizeController, t_final, dt, dtype, *, save_every=None, flags=None) -> int:
    r"""The attempted steps per trajectory of a run under the checked policy ``stepsize``
    (`jaxsleigh.integrate.stepsize.check_policy`): its ``max_steps`` where given, else `default_max_steps` of the
    horizon ``t_final`` / ``dt`` (saved every ``save_every`` base steps), \(20\,(n + n_{out} + 8)\) attempts in
    float32 and \(30\,(n + n_{out} + 8)\) in float64 for ``"adaptive"``, \(n + n_{out} + 8\) for ``"rk4"``, with
    \(n = t_{final}/dt\). A static number (a Python ``int``): the default needs ``t_final`` and ``dt`` concrete,
    a ``ValueError`` says so where they are traced. ``flags`` names the keywords in messages, as in
    `make_horizon`."""
    if stepsize.max_steps is not None:
        return int(stepsize.max_steps)
    if not is_concrete((t_final, dt)):
        raise ValueError("the default step budget comes from t_final / dt: give them as concrete numbers, or give "
                         "stepsize=jaxsleigh.StepSizeController(max_steps=...)")
    return default_max_steps(make_horizon(t_final, dt, save_every, flags=flags), stepsize.method == "adaptive",
                             dtype)


#: attempts after which the ensembles' adaptive engine steps a lane that is still in a stiff flight (its mean step
#: below `FLIGHT_STEP` base steps: a straggler near the singular set) with the linearly implicit Rosenbrock step
#: (`jaxsleigh.integrate.rosenbrock`), for the rest of its run (`_segment`). A lane's own state decides, so where it
#: runs (a part, the pool of stragglers) never does. A lane that is slow but not stiff (the `tuned` gains' settled
#: phase, ~2e-3 s steps) stays on the explicit step, which handles its oscillation better.
STIFF_AFTER = 20_000

#: a flight's mean step, in base steps, at the dtype's default tolerances (`flight_step` lowers it for tighter ones):
#: at 20,000 attempts the default basin's fliers had reached t = 0.02-12 s, the `tuned` gains' slow lanes 40 s or
#: more (dt = 0.01)
FLIGHT_STEP = 0.1


def flight_step(rtol, atol, dtype) -> float:
    r"""The mean step, in base steps, below which a lane flies (`flying`): `FLIGHT_STEP` at the dtype's default
    tolerances (`jaxsleigh.integrate.stepsize.DEFAULT_RTOL`) or looser, and for tighter ones

    \[ \text{FLIGHT\_STEP} \cdot \left(\frac{\min(r, a)}{\min(r_0, a_0)}\right)^{1/5}, \]

    the factor by which they shrink an explicit step that accuracy limits (the embedded RK4 estimate's local error
    goes as \(h^5\)). A stiff flight's step is limited by stability, not accuracy, and does not shrink; a lane of the
    `tuned` gains' settled phase at 1e-10 takes 4.8e-2 base steps on average over 100 s and, judged by
    `FLIGHT_STEP` alone, moved to the implicit step, of lower order, which then spent 10^6 attempts by t = 58 s."""
    return FLIGHT_STEP * min(1.0, min(float(rtol), float(atol)) / default_tolerance(dtype)) ** 0.2


def default_tolerance(dtype) -> float:
    """The smaller of the dtype's default ``rtol`` and ``atol`` (`jaxsleigh.integrate.stepsize.DEFAULT_RTOL`): the
    tolerance at which `flight_step` is `FLIGHT_STEP`."""
    name = np.dtype(dtype).name
    return min(DEFAULT_RTOL.get(name, 1e-6), DEFAULT_ATOL.get(name, 1e-6))
