"""Figures of controller comparisons (`jaxsleigh.studies.compare`): the table as a figure, and a measure
against an actuator's number (sampling period, saturation level), one curve per controller."""
from __future__ import annotations

import numpy as np

from .base import new_figure, save_figure, stamp

__all__ = ["plot_compare_table", "plot_against"]

_COLUMNS = (("settled", "settled", lambda v: f"{100 * v:.0f}%"),
            ("median_T", "median T [s]", lambda v: f"{v:.3g}"),
            ("p90_T", "p90 T [s]", lambda v: f"{v:.3g}"),
            ("energy_p50", "energy p50", lambda v: f"{v:.3g}"),
            ("energy_p90", "energy p90", lambda v: f"{v:.3g}"),
            ("u_peak_max", "peak |u|", lambda v: f"{v:.3g}"),
            ("min_abs_theta", "min |θ|", lambda v: f"{v:.2g}"))


def plot_compare_table(record: dict, path=None, *, title: str = "Controllers on the same plant and starts",
                       show_stamp: bool = True):
    """The rows of a comparison (``record["rows"]``, as ``jaxsleigh compare`` writes them) as a table figure,
    the best value of each column per start set in bold (most settled, shortest times, least energy and
    peak force). Saved to ``path`` when given; returns the figure."""
    rows = record["rows"]
    header = ["controller", "starts"] + [c[1] for c in _COLUMNS]
    cells = [[r["controller"], r["starts"]] + [fmt(r[k]) for k, _, fmt in _COLUMNS] for r in rows]
    fig = new_figure((1.25 * len(header) + 0.5, 0.32 * len(rows) + 1.4))
    ax = fig.subplots()
    ax.axis("off")
    table = ax.table(cellText=cells, colLabels=header, loc="center", cellLoc="center")
    table.auto_set_font_size(False)
    table.set_fontsize(8)
    table.scale(1.0, 1.25)
    for j, (key, _, _) in enumerate(_COLUMNS):
        for start in {r["starts"] for r in rows}:
            idx = [i for i, r in enumerate(rows) if r["starts"] == start]
            vals = np.array([rows[i][key] for i in idx], np.float64)
            if not np.isfinite(vals).any() or key == "min_abs_theta":
                continue
            best = np.nanmax(vals) if key == "settled" else np.nanmin(vals)
            for i, v in zip(idx, vals):
                if v == best:
                    table[i + 1, j + 2].set_text_props(fontweight="bold")
    s = record.get("settings", {})
    fig.suptitle(f"{title}\n{s.get('samples', '?')} starts per distribution, T = {s.get('t_final', 0):g} s, "
                 f"saturation {s.get('saturation')}, sample period {s.get('sample_period')}", fontsize=9)
    if show_stamp:
        stamp(fig, {"dtype": s.get("dtype"), "t_final": s.get("t_final"), "eps": s.get("eps")},
              record.get("run_info"))
    if path is not None:
        save_figure(fig, path)
    return fig


def plot_against(curves: dict, xlabel: str, ylabel: str = "fraction settled", path=None, *, title: str = "",
                 log_x: bool = True, provenance: str = ""):
    """One curve per controller: ``curves = {name: (x, y)}``. Saved to ``path`` when given; returns the
    figure."""
    fig = new_figure((5.6, 4.0))
    ax = fig.subplots()
    for name, (x, y) in curves.items():
        ax.plot(x, y, "o-", label=name)
    if log_x:
        ax.set_xscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.suptitle(title + (f"\n{provenance}" if provenance else ""), fontsize=9)
    if path is not None:
        save_figure(fig, path)
    return fig
