r"""Where starts settle: which reach and keep \(|q| \le \epsilon\) within the horizon, and how fast.

(The command is called ``basin``, but a map of it is not a basin of attraction in the control sense:
the paper argues convergence from every start off \(\theta = 0\); a start that has not settled
by the horizon is "not settled yet", not "diverges".)

A basin study integrates the closed loop from many starts with `jaxsleigh.studies.ensemble.run_ensemble`
(chunked, checkpointed, sharded over devices) and keeps, per start, the convergence time
``T_eps``, the status, \(H_d(0)\), the closest approach to the singular set
(``min_abs_theta``), the largest \(|q|\) (``max_excursion``) and the steps used.

Starts come from

* `grid_starts`: a grid over any slice of \((x, y, \theta)\): each coordinate is a range
  ``"LO:HI:N"`` or one fixed value (an x-y map at fixed heading, an x-theta or y-theta map at
  fixed position, a line, or a 3-D grid);
* `sample_starts`: Monte-Carlo samples, uniform in a box;
* `array_starts`: a user's ``(N, 3)`` or ``(N, 5)`` array.

`run_basin` returns a `BasinResult`; its summary is the fraction \(S\) of valid
starts that converged within the horizon, with standard error \(\sqrt{S(1-S)/N}\)
(`fraction_converged`), and the distribution of ``T_eps``. `save_basin` writes it to
an ``.npz`` whose bytes depend only on the inputs (no wall time, no zip timestamps), so a resumed
run ends with the same file as an uninterrupted one; `load_basin` reads it back.

Starts on the singular set \(\theta_0 = 0\) (where the control law is undefined) are flagged
with status ``SINGULAR_START``, not integrated, and left out of \(N\) in the fraction.

Two small analyses serve the singular-set study: `power_law_fit` (log-log least squares
with the slope's standard error) and `path_length` (of decimated paths).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, NamedTuple, Optional, Sequence

import numpy as np

from .config import reject_traced
from .ensemble import LaneRules, run_ensemble_resolved, summary_repr
from .options import RunOptions, SaveAt, study_options, takes_objects
from ..integrate.stepsize import StepSizeController
from ..files.npz import read_result, write_result
from ..files.npz import parse_number as _number
from ..model.params import Gains, PlantParams
from ..status import CONVERGED, NOT_INTEGRATED, VALID, Status
from ..validate import check_memory, whole

__all__ = [
    "COORDS",
    "Axis",
    "parse_axis",
    "BasinStarts",
    "grid_starts",
    "sample_starts",
    "array_starts",
    "BasinResult",
    "run_basin",
    "fraction_converged",
    "fraction_by",
    "t_eps_percentiles",
    "save_basin",
    "load_basin",
    "PowerLawFit",
    "power_law_fit",
    "path_length",
]

COORDS = ("x", "y", "theta")

#: The slice used when no coordinate is given: an x-y map at heading pi/4.
DEFAULT_SLICE = {"x": "-3:3:64", "y": "-3:3:64", "theta": "pi/4"}
#: Where a coordinate that is not given is held in a grid (x and y in m, theta in rad).
DEFAULT_FIXED = {"x": 1.0, "y": 1.0, "theta": math.pi / 4}
#: The Monte-Carlo box when a coordinate is not given.
DEFAULT_BOX = {"x": (-3.0, 3.0), "y": (-3.0, 3.0), "theta": (-math.pi, math.pi)}
#: Percentiles of T_eps reported in summaries.
PERCENTILES = (10.0, 25.0, 50.0, 75.0, 90.0)

_FLAGGED = NOT_INTEGRATED


# ---------------------------------------------------------------------------------------------
# axes and grids
# ---------------------------------------------------------------------------------------------

class Axis(NamedTuple):
    """One coordinate of a grid: ``n`` points evenly spaced from ``lo`` to ``hi`` (both included),
    or a fixed value (``n == 1``, ``lo == hi``)."""

    lo: float
    hi: float
    n: int

    @property
    def fixed(self) -> bool:
        return self.n == 1

    def values(self) -> np.ndarray:
        v = np.linspace(self.lo, self.hi, self.n) if self.n > 1 else np.array([self.lo])
        # a grid symmetric about 0 hits 0 only up to rounding; snap it, so the start is flagged as
        # singular instead of integrated from theta0 ~ 1e-17 (H_d(0) ~ 1e68)
        tiny = 1e-12 * max(abs(self.lo), abs(self.hi))
        return np.where(np.abs(v) <= tiny, 0.0, v)


def parse_axis(spec, name: str = "x") -> Axis:
    """A grid axis from ``"LO:HI:N"``, ``"VALUE"``, a number, ``(lo, hi, n)`` or an `Axis`.

    Numbers may be written with ``pi`` (``"-pi:pi:64"``, ``"pi/8"``). ``name`` is used in the
    error messages (e.g. ``"--theta"``), which say what to write instead.
    """
    hint = _axis_hint(name)
    lo, hi, n = _axis_fields(spec, name, hint)
    lo, hi = float(lo), float(hi)
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ValueError(f"{name} {spec!r} has a non-finite bound; {hint}")
    if not (math.isfinite(float(n)) and float(n) == int(n)):     # N = nan or inf: not a count either
        raise ValueError(f"{name} {spec!r}: N = {n} must be a whole number of points; {hint}")
    n = int(n)
    if n != 1 or lo != hi:
        _check_axis_range(spec, name, lo, hi, n)
    return Axis(lo, hi, n)


def _axis_hint(name: str) -> str:
    """The "what to write instead" tail of `parse_axis`'s messages, with an example for ``name``."""
    example = {"x": "-3:3:64", "y": "-3:3:64", "theta": "-pi:pi:64"}.get(name.lstrip("-"), "-3:3:64")
    return f"write LO:HI:N (e.g. {name} {example}) or a single value to hold it fixed (e.g. {name} 0.5)"


