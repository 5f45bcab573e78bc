r"""The accuracy audit: a random sample of a result's rows re-run in float64 at tight tolerances.

Error control judges each step's local error; what a study reports (the control energy
\(E = \int_0^T \|u\|^2 dt\), \(T_\epsilon\), the final state) is a global quantity, and some laws make it
sensitive below any step's tolerance. A settled phase whose \((w_2, p_1)\) oscillation is weakly unstable
grows from an amplitude of \(10^{-9}\) to \(10^{-2}\) over tens of seconds: a run whose absolute tolerance is
\(10^{-6}\) damps the seed numerically and reports a fraction of the energy (the 0.2 release's ``balanced``
gains: a median of 7.6 against 136 in float64; ``docs/evidence/accuracy.md``). No local estimate sees an error
in a mode that is below the tolerance, so the library checks its result globally instead.

**Unresolved rows, flagged row by row.** Such a row is seen in what the run computes anyway: it ends near the
target with its settled pair weakly damped or growing and with \(|\theta(T)|\) back above its closest approach
(``result.unresolved``, `jaxsleigh.integrate.guard.grown_settled_mode`). Every such row is counted
(``unresolved_rows``) and an `jaxsleigh.errors.AccuracyWarning` names them: what they report hangs on a seed below
every tolerance, and no sample is needed to say so.

**The sample.** `audit_sample` orders the rows with ``numpy.random.default_rng(seed)``: the unresolved rows first
(most at risk), then the others, each in a seeded random order (the same rows on every run and in every process for
the same result). It takes the first \(k = \min(\text{max\_rows}, \lceil \text{fraction}\cdot N\rceil)\), then
the longest prefix of those whose estimated cost fits ``budget`` (10%) of the run's wall time \(W\). A row's cost is
estimated from the run's own steps: the run spent \(W / \sum_j n_j\) per lane-step, and a reference row of
\(n_i\) run steps costs `REFERENCE_COST` \(\cdot\, n_i\) of those (more steps at 1e-10, float64, a batch of a few
lanes; `REFERENCE_COST_FIXED` after fixed steps), so rows are kept while \(\text{REFERENCE\_COST} \sum_{i \in S} n_i \le \text{budget} \sum_j n_j\),
times `run_scale` \((N)\) above `BATCH_STARTS` starts (a large run batches its lanes better, so its lane-steps
cost less), which needs no clock and draws the same rows on any machine. It integrates them again in
float64 at ``rtol = atol = 1e-10`` (the reference; a law that float64 resolves only at a tighter \(\tau\) declares it,
``reference_tol``, and its ladder starts there, its rows counted \((10^{-10}/\tau)^{1/5}\) times dearer, `for_law`:
Aicardi's law, 1e-12), and records, over the rows that reached the horizon in both:

* ``worst_energy_rel``: \(\max |E - E_{\text{ref}}| / |E_{\text{ref}}|\) (the row's energy, relative);
* ``worst_T_eps_s``: \(\max |T_\epsilon - T_{\epsilon,\text{ref}}|\) (``inf`` where one settled and the other not);
* ``worst_state``: \(\max \|q(T) - q_{\text{ref}}(T)\|_\infty\), the final position (the final momentum of a run
  that still oscillates at the horizon hangs on the oscillation's phase, not on the accuracy of what is reported);
* ``status_mismatch``: rows whose status differs (``NOT_SETTLING`` and OK unsettled count as one answer);

and ``passed``: every figure within its threshold (`Audit`). A row off its 1e-10 reference is re-run at 1e-12 and,
if still off, at 1e-13: it is off only against a reference that converged (1e-12 and 1e-13 agree), and the record
counts the rows whose reference moved (``reference_unconverged``) or did not converge (``reference_not_converged``,
`audit_rows`). A result that fails says so: ``run_info["audit"]``, an `jaxsleigh.errors.AccuracyWarning` naming the
settings that agree, and the command line's audit line. The record also says what the audit cost (``wall_s``, and
``share_of_run``: that over the run's wall time) and how many of the unresolved rows it re-ran
(``unresolved_audited``).

**What it does not check** (``coverage``, `coverage`): the flag detects one mechanism, the grown settled mode of the
laws of the w chart; a law of the physical chart (Aicardi's, Astolfi's, Samson's, any ``u = law(q, v)``), a sampled
law and the plain fixed-step path have no per-row flag, and their rows are checked only by the sample: a 2% tail of
rows drawn at random is re-run with probability \(1 - \binom{N - m}{k} / \binom{N}{k}\) (`tail_detection`;
\(m = \lceil 0.02 N\rceil\), \(k\) the rows judged), 0 where the budget affords no row (512 starts), 95% only
from 146 rows of 4,096. The record states both, and the audit's line states the second for such a law. A budgeted
audit holds each reference row to `REFERENCE_STEPS` per step of the row in the run; a reference that runs out of
them (one that would cost a multiple of the budget's estimate) is not judged, and the record counts it
(``reference_unfinished``).
"""
from __future__ import annotations

