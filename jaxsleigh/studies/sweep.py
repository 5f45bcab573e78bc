r"""Parameter sweeps: convergence over gains and plants, as one vectorised, checkpointed ensemble.

A sweep runs the product of a set of starts (a grid, Monte-Carlo samples or an array, as
`run_basin` takes them) and a set of parameter values. Because gains and
plant parameters are pytree leaves that may carry a per-trajectory axis (`jaxsleigh.model.lanes`),
the ``P`` values x ``N`` starts are just ``P * N`` rows of **one** call of
`run_ensemble`: chunked (memory bounded by the chunk), checkpointed,
resumable, sharded over devices, compiled once (changing the values never recompiles).

Rows are ordered value-major: row ``p * N + i`` is start ``i`` under value set ``p``, so the
per-start results reshape to ``(P, N)``. Per value the sweep summarises the fraction of valid
starts that converged (+- its binomial standard error), the ``T_eps`` percentiles of the converged
starts, the statuses (failures by kind) and the control effort of the converged starts (median
control energy \(\int_0^T \|u\|^2 dt\) and median peak \(\|u\|\)).

Parameters (``NAME`` of ``--param NAME=LO:HI:P[:log]``):

* gains: ``k``, ``l1``, ``l2``, ``l3`` (the diagonal of ``L``), ``d11``, ``d22``, ``d12`` (entries
  of the symmetric ``D_hat``);
* plant: ``m``, ``J``, ``l`` (``l = 0`` is the knife edge);
* damping: ``coulomb_eps``, ``coulomb_scale`` (with Coulomb damping), ``c1``, ``c2`` (viscous).

One parameter gives a line of ``P`` values, two give a ``P1 x P2`` grid (the first one slowest).
`sweep` also takes explicit value sets (``{"m": [...], "J": [...]}``, zipped, not
crossed): sampled plants, as in ``experiments/studies/robustness.py``.
"""
from __future__ import annotations

import itertools
import math
from pathlib import Path
from typing import Any, Mapping, NamedTuple, Optional, Sequence

import jax
import numpy as np

from .basin import PERCENTILES, BasinStarts, array_starts, fraction_converged, starts_from_spec, t_eps_percentiles
from ..model.damping import CoulombDamping, ViscousDamping, damping_from_name
from ..model.params import Gains, PlantParams, as_gains, as_plant, gains_to_dict
from ..status import CONVERGED, VALID, Status
from ..validate import check_memory
from .config import plant_to_dict, reject_traced
from .options import RunOptions, SaveAt, study_options, takes_objects
from ..integrate.stepsize import StepSizeController
from .ensemble import run_ensemble_resolved, summary_repr
from ..files.npz import parse_number, read_result, write_result
from ..model.controller import PerTrajectory, as_controller, controller_record, law_leaf_names
from ..model.lanes import broadcast_lanes, check_lanes, take_lanes

__all__ = ["PARAM_NAMES", "ParamAxis", "parse_param", "param_grid", "check_rows", "apply_params", "SweepResult", "sweep",
           "save_sweep", "load_sweep"]

#: Sweepable parameters: name -> (where it lives, condition, what it must be).
PARAM_NAMES = {
    "k": ("gains.k", lambda v: v > 0, "> 0"),
    "l1": ("gains.L", lambda v: v > 0, "> 0"),
    "l2": ("gains.L", lambda v: v > 0, "> 0"),
    "l3": ("gains.L", lambda v: v > 0, "> 0"),
    "d11": ("gains.D_hat", lambda v: v > 0, "> 0"),
    "d22": ("gains.D_hat", lambda v: v > 0, "> 0"),
    "d12": ("gains.D_hat", lambda v: np.isfinite(v), "finite (and D_hat positive definite)"),
    "m": ("plant.m", lambda v: v > 0, "> 0"),
    "J": ("plant.J", lambda v: v >= 0, ">= 0"),
    "l": ("plant.l", lambda v: v >= 0, ">= 0 (0 is the knife edge)"),
    "coulomb_eps": ("plant.damping.eps", lambda v: v > 0, "> 0"),
    "coulomb_scale": ("plant.damping.scale", lambda v: v >= 0, ">= 0"),
    "c1": ("plant.damping.c1", lambda v: v >= 0, ">= 0"),
    "c2": ("plant.damping.c2", lambda v: v >= 0, ">= 0"),
}
_EXAMPLE = "--param k=0.01:1:9:log"
#: Host memory one parameter value needs before any start runs: the value and its per-lane plant and gains.
BYTES_PER_VALUE = 256
#: Host memory one row (a start under a value set) needs: the run's per-start share and the row's lanes.
BYTES_PER_ROW = 560
_FEWER = "use fewer values (a smaller P in NAME=LO:HI:P) or split the sweep into several runs"


