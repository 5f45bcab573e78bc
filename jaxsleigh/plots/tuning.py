"""Figures of gain tuning: the optimisation history, before/after paths and convergence times.

* `plot_history`: loss (valid and rejected candidates, running best), gradient norm and the
  gains per iteration.
* `plot_paths_before_after`: paths of the contact point under two sets of gains, side by side.
* `plot_convergence_times`: empirical distribution (CDF) and histogram of ``T_eps`` per set
  of gains, medians marked.
* `plot_per_plant`: median ``T_eps`` and the fraction converged per plant, per set of gains.
* `plot_effort_history`: the effort-budgeted run: training energy against its budget, the
  multiplier, and the integration-cost probe against its budget with the returned iteration marked.
* `plot_search_history`: the derivative-free search (`jaxsleigh.tuning.search`): each generation's
  best median T_0.05 and median energy against the budget, and the step size.
* `plot_front`: the time-effort Pareto front (median T_0.05 against median control energy on
  held-out starts) with reference gains and a random-search baseline.

Like `jaxsleigh.plots.paper_figures`, everything builds `matplotlib.figure.Figure` objects (no
``pyplot``, no global state) and accepts ``ax``/``axes`` to draw into existing figures.
"""
from __future__ import annotations

from typing import Mapping, Optional, Sequence

import numpy as np

from .base import figure_and_axes, save_figure
from .paper_figures import plot_paths

__all__ = ["plot_history", "plot_paths_before_after", "plot_convergence_times", "plot_per_plant",
           "plot_effort_history", "plot_search_history", "plot_front", "save_figure"]


def _field(obj, name):
    return obj[name] if isinstance(obj, Mapping) or hasattr(obj, "files") else getattr(obj, name)


def _field_arrays(obj, **dtypes):
    """The fields ``name=dtype`` of ``obj`` (a mapping, ``.npz`` or object) as arrays of that dtype, in the order
    given (the first one missing raises)."""
    return [np.asarray(_field(obj, name), dtype) for name, dtype in dtypes.items()]


def plot_history(history, axes=None, *, title: str = "Gain tuning", probe_budget: Optional[float] = None):
    """Loss, gradient norm, integration cost (the probe's attempted steps) and gains per iteration.

    Args:
      history: a `TuneHistory` (or the ``.npz`` written by
        `save_history`, or any mapping with its fields).
      axes: four axes to draw into (default: a new figure).
      probe_budget: drawn as a horizontal line on the cost panel when given.

    Returns:
      The `matplotlib.figure.Figure`.
    """
    loss, valid, best, gnorm, L, k, D, probe = _history_arrays(history)
    it = np.arange(loss.size)
    fig, axes, own = figure_and_axes(axes, (7.0, 9.5), (4, 1), sharex=True)
    _draw_loss(axes[0], it, loss, valid, best)
    axes[1].semilogy(it, gnorm, color="C1", linewidth=1)
    axes[1].set_ylabel("‖∇ loss‖ (log-gains)")
    axes[1].grid(True, alpha=0.3, which="both")
    shown = np.isfinite(probe)
    _draw_probe(axes[2], it, probe, shown & valid, shown & ~valid, probe_budget, ("probe (valid)", "probe (rejected)"),
                cross=4)
    axes[2].legend(fontsize=8)
    axes[2].grid(True, alpha=0.3, which="both")
    _draw_gains(axes[3], it, L, k, D)
    axes[0].set_xlim(0, max(1, loss.size - 1))
    if own:
        fig.suptitle(title, fontsize=11)
    return fig


def _history_arrays(history):
    """``(loss, valid, best, grad_norm, L, k, D_hat, probe_attempts)`` of ``history`` as arrays (the probe all NaN
    when the history has none)."""
    loss, valid, best, gnorm, L, k, D = _field_arrays(history, loss=float, valid=bool, best=float, grad_norm=float,
                                                      L=float, k=float, D_hat=float)
    try:
        probe = np.asarray(_field(history, "probe_attempts"), float)
    except (KeyError, AttributeError):
        probe = np.full(loss.size, np.nan)
    return loss, valid, best, gnorm, L, k, D, probe