import math
import time
import warnings
from typing import Callable, NamedTuple, Optional

import numpy as np

from ..status import Status
from ..errors import AccuracyWarning
from ..model.controller import PerTrajectory

__all__ = ["Audit", "audit_rows", "audit_sample", "audit_line", "coverage", "for_law", "resolve", "tail_detection",
           "REFERENCE_COST", "REFERENCE_COST_FIXED", "REFERENCE_STEPS", "BATCH_STARTS", "BATCH_EXPONENT", "COST",
           "run_scale", "without_cost"]

#: What an audit's record says of its cost (``wall_s``, ``share_of_run``): it varies between runs, so a result file
#: leaves it out (the rows re-run do not vary: they are chosen from the run's steps, not from a clock).
COST = ("wall_s", "share_of_run")


def without_cost(rec: Optional[dict]) -> Optional[dict]:
    """An audit's record without its cost (`COST`), as a result file keeps it; ``None`` stays ``None``."""
    return None if rec is None else {k: v for k, v in rec.items() if k not in COST}

#: the cost of a reference row (float64, rtol = atol = 1e-10, in a batch of a few lanes) per step of the adaptive run
#: it audits, in units of the run's own cost per lane-step: one row of the paper's gains over 100 s took 0.08 s
#: against 0.43 s for a 512-start run of 918 steps a row (a factor of 94; eight rows together, 28), warm, on a
#: 2-core x86_64 CPU; at 100, four rows of a 4,096-start run took 7-11% of it on that machine under a load of 7-10
#: (``experiments/studies/audit_power.py``), so 150 keeps the audit inside 10% with room. It is the paper's law's: a
#: law whose reference takes far more steps than its run would overrun it (Aicardi's law, whose float64 reference
#: takes 18,000-57,000 steps a row against the run's 740 at 1e-10, where it chatters about its goal: 2 rows of a
#: 4,096-start run took 50-59% of it, warm), so a budgeted audit holds each reference to `REFERENCE_STEPS`, and that
#: law's audit starts at 1e-12 (`for_law`), where its rows converge in 20-25 steps a run step. The laws of the
#: physical chart had also paid 0.1-0.2 s a reference call to compile the law check again (`as_controller`), now
#: compiled once: at 4,096 starts the audits of Aicardi's, Astolfi's and Samson's laws and the paper's took 7%, 7-8%,
#: 2-6% and 4-6% of their runs (``docs/evidence/accuracy.md``)
REFERENCE_COST = 150.0
#: the number of starts at which `REFERENCE_COST` was measured: up to it, the budget takes a run's wall time to be
#: linear in its lane-steps, and above it, a run of \(N\) starts to spend \((\text{BATCH\_STARTS} / N)^{\beta}\) of
#: that per lane-step (`run_scale`, \(\beta\) = `BATCH_EXPONENT`), since a large run batches its lanes better and
#: keeps both cores busy while the reference's few lanes do not: under a light load (about 1) the paper's law's run of
#: 16,384 starts took 2.0-2.4 s against 0.81 s for 4,096 (0.62-0.74 of 4 times as much; Astolfi's, under a load of
#: 1.6-5.6, 2.1-2.4 s against 0.9-0.96 s: 0.55-0.67), and the paper's law's audit of 11 rows (what an estimate linear
#: in the steps affords) took 10.4-13.6% of the run, 0.21-0.28 s, where 2 rows of 4,096 took 7.0-7.7%
#: (``docs/evidence/accuracy.md``)
BATCH_STARTS = 4096
#: \(\beta\) of `BATCH_STARTS`: \(4^{-0.4}\) = 0.57 at 16,384 starts, at the low end of the 0.55-0.74 measured there,
#: so the paper's law audits 6 rows of 16,384 README starts (11 before): 0.14-0.16 s by the cost of 2 and 11 rows
#: (about 0.022 s a call and 0.020 s a row), 6-8% of its 2.0-2.4 s under a light load; 4,096 starts and fewer are
#: unchanged (2 rows of the paper's law). Above 16,384 (one CPU chunk, `jaxsleigh.cores.CPU_CHUNK`) it is not
#: measured: a run's lane-steps cannot grow much cheaper there, so the estimate only grows more cautious
BATCH_EXPONENT = 0.4
#: the most steps a budgeted audit lets a reference row take at ``rtol = atol = 1e-10``, per step of the row in the
#: run, and \((10^{-10} / \tau)^{1/5}\) times that at a tighter \(\tau\) (an explicit step's count grows like
#: \(\tau^{-1/5}\)): the paper's law takes 2-17 (16.6 at most on 144 held-out starts, near theta = 0 and wide ones
#: included, ``docs/evidence/accuracy.md``; scratch runs on a 2-core x86_64 machine), the presets ``balanced``,
#: ``tuned``, ``shaped`` and the laws of Astolfi and Samson 1.3-19.7 (24 README and 24 wide starts each), so 35 stops
#: none of their rows, while it stops the references that would cost a multiple of what `REFERENCE_COST` assumes
#: (Aicardi's law at 1e-10, 72 a row: it chatters about its goal), which then end unfinished and are not judged
#: (``reference_unfinished``) instead of overrunning the budget
REFERENCE_STEPS = 35.0
#: the same for a run of fixed steps, whose lane-steps cost a fraction of an adaptive one's and count every base
#: step: four reference rows took 0.16 s against 0.34 s for the plain fixed-step path of 4,096 starts of 10,000
#: steps each (a factor of about 480 a row; one row costs half of four)
REFERENCE_COST_FIXED = 1000.0