class ParamAxis(NamedTuple):
    """``n`` values of parameter ``name`` from ``lo`` to ``hi`` (both included), evenly spaced, or
    log-spaced when ``log``."""

    name: str
    lo: float
    hi: float
    n: int
    log: bool = False

    def values(self) -> np.ndarray:
        if self.n == 1:
            return np.array([self.lo])
        return np.geomspace(self.lo, self.hi, self.n) if self.log else np.linspace(self.lo, self.hi, self.n)

    def spec(self) -> str:
        return f"{self.name}={self.lo:g}:{self.hi:g}:{self.n}" + (":log" if self.log else "")


def _check_name(name: str, flag: str, law_names: Sequence[str] = ()) -> None:
    if name not in PARAM_NAMES and name not in law_names:
        extra = f", or of the controller: {', '.join(law_names)}" if law_names else ""
        raise ValueError(f"{flag}: unknown parameter {name!r}; choose one of {', '.join(PARAM_NAMES)}{extra} "
                         f"(e.g. {_EXAMPLE})")


def _check_values(name: str, values: np.ndarray, label: str) -> None:
    """Every value of ``name`` admissible, else a ValueError naming ``label`` (the --param). A parameter of
    a user's law needs only be finite (the law is checked on its first value set)."""
    v = np.asarray(values, np.float64)
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{label}: every value of {name} must be finite, got {v[~np.isfinite(v)][0]}")
    if name not in PARAM_NAMES:
        return
    _, cond, need = PARAM_NAMES[name]
    bad = ~cond(v)
    if np.any(bad):
        raise ValueError(f"{label}: {name} must be {need}, but the range includes {name} = {v[bad][0]:g} "
                         f"({int(bad.sum())} of {v.size} values); change the range")


def parse_param(spec, flag: str = "--param", law_names: Sequence[str] = ()) -> ParamAxis:
    """A `ParamAxis` from ``"NAME=LO:HI:P[:log]"`` (or ``"NAME=VALUE"``), or a ParamAxis.

    ``NAME`` is one of `PARAM_NAMES` or, sweeping a user's law, one of its scalar parameters
    (``law_names``). Values may use ``pi``. The values are checked eagerly: a range that includes an inadmissible
    value (``m <= 0``, ``k <= 0``, ``J < 0``, ...) raises ``ValueError`` naming the ``--param``.
    """
    if isinstance(spec, ParamAxis):
        ax, label = spec, f"{flag} {spec.spec()}"
    else:
        text = str(spec)
        label = f"{flag} {text}"
        hint = f"write NAME=LO:HI:P or NAME=LO:HI:P:log (e.g. {_EXAMPLE})"
        if "=" not in text:
            raise ValueError(f"could not parse {label}: no '='; {hint}")
        name, rng = (s.strip() for s in text.split("=", 1))
        _check_name(name, label, law_names)
        parts = rng.split(":")
        log = False
        if parts and parts[-1].strip().lower() in ("log", "lin", "linear"):
            log = parts.pop().strip().lower() == "log"
        try:
            vals = [parse_number(s) for s in parts]
        except ValueError as e:
            raise ValueError(f"could not parse {label}: {e}; {hint}") from None
        if len(vals) == 1:
            ax = ParamAxis(name, vals[0], vals[0], 1, log)
        elif len(vals) == 3:
            if not math.isfinite(vals[2]) or float(vals[2]) != int(vals[2]) or vals[2] < 2:
                raise ValueError(f"{label}: P = {vals[2]:g} must be a whole number of values >= 2; {hint}")
            ax = ParamAxis(name, vals[0], vals[1], int(vals[2]), log)
        else:
            raise ValueError(f"could not parse {label}: got {len(vals)} number(s); {hint}")
    _check_name(ax.name, label, law_names)
    if not (math.isfinite(ax.lo) and math.isfinite(ax.hi)):
        raise ValueError(f"{label}: the bounds must be finite")
    if ax.n > 1 and not ax.lo < ax.hi:
        raise ValueError(f"{label}: LO must be below HI (e.g. {flag} {ax.name}={min(ax.lo, ax.hi):g}:"
                         f"{max(ax.lo, ax.hi):g}:{ax.n})")
    if ax.log and not ax.lo > 0:
        raise ValueError(f"{label}: a log range needs LO > 0, got {ax.lo:g}; use a linear range to include 0")
    # the count comes from the user: refuse it before a single value is materialised
    check_memory(ax.n, label, bytes_per_start=BYTES_PER_VALUE, unit="values", fix=_FEWER)
    _check_values(ax.name, ax.values(), label)
    return ax