def _axis_fields(spec, name: str, hint: str):
    """``(lo, hi, n)`` as given by any form `parse_axis` accepts, not yet checked."""
    if isinstance(spec, Axis):
        lo, hi, n = spec
    elif isinstance(spec, str):
        lo, hi, n = _axis_fields_from_text(spec, name, hint)
    elif np.ndim(spec) == 0:
        try:
            lo = hi = float(spec)
        except (TypeError, ValueError):
            raise ValueError(f"{name} must be a number, a string or (lo, hi, n), got {spec!r}; {hint}") from None
        n = 1
    else:
        if len(spec) != 3:
            raise ValueError(f"{name} as a sequence must be (lo, hi, n), got {spec!r}; {hint}")
        try:
            lo, hi, n = (float(v) for v in spec)
        except (TypeError, ValueError):
            raise ValueError(f"{name} as a sequence must be three numbers (lo, hi, n), got {spec!r}; {hint}") from None
    return lo, hi, n


def _axis_fields_from_text(spec: str, name: str, hint: str):
    """``(lo, hi, n)`` from ``"LO:HI:N"`` or ``"VALUE"`` (numbers may use ``pi``)."""
    parts = spec.split(":")
    try:
        vals = [_number(s) for s in parts]
    except ValueError as e:
        raise ValueError(f"could not parse {name} {spec!r}: {e}; {hint}") from None
    if len(parts) == 1:
        return vals[0], vals[0], 1
    if len(parts) == 3:
        return tuple(vals)
    raise ValueError(f"could not parse {name} {spec!r}: got {len(parts)} field(s) separated by ':'; {hint}")


def _check_axis_range(spec, name: str, lo: float, hi: float, n: int) -> None:
    """Refuse a range (not a fixed value) with too few points or with ``LO >= HI``."""
    if n < 2:
        raise ValueError(f"{name} {spec!r}: a range needs N >= 2 points; to hold {name} fixed write one value "
                         f"(e.g. {name} {_fmt(lo)})")
    if lo == hi:
        raise ValueError(f"{name} {spec!r}: LO and HI are equal; to hold {name} fixed write one value "
                         f"(e.g. {name} {_fmt(lo)}), for a range write e.g. {name} {_fmt(lo)}:{_fmt(lo + 1)}:{n}")
    if not lo < hi:
        raise ValueError(f"{name} {spec!r}: LO must be below HI; write e.g. {name} "
                         f"{_fmt(min(lo, hi))}:{_fmt(max(lo, hi))}:{n}")


def _fmt(v: float) -> str:
    return f"{v:g}"