class Audit(NamedTuple):
    """The audit's sample and thresholds.

    Attributes:
      fraction, max_rows: rows re-run: ``min(max_rows, ceil(fraction * N))``.
      min_starts: a result of fewer starts is not audited (its record says so), unless ``rows`` is given.
      rows: re-run exactly this many rows (at most N), whatever N.
      seed: of the draw of the rows.
      rtol, atol: the reference's tolerances (float64).
      confirm_tol: the tolerance at which a row off its reference is re-run; that run is then its reference.
      tightest_tol: the tolerance at which a row still off its ``confirm_tol`` reference is re-run: the row is off
        only where that run agrees with the ``confirm_tol`` one (a converged reference); where it agrees with the
        result, the result stands; where it agrees with neither, the row is not judged (`audit_rows`).
      energy_rel, T_eps_s, state: the thresholds of ``passed`` (relative energy, seconds, absolute state).
      budget: the audit's largest estimated cost as a share of the run's wall time (`audit_sample`); ``None``:
        no limit. ``rows`` given is re-run whatever it costs.
    """

    fraction: float = 0.01
    max_rows: int = 64
    min_starts: int = 500
    rows: Optional[int] = None
    seed: int = 0
    rtol: float = 1e-10
    atol: float = 1e-10
    confirm_tol: float = 1e-12
    energy_rel: float = 0.02
    T_eps_s: float = 0.05
    state: float = 1e-3
    budget: float | None = 0.10
    tightest_tol: float = 1e-13

    def count(self, n: int) -> int:
        """How many of ``n`` rows this audit re-runs (0: none)."""
        if self.rows is not None:
            return int(min(max(int(self.rows), 0), n))
        if n < self.min_starts:
            return 0
        return int(min(self.max_rows, math.ceil(self.fraction * n), n))


def resolve(audit) -> Optional[Audit]:
    """A front's ``audit`` argument as an `Audit` (``None`` or ``True``: the default one; ``False``: none)."""
    if audit is False:
        return None
    if audit is None or audit is True:
        return Audit()
    if isinstance(audit, Audit):
        return audit
    raise ValueError(f"audit must be True, False, None or a jaxsleigh.Audit(...), got {audit!r}")