def _draw_loss(ax, it, loss, valid, best):
    """The candidates' loss (valid, and rejected ones at their loss or, non-finite, at the largest valid one: the
    largest finite one, or 1, when no candidate was valid) and the running best."""
    ax.plot(it[valid], loss[valid], ".-", color="C0", markersize=3, linewidth=1, label="candidate (valid)")
    if np.any(~valid):
        finite = loss[np.isfinite(loss)]
        top = np.nanmax(loss[valid]) if valid.any() else (finite.max() if finite.size else 1.0)
        ax.plot(it[~valid], np.where(np.isfinite(loss[~valid]), loss[~valid], top), "x",
                color="C3", label="rejected (failed lane, probe over budget or non-finite)")
    ax.plot(it, best, color="k", linewidth=1.2, label="best valid")
    ax.set_ylabel("loss (soft time outside\n|q| ≤ ε, ÷ horizon)")
    ax.legend(fontsize=8)
    ax.grid(True, alpha=0.3)


def _draw_probe(ax, it, probe, kept, rejected, probe_budget, labels, *, cross: float):
    """The probe's most attempted steps per iteration: dots where ``kept``, crosses (of size ``cross``) where
    ``rejected`` (``labels``: their legend texts), and its budget if given."""
    ax.semilogy(it[kept], probe[kept], ".", color="C2", markersize=3, label=labels[0])
    if np.any(rejected):
        ax.semilogy(it[rejected], probe[rejected], "x", color="C3", markersize=cross, label=labels[1])
    if probe_budget is not None:
        ax.axhline(probe_budget, color="k", linestyle="--", linewidth=1, label="probe budget")
    ax.set_ylabel("most attempted steps\nof a probe per 100 s")


def _draw_gains(ax, it, L, k, D):
    """The gains per iteration: L1..L3, k and the extreme eigenvalues of D_hat's symmetric part."""
    for i in range(3):
        ax.semilogy(it, L[:, i], color=f"C{i}", label=f"L{i + 1}")
    ax.semilogy(it, k, color="C3", label="k")
    eig = np.linalg.eigvalsh(0.5 * (D + np.swapaxes(D, -1, -2)))
    ax.semilogy(it, eig[:, 0], color="C4", linestyle="--", label="λ_min(D̂)")
    ax.semilogy(it, eig[:, 1], color="C5", linestyle="--", label="λ_max(D̂)")
    ax.set_ylabel("gain")
    ax.set_xlabel("iteration")
    ax.legend(fontsize=8, ncol=3)
    ax.grid(True, alpha=0.3, which="both")


def plot_paths_before_after(before, after, *, names: Sequence[str] = ("paper gains", "tuned gains"),
                            axes=None, share: bool = True):
    """Paths of the contact point under two sets of gains (two `Solution`
    objects from the same starts), side by side; with ``share`` both panels get the same limits."""
    fig, axes, _ = figure_and_axes(axes, (12.0, 6.6), (1, 2))
    for ax, sol, name in zip(axes, (before, after), names):
        plot_paths(sol, ax=ax, legend=ax is axes[-1])
        ax.set_title(f"{name}: {ax.get_title()}", fontsize=9)
    if share:
        # equal aspect with 'datalim' cannot be shared between axes: set common limits instead
        lims = []
        for ax in axes:
            ax.apply_aspect()
            lims.append((ax.get_xlim(), ax.get_ylim()))
        x0, x1 = min(l[0][0] for l in lims), max(l[0][1] for l in lims)
        y0, y1 = min(l[1][0] for l in lims), max(l[1][1] for l in lims)
        for ax in axes:
            ax.set_aspect("equal", adjustable="box")
            ax.set_xlim(x0, x1)
            ax.set_ylim(y0, y1)
    return fig