class BasinStarts(NamedTuple):
    """Initial conditions of a basin study and how they were made.

    Attributes:
      ics: ``(N, 3)`` ``(x, y, theta)`` with zero momentum, or ``(N, 5)`` with momentum.
      kind: ``"grid"``, ``"samples"`` or ``"array"``.
      shape: the grid's shape, slowest axis first (e.g. ``(n_y, n_x)`` for an x-y map, whose rows
        are then ``y`` and columns ``x``); ``(N,)`` for samples and arrays.
      axes: the coordinates that vary, *fastest first* (``("x", "y")``: ``x`` runs along the rows
        of the map, i.e. horizontally); ``()`` for samples and arrays.
      spec: JSON-ready description (grid axes; box and seed of samples; source of an array).
    """

    ics: np.ndarray
    kind: str
    shape: tuple
    axes: tuple
    spec: dict

    def axis(self, name: str) -> Axis:
        """The `Axis` of coordinate ``name`` of a grid (fixed coordinates have ``n = 1``)."""
        if self.kind != "grid":
            raise ValueError(f"starts of kind {self.kind!r} have no grid axes")
        return Axis(*self.spec[name])

    def reshape(self, a) -> np.ndarray:
        """Per-start array ``(N, ...)`` -> grid-shaped ``shape + (...)``."""
        a = np.asarray(a)
        return a.reshape(tuple(self.shape) + a.shape[1:])


def grid_starts(x=None, y=None, theta=None) -> BasinStarts:
    r"""Starts on a grid over a slice of \((x, y, \theta)\), at rest.

    Each coordinate is a range (``"LO:HI:N"`` or ``(lo, hi, n)``) or one value (held fixed). With
    none given the slice is ``x, y in [-3, 3]`` (64 x 64) at ``theta = pi/4``; otherwise a
    coordinate not given is held at ``x = 1``, ``y = 1``, ``theta = pi/4``.

    Examples: ``grid_starts(x="-3:3:128", y="-3:3:128", theta="pi/8")`` (x-y map),
    ``grid_starts(x="-3:3:128", y=1, theta="-pi:pi:128")`` (x-theta map at y = 1).

    Grid points with ``theta = 0`` exactly lie on the singular set: they are kept (so the grid
    stays rectangular) and flagged by `run_basin`. A fixed ``theta = 0`` is an error.
    """
    given = {"x": x, "y": y, "theta": theta}
    if all(v is None for v in given.values()):
        given = dict(DEFAULT_SLICE)
    axes = {c: parse_axis(DEFAULT_FIXED[c] if v is None else v, c) for c, v in given.items()}
    if axes["theta"].fixed and axes["theta"].lo == 0.0:
        raise ValueError("theta = 0 is the singular set, where the control law is undefined; hold theta at a "
                         "non-zero value (e.g. --theta 1e-3) or give it a range (e.g. --theta -pi:pi:64)")
    varying = tuple(c for c in COORDS if not axes[c].fixed)
    check_memory(math.prod(axes[c].n for c in COORDS), "grid_starts")
    slow_first = varying[::-1]
    if varying:
        mesh = np.meshgrid(*[axes[c].values() for c in slow_first], indexing="ij")
        shape = mesh[0].shape
        cols = {c: m.ravel() for c, m in zip(slow_first, mesh)}
    else:
        shape = (1,)
        cols = {}
    n = int(np.prod(shape))
    ics = np.column_stack([cols[c] if c in cols else np.full(n, axes[c].lo) for c in COORDS])
    spec = {"kind": "grid", **{c: [axes[c].lo, axes[c].hi, axes[c].n] for c in COORDS}}
    return BasinStarts(ics, "grid", tuple(int(s) for s in shape), varying, spec)