def for_law(audit: Optional[Audit], law) -> Optional[Audit]:
    r"""``audit`` for a run of ``law`` (a `jaxsleigh.model.controller.PerTrajectory` is its law's): a law that
    declares a class attribute ``reference_tol`` \(\tau\), the loosest tolerance at which float64 resolves it,
    starts the ladder there where \(\tau\) is tighter than ``audit.rtol``: the reference at \(\tau\), a row off it
    confirmed at \(\tau / 10\) and one still off at \(\tau / 100\) (where ``confirm_tol`` and ``tightest_tol``
    are not already tighter); `audit_sample` then counts its rows \((10^{-10} / \tau)^{1/5}\) times dearer.
    Aicardi's law declares 1e-12: at 1e-10 its reference chatters about the goal (the law is discontinuous there),
    and a budgeted audit stopped it unjudged at 8-14% of a 4,096-start run; at 1e-12 the row the budget affords
    converges (``docs/evidence/accuracy.md``). What the law is decides, never a clock: the same tolerances and rows
    on any machine."""
    inner = law.law if isinstance(law, PerTrajectory) else law
    tol = getattr(type(inner), "reference_tol", None)
    if audit is None or tol is None or not float(tol) < audit.rtol:
        return audit
    tol = float(tol)
    confirm = min(audit.confirm_tol, tol / 10)
    return audit._replace(rtol=tol, atol=min(audit.atol, tol), confirm_tol=confirm,
                          tightest_tol=min(audit.tightest_tol, confirm / 10))


def _answers(status, T_eps) -> np.ndarray:
    """Statuses as answers: ``NOT_SETTLING`` (certified not to settle, `jaxsleigh.integrate.stragglers`) and OK without
    settling (``T_eps = inf``) say the same, so they compare equal."""
    st = np.array(status, np.int64)
    T = np.asarray(T_eps, np.float64)
    st[st == Status.NOT_SETTLING] = -1
    st[(st == Status.OK) & np.isinf(T)] = -1
    return st


class _Rows(NamedTuple):
    """What the audit compares of a run, one row per audited row (NumPy arrays)."""

    status: np.ndarray
    T_eps: np.ndarray
    u_energy: np.ndarray
    y: np.ndarray          # (k, 3): q_final

    @classmethod
    def of(cls, r, rows=None) -> "_Rows":
        sel = (lambda a: np.asarray(a)) if rows is None else (lambda a: np.asarray(a)[rows])  # noqa: E731
        return cls(sel(r.status).astype(np.int64),
                   *(sel(a).astype(np.float64) for a in (r.T_eps, r.u_energy, r.q_final)))

    def take(self, idx) -> "_Rows":
        return _Rows(*(a[idx] for a in self))

    def put(self, idx, other: "_Rows") -> "_Rows":
        out = _Rows(*(a.copy() for a in self))
        for a, b in zip(out, other):
            a[idx] = b
        return out


def _differences(a: _Rows, ref: _Rows) -> dict:
    """Per row: ``same`` answer (status, `_answers`), and where both reached the horizon (``both``) the energy's
    relative difference ``dE``, ``dT`` of T_eps (0 where neither settled) and ``dy``, the final position's largest.
    What a run did not measure (NaN: the plain fixed-step path has no T_eps and no energy) is not compared: its OK
    says only that it reached the horizon, which any reference that did (or was certified not to settle) agrees with."""
    both = (a.status == Status.OK) & (ref.status == Status.OK)
    unmeasured = (a.status == Status.OK) & np.isnan(a.T_eps)
    with np.errstate(invalid="ignore", divide="ignore"):
        dT = np.where(np.isinf(a.T_eps) & np.isinf(ref.T_eps) | unmeasured, 0.0, np.abs(a.T_eps - ref.T_eps))
        fin = np.isfinite(a.u_energy) & np.isfinite(ref.u_energy)
        dE = np.where(fin, np.abs(a.u_energy - ref.u_energy) / np.maximum(np.abs(ref.u_energy), 1e-300), 0.0)
        dy = np.max(np.abs(a.y - ref.y), axis=1)
    # a reference that did not finish (its budget, its step size) answers nothing: the row is not judged
    judged = np.isin(ref.status, [Status.OK, Status.NOT_SETTLING])
    same = ~judged | (_answers(a.status, a.T_eps) == _answers(ref.status, ref.T_eps)) | unmeasured
    return {"same": same, "both": both, "judged": judged,
            "dT": np.where(both, dT, 0.0), "dE": np.where(both, dE, 0.0), "dy": np.where(both, dy, 0.0)}


def _agree(d: dict, audit: "Audit") -> np.ndarray:
    return d["same"] & (d["dT"] <= audit.T_eps_s) & (d["dE"] <= audit.energy_rel) & (d["dy"] <= audit.state)