def plot_convergence_times(times: Mapping[str, np.ndarray], *, horizon: float = 100.0, eps: float = 0.05,
                           axes=None, title: Optional[str] = None):
    """Distribution of the hard convergence time ``T_eps`` per set of gains.

    ``times`` maps a label to the (N,) times (``inf``: not settled by ``horizon``; ``nan``: failed,
    counted as not settled). Left: the fraction settled by time t (empirical CDF), medians marked;
    right: histograms on a log time axis.
    """
    fig, axes, _ = figure_and_axes(axes, (11.0, 4.2), (1, 2))
    finite_all = np.concatenate([np.asarray(T, float)[np.isfinite(T)] for T in times.values()] + [[horizon]])
    lo = max(min(finite_all.min(), horizon) * 0.8, 1e-2)
    bins = np.geomspace(lo, horizon, 40)
    for i, (name, T) in enumerate(times.items()):
        T = np.where(np.isnan(np.asarray(T, float)), np.inf, np.asarray(T, float))
        n = T.size
        ts = np.sort(T[np.isfinite(T)])
        frac = np.arange(1, ts.size + 1) / n
        med = float(np.median(T))
        color = f"C{i}"
        axes[0].step(np.concatenate([[0.0], ts, [horizon]]), np.concatenate([[0.0], frac, [frac[-1] if frac.size else 0]]),
                     where="post", color=color,
                     label=f"{name}: median {med:.1f} s, {100 * ts.size / n:.2f}% by {horizon:g} s (N = {n})")
        if np.isfinite(med):
            axes[0].axvline(med, color=color, linestyle=":", linewidth=1)
        axes[1].hist(ts, bins=bins, color=color, alpha=0.55, label=name)
    axes[0].set_xlim(0, horizon)
    axes[0].set_ylim(0, 1.02)
    axes[0].set_xlabel("time t [s]")
    axes[0].set_ylabel(f"fraction with |q| ≤ {eps:g} from then on")
    axes[0].legend(fontsize=8, loc="lower right")
    axes[0].grid(True, alpha=0.3)
    axes[1].set_xscale("log")
    axes[1].set_xlabel(f"T_{eps:g} [s] (log scale)")
    axes[1].set_ylabel("starts")
    axes[1].legend(fontsize=8)
    axes[1].grid(True, alpha=0.3)
    fig.suptitle(title or f"Convergence time T_{eps:g} on held-out starts (accurate adaptive engine)", fontsize=11)
    return fig


def plot_per_plant(table: Mapping[str, Mapping[str, object]], *, axes=None, horizon: float = 100.0):
    """Median ``T_eps`` (with its standard error) and fraction converged per plant.

    ``table`` maps a plant label to ``{gains label: Validation}`` (`Validation`).
    """
    plants = list(table)
    labels = list(next(iter(table.values())))
    fig, axes, _ = figure_and_axes(axes, (11.0, 4.4), (1, 2), sharey=True)
    y = np.arange(len(plants))
    h = 0.8 / len(labels)
    for j, lab in enumerate(labels):
        med, se, frac, fse = (np.array([getattr(table[p][lab], name) for p in plants], float)
                              for name in ("median_T", "median_se", "frac_converged", "frac_se"))
        yj = y + (j - (len(labels) - 1) / 2) * h
        shown = np.where(np.isfinite(med), med, horizon)
        axes[0].barh(yj, shown, height=h, xerr=np.nan_to_num(se), color=f"C{j}", label=lab, hatch=None)
        for yi, m in zip(yj, med):
            if not np.isfinite(m):
                axes[0].text(horizon, yi, " > horizon", va="center", fontsize=7)
        axes[1].barh(yj, 100 * frac, height=h, xerr=100 * fse, color=f"C{j}", label=lab)
    axes[0].set_yticks(y, plants, fontsize=8)
    axes[0].invert_yaxis()
    axes[0].set_xlabel("median T_0.05 [s]")
    axes[0].grid(True, axis="x", alpha=0.3)
    axes[0].legend(fontsize=8)
    axes[1].set_xlabel(f"converged by {horizon:g} s [%]")
    axes[1].set_xlim(0, 100)
    axes[1].grid(True, axis="x", alpha=0.3)
    fig.suptitle("Robustness: the same gains on other plants (held-out starts, accurate engine)", fontsize=11)
    return fig


