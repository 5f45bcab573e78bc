"""Figures of basin studies and of the singular-set study, from a `BasinResult`.

* `plot_basin_map`: convergence time ``T_eps`` over a 2-D grid as a heat map with a log colour
  scale; starts that did not settle within the horizon, that failed, and that lie on the singular
  set (not integrated) each have their own flat colour, and the singular set ``theta = 0`` is drawn.
  Other per-start fields (``Hd0``, ``max_excursion``, ``n_steps``, ``min_abs_theta``) too.
* `plot_fraction_vs_theta`: fraction converged against ``theta0`` with standard-error bars;
  `plot_fraction_vs_distance`: the same against the initial distance ``|(x0, y0)|``.
* `plot_t_eps_distribution`: histogram of ``T_eps`` and the fraction converged by time t.
* `plot_t_eps_scatter`: ``T_eps`` against ``|theta0|`` (for samples and files of starts).
* `plot_basin`: the overview (map or scatter, fraction, distribution) drawn by
  ``jaxsleigh basin --plot``.
* `plot_power_laws`: log-log data with fitted power laws (the singular-set study).

As in `jaxsleigh.plots.paper_figures`, figures are `matplotlib.figure.Figure` objects built without
``pyplot`` (no backend, no global state; `jaxsleigh.plots.base`); pass ``ax`` to draw into your
own axes; save with `jaxsleigh.plots.paper_figures.save_figure`. Titles name the dtype, method, step, ``eps``
and horizon; a stamp along the top edge adds the tolerances and the device (when the result holds it).
"""
from __future__ import annotations

from typing import Mapping, Optional

import numpy as np

from ..studies.basin import BasinResult, fraction_by, fraction_converged, t_eps_percentiles
from .base import T_EPS, check_stamp, figure_and_axes, new_figure, provenance, stamp

__all__ = [
    "plot_basin_map",
    "plot_fraction_vs_theta",
    "plot_fraction_vs_distance",
    "plot_t_eps_distribution",
    "plot_t_eps_scatter",
    "plot_basin",
    "plot_power_laws",
    "CATEGORY_COLOURS",
]

#: Flat colours of the starts without a convergence time.
CATEGORY_COLOURS = {
    "not converged": "#c8c8c8",     # reached the horizon outside the ball (T_eps = inf)
    "failed": "#d62728",            # stopped before the horizon (status >= 3)
    "singular start": "#000000",    # theta0 = 0 or non-finite: not integrated
}

_SINGULAR_LINE = "#ff7f0e"       # the singular set theta = 0, drawn over the map
_LABELS = {"x": "x₀ [m]", "y": "y₀ [m]", "theta": "θ₀ [rad]"}
_FIELDS = {
    "T_eps": f"convergence time {T_EPS} [s]",
    "Hd0": "H_d(0) [J]",
    "max_excursion": "max |q(t)|",
    "min_abs_theta": "min |θ(t)| [rad]",
    "n_steps": "accepted steps",
    "Hd_final": "H_d(T) [J]",
}


def _provenance(res: BasinResult) -> str:
    return provenance(res.settings, fields=("dt", "eps", "t_final"))


#: ``gid`` of the counts line under the convergence-time histogram (`plot_t_eps_distribution`).
FOOTER_GID = "jaxsleigh-t-eps-counts"


def _stamp(fig, res: BasinResult, on: bool = True) -> None:
    if check_stamp(on):
        stamp(fig, res.settings, res.run_info)


def _titled(fig, ax, own: bool, title: str, res: BasinResult, stamp: bool, *, fraction_on_axes: bool = False):
    """Finish a panel: on its own figure, ``title`` with the provenance and the fraction as the suptitle and the
    stamp; on a caller's axes, ``title`` as the axes' title (with the fraction when ``fraction_on_axes``). Returns
    the figure."""
    if own:
        fig.suptitle(f"{title}\n({_provenance(res)}; {_fraction_text(res)})", fontsize=10)
        _stamp(fig, res, stamp)
    else:
        ax.set_title(f"{title}\n({_fraction_text(res)})" if fraction_on_axes else title, fontsize=9)
    return fig