def param_grid(axes: Sequence, law_names: Sequence[str] = ()) -> tuple[tuple, np.ndarray, tuple]:
    """``(names, values (P, n_params), grid_shape)`` of the product of the axes (first slowest)."""
    axes = [parse_param(a, law_names=law_names) for a in axes]
    if not axes:
        raise ValueError(f"a sweep needs at least one parameter (e.g. {_EXAMPLE})")
    names = tuple(a.name for a in axes)
    if len(set(names)) != len(names):
        raise ValueError(f"each parameter may be swept once, got {', '.join(names)}")
    # the product of the counts, before itertools.product builds it
    check_memory(math.prod(a.n for a in axes), " x ".join(f"--param {a.spec()}" for a in axes),
                 bytes_per_start=BYTES_PER_VALUE, unit="value sets", fix=_FEWER)
    values = np.array(list(itertools.product(*(a.values() for a in axes))), np.float64).reshape(-1, len(axes))
    return names, values, tuple(a.n for a in axes)


def check_rows(n_values: int, n_starts: int, what: str = "sweep") -> None:
    """Refuse, before anything is built, a sweep whose ``n_values x n_starts`` rows would not fit in
    host memory (`check_memory`); the message names both counts and the memory."""
    check_memory(int(n_values) * int(n_starts), what, bytes_per_start=BYTES_PER_ROW,
                 unit=f"rows ({int(n_values):,} values x {int(n_starts):,} starts)",
                 fix="use fewer values (a smaller P in --param NAME=LO:HI:P) or fewer starts (fewer --samples, "
                     "a coarser grid, a smaller --ics file), or split the sweep into several runs")


def apply_params(names: Sequence[str], values, plant: Optional[PlantParams] = None, gains: Any = None, *,
                 labels: Optional[Mapping[str, str]] = None, controller: Any = None) -> tuple[PlantParams, Any]:
    """Per-lane ``(plant, gains)`` with ``P`` lanes: the base ``plant`` / ``gains`` (the paper's by
    default) with parameter ``names[j]`` set to ``values[:, j]``; validated, every lane at once
    (``labels``: name -> text naming it in messages, e.g. its ``--param``). With ``controller`` (a user's
    law, `jaxsleigh.model.controller`) the second item is that law per lane
    (`jaxsleigh.model.controller.PerTrajectory`): names that are not plant parameters set its scalar
    parameters."""
    names = tuple(names)
    values = _value_table(names, values)
    labels = dict(labels or {})
    lab = lambda n: labels.get(n, f"parameter {n}")  # noqa: E731
    law_names = _law_scalar_names(controller) if controller is not None else ()
    for j, n in enumerate(names):
        _check_name(n, lab(n), law_names)
        _check_values(n, values[:, j], lab(n))
    if controller is not None:
        return _apply_law_params(names, values, as_plant(plant), controller, lab)
    plant, gains = as_plant(plant), as_gains(gains)
    P = values.shape[0]
    col = {n: values[:, j] for j, n in enumerate(names)}
    rep = lambda x: np.repeat(np.asarray(x, np.float64)[..., None], P, axis=-1)  # noqa: E731
    m, J, l = (col.get(f, rep(getattr(plant, f))) for f in ("m", "J", "l"))
    flags = {"plant.m": lab("m"), "plant.J": lab("J") if "J" in col else lab("l") if "l" in col else "plant.J",
             "gains.D_hat": " / ".join(lab(n) for n in ("d11", "d22", "d12") if n in col) or "gains.D_hat"}
    return check_lanes(PlantParams(m, J, l, _lane_damping(plant.damping, col, rep, lab)),
                       _lane_gains(gains, col, rep), flags=flags)


def _value_table(names: tuple, values) -> np.ndarray:
    """``values`` as a float64 ``(P, len(names))`` table (one column for a 1-D ``values``), checked."""
    values = np.asarray(values, np.float64)
    if values.ndim == 1:
        values = values[:, None]
    if values.ndim != 2 or values.shape[1] != len(names) or values.shape[0] == 0:
        raise ValueError(f"values must have shape (P, {len(names)}) for the parameters {names}, got {values.shape}")
    return values


