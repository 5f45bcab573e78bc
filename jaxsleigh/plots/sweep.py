"""Figures of parameter sweeps (`jaxsleigh.sweep`): the fraction converged and the ``T_eps``
percentiles against one parameter, or heat maps over a grid of two."""
from __future__ import annotations

from typing import Optional

import numpy as np

from .base import T_EPS, figure_and_axes
from ..studies.sweep import SweepResult

__all__ = ["plot_sweep", "plot_sweep_line", "plot_sweep_grid"]

_LABELS = {"k": "k", "l1": "$L_1$", "l2": "$L_2$", "l3": "$L_3$", "d11": r"$\hat D_{11}$", "d22": r"$\hat D_{22}$",
           "d12": r"$\hat D_{12}$", "m": "m [kg]", "J": "J [kg m$^2$]", "l": "l [m]",
           "coulomb_eps": r"Coulomb $\epsilon$", "coulomb_scale": "Coulomb scale c", "c1": "viscous $c_1$",
           "c2": "viscous $c_2$"}


def _subtitle(res: SweepResult) -> str:
    s = res.settings
    return (f"{res.ics.shape[0]} starts x {res.values.shape[0]} values; converged: |q| <= {s.get('eps', 0):g} "
            f"from {T_EPS} to {s.get('t_final', 0):g} s; {s.get('dtype', '')}")


def _panels(res: SweepResult, axes, width: float, height: float):
    """``(fig, axes)``: the given axes, or a new row of ``width`` x ``height`` inch panels, three when the effort
    was recorded (else two)."""
    effort = axes is None and any(np.isfinite(v).any() for v in res.effort_medians().values())
    n = len(axes) if axes is not None else 3 if effort else 2
    fig, axes, _ = figure_and_axes(axes, (width * n, height), (1, n))
    return fig, axes


def plot_sweep_line(res: SweepResult, axes=None, *, column: int = 0):
    """Panels against parameter ``res.names[column]``: the fraction converged (+- 1 s.e.), the
    ``T_eps`` percentiles 10/50/90 of the converged starts (25-75 shaded) and, when the effort was
    recorded, the median control energy and median peak ``||u||`` of the converged starts (a third
    panel; pass two ``axes`` to leave it out)."""
    fig, axes = _panels(res, axes, 5.4, 4.2)
    ax_f, ax_t = axes[0], axes[1]
    x = res.values[:, column]
    order = np.argsort(x, kind="stable")
    x = x[order]
    S, se = (a[order] for a in res.fractions())
    pct = res.percentiles()[order]
    if len(axes) > 2:
        _draw_effort_medians(axes[2], x, order, res.effort_medians())
    _draw_fraction(ax_f, x, S, se)
    _draw_t_eps_percentiles(ax_t, x, pct)
    log = _log_x(res, column, x)
    for ax in axes:
        ax.set_xlabel(_LABELS.get(res.names[column], res.names[column]))
        if log:
            ax.set_xscale("log")
        ax.grid(alpha=0.3)
    fig.suptitle(_subtitle(res), fontsize=9)
    return fig


def _draw_effort_medians(ax_e, x, order, eff):
    """The median control energy (log axis where it spans more than a factor 20) and, on a twin axis, the median
    peak ``||u||`` of the converged starts (``eff``: `SweepResult.effort_medians`, whose rows ``order`` sorts by ``x``)."""
    e = eff.get("u_energy_median", np.full(x.size, np.nan))[order]
    pk = eff.get("u_norm_peak_median", np.full(x.size, np.nan))[order]
    ax_e.plot(x, e, "o-", ms=4, color="C2", label=r"median $\int_0^T \|u\|^2 dt$")
    ax_e.set_ylabel("median control energy", color="C2")
    ax_p = ax_e.twinx()
    ax_p.plot(x, pk, "s--", ms=4, color="C4", label=r"median peak $\|u\|$")
    ax_p.set_ylabel(r"median peak $\|u\|$", color="C4")
    ax_e.set_title("control effort of the converged starts", fontsize=10)
    fin = e[np.isfinite(e)]
    if fin.size > 1 and fin.min() > 0 and fin.max() / fin.min() > 20:
        ax_e.set_yscale("log")
    ax_e.legend(handles=ax_e.get_lines() + ax_p.get_lines(), fontsize=8)


