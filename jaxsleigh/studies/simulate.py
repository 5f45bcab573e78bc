"""Simulate the closed loop from one or many initial conditions and keep decimated trajectories.

`simulate` is the entry point for figures and for inspecting a few trajectories; for large
batches with summaries only, see `jaxsleigh.studies.ensemble`.
"""
from __future__ import annotations

import functools
import time
from typing import Any, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from ..cache import kept_jit
from ..model.charts import WChart, chart_for
from ..model.closed_loop import ClosedLoop, closed_loop_hamiltonian_w
from .config import DEFAULT_ATOL, DEFAULT_RTOL, MAX_STEP_FACTOR, plant_to_dict, reject_traced, solve_config  # noqa: F401
from ..model.w_laws import control_w_components
from ..model.coordinates import w_to_q
from ..integrate.engine import STIFF_AFTER, check_ics, drive_saving, flight_step, initial_w, working_dtype
from ..integrate.stepsize import StepSizeController
from .options import RunOptions, SaveAt, study_options, takes_objects
from ..integrate.observers import DEFAULT_OBSERVERS, collect
from ..model.params import PlantParams
from ..model.plant import velocity
from ..controllers.actuators import is_sampled
from ..progress import Progress
from .sampled import sampled_solution
from ..status import CONVERGED, VALID, has_result
from .ensemble import summary_repr
from ..model.lanes import lane_table
from ..validate import check_memory

__all__ = ["Solution", "simulate", "DEFAULT_RTOL", "DEFAULT_ATOL"]


class Solution(NamedTuple):
    r"""Decimated closed-loop trajectories, and the per-trajectory summaries of the whole run.

    The fields use the library's one vocabulary (`docs/concepts.md`). The summaries (``T_eps`` to ``u_abs_int``)
    are integrated to RK4 order along every step, not from the saved samples; `effort` gathers them in a dict.

    Attributes:
      t: (T,) saved times (0 included).
      q: (N, T, 3) configuration ``(x, y, theta)`` at the saved times (``q_final``: the last).
      p: (N, T, 2) momentum at the saved times (``p_final``: the last).
      u: (N, T, 2) control at the saved times.
      Hd: (N, T) closed-loop Hamiltonian (NaN for a law without it).
      status: (N,) `Status` codes.
      n_steps: (N,) accepted steps.
      n_rejected: (N,) rejected attempts.
      settings: what produced it (plant, law, horizon, method, dtype, tolerances).
      T_eps: (N,) the start of the last stay in the ball \(|q| \le \varepsilon\) (``inf``: not settled).
      min_abs_theta: (N,) closest approach to \(\theta = 0\).
      max_excursion: (N,) largest \(|q(t)|\).
      u_peak: (N, 2) largest \(|u_1|\), \(|u_2|\).
      u_norm_peak: (N,) largest \(\|u\|\).
      u_energy: (N,) \(\int \|u\|^2 dt\).
      u_abs_int: (N,) \(\int \|u\| dt\).
      run_info: what varies between runs (``wall_s``, ``devices``).
    """

    t: np.ndarray
    q: np.ndarray
    p: np.ndarray
    u: np.ndarray
    Hd: np.ndarray
    status: np.ndarray
    n_steps: np.ndarray
    n_rejected: np.ndarray
    settings: dict
    T_eps: Optional[np.ndarray] = None
    min_abs_theta: Optional[np.ndarray] = None
    max_excursion: Optional[np.ndarray] = None
    u_peak: Optional[np.ndarray] = None
    u_norm_peak: Optional[np.ndarray] = None
    u_energy: Optional[np.ndarray] = None
    u_abs_int: Optional[np.ndarray] = None
    run_info: Optional[dict] = None

    @property
    def effort(self) -> dict:
        """The summaries as ``{name: (N, ...)}`` (those recorded)."""
        return {k: getattr(self, k) for k in SUMMARY_NAMES if getattr(self, k) is not None}

    @property
    def q_final(self) -> np.ndarray:
        """(N, 3) the configuration at the last saved time."""
        return np.asarray(self.q)[:, -1]

    @property
    def p_final(self) -> np.ndarray:
        """(N, 2) the momentum at the last saved time."""
        return np.asarray(self.p)[:, -1]

    @property
    def Hd0(self) -> np.ndarray:
        """(N,) the closed-loop energy \\(H_d\\) at the start (NaN for a law without it)."""
        return np.asarray(self.Hd)[:, 0]

    @property
    def Hd_final(self) -> np.ndarray:
        """(N,) \\(H_d\\) at the last saved time (NaN for a law without it, or where the run failed)."""
        return np.asarray(self.Hd)[:, -1]

    @property
    def t_reached(self) -> np.ndarray:
        """(N,) the last saved time each trajectory reached with a finite state (``t[-1]`` for a run that ended OK;
        NaN for a start that was not integrated)."""
        t = np.asarray(self.t, np.float64)
        finite = np.isfinite(np.asarray(self.q)).all(axis=-1)
        last = finite.shape[1] - 1 - np.argmax(finite[:, ::-1], axis=1)
        return np.where(finite.any(axis=1), t[last], np.nan)

    converged = CONVERGED
    valid = VALID

    def __repr__(self) -> str:
        # a summary, not every trajectory
        nan = np.full(np.shape(self.status), np.nan)
        Hd = np.asarray(self.Hd, np.float64)
        return summary_repr("Solution", self, status=self.status, T_eps=nan if self.T_eps is None else self.T_eps,
                            Hd0=Hd[:, 0] if Hd.ndim == 2 and Hd.shape[1] else None, u_energy=self.u_energy,
                            head=f" trajectories, {np.size(self.t)} saved times")