def sample_starts(n: int, *, seed: int = 0, x=None, y=None, theta=None) -> BasinStarts:
    r"""``n`` starts at rest, uniform in a box of \((x, y, \theta)\).

    Each coordinate is an interval (``"LO:HI"``, ``"LO:HI:N"`` with ``N`` ignored, ``(lo, hi)``)
    or one value (held fixed); defaults: ``|x|, |y| <= 3``, ``theta in (-pi, pi)``. The draw is
    reproducible from ``seed`` (NumPy's PCG64). A sample with ``theta = 0`` exactly would be
    flagged as singular by `run_basin` (probability ~1e-16 per sample).
    """
    n = whole("n", n, maximum=2**62, example=100000)
    seed = whole("seed", seed, minimum=0, maximum=2**63 - 1, example=1)
    check_memory(n, "sample_starts")
    box = {}
    for c, v in (("x", x), ("y", y), ("theta", theta)):
        if v is None:
            box[c] = DEFAULT_BOX[c]
            continue
        if isinstance(v, str) and v.count(":") in (1, 2):
            v = ":".join(v.split(":")[:2]) + ":2"       # "LO:HI[:N]" -> an interval, N ignored
        elif not isinstance(v, (str, Axis)) and np.ndim(v) == 1 and len(v) == 2:
            v = (v[0], v[1], 2)
        a = parse_axis(v, c)
        box[c] = (a.lo, a.hi)
    if box["theta"] == (0.0, 0.0):
        raise ValueError("theta = 0 is the singular set; sample theta in an interval (e.g. --theta -pi:pi) "
                         "or hold it at a non-zero value (e.g. --theta 0.5)")
    rng = np.random.default_rng(seed)
    cols = [lo + (hi - lo) * rng.random(n) for lo, hi in box.values()]
    ics = np.column_stack(cols)
    spec = {"kind": "samples", "n": n, "seed": seed, **{c: list(box[c]) for c in COORDS}}
    return BasinStarts(ics, "samples", (n,), (), spec)


def array_starts(ics, *, source: Optional[str] = None) -> BasinStarts:
    """Wrap a user's ``(N, 3)`` or ``(N, 5)`` array (``source``: where it came from, recorded)."""
    arr = np.array(ics, dtype=np.float64)
    if arr.ndim == 1 and arr.shape[0] in (3, 5):
        arr = arr[None]
    if arr.ndim != 2 or arr.shape[1] not in (3, 5) or arr.shape[0] == 0:
        raise ValueError(f"initial conditions must have shape (N, 3) [x, y, theta] or (N, 5) "
                         f"[x, y, theta, p1, p2], got {np.shape(ics)}")
    spec = {"kind": "array", "n": int(arr.shape[0]), "source": None if source is None else str(source)}
    return BasinStarts(arr, "array", (int(arr.shape[0]),), (), spec)


def starts_from_spec(ics: np.ndarray, spec: dict) -> BasinStarts:
    """The `BasinStarts` of a saved basin from its starts ``ics`` and the settings' ``"starts"`` entry ``spec``."""
    kind = spec["kind"]
    if kind == "grid":
        g = grid_starts(*(Axis(*spec[c]) for c in COORDS))
        return g._replace(ics=ics)
    if kind == "samples":
        return BasinStarts(ics, "samples", (ics.shape[0],), (), spec)
    return BasinStarts(ics, "array", (ics.shape[0],), (), spec)


# ---------------------------------------------------------------------------------------------
# summaries
# ---------------------------------------------------------------------------------------------

def fraction_converged(converged, valid=None) -> tuple[float, float]:
    r"""Fraction \(S\) of the valid starts that converged, and its standard error.

    \[ S = \frac{n_\mathrm{conv}}{N}, \qquad \mathrm{se}(S) = \sqrt{\frac{S (1 - S)}{N}} \]

    (binomial; zero when \(S\) is 0 or 1). ``valid`` (bool, default all) selects the starts
    counted in \(N\). Returns ``(nan, nan)`` when \(N = 0\).
    """
    conv = np.asarray(converged, dtype=bool).ravel()
    ok = np.ones_like(conv) if valid is None else np.asarray(valid, dtype=bool).ravel()
    if ok.shape != conv.shape:
        raise ValueError(f"converged and valid must have the same shape, got {conv.shape} and {ok.shape}")
    n = int(ok.sum())
    if n == 0:
        return math.nan, math.nan
    s = float(np.sum(conv & ok)) / n
    return s, math.sqrt(s * (1.0 - s) / n)


