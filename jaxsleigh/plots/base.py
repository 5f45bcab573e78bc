"""Scaffolding shared by the plotting modules: figures, the provenance stamp, saving.

* `new_figure` / `figure_and_axes`: a `matplotlib.figure.Figure` with constrained
  layout, built without ``pyplot`` (no backend is selected, no global GUI state is touched, so it
  works headless and inside other applications); ``figure_and_axes`` draws into given axes when a
  caller passes them.
* `provenance`: the short text of what produced the data (``'float32, adaptive RK4, dt =
  0.01 s'``), used in titles.
* `stamp`: the provenance line at the top of every figure a plotting function owns (above the
  title, small grey type): dtype, method, step, tolerances, ``eps``, horizon and the device the data
  was computed on, less what the title already says (from the result's settings or run information; ``device not recorded`` when
  neither holds it, e.g. a file from an older version).
* `save_figure`: PNG/PDF/SVG by suffix, parent folders created, written atomically.

Used by `jaxsleigh.plots.paper_figures`, `jaxsleigh.plots.basin` and the other ``*_plots`` modules.
Numerics modules never import this (nor any plotting module).
"""
from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Mapping, Optional, Sequence

from ..files.npz import atomic_write

__all__ = ["METHOD_NAMES", "STAMP_GID", "T_EPS", "check_stamp", "new_figure", "figure_and_axes", "save_figure", "provenance",
           "device_text", "provenance_line", "provenance_parts", "stamp"]

#: Display names of the integration methods.
METHOD_NAMES = {"adaptive": "adaptive RK4", "rk4": "fixed-step RK4", "sampled": "zero-order hold, adaptive RK4 between samples"}

#: The convergence time's symbol in every figure (mathtext, one spelling across the plotting modules).
T_EPS = r"$T_\varepsilon$"

#: ``gid`` of the stamp's text artist (find it with ``[t for t in fig.texts if t.get_gid() == STAMP_GID]``).
STAMP_GID = "jaxsleigh-provenance"


def new_figure(figsize):
    """A `Figure` of ``figsize`` inches with constrained layout (no pyplot)."""
    from matplotlib.figure import Figure  # no pyplot: no backend, no global state

    return Figure(figsize=figsize, layout="constrained")


def figure_and_axes(ax, figsize, shape=None, **subplots_kw):
    """``(fig, ax, own)``: a new figure of ``figsize`` (``own=True``) when ``ax`` is ``None``, else the given axes
    and their figure. One axes, or with ``shape = (rows, cols)`` a list of that many (``subplots_kw``: e.g.
    ``sharex=True``); given axes must then be that many."""
    if ax is None:
        fig = new_figure(figsize)
        if shape is None:
            return fig, fig.add_subplot(1, 1, 1), True
        return fig, list(fig.subplots(*shape, squeeze=False, **subplots_kw).ravel()), True
    if shape is None:
        return ax.figure, ax, False
    axes = list(ax)
    if len(axes) != shape[0] * shape[1]:
        raise ValueError(f"need {shape[0] * shape[1]} axes, got {len(axes)}")
    return axes[0].figure, axes, False