#: The per-trajectory summaries a `Solution` carries (the observers' standard fields).
SUMMARY_NAMES = ("T_eps", "min_abs_theta", "max_excursion", "u_peak", "u_norm_peak", "u_energy", "u_abs_int")


@kept_jit(static_argnames=("chart",))
def _outputs(yw, t, args: ClosedLoop, chart=WChart()):
    """Chart trajectories ``(N, T, 5)`` at times ``t`` (T,) -> q, u, Hd (vmapped over batch and time; Hd is
    NaN for a law without it)."""

    def one(y, t):
        if chart.name == "w":
            w, p = y[:3], y[3:]
            u = jnp.stack(control_w_components(w, velocity(p, args.plant), args.controller)).astype(y.dtype)
            return w_to_q(w), u, closed_loop_hamiltonian_w(y, args)
        u = jnp.stack(chart.field_and_control(t, y, args)[1])
        return chart.from_chart(y)[:3], u, jnp.full((), jnp.nan, y.dtype)

    return jax.vmap(jax.vmap(one, in_axes=(0, 0)), in_axes=(0, None))(yw, t)


@functools.partial(jax.jit, static_argnames=("chart",))
def _outputs_lanes(yw, t, args: ClosedLoop, chart=WChart()):
    """`_outputs` with canonical per-lane ``args`` (one lane per trajectory)."""
    axes = jax.tree_util.tree_map(lambda _: -1, args)
    return jax.vmap(lambda y, a: _outputs.__wrapped__(y[None], t, a, chart), in_axes=(0, axes))(yw, args)


#: Host memory one saved point of one start takes: the state, its outputs (q, p, u, H_d) and their copies (the
#: engine's trajectory, the host arrays, the file written), about 24 numbers of 8 bytes.
BYTES_PER_SAVE = 192


def check_saves(ics, cfg, names: dict | None = None) -> None:
    r"""Refuse, before any work, trajectories that would not fit in memory: \(N\) starts x the saved points
    (``t_final / (dt x saveat.every) + 1``, a sampled law's ``t_final / period + 1``) x `BYTES_PER_SAVE`.
    ``names`` maps ``ics``, ``t_final`` and ``every`` to the keywords or flags the message names."""
    w = {"ics": "ics", "t_final": "t_final", "every": "saveat.every", **(names or {})}
    shape = np.shape(ics)
    n = 1 if len(shape) < 2 else int(shape[0])
    h = cfg.horizon
    if is_sampled(cfg.controller):
        saves = int(np.ceil(h.t_final / float(cfg.controller.sampler.period) - 1e-9)) + 1
        every = w["every"] if "every" in (names or {}) else "the sample period"
        fix = f"use a shorter {w['t_final']}, a longer {every} or fewer starts"
    else:
        saves = h.n_out + 1
        fix = f"save fewer points (a larger {w['every']}, a shorter {w['t_final']}) or simulate fewer starts"
    check_memory(n * saves, f"{w['ics']} x {w['t_final']} / {w['every']}", bytes_per_start=BYTES_PER_SAVE,
                 unit=f"saved points ({n:,} start{'s' if n != 1 else ''} x {saves:,} points each)", fix=fix)


