"""Ensembles: many initial conditions at once, chunked, checkpointed, sharded across devices.

`run_ensemble` integrates up to ~10^7 initial conditions on one machine. Memory is bounded
by the chunk (``chunk_size`` trajectories at a time), not by the number of steps: each trajectory
carries its final state and on-line summaries, updated inside the scan at every accepted step:

* ``T_eps``: convergence time, the first time after which \\(|q| \\le \\epsilon\\) holds at every
  accepted step until the horizon (``inf`` if it has not settled by then, ``nan`` if the
  trajectory failed); ``|q| = \\sqrt{x^2 + y^2 + \\theta^2}``;
* ``min_abs_theta`` (closest approach to the singular set), ``max_excursion`` (largest ``|q|``),
  ``Hd0`` and ``Hd_final``, ``n_steps`` / ``n_rejected``, ``status``.

Decimated trajectories are stored only when asked for (``save_every``). With ``checkpoint_dir``
every finished chunk is written to disk at once, and ``resume=True`` picks an interrupted run up
from the finished chunks, ending with the same result as an uninterrupted run.
"""
from __future__ import annotations

import collections
import concurrent.futures
import contextlib
import functools
import threading
import time
from typing import Any, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from ..cache import kept_jit
from ..model.charts import WChart, chart_for
from ..model.closed_loop import ClosedLoop, closed_loop_hamiltonian_w
from ..files.checkpoint import run_key
from ..files.chunks import ChunkStore, starts_digest
from .config import reject_traced, solve_config
from .options import RunOptions, SaveAt, study_options, takes_objects
from .audit import audit_rows, for_law, resolve as resolve_audit
from ..integrate.guard import GREW, NEAR, grown_settled_mode
from ..integrate.horizon import reference_max_steps
from ..integrate.stepsize import StepSizeController
from ..integrate.observers import DEFAULT_OBSERVERS, collect
from ..integrate.engine import (STIFF_AFTER, active_lanes, advance_pool, check_ics, drive_final, drive_plain,
                                drive_saving, finish_state, flight_step, initial_w, put_lanes,
                                take_lanes_of, working_dtype)
from ..integrate.pool import Ladder, StragglerPool
from ..cores import PART_SIZE, default_chunk_size, run_parts, workers
from ..model.params import Gains, PlantParams
from ..controllers.actuators import is_sampled
from ..progress import Progress
from .sampled import sampled_settings, sampled_summaries
from ..status import CONVERGED, VALID, Status, converged, counts_in_words, has_result, integrated
from ..validate import check_memory, whole
from ..integrate.stepper import controls, init_batch
from ..model.lanes import has_lanes, lane_table, take_lanes

__all__ = ["EnsembleResult", "run_ensemble", "SUMMARY_FIELDS"]

#: a part hands its still-active lanes to the chunk's tail batch once at most this many are left (or, on CPU, a
#: quarter of the part if that is more: `hand_off_at`); the default 10^5-start basin took 20.9 s with 128, 24.7 s
#: with 16, 67.3 s with 0 (every part finishing its own stragglers; python experiments/performance/engine_defaults.py)
TAIL_LANES = 128

#: the pool of stragglers' batches (`tail_ladder`). On XLA:CPU the compiled step gives every lane the same bits at
#: 64, 128 and 256 lanes (float32; 8, 16-32 and 1024 each round otherwise; float64 from 32 on), so a straggler's
#: result does not depend on the lanes that share its batch. On CPU the pool runs batches of TAIL_MIN lanes only
#: (`CPU_TAIL_LADDER`): one shape whatever the lanes, so a later call with other numbers finds its programs compiled;
#: an accelerator's pool (several devices) takes powers of two from TAIL_MIN to TAIL_MAX (`TAIL_LADDER`).
TAIL_MIN, TAIL_MAX = 64, 256
TAIL_LADDER = Ladder(floor=TAIL_MIN, ceiling=TAIL_MAX)
CPU_TAIL_LADDER = Ladder(floor=TAIL_MIN, ceiling=TAIL_MIN)


def tail_ladder(backend: Optional[str] = None) -> Ladder:
    """The pool of stragglers' batch sizes on ``backend`` (default JAX's): `CPU_TAIL_LADDER` on CPU, else
    `TAIL_LADDER`."""
    return CPU_TAIL_LADDER if (backend or jax.default_backend()) == "cpu" else TAIL_LADDER


