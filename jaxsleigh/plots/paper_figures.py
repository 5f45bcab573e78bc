"""Figures of the paper's Section 5 from a `Solution`.

* `plot_paths`: paths in the x-y plane with the sleigh drawn ghosted at each start and solid at
  the target (paper Fig. 2).
* `plot_configuration`, `plot_momentum`, `plot_control`: time histories of
  ``q``, ``p`` and ``u`` (paper Figs. 3-5).
* `plot_hamiltonian`: the closed-loop Hamiltonian ``H_d(t)`` on a log scale.

Figures are built with the object-oriented API (`matplotlib.figure.Figure`), never through
``pyplot``: nothing here selects a backend or touches global GUI state, so the module works on
headless machines and inside other applications. To draw into your own figure, pass ``ax`` /
``axes`` (e.g. from ``plt.subplots``). `save_figure` writes PNG/PDF/SVG files. The scaffolding
(figures, provenance, saving) is shared with the other plotting modules in `jaxsleigh.plots.base`.

Each function accepts a ``Solution``, a mapping with the same keys (e.g. the ``.npz`` file written
by ``jaxsleigh simulate``, see `load_solution`) or any object with those attributes. Every
figure's title names the dtype and integration method that produced it, and a stamp along its top
edge adds the step, tolerances and the device (`jaxsleigh.plots.base.stamp`); trajectories
whose status is not ``OK`` are drawn dashed and flagged in the legend.
"""
from __future__ import annotations

import json
import math
from fractions import Fraction
from types import SimpleNamespace
from typing import Optional, Sequence

import numpy as np

from . import base as _pb
from .base import provenance, save_figure, stamp  # noqa: F401 (stamp: public before)
from ..status import Status
from ..files.npz import read_npz

__all__ = [
    "plot_paths",
    "plot_configuration",
    "plot_momentum",
    "plot_control",
    "plot_hamiltonian",
    "sleigh_outline",
    "format_start",
    "load_solution",
    "save_figure",
]



# ---------------------------------------------------------------------------------------------
# inputs
# ---------------------------------------------------------------------------------------------

def load_solution(path) -> SimpleNamespace:
    """Read an ``.npz`` written by ``jaxsleigh simulate`` / ``jaxsleigh paper`` for plotting.

    Returns a namespace with ``t, q, p, u, Hd, status, n_steps, settings`` (``settings`` decoded
    from ``settings_json``; it also holds ``ics`` and ``command``).
    """
    data = read_npz(path, "simulation file (written by jaxsleigh simulate / paper)",
                    ("t", "q", "p", "u", "Hd", "status"), kind="simulation")
    settings = json.loads(str(data["settings_json"])) if "settings_json" in data else {}
    return SimpleNamespace(t=data["t"], q=data["q"], p=data["p"], u=data["u"], Hd=data["Hd"],
                           status=data["status"], n_steps=data.get("n_steps"), settings=settings)


def _get(sol, name):
    if isinstance(sol, dict) or hasattr(sol, "files"):   # dict or NpzFile
        return sol[name]
    return getattr(sol, name)


def _run_info(sol) -> dict:
    """Wall time and devices of the run: the result's ``run_info``, or the file's ``settings_json["run_info"]``."""
    info = getattr(sol, "run_info", None)
    return dict(info) if info else dict(_settings(sol).get("run_info") or {})


def _settings(sol) -> dict:
    try:
        s = _get(sol, "settings")
    except (KeyError, AttributeError):
        s = None
    if s is None:
        try:
            s = json.loads(str(_get(sol, "settings_json")))
        except (KeyError, AttributeError):
            s = {}
    return dict(s)


def _arrays(sol):
    t = np.asarray(_get(sol, "t"), dtype=float)
    q = _batched(_get(sol, "q"))                 # a single trajectory (T, 3) as (1, T, 3)
    status = np.asarray(_get(sol, "status")).astype(int).reshape(-1)
    if q.shape[1] != t.shape[0]:
        raise ValueError(f"q has {q.shape[1]} time samples but t has {t.shape[0]}")
    return t, q, status


