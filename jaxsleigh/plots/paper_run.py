"""The simulation of the paper's Section 5: six starts, the paper's plant and gains, 100 s.

`run_paper` simulates and writes Figs. 2-5 of the paper (plus ``H_d(t)``) and the data; it
backs ``jaxsleigh paper`` and ``experiments/studies/paper_figures.py``.

The paper's set of starts is not published except for the blue run at ``(-3, -2, pi/8)``; the
others here are a well-spread assortment of positions and headings, all with zero momentum.
"""
from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from ..integrate.engine import MAX_BASE_STEPS
from ..model.params import paper_gains, paper_plant
from ..integrate.stepsize import StepSizeController
from ..studies.options import RunOptions, SaveAt
from ..studies.simulate import simulate
from ..files.npz import write_npz
from ..files.runner import run_record, write_sidecar
from ..status import Status
from ..validate import output_file

__all__ = ["PAPER_ICS", "PAPER_T_FINAL", "FIGURES", "run_paper", "summary_table"]

#: Starts ``(x [m], y [m], theta [rad])`` with zero momentum; the first is the paper's blue run.
PAPER_ICS = np.array([
    (-3.0, -2.0, math.pi / 8),
    (3.0, 2.0, -math.pi / 2),
    (-2.0, 3.0, 3 * math.pi / 4),
    (2.0, -3.0, math.pi / 3),
    (3.0, -1.0, -2.5),
    (-1.0, -3.0, -math.pi / 4),
])

#: Horizon of the paper's simulation [s].
PAPER_T_FINAL = 100.0

#: File stem -> plotting function name.
FIGURES = {
    "fig2_paths": "plot_paths",
    "fig3_configuration": "plot_configuration",
    "fig4_momentum": "plot_momentum",
    "fig5_control": "plot_control",
    "fig_hamiltonian": "plot_hamiltonian",
}


def _save_every(t_final: float, dt: float, spacing: float = 0.05) -> int:
    """Largest K <= spacing/dt dividing the number of steps (outputs about every ``spacing`` s); 1 for a horizon
    `simulate` will refuse (more base steps than a run can take, say a subnormal ``dt``: its message names it)."""
    if not t_final / dt <= MAX_BASE_STEPS:
        return 1
    n_steps = max(1, int(round(t_final / dt)))
    k = max(1, int(round(spacing / dt)))
    while n_steps % k:
        k -= 1
    return k


def run_paper(out_dir, *, x64: bool = False, dt: float = 0.01, progress: Any = None,
              t_final: float = PAPER_T_FINAL, ics: Optional[np.ndarray] = None,
              method: str = "adaptive", command: Optional[Sequence[str]] = None, stamp: bool = True) -> dict:
    """Simulate the paper's setting and write its figures and data into ``out_dir``.

    Args:
      out_dir: folder (created) for ``fig2_paths.png``, ``fig3_configuration.png``,
        ``fig4_momentum.png``, ``fig5_control.png``, ``fig_hamiltonian.png`` and ``paper.npz``
        (same keys as ``jaxsleigh simulate``), and the run's sidecar ``paper.run.json`` (wall time, devices,
        command: what varies between runs, so that the figures and ``paper.npz`` are the same bytes every time).
      x64: compute in float64 (default float32).
      dt: base step [s]; outputs are kept about every 0.05 s (smooth paths in the fast first second).
      progress: passed to `simulate`.
      t_final: horizon [s] (the paper's 100 s; shorter for quick looks and tests).
      ics: starts (default `PAPER_ICS`).
      method: ``"adaptive"`` (default) or ``"rk4"``.
      command: recorded in the npz's ``settings_json`` and in the sidecar.
      stamp: draw the provenance line on the figures (``False``: for a publication).

    Returns:
      ``{stem: Path}`` for the five figures, ``"npz"`` and ``"run"`` (the sidecar).
    """
    from . import paper_figures as plotting

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for name in ("paper.npz", "paper.run.json", *(f"{stem}.png" for stem in FIGURES)):     # regular files only, before any work
        output_file(out / name)
    ics = PAPER_ICS if ics is None else np.asarray(ics, dtype=np.float64)
    t0 = time.perf_counter()
    sol = simulate(ics, plant=paper_plant(), gains=paper_gains(), t_final=t_final, dt=dt, x64=x64,
                   stepsize=StepSizeController(method=method), saveat=SaveAt(every=_save_every(t_final, dt)),
                   run=RunOptions(progress=progress))
    paths = {}
    for stem, fn_name in FIGURES.items():
        fig = getattr(plotting, fn_name)(sol, stamp=stamp)
        paths[stem] = plotting.save_figure(fig, out / f"{stem}.png")
    # the data last: where paper.npz is, every figure of its run is (an interrupted run leaves none)
    command = list(command) if command is not None else ["run_paper", str(out)]
    npz = write_npz(out / "paper.npz", sol, ics=ics, command=command)
    side = write_sidecar(npz, run_record(command, time.perf_counter() - t0, (sol.run_info or {}).get("devices")))
    return {"npz": npz, **paths, "run": side}


def summary_table(path_or_solution) -> str:
    """One line per run: start, status, final |q|, H_d(0) and H_d(T), max |u|."""
    from .paper_figures import format_start, load_solution

    sol = load_solution(path_or_solution) if isinstance(path_or_solution, (str, Path)) else path_or_solution
    q, Hd, u, status = (np.asarray(a) for a in (sol.q, sol.Hd, sol.u, sol.status))
    ics = sol.settings.get("ics") if isinstance(sol.settings, dict) else None
    lines = [f"{'start (x0, y0, theta0)':<24} {'status':<20} {'|q(T)|':>9} {'H_d(0)':>10} {'H_d(T)':>10} "
             f"{'max|u|':>9}"]
    for i in range(q.shape[0]):
        start = ics[i][:3] if ics is not None else q[i, 0]
        st = int(status[i])
        name = Status(st).name.lower() if st in Status._value2member_map_ else str(st)
        ok = np.flatnonzero(np.all(np.isfinite(q[i]), axis=1))
        last = ok[-1] if ok.size else 0
        qn = float(np.linalg.norm(q[i, last]))
        lines.append(f"{format_start(start):<24} {f'{st} {name}':<20} {qn:9.2e} {Hd[i, 0]:10.3g} "
                     f"{Hd[i, last]:10.3g} {np.nanmax(np.abs(u[i])):9.3g}")
    return "\n".join(lines)
