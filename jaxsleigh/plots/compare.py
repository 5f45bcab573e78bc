r"""Figures of controller comparisons (`jaxsleigh.studies.compare`).

* `plot_compare_ecdf`: the laws side by side, one row of panels per start distribution: the empirical
  distribution (ECDF) of \(T_\varepsilon\) over the starts (the settled fraction against time; starts that
  did not settle keep a law's curve below 1) and of the control energy \(\int_0^T \|u\|^2 dt\) (log axis;
  starts whose integration failed keep it below 1).
* `plot_against`: a measure against an actuator's number (sampling period, saturation level), one curve per
  controller.
"""
from __future__ import annotations

import textwrap

import numpy as np

from .base import T_EPS, figure_and_axes, save_figure, stamp
from ..controllers.registry import controller_names

__all__ = ["plot_compare_ecdf", "ecdf_steps", "plot_against", "ENERGY_LABEL"]

#: The control energy's axis label: \(\int_0^T \|u\|^2 dt\) with u = (force [N], torque [N m]).
ENERGY_LABEL = r"control energy $E = \int_0^T \|u\|^2\,dt$  [N² s, (N m)² s]"


def _values(xs) -> np.ndarray:
    """A JSON list (``null``: did not settle, not defined) as float64, ``null`` as NaN."""
    return np.array([np.nan if x is None else x for x in xs], np.float64)


def ecdf_steps(values, n: int, *, start: float, end: float):
    r"""The empirical distribution of the finite ``values`` over ``n`` starts as a step curve ``(x, y)`` from
    ``(start, 0)`` to ``end``: \(F(x) = \#\{i : v_i \le x\} / n\). Non-finite values (a start that did not settle,
    or failed) never count, so the curve ends at the finite share, below 1 when some are missing.
    Draw with ``drawstyle="steps-post"``."""
    v = np.asarray(values, np.float64)
    v = np.sort(v[np.isfinite(v)])
    y = np.arange(1, v.size + 1) / max(int(n), 1)
    top = y[-1] if y.size else 0.0
    return np.concatenate([[start], v, [end]]), np.concatenate([[0.0], y, [top]])


def _settings_line(record: dict) -> str:
    """``'256 starts per distribution · float32 · horizon 100 s · ε = 0.05'``, with the saturation, the sample
    period and the equal-energy budget only when the run had them."""
    s = record.get("settings", {})
    parts = [f"{s['samples']} starts per distribution" if "samples" in s else None, s.get("dtype"),
             f"horizon T = {float(s['t_final']):g} s" if "t_final" in s else None,
             f"ε = {float(s['eps']):g}" if "eps" in s else None]
    if s.get("saturation") is not None:
        parts.append(f"saturation |u_i| ≤ {float(s['saturation']):g}")
    if s.get("sample_period") is not None:
        parts.append(f"zero-order hold every {float(s['sample_period']):g} s"
                     + (f", delay {s['delay']} samples" if s.get("delay") else "")
                     + (f", noise σ = {float(s['noise']):g}" if s.get("noise") else ""))
    eq = record.get("equal_energy")
    if eq:
        parts.append(f"literature laws tuned to the paper's training energy {float(eq['budget']):.3g} N² s")
    return "  ·  ".join(p for p in parts if p)


_DASHES = ("-", "--", "-.", ":", (0, (6, 2, 1, 2, 1, 2)))


def _law_styles(names) -> dict:
    """One colour and dash pattern per law, the same in every panel (laws with equal curves stay visible) and in
    every figure (a law of `jaxsleigh.controllers.registry` keeps its place in that list)."""
    order = controller_names() + [n for n in names if n not in controller_names()]
    return {n: {"color": f"C{order.index(n) % 10}", "linestyle": _DASHES[order.index(n) % len(_DASHES)]}
            for n in names}