def plot_effort_history(history, *, budget: float, probe_budget: Optional[float] = None,
                        returned: Optional[int] = None, axes=None, title: str = "Effort-budgeted tuning"):
    """Three panels per iteration: the batch's geometric-mean control energy against ``budget``; the
    soft time f and the augmented Lagrangian's multiplier; the probe's most attempted steps per 100 s
    against ``probe_budget`` (rejections by the probe marked). ``returned``: the iteration whose gains
    were returned, marked on every panel (where the probe's steps sit far below its budget, the
    integrator did not shape the answer)."""
    energy, soft, lam, probe, active, valid = _field_arrays(
        history, energy=float, soft_loss=float, multiplier=float, probe_attempts=float, probe_active=bool, valid=bool)
    it = np.arange(energy.size)
    fig, axes, own = figure_and_axes(axes, (7.0, 7.5), (3, 1), sharex=True)
    _draw_energy(axes[0], it, energy, valid, budget)
    _draw_soft_time(axes[1], it, soft, lam, valid)
    # within its budget, and active: the candidate rejected
    _draw_probe(axes[2], it, probe, np.isfinite(probe) & ~active, active, probe_budget,
                ("probe within budget", "probe active (rejected)"), cross=5)
    axes[2].set_xlabel("iteration")
    for a in axes:
        if returned is not None:
            a.axvline(returned, color="C3", linewidth=1, alpha=0.6, label="returned gains" if a is axes[0] else None)
        a.grid(True, alpha=0.3, which="both")
        a.legend(fontsize=8, loc="best")
    if own:
        fig.suptitle(title, fontsize=11)
    return fig


def _draw_energy(ax, it, energy, valid, budget):
    """The valid candidates' training energy against its budget."""
    ax.semilogy(it[valid], energy[valid], ".-", color="C0", markersize=3, linewidth=1, label="candidate")
    ax.axhline(budget, color="k", linestyle="--", linewidth=1, label="energy budget")
    ax.set_ylabel("geometric-mean\n∫|u|² dt (training)")


def _draw_soft_time(ax, it, soft, lam, valid):
    """The valid candidates' soft time f and, on a twin axis, the multiplier of every iteration."""
    ax.plot(it[valid], soft[valid], ".-", color="C1", markersize=3, linewidth=1, label="soft time f")
    ax.set_ylabel("f (soft time ÷ horizon)")
    ax2 = ax.twinx()
    ax2.plot(it, lam, color="C4", linewidth=1, label="multiplier λ")
    ax2.set_ylabel("λ", color="C4")


def plot_search_history(history, *, reference: Mapping, returned: Optional[int] = None, axes=None,
                        title: str = "Derivative-free search (CMA-ES) of the gains"):
    """Per generation: the best candidate's median T_0.05 (feasible ones filled) with the reference
    gains' as a line; its median energy against the budget; the step size sigma.

    Args:
      history: `jaxsleigh.tuning.SearchResult.history` (or its ``.npz``).
      reference: `jaxsleigh.tuning.SearchResult.reference` (``median_T``, ``median_energy``,
        ``energy_budget``).
      returned: the generation of the returned gains, marked.
    """
    fig, axes, _ = figure_and_axes(axes, (11.0, 3.6), (1, 3))
    gen, feas, T, E, sigma = _field_arrays(history, generation=None, feasible=bool, median_T=float,
                                           median_energy=float, sigma=float)
    for ax, y, ref, lab in ((axes[0], T, reference["median_T"], "median T_0.05 [s]"),
                            (axes[1], E, reference["median_energy"], "median energy ∫|u|² dt")):
        ax.plot(gen, y, "-", color="C0", lw=0.8)
        ax.plot(gen[feas], y[feas], "o", color="C0", ms=3, label="generation's best (feasible)")
        ax.plot(gen[~feas], y[~feas], "o", color="C3", ms=3, mfc="none", label="generation's best (infeasible)")
        ax.axhline(ref, color="C7", ls=":", label="reference gains")
        if returned is not None:
            ax.axvline(returned, color="C1", lw=1, label="returned")
        ax.set_xlabel("generation")
        ax.set_ylabel(lab)
        ax.grid(True, alpha=0.3)
    axes[1].axhline(reference["energy_budget"], color="C3", ls="--", label="budget")
    axes[0].legend(fontsize=7)
    axes[1].legend(fontsize=7)
    axes[2].semilogy(gen, sigma, color="C2")
    axes[2].set_xlabel("generation")
    axes[2].set_ylabel("step size σ")
    axes[2].grid(True, alpha=0.3, which="both")
    fig.suptitle(title)
    return fig