def _lane_damping(d, col: dict, rep, lab):
    """The plant's damping model with the swept columns ``col`` of its numbers put in (the rest repeated per
    lane by ``rep``); a number of the other damping family is refused, naming the flag that switches."""
    if isinstance(d, str):
        d = damping_from_name(d)
    for n, kind in (("coulomb_eps", CoulombDamping), ("coulomb_scale", CoulombDamping),
                    ("c1", ViscousDamping), ("c2", ViscousDamping)):
        if n in col and not isinstance(d, kind):
            fam = "coulomb" if kind is CoulombDamping else "viscous"
            raise ValueError(f"{lab(n)}: {n} is a parameter of {fam} damping, but the plant's damping is "
                             f"{type(d).__name__}; add --damping {fam}")
    if hasattr(d, "_fields"):
        names_d = {"eps": "coulomb_eps", "scale": "coulomb_scale", "c1": "c1", "c2": "c2"}
        d = type(d)(*(col.get(names_d[f], rep(getattr(d, f))) for f in d._fields))
    return d


def _lane_gains(gains: Gains, col: dict, rep) -> Gains:
    """The paper's gains with the swept columns ``col`` put in (``l1..l3``: L's diagonal; ``d11``, ``d22``,
    ``d12``: D_hat's entries, ``d12`` on both sides), the rest repeated per lane by ``rep``."""
    L = rep(gains.L)
    for i, n in enumerate(("l1", "l2", "l3")):
        if n in col:
            L[i] = col[n]
    D = rep(np.asarray(gains.D_hat, np.float64))
    if "d11" in col:
        D[0, 0] = col["d11"]
    if "d22" in col:
        D[1, 1] = col["d22"]
    if "d12" in col:
        D[0, 1] = D[1, 0] = col["d12"]
    return Gains(L, col.get("k", rep(gains.k)), D)


def _law_scalar_names(law) -> tuple:
    """The names of a user's law's scalar parameters (what a sweep may set)."""
    return tuple(n for n, v in law_leaf_names(law).items() if np.ndim(v) == 0)


_GAIN_PARAMS = ("k", "l1", "l2", "l3", "d11", "d12", "d22")


def _apply_law_params(names, values, plant: PlantParams, law, lab) -> tuple[PlantParams, Any]:
    """`apply_params` for a user's law: the plant's parameters (as for the paper's law) and the law's scalar
    parameters, per lane."""
    law_names = _law_scalar_names(law)
    gain = [n for n in names if n in _GAIN_PARAMS and n not in law_names]
    if gain:
        raise ValueError(f"{lab(gain[0])}: {gain[0]} is a gain of the paper's law; with a controller of your own a "
                         f"sweep sets the plant's parameters and the controller's "
                         f"({', '.join(_law_scalar_names(law))})")
    P = values.shape[0]
    plant_idx = [j for j, n in enumerate(names) if n in PARAM_NAMES and n not in _GAIN_PARAMS]
    if plant_idx:                  # the plant's lanes exactly as under the paper's law
        plant, _ = apply_params([names[j] for j in plant_idx], values[:, plant_idx], plant, None,
                                labels={names[j]: lab(names[j]) for j in plant_idx})
    col = {n: values[:, j] for j, n in enumerate(names) if j not in plant_idx}
    leaves, tree = jax.tree_util.tree_flatten(law)
    lanes = [col[n] if n in col else np.repeat(np.asarray(x, np.float64)[..., None], P, axis=-1)
             for n, x in zip(law_leaf_names(law), leaves)]
    return check_lanes(plant, PerTrajectory(jax.tree_util.tree_unflatten(tree, lanes)))


# ---------------------------------------------------------------------------------------------
# result
# ---------------------------------------------------------------------------------------------