def _draw_distribution(ax_t, ax_e, rows, styles, t_final: float) -> None:
    """One start distribution: ECDFs of T_eps (left) and of the energy (right), one curve per law."""
    energies = [e for r in rows for e in _values(r["per_start"]["energy"]) if np.isfinite(e) and e > 0]
    lo, hi = (min(energies), max(energies)) if energies else (1e-3, 1.0)
    for r in rows:
        name, n = r["controller"], len(r["per_start"]["T_eps"])
        T = _values(r["per_start"]["T_eps"])
        x, y = ecdf_steps(T, n, start=0.0, end=t_final)
        ax_t.plot(x, y, drawstyle="steps-post", lw=1.6, **styles[name],
                  label=f"{name}: {np.sum(np.isfinite(T))}/{n} settled")
        E = _values(r["per_start"]["energy"])
        E = np.where(E > 0, E, np.nan)
        x, y = ecdf_steps(E, n, start=lo, end=hi * 1.5)
        ax_e.plot(x, y, drawstyle="steps-post", lw=1.6, label=name, **styles[name])
    ax_t.set_xlim(0.0, t_final)
    ax_t.set_xlabel(f"{T_EPS} [s]")
    ax_t.set_ylabel(f"settled fraction ({T_EPS} ≤ t)")
    ax_t.legend(fontsize=7, loc="best", framealpha=0.85)
    ax_e.set_xscale("log")
    ax_e.set_xlim(lo / 1.5, hi * 1.5)
    ax_e.set_xlabel(ENERGY_LABEL)
    ax_e.set_ylabel("fraction of starts with energy ≤ E")
    for ax in (ax_t, ax_e):
        ax.set_ylim(-0.02, 1.04)
        ax.axhline(1.0, color="0.6", lw=0.6, ls=":")
        ax.grid(alpha=0.3)


def plot_compare_ecdf(record: dict, path=None, *, title: str = "Controllers on the same plant and starts",
                      show_stamp: bool = True):
    r"""The laws of a comparison side by side (``record`` as ``jaxsleigh compare`` writes it; its rows must carry
    ``per_start``): one row of panels per start distribution, left the ECDF of \(T_\varepsilon\) (the settled
    fraction against time, reaching the settled share at the horizon), right the ECDF of the control energy on
    a log axis. The subtitle says how many starts, the dtype, the horizon, the actuator (when set) and the
    command. Saved to ``path`` when given; returns the figure."""
    rows = record["rows"]
    if any("per_start" not in r for r in rows):
        raise ValueError("the record's rows carry no per-start values (per_start): it was written by an older "
                         "version; rerun jaxsleigh compare to get them")
    dists = list(dict.fromkeys(r["starts"] for r in rows))
    styles = _law_styles(dict.fromkeys(r["controller"] for r in rows))
    s = record.get("settings", {})
    t_final = float(s.get("t_final") or max((t for r in rows for t in r["per_start"]["T_eps"] if t is not None),
                                            default=1.0))
    described = s.get("starts") if isinstance(s.get("starts"), dict) else {}
    fig, axes, _ = figure_and_axes(None, (11.0, 2.9 * len(dists) + 1.3), (len(dists), 2))
    for ax_t, ax_e, d in zip(axes[::2], axes[1::2], dists):
        _draw_distribution(ax_t, ax_e, [r for r in rows if r["starts"] == d], styles, t_final)
        ax_t.set_title(f"{d} starts" + (f": {described[d]}" if d in described else ""), fontsize=9, loc="left")
    command = " ".join(str(c) for c in record.get("command", []))
    lines = [title, _settings_line(record)] + (textwrap.wrap(command, 150) if command else [])
    fig.suptitle("\n".join(lines), fontsize=9)
    if show_stamp:
        stamp(fig, {k: s[k] for k in ("dtype", "method", "dt", "eps", "t_final") if s.get(k) is not None},
              record.get("run_info"))
    if path is not None:
        save_figure(fig, path)
    return fig


def plot_against(curves: dict, xlabel: str, ylabel: str = "fraction settled", path=None, *, title: str = "",
                 log_x: bool = True, provenance: str = ""):
    """One curve per controller: ``curves = {name: (x, y)}``. Saved to ``path`` when given; returns the
    figure."""
    fig, ax, _ = figure_and_axes(None, (5.6, 4.0))
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