def audit_sample(audit: "Audit", n: int, *, unresolved=None, steps=None, fixed_step: bool = False) -> np.ndarray:
    r"""The rows of a result of ``n`` rows that ``audit`` re-runs, sorted (none: empty): the ``unresolved`` rows
    (bool, ``(n,)``) first, then the others, each in the seeded order of ``numpy.random.default_rng(audit.seed)``;
    the first ``audit.count(n)``, cut to the longest prefix whose estimated cost fits ``audit.budget`` of the run
    when ``steps`` (each row's steps in the run) is given and ``audit.rows`` is not (`REFERENCE_COST` times
    \((10^{-10} / \text{rtol})^{1/5}\) for a reference tighter than 1e-10, `for_law`; `REFERENCE_COST_FIXED` for a
    run of ``fixed_step`` steps; the budget times `run_scale` of ``n``). They depend on the result's rows and the
    audit only, never on a clock."""
    k = audit.count(n)
    if not k:
        return np.zeros(0, np.int64)
    rng = np.random.default_rng(audit.seed)
    if unresolved is None:
        order = rng.permutation(n)
    else:
        flag = np.asarray(unresolved, bool)
        first, rest = np.flatnonzero(flag), np.flatnonzero(~flag)
        order = np.concatenate([rng.permutation(first), rng.permutation(rest)]).astype(np.int64)
    rows = order[:k]
    if steps is not None and audit.rows is None and audit.budget is not None:
        s = np.nan_to_num(np.asarray(steps, np.float64), nan=0.0)
        s = np.maximum(s, 0.0)
        allowance = audit.budget * float(np.sum(s)) * run_scale(n)
        factor = REFERENCE_COST_FIXED if fixed_step else REFERENCE_COST * _steps_scale(audit.rtol)
        rows = rows[:int(np.searchsorted(np.cumsum(factor * s[rows]), allowance, side="right"))]
    return np.sort(rows)


def run_scale(n: int) -> float:
    r"""The run's estimated wall time per lane-step at ``n`` rows, relative to a run of `BATCH_STARTS`:
    \(\min(1, (\text{BATCH\_STARTS} / n)^{\text{BATCH\_EXPONENT}})\). A function of ``n`` alone, never of the machine."""
    return min(1.0, (BATCH_STARTS / max(int(n), 1)) ** BATCH_EXPONENT)


def _cap(audit: "Audit", steps, rows: np.ndarray, tol: float) -> dict:
    r"""``{"max_steps": m}`` for a budgeted audit's reference of ``rows`` at ``tol`` (``{}`` for an audit of
    ``rows`` asked for, without a budget or without the run's steps): \(m = \lceil\) `REFERENCE_STEPS`
    \(\cdot (10^{-10}/\tau)^{1/5} \max_{i} n_i \rceil\) over the rows' run steps \(n_i\)."""
    if steps is None or audit.rows is not None or audit.budget is None:
        return {}
    s = np.nan_to_num(np.asarray(steps, np.float64)[rows], nan=0.0)
    return {"max_steps": int(math.ceil(REFERENCE_STEPS * _steps_scale(tol) * max(float(np.max(s)), 1.0)))}


def _steps_scale(tol: float) -> float:
    r"""How many times its steps at 1e-10 an adaptive reference takes at ``tol``: \((10^{-10} / \tau)^{1/5}\), at
    least 1 (an explicit step's count grows like \(\tau^{-1/5}\))."""
    return max(1.0, (1e-10 / float(tol)) ** 0.2)


def tail_detection(n: int, k: int, share: float = 0.02) -> float:
    r"""The probability that ``k`` rows drawn at random without replacement from ``n`` hold at least one row of a
    tail of \(m = \lceil \text{share} \cdot n \rceil\) rows: \(1 - \binom{n - m}{k} / \binom{n}{k}
    = 1 - \prod_{i=0}^{k-1} \frac{n - m - i}{n - i}\) (0 for ``k = 0``)."""
    m = min(n, math.ceil(share * n - 1e-9))
    miss = 1.0
    for i in range(max(int(k), 0)):
        miss *= max(n - m - i, 0) / (n - i)
    return 1.0 - miss


def coverage(flag: Optional[str], n: int, sampled: int) -> dict:
    """What the audit of a result of ``n`` rows checks: the per-row ``flag`` (what it detects, or ``None``: the law
    has none) and the sample of ``sampled`` rows judged (their reference finished), with the probability that it
    re-runs a row of a 2% tail drawn at random (`tail_detection`; the rows the flag does not see are found only so)."""
    return {"flag": flag or "none: no per-row check of what this law reports; only the sampled rows are checked",
            "sampled_rows": int(sampled), "tail_2pct_detection": round(tail_detection(n, sampled), 4)}