def _batched(a):
    """(T, k) for one trajectory -> (1, T, k)."""
    a = np.asarray(a, dtype=float)
    return a[None] if a.ndim == 2 else a


# ---------------------------------------------------------------------------------------------
# labels
# ---------------------------------------------------------------------------------------------

def _angle_text(theta: float) -> str:
    """theta as a small multiple of pi where it is one (``'3π/4'``), else ``'2.5'``."""
    if not math.isfinite(theta):
        return str(theta)
    if theta == 0:
        return "0"
    frac = Fraction(theta / math.pi).limit_denominator(16)
    # float32 solutions hold theta to ~1e-7 relative; small denominators cannot collide at 1e-6
    if frac != 0 and abs(float(frac) * math.pi - theta) < 1e-6 * max(1.0, abs(theta)):
        num, den = frac.numerator, frac.denominator
        sign = "−" if num < 0 else ""
        num = abs(num)
        head = "π" if num == 1 else f"{num}π"
        return f"{sign}{head}" if den == 1 else f"{sign}{head}/{den}"
    return _num_text(theta)


def _num_text(v: float) -> str:
    return f"{v:g}".replace("-", "−")


def format_start(q0, p0=None) -> str:
    """Legend text of a start: ``'(−3, −2, π/8)'``, with ``p0`` appended when non-zero."""
    q0 = np.asarray(q0, dtype=float)
    text = f"({_num_text(q0[0])}, {_num_text(q0[1])}, {_angle_text(q0[2])})"
    if p0 is not None:
        p0 = np.asarray(p0, dtype=float)
        if np.all(np.isfinite(p0)) and np.any(p0 != 0):
            text += f", p₀ = ({_num_text(p0[0])}, {_num_text(p0[1])})"
    return text


def _starts(sol, q) -> list[np.ndarray]:
    """Initial (x, y, theta[, p1, p2]) of each run; from the settings' ``ics`` when q(0) is NaN."""
    ics = _settings(sol).get("ics")
    return [np.asarray(ics[i], dtype=float) if ics is not None and i < len(ics) else q[i, 0] for i in range(q.shape[0])]


def _labels(sol, q, status, labels: Optional[Sequence[str]]) -> list[str]:
    if labels is None:                   # "run i" for a flagged start, whose initial condition is unknown
        labels = [format_start(s[:3], s[3:5] if s.size >= 5 else None) if np.any(np.isfinite(s)) else f"run {i}"
                  for i, s in enumerate(_starts(sol, q))]
    labels = [str(x) for x in labels]
    if len(labels) != q.shape[0]:
        raise ValueError(f"got {len(labels)} labels for {q.shape[0]} trajectories")
    return [lab if st == 0 else
            f"{lab}  [status {st}: {Status(st).name.lower() if st in Status._value2member_map_ else 'unknown'}]"
            for lab, st in zip(labels, status)]


def _style(i: int, st: int) -> dict:
    return {"color": f"C{i % 10}", "linestyle": "-" if st == 0 else "--", "linewidth": 1.4}


def _status_note(status, marker: str = "None", more: str = "") -> tuple[list, list]:
    """The legend entry of the runs drawn dashed (status not OK), ``more`` added to its text: ``([handle], [text])``,
    or two empty lists when every run is OK."""
    n_bad = int(np.sum(status != 0))
    if not n_bad:
        return [], []
    from matplotlib.lines import Line2D

    return ([Line2D([], [], color="0.4", linestyle="--", marker=marker)],
            [f"dashed: status ≠ 0 ({n_bad} run{'s' if n_bad > 1 else ''}, see jaxsleigh.status){more}"])


#: The title of the runs' legend.
_START_TITLE = "start (x₀ [m], y₀ [m], θ₀ [rad])"