class SweepResult(NamedTuple):
    """Per value set and start (arrays ``(P, N)``), per value set (``(P,)``), the starts, the settings.

    Attributes:
      names: the swept parameters; values: ``(P, n_params)`` their values per value set.
      grid_shape: ``(P,)``, ``(P1, P2)`` for a two-parameter grid (first parameter slowest), or
        ``(P,)`` for explicit value sets; axes: the `ParamAxis` of a grid (``()`` otherwise).
      starts: the `BasinStarts`; ics: ``(N, 5)``.
      T_eps, status, n_steps, min_abs_theta, Hd0: ``(P, N)`` per-row results.
      q_final ``(P, N, 3)``, p_final ``(P, N, 2)``, Hd_final, n_rejected ``(P, N)``: each row's final state, its
        closed-loop energy there and its rejected steps, as in `jaxsleigh.EnsembleResult` (``None`` in a file
        written before they were saved).
      u_energy, u_abs_int, u_norm_peak: ``(P, N)`` control effort (as in `jaxsleigh.EnsembleResult`;
        ``None`` when not recorded); `effort` gathers them in a dict and `effort_medians` summarises
        them per value set.
      settings: base plant and gains, the sweep, the starts, the solver settings.
      run_info: wall time, devices, chunks reused (not saved: they vary between runs).
      unresolved: ``(P, N)`` bool, the rows whose settled oscillation grew (as in `jaxsleigh.EnsembleResult`;
        ``None`` in a file written before it was saved).
    """

    names: tuple
    values: np.ndarray
    grid_shape: tuple
    axes: tuple
    starts: BasinStarts
    ics: np.ndarray
    T_eps: np.ndarray
    status: np.ndarray
    n_steps: np.ndarray
    min_abs_theta: np.ndarray
    Hd0: np.ndarray
    settings: dict
    run_info: Optional[dict] = None
    u_energy: Optional[np.ndarray] = None
    u_abs_int: Optional[np.ndarray] = None
    u_norm_peak: Optional[np.ndarray] = None
    q_final: Optional[np.ndarray] = None
    p_final: Optional[np.ndarray] = None
    Hd_final: Optional[np.ndarray] = None
    n_rejected: Optional[np.ndarray] = None
    unresolved: np.ndarray | None = None

    @property
    def effort(self) -> dict:
        """``{name: (P, N)}`` of the control-effort fields that were recorded."""
        return {k: getattr(self, k) for k in ("u_energy", "u_abs_int", "u_norm_peak") if getattr(self, k) is not None}

    valid = VALID
    converged = CONVERGED

    def fractions(self) -> tuple[np.ndarray, np.ndarray]:
        """``(fraction (P,), fraction_se (P,))`` of the valid starts that converged, per value set."""
        out = np.array([fraction_converged(c, v) for c, v in zip(self.converged, self.valid)], np.float64)
        return out[:, 0], out[:, 1]

    @property
    def fraction(self) -> np.ndarray:
        return self.fractions()[0]

    @property
    def fraction_se(self) -> np.ndarray:
        return self.fractions()[1]

    def percentiles(self, q: Sequence[float] = PERCENTILES) -> np.ndarray:
        """``(P, len(q))`` percentiles of ``T_eps`` of the converged starts (NaN where none converged)."""
        return np.array([t_eps_percentiles(t[c], q) for t, c in zip(self.T_eps, self.converged)])

    def effort_medians(self) -> dict:
        """Per value set, the medians over the **converged** starts of the control effort:
        ``{"u_energy_median": (P,), "u_norm_peak_median": (P,)}`` (control energy
        \\(\\int_0^T \\|u\\|^2 dt\\) up to the horizon, largest \\(\\|u\\|\\)); NaN where none
        converged or the effort was not recorded; ``{}`` when the run recorded no effort."""
        out = {}
        for k in EFFORT_MEDIANS:
            if k in self.effort:
                out[f"{k}_median"] = _medians(self.effort[k], self.converged)
        return out

    def status_counts(self) -> tuple[np.ndarray, np.ndarray]:
        """``(codes (K,), counts (P, K))``: how many starts of each value set ended with each status."""
        codes = np.array(sorted(int(s) for s in Status), np.int32)
        return codes, (self.status[..., None] == codes).sum(axis=1).astype(np.int64)

    def __repr__(self) -> str:
        # a summary, not every (P, N) array (see `table` for one line per value set)
        P, N = np.shape(self.status)[:2] if np.ndim(self.status) == 2 else (len(self.values), 0)
        S = self.fraction
        ranges = ", ".join(f"{n} {np.nanmin(self.values[:, i]):.4g}..{np.nanmax(self.values[:, i]):.4g}"
                           for i, n in enumerate(self.names)) if np.size(self.values) else "none"
        fr = (f"fraction converged per value set: min {np.nanmin(S):.4f}, max {np.nanmax(S):.4f}"
              if np.isfinite(S).any() else "fraction converged per value set: no valid starts")
        return summary_repr("SweepResult", self, status=self.status, T_eps=self.T_eps, Hd0=self.Hd0,
                            u_energy=self.effort.get("u_energy"),
                            head=f" rows = {P} value sets x {N} starts; swept {ranges}", extra=(fr,))

    def table(self) -> str:
        """One line per value set: the values, fraction +- s.e., median T_eps, failures (valid starts
        that did not reach the horizon, budget-exhausted ones included) and (when recorded) the median
        control energy of the converged starts; a last line says what "failed" counts."""
        S, se = self.fractions()
        med = self.percentiles((50.0,))[:, 0]
        eff = self.effort_medians()
        energy = eff.get("u_energy_median")
        head = "   fraction +- s.e.   median T_eps   failed" + ("   median int|u|^2" if energy is not None else "")
        lines = [" ".join(f"{n:>10}" for n in self.names) + head]
        failed = (self.valid & (self.status != Status.OK) & (self.status != Status.NOT_SETTLING)).sum(axis=1)
        for p in range(self.values.shape[0]):
            vals = " ".join(f"{v:10.4g}" for v in self.values[p])
            line = f"{vals}   {S[p]:.3f} +- {se[p]:.3f}      {med[p]:9.3g}      {failed[p]:6d}"
            if energy is not None:
                line += f"   {energy[p]:16.4g}"
            lines.append(line)
        lines.append("failed: starts that did not reach the horizon, including those whose adaptive step budget "
                     "ran out (BUDGET_EXHAUSTED: raise max_steps / --max-steps), not those certified not to settle "
                     "(NOT_SETTLING, unsettled); see the status counts")
        return "\n".join(lines)