def audit_rows(result, rerun: Callable[[np.ndarray, float, float], object], audit: "Audit", *,
               what: str = "result", reference: Optional[Callable[[], object]] = None,
               fixed_step: bool = False, run_wall_s: float | None = None, flag: Optional[str] = None) -> dict:
    r"""Audit ``result`` (per-row ``status``, ``T_eps``, ``u_energy``, ``q_final``, ``p_final``) against
    ``rerun(rows, rtol, atol)``, the same study of the rows ``rows`` in float64 at those tolerances. Returns the
    record (also when nothing was re-run: ``{"rows": 0, "why": ...}``) and warns when it fails.

    **The reference converges or the row is not judged.** A row off its reference at ``audit.rtol`` is re-run at
    ``audit.confirm_tol`` \(\tau_1\), and one still off that at ``audit.tightest_tol`` \(\tau_2\). With \(r_\tau\) the
    row's float64 run at \(\tau\) and \(a \approx b\) agreement within the thresholds: \(r_{\tau_1} \approx\) result or
    \(r_{\tau_2} \approx\) result: the row agrees (two computations give its figures; the looser reference was not
    converged); \(r_{\tau_1} \approx r_{\tau_2} \not\approx\) result: the row is off (a converged reference); otherwise
    the row is judged against \(r_{\tau_2}\) and counted in ``reference_not_converged``: the audit cannot confirm it
    either way, and does not pass it. Float64 at 1e-10 is itself wrong for some laws: Aicardi's law is discontinuous at
    its goal, and once the distance \(e\) to the goal is below the absolute tolerance the angle of \((x, y)\), which the
    law turns towards, is not resolved: the run chatters about the goal and spends up to \(10^{14}\) times the energy
    (at 1e-10 on most starts, at 1e-12 on some, depending on the last bits of the batch), while at 1e-13 and 1e-14
    float64 agrees with itself, with SciPy's DOP853 and with float32 at its defaults (``docs/evidence/accuracy.md``).
    ``reference_unconverged`` counts the rows whose reference moved between tolerances. A flagged row
    (``result.unresolved``) is not re-run at \(\tau_2\): it is reported as unresolved whatever its references say, and
    they hang on a seed below every tolerance.

    ``reference()``, if given, returns what ``rerun(audit_sample(audit, n), audit.rtol, audit.atol)`` returns,
    computed ahead (e.g. in a thread of its own while the run finished its last lanes). ``fixed_step``: the result
    came from fixed steps of ``dt``, which no tolerance changes, and the warning says so. ``result.unresolved`` (if
    any) are re-run first and counted, and warned about whatever the sample finds; ``run_wall_s``, the run's wall
    time, gives ``share_of_run``. ``flag``: what ``result.unresolved`` detects for this law (``None``: the law has
    no per-row check); the record's ``coverage`` (`coverage`) says so, with the probability that the sample sees a
    2% tail."""
    n = int(np.shape(result.status)[0])
    flags = getattr(result, "unresolved", None)
    flags = np.zeros(n, bool) if flags is None else np.asarray(flags, bool)
    unresolved = {"unresolved_rows": int(flags.sum())}
    if unresolved["unresolved_rows"]:
        _warn_unresolved(flags, what)
    k = audit.count(n)
    if k == 0:
        return {"rows": 0, "why": f"fewer than {audit.min_starts} starts", "how": _SMALL_RUN_PYTHON, **unresolved,
                "coverage": coverage(flag, n, 0)}
    steps = getattr(result, "n_steps", None)
    rows = audit_sample(audit, n, unresolved=flags, steps=steps, fixed_step=fixed_step)
    if rows.size == 0:
        return {"rows": 0, "why": f"no row's reference fits {audit.budget:.0%} of the run's time", **unresolved,
                "how": _SMALL_RUN_PYTHON, "wall_s": 0.0, "coverage": coverage(flag, n, 0)}
    k = int(rows.size)
    if reference is not None:               # computed ahead: its own seconds are for the caller to add, not the wait
        first = reference()
        t0 = time.perf_counter()
    else:
        t0 = time.perf_counter()
        first = rerun(rows, audit.rtol, audit.atol, **_cap(audit, steps, rows, audit.rtol))
    mine = _Rows.of(result, rows)
    ref, off, still, moved, unjudged = _ladder(mine, _Rows.of(first), rows, rerun, audit, steps, flags)
    d = _differences(mine, ref)
    worst = {k_: float(np.max(d[k_])) for k_ in ("dE", "dT", "dy")}
    rec = {"rows": k, "seed": audit.seed, "reference": f"float64, rtol = atol = {audit.rtol:g}",
           "rows_confirmed": int(off.size), "confirmed_at": f"rtol = atol = {audit.confirm_tol:g}",
           "rows_confirmed_tighter": int(still.size) if audit.tightest_tol < audit.confirm_tol else 0,
           "tightest": f"rtol = atol = {audit.tightest_tol:g}",
           "reference_unconverged": int(moved.sum()), "reference_not_converged": int(unjudged.sum()),
           "reference_unfinished": int(np.sum(~d["judged"])),
           "compared": int(d["both"].sum()),
           "status_mismatch": int(np.sum(~d["same"])), "worst_energy_rel": worst["dE"],
           "share_energy_off_5pct": float(np.mean(d["dE"][d["both"]] > 0.05)) if d["both"].any() else None,
           "worst_T_eps_s": worst["dT"], "worst_state": worst["dy"],
           "thresholds": {"energy_rel": audit.energy_rel, "T_eps_s": audit.T_eps_s, "state": audit.state},
           "wall_s": round(time.perf_counter() - t0, 3), **unresolved,
           "unresolved_audited": int(flags[rows].sum()), "coverage": coverage(flag, n, int(np.sum(d["judged"])))}
    if run_wall_s:
        rec["share_of_run"] = round(rec["wall_s"] / run_wall_s, 4)
    rec["passed"] = bool(np.all(_agree(d, audit)))
    if not rec["passed"]:
        # the tolerance of the tightest reference the failing rows were judged against
        tol = (audit.tightest_tol if rec["rows_confirmed_tighter"] else audit.confirm_tol if off.size else audit.rtol)
        fix = ("it took fixed steps of dt, which no tolerance changes: run it with the adaptive method (the default; "
               "--method adaptive) or a smaller dt" if fixed_step else
               f"run it with x64=True and StepSizeController(rtol={tol:g}, atol={tol:g}) (--x64 --rtol {tol:g} --atol "
               f"{tol:g})")
        warnings.warn(f"the accuracy audit of this {what} failed: {audit_line(rec)}. What it reports is not what "
                      f"float64 gives for this law at these settings; {fix}, or trust only what the audit confirms",
                      AccuracyWarning, stacklevel=3)
    return rec