def fraction_by(values, converged, valid=None, *, bins=None):
    """Fraction converged (and its standard error) in groups of ``values`` (e.g. ``theta0``).

    ``bins``: ``None`` groups equal values (the rows of a grid), an int makes that many equal-width
    bins over the valid values, an array gives the bin edges.

    Returns ``(centres, fraction, se, counts)``, arrays over the non-empty groups.
    """
    v = np.asarray(values, dtype=float).ravel()
    conv = np.asarray(converged, dtype=bool).ravel()
    ok = np.ones_like(conv) if valid is None else np.asarray(valid, dtype=bool).ravel()
    v, conv = v[ok], conv[ok]
    if bins is None:
        centres, inverse = np.unique(v, return_inverse=True)
        groups = [inverse == i for i in range(centres.size)]
    else:
        edges = np.histogram_bin_edges(v, bins=bins) if np.ndim(bins) == 0 else np.asarray(bins, float)
        idx = np.clip(np.searchsorted(edges, v, side="right") - 1, 0, edges.size - 2)
        centres = 0.5 * (edges[:-1] + edges[1:])
        groups = [idx == i for i in range(centres.size)]
    out = [(c, *fraction_converged(conv[g]), int(g.sum())) for c, g in zip(centres, groups) if g.any()]
    if not out:
        empty = np.zeros(0)
        return empty, empty, empty, np.zeros(0, int)
    c, f, se, n = (np.asarray(a) for a in zip(*out))
    return c.astype(float), f.astype(float), se.astype(float), n.astype(int)


def t_eps_percentiles(T_eps, q: Sequence[float] = PERCENTILES) -> np.ndarray:
    """Percentiles ``q`` of the finite ``T_eps`` (the converged starts); NaN when none converged."""
    t = np.asarray(T_eps, dtype=float)
    t = t[np.isfinite(t)]
    if t.size == 0:
        return np.full(len(q), np.nan)
    return np.percentile(t, q)


# ---------------------------------------------------------------------------------------------
# result
# ---------------------------------------------------------------------------------------------

class BasinResult(NamedTuple):
    """Per-start results of a basin study (NumPy arrays, first axis N), the starts and the settings.

    Attributes:
      starts: the `BasinStarts` (grid shape and axes, or samples' box and seed).
      ics: ``(N, 5)`` initial conditions ``(x, y, theta, p1, p2)``.
      T_eps: convergence time [s]: the first time after which \\(|q| \\le \\epsilon\\) holds at
        every accepted step up to the horizon; ``inf``: not settled by then; ``nan``: failed or
        not integrated.
      status: `Status` codes.
      Hd0, Hd_final: \\(H_d\\) at the start and at the horizon.
      min_abs_theta: closest approach to the singular set, \\(\\min_t |\\theta(t)|\\).
      max_excursion: \\(\\max_t |q(t)|\\).
      n_steps, n_rejected: accepted and rejected steps.
      q_final, p_final: ``(N, 3)``, ``(N, 2)`` state at the horizon (NaN if failed).
      settings: plant, gains, eps, horizon, method, dtype, tolerances, budget, chunk size, starts.
      run_info: wall time and devices of the run that produced it (not saved in the ``.npz``: they
        vary between runs); ``None`` when loaded from a file.
      u_peak, u_norm_peak, u_energy, u_abs_int: control effort (see
        `EnsembleResult`); ``None`` in files of jaxsleigh 0.1.
      unresolved: ``(N,)`` bool, the starts whose settled oscillation grew (see `EnsembleResult`); ``None`` in
        files written before it was saved.
    """

    starts: BasinStarts
    ics: np.ndarray
    T_eps: np.ndarray
    status: np.ndarray
    Hd0: np.ndarray
    Hd_final: np.ndarray
    min_abs_theta: np.ndarray
    max_excursion: np.ndarray
    n_steps: np.ndarray
    n_rejected: np.ndarray
    q_final: np.ndarray
    p_final: np.ndarray
    settings: dict
    run_info: Optional[dict] = None
    u_peak: Optional[np.ndarray] = None
    u_norm_peak: Optional[np.ndarray] = None
    u_energy: Optional[np.ndarray] = None
    u_abs_int: Optional[np.ndarray] = None
    unresolved: np.ndarray | None = None

    valid = VALID
    converged = CONVERGED

    @property
    def not_converged(self) -> np.ndarray:
        """Not settled within the horizon (``T_eps = inf``): reached it outside the ball, or certified not to settle
        before it (``NOT_SETTLING``, stopped early)."""
        return (((self.status == Status.OK) & ~np.isfinite(self.T_eps))
                | (self.status == Status.NOT_SETTLING))

    @property
    def failed(self) -> np.ndarray:
        """Integrated but stopped before the horizon without an answer (non-finite, budget, underflow, ...); a start
        certified not to settle (``NOT_SETTLING``) has one: `not_converged`."""
        return self.valid & (self.status != Status.OK) & (self.status != Status.NOT_SETTLING)

    @property
    def fraction(self) -> float:
        """Fraction of valid starts that converged within the horizon."""
        return fraction_converged(self.converged, self.valid)[0]

    @property
    def fraction_se(self) -> float:
        """Standard error \\(\\sqrt{S(1-S)/N}\\) of `fraction`."""
        return fraction_converged(self.converged, self.valid)[1]

    def map(self, name: str = "T_eps") -> np.ndarray:
        """A per-start field shaped like the grid (rows: the slower axis)."""
        return self.starts.reshape(getattr(self, name))

    def summary(self) -> dict:
        """JSON-ready counts, fraction +- standard error and percentiles of ``T_eps``."""
        s, se = fraction_converged(self.converged, self.valid)
        counts = {Status(int(c)).name.lower(): int(n) for c, n in
                  zip(*np.unique(self.status, return_counts=True))}
        pct = t_eps_percentiles(self.T_eps[self.converged])
        conv_t = self.T_eps[self.converged]
        return {
            "n": int(self.status.size), "n_valid": int(self.valid.sum()),
            "n_converged": int(self.converged.sum()), "n_not_converged": int(self.not_converged.sum()),
            "n_failed": int(self.failed.sum()), "n_flagged": int((~self.valid).sum()),
            "status_counts": counts, "fraction": s, "fraction_se": se,
            "eps": self.settings.get("eps"), "t_final": self.settings.get("t_final"),
            "T_eps_percentiles": {f"p{q:g}": float(v) for q, v in zip(PERCENTILES, pct)},
            "T_eps_mean": float(conv_t.mean()) if conv_t.size else math.nan,
        }

    def __repr__(self) -> str:
        # a summary, not every array (see `describe` for two lines, `summary` for a dict)
        st = self.starts
        how = (f"grid {' x '.join(str(n) for n in st.shape)} over {', '.join(st.axes) or 'one point'}"
               if st.kind == "grid" else f"{st.kind}")
        return summary_repr("BasinResult", self, status=self.status, T_eps=self.T_eps, Hd0=self.Hd0,
                            u_energy=self.u_energy, head=f" starts, {how}",
                            extra=(f"fraction {self.fraction:.4f} +- {self.fraction_se:.4f} (binomial s.e.)",))

    def describe(self) -> str:
        """Two lines for humans: counts, fraction and T_eps percentiles."""
        d = self.summary()
        st = ", ".join(f"{n} {name}" for name, n in d["status_counts"].items())
        p = d["T_eps_percentiles"]
        return (f"N = {d['n']} ({st}); converged within {d['t_final']:g} s (|q| <= {d['eps']:g}): "
                f"{d['n_converged']}/{d['n_valid']} = {d['fraction']:.4f} +- {d['fraction_se']:.4f}\n"
                f"T_eps of the converged [s]: p10 {p['p10']:.3g}, p25 {p['p25']:.3g}, median {p['p50']:.3g}, "
                f"p75 {p['p75']:.3g}, p90 {p['p90']:.3g}")