#: each row's end, saved with the sweep (absent from files written before they were)
FINAL_FIELDS = ("q_final", "p_final", "Hd_final", "n_rejected", "unresolved")

#: effort summaries whose per-value medians (over the converged starts) a sweep reports
EFFORT_MEDIANS = ("u_energy", "u_norm_peak")


def _medians(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Row-wise median of the finite ``values`` where ``mask`` (NaN for a row with none)."""
    v = np.asarray(values, np.float64)
    out = np.full(v.shape[0], np.nan)
    for p in range(v.shape[0]):
        x = v[p][mask[p] & np.isfinite(v[p])]
        if x.size:
            out[p] = np.median(x)
    return out


def _as_starts(starts) -> BasinStarts:
    return starts if isinstance(starts, BasinStarts) else array_starts(starts)


def _resolve_controller(controller, gains) -> tuple[Any, tuple]:
    """A user's law as a controller and the names of its scalar parameters (``(None, ())`` for the paper's law);
    refuses ``gains`` and ``controller`` together."""
    if controller is None:
        return None, ()

    if gains is not None:
        raise ValueError("give either gains (the paper's law) or controller (any law u = law(q, v)), not both")
    controller = as_controller(controller)
    return controller, _law_scalar_names(controller)


def _value_sets(params, n_starts: int, law_names: Sequence[str], labels: Optional[Mapping[str, str]]) -> tuple:
    """``(names, values (P, n_params), grid_shape, axes, labels)`` of ``params`` (explicit value sets or one or two
    ranges), refusing more rows than host memory holds; ranges add their ``--param`` to ``labels``."""
    if isinstance(params, Mapping):
        names = tuple(params)
        cols = [np.atleast_1d(np.asarray(params[n], np.float64)) for n in names]
        if not names or len({c.shape for c in cols}) != 1 or cols[0].ndim != 1:
            raise ValueError("explicit value sets must be a non-empty mapping of equal-length 1-D arrays")
        check_rows(cols[0].size, n_starts)
        return names, np.stack(cols, axis=1), (cols[0].size,), (), labels
    if isinstance(params, (str, ParamAxis)):
        params = [params]
    axes = tuple(parse_param(a, law_names=law_names) for a in params)
    if len(axes) > 2:
        raise ValueError("a sweep grid takes one or two parameters; pass explicit value sets for more")
    check_rows(math.prod(a.n for a in axes), n_starts)
    names, values, shape = param_grid(axes, law_names)
    labels = {a.name: f"--param {a.spec()}" for a in axes} | dict(labels or {})
    return names, values, shape, axes, labels


def _row_lanes(names, values: np.ndarray, plant, gains, controller, labels, n_starts: int) -> tuple:
    """``(base_plant, base_gains, plant, law)``: the base values and the per-row lanes of the plant and of the gains
    (or the user's law), row ``p * N + i`` under value set ``p``."""
    base_plant, base_gains = as_plant(plant), (as_gains(gains) if controller is None else None)
    lane_plant, lane_gains = apply_params(names, values, base_plant, base_gains, labels=labels, controller=controller)
    P = values.shape[0]
    rows = np.repeat(np.arange(P), n_starts)               # row p * N + i: start i, value set p
    lp, lg = take_lanes(broadcast_lanes(lane_plant, lane_gains, P), rows)
    return base_plant, base_gains, lp, lg


def _sweep_settings(run_settings: Mapping, controller, base_plant, base_gains, st: BasinStarts, names, axes,
                    P: int, N: int) -> dict:
    """The sweep's settings: the run's (less its per-lane plant and gains), the controller, the base plant and
    gains, the starts and what was swept."""
    settings = {k: v for k, v in run_settings.items() if k not in ("save_every", "plant", "gains")}
    if controller is not None:
        settings["controller"] = controller_record(controller)
    settings.update(plant=plant_to_dict(base_plant),
                    gains=gains_to_dict(base_gains) if controller is None else None, starts=st.spec,
                    sweep={"names": list(names), "axes": [a.spec() for a in axes], "n_values": P, "n_starts": N})
    return settings


def _sweep_result(res, names, values: np.ndarray, shape, axes, st: BasinStarts, settings: dict) -> SweepResult:
    """The `SweepResult` of the ensemble ``res`` of ``P * N`` rows: its per-row results reshaped to ``(P, N)``."""
    P, N = values.shape[0], st.ics.shape[0]
    run_info = dict(res.run_info)
    per = lambda a: np.asarray(a).reshape((P, N) + np.shape(a)[1:])  # noqa: E731
    effort = {k: per(getattr(res, k)) for k in ("u_energy", "u_abs_int", "u_norm_peak")
              if getattr(res, k, None) is not None}
    return SweepResult(names=names, values=values, grid_shape=tuple(shape), axes=axes, starts=st,
                       ics=res.ics[:N], T_eps=per(res.T_eps), status=per(res.status), n_steps=per(res.n_steps),
                       min_abs_theta=per(res.min_abs_theta), Hd0=per(res.Hd0), **effort, settings=settings,
                       run_info=run_info, q_final=per(res.q_final), p_final=per(res.p_final),
                       Hd_final=per(res.Hd_final), n_rejected=per(res.n_rejected),
                       unresolved=None if res.unresolved is None else per(res.unresolved))


def _sweep(starts, params, *, plant: Optional[PlantParams], gains: Any, controller: Any, t_final: float,
           dt: float, eps: float, x64: bool, labels: Optional[Mapping[str, str]], stepsize: StepSizeController,
           run: RunOptions) -> Optional[SweepResult]:
    r"""`sweep` (see there) with its option objects checked (`study_options`): run every start under
    every parameter value set, as one ensemble of ``P * N`` rows, and summarise per value set. ``labels``:
    parameter name -> text naming it in error messages (the CLI passes its ``--param``). ``run.chunk_size``
    counts rows (default as `run_basin`). Returns a `SweepResult` (``None`` with ``run.shard``)."""
    reject_traced("sweep", **locals())    # first: a NumPy front, neither jittable nor differentiable

    st = _as_starts(starts)
    controller, law_names = _resolve_controller(controller, gains)
    names, values, shape, axes, labels = _value_sets(params, st.ics.shape[0], law_names, labels)
    base_plant, base_gains, lp, lg = _row_lanes(names, values, plant, gains, controller, labels, st.ics.shape[0])
    P, N = values.shape[0], st.ics.shape[0]
    law = {"gains": lg, "controller": None} if controller is None else {"gains": None, "controller": lg}
    res = run_ensemble_resolved(np.tile(st.ics, (P, 1)), plant=lp, **law, t_final=t_final, dt=dt, eps=eps, x64=x64,
                                observers=None, stepsize=stepsize, saveat=SaveAt(), run=run)
    if res is None:                                # a shard of a multi-process run: chunks written
        return None
    settings = _sweep_settings(res.settings, controller, base_plant, base_gains, st, names, axes, P, N)
    return _sweep_result(res, names, values, shape, axes, st, settings)


@takes_objects
def sweep(starts, params, *, plant: Optional[PlantParams] = None, gains: Any = None, controller: Any = None,
          t_final: float = 100.0, dt: float = 0.01, eps: float = 0.05, x64: bool = False,
          stepsize: Optional[StepSizeController] = None, run: Optional[RunOptions] = None,
          labels: Optional[Mapping[str, str]] = None) -> Optional[SweepResult]:
    r"""Run every start under every parameter value set, as one ensemble, and summarise per value set.

    Args:
      starts: a `BasinStarts` (`grid_starts`, `sample_starts`) or an ``(N, 3)`` / ``(N, 5)`` array.
      params: one or two ranges (``"NAME=LO:HI:P[:log]"`` strings or `ParamAxis`; two make a grid), or a
        mapping ``{name: values}`` of explicit value sets (equal lengths ``P``; zipped, not crossed). Names:
        `PARAM_NAMES`, or, with ``controller``, also its scalar parameters.
      plant, gains, controller: the base values of everything not swept (default: the paper's).
      t_final, dt, eps, x64, stepsize, run: as in `jaxsleigh.run_basin`; ``run.chunk_size`` counts rows
        (start x value set): memory is bounded by the chunk, not by ``P * N``.
      labels: parameter name -> text naming it in error messages (the command line passes its ``--param``).

    Returns:
      `SweepResult` (``None`` for one share of a multi-process run).

    Raises:
      TypeError: a keyword of jaxsleigh 0.1 (``rtol=``, ``chunk_size=``, ...), naming the object that holds it now.
      ValueError: an option object of the wrong type or with a bad value.
    """
    stepsize, _, run = study_options("sweep", stepsize, None, run)
    return _sweep(starts, params, plant=plant, gains=gains, controller=controller, t_final=t_final, dt=dt, eps=eps,
                  x64=x64, labels=labels, stepsize=stepsize, run=run)


# ---------------------------------------------------------------------------------------------
# files
# ---------------------------------------------------------------------------------------------

def save_sweep(path, result: SweepResult) -> Path:
    """Write a `SweepResult` to ``.npz`` deterministically (the writer of
    `save_basin`: equal inputs, equal bytes; nothing that varies between runs).

    Keys: ``names`` (n_params,), ``values`` (P, n_params), ``grid_shape``, ``ics`` (N, 5);
    per value set and start ``T_eps``, ``status``, ``n_steps``, ``n_rejected``, ``min_abs_theta``, ``Hd0``,
    ``Hd_final``, ``unresolved`` (bool) (P, N), ``q_final`` (P, N, 3), ``p_final`` (P, N, 2) (and the control-effort summaries when
    recorded); per value set ``fraction``, ``fraction_se``,
    ``n_valid``, ``n_converged`` (P,), ``T_eps_percentiles`` (P, 5) at ``T_eps_percentile_levels``,
    ``status_counts`` (P, K) for the codes ``status_codes`` (K,), and with the effort recorded
    ``u_energy_median``, ``u_norm_peak_median`` (P,) over the converged starts; for grids ``axis_<name>`` (the
    values of each axis) and ``axis_log``; the settings as JSON (``settings_json``, with the status
    legend) and as scalars ``eps, t_final, dt, method, dtype, max_steps``, the base ``gains_L,
    gains_k, gains_D_hat, params (m, J, l), damping``.
    """
    r = result
    S, se = r.fractions()
    codes, counts = r.status_counts()
    arrays = {
        "names": np.asarray(r.names, dtype="<U16"), "values": np.asarray(r.values, np.float64),
        "grid_shape": np.asarray(r.grid_shape, np.int64), "ics": np.asarray(r.ics, np.float64),
        "T_eps": np.asarray(r.T_eps, np.float64), "status": np.asarray(r.status, np.int32),
        "n_steps": np.asarray(r.n_steps, np.int64), "min_abs_theta": np.asarray(r.min_abs_theta, np.float64),
        "Hd0": np.asarray(r.Hd0, np.float64),
        "fraction": S, "fraction_se": se, "n_valid": r.valid.sum(axis=1).astype(np.int64),
        "n_converged": r.converged.sum(axis=1).astype(np.int64),
        "T_eps_percentiles": r.percentiles(), "T_eps_percentile_levels": np.asarray(PERCENTILES),
        "status_codes": codes, "status_counts": counts,
    }
    arrays.update({k: np.asarray(v, np.float64) for k, v in sorted(r.effort.items())})
    kinds = {"n_rejected": np.int64, "unresolved": bool}
    arrays.update({k: np.asarray(getattr(r, k), kinds.get(k, np.float64)) for k in FINAL_FIELDS
                   if getattr(r, k) is not None})
    arrays.update(r.effort_medians())
    for a in r.axes:
        arrays[f"axis_{a.name}"] = a.values()
    if r.axes:
        arrays["axis_log"] = np.array([a.log for a in r.axes])
    return write_result(path, arrays, r.settings)


def load_sweep(path) -> SweepResult:
    """Read an ``.npz`` written by `save_sweep` (or ``jaxsleigh sweep``)."""
    d, settings = read_result(path, "sweep file (written by jaxsleigh sweep / save_sweep)",
                              ("values", "names", "grid_shape", "ics", "T_eps", "status", "n_steps", "min_abs_theta",
                               "Hd0"), kind="sweep")
    axes = tuple(parse_param(a, law_names=tuple(settings["sweep"]["names"])) for a in settings["sweep"]["axes"])
    recorded = {k: d[k] for k in ("u_energy", "u_abs_int", "u_norm_peak", *FINAL_FIELDS) if k in d}
    return SweepResult(names=tuple(str(n) for n in d["names"]), values=d["values"],
                       grid_shape=tuple(int(x) for x in d["grid_shape"]), axes=axes,
                       starts=starts_from_spec(d["ics"], settings["starts"]), ics=d["ics"], T_eps=d["T_eps"],
                       status=d["status"], n_steps=d["n_steps"], min_abs_theta=d["min_abs_theta"], Hd0=d["Hd0"],
                       **recorded, settings=settings, run_info=None)