def _ladder(mine: "_Rows", ref: "_Rows", rows: np.ndarray, rerun, audit: "Audit", steps, flags: np.ndarray):
    """The audit's ladder of references (`audit_rows`): the rows of ``mine`` off their first reference ``ref`` re-run
    at ``audit.confirm_tol``, and those still off it at ``audit.tightest_tol``. Returns ``(ref, off, still, moved,
    unjudged)``: each row's tightest finished reference, the rows off the first one, those re-run at the tightest
    tolerance, those whose reference moved between tolerances, and those whose two tightest references disagree with
    each other and with the result (not judged)."""
    k = rows.size
    finished = (Status.OK, Status.NOT_SETTLING)
    off = np.where(~_agree(_differences(mine, ref), audit))[0]
    moved = np.zeros(k, bool)                       # the reference changed between tolerances
    unjudged = np.zeros(k, bool)                    # two tightest references disagree, and with the result
    still = np.zeros(0, np.int64)
    if off.size:
        tight = _Rows.of(rerun(rows[off], audit.confirm_tol, audit.confirm_tol,
                               **_cap(audit, steps, rows[off], audit.confirm_tol)))
        done = np.isin(tight.status, finished)
        moved[off] = ~_agree(_differences(ref.take(off), tight), audit) & done
        ref = ref.put(off[done], tight.take(done))
        # a flagged row's figures hang on a seed below every tolerance: a tighter reference would not settle them
        still = off[done & ~_agree(_differences(mine.take(off), tight), audit) & ~flags[rows[off]]]
        if still.size and audit.tightest_tol < audit.confirm_tol:
            tighter = _Rows.of(rerun(rows[still], audit.tightest_tol, audit.tightest_tol,
                                     **_cap(audit, steps, rows[still], audit.tightest_tol)))
            done = np.isin(tighter.status, finished)
            converged = _agree(_differences(ref.take(still), tighter), audit)
            agrees = _agree(_differences(mine.take(still), tighter), audit)
            moved[still] |= ~converged & done
            unjudged[still] = done & ~converged & ~agrees
            ref = ref.put(still[done], tighter.take(done))
    return ref, off, still, moved, unjudged