def _run_basin(starts, *, plant: Optional[PlantParams], gains: Optional[Gains], controller: Any, t_final: float,
               dt: float, eps: float, x64: bool, stepsize: StepSizeController,
               run: RunOptions) -> Optional[BasinResult]:
    r"""`run_basin` (see there) with its option objects checked (`study_options`): integrate the
    closed loop from every start (``starts``: a `BasinStarts` or an ``(N, 3)`` / ``(N, 5)`` array) and summarise
    convergence. ``run.chunk_size`` defaults to 16384 on CPU (2^22 per device on accelerators,
    `jaxsleigh.cores.default_chunk_size`). Returns a `BasinResult` (``None`` with ``run.shard``)."""
    reject_traced("run_basin", **locals())    # first: a NumPy front, neither jittable nor differentiable
    if not isinstance(starts, BasinStarts):
        starts = array_starts(starts)
    res = run_ensemble_resolved(starts.ics, plant=plant, gains=gains, controller=controller, t_final=t_final, dt=dt,
                                eps=eps, x64=x64, observers=None, stepsize=stepsize, saveat=SaveAt(), run=run,
                                rules=LaneRules(certify=True))
    if res is None:                               # a shard of a multi-process run: chunks written
        return None
    settings = {k: v for k, v in res.settings.items() if k not in ("save_every",)}
    settings["starts"] = starts.spec
    run_info = dict(res.run_info)
    # every per-start field has the ensemble's name: taken over by name, not copied one by one
    return BasinResult(starts=starts, settings=settings, run_info=run_info,
                       **{k: getattr(res, k) for k in BasinResult._fields if k not in ("starts", "settings", "run_info")})


