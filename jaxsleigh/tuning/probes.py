r"""Safety guards of the tuner that use the accurate engine: the integration-cost probe (a candidate whose
hardest training starts need more than ``probe_budget`` attempted steps to simulate the validation
horizon is invalid) and the final check (every training and guard start ends with status OK).

Both are guards, not the objective: the history records per iteration whether the probe was
*active* (it rejected the candidate), so a result can be shown to be shaped by the objective and its
effort budget rather than by the integrator's budget.
"""
from __future__ import annotations

import math

import numpy as np

from ..integrate.stepsize import StepSizeController
from ..model.params import Gains
from ..status import Status
from ..studies.options import RunOptions
from ..studies.ensemble import run_ensemble

__all__ = ["probe", "hardest", "check"]


def probe(g: Gains, sets, horizon: float, budget: int, x64) -> tuple:
    """Integrate every ``(starts, plant)`` of ``sets`` over ``horizon`` with the accurate engine and
    ``budget`` attempts per start. Returns ``(all OK, [attempts per start of each set])``."""
    ok, attempts = True, []
    for starts, plant in sets:
        r = run_ensemble(starts, plant=plant, gains=g, t_final=horizon, x64=x64,
                         stepsize=StepSizeController(max_steps=budget), run=RunOptions(progress=False))
        attempts.append(np.asarray(r.n_steps + r.n_rejected))
        ok = ok and bool(np.all(r.status == Status.OK))
    return ok, attempts


def hardest(sets, attempts, probe: int) -> list:
    """The ``probe`` starts that needed the most attempts, shared among the sets by size."""
    n = sum(s.shape[0] for s, _ in sets)
    out = []
    for (starts, plant), a in zip(sets, attempts):
        k = max(1, int(math.ceil(probe * starts.shape[0] / n)))
        out.append((starts[np.argsort(-a, kind="stable")[:k]], plant))
    return out


def check(g: Gains, checks, horizon: float, x64, attempts: list | None = None) -> str:
    """Empty if every start of every ``(starts, plant)`` ends with status OK after ``horizon``
    seconds of the accurate engine (default budget), else what went wrong. ``attempts``, a list, gets
    the attempted steps of every start of each set appended (to tell whether the probe's budget binds
    at the checked gains)."""
    for starts, plant in checks:
        r = run_ensemble(starts, plant=plant, gains=g, t_final=horizon, x64=x64, run=RunOptions(progress=False))
        if attempts is not None:
            attempts.append(np.asarray(r.n_steps + r.n_rejected))
        bad = r.status != Status.OK
        if np.any(bad):
            codes = ", ".join(f"{int(np.sum(r.status == c))} {Status(c).name.lower()}" for c in np.unique(r.status[bad]))
            return f"{int(bad.sum())} of {bad.size} starts failed: {codes}"
    return ""