def _warn_unresolved(flags: np.ndarray, what: str) -> None:
    rows = np.flatnonzero(flags)
    shown = ", ".join(str(int(i)) for i in rows[:8]) + (", ..." if rows.size > 8 else "")
    warnings.warn(f"{rows.size} of {flags.size} rows of this {what} are unresolved (rows {shown}; result.unresolved): "
                  f"their settled oscillation grew back out near the target and is weakly damped or growing at the "
                  f"horizon, so their control energy (and final state) hangs on the oscillation's seed, which is "
                  f"below every tolerance; float64 at tight tolerances can disagree with itself there. Report these "
                  f"rows apart, or judge the law on a shorter horizon", AccuracyWarning, stacklevel=4)


#: How Python audits a run too small for the default audit (``run_info["audit"]["how"]`` of such a run).
_SMALL_RUN_PYTHON = "run=jaxsleigh.RunOptions(audit=jaxsleigh.Audit(rows=k)) audits a small run"


def audit_line(rec: Optional[dict], *, flag: Optional[str] = None) -> str:
    """One line: what the audit found (or why it did not run, and how to audit a small run anyway). ``flag`` (the
    command line's ``"--audit-rows"``) words that advice as the flag; without it, as Python's ``RunOptions``."""
    if not rec:
        return "accuracy audit: not run"
    if not rec.get("rows"):
        why = rec.get("why", "no rows")
        how = rec.get("how")
        if how and flag is not None:
            how = f"{flag} K audits a small run"
        elif how is None and flag is not None and "RunOptions(" in why:   # a record written before "how" existed
            why, how = why.split(" (", 1)[0], f"{flag} K audits a small run"
        return (f"accuracy audit: not run ({why}{'; ' + how if how else ''}){_unresolved_words(rec)}"
                + _coverage_words(rec))
    f = lambda v, fmt: "n/a" if v is None else format(v, fmt)  # noqa: E731
    again = (f", {rec['rows_confirmed']} re-run at {rec['confirmed_at']}" if rec.get("rows_confirmed") else "")
    if rec.get("rows_confirmed_tighter"):
        again += f", {rec['rows_confirmed_tighter']} at {rec['tightest']}"
    unjudged = (f"; {rec['reference_not_converged']} rows off a reference that did not converge ("
                f"{rec['confirmed_at']} and {rec['tightest']} disagree)" if rec.get("reference_not_converged") else "")
    judged = rec["rows"] - rec.get("reference_unfinished", 0)
    verdict = "FAILED" if not rec["passed"] else "passed" if judged else "no row judged"
    if rec.get("reference_unfinished"):
        unjudged += f"; {rec['reference_unfinished']} rows not judged (their reference did not finish in its steps)"
    return (f"accuracy audit ({rec['rows']} rows against {rec['reference']}{again}): "
            f"{verdict}; worst energy {f(rec['worst_energy_rel'], '.2%')}, "
            f"worst T_eps {f(rec['worst_T_eps_s'], '.2g')} s, worst final position {f(rec['worst_state'], '.2g')}, "
            f"status mismatches {rec['status_mismatch']}"
            + (f"; cost {rec['wall_s']:.2g} s ({rec['share_of_run']:.1%} of the run)" if "share_of_run" in rec else "")
            + unjudged + _unresolved_words(rec) + _coverage_words(rec))


def _coverage_words(rec: dict) -> str:
    """What a record of a law without a per-row flag does not check (nothing for a law with one, or an old record)."""
    cov = rec.get("coverage")
    if not cov or not str(cov.get("flag", "")).startswith("none"):
        return ""
    return (f"; no per-row flag for this law: a 2% tail of off rows is re-run with probability "
            f"{cov['tail_2pct_detection']:.0%} ({cov['sampled_rows']} sampled rows)")


def _unresolved_words(rec: dict) -> str:
    u = rec.get("unresolved_rows")
    if not u:
        return ""
    return (f"; {u} rows unresolved (settled oscillation grew: result.unresolved"
            + (f", {rec['unresolved_audited']} of them re-run" if "unresolved_audited" in rec else "") + ")")