def _ncol(labels, width_chars: int = 110) -> int:
    """Columns of a legend below the axes that fit the figure's width."""
    longest = max((len(s) for s in labels), default=1)
    return max(1, min(3, width_chars // (longest + 8)))


# ---------------------------------------------------------------------------------------------
# figure helpers
# ---------------------------------------------------------------------------------------------

def _time_figure(sol, series, ylabels, title, *, axes=None, yscales=None, figsize=None,
                 labels=None, legend=True, stamp=True):
    """Stacked time histories: ``series`` is a list of (N, T) arrays, one axis each."""
    t, q, status = _arrays(sol)
    fig, axes, own = _pb.figure_and_axes(axes, figsize or (7.0, 1.9 * len(series) + 1.2), (len(series), 1),
                                         sharex=True)
    names = _labels(sol, q, status, labels)
    _draw_series(axes, t, series, names, status, ylabels, yscales)
    _title(fig, axes[0], own, sol, title, stamp)
    if legend:
        _time_legend(fig, axes, own, status)
    return fig


def _draw_series(axes, t, series, names, status, ylabels, yscales):
    """One line per run on each axis (dashed where its status is not OK), its y-label and y-scale."""
    for k, (ax, data) in enumerate(zip(axes, series)):
        for i in range(data.shape[0]):
            ax.plot(t, data[i], label=names[i], **_style(i, int(status[i])))
        ax.set_ylabel(ylabels[k])
        ax.grid(True, alpha=0.3)
        if yscales is not None and yscales[k] is not None:
            yscales[k](ax, data)
    axes[-1].set_xlabel("time t [s]")
    axes[0].set_xlim(t[0], t[-1])


def _title(fig, ax, own, sol, title, with_stamp, span=""):
    """The title with the provenance (``'float32, adaptive RK4, dt = 0.01 s'``, and ``span``, e.g. the time interval):
    the figure's (and the stamp) when it is ``own``, else that of the (top) axes ``ax``."""
    what = provenance(_settings(sol))
    if own:
        fig.suptitle(f"{title}\n({what}{span})", fontsize=11)
        if _pb.check_stamp(with_stamp):
            _pb.stamp(fig, _settings(sol), _run_info(sol))
    else:
        ax.set_title(f"{title} ({what})", fontsize=10)


def _time_legend(fig, axes, own, status):
    """The runs' legend with the status note: below the figure when it is ``own``, else on the top axis."""
    handles, labs = axes[0].get_legend_handles_labels()
    note_handles, note = _status_note(status)
    handles, labs = handles + note_handles, labs + note
    if own:
        fig.legend(handles, labs, loc="outside lower center", ncol=min(_ncol(labs), len(labs)),
                   fontsize=8, title=_START_TITLE, title_fontsize=8, frameon=False)
    else:
        axes[0].legend(handles, labs, fontsize=7, title=_START_TITLE, title_fontsize=7)


# ---------------------------------------------------------------------------------------------
# Fig. 2: paths
# ---------------------------------------------------------------------------------------------

# Body outline of the sleigh in body coordinates, in units of the glyph length: the contact point
# (the knife edge) at the origin, the heading along +x; a rounded arrow whose nose lies past the
# centre of mass (at x = l).
_BODY = np.array([[-0.30, -0.32], [0.80, -0.32], [1.30, 0.0], [0.80, 0.32], [-0.30, 0.32]])
_BLADE = np.array([[-0.42, 0.0], [0.42, 0.0]])


def sleigh_outline(x: float, y: float, theta: float, *, size: float = 1.0) -> dict:
    """World coordinates of the sleigh glyph at pose ``(x, y, theta)``.

    Returns ``{"body": (5, 2), "blade": (2, 2), "contact": (2,), "com": (2,)}``: the body polygon,
    the knife edge through the contact point ``(x, y)`` along the heading, the contact point, and
    the centre of mass at distance ``size`` ahead along the heading (``size`` = ``l`` draws the
    sleigh to scale).
    """
    c, s = math.cos(theta), math.sin(theta)
    rot = np.array([[c, -s], [s, c]])
    origin = np.array([x, y], dtype=float)

    def world(pts):
        return origin + (size * pts) @ rot.T

    return {"body": world(_BODY), "blade": world(_BLADE), "contact": origin,
            "com": world(np.array([[1.0, 0.0]]))[0]}


def _draw_sleigh(ax, x, y, theta, *, size, color, alpha, zorder):
    from matplotlib.patches import Polygon

    g = sleigh_outline(x, y, theta, size=size)
    ax.add_patch(Polygon(g["body"], closed=True, facecolor=color, edgecolor=color, alpha=alpha,
                         linewidth=1.5, joinstyle="round", zorder=zorder))
    ax.plot(*g["blade"].T, color="k", alpha=max(alpha, 0.5) if alpha < 1 else 1.0, linewidth=2.2,
            solid_capstyle="round", zorder=zorder + 0.1)
    ax.plot(*g["com"], "o", color="red", alpha=alpha, markersize=4, zorder=zorder + 0.2)
    ax.plot(*g["contact"], "o", color="k", alpha=alpha, markersize=2.5, zorder=zorder + 0.2)


def _default_glyph_size(q, l_val: float) -> float:
    """Glyph length: to scale (CoM at ``l``) but at most 7 % of the extent of the paths."""
    finite = q[..., :2][np.all(np.isfinite(q[..., :2]), axis=-1)]
    extent = float(np.ptp(np.vstack([finite, [[0.0, 0.0]]]), axis=0).max()) if finite.size else 1.0
    return min(l_val if l_val > 0 else 0.5, 0.07 * max(extent, 1e-3))


def _draw_paths(ax, q, status, names, starts, glyph_size):
    """One path per run, its ghosted sleigh at the start, and a cross where a failed run stopped."""
    for i in range(q.shape[0]):
        st = int(status[i])
        style = _style(i, st)
        ax.plot(q[i, :, 0], q[i, :, 1], label=names[i], zorder=2, **style)
        s0 = starts[i]
        if np.all(np.isfinite(s0[:3])):
            _draw_sleigh(ax, s0[0], s0[1], s0[2], size=glyph_size, color=style["color"], alpha=0.3, zorder=3)
        fin = q[i, :, :]
        ok = np.flatnonzero(np.all(np.isfinite(fin), axis=1))
        if st != 0 and ok.size:      # where a failed run stopped
            ax.plot(*fin[ok[-1], :2], "x", color=style["color"], markersize=8, zorder=4)


def _glyph_scale_text(glyph_size: float, l_val: float) -> str:
    """How the sleigh glyph is scaled, for the legend (``to scale``, ``drawn at 0.5× scale``, ...)."""
    return "to scale" if l_val > 0 and abs(glyph_size - l_val) < 1e-12 else \
        f"drawn at {glyph_size / l_val:.2g}× scale" if l_val > 0 else f"CoM drawn {glyph_size:g} m ahead"


def _paths_legend(fig, ax, own, status, glyph_size, l_val):
    """Legend of the paths figure: runs, ghosted start sleigh, target and the status note."""
    from matplotlib.patches import Patch

    handles, labs = ax.get_legend_handles_labels()
    handles += [Patch(facecolor="0.5", alpha=0.3, edgecolor="0.5"), Patch(facecolor="0.25")]
    labs += [f"sleigh at start (ghosted, {_glyph_scale_text(glyph_size, l_val)})",
             "target (0, 0, 0); red dot: centre of mass"]
    note_handles, note = _status_note(status, marker="x", more="; ×: where it stopped")
    handles, labs = handles + note_handles, labs + note
    kw = dict(fontsize=7.5, title=_START_TITLE, title_fontsize=7.5)
    if own:
        fig.legend(handles, labs, loc="outside lower center", ncol=min(2, _ncol(labs, 115)),
                   frameon=False, **kw)
    else:
        ax.legend(handles, labs, loc="best", framealpha=0.85, **kw)


def plot_paths(sol, ax=None, *, labels: Optional[Sequence[str]] = None, glyph_size: Optional[float] = None,
               legend: bool = True, stamp: bool = True):
    """Paths of the contact point ``(x, y)`` (paper Fig. 2).

    Each run is a colour; the sleigh is drawn ghosted (alpha 0.3) at each start and solid (black)
    at the target ``(0, 0, 0)``. The glyph is a body outline along the heading with the knife edge
    at the contact point and the centre of mass (red dot) at distance ``glyph_size`` ahead
    (default: the plant's ``l``, i.e. to scale; 0.5 m for the knife edge ``l = 0``).

    Args:
      sol: a `Solution` (or mapping / npz with ``t, q, status``).
      ax: axes to draw into; a new figure is made when ``None``.
      labels: legend text per run (default: the start, e.g. ``(−3, −2, π/8)``).
      glyph_size: length scale of the sleigh glyph in metres.
      legend: draw the legend.
      stamp: write the provenance line (dtype, method, step, device) along the top edge; ``False``
        for a publication (the title still names the dtype and method).

    Returns:
      The `matplotlib.figure.Figure`.
    """
    t, q, status = _arrays(sol)
    l_val = float(_settings(sol).get("plant", {}).get("l", 1.0) or 0.0)
    if glyph_size is None:
        glyph_size = _default_glyph_size(q, l_val)
    fig, ax, own = _pb.figure_and_axes(ax, (6.6, 7.6))
    _draw_paths(ax, q, status, _labels(sol, q, status, labels), _starts(sol, q), glyph_size)
    # the target sits under the paths so that their final approach stays visible
    _draw_sleigh(ax, 0.0, 0.0, 0.0, size=glyph_size, color="0.25", alpha=1.0, zorder=1)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(True, alpha=0.3)
    ax.autoscale_view()
    _title(fig, ax, own, sol, "Paths of the contact point (x, y)", stamp, span=f", t ∈ [0, {t[-1]:g}] s")
    if legend:
        _paths_legend(fig, ax, own, status, glyph_size, l_val)
    return fig


# ---------------------------------------------------------------------------------------------
# Figs. 3-5 and H_d
# ---------------------------------------------------------------------------------------------

def plot_configuration(sol, axes=None, *, labels: Optional[Sequence[str]] = None, stamp: bool = True):
    """``x, y, theta`` against time, three stacked axes, one line per run (paper Fig. 3).
    ``stamp=False`` leaves out the provenance line (as for every figure of this module)."""
    _, q, _ = _arrays(sol)
    return _time_figure(sol, [q[..., 0], q[..., 1], q[..., 2]],
                        ["x [m]", "y [m]", "θ [rad]"], "Configuration q = (x, y, θ)",
                        axes=axes, labels=labels, stamp=stamp)


def plot_momentum(sol, axes=None, *, labels: Optional[Sequence[str]] = None, scale: str = "symlog",
                  linthresh: Optional[float] = None, stamp: bool = True):
    """Momenta ``p1`` (linear, kg m/s) and ``p2`` (angular, kg m²/s) against time (paper Fig. 4).

    The first instants carry a spike (``p2`` about 23 from the paper's starts, against values below
    1 afterwards), so the y-axes are ``scale="symlog"`` by default, as in `plot_control`
    (linear below ``linthresh``, default: the 90th percentile of ``|p|`` rounded up to a power of
    ten); ``scale="linear"`` shows the spike at full height. ``stamp=False``: no provenance line.
    """
    p = _batched(_get(sol, "p"))
    tf, suffix = _y_scale(scale, linthresh)
    return _time_figure(sol, [p[..., 0], p[..., 1]],
                        [f"p₁ [kg m/s]{suffix}", f"p₂ [kg m²/s]{suffix}"], "Momentum p = (p₁, p₂)",
                        axes=axes, labels=labels, yscales=[tf, tf], stamp=stamp)


def _y_scale(scale, linthresh, t=None, clip_after=None):
    """``(apply(ax, data) or None, y-label suffix)`` of ``scale``: ``"symlog"``, ``"linear"`` or, given the times
    ``t``, ``"clip"`` (after ``clip_after`` seconds, default 2 % of the horizon)."""
    if scale == "symlog":
        return _symlog(linthresh), " (symlog)"
    if scale == "clip" and t is not None:
        return _clip(0.02 * float(t[-1] - t[0]) if clip_after is None else float(clip_after), t), " (clipped)"
    if scale == "linear":
        return None, ""
    choices = "'symlog' or 'linear'" if t is None else "'symlog', 'clip' or 'linear'"
    raise ValueError(f"scale must be {choices}, got {scale!r}")


def _symlog(linthresh):
    def apply(ax, data):
        finite = np.abs(data[np.isfinite(data)])
        if finite.size == 0:
            return
        thr = linthresh
        if thr is None:           # linear over the late, small values; log over the initial transient
            thr = max(float(np.percentile(finite, 90)), 1e-6)
            thr = 10 ** math.ceil(math.log10(thr))
        ax.set_yscale("symlog", linthresh=thr, linscale=1.0)
        ax.axhspan(-thr, thr, color="0.9", zorder=0, linewidth=0)
        ax.text(0.995, 0.03, f"symlog: linear for |·| < {thr:g}", transform=ax.transAxes,
                ha="right", va="bottom", fontsize=7, color="0.35")
    return apply


def _clip(after, t):
    def apply(ax, data):
        late = np.abs(data[:, t >= after])
        late = late[np.isfinite(late)]
        finite = np.abs(data[np.isfinite(data)])
        if late.size == 0 or finite.size == 0:
            return
        lim = 1.1 * float(late.max())
        peak = float(finite.max())
        if peak > lim > 0:
            ax.set_ylim(-lim, lim)
            ax.text(0.995, 0.97, f"y-range clipped to |·| max over t ≥ {after:g} s; peak |·| = {peak:.3g}",
                    transform=ax.transAxes, ha="right", va="top", fontsize=7, color="0.35")
    return apply


def plot_control(sol, axes=None, *, labels: Optional[Sequence[str]] = None, scale: str = "symlog",
                 linthresh: Optional[float] = None, clip_after: Optional[float] = None, stamp: bool = True):
    """Control force ``u1`` [N] and torque ``u2`` [N m] against time (paper Fig. 5).

    Runs that start near ``theta = 0`` have a control orders of magnitude larger in the first
    instants than afterwards, so the y-axis is ``scale="symlog"`` by default (linear below
    ``linthresh``, default: the 90th percentile of ``|u|`` rounded up to a power of ten, log above);
    ``scale="clip"`` keeps a linear axis clipped to the largest ``|u|`` after ``clip_after``
    seconds (default 2 % of the horizon) and says so on the axis; ``scale="linear"`` shows
    everything. ``stamp=False``: no provenance line.
    """
    u = _batched(_get(sol, "u"))
    tf, suffix = _y_scale(scale, linthresh, np.asarray(_get(sol, "t"), dtype=float), clip_after)
    return _time_figure(sol, [u[..., 0], u[..., 1]],
                        [f"u₁ [N]{suffix}", f"u₂ [N m]{suffix}"], "Control u = (u₁, u₂)",
                        axes=axes, labels=labels, yscales=[tf, tf], stamp=stamp)


def plot_hamiltonian(sol, ax=None, *, labels: Optional[Sequence[str]] = None, stamp: bool = True):
    """Closed-loop Hamiltonian ``H_d(t)`` on a log y-scale (non-increasing along the exact flow);
    ``stamp=False``: no provenance line."""
    Hd = np.atleast_2d(np.asarray(_get(sol, "Hd"), dtype=float))
    return _time_figure(sol, [Hd], ["H_d [J]"], "Closed-loop Hamiltonian H_d", axes=None if ax is None else [ax],
                        labels=labels, yscales=[lambda ax, data: ax.set_yscale("log")], figsize=(7.0, 4.6), stamp=stamp)