def _fraction_text(res: BasinResult) -> str:
    s, se = fraction_converged(res.converged, res.valid)
    return f"converged: {s:.3f} ± {se:.3f} of N = {int(res.valid.sum())}"


def _edges(c: np.ndarray) -> np.ndarray:
    """Cell edges around grid centres (half a spacing beyond the ends)."""
    c = np.asarray(c, dtype=float)
    if c.size == 1:
        return np.array([c[0] - 0.5, c[0] + 0.5])
    mid = 0.5 * (c[:-1] + c[1:])
    return np.concatenate([[c[0] - (mid[0] - c[0])], mid, [c[-1] + (c[-1] - mid[-1])]])


def _categories(res: BasinResult) -> np.ndarray:
    """0: has a value; 1: not converged; 2: failed; 3: flagged (not integrated)."""
    cat = np.zeros(res.status.shape, int)
    cat[res.not_converged] = 1
    cat[res.failed] = 2
    cat[~res.valid] = 3
    return cat


#: The kinds of `jaxsleigh.BasinStarts`, with their article, for messages.
_KIND_WORDS = {"grid": "a grid", "samples": "samples", "array": "an array"}


def _check_map(res: BasinResult, field: str) -> None:
    """Refuse starts that are not a grid with two varying coordinates, and an unknown ``field``."""
    st = res.starts
    if st.kind != "grid" or len(st.axes) != 2:
        raise ValueError(f"a map needs a grid with two varying coordinates (e.g. --x -3:3:64 --y -3:3:64); "
                         f"these starts are {_KIND_WORDS.get(st.kind, repr(st.kind))} varying "
                         f"{list(st.axes) or 'no grid axis'}: use "
                         f"plot_t_eps_scatter or plot_fraction_vs_theta")
    if field not in _FIELDS and not hasattr(res, field):
        raise ValueError(f"unknown field {field!r}; choose one of {sorted(_FIELDS)}")


def _map_values(res: BasinResult, field: str) -> tuple[np.ndarray, np.ndarray]:
    """``(values, categories)`` on the grid: the values drawn on the log scale (NaN where a flat colour is) and
    the `_categories` drawn flat (0 where a value is; for fields other than ``T_eps`` unsettled starts have one)."""
    data = np.asarray(res.map(field), dtype=float)
    cat = res.starts.reshape(_categories(res))
    if field == "T_eps":
        show = cat == 0
        floor = max(float(res.settings.get("dt", 0.01)), 1e-6)
        values = np.where(show, np.maximum(data, floor), np.nan)
    else:
        show = (cat == 0) | (cat == 1)
        values = np.where(show & np.isfinite(data) & (data > 0), data, np.nan)
        cat = np.where(cat == 1, 0, cat)
    return values, cat


def _draw_values(ax, he: np.ndarray, ve: np.ndarray, values: np.ndarray, res: BasinResult, field: str, cmap: str):
    """Draw the finite ``values`` on a log colour scale (up to the horizon for ``T_eps``); the mesh, or None when
    there is none."""
    from matplotlib.colors import LogNorm

    finite = values[np.isfinite(values)]
    if not finite.size:
        return None
    lo, hi = float(finite.min()), float(finite.max())
    if field == "T_eps":
        hi = max(hi, float(res.settings.get("t_final", hi)))
    if hi <= lo:
        hi = lo * 10.0
    return ax.pcolormesh(he, ve, np.ma.masked_invalid(values), cmap=cmap, norm=LogNorm(lo, hi),
                         shading="flat", rasterized=True)