def _simulate(ics, *, plant: Optional[PlantParams], gains: Any, controller: Any, t_final: float, dt: float,
              x64: bool, stepsize: StepSizeController, saveat: SaveAt, run: RunOptions) -> Solution:
    """`simulate` (see there) with its option objects checked (`study_options`; ``saveat.every``
    already defaulted to 10): simulate the closed loop (plant eq. 1 + control law eq. 13, or any law).

    Raises:
      ValueError: any bad option, or a single start (or every start of a batch) that cannot be
        integrated. A bad row of a larger batch is flagged in ``status`` (outputs NaN) and named in
        a `FlaggedStartsWarning`; the other rows are computed.
    """
    reject_traced("simulate", **locals())    # first: a NumPy front, neither jittable nor differentiable
    cfg = solve_config(plant=plant, gains=gains, t_final=t_final, dt=dt, save_every=saveat.every, x64=x64,
                       stepsize=stepsize, controller=controller)
    check_saves(ics, cfg)
    progress = run.progress
    if is_sampled(cfg.controller):
        if cfg.lanes is not None:
            raise ValueError("per-trajectory parameters are not available for a sampled law yet; drop them")
        return Solution(**sampled_solution(cfg, ics, progress))
    horizon = cfg.horizon
    chart = chart_for(cfg.law)
    ics5, status0 = check_ics(ics, cfg.dtype, singular=chart.singular)
    with jax.enable_x64(cfg.x64):
        dtype = working_dtype()
        args = cfg.lane_loop(ics5.shape[0]) or ClosedLoop(cfg.plant, cfg.law)
        y0w = initial_w(ics5, status0, dtype, chart)
        t_start = time.perf_counter()
        with Progress(progress, desc="simulate") as bar:
            step = cfg.stepsize
            final, ys = drive_saving(y0w, status0, args, horizon, step, eps=cfg.eps, progress=bar,
                                     stiff_after=STIFF_AFTER)
        yw = np.concatenate([np.asarray(y0w)[:, None], ys], axis=1)
        bad = status0 != 0
        yw[bad] = np.nan
        q, u, Hd = _trajectory_outputs(yw, horizon, args, chart, lanes=cfg.lanes is not None)
    # where it ran (named on every figure of it) and how long it took: they vary between runs
    run_info = {"wall_s": time.perf_counter() - t_start, "devices": [str(jax.devices()[0])]}
    # restore the exact initial state (the w chart round trip rounds it in float32)
    q[:, 0] = np.where(bad[:, None], np.nan, ics5[:, :3])
    effort = collect(DEFAULT_OBSERVERS, final.obs, final.quad)
    none = bad | ~has_result(np.asarray(final.status))      # not integrated or failed: NaN, not a partial integral
    for k, v in effort.items():
        v[none] = np.nan
    effort["T_eps"] = np.where(np.asarray(final.status) == 0, effort["T_eps"], np.nan)
    return Solution(t=horizon.t(), q=q, p=yw[..., 3:], u=u, Hd=Hd, status=np.asarray(final.status),
                    n_steps=np.asarray(final.n_accept), n_rejected=np.asarray(final.n_reject),
                    settings=_solution_settings(cfg, args, ics5.shape[0], step.method == "adaptive"),
                    run_info=run_info,
                    **{k: effort[k] for k in SUMMARY_NAMES if k in effort})