def _draw_fraction(ax_f, x, S, se):
    """The fraction converged with its standard error."""
    ax_f.errorbar(x, S, yerr=se, marker="o", ms=4, capsize=3, color="C0")
    ax_f.set_ylim(-0.03, 1.03)
    ax_f.set_ylabel("fraction converged")


def _draw_t_eps_percentiles(ax_t, x, pct):
    """The ``T_eps`` percentiles 10/50/90 of the converged starts (``pct``'s columns 0, 2, 4), 25-75 shaded."""
    ax_t.fill_between(x, pct[:, 1], pct[:, 3], color="C1", alpha=0.25, lw=0, label="p25-p75")
    for j, (q, ls) in enumerate(((10, ":"), (50, "-"), (90, "--"))):
        ax_t.plot(x, pct[:, [0, 2, 4][j]], ls, color="C1", marker="o" if q == 50 else None, ms=4, label=f"p{q}")
    ax_t.set_ylabel(f"{T_EPS} of the converged [s]")
    ax_t.legend(fontsize=8)


def _log_x(res: SweepResult, column: int, x) -> bool:
    """A log x-axis: the grid axis of the parameter is log-spaced or, for explicit value sets, the values are
    positive and span more than a factor 20."""
    return any(a.log for a in res.axes if a.name == res.names[column]) or (
        not res.axes and np.all(x > 0) and x.max() / x.min() > 20)


def plot_sweep_grid(res: SweepResult, axes=None):
    """Heat maps over a grid of two parameters: the fraction converged, the median ``T_eps`` and,
    when the effort was recorded, the median control energy of the converged starts (rows: the
    first parameter, columns: the second; pass two ``axes`` to leave the third out)."""
    if len(res.grid_shape) != 2:
        raise ValueError("a heat map needs a sweep over two parameters (two --param)")
    fig, axes = _panels(res, axes, 5.75, 4.6)
    n1, n2 = res.grid_shape
    a1, a2 = res.axes if res.axes else (None, None)
    v1 = res.values[::n2, 0]
    v2 = res.values[:n2, 1]
    S = res.fraction.reshape(n1, n2)
    med = res.percentiles((50.0,))[:, 0].reshape(n1, n2)
    panels = [(axes[0], S, "fraction converged", "viridis", (0, 1)),
              (axes[1], med, f"median {T_EPS} of the converged [s]", "magma_r", (None, None))]
    if len(axes) > 2:
        energy = res.effort_medians().get("u_energy_median", np.full(n1 * n2, np.nan)).reshape(n1, n2)
        panels.append((axes[2], energy, r"median $\int_0^T \|u\|^2 dt$ of the converged", "cividis",
                       (None, None)))
    for ax, data, title, cmap, vr in panels:
        im = ax.imshow(data, origin="lower", aspect="auto", cmap=cmap, vmin=vr[0], vmax=vr[1],
                       extent=(-0.5, n2 - 0.5, -0.5, n1 - 0.5))
        ax.set_xticks(range(n2), [f"{v:.3g}" for v in v2], rotation=45 if n2 > 6 else 0, fontsize=8)
        ax.set_yticks(range(n1), [f"{v:.3g}" for v in v1], fontsize=8)
        ax.set_xlabel(_LABELS.get(res.names[1], res.names[1]) + (" (log spaced)" if a2 is not None and a2.log else ""))
        ax.set_ylabel(_LABELS.get(res.names[0], res.names[0]) + (" (log spaced)" if a1 is not None and a1.log else ""))
        ax.set_title(title, fontsize=10)
        fig.colorbar(im, ax=ax)
        if n1 * n2 <= 64:
            for i in range(n1):
                for j in range(n2):
                    if np.isfinite(data[i, j]):
                        ax.text(j, i, f"{data[i, j]:.2g}", ha="center", va="center", fontsize=7, color="w")
    fig.suptitle(_subtitle(res), fontsize=9)
    return fig


def plot_sweep(res: SweepResult, axes: Optional[object] = None):
    """The figure ``jaxsleigh sweep --plot`` draws: `plot_sweep_grid` for two parameters, else
    `plot_sweep_line` against the first."""
    if len(res.grid_shape) == 2:
        return plot_sweep_grid(res, axes)
    return plot_sweep_line(res, axes)