def _draw_categories(ax, he: np.ndarray, ve: np.ndarray, cat: np.ndarray) -> np.ma.MaskedArray:
    """Draw the starts of categories 1-3 in their flat `CATEGORY_COLOURS`; the categories, masked where 0."""
    from matplotlib.colors import BoundaryNorm, ListedColormap

    colours = [CATEGORY_COLOURS[k] for k in ("not converged", "failed", "singular start")]
    cat_m = np.ma.masked_equal(cat, 0)
    if cat_m.count():
        ax.pcolormesh(he, ve, cat_m, cmap=ListedColormap(colours), norm=BoundaryNorm([0.5, 1.5, 2.5, 3.5], 3),
                      shading="flat", rasterized=True)
    return cat_m


def _frame_map(ax, st, he: np.ndarray, ve: np.ndarray) -> bool:
    """The singular set ``theta = 0`` as a dashed line (when ``theta`` is an axis), the labels, limits and aspect;
    whether the line was drawn."""
    h_name, v_name = st.axes
    line = "theta" in st.axes
    if line:
        draw = ax.axhline if v_name == "theta" else ax.axvline
        draw(0.0, color=_SINGULAR_LINE, linestyle="--", linewidth=1.4)
    ax.set_xlabel(_LABELS[h_name])
    ax.set_ylabel(_LABELS[v_name])
    ax.set_xlim(he[0], he[-1])
    ax.set_ylim(ve[0], ve[-1])
    if {h_name, v_name} == {"x", "y"}:
        ax.set_aspect("equal")
    return line


def _map_title(st, field: str) -> str:
    """The map's title: what is drawn and at which fixed coordinate (saying when the slice misses ``theta = 0``)."""
    fixed = [c for c in ("x", "y", "theta") if c not in st.axes]
    at = ", ".join(f"{'θ₀' if c == 'theta' else c + '₀'} = {st.axis(c).lo:.4g}" for c in fixed)
    if "theta" in fixed:
        at += " (the singular set θ = 0 is not in this slice)"
    # T_eps maps show which starts settled within the horizon (grey: not by T), not a basin of
    # attraction in the control sense
    name = f"Convergence time {T_EPS} of the starts settled within the horizon" if field == "T_eps" \
        else _FIELDS.get(field, field)
    return f"{name} at {at}" if at else name