def hand_off_at(lanes: int, backend: Optional[str] = None) -> int:
    """How few still-active lanes a part of ``lanes`` runs down to before it hands them to the pool of stragglers.
    On CPU: `TAIL_LANES`, or a quarter of the part if that is more, where the engine would otherwise compact the
    part to a smaller batch (`jaxsleigh.integrate.pool.Ladder.shrinks`): a part then only ever runs at its own size,
    and its last lanes at the pool's one size (`tail_ladder`), so no batch shape depends on how fast the lanes
    settle. On an accelerator (a compaction floor of 8,192 lanes, `jaxsleigh.integrate.engine.min_batch`):
    `TAIL_LANES`."""
    if (backend or jax.default_backend()) != "cpu":
        return TAIL_LANES
    return max(TAIL_LANES, lanes // 4)


#: chunks whose parts are done may wait this many at most for their stragglers before the next chunk starts
MAX_PENDING = 16

SUMMARY_FIELDS = ("q_final", "p_final", "T_eps", "min_abs_theta", "max_excursion", "Hd0", "Hd_final", "t_reached",
                  "n_steps", "n_rejected", "status", "u_peak", "u_norm_peak", "u_energy", "u_abs_int")


class EnsembleResult(NamedTuple):
    r"""Per-initial-condition results (NumPy arrays, first axis N) and the settings.

    Attributes (the library's one vocabulary, `docs/concepts.md`):
      ics: (N, 5) initial conditions ``(x, y, theta, p1, p2)``.
      q_final, p_final: (N, 3), (N, 2) state at the horizon (NaN if the trajectory failed).
      T_eps: (N,) convergence time (``inf``: not settled by the horizon; ``nan``: failed).
      min_abs_theta, max_excursion, Hd0, Hd_final, t_reached: (N,) on-line summaries.
      n_steps, n_rejected, status: (N,) integers.
      u_peak: (N, 2) largest ``|u_1|`` [N] and ``|u_2|`` [N m] over the run; u_norm_peak: (N,)
        largest ``||u||``; u_energy: (N,) control energy \(\int_0^T \|u\|^2 dt\); u_abs_int: (N,)
        \(\int_0^T \|u\| dt\) (RK4-order quadrature, `ControlEffort`;
        up to the time reached; NaN for starts not integrated and on the plain fixed-step path).
      t, q, p: trajectories ``(T,)``, ``(N, T, 3)``, ``(N, T, 2)`` (every ``save_every`` base steps) when
        ``save_every`` was given, else ``None`` (as in `jaxsleigh.Solution`).
      settings: everything that produced the result (the same for every run of the same call).
      run_info: what varies between runs: ``wall_s``, ``devices``, ``chunks_reused``.
      params: with per-trajectory parameters, the values each row used: ``{name: (N,)}`` with
        names ``m, J, l``, the damping's numbers, ``k, l1, l2, l3, d11, d12, d22``
        (`jaxsleigh.model.lanes.lane_table`); ``None`` for one plant and one set of gains.
      observed: the fields of observers beyond the standard ones, ``{name: (N, ...)}``.
      unresolved: (N,) bool: the row's settled oscillation grew and is weakly damped or growing at the horizon
        (`jaxsleigh.integrate.guard.grown_settled_mode`), so its energy hangs on a seed below every tolerance and
        is not resolved by any setting; the accuracy audit re-runs these rows first (`jaxsleigh.studies.audit`).
        All ``False`` for laws without the settled pair and on the plain fixed-step path (no ``min_abs_theta``).
    """

    ics: np.ndarray
    q_final: np.ndarray
    p_final: np.ndarray
    T_eps: np.ndarray
    min_abs_theta: np.ndarray
    max_excursion: np.ndarray
    Hd0: np.ndarray
    Hd_final: np.ndarray
    t_reached: np.ndarray
    n_steps: np.ndarray
    n_rejected: np.ndarray
    status: np.ndarray
    u_peak: np.ndarray
    u_norm_peak: np.ndarray
    u_energy: np.ndarray
    u_abs_int: np.ndarray
    settings: dict
    t: Optional[np.ndarray] = None
    q: Optional[np.ndarray] = None
    p: Optional[np.ndarray] = None
    params: Optional[dict] = None
    observed: Optional[dict] = None
    run_info: Optional[dict] = None
    unresolved: np.ndarray | None = None

    converged = CONVERGED
    valid = VALID

    def __getattr__(self, name):
        renamed = {"q_traj": "q", "p_traj": "p"}
        if name in renamed:
            raise AttributeError(f"EnsembleResult.{name} is now .{renamed[name]} (the trajectory, as in Solution); "
                                 f"the final state is .q_final / .p_final")
        raise AttributeError(f"'EnsembleResult' object has no attribute {name!r}")

    def __repr__(self) -> str:
        # a summary, not every array (print(result) of 10^6 starts would dump them all)
        return summary_repr("EnsembleResult", self, status=self.status, T_eps=self.T_eps, Hd0=self.Hd0,
                            u_energy=self.u_energy)


def _num(v) -> str:
    """A setting for a summary: ``'0.1'``, or ``'per trajectory'`` for a per-lane record."""
    return f"{v:g}" if isinstance(v, (int, float)) and not isinstance(v, bool) else "per trajectory"


def _quantiles(values, mask=None, unit: str = "") -> str:
    """``'p10 1.2, median 3.4, p90 5.6 s'`` of the finite ``values`` (where ``mask``); ``'none'``."""
    v = np.asarray(values, np.float64).ravel()
    keep = np.isfinite(v) if mask is None else np.isfinite(v) & np.asarray(mask, bool).ravel()
    if not keep.any():
        return "none"
    p10, p50, p90 = np.percentile(v[keep], (10.0, 50.0, 90.0))
    return f"p10 {p10:.4g}, median {p50:.4g}, p90 {p90:.4g}{unit}"


def summary_repr(name: str, result, *, status, T_eps, Hd0=None, u_energy=None, head: str = "",
                 extra: tuple = ()) -> str:
    """The summary that ``repr`` / ``print`` of a result shows instead of every array: N, status counts,
    converged fraction, T_eps median, energy quantiles, the settings' essentials and the arrays' shapes.

    Args:
      name: the class name; result: the result (a NamedTuple); status, T_eps: its per-start arrays
        (any shape); Hd0, u_energy: optional per-start energies; head: text after ``N = ...``;
        extra: further lines (without indent) after the convergence line.
    """
    st = np.asarray(status).ravel()
    t = np.asarray(T_eps, np.float64).ravel()
    valid = integrated(st)
    conv = converged(st, t)
    n_valid = int(valid.sum())
    frac = f"{conv.sum() / n_valid:.4f}" if n_valid else "nan"
    med = f"{np.median(t[conv]):.4g} s" if conv.any() else "none converged"
    s = result.settings or {}
    g, pl = s.get("gains") or {}, s.get("plant") or {}
    lines = [f"{name}(N = {st.size}{head}: {counts_in_words(st) if st.size else 'empty'}",
             f"  converged (|q| <= eps within t_final): {int(conv.sum())}/{n_valid} valid = {frac}; "
             f"T_eps median {med}", *("  " + e for e in extra)]
    if Hd0 is not None:
        lines.append(f"  H_d(0) [J]: {_quantiles(Hd0, valid)}")
    if u_energy is not None:
        lines.append(f"  control energy int |u|^2 dt of the converged: {_quantiles(u_energy, conv)}")
    L = g.get("L")
    gains = (f"L = {[round(float(x), 4) for x in L]}, k = {_num(g.get('k'))}"
             if isinstance(L, (list, tuple)) else "per trajectory") if g else "not recorded"
    plant = (f"m = {_num(pl.get('m'))}, J = {_num(pl.get('J'))}, l = {_num(pl.get('l'))}, "
             f"{str(pl.get('damping', '?')).replace('Damping', '').lower()} damping") if pl else "not recorded"
    lines.append(f"  settings: {s.get('dtype', '?')}, {s.get('method', '?')}, t_final = {_num(s.get('t_final'))} s, "
                 f"dt = {_num(s.get('dt'))} s" + (f", eps = {_num(s['eps'])}" if "eps" in s else "")
                 + f"; gains {gains}; plant {plant}")
    arrays = [f"{f} {tuple(np.shape(v))}" for f, v in zip(result._fields, result)
              if isinstance(v, np.ndarray)]
    lines.append("  arrays: " + ", ".join(arrays) + ")")
    return "\n".join(lines)


@kept_jit()
def _hd_batch(yw, args):
    return jax.vmap(closed_loop_hamiltonian_w, in_axes=(0, None))(yw, args)


@kept_jit()
def _hd_lanes(yw, args):
    # closed_loop_hamiltonian_w broadcasts over a trailing batch axis, per-lane args included
    return closed_loop_hamiltonian_w(yw.T, args)


def _hd_any(yw, args):
    """H_d of a batch ``yw`` (N, 5) under one plant or per-lane (canonical) ``args``."""
    return _hd_lanes(yw, args) if has_lanes(args.plant, args.gains) else _hd_batch(yw, args)


@kept_jit(static_argnames=("chart",))
def _to_q_batch(yw, chart=WChart()):
    return jax.vmap(chart.from_chart)(yw)


def _ends(y, ok, y0w, status0, args) -> tuple:
    """``(chart, invalid, q_final, p_final, Hd0)`` of a chunk's final chart states ``y`` (N, 5): NaN where the run
    did not end OK (``ok``); ``Hd0`` NaN where the start was not integrated (``invalid``) and for a law without the
    paper's H_d."""
    chart = chart_for(args.controller)
    yq = np.array(_to_q_batch(jax.device_put(y), chart), np.float64)   # (jnp.asarray compiles a copy)
    yq[~ok] = np.nan
    invalid = np.asarray(status0) != Status.OK
    hd0 = np.array(_hd_any(y0w, args), np.float64) if chart.has_energy else np.full(len(ok), np.nan)
    hd0[invalid] = np.nan
    return chart, invalid, yq[:, :3], yq[:, 3:], hd0


def _chunk_summaries(final, y0w, status0, args, observers=DEFAULT_OBSERVERS) -> dict:
    """Host-side summaries of one chunk from the final (batch-last) stepper state. Standard
    summaries that no observer provides are NaN; other observers' results are added by name.
    ``Hd0`` and ``Hd_final`` are NaN for a law without the paper's H_d."""
    status = np.asarray(final.status)
    ok = status == Status.OK
    chart, invalid, q_final, p_final, hd0 = _ends(np.moveaxis(np.asarray(final.y), -1, 0), ok, y0w, status0, args)
    obs = collect(observers, final.obs, final.quad)
    n = status.shape[0]
    for k, shape in (("T_eps", ()), ("min_abs_theta", ()), ("max_excursion", ()), ("u_peak", (2,)),
                     ("u_norm_peak", ()), ("u_energy", ()), ("u_abs_int", ())):
        obs.setdefault(k, np.full((n,) + shape, np.nan))
    out = {
        "q_final": q_final, "p_final": p_final,
        # certified not to settle (jaxsleigh.integrate.stragglers): not settled within the horizon, T_eps = inf
        "T_eps": np.where(ok, obs.pop("T_eps"), np.where(status == Status.NOT_SETTLING, np.inf, np.nan)),
        "Hd0": hd0,
        "Hd_final": np.where(ok & chart.has_energy, np.asarray(final.Hd, np.float64), np.nan),
        "t_reached": np.where(invalid, np.nan, np.asarray(final.t, np.float64)),
        "n_steps": np.asarray(final.n_accept, np.int64),
        "n_rejected": np.asarray(final.n_reject, np.int64),
        "status": status.astype(np.int32),
    }
    # a row without a result (not integrated, or failed while stepping: jaxsleigh.status.NO_RESULT) has NaN
    # summaries, not the integrals up to its failure
    none = invalid | ~has_result(status)
    for k, v in obs.items():
        out[k] = np.where(none.reshape((-1,) + (1,) * (v.ndim - 1)), np.nan, v)
    return out


def _plain_summaries(y, status, y0w, status0, args, horizon) -> dict:
    """Summaries of `drive_plain`: final state, H_d, status; no path data."""
    ok = status == Status.OK
    chart, invalid, q_final, p_final, hd0 = _ends(y, ok, y0w, status0, args)
    nan = np.full(len(status), np.nan)
    hd = np.array(_hd_batch(jnp.asarray(y, y0w.dtype), args), np.float64) if chart.has_energy else nan
    return {"q_final": q_final, "p_final": p_final, "T_eps": nan, "min_abs_theta": nan, "max_excursion": nan,
            "Hd0": hd0, "Hd_final": np.where(ok, hd, np.nan), "t_reached": np.where(ok, horizon.t_final, np.nan),
            "n_steps": np.where(invalid, 0, horizon.n_steps).astype(np.int64),
            "n_rejected": np.zeros(len(status), np.int64), "status": status.astype(np.int32),
            "u_peak": np.full((len(status), 2), np.nan), "u_norm_peak": nan, "u_energy": nan, "u_abs_int": nan}


def _refuse_for_sampled(**given) -> None:
    """What a sampled law (`jaxsleigh.studies.sampled`) cannot do in `run_ensemble` yet, refused by name."""
    what = {"save_every": "save_every (use simulate for the samples)", "observers": "observers",
            "summaries": "summaries=False"}
    for name, value in given.items():
        if value not in (None, False):
            raise ValueError(f"not available for a sampled law (controller=sampled(...)) yet: {what[name]}")


def _checked_options(stepsize: StepSizeController, saveat: SaveAt, run: RunOptions) -> tuple:
    """The run options checked in turn (the first wrong one is refused): ``(chunk_size, shard, segment)``
    resolved (the default chunk size; whole numbers)."""
    summaries, method, save_every = saveat.summaries, stepsize.method, saveat.every
    chunk_size, shard, checkpoint_dir, resume = run.chunk_size, run.shard, run.checkpoint_dir, run.resume
    if not isinstance(summaries, (bool, np.bool_)):
        raise ValueError(f"summaries must be True or False, got {summaries!r}")
    if not summaries and (method != "rk4" or stepsize.check_passivity or save_every is not None):
        raise ValueError("summaries=False is the plain fixed-step path: it needs method='rk4', "
                         "check_passivity=False and no save_every")
    chunk_size = default_chunk_size(devices=run.devices) if chunk_size is None else \
        whole("chunk_size", chunk_size, example=16384)
    if shard is not None:
        if checkpoint_dir is None:
            raise ValueError("shard=(index, count) writes its chunks to checkpoint_dir; give one")
        count = whole("shard count", shard[1])
        shard = (whole("shard index", shard[0], minimum=0, maximum=count - 1), count)
    segment = whole("segment", run.segment, example=1000)
    if not isinstance(resume, (bool, np.bool_)):
        raise ValueError(f"resume must be True or False, got {resume!r}")
    if resume and checkpoint_dir is None:
        raise ValueError("resume=True needs checkpoint_dir (the folder of the interrupted run's chunks)")
    return chunk_size, shard, segment


def _lane_args(cfg, ics5: np.ndarray, summaries) -> Optional[ClosedLoop]:
    """The per-trajectory parameters broadcast to one lane per start (``None``: one plant and one law)."""
    if cfg.lanes is not None and not summaries:
        raise ValueError("summaries=False (the plain fixed-step path) runs one plant and one set of gains; "
                         "per-trajectory parameters need summaries=True")
    return cfg.lane_loop(ics5.shape[0])


def _rows_law(lane_args: Optional[ClosedLoop], rows, **law) -> dict:
    """The keywords ``plant``, ``gains``, ``controller`` of a run of the rows ``rows`` only (the per-trajectory
    parameters of those rows; the audit's re-run)."""
    if lane_args is None:
        return law
    per_row = take_lanes(lane_args.controller, rows)
    paper = isinstance(per_row, Gains)
    return {"plant": take_lanes(lane_args.plant, rows), "gains": per_row if paper else None,
            "controller": None if paper else per_row}


def _ensemble_settings(cfg, sampled: bool, save_every, chunk_size: int, summaries, observers) -> dict:
    """Everything that produces the result (the same for every run of the same call)."""
    settings = {
        **(sampled_settings(cfg) if sampled else cfg.settings()), "save_every": save_every,
        "chunk_size": chunk_size, "summaries": bool(summaries),
    }
    if observers is not None:
        settings["observers"] = [repr(o) for o in observers]
    return settings


def _part_sizes(chunk: int, devs) -> list:
    """The lanes of each part a chunk of ``chunk`` starts is cut into."""
    # every chunk is cut into parts of PART_SIZE lanes (a smaller chunk is one part), the last padded
    # (jaxsleigh.cores): the same parts whatever the number of cores, so every start meets the same
    # compiled program, and the bytes never depend on how many cores ran it
    # (on an accelerator one part per device: a GPU wants large batches, not parts of 1024)
    per_part = PART_SIZE if jax.default_backend() == "cpu" else -(-chunk // len(devs))
    lanes = min(per_part, -(-chunk // 8) * 8)
    lanes = -(-lanes // 8) * 8
    return [lanes] * -(-chunk // lanes)


def _open_store(checkpoint_dir, resume, settings: dict, ics5: np.ndarray, chunk: int) -> Optional[ChunkStore]:
    """The checkpoint folder's store, opened (``None`` without ``checkpoint_dir``)."""
    if checkpoint_dir is None:
        return None
    keyed = {k: v for k, v in settings.items() if k not in ("wall_s", "devices")}
    store = ChunkStore(checkpoint_dir, run_key(keyed, ics5))
    store.open(resume=bool(resume), manifest={"n": ics5.shape[0], "chunk": chunk, "starts": starts_digest(ics5),
                                              "settings": settings})
    return store


class _PartProgress:
    """One part's progress (reported from its thread), mapped onto the whole run's bar: the parts of the chunk
    of rows lo:hi (of n) share ``done`` (each one's fraction) and ``lock``; ``cuts`` are their bounds."""

    def __init__(self, i, done, lock, bar, cuts, lo, hi, n):
        self.i, self.done, self.lock, self.bar = i, done, lock, bar
        self.cuts, self.lo, self.hi, self.n = cuts, lo, hi, n

    def update(self, frac):
        self.done[self.i] = frac
        with self.lock:
            self.bar.update((self.lo + float(self.done @ np.diff(self.cuts)) / self.cuts[-1] * (self.hi - self.lo))
                            / self.n)


class _Chunks:
    """The per-chunk work of `run_ensemble_resolved`, holding what every chunk shares: a chunk's rows computed by the
    sampled-data loop (`sampled_part`) or by the engine (`engine_part`: parts run concurrently on the devices,
    their stiff stragglers finished in one tail batch in the background)."""

    def __init__(self, cfg, *, step, observers, saveat: SaveAt, segment, dtype, devs, lane_args, ics5, status0, chunk,
                 bar, tail_pool, rules: "LaneRules"):
        self.cfg, self.horizon, self.eps, self.adaptive = cfg, cfg.horizon, cfg.eps, cfg.adaptive
        self.step, self.observers, (self.save_every, self.summaries) = step, observers, saveat
        self.segment, self.chart, self.dtype, self.devs = segment, chart_for(cfg.law), dtype, devs
        self.args, self.lane_args, self.ics5, self.status0 = ClosedLoop(cfg.plant, cfg.law), lane_args, ics5, status0
        self.n, self.chunk, self.part_sizes = ics5.shape[0], chunk, _part_sizes(chunk, devs)
        self.bar, self.tail_pool = bar, tail_pool
        self._pool, self._pool_lock = None, threading.Lock()
        self.store = None                 # the checkpoint store, where chunks in progress are written
        self.rules = rules._replace(certify=rules.certify and self.adaptive)   # (a fixed step certifies nothing)

    def sampled_part(self, lo, hi):
        """The sampled-data loop's summaries of rows lo:hi (their lanes, in a sweep)."""
        if self.lane_args is None:
            return sampled_summaries(self.cfg, self.ics5[lo:hi])
        return sampled_summaries(self.cfg, self.ics5[lo:hi], take_lanes(self.lane_args, np.arange(lo, hi)))

    def engine_part(self, lo, hi, ci=None, pending=None):
        """The engine's summaries (and trajectories) of rows lo:hi, padded to the chunk's shape and
        cut into its parts, which run concurrently on the devices; returns a function that gives them.
        With stragglers and a store, the parts' states are written as the chunk's work in progress (`pending`,
        `jaxsleigh.files.chunks.ChunkStore.save_pending`) before they go to the pool; ``pending`` (those arrays, read
        back on resume) takes the parts' place."""
        part_sizes = self.part_sizes
        pad = sum(part_sizes) - (hi - lo)
        st = np.concatenate([self.status0[lo:hi], np.full(pad, Status.INVALID_INPUT, np.int32)])
        ic = np.concatenate([self.ics5[lo:hi], np.zeros((pad, 5))])
        rows = np.concatenate([np.arange(lo, hi), np.full(pad, lo)])   # padding rows reuse the first's lanes
        y0w = np.asarray(initial_w(ic, st, self.dtype, self.chart))     # once per chunk: op by op, it is not cheap
        cuts = np.cumsum([0] + part_sizes)
        bar_lock = threading.Lock()
        done = np.zeros(len(part_sizes))
        # the adaptive engine's few stiff stragglers are gathered from the parts into one batch (_tail); on CPU a
        # lone part's too, unless its run lets compaction change bits (its batch shapes then never depend on how
        # fast its lanes settle: `hand_off_at`)
        lone = self.rules.bitwise and jax.default_backend() == "cpu"
        tails = self.summaries and self.save_every is None and self.adaptive and (len(part_sizes) > 1 or lone)

        def part(i):
            a0, a1 = cuts[i], cuts[i + 1]
            with jax.enable_x64(self.cfg.x64):       # the dtype switch is per thread
                sub = _PartProgress(i, done, bar_lock, self.bar, cuts, lo, hi, self.n)
                return self._engine_rows(jax.device_put(y0w[a0:a1]), st[a0:a1], rows[a0:a1], sub, tails)

        if tails and pending is not None:
            pieces = self._pieces_from(pending, len(part_sizes))
        else:
            pieces = run_parts(part, range(len(part_sizes)), self.devs)
            if tails and self.store is not None and ci is not None:
                self.store.save_pending(ci, self._pieces_to(pieces), lo=lo, starts=self.ics5[lo:hi])
        if not tails:
            return lambda: {k: np.concatenate([p[k] for p in pieces]) for k in pieces[0]}
        return self._tail(pieces, [np.arange(cuts[i], cuts[i + 1]) for i in range(len(part_sizes))], y0w, st, rows, lo)

    @staticmethod
    def _pieces_to(pieces) -> dict:
        """The parts' host states as named arrays (``p<part>_<leaf>``) for a pending chunk's file."""
        return {f"p{p:04d}_{i:03d}": np.asarray(leaf) for p, piece in enumerate(pieces)
                for i, leaf in enumerate(jax.tree_util.tree_leaves(piece))}

    def _pieces_from(self, arrays: dict, n_parts: int) -> list:
        """`_pieces_to` read back: the parts' host states (the tree of the stepper's state, from its shape)."""
        with jax.enable_x64(self.cfg.x64):
            ctl = controls(self.step, self.dtype, dt=self.horizon.dt, eps=self.eps, xp=np)
            shape = jax.eval_shape(lambda y, s: init_batch(y, s, self.args, ctl, observers=self.observers),
                                   jax.ShapeDtypeStruct((1, 5), self.dtype), jax.ShapeDtypeStruct((1,), jnp.int32))
        tree = jax.tree_util.tree_structure(shape)
        return [jax.tree_util.tree_unflatten(tree, [arrays[f"p{p:04d}_{i:03d}"] for i in range(tree.num_leaves)])
                for p in range(n_parts)]

    def _lanes_args(self, rows):
        """The closed loop's ``args`` for ``rows`` (their lanes, with per-trajectory parameters)."""
        if self.lane_args is None:
            return self.args
        return take_lanes(self.lane_args, rows)

    def _engine_rows(self, y0w, st, rows, sub, tails=False):
        """The engine's summaries (and trajectories) of one part, on the current default device; with
        ``tails``, its final state with its last few still-active lanes not yet finished."""
        a = self._lanes_args(rows)
        horizon, step, segment, observers = self.horizon, self.step, self.segment, self.observers
        kw = dict(eps=self.eps, progress=sub, observers=observers)
        fin = dict(certify=self.rules.certify, stiff_after=STIFF_AFTER, bitwise=self.rules.bitwise)
        if not self.summaries:
            part = _plain_summaries(*drive_plain(y0w, st, a, horizon, segment=segment, progress=sub),
                                    y0w, st, a, horizon)
        elif tails:
            return drive_final(y0w, st, a, horizon, step, segment=segment, stop_at=hand_off_at(st.size), finish=False,
                               **kw, **fin)
        elif self.save_every is None:
            final = drive_final(y0w, st, a, horizon, step, segment=segment, **kw, **fin)
            part = _chunk_summaries(final, y0w, st, a, observers)
        else:
            final, ys = drive_saving(y0w, st, a, horizon, step, stiff_after=STIFF_AFTER, **kw)
            part = _chunk_summaries(final, y0w, st, a, observers)
            yw = np.concatenate([np.asarray(y0w)[:, None], ys], axis=1)
            chart = self.chart
            yq = np.array(jax.vmap(lambda y: _to_q_batch(y, chart))(jnp.asarray(yw)), np.float64)
            yq[st != Status.OK] = np.nan
            part["q_traj"], part["p_traj"] = yq[..., :3], yq[..., 3:]
        return part

    def _tail(self, fulls, where, y0w, st, rows, lo):
        """The parts' still-active lanes (a few stiff stragglers each) handed to the run's one pool of stragglers
        (`stragglers`), which steps them with every other chunk's in the background while the next chunks' parts
        run; returns a function that waits for them and gives the chunk's summaries (``ready()``: they are back).
        Neither the gathering nor the pool's batches change a lane's bits, so neither do the number of cores."""
        active = [active_lanes(f, self.horizon, self.step) for f in fulls]
        sel = np.concatenate([w[a] for w, a in zip(where, active)])
        owner = None
        if sel.size:
            lanes = jax.tree_util.tree_map(lambda *xs: np.concatenate(xs, axis=-1),
                                           *[take_lanes_of(f, np.flatnonzero(a)) for f, a in zip(fulls, active)])
            owner = self.stragglers().add(lanes, rows[sel])

        def result():
            done = None if owner is None else self.stragglers().wait(owner)
            return self._tail_summaries(fulls, where, active, done, y0w, st, rows)

        result.ready = lambda: owner is None or owner.event.is_set()
        return result

    def stragglers(self) -> StragglerPool:
        """The run's pool of stragglers (its loop stepping them with `run_stragglers` until every chunk's are
        done), started in the tail thread on first use."""
        with self._pool_lock:
            if self._pool is None:
                self._pool = StragglerPool(self.run_stragglers,
                                           lambda lanes: active_lanes(lanes, self.horizon, self.step))
                self._pool.future = self.tail_pool.submit(self._pool.run)
            return self._pool

    def close_stragglers(self) -> None:
        """No more stragglers will come: the pool's thread ends once its lanes are done."""
        with self._pool_lock:
            if self._pool is not None:
                self._pool.close()

    def run_stragglers(self, lanes, rows):
        """One segment of the pool's ``lanes`` (host, batch-last; their ``rows`` give per-lane parameters) in the
        batches of `tail_ladder`, then the lanes that cannot settle stopped, on the first device
        (`jaxsleigh.integrate.engine.advance_pool`)."""
        with jax.default_device(self.devs[0]), jax.enable_x64(self.cfg.x64):
            return advance_pool(lanes, lambda fill: self._lanes_args(rows[fill]), self.horizon, self.step,
                                eps=self.eps, ladder=tail_ladder(), segment=self.segment, observers=self.observers,
                                certify=self.rules.certify, stiff_after=STIFF_AFTER)

    def _tail_summaries(self, fulls, where, active, done, y0w, st, rows):
        """The chunk's summaries: every part's final state with its finished tail lanes (``done``) put back."""
        out, k = [], 0
        for f, w, a in zip(fulls, where, active):
            if a.any():
                m = int(a.sum())
                f = put_lanes(f, np.flatnonzero(a), take_lanes_of(done, np.arange(k, k + m)))
                k += m
            with jax.enable_x64(self.cfg.x64):
                out.append(_chunk_summaries(finish_state(f, self.horizon), y0w[w], st[w], self._lanes_args(rows[w]),
                                            self.observers))
        return {key: np.concatenate([p[key] for p in out]) for key in out[0]}


def _chunk_result(chunks: _Chunks, store: Optional[ChunkStore], ci, lo, hi, *, fields, sampled) -> tuple:
    """``(result, new)`` for chunk ``ci`` (rows ``lo:hi``): ``result()`` gives its summaries, read back from
    ``store`` when it holds them (``new`` False), else computed (sampled-data loops at once; the engine's parts
    started, their tails maybe still running: ``result.ready()`` says)."""
    pending = None
    if store is not None:
        part = store.load(ci, hi - lo, fields=fields, lo=lo, starts=chunks.ics5[lo:hi])
        if part is not None:
            return (lambda: part), False
        if not sampled:         # its parts ended, its stragglers did not: they go on from there
            pending = store.load_pending(ci, hi - lo, lo=lo, starts=chunks.ics5[lo:hi])
    if sampled:
        part = chunks.sampled_part(lo, hi)
        return (lambda: part), True
    return chunks.engine_part(lo, hi, ci, pending), True


def _run_chunks(chunks: _Chunks, store: Optional[ChunkStore], *, resume, shard, fields, sampled) -> tuple:
    """Every chunk (of this ``shard``) in order: reused from ``store`` when resuming, else computed and written;
    returns the chunks' summaries (none with ``shard``) and the number of chunks reused."""
    n, chunk, ics5 = chunks.n, chunks.chunk, chunks.ics5
    chunks.store = store
    parts, reused = [], 0
    pending: collections.deque = collections.deque()

    def done_chunk(ci, lo, hi, result, new):
        part = {k: v[:hi - lo] for k, v in result().items()}
        if store is not None and new:
            store.save(ci, part, lo=lo, starts=ics5[lo:hi])
            store.drop_pending(ci)
        if shard is None:
            parts.append(part)
        chunks.bar.update(hi / n)

    def ready(entry):
        return getattr(entry[3], "ready", lambda: True)()

    starts = list(range(0, n, chunk))
    try:
        for ci, lo in enumerate(starts):
            hi = min(lo + chunk, n)
            if shard is not None and ci % shard[1] != shard[0]:
                continue
            result, new = _chunk_result(chunks, store if resume else None, ci, lo, hi, fields=fields, sampled=sampled)
            reused += not new
            pending.append((ci, lo, hi, result, new))    # in order, behind any chunk still finishing
            # chunks end in order; their stragglers run in the pool behind the next chunks' parts (at most
            # MAX_PENDING chunks wait for theirs)
            while pending and (len(pending) > MAX_PENDING or ready(pending[0])):
                done_chunk(*pending.popleft())
        chunks.close_stragglers()
    except BaseException:
        # interrupted: a chunk whose stragglers are in the pool still ends and is written (nothing finished is lost)
        chunks.close_stragglers()
        while pending:
            try:
                done_chunk(*pending.popleft())
            except BaseException:
                break
        raise
    while pending:
        done_chunk(*pending.popleft())
    return parts, reused


def _ensemble_result(out: dict, *, ics5, settings, horizon, save_every, lane_args, run_info) -> EnsembleResult:
    """The `EnsembleResult` of the chunks' concatenated summaries ``out``."""
    traj = {}
    if save_every is not None:
        traj = {"t": horizon.t(), "q": out.pop("q_traj"), "p": out.pop("p_traj")}
    if lane_args is not None:
        traj["params"] = lane_table(lane_args.plant, lane_args.gains, ics5.shape[0])
    observed = {k: out[k] for k in out if k not in SUMMARY_FIELDS}
    return EnsembleResult(ics=ics5, settings=settings, **{k: out[k] for k in SUMMARY_FIELDS}, **traj,
                          observed=observed or None, run_info=run_info)


class LaneRules(NamedTuple):
    """What the engine may do with lanes beyond what the options say: the questions of the run's caller.

    Attributes:
      certify: stop the starts that cannot settle before the horizon, status ``NOT_SETTLING``
        (`jaxsleigh.integrate.stragglers`; recorded in the settings): a basin's question, does it settle?
      bitwise: compaction keeps every lane's bits (`jaxsleigh.integrate.engine.min_batch`). ``False`` lets it gather
        the last stragglers below the dtype's floor, at the cost of their last bits: for a run of the same rows in
        the same batch every time (the accuracy audit's reference), where a lone stiff row otherwise steps at a
        batch's cost.
    """

    certify: bool = False
    bitwise: bool = True


def run_ensemble_resolved(ics, *, plant: Optional[PlantParams], gains: Any, controller: Any, t_final: float,
                          dt: float, eps: float, x64: bool, observers: Optional[tuple], stepsize: StepSizeController,
                          saveat: SaveAt, run: RunOptions, rules: LaneRules = LaneRules()) -> Optional[EnsembleResult]:
    """`run_ensemble` (see there) with its three option objects checked (`study_options`).

    The per-trajectory leaves of ``plant`` / ``gains`` (`jaxsleigh.model.lanes`) come back in ``params``;
    ``saveat.summaries=False`` (with ``StepSizeController(method="rk4", check_passivity=False)``, no
    ``saveat.every``) runs plain RK4 for the final state only (``T_eps``, ``min_abs_theta``,
    ``max_excursion`` NaN; status judged at the end). ``run.chunk_size``: trajectories integrated, checkpointed
    and shown by the progress bar at once (default 16384 on CPU, 2^22 per device on an accelerator,
    `jaxsleigh.cores.default_chunk_size`). ``run.shard = (index, count)``: compute only the chunks
    ``i % count == index`` not already in ``run.checkpoint_dir``, write them there and return ``None``
    (the tasks of `jaxsleigh.files.workers`); a later call without it assembles the result.

    ``rules`` (`LaneRules`): a basin stops the starts that cannot settle; the audit's reference gives up bits.

    Returns:
      `EnsembleResult` (``None`` with ``run.shard``).
    """
    reject_traced("run_ensemble", **locals())    # first: a NumPy front, neither jittable nor differentiable
    spec = resolve_audit(run.audit)
    save_every, summaries = saveat
    cfg = solve_config(plant=plant, gains=gains, t_final=t_final, dt=dt, save_every=save_every, x64=x64, eps=eps,
                       stepsize=stepsize, controller=controller)
    chunk_size, shard, segment = _checked_options(stepsize, saveat, run)
    n_rows = int(np.shape(ics)[0]) if np.ndim(ics) == 2 else 1
    check_memory(n_rows, "run_ensemble")
    sampled = is_sampled(cfg.controller)
    if sampled:
        _refuse_for_sampled(save_every=save_every, observers=observers, summaries=not summaries)
    chart = chart_for(cfg.law)
    ics5, status0 = check_ics(ics, cfg.dtype, singular=chart.singular)
    lane_args = _lane_args(cfg, ics5, summaries)
    step = cfg.stepsize
    cores = None if run.cores is None else whole("cores", run.cores, example=2)
    devs = workers(run.devices, cores)
    with jax.enable_x64(cfg.x64):
        dtype = working_dtype()
        settings = _ensemble_settings(cfg, sampled, save_every, chunk_size, summaries, observers)
        if rules.certify:
            settings["stops_unsettled"] = True
        if step.method == "adaptive" and summaries:
            # the flight rule of the implicit step (`jaxsleigh.integrate.engine.flying`)
            settings["stiff_after"], settings["flight_step"] = STIFF_AFTER, flight_step(step.rtol, step.atol, dtype)
        devices_used = [str(d) for d in devs]
        n = ics5.shape[0]
        chunk = int(min(chunk_size, n))
        store = _open_store(run.checkpoint_dir, run.resume, settings, ics5, chunk)
        observers = DEFAULT_OBSERVERS if observers is None else tuple(observers)
        extra = tuple(f for o in observers for f in o.fields if f not in SUMMARY_FIELDS)
        fields = SUMMARY_FIELDS + extra + (("q_traj", "p_traj") if save_every is not None else ())
        t_start = time.perf_counter()
        audit = None if spec is None else _RunAudit(for_law(spec, cfg.controller), n, _float64_rerun(
            ics5, lane_args, cfg, plant=plant, gains=gains, controller=controller, t_final=t_final, dt=dt, eps=eps),
            fixed_step=not cfg.adaptive, flag=unresolved_flag(chart, sampled=sampled, summaries=saveat.summaries))
        # the store's lock on the folder is held until the last chunk is written or read
        with Progress(run.progress, desc=f"ensemble ({n} ics)") as bar, (store or contextlib.nullcontext()), \
                concurrent.futures.ThreadPoolExecutor(len(devs)) as tail_pool:
            chunks = _Chunks(cfg, step=step, observers=observers, saveat=saveat, segment=segment, dtype=dtype,
                             devs=devs, lane_args=lane_args, ics5=ics5, status0=status0, chunk=chunk, bar=bar,
                             tail_pool=tail_pool, rules=rules)
            parts, reused = _run_chunks(chunks, store, resume=run.resume, shard=shard, fields=fields,
                                        sampled=sampled)
        if shard is not None:
            return None
        out = {k: np.concatenate([pt[k] for pt in parts]) for k in parts[0]}
        run_info = {"wall_s": time.perf_counter() - t_start, "devices": devices_used, "chunks_reused": reused}
    result = _ensemble_result(out, ics5=ics5, settings=settings, horizon=cfg.horizon, save_every=save_every,
                              lane_args=lane_args, run_info=run_info)
    result = result._replace(unresolved=unresolved_rows(result, cfg, None if sampled else lane_args,
                                                        sampled=sampled))
    if audit is not None:
        run_info["audit"] = audit.record(result)
    return result


def _float64(tree):
    return jax.tree_util.tree_map(
        lambda a: jnp.asarray(a, jnp.float64) if jnp.issubdtype(jnp.result_type(a), jnp.floating) else a, tree)


@functools.partial(jax.jit, static_argnums=(0,))
def _grown(chart, t, y, args, min_abs_theta, eps):
    return grown_settled_mode(chart, t, chart.to_chart(y), args, min_abs_theta, eps)


def unresolved_rows(result, cfg, lane_args: ClosedLoop | None, *, sampled: bool = False) -> np.ndarray:
    """``result.unresolved``: the rows whose settled oscillation grew (`grown_settled_mode`), judged in float64 at
    their final states. Only rows that reached the horizon within `NEAR` radii of the target, ``|theta(T)|`` above
    `GREW` times their smallest, are evaluated (three forward-mode products of the field each, on a padded batch
    of a power of two rows: one compiled program per size)."""
    n = int(np.shape(result.status)[0])
    flags = np.zeros(n, bool)
    chart = chart_for(cfg.law)
    if sampled or not isinstance(chart, WChart):
        return flags
    q, p = np.asarray(result.q_final, np.float64), np.asarray(result.p_final, np.float64)
    mn = np.asarray(result.min_abs_theta, np.float64)
    with np.errstate(invalid="ignore"):
        cand = ((np.asarray(result.status) == Status.OK) & np.isfinite(mn) & np.all(np.isfinite(q), axis=1)
                & np.all(np.isfinite(p), axis=1) & (np.abs(q[:, 2]) > GREW * mn)
                & (np.sum(q * q, axis=1) <= (NEAR * cfg.eps) ** 2 * 1.01))
    idx = np.flatnonzero(cand)
    if idx.size == 0:
        return flags
    size = max(64, 1 << int(np.ceil(np.log2(idx.size))))
    pad = np.concatenate([idx, np.full(size - idx.size, idx[0])])
    y = np.concatenate([q[pad], p[pad]], axis=1).T
    with jax.enable_x64(True):
        args = ClosedLoop(cfg.plant, cfg.law) if lane_args is None else take_lanes(lane_args, pad)
        got = _grown(chart, jnp.float64(cfg.horizon.t_final), jnp.asarray(y), _float64(args), jnp.asarray(mn[pad]),
                     jnp.float64(cfg.eps))
        flags[idx] = np.asarray(got)[:idx.size]
    return flags


def unresolved_flag(chart, *, sampled: bool, summaries: bool) -> Optional[str]:
    """What ``result.unresolved`` detects for a law integrated in ``chart`` (the audit's ``coverage``), or ``None``
    where it flags no row: a law of the physical chart (no settled pair to test), a sampled law, and the plain
    fixed-step path (no ``min_abs_theta``)."""
    if sampled or not summaries or not isinstance(chart, WChart):
        return None
    return ("rows whose settled (w2, p1) oscillation grew back out near the target, weakly damped or growing "
            "(result.unresolved)")


def _float64_rerun(ics5, lane_args, cfg, *, plant, gains, controller, t_final, dt, eps):
    """``rerun(rows, rtol, atol, max_steps=None)``: the same study of some rows of ``ics5``, in float64 at the
    tolerances given, within ``max_steps`` a row if given (the accuracy audit's reference, `jaxsleigh.studies.audit`).
    Its last stragglers are gathered down to one lane (``LaneRules(bitwise=False)``): the rows and their batch are the
    same in every run of the study, so the reference is too, and a lone stiff row steps at its own cost, not at a
    batch of 32's (half the tuned preset's validation)."""
    def rerun(rows, rtol, atol, max_steps=None):
        law = _rows_law(lane_args, rows, plant=plant, gains=gains, controller=controller)
        budget = min(reference_max_steps(cfg.horizon), max_steps or 2_000_000_000)
        return run_ensemble_resolved(ics5[rows], **law, t_final=t_final, dt=dt, eps=eps, x64=True, observers=None,
                                     stepsize=StepSizeController(rtol=rtol, atol=atol, max_steps=budget),
                                     saveat=SaveAt(), run=RunOptions(progress=False, audit=False),
                                     rules=LaneRules(bitwise=False))
    return rerun


class _RunAudit:
    """The accuracy audit of an ensemble (`jaxsleigh.studies.audit`), once its result is assembled: the rows it
    re-runs are chosen from the result (its unresolved rows first, within a budget set by the run's own steps)."""

    def __init__(self, spec, n: int, rerun, *, fixed_step: bool, flag: Optional[str] = None):
        self.spec, self.n, self.rerun, self.fixed_step, self.flag = spec, n, rerun, fixed_step, flag

    def record(self, result) -> dict:
        return audit_rows(result, self.rerun, self.spec, what="ensemble", fixed_step=self.fixed_step,
                          run_wall_s=(result.run_info or {}).get("wall_s"), flag=self.flag)


@takes_objects
def run_ensemble(ics, *, plant: Optional[PlantParams] = None, gains: Any = None, controller: Any = None,
                 t_final: float = 100.0, dt: float = 0.01, eps: float = 0.05, x64: bool = False,
                 stepsize: Optional[StepSizeController] = None, saveat: Optional[SaveAt] = None,
                 run: Optional[RunOptions] = None,
                 observers: Optional[tuple] = None) -> Optional[EnsembleResult]:
    """Integrate the closed loop from many initial conditions; keep final states and summaries.

    Args:
      ics: ``(N, 3)`` or ``(N, 5)`` initial conditions (see `jaxsleigh.simulate`). Invalid rows (theta = 0
        under the paper's law, non-finite) are flagged in ``status`` and the rest are computed.
      plant, gains: the paper's plant and gains by default; their leaves may vary per trajectory, with a
        trailing axis of size N (or 1) (`jaxsleigh.model.lanes`); the rows' values come back in ``params``.
      controller: any feedback law ``u = law(q, v)`` instead of the paper's (`jaxsleigh.model.controller`),
        integrated in the physical chart; ``Hd0``/``Hd_final`` are then NaN.
      t_final, dt: horizon and base step; eps: radius of the ball ``|q| <= eps`` of ``T_eps``; x64: float64.
      stepsize: `jaxsleigh.StepSizeController` (method, tolerances, policy, step cap and budget, passivity
        monitor; defaults per dtype).
      saveat: `jaxsleigh.SaveAt` (default: final states and summaries; ``every=k``: also the trajectories every
        ``k`` base steps, ``N * T * 5`` numbers; ``summaries=False``: the plain fixed-step path).
      run: `jaxsleigh.RunOptions` (chunks, devices, checkpoint and resume, progress, a process's share; its
        ``audit``: 1% of the rows, at most 64, none below 500 starts, the ``unresolved`` ones first, as many as fit
        10% of the run's time, re-run in float64 at rtol = atol = 1e-10, the worst differences and its cost in
        ``run_info["audit"]`` and an `AccuracyWarning` beyond its thresholds or for unresolved rows,
        `jaxsleigh.studies.audit`; ``RunOptions(audit=False)``: none).
        Every finished chunk is written atomically and carries the fingerprint of its run; a chunk of another
        run stops the run with a `CheckpointError`, a damaged one is recomputed.
      observers: the on-line summaries (`jaxsleigh.integrate.observers`; default `DEFAULT_OBSERVERS`); the
        standard fields that no given observer provides are NaN, other observers' results are in ``observed``.

    Returns:
      `EnsembleResult` (``None`` for one share of a multi-process run).

    Raises:
      TypeError: a keyword of jaxsleigh 0.1 (``rtol=``, ``chunk_size=``, ...), naming the object that holds it now.
      ValueError: an option object of the wrong type or with a bad value.
    """
    stepsize, saveat, run = study_options("run_ensemble", stepsize, saveat, run)
    return run_ensemble_resolved(ics, plant=plant, gains=gains, controller=controller, t_final=t_final, dt=dt,
                                 eps=eps, x64=x64, observers=observers, stepsize=stepsize, saveat=saveat, run=run)