@takes_objects
def run_basin(starts, *, plant: Optional[PlantParams] = None, gains: Optional[Gains] = None, controller: Any = None,
              t_final: float = 100.0, dt: float = 0.01, eps: float = 0.05, x64: bool = False,
              stepsize: Optional[StepSizeController] = None,
              run: Optional[RunOptions] = None) -> Optional[BasinResult]:
    r"""Integrate the closed loop from every start and summarise convergence (settled within the horizon).

    A start that cannot settle before the horizon any more (far from the target with too little \(H_d\) left to
    come back: `jaxsleigh.integrate.stragglers`) is stopped there with status ``NOT_SETTLING`` and ``T_eps = inf``:
    not settled, like a start that reaches the horizon outside the ball, at a fraction of the steps.

    Args:
      starts: a `BasinStarts` (`grid_starts`, `sample_starts`) or an ``(N, 3)`` / ``(N, 5)`` array.
      plant, gains, controller, t_final, dt, x64: as in `jaxsleigh.run_ensemble` (defaults: the paper's
        plant and law, 100 s, float32).
      eps: radius of the ball \(|q| \le \epsilon\) of ``T_eps``.
      stepsize: `jaxsleigh.StepSizeController` (default: adaptive RK4).
      run: `jaxsleigh.RunOptions` (its ``chunk_size`` defaults to 16384 on CPU, 2^22 per device on
        accelerators; ``checkpoint_dir`` and ``resume`` continue an interrupted run; ``segment`` does not apply).

    Returns:
      `BasinResult` (``None`` for one share of a multi-process run).

    Raises:
      TypeError: a keyword of jaxsleigh 0.1 (``rtol=``, ``chunk_size=``, ...), naming the object that holds it now.
      ValueError: an option object of the wrong type or with a bad value.
    """
    stepsize, _, run = study_options("run_basin", stepsize, None, run)
    return _run_basin(starts, plant=plant, gains=gains, controller=controller, t_final=t_final, dt=dt, eps=eps,
                      x64=x64, stepsize=stepsize, run=run)


# ---------------------------------------------------------------------------------------------
# files
# ---------------------------------------------------------------------------------------------

_PER_START = ("T_eps", "status", "Hd0", "Hd_final", "min_abs_theta", "max_excursion", "n_steps", "n_rejected",
              "q_final", "p_final")
_EFFORT = ("u_peak", "u_norm_peak", "u_energy", "u_abs_int", "unresolved")


def save_basin(path, result: BasinResult) -> Path:
    """Write a `BasinResult` to ``.npz`` (appended when missing); returns the path.

    Keys: the starts ``ics`` ``(N, 3)`` or ``(N, 5)`` (as given); per start ``T_eps``, ``status``,
    ``Hd0``, ``Hd_final``, ``min_abs_theta``, ``max_excursion``, ``n_steps``, ``n_rejected``,
    ``q_final`` ``(N, 3)``, ``p_final`` ``(N, 2)``, ``converged``, ``valid`` and ``unresolved`` (bool); the summary
    ``fraction``, ``fraction_se``, ``n_valid``, ``n_converged``, ``T_eps_percentiles`` (at
    ``T_eps_percentile_levels``); the starts' layout ``kind``, ``grid_shape``, ``grid_axes`` and, for
    grids, ``axis_x``, ``axis_y``, ``axis_theta`` (values; one entry for a fixed coordinate), for
    samples ``box`` ``(3, 2)`` and ``seed``; the settings as JSON (``settings_json``, with the status
    legend) and as scalars ``eps, t_final, dt, method, dtype, max_steps, gains_L, gains_k,
    gains_D_hat, params (m, J, l), damping``.

    Nothing that varies between runs (wall time, devices) is written, and the zip members carry
    a fixed timestamp: the same inputs give the same bytes.
    """
    r, st = result, result.starts
    summ = r.summary()
    arrays = {"ics": np.asarray(st.ics, np.float64)}
    arrays.update({k: np.asarray(getattr(r, k)) for k in _PER_START})
    arrays.update({k: np.asarray(getattr(r, k)) for k in _EFFORT if getattr(r, k) is not None})
    arrays.update(
        converged=r.converged, valid=r.valid,
        fraction=np.float64(summ["fraction"]), fraction_se=np.float64(summ["fraction_se"]),
        n_valid=np.int64(summ["n_valid"]), n_converged=np.int64(summ["n_converged"]),
        T_eps_percentiles=t_eps_percentiles(r.T_eps[r.converged]),
        T_eps_percentile_levels=np.asarray(PERCENTILES),
        kind=np.array(st.kind), grid_shape=np.asarray(st.shape, np.int64),
        grid_axes=np.asarray(st.axes if st.axes else [], dtype="<U5"),
    )
    if st.kind == "grid":
        for c in COORDS:
            arrays[f"axis_{c}"] = st.axis(c).values()
    elif st.kind == "samples":
        arrays["box"] = np.asarray([st.spec[c] for c in COORDS], np.float64)
        arrays["seed"] = np.int64(st.spec["seed"])
    return write_result(path, arrays, r.settings)