def _map_legend(fig, ax, own: bool, cat_m: np.ma.MaskedArray, line: bool) -> None:
    """The legend of the flat colours present (and of the singular line): under its own figure, or in the axes."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    present = set(np.unique(cat_m.compressed()).tolist())
    texts = {"not converged": f"not settled by T ({T_EPS} = ∞)", "failed": "failed (status ≥ 3)",
             "singular start": "θ₀ = 0: not integrated"}
    handles = [Patch(facecolor=CATEGORY_COLOURS[n], edgecolor="0.5", linewidth=0.5, label=text)
               for i, (n, text) in enumerate(texts.items(), start=1) if i in present]
    if line:
        handles.append(Line2D([], [], color=_SINGULAR_LINE, linestyle="--", linewidth=1.4, label="singular set θ = 0"))
    if handles and own:
        fig.legend(handles=handles, loc="outside lower center", ncol=min(4, len(handles)), fontsize=8, frameon=False)
    elif handles:
        ax.legend(handles=handles, loc="upper right", fontsize=7, framealpha=0.85)


def plot_basin_map(res: BasinResult, ax=None, *, field: str = "T_eps", cmap: str = "viridis",
                   legend: bool = True, colorbar: bool = True, stamp: bool = True):
    """Heat map of ``field`` (default ``T_eps``) over a grid with two varying coordinates.

    The colour scale is logarithmic. For ``T_eps`` the starts without a convergence time are drawn
    flat: light grey (reached the horizon outside the ball), red (failed before the horizon) and
    black (``theta0 = 0``, not integrated); for other fields only failed and flagged starts are.
    The singular set ``theta = 0`` is drawn as a dashed line when ``theta`` is an axis of the map
    (an x-y map at fixed ``theta0`` does not meet it; the title says so). ``stamp=False`` leaves
    out the provenance line along the top edge (as for every figure of this module), for a
    publication.

    Returns:
      The `matplotlib.figure.Figure`.
    """
    _check_map(res, field)
    st = res.starts
    h_name, v_name = st.axes
    hv, vv = st.axis(h_name).values(), st.axis(v_name).values()
    fig, ax, own = figure_and_axes(ax, (7.2, 6.4))
    values, cat = _map_values(res, field)
    he, ve = _edges(hv), _edges(vv)
    mesh = _draw_values(ax, he, ve, values, res, field, cmap)
    cat_m = _draw_categories(ax, he, ve, cat)
    line = _frame_map(ax, st, he, ve)
    _titled(fig, ax, own, _map_title(st, field), res, stamp, fraction_on_axes=True)
    if colorbar and mesh is not None:
        fig.colorbar(mesh, ax=ax, label=_FIELDS.get(field, field) + " (log scale)", shrink=0.9)
    if legend:
        _map_legend(fig, ax, own, cat_m, line)
    return fig


def plot_fraction_vs_theta(res: BasinResult, ax=None, *, bins=None, log_abs: bool = False, stamp: bool = True):
    """Fraction of starts converged within the horizon against ``theta0``, with ``± se`` bars.

    Grid rows of equal ``theta0`` form the groups (``bins=None``) when there are at most 256
    distinct values; otherwise (samples) 24 bins. ``log_abs=True`` plots against ``|theta0|`` on a
    log axis (log-spaced bins), which resolves the approach to the singular set.
    """
    theta = res.ics[:, 2]
    x = np.abs(theta) if log_abs else theta
    ok = res.valid & np.isfinite(x) & ((x > 0) if log_abs else True)
    if bins is None and np.unique(x[ok]).size > 256:
        bins = 24
    if bins is not None and log_abs and np.ndim(bins) == 0 and ok.any():
        lo, hi = float(x[ok].min()), float(x[ok].max())
        bins = np.geomspace(lo, hi * (1 + 1e-12), int(bins) + 1) if hi > lo else int(bins)
    return _fraction_figure(res, ax, x, ok, bins, "|θ₀| [rad]" if log_abs else "θ₀ [rad]",
                            "Fraction converged against the initial heading", stamp, log_x=log_abs,
                            singular_line=not log_abs)


def plot_fraction_vs_distance(res: BasinResult, ax=None, *, bins: int = 16, stamp: bool = True):
    """Fraction converged against the initial distance \\(\\sqrt{x_0^2 + y_0^2}\\) (equal-width
    bins, ``± se`` bars): the view of an x-y slice at fixed heading."""
    return _fraction_figure(res, ax, np.hypot(res.ics[:, 0], res.ics[:, 1]), res.valid, bins,
                            "initial distance √(x₀² + y₀²) [m]", "Fraction converged against the initial distance",
                            stamp)


def _fraction_figure(res: BasinResult, ax, x, ok, bins, xlabel: str, title: str, stamp: bool, *,
                     log_x: bool = False, singular_line: bool = False):
    """The fraction of the starts ``ok`` converged against ``x`` in ``bins`` (`fraction_by`), with ``± se`` bars
    (a log x-axis with ``log_x``; the singular set ``theta = 0`` dashed with ``singular_line``); the figure."""
    fig, ax, own = figure_and_axes(ax, (6.4, 4.2))
    c, f, se, n = fraction_by(x, res.converged, ok, bins=bins)
    ax.errorbar(c, f, yerr=se, fmt="o-", markersize=3, linewidth=1.0, capsize=2, color="C0",
                label="fraction converged ± s.e.")
    if log_x:
        ax.set_xscale("log")
    if singular_line:
        ax.axvline(0.0, color=_SINGULAR_LINE, linestyle="--", linewidth=1.2, label="singular set θ = 0")
    ax.set_xlabel(xlabel)
    ax.set_ylim(-0.03, 1.03)
    ax.set_ylabel("fraction converged")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    return _titled(fig, ax, own, title, res, stamp)


def plot_t_eps_distribution(res: BasinResult, ax=None, *, bins: int = 40, stamp: bool = True):
    """Histogram of ``T_eps`` of the converged starts and, on the right axis, the fraction of valid
    starts converged by time t (which ends at the fraction converged at the horizon)."""
    fig, ax, own = figure_and_axes(ax, (6.4, 4.2))
    t_final = float(res.settings.get("t_final", np.nanmax(res.T_eps[res.converged], initial=1.0)))
    T = res.T_eps[res.converged]
    n_valid = int(res.valid.sum())
    ax.hist(T, bins=np.linspace(0.0, t_final, bins + 1), color="C0", alpha=0.75)
    ax.set_xlim(0.0, t_final)
    ax.set_xlabel(f"{T_EPS} [s]")
    ax.set_ylabel("starts per bin")
    ax.grid(True, alpha=0.3)
    right = ax.twinx()
    ts = np.sort(T)
    if n_valid:
        right.step(np.concatenate([[0.0], ts, [t_final]]),
                   np.concatenate([[0.0], np.arange(1, ts.size + 1), [ts.size]]) / n_valid,
                   where="post", color="C3", linewidth=1.3)
    right.set_ylim(0.0, 1.02)
    right.set_ylabel("fraction converged by t", color="C3")
    pct = t_eps_percentiles(T, (50.0,))[0]
    if np.isfinite(pct):
        ax.axvline(pct, color="k", linestyle=":", linewidth=1.0)
        ax.text(pct, ax.get_ylim()[1] * 0.97, f" median {pct:.3g} s", fontsize=7, va="top")
    note = (f"not settled by T: {int(res.not_converged.sum())}, failed: {int(res.failed.sum())}, "
            f"not integrated: {int((~res.valid).sum())}")
    # under the x label, wherever the layout puts it (a fixed offset in axes units overlapped the
    # label in the small panel of plot_basin); as an annotation of the axes the constrained layout
    # keeps room for it
    ax.annotate(note, xy=(0.0, 0.0), xycoords=("axes fraction", ax.xaxis.label), xytext=(0, -2),
                textcoords="offset points", ha="left", va="top", fontsize=7, color="0.3", gid=FOOTER_GID)
    title = "Distribution of the convergence time"
    return _titled(fig, ax, own, title, res, stamp)


def plot_t_eps_scatter(res: BasinResult, ax=None, *, stamp: bool = True):
    """``T_eps`` against ``|theta0|`` (log x); starts not settled by the horizon are drawn at the
    horizon (grey triangles), failed ones there too (red crosses)."""
    fig, ax, own = figure_and_axes(ax, (6.4, 4.6))
    th = np.abs(res.ics[:, 2])
    t_final = float(res.settings.get("t_final", 1.0))
    conv, nc, fail = res.converged, res.not_converged, res.failed
    size = 4 if res.status.size > 2000 else 10
    floor = max(float(res.settings.get("dt", 0.01)), 1e-6)
    ax.scatter(th[conv], np.maximum(res.T_eps[conv], floor), s=size, color="C0", alpha=0.6, linewidths=0,
               label=f"converged ({int(conv.sum())})")
    ax.scatter(th[nc], np.full(int(nc.sum()), t_final), s=size + 6, marker="^",
               color=CATEGORY_COLOURS["not converged"], edgecolors="0.4", linewidths=0.3,
               label=f"not settled by T ({int(nc.sum())})")
    ax.scatter(th[fail], np.full(int(fail.sum()), t_final), s=size + 10, marker="x",
               color=CATEGORY_COLOURS["failed"], label=f"failed ({int(fail.sum())})")
    ax.set_xscale("log")
    ax.set_ylim(0.0, 1.05 * t_final)
    ax.set_xlabel("|θ₀| [rad]")
    ax.set_ylabel(f"{T_EPS} [s]")
    ax.grid(True, which="both", alpha=0.25)
    ax.legend(fontsize=7, loc="best")
    title = "Convergence time against the distance to the singular set"
    return _titled(fig, ax, own, title, res, stamp)


def plot_basin(res: BasinResult, *, stamp: bool = True):
    """Overview: the ``T_eps`` map (2-D grids) or the ``T_eps``-against-``|theta0|`` scatter, the
    fraction against ``theta0`` (against the initial distance when ``theta0`` is the same for all
    starts) and the ``T_eps`` distribution. The title says what the map is: which starts settled
    within the horizon (grey: not by ``T``), not a basin of attraction in the control sense."""
    fig = new_figure((13.0, 6.2))
    gs = fig.add_gridspec(2, 2, width_ratios=[1.35, 1.0])
    main = fig.add_subplot(gs[:, 0])
    if res.starts.kind == "grid" and len(res.starts.axes) == 2:
        plot_basin_map(res, main)
    else:
        plot_t_eps_scatter(res, main)
    if np.unique(res.ics[res.valid, 2]).size > 1:
        plot_fraction_vs_theta(res, fig.add_subplot(gs[0, 1]), log_abs=res.starts.kind != "grid")
    else:
        plot_fraction_vs_distance(res, fig.add_subplot(gs[0, 1]))
    plot_t_eps_distribution(res, fig.add_subplot(gs[1, 1]))
    fig.suptitle(f"Starts settled within the horizon: |q| ≤ ε from {T_EPS} to T ({_provenance(res)})",
                 fontsize=11)
    _stamp(fig, res, stamp)
    return fig


def plot_power_laws(x, series: Mapping[str, np.ndarray], ax=None, *, fits: Optional[Mapping] = None,
                    fit_ranges: Optional[Mapping] = None, expected: Optional[Mapping[str, float]] = None,
                    xlabel: str = "|θ₀| [rad]", ylabel: str = "", title: str = ""):
    """Log-log points of each series against ``x`` with its fitted power law.

    Args:
      x: (n,) abscissa (e.g. ``|theta0|``).
      series: label -> (n,) values (non-finite or non-positive points are skipped).
      fits: label -> `PowerLawFit`, drawn as a line.
      fit_ranges: label -> ``(lo, hi)``, the range of ``x`` the fit used (default: the series').
      expected: label -> the exponent expected from theory, added to the legend.
    """
    fig, ax, own = figure_and_axes(ax, (6.2, 4.6))
    x = np.asarray(x, dtype=float)
    for i, (label, y) in enumerate(series.items()):
        y = np.asarray(y, dtype=float)
        ok = np.isfinite(y) & (y > 0) & np.isfinite(x) & (x > 0)
        text = label
        fit = None if fits is None else fits.get(label)
        if fit is not None:
            text += f": slope {fit.exponent:.2f} ± {fit.exponent_se:.2f}"
        if expected is not None and label in expected:
            text += f" (expected {expected[label]:g})"
        ax.loglog(x[ok], y[ok], "o", color=f"C{i}", markersize=4, label=text)
        if fit is not None and ok.any():
            lo, hi = (x[ok].min(), x[ok].max()) if fit_ranges is None or label not in fit_ranges \
                else fit_ranges[label]
            xs = np.geomspace(lo, hi, 50)
            ax.loglog(xs, fit(xs), "-", color=f"C{i}", linewidth=1.0, alpha=0.8)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(True, which="both", alpha=0.25)
    ax.legend(fontsize=7, loc="best")
    if title:
        (fig.suptitle if own else ax.set_title)(title, fontsize=10)
    return fig