def save_figure(fig, path, *, dpi: int = 150) -> Path:
    """Save ``fig`` (format from the suffix), creating parent folders; returns the path.

    Written as the result files are (`jaxsleigh.files.npz.atomic_write`): into a temporary file in the same
    folder, then renamed into place, so that a failed write (a full disk) leaves no truncated figure; a full
    disk or quota raises `jaxsleigh.errors.DiskFullError` naming the file. The same figure saves as the same bytes
    (no date in a ``.pdf``, ``.svg`` or ``.ps``; fixed ids in an ``.svg``)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fmt = path.suffix.lower().lstrip(".") or None
    meta = {"metadata": _NO_DATE[fmt]} if fmt in _NO_DATE else {}

    def write(f):
        import matplotlib

        # fixed ids in an .svg; a .ps dates itself from SOURCE_DATE_EPOCH only
        was = os.environ.get("SOURCE_DATE_EPOCH")
        os.environ["SOURCE_DATE_EPOCH"] = was or "0"
        try:
            with matplotlib.rc_context({"svg.hashsalt": "jaxsleigh"}):
                fig.savefig(f, format=fmt, dpi=dpi, **meta)
        finally:
            if was is None:
                os.environ.pop("SOURCE_DATE_EPOCH", None)
    return atomic_write(path, write)


#: The metadata a figure format would date with the time it was saved: left out, so that the same command
#: draws the same bytes (a ``.png`` holds no date).
_NO_DATE = {"pdf": {"CreationDate": None}, "svg": {"Date": None}}


def provenance(settings: Mapping, *, fields: Sequence[str] = ("dt",)) -> str:
    """``'float32, adaptive RK4, dt = 0.01 s'`` from a result's settings (what produced a figure).

    ``fields`` picks the settings appended after dtype and method, in this order: ``"dt"``,
    ``"eps"``, ``"t_final"`` (each only when present).
    """
    return ", ".join(_setting_parts(settings or {}, fields))


def _setting_parts(s: Mapping, fields: Sequence[str]) -> list:
    """The dtype, the method and those of ``fields`` that the settings ``s`` hold, in this order: ``"dt"``,
    ``"rtol"`` (with ``atol``, for the adaptive method), ``"eps"``, ``"t_final"``."""
    method = s.get("method")
    parts = [str(s.get("dtype", "dtype unknown")),
             "method unknown" if method is None else METHOD_NAMES.get(method, str(method))]
    if "dt" in fields and "dt" in s:
        parts.append(f"dt = {float(s['dt']):g} s")
    if "rtol" in fields and method == "adaptive" and "rtol" in s and "atol" in s:
        parts.append(f"rtol = {float(s['rtol']):g}, atol = {float(s['atol']):g}")
    if "eps" in fields and "eps" in s:
        parts.append(f"ε = {float(s['eps']):g}")
    if "t_final" in fields and "t_final" in s:
        parts.append(f"T = {float(s['t_final']):g} s")
    return parts


def device_text(settings: Optional[Mapping], run_info: Optional[Mapping] = None) -> str:
    """The device(s) the data was computed on, from ``settings`` or ``run_info`` (``'cpu:0'``,
    ``'cpu, 2 cores'`` for one CPU device per core, ``'2 devices: cuda:0, cuda:1'``); ``'device not
    recorded'`` when neither names one."""
    for src in (settings or {}, run_info or {}):
        dev = src.get("devices", src.get("device"))
        if dev:
            if isinstance(dev, str):
                return dev
            dev = [str(d) for d in dev]
            if len(dev) > 1 and all(d.startswith("cpu") for d in dev):
                return f"cpu, {len(dev)} cores"
            return dev[0] if len(dev) == 1 else f"{len(dev)} devices: {', '.join(dev)}"
    return "device not recorded"


def provenance_line(settings: Optional[Mapping], run_info: Optional[Mapping] = None, *, said: str = "") -> str:
    """One line naming the dtype, method, step, tolerances (adaptive), ``eps``, horizon and device; the parts that
    ``said`` (a figure's title) already names are left out."""
    return "  ·  ".join(p for p in provenance_parts(settings, run_info) if not _names(said, p))


def _names(text: str, part: str) -> bool:
    """Whether ``text`` names ``part`` as a whole (``'ε = 0.3'`` is not named by ``'ε = 0.35'``)."""
    return bool(text) and re.search(rf"(?<![\w.]){re.escape(part)}(?![\w.])", text) is not None


def provenance_parts(settings: Optional[Mapping], run_info: Optional[Mapping] = None) -> list:
    """The items of `provenance_line`: dtype, method, step, tolerances (adaptive), ``eps``, horizon, device and
    the jaxsleigh version."""
    s = settings or {}
    parts = _setting_parts(s, ("dt", "rtol", "eps", "t_final"))
    device = device_text(s, run_info)
    parts.append(device if device == "device not recorded" else f"device {device}")
    from .. import __version__

    parts.append(f"jaxsleigh {__version__}")
    return parts


def check_stamp(stamp) -> bool:
    """``stamp`` (the plotting functions' option) as a bool; anything but True/False is a ValueError."""
    if not isinstance(stamp, bool):
        raise ValueError(f"stamp must be True (draw the provenance line) or False (leave it out, e.g. for a "
                         f"publication), got {stamp!r}")
    return stamp


def stamp(fig, settings: Optional[Mapping], run_info: Optional[Mapping] = None):
    """Write `provenance_line` in small grey type at the top left of ``fig``; a second call
    replaces the first. Returns the text artist. (The plotting functions' ``stamp=False`` skips it,
    for a publication.)

    The line sits in a blank first line added to the suptitle, so the constrained layout keeps room
    for it (call this after ``suptitle``; a figure without one gets a blank one). What the suptitle already says
    (the dtype, the method, dt, ...) is not repeated.
    """
    for t in list(fig.texts):
        if t.get_gid() == STAMP_GID:
            t.remove()
    title = fig.get_suptitle()
    size = fig._suptitle.get_fontsize() if fig._suptitle is not None else 10   # suptitle() would reset it
    fig.suptitle("\n" + title.lstrip("\n"), fontsize=size)
    return fig.text(0.005, 0.995, provenance_line(settings, run_info, said=title), ha="left", va="top",
                    fontsize=6.5, color="0.4", gid=STAMP_GID)