def _trajectory_outputs(yw: np.ndarray, horizon, args: ClosedLoop, chart, *, lanes: bool):
    """``(q, u, Hd)`` along the saved w-chart states ``yw`` (N, T, 5), as NumPy arrays (``lanes``: one
    closed loop per trajectory)."""
    t = np.asarray(horizon.t(), yw.dtype)
    if not lanes:
        return tuple(np.array(a) for a in _outputs(yw, t, args, chart))
    return tuple(np.array(o[:, 0]) for o in _outputs_lanes(yw, t, args, chart))


def _solution_settings(cfg, args: ClosedLoop, n: int, adaptive: bool = False) -> dict:
    """The settings a `Solution` records: the run's, with its save interval, the flight rule of the implicit step
    (``adaptive``) and, with per-trajectory parameters, the values each trajectory used; without the ensemble-only
    ``check_passivity`` and ``eps``."""
    settings = {**cfg.settings(), "save_every": cfg.horizon.save_every}
    if adaptive:
        settings["stiff_after"], settings["flight_step"] = STIFF_AFTER, flight_step(cfg.stepsize.rtol, cfg.stepsize.atol, cfg.dtype)
    if cfg.lanes is not None:
        settings["params"] = {k: v.tolist() for k, v in lane_table(args.plant, args.controller, n).items()}
    settings.pop("check_passivity")
    settings.pop("eps")
    return settings


@takes_objects
def simulate(ics, *, plant: Optional[PlantParams] = None, gains: Any = None, controller: Any = None,
             t_final: float = 100.0, dt: float = 0.01, x64: bool = False,
             stepsize: Optional[StepSizeController] = None, saveat: Optional[SaveAt] = None,
             run: Optional[RunOptions] = None) -> Solution:
    """Simulate the closed loop (plant eq. 1 + control law eq. 13, or any law) and keep decimated trajectories.

    Args:
      ics: ``(3,)``, ``(5,)``, ``(N, 3)`` or ``(N, 5)``: ``(x, y, theta[, p1, p2])``.
      plant, gains: defaults are the paper's (m = 2, J = 1, l = 1, Coulomb; L = diag(2, .5, .8), k = 0.1,
        D_hat = diag(4, 8)). ``gains`` may also be a preset name (``"tuned"``) or a gains file. Both are
        validated eagerly. Leaves may vary per trajectory (`jaxsleigh.model.lanes`).
      controller: any feedback law ``u = law(q, v)`` instead of the paper's (`jaxsleigh.model.controller`);
        integrated in the physical chart, and ``Hd`` is NaN (H_d belongs to the paper's law).
      t_final, dt: horizon and base step (``t_final`` a multiple of ``dt``); x64: compute in float64.
      stepsize: `jaxsleigh.StepSizeController` (default: adaptive RK4, tolerances per dtype, step cap 100 dt; its
        ``check_passivity`` does not apply).
        Adaptive, a start still in a stiff flight after `jaxsleigh.integrate.engine.STIFF_AFTER` attempts (a mean
        step below a tenth of ``dt``: within ~1e-3 rad of theta = 0) goes on with the linearly implicit step
        (`jaxsleigh.integrate.rosenbrock`), as in ensembles and basins; every other start is stepped as without it.
      saveat: `jaxsleigh.SaveAt` (``every``: keep every ``every``-th base step, default 10; ``summaries`` does not
        apply).
      run: `jaxsleigh.RunOptions` (only ``progress`` applies).

    Returns:
      `Solution`, as NumPy arrays; its ``settings`` record the flight rule (``stiff_after``, ``flight_step``).

    Raises:
      ValueError: any bad option (an object's field that does not apply, changed from its default, included), or a
        single start (or every start of a batch) that cannot be integrated. A bad row of a larger batch is flagged
        in ``status`` (outputs NaN) and named in a `FlaggedStartsWarning`; the other rows are computed.
      TypeError: a keyword of jaxsleigh 0.1 (``rtol=``, ``save_every=``, ...), naming the object that holds it now.
    """
    stepsize, saveat, run = study_options("simulate", stepsize, saveat, run, saveat_default=SaveAt(every=10))
    return _simulate(ics, plant=plant, gains=gains, controller=controller, t_final=t_final, dt=dt, x64=x64,
                     stepsize=stepsize, saveat=saveat, run=run)