def _front_xy(points):
    e = np.array([float(p["evaluation"]["median_energy"]) for p in points])
    t = np.array([float(p["evaluation"]["median_T_0.05_s"]) for p in points])
    se = np.array([float(p["evaluation"]["median_se_s"]) for p in points])
    return e, t, np.where(np.isfinite(se), se, 0.0)


def plot_front(front: Mapping, *, baseline: Optional[Mapping] = None, references: Optional[Mapping] = None,
               highlight: Optional[Mapping] = None, ax=None, title: str = "Time-effort Pareto front"):
    """Median T_0.05 (± s.e.) against median control energy on held-out starts, log-log.

    Args:
      front: a front document (`jaxsleigh.tuning.front_dict` / ``front.json``) whose points
        were evaluated.
      baseline: another front document (e.g. `jaxsleigh.tuning.random_search`), drawn dashed.
      references: ``{name: figures}`` (the documents' ``references`` entries, e.g. paper and tuned;
        default: ``front["references"]``), drawn as labelled markers.
      highlight: ``{name: figures}`` to mark specially (e.g. the ``balanced`` preset).
    """
    fig, ax, _ = figure_and_axes(ax, (7.0, 5.0))
    pts = [p for p in front["points"] if "evaluation" in p]
    e, t, se = _front_xy(pts)
    ax.errorbar(e, t, yerr=se, fmt="o-", color="C0", markersize=4, capsize=2,
                label=f"gradient front ({front.get('method', '')}, {front.get('evaluations', '?')} evaluations)")
    if baseline is not None:
        bp = [p for p in baseline["points"] if "evaluation" in p]
        if bp:
            be, bt, bse = _front_xy(bp)
            ax.errorbar(be, bt, yerr=bse, fmt="s--", color="C7", markersize=4, capsize=2,
                        label=f"random search ({baseline.get('evaluations', '?')} evaluations)")
    refs = front.get("references", {}) if references is None else references
    markers = {"paper": ("*", "C3"), "tuned": ("D", "C2")}
    for name, r in refs.items():
        m, c = markers.get(name, ("^", "C5"))
        ax.errorbar([float(r["median_energy"])], [float(r["median_T_0.05_s"])],
                    yerr=[[_finite(r["median_se_s"])], [_finite(r["median_se_s"])]], fmt=m, color=c, markersize=11,
                    capsize=2, label=f"{name} gains")
    for name, r in (highlight or {}).items():
        ax.plot([float(r["median_energy"])], [float(r["median_T_0.05_s"])], "o", markersize=13, markerfacecolor="none",
                markeredgecolor="C1", markeredgewidth=2, label=name)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("median control energy ∫₀¹⁰⁰ |u|² dt on held-out starts")
    ax.set_ylabel("median T_0.05 on held-out starts [s]")
    ax.grid(True, alpha=0.3, which="both")
    ax.legend(fontsize=8, loc="upper right")
    ax.set_title(title, fontsize=11)
    caption = _front_caption(front)
    if caption:
        # bottom left: fast at little energy, where no gains are
        t = ax.text(0.01, 0.01, caption, transform=ax.transAxes, ha="left", va="bottom", fontsize=6.5, color="0.4",
                    wrap=True)
        t.set_in_layout(False)          # a long command must not squeeze the axes
    return fig


def _front_caption(front: Mapping) -> str:
    """What made the front's held-out figures (starts, dtype, tolerance), then the command: what the file records."""
    held = front.get("held_out") or {}
    parts = []
    if held.get("n"):
        parts.append(f"{held['n']} held-out starts (seed {held.get('seed', '?')})")
    x64 = (front.get("settings") or {}).get("x64")
    if x64 is not None:
        parts.append("float64" if x64 else "float32")
    if held:
        parts.append("adaptive RK4, atol " + (f"{held['atol']:g}" if held.get("atol") else "default"))
    text = "  ·  ".join(parts)
    if front.get("command"):
        import textwrap

        text += ("\n" if text else "") + "\n".join(textwrap.wrap(" ".join(map(str, front["command"])), 110))
    return text


def _finite(x) -> float:
    x = float(x)
    return x if np.isfinite(x) else 0.0
