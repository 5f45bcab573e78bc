"""Status codes of a trajectory (one ``int32`` per initial condition).

Inside jitted code trouble is reported as data: the trajectory is frozen at its last good state,
its status says why, and saved outputs after that point are NaN. Nothing is silently wrong.
"""
from __future__ import annotations

import enum

import numpy as np

__all__ = ["Status", "DESCRIPTIONS", "NOT_INTEGRATED", "FAILED", "NO_RESULT", "describe", "counts_in_words",
           "converged", "integrated", "has_result"]


class Status(enum.IntEnum):
    OK = 0
    SINGULAR_START = 1
    INVALID_INPUT = 2
    NONFINITE = 3
    BUDGET_EXHAUSTED = 4
    CROSSED_SINGULAR = 5
    STEP_UNDERFLOW = 6
    UNRELIABLE = 7
    OUT_OF_RANGE = 8
    NOT_SETTLING = 9


DESCRIPTIONS = {
    Status.OK: "reached the horizon",
    Status.SINGULAR_START: ("starts on the singular set theta = 0 where the control law is undefined; "
                            "not integrated, outputs NaN"),
    Status.INVALID_INPUT: "non-finite initial condition; not integrated, outputs NaN",
    Status.NONFINITE: ("the state, the law's output or its effort integral became inf/NaN (a diverging run); "
                       "outputs NaN from then on. Under fixed-step "
                       "RK4: a step too large, usually near theta = 0 (use the adaptive method or a smaller dt). "
                       "In the sampled-data loop: a law whose output is not finite on what it measures. Under the "
                       "adaptive stepper: the vector field (a law's output) is not finite where the run is, so its "
                       "rejected steps shrank to nothing (not a STEP_UNDERFLOW); no result: final state and "
                       "summaries NaN"),
    Status.BUDGET_EXHAUSTED: ("the adaptive stepper used its step budget before the horizon; outputs NaN "
                              "after the last time reached; raise max_steps, unless the run is flying away "
                              "(a large max_excursion): a law whose output is unbounded on what it measures "
                              "(Astolfi's divides by the measured theta, which measurement noise makes cross 0) "
                              "needs a saturation or less noise, not more steps. A start within ~1e-3 rad of "
                              "theta = 0 can fly off stiff: simulate, run_ensemble and basins switch it to the "
                              "implicit step after 20,000 attempts; solve does not (use simulate, or raise "
                              "max_steps)"),
    Status.CROSSED_SINGULAR: ("a fixed RK4 step jumped across theta = 0, which the exact closed loop never "
                              "does; no result (final state and summaries NaN), the trajectory NaN after; use the "
                              "adaptive method or a smaller dt"),
    Status.STEP_UNDERFLOW: ("the adaptive step size fell below its floor (1e-18 dt) on finite steps whose error it "
                            "could not bring within the tolerances; no result: final state and summaries NaN, "
                            "the trajectory NaN after the last time reached"),
    Status.UNRELIABLE: ("a fixed RK4 step increased H_d, which the exact closed loop never does (eq. 18): "
                        "the step is too large there; no result (final state and summaries NaN), the trajectory NaN "
                        "after; use the adaptive method or a smaller dt"),
    Status.OUT_OF_RANGE: ("the start overflows the working precision: its w-chart state (~ 1/theta0^2), H_d, vector "
                          "field or effort integrand |u|^2 is too large for the dtype, because it is too close to "
                          "theta = 0 or too far from the origin (|x|, |y|, |p| so large that H_d, which grows as "
                          "their square, overflows); the warning names which; not integrated, outputs NaN; use "
                          "float64 (x64=True, --x64), a larger |theta0| or a start nearer the origin"),
    Status.NOT_SETTLING: ("certified not to settle within the horizon: it is so far from the target that the "
                          "energy H_d it has left (which never rises, eq. 18) cannot carry it into the ball |q| <= eps "
                          "in the time left; stopped early, T_eps = inf (not settled, as for a start that reaches "
                          "the horizon outside the ball), outputs NaN after the time reached"),
}

#: Codes of starts that were flagged before integration (never stepped).
NOT_INTEGRATED = (Status.SINGULAR_START, Status.INVALID_INPUT, Status.OUT_OF_RANGE)

#: Codes of runs that failed while stepping: the trajectory is not trusted from the failure on.
FAILED = (Status.NONFINITE, Status.CROSSED_SINGULAR, Status.STEP_UNDERFLOW, Status.UNRELIABLE)

#: Codes of rows without a result (`NOT_INTEGRATED` and `FAILED`): every result (`jaxsleigh.solve`,
#: `jaxsleigh.simulate`, `jaxsleigh.run_ensemble`, basins, sweeps) reports their final state, H_d and summaries
#: (``T_eps``, ``u_energy``, peaks, ...) as NaN, never the last good value nor a partial integral. A run stopped
#: early with a good state (``BUDGET_EXHAUSTED``, ``NOT_SETTLING``) is not among them: its summaries are up to the
#: time it reached, its final state NaN where the front says so.
NO_RESULT = NOT_INTEGRATED + FAILED


def describe() -> str:
    """One line per code, for ``--help`` texts and file metadata."""
    return "\n".join(f"{int(s)} = {s.name.lower()}: {DESCRIPTIONS[s]}" for s in Status)


def counts_in_words(status) -> str:
    """``'2 ok, 1 singular_start'``: how many trajectories ended with each status, by name."""
    codes, counts = np.unique(np.asarray(status, dtype=np.int64), return_counts=True)
    names = {int(s): s.name.lower() for s in Status}
    return ", ".join(f"{int(n)} {names.get(int(c), f'code {int(c)}')}" for c, n in zip(codes, counts))


def converged(status, T_eps):
    """The one definition of "converged": the trajectory reached the horizon with status OK and settled in the
    ball, ``T_eps`` finite. Arrays of any shape (a sweep's (P, N) too)."""
    return (np.asarray(status) == Status.OK) & np.isfinite(np.asarray(T_eps, np.float64))


def integrated(status):
    """Starts that were integrated (not flagged as `NOT_INTEGRATED`): the population of a fraction."""
    return ~np.isin(np.asarray(status), [int(s) for s in NOT_INTEGRATED])


def has_result(status):
    """Rows whose status is not in `NO_RESULT` (never flagged, never failed): the only rows with finite outputs.
    NumPy arrays of any shape; under ``jit`` use ``~jnp.isin(status, jnp.asarray(NO_RESULT))``."""
    return ~np.isin(np.asarray(status), [int(s) for s in NO_RESULT])


def _converged_of(result):
    t_eps = getattr(result, "T_eps", None)
    return converged(result.status, np.full(np.shape(result.status), np.nan) if t_eps is None else t_eps)


#: The results' ``converged`` property (every result class takes it as ``converged = CONVERGED``): `converged` of
#: its ``status`` and ``T_eps`` (none when no ``T_eps`` was recorded).
CONVERGED = property(_converged_of, doc="Boolean: status OK and settled within the horizon (`jaxsleigh.status.converged`).")

#: The results' ``valid`` property: `integrated` of its ``status``.
VALID = property(lambda result: integrated(result.status),
                 doc="Boolean: integrated (not on the singular set, finite start): the population of a fraction.")