def load_basin(path) -> BasinResult:
    """Read an ``.npz`` written by `save_basin` (or ``jaxsleigh basin``)."""
    data, settings = read_result(path, "basin file (written by jaxsleigh basin / save_basin)", ("ics",) + _PER_START,
                                 kind="basin")
    ics = data["ics"]
    starts = starts_from_spec(ics, settings["starts"])
    ics5 = ics if ics.shape[1] == 5 else np.concatenate([ics, np.zeros((ics.shape[0], 2))], axis=1)
    return BasinResult(starts=starts, ics=ics5, settings=settings, run_info=None,
                       **{k: data[k] for k in _PER_START}, **{k: data[k] for k in _EFFORT if k in data})


# ---------------------------------------------------------------------------------------------
# analyses for the singular-set study
# ---------------------------------------------------------------------------------------------

class PowerLawFit(NamedTuple):
    r"""Least-squares fit \(\log y = \log c + a \log x\) (so \(y \approx c\,x^a\)).

    Attributes:
      exponent: \(a\).
      exponent_se: its standard error (from the residuals; ``nan`` with two points).
      prefactor: \(c\).
      r2: coefficient of determination in log-log.
      n: points used.
    """

    exponent: float
    exponent_se: float
    prefactor: float
    r2: float
    n: int

    def __call__(self, x):
        return self.prefactor * np.asarray(x, dtype=float) ** self.exponent


def power_law_fit(x, y) -> PowerLawFit:
    """Fit \\(y = c\\,x^a\\) by least squares in log-log over the points with ``x, y > 0`` finite."""
    x = np.asarray(x, dtype=float).ravel()
    y = np.asarray(y, dtype=float).ravel()
    ok = np.isfinite(x) & np.isfinite(y) & (x > 0) & (y > 0)
    lx, ly = np.log(x[ok]), np.log(y[ok])
    n = int(ok.sum())
    if n < 2 or np.ptp(lx) == 0:
        raise ValueError(f"a power-law fit needs at least two points with distinct x > 0 and y > 0, got {n}")
    xm, ym = lx.mean(), ly.mean()
    sxx = float(np.sum((lx - xm) ** 2))
    a = float(np.sum((lx - xm) * (ly - ym)) / sxx)
    b = ym - a * xm
    resid = ly - (a * lx + b)
    ss_tot = float(np.sum((ly - ym) ** 2))
    r2 = 1.0 - float(np.sum(resid ** 2)) / ss_tot if ss_tot > 0 else 1.0
    se = math.sqrt(float(np.sum(resid ** 2)) / (n - 2) / sxx) if n > 2 else math.nan
    return PowerLawFit(a, se, float(np.exp(b)), r2, n)


def path_length(q) -> np.ndarray:
    """Length of the path of the contact point: \\(\\sum |\\Delta (x, y)|\\) over a decimated
    trajectory ``q`` of shape ``(T, 3)`` or ``(N, T, 3)`` (NaN samples, after a failure, are
    skipped). Decimation cuts corners: save finely enough (see the singular-set study)."""
    q = np.asarray(q, dtype=float)
    single = q.ndim == 2
    q = q[None] if single else q
    d = np.linalg.norm(np.diff(q[..., :2], axis=-2), axis=-1)
    out = np.nansum(d, axis=-1)
    return out[0] if single else out
