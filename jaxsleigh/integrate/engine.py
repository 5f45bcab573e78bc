"""Host-side driver of the stepper: input checks, the segment loop, batch compaction.

Two regimes share the stepper of `jaxsleigh.integrate.stepper`: `drive_final` (ensembles: final
state and on-line summaries, host loop over segments with batch compaction) and
`drive_saving` (decimated trajectories on a uniform save grid).
"""
from __future__ import annotations

import functools
import warnings
from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from ..cache import kept_jit
from ..cores import configure
from ..model.closed_loop import ClosedLoop, closed_loop_hamiltonian_w, state_to_w
from ..model.lanes import broadcast_lanes, has_lanes, take_lanes
from ..model.charts import WChart, chart_for
from ..status import Status
from .observers import DEFAULT_OBSERVERS
from .stepsize import StepSizeController
from .horizon import (BUDGET_FACTOR, FLIGHT_STEP, MAX_BASE_STEPS, STIFF_AFTER, Horizon,  # noqa: F401  (re-exported)
                      default_max_steps, flight_step, make_horizon)
from .stragglers import certify
from .pool import Ladder, bucket, padded, put_lanes, take_lanes_of  # (bucket and the last two re-exported)
from .stepper import (Controls, Count, StepState, controls, init_batch, init_batch_lanes, run, run_plain,
                      run_stops)
from ..errors import FlaggedStartsWarning
from ..model.params import paper_gains, paper_plant

__all__ = ["Horizon", "check_ics", "make_horizon", "initial_w", "drive_final", "advance_lanes", "advance_pool",
           "drive_saving", "drive_plain",
           "shard_batch", "batch_mesh", "active_lanes", "bucket", "take_lanes_of", "put_lanes", "finish_state",
           "working_dtype", "default_max_steps", "METHODS"]

METHODS = ("adaptive", "rk4")


def working_dtype():
    """float64 where x64 is enabled (``jax.enable_x64``), else float32 (no computation: an array made
    to ask would be a program of its own)."""
    return np.dtype(jax.dtypes.canonicalize_dtype(np.float64))


_WHY = {
    Status.SINGULAR_START: "theta0 = 0 is on the singular set, where the control law is undefined; "
                           "start with theta0 != 0 (e.g. 1e-3)",
    Status.INVALID_INPUT: "it has a non-finite entry",
    Status.OUT_OF_RANGE: "the start overflows the working precision (its w-chart state, H_d, vector field or "
                         "|u|^2); use float64 (x64=True, --x64)",
}


def _rows(idx: np.ndarray, limit: int = 5) -> str:
    shown = ", ".join(str(int(i)) for i in idx[:limit])
    return f"row{'s' if idx.size > 1 else ''} {shown}" + (f" and {idx.size - limit} more" if idx.size > limit else "")


#: Starts with |theta0| >= this and |x|, |y|, |p1|, |p2| <= `_PLAIN_REACH` are representable in float32 with a wide
#: margin (w ~ |z| / theta0^2 <= 2e6; tests/test_reliability.py checks the corners): `_representable` needs no
#: compiled check for them, which saves a float64 program's tracing in every process that runs ordinary starts.
_PLAIN_THETA, _PLAIN_REACH = 1e-2, 1e2


def _representable(ics5: np.ndarray, dtype, block: int = 1 << 16) -> np.ndarray:
    """Rows whose w-chart state, vector field and H_d are finite (with room) in ``dtype``: computed
    in float64 in blocks (memory bounded by the block), compared with the dtype's range. Rows in the plain region
    (`_PLAIN_THETA`, `_PLAIN_REACH`) are representable without the computation."""
    ok = (np.abs(ics5[:, 2]) >= _PLAIN_THETA) & np.all(np.abs(ics5[:, [0, 1, 3, 4]]) <= _PLAIN_REACH, axis=1)
    rest = np.flatnonzero(~ok)
    if rest.size == 0:
        return ok
    ics5 = ics5[rest]
    for lo in range(0, ics5.shape[0], block):
        ok[rest[lo:lo + block]] = ~np.any(_start_sizes(ics5[lo:lo + block], dtype), axis=0)
    return ok


#: what `_representable` checks at a start, in order: its w-chart state, H_d and vector field must stay below
#: 1e-4 of the dtype's largest number; the effort integrand |u|^2 (the observers' quadrature rows) below 1/16 of it
_SIZES = ("w-chart state", "shaped energy H_d", "vector field", "effort integrand |u|^2")


def _start_sizes(ics5: np.ndarray, dtype) -> np.ndarray:
    """(4, N) booleans, one row per quantity of `_SIZES`: whether it overflows ``dtype`` at each start (computed in
    float64)."""
    top = float(np.finfo(np.dtype(dtype)).max)
    big = top * 1e-4
    with jax.enable_x64(True):
        yw, hd, fw, u2 = (np.asarray(a) for a in _w_check(jnp.asarray(ics5, jnp.float64),
                                                          ClosedLoop(paper_plant(), paper_gains())))
    return np.stack([~np.all(np.abs(yw) < big, axis=1), ~(np.abs(hd) < big), ~np.all(np.abs(fw) < big, axis=1),
                     ~(u2 < top / 16)])


def _out_of_range_why(row: np.ndarray, dtype) -> str:
    """Why the start ``row`` (5,) is ``OUT_OF_RANGE`` in ``dtype``: which quantity of `_SIZES` overflows, and the
    start's cause: |theta0| so small (w ~ 1/theta0^2), or |x|, |y|, |p| so large (H_d grows as their square)."""
    over = _start_sizes(np.asarray(row, np.float64)[None], dtype)[:, 0]
    names = [n for n, o in zip(_SIZES, over) if o] or ["state"]
    what = names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]
    big = [f"|{n}| = {abs(v):.3g}" for n, v in zip(("x", "y", "p1", "p2"), row[[0, 1, 3, 4]]) if abs(v) > _PLAIN_REACH]
    causes, remedies = [], []
    if abs(row[2]) < _PLAIN_THETA:
        causes.append(f"|theta0| = {abs(row[2]):.3g} is so close to theta = 0 (w ~ 1/theta0^2)")
        remedies.append("a larger |theta0|")
    if big or not causes:
        causes.append(f"{', '.join(big) or 'the start'} {'is' if len(big) < 2 else 'are'} so large (H_d grows as "
                      f"the square of the distance to the origin)")
        remedies.append("a start nearer the origin")
    return (f"its {what} overflow{'s' if len(names) == 1 else ''} {np.dtype(dtype).name} because "
            f"{' and '.join(causes)}; use float64 (x64=True, --x64) or {' or '.join(remedies)}")


@kept_jit()
def _w_check(ics, args):
    def one(y):
        yw = state_to_w(y)
        f, u = WChart().field_and_control(0.0, yw, args)
        return yw, closed_loop_hamiltonian_w(yw, args), f, u[0] * u[0] + u[1] * u[1]

    return jax.vmap(one)(ics)


def check_ics(ics, dtype=None, *, name: str = "initial condition", singular: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Validate initial conditions; returns ``(ics (N, 5) float64, status0 (N,) int32)``.

    ``ics`` is ``(3,)``/``(5,)`` for one start or ``(N, 3)``/``(N, 5)`` for many: ``(x, y, theta)``
    with zero momentum, or ``(x, y, theta, p1, p2)``. Rows on the singular set ``theta = 0``
    (status ``SINGULAR_START``), with non-finite entries (``INVALID_INPUT``) or, with ``dtype``
    given, so close to it that they overflow that precision (``OUT_OF_RANGE``) are flagged, not
    integrated, and named in one `FlaggedStartsWarning`; the other rows
    are computed. ``singular=False`` (a law without the singular set, integrated in the physical
    chart) flags non-finite rows only. A single start that is bad, or a batch whose every row is, raises ``ValueError``
    with a message that says what to change.

    Every run checks its starts here first: it is where a run begins, so here jaxsleigh asks JAX for one CPU
    device per core if JAX has not started yet (`jaxsleigh.cores.configure`).
    """
    configure()
    arr = _ics_rows(ics, name)
    status = _start_status(arr, dtype, singular)
    bad = np.flatnonzero(status)
    if bad.size:
        warnings.warn(FlaggedStartsWarning(_flagged_message(arr, status, bad, name, dtype), rows=bad,
                                           status=status[bad]),
                      stacklevel=3)
    return arr, status


def _ics_rows(ics, name: str) -> np.ndarray:
    """``ics`` as ``(N, 5)`` float64 rows (zero momentum appended to ``(x, y, theta)``), or a ``ValueError``."""
    try:
        raw = np.asarray(ics)
    except (TypeError, ValueError):
        raise ValueError(f"{name}s must be an array of numbers, got {type(ics).__name__}") from None
    if raw.dtype == bool or np.iscomplexobj(raw) or not np.issubdtype(raw.dtype, np.number):
        raise ValueError(f"{name}s must be real numbers (x, y, theta[, p1, p2]), got an array of "
                         f"dtype {raw.dtype}")
    arr = raw.astype(np.float64)
    if arr.ndim == 1:
        arr = arr[None]
    if arr.ndim != 2 or arr.shape[1] not in (3, 5) or arr.shape[0] == 0:
        raise ValueError(f"{name}s must have shape (3,), (5,), (N, 3) or (N, 5) "
                         f"[(x, y, theta) or (x, y, theta, p1, p2)], got {np.shape(ics)}")
    if arr.shape[1] == 3:
        arr = np.concatenate([arr, np.zeros((arr.shape[0], 2))], axis=1)
    return arr


def _start_status(arr: np.ndarray, dtype, singular: bool) -> np.ndarray:
    """Each row's starting status: ``INVALID_INPUT``, ``SINGULAR_START``, ``OUT_OF_RANGE`` or ``OK``."""
    status = np.zeros(arr.shape[0], np.int32)
    finite = np.all(np.isfinite(arr), axis=1)
    status[~finite] = Status.INVALID_INPUT
    if singular:
        status[finite & (arr[:, 2] == 0.0)] = Status.SINGULAR_START
    if dtype is not None and singular:
        cand = np.flatnonzero(status == Status.OK)
        rep = _representable(arr[cand], dtype)
        status[cand[~rep]] = Status.OUT_OF_RANGE
    return status


def _flagged_message(arr: np.ndarray, status: np.ndarray, bad: np.ndarray, name: str, dtype=None) -> str:
    """The warning text naming the flagged rows ``bad`` by status (an ``OUT_OF_RANGE`` row by what overflows
    ``dtype`` and why, `_out_of_range_why`); a ``ValueError`` if no row is left."""
    def why(row: int) -> str:
        code = Status(int(status[row]))
        if code == Status.OUT_OF_RANGE and dtype is not None:
            return _out_of_range_why(arr[row], dtype)
        return _WHY[code]

    first = int(bad[0])
    msg = f"{name} {first} {arr[first].tolist()} is invalid: {why(first)}"
    if bad.size == arr.shape[0]:
        if arr.shape[0] == 1:
            raise ValueError(msg)
        raise ValueError(f"all {arr.shape[0]} {name}s are invalid; first: {msg}")
    parts = []
    for code in np.unique(status[bad]):
        idx = np.flatnonzero(status == code)
        parts.append(f"{_rows(idx)} (status {int(code)} {Status(int(code)).name.lower()}: "
                     f"{'' if idx.size == 1 else f'row {int(idx[0])}: '}{why(int(idx[0]))})")
    return (f"{bad.size} of {arr.shape[0]} {name}s flagged and not integrated (outputs NaN, the rest are "
            f"computed): " + "; ".join(parts))


#: the starts' chart change, compiled (op by op it was ~10 programs per process, each a cache load)
@kept_jit()
def _to_w_batch(ics):
    return jax.vmap(state_to_w)(ics)


def initial_w(ics5: np.ndarray, status0: np.ndarray, dtype, chart=None) -> jax.Array:
    """Map validated physical starts to the w chart (or to ``chart``, `jaxsleigh.model.charts`), in float64
    then cast to ``dtype``. Rows whose ``status0`` is not OK get a harmless placeholder (they are never
    stepped)."""
    safe = np.where(status0[:, None] == 0, ics5, np.array([1.0, 0.0, 1.0, 0.0, 0.0]))
    if chart is not None and not chart.singular:
        return jnp.asarray(chart.to_chart(safe), dtype)
    with jax.enable_x64(True):
        yw = np.asarray(_to_w_batch(np.asarray(safe, np.float64)))
    if np.any(~np.isfinite(yw[status0 == 0])):
        raise ValueError("an initial condition overflows the w chart (|theta0| too small for this "
                         "precision); check the starts with check_ics(ics, dtype) first, or use |theta0| >= 1e-150")
    return jax.device_put(np.asarray(yw, np.dtype(dtype)))   # cast on the host, copied: no program for it


@kept_jit(static_argnames=("observers",))
def _init_batch(y0w, status0, args, ctl, observers=DEFAULT_OBSERVERS):
    return init_batch(y0w, status0, args, ctl, observers=observers)


def _active(s, target, ctl) -> np.ndarray:
    """Which lanes still step (`is_active`), on the host: four small reads instead of a compiled program per
    batch size (the host asks once per segment)."""
    return ((np.asarray(s.status) == Status.OK) & (np.asarray(s.t) < target)
            & (np.asarray(s.n_accept) + np.asarray(s.n_reject) < ctl.max_steps))


def _put(a):
    """A host array on the default device, copied, without a program: `jnp.asarray` of a NumPy array compiles one
    (``lax.stage``) per shape and dtype, five per batch size of a state."""
    return jax.device_put(a) if isinstance(a, (np.ndarray, np.generic)) else jnp.asarray(a)


#: ``n_attempts`` is traced: one program serves every segment length (a short horizon's, a tail's)
@kept_jit(static_argnames=("adaptive", "monitor", "observers", "implicit"), donate_argnums=(0,))
def _segment_batch(state, target, args, ctl, n_attempts, adaptive, monitor=True, observers=DEFAULT_OBSERVERS,
                   implicit=False):
    return run(state, target, args, ctl, Count(n_attempts), adaptive=adaptive, monitor=monitor, observers=observers,
               implicit=implicit)


def flying(state, ctl: Controls, stiff_after: int) -> np.ndarray:
    """The lanes of a batch-last ``state`` that take the linearly implicit step from its next segment on (`_segment`):
    those that already do, and those still OK that have made ``stiff_after`` attempts (0: never) or more at a mean
    step below `flight_step` base steps ``ctl.dt`` (``t < flight_step dt n`` after ``n`` attempts). Read on the
    host."""
    was = np.asarray(state.stiff)
    if not stiff_after:
        return was
    n = np.asarray(state.n_accept) + np.asarray(state.n_reject)
    ok = np.asarray(state.status) == Status.OK
    flight = flight_step(ctl.rtol, ctl.atol, np.asarray(ctl.rtol).dtype)
    return was | (ok & (n >= stiff_after) & (np.asarray(state.t, np.float64) < flight * float(ctl.dt) * n))



def _segment(state, target, args, ctl, segment: int, adaptive: bool, monitor: bool, observers, stiff_after: int):
    """One segment of ``segment`` attempts of a batch; with ``stiff_after`` (adaptive; 0: never) the lanes that fly
    (`flying`) take the linearly implicit step, the others the explicit one (`_by_kind`)."""
    def step(st, implicit):
        return _segment_batch(st, target, args, ctl, np.int32(segment), adaptive, monitor, observers, implicit), None

    if not (adaptive and stiff_after):
        return step(state, False)[0]
    return _by_kind(state, flying(state, ctl, stiff_after), step, _put)[0]


def _by_kind(state, flies, step, put, merge=None):
    """``step(state, implicit) -> (state, out)`` with the lanes ``flies`` (remembered from then on in ``state.stiff``)
    on the implicit step and the others on the explicit one. A batch that holds both kinds is stepped twice, each
    time with the other kind's lanes held (status set aside, so they idle), and each lane by its own kind's program:
    its bits never depend on whether its neighbours are of the other kind. ``merge(out_explicit, out_implicit)``
    combines the two passes' ``out``."""
    if not np.array_equal(flies, np.asarray(state.stiff)):
        state = state._replace(stiff=put(flies))
    status = np.asarray(state.status)
    ok = status == Status.OK
    old = ok & flies
    if not old.any() or old.sum() == ok.sum():
        return step(state, bool(old.any()))
    young = ok & ~old

    def held(st, status):
        return st._replace(status=put(np.asarray(status, np.int32)))

    first, out1 = step(held(state, np.where(old, Status.INVALID_INPUT, status)), False)
    s1 = np.asarray(first.status)
    second, out2 = step(held(first, np.where(young, Status.INVALID_INPUT, np.where(old, Status.OK, s1))), True)
    return held(second, np.where(young, s1, np.asarray(second.status))), merge and merge(out1, out2)


@kept_jit(static_argnames=("adaptive", "monitor", "observers", "implicit"), donate_argnums=(0,))
def _saving_batch(state, save_times, args, ctl, adaptive, monitor=True, observers=DEFAULT_OBSERVERS, implicit=False):
    return run_stops(state, save_times, args, ctl, adaptive=adaptive, monitor=monitor, observers=observers,
                      implicit=implicit)


def shard_batch(tree, mesh):
    """Place every leaf of a batch-last pytree with its last axis split over ``mesh``'s devices."""
    def put(a):
        return jax.device_put(a, NamedSharding(mesh, PartitionSpec(*([None] * (np.ndim(a) - 1)), "batch")))

    return jax.tree_util.tree_map(put, tree)


def batch_mesh(devices=None):
    """A 1-D mesh named ``"batch"`` over ``devices`` (default: all of this process's devices, so a
    process of a multi-process run shards over its own), or ``None`` for one device."""
    devices = jax.local_devices() if devices is None else list(devices)
    return Mesh(np.array(devices), ("batch",)) if len(devices) > 1 else None



#: the smallest batch compaction gathers the active lanes into (a power of two), per dtype. A few stiff
#: stragglers (starts near theta = 0) can take 100x the median's steps, and small batches make them cheaper. In float64 a batch of
#: 32 or more lanes steps every lane bitwise as the uncompacted batch (tests/test_engine.py), 16 does not;
#: in float32 no size did (XLA compiles small batches with other rounding), so float32 takes the fastest.
MIN_BATCH = {"float32": 8, "float64": 32}

#: the smallest compacted batch on an accelerator. There a loop iteration costs about the same for 8,192 lanes as
#: for 128 (one H200: 0.26-0.29 s per segment of 1,000 attempts at 8,192, 0.26 s at 128), while each new batch
#: shape compiles its programs again (4.5 s for the explicit step, 6-8 s for the implicit one): smaller batches
#: only add compilations (`experiments/performance/basin_segments.py`).
ACCELERATOR_MIN_BATCH = 1 << 13


def min_batch(dtype, backend: Optional[str] = None, *, bitwise: bool = True) -> int:
    """The smallest batch `drive_final` compacts to: `MIN_BATCH` of ``dtype`` on CPU, `ACCELERATOR_MIN_BATCH`
    on any other ``backend`` (default JAX's). Without ``bitwise``, 1 on CPU: compaction then changes the last bits
    of the lanes it gathers, which only a run whose batches are always the same rows may accept (the accuracy audit's
    reference, whose last straggler then steps alone instead of in a batch of 32)."""
    cpu = (backend or jax.default_backend()) == "cpu"
    if not bitwise and cpu:
        return 1
    small = MIN_BATCH.get(np.dtype(dtype).name, 32)
    return small if cpu else max(small, ACCELERATOR_MIN_BATCH)


def _finish(full: StepState, t_final: float) -> StepState:
    """Mark trajectories that stopped short of the horizon while still OK (out of budget)."""
    status = np.array(full.status)
    status[(status == Status.OK) & (np.asarray(full.t) < t_final)] = Status.BUDGET_EXHAUSTED
    return full._replace(status=status)


def drive_final(y0w, status0, args: ClosedLoop, horizon: Horizon, step: StepSizeController, *, eps: float,
                segment: int = 1000, compact: bool = True, progress=None,
                observers=DEFAULT_OBSERVERS, state: Optional[StepState] = None, stop_at: int = 0,
                finish: bool = True, certify: bool = False, stiff_after: int = 0, bitwise: bool = True) -> StepState:
    """Run a batch to the horizon keeping only the final state and the on-line summaries
    (``observers``, `jaxsleigh.integrate.observers`), taking steps as ``step`` says (a resolved
    `StepSizeController`: every number set, e.g. `jaxsleigh.studies.config.SolveConfig.stepsize`);
    ``eps`` is the radius of the ball of ``T_eps``.

    The jitted kernel runs ``segment`` attempted steps; between segments the host checks which
    trajectories are still active and, when at most a quarter are, gathers them into a smaller
    batch (a power of two, >= `min_batch`, so few shapes compile: the `jaxsleigh.integrate.pool.Ladder` with that
    floor): the cost then follows the sum over trajectories of the steps each needs, not the batch's maximum.

    With ``certify``, between segments the adaptive engine stops the lanes that cannot settle before the horizon
    (`jaxsleigh.integrate.stragglers`: far from the target with too little H_d left; status ``NOT_SETTLING``):
    what a basin asks (does it settle?), not what an ensemble's final states need.

    ``stiff_after`` (adaptive only; 0: never, the ensembles use `STIFF_AFTER`): a lane still in a stiff flight
    after that many attempts takes the linearly implicit step of `jaxsleigh.integrate.rosenbrock` (`_segment`).

    ``bitwise=False`` lets compaction go below `MIN_BATCH` (`min_batch`): cheaper for a lone straggler, at the cost
    of the gathered lanes' last bits.

    Returns the final `StepState` as batch-last NumPy arrays, with
    trajectories that ran out of budget marked ``BUDGET_EXHAUSTED``. ``progress`` has
    ``update(fraction_done)``. (Several devices: the plain fixed-step `drive_plain` takes a mesh; this adaptive
    driver runs on one.)

    ``args`` may carry per-trajectory leaves (a trailing axis of size N or 1, see
    `jaxsleigh.model.lanes`); they are broadcast to N lanes and gathered with the state on compaction.

    **Tails.** ``stop_at`` returns as soon as at most that many lanes are still active, and
    ``finish=False`` returns the state as it is (still-active lanes not marked); ``state`` (a batch-last host
    `StepState`, ``y0w`` and ``status0`` then ``None``) continues from there. Together they let several
    batches hand their few stiff stragglers to one batch (`active_lanes`, `take_lanes_of`), which costs a
    fraction of each batch finishing its own in batches of `MIN_BATCH` lanes.
    """
    dtype = y0w.dtype if state is None else state.y.dtype
    n = y0w.shape[0] if state is None else state.t.shape[-1]
    ladder = Ladder(floor=min_batch(dtype, bitwise=bitwise))
    # a short horizon needs no more attempts than its base steps (+ rounding slack) per segment
    segment = max(1, min(segment, horizon.n_steps + 8))
    ctl = controls(step, dtype, dt=horizon.dt, eps=eps, xp=np)
    adaptive, monitor, max_steps = step.method == "adaptive", step.check_passivity, step.max_steps
    target = np.asarray(horizon.t_final, np.dtype(dtype))
    b = _first_batch(y0w, status0, state, args, ctl, observers, n, dtype)
    for _ in range(-(-max_steps // segment) + 1):
        if adaptive and certify:
            b = _certified(b, horizon, eps)
        act = np.asarray(_active(b.state, target, ctl))
        if progress is not None:
            frac = np.where(act, np.asarray(b.state.t, np.float64) / horizon.t_final, 1.0)
            progress.update((n - b.idx.size + frac.sum()) / n)
        if not act.any() or act.sum() <= stop_at:
            break
        if compact and ladder.shrinks(b.idx.size, int(act.sum())):
            b = _compacted(b, act, ladder, dtype)
        b = b._replace(state=_segment(b.state, target, b.args, ctl, segment, adaptive, monitor, observers,
                                      stiff_after))
    full = _merged(b.full, b.idx, jax.tree_util.tree_map(np.asarray, b.state))
    return _finish(full, horizon.t_final) if finish else full


def advance_lanes(state: StepState, args: ClosedLoop, horizon: Horizon, step: StepSizeController, *, eps: float,
                  segment: int = 1000, observers=DEFAULT_OBSERVERS, certify: bool = False,
                  stiff_after: int = 0) -> StepState:
    """One segment of a batch-last host ``state`` (as `drive_final` steps it: ``segment`` attempts, then, with
    ``certify``, the lanes that cannot settle stopped), returned on the host, not finished. `drive_final(stop_at=...)` followed by calls of this
    steps every lane exactly as `drive_final` alone would, at the same segment boundaries: what a pool of stragglers
    gathered from many batches runs (`jaxsleigh.studies.ensemble`). Per-lane ``args`` are given for the batch's
    lanes."""
    dtype = state.y.dtype
    segment = max(1, min(segment, horizon.n_steps + 8))
    ctl = controls(step, dtype, dt=horizon.dt, eps=eps, xp=np)
    if has_lanes(args.plant, args.gains):
        args = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), args)
    target = np.asarray(horizon.t_final, np.dtype(dtype))
    dev = jax.tree_util.tree_map(_put, state)
    dev = _segment(dev, target, args, ctl, segment, step.method == "adaptive", step.check_passivity, observers,
                   stiff_after)
    b = _Batch(dev, args, None, np.arange(state.t.shape[-1]), None)
    if certify and step.method == "adaptive":
        b = _certified(b, horizon, eps)
    return jax.tree_util.tree_map(np.asarray, b.state)


def advance_pool(lanes: StepState, args_of, horizon: Horizon, step: StepSizeController, *, eps: float,
                 ladder: Ladder, segment: int = 1000, observers=DEFAULT_OBSERVERS, certify: bool = False,
                 stiff_after: int = 0) -> StepState:
    """One segment (`advance_lanes`) of every lane of a pool's batch-last host ``lanes``, in batches of the
    ``ladder``'s sizes (at most its ceiling each, padded with idle copies of a lane); ``args_of(rows)`` gives the
    closed loop's ``args`` for the lanes ``rows`` of ``lanes``. The lanes on the implicit step (`flying`) run in
    batches of their own: a batch that held both kinds would run both programs over all its lanes. What the loop of
    a `jaxsleigh.integrate.pool.StragglerPool` calls once per segment."""
    flies = flying(lanes, controls(step, lanes.y.dtype, dt=horizon.dt, eps=eps, xp=np), stiff_after)
    kinds = [np.flatnonzero(~flies), np.flatnonzero(flies)]
    out = []
    for idx in (group for kind in kinds for group in ladder.groups(kind)):
        m = idx.size
        fill = padded(idx, ladder.size(m))
        batch = take_lanes_of(lanes, fill)
        idle = np.where(np.arange(fill.size) < m, batch.status, Status.INVALID_INPUT)
        batch = batch._replace(status=idle.astype(batch.status.dtype))
        done = advance_lanes(batch, args_of(fill), horizon, step, eps=eps, segment=segment, observers=observers,
                             certify=certify, stiff_after=stiff_after)
        out.append(take_lanes_of(done, np.arange(m)))
    joined = jax.tree_util.tree_map(lambda *xs: np.concatenate(xs, axis=-1), *out)
    return take_lanes_of(joined, np.argsort(np.concatenate(kinds)))


def _certified(b: "_Batch", horizon: Horizon, eps: float) -> "_Batch":
    """``b`` with its lanes that cannot settle before the horizon stopped (status ``NOT_SETTLING``,
    `jaxsleigh.integrate.stragglers`); checked between segments, at the same attempt counts in every batch."""
    st = b.state
    status = certify(np.asarray(st.status), np.asarray(st.t), np.asarray(st.y), np.asarray(st.Hd), args=b.args,
                     t_final=horizon.t_final, eps=eps)
    if status is None:
        return b
    return b._replace(state=st._replace(status=_put(status)))


class _Batch(NamedTuple):
    """The batch `drive_final` steps: its ``state`` and ``args``, ``lane_host`` (the per-lane parameters on the
    host, None without), ``idx`` (the rows of the full batch it holds, -1 for padding) and ``full`` (the full
    batch as lanes are compacted away; None until the first compaction)."""
    state: StepState
    args: ClosedLoop
    lane_host: Optional[ClosedLoop]
    idx: np.ndarray
    full: Optional[StepState]


def _first_batch(y0w, status0, state, args: ClosedLoop, ctl, observers, n: int, dtype) -> _Batch:
    """The whole batch of `drive_final`, from ``y0w`` and ``status0`` or a host ``state`` to continue."""
    lane_host, args, first = _started(y0w, status0, state is None, args, ctl, observers, n, dtype)
    state = first if state is None else jax.tree_util.tree_map(_put, state)
    return _Batch(state, args, lane_host, np.arange(n), None)


def _started(y0w, status0, start: bool, args: ClosedLoop, ctl, observers, n: int, dtype):
    """``(lane_host, args, state)`` of a batch of ``n`` lanes: with per-lane parameters (`jaxsleigh.model.lanes`)
    ``lane_host`` holds them on the host, one lane per trajectory, and ``args`` on the device (else ``None`` and
    ``args`` as given); ``state`` is the stepper's first state from ``y0w`` and ``status0`` if ``start``, else
    ``None``."""
    lane_host = None
    if has_lanes(args.plant, args.gains):    # per-lane parameters: one lane per trajectory of the batch
        lane_host = ClosedLoop(*broadcast_lanes(args.plant, args.gains, n))
        args = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), lane_host)
    if not start:
        return lane_host, args, None
    init = _init_batch if lane_host is None else init_batch_lanes
    return lane_host, args, init(y0w, np.asarray(status0, np.int32), args, ctl, observers)


def _merged(full, idx: np.ndarray, host: StepState) -> StepState:
    """The full batch with the rows ``idx`` of the host batch ``host`` written back (``host`` itself before the
    first compaction, ``full`` None)."""
    return host if full is None else put_lanes(full, idx, host)


def _compacted(b: _Batch, act: np.ndarray, ladder: Ladder, dtype) -> _Batch:
    """``b``'s active lanes (``act``) gathered into a smaller batch of the ``ladder``'s size, padded with copies of
    one active lane; the rows left behind go to ``full``."""
    keep = np.flatnonzero(act)
    size = ladder.size(keep.size)
    host = jax.tree_util.tree_map(np.asarray, b.state)
    full = _merged(b.full, b.idx, host)
    pad = padded(keep, size)                 # only real lanes are written back
    state = jax.tree_util.tree_map(lambda a: _put(a[..., pad]), host)
    args, lane_host = b.args, b.lane_host
    if lane_host is not None:                # the parameters follow their trajectories
        lane_host = take_lanes(lane_host, pad)
        args = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), lane_host)
    idx = np.concatenate([b.idx[keep], np.full(size - keep.size, -1)])
    return _Batch(state, args, lane_host, idx, full)


def active_lanes(full: StepState, horizon: Horizon, step: StepSizeController) -> np.ndarray:
    """The lanes of a host state (from ``drive_final(finish=False)``) that would still step: OK, short of
    the horizon, within budget (`is_active`, on the host)."""
    t_final = np.asarray(horizon.t_final, np.asarray(full.t).dtype)
    return ((np.asarray(full.status) == Status.OK) & (np.asarray(full.t) < t_final)
            & (np.asarray(full.n_accept) + np.asarray(full.n_reject) < step.max_steps))


def finish_state(full: StepState, horizon: Horizon) -> StepState:
    """Mark the lanes of a host state that stopped short of the horizon while OK (out of budget)."""
    return _finish(full, horizon.t_final)


def drive_saving(y0w, status0, args: ClosedLoop, horizon: Horizon, step: StepSizeController, *, eps: float,
                 block: int = 100, progress=None, observers=DEFAULT_OBSERVERS, stiff_after: int = 0,
                 segment: int = 1000):
    """Run a batch through the horizon's save grid (steps as in `drive_final`); returns ``(final_state, ys)`` with ``ys`` of
    shape (N, n_out, 5) in the w chart (NaN where a trajectory never got). The host loops over
    blocks of ``block`` save times (for the progress bar). ``args`` may carry per-trajectory
    leaves, as in `drive_final`.

    ``stiff_after`` (adaptive only; 0: never): as in `drive_final`, a lane still in a stiff flight after that many
    attempts takes the linearly implicit step (`flying`). A lane that has not flown is stopped for the check at
    ``stiff_after`` attempts and then every ``segment`` (a per-lane budget, `_saving_block`), at the attempt counts
    where `drive_final` checks it, and goes on from where it stopped: bit for bit as without the checks."""
    dtype = y0w.dtype
    ctl = controls(step, dtype, dt=horizon.dt, eps=eps, xp=np)
    adaptive, monitor = step.method == "adaptive", step.check_passivity
    _, args, state = _started(y0w, status0, True, args, ctl, observers, y0w.shape[0], dtype)
    save_times = horizon.save_times()
    out = []
    for i in range(0, save_times.size, block):
        times = save_times[i:i + block]
        # every block has ``block`` times (one program for any horizon): a short one repeats its last time, at
        # which every lane already is or has stopped, so the padding takes no step and its rows are dropped
        padded = np.asarray(np.concatenate([times, np.repeat(times[-1:], block - times.size)]), np.dtype(dtype))
        if adaptive and stiff_after:
            state, ys = _saving_block(state, padded, args, ctl, monitor, observers, stiff_after, segment)
        else:
            state, ys = _saving_batch(state, padded, args, ctl, adaptive, monitor, observers)
        out.append(np.asarray(ys)[:times.size])
        if progress is not None:
            progress.update(min(i + block, save_times.size) / save_times.size)
    ys = np.moveaxis(np.concatenate(out, axis=0), -1, 0)     # (K, 5, N) blocks -> (N, K, 5)
    return _finish(jax.tree_util.tree_map(np.asarray, state), horizon.t_final), ys


def _saving_block(state, times, args, ctl, monitor: bool, observers, stiff_after: int, segment: int):
    """`drive_saving`'s block of save ``times`` with the switch to the implicit step: each lane that has not flown
    runs to its next check (``stiff_after`` attempts, then every ``segment``; the budget ``ctl.max_steps`` per
    lane), and the block is run again from there until no lane stops at a check before its end. A lane that stopped
    goes on from its state, as a segment of `drive_final` does; its rows are the first pass's that reached them."""
    budget = int(ctl.max_steps)
    ys = None
    while True:
        flies = flying(state, ctl, stiff_after)
        n = np.asarray(state.n_accept) + np.asarray(state.n_reject)
        check = np.where(n < stiff_after, stiff_after, (n // segment + 1) * segment)
        cap = np.where(flies, budget, np.minimum(check, budget)).astype(np.int32)
        per_lane = ctl._replace(max_steps=cap)

        def step(st, implicit):
            st, y = _saving_batch(st, times, args, per_lane, True, monitor, observers, implicit)
            return st, np.asarray(y)

        state, y = _by_kind(state, flies, step, _put, _first_reached)
        ys = y if ys is None else _first_reached(ys, y)
        n = np.asarray(state.n_accept) + np.asarray(state.n_reject)
        stopped = (np.asarray(state.status) == Status.OK) & (np.asarray(state.t) < times[-1]) & (n >= cap) \
            & (cap < budget)
        if not stopped.any():
            return state, ys


def _first_reached(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rows of saved states: ``a``'s, and ``b``'s where ``a`` has none (NaN: the lane had not reached that time)."""
    return np.where(np.isnan(a), b, a)


# the plain fixed-step path: cache blocks of PLAIN_BLOCK trajectories, optionally over several devices
from .stepper import PLAIN_BLOCK  # noqa: E402  (kept next to its users)
from . import gpu_plain  # noqa: E402


@functools.partial(jax.jit, static_argnames=("n_steps", "block"), donate_argnums=(0,))
def _plain_batch(y, args, dt, n_steps, block=PLAIN_BLOCK):
    return run_plain(y, args, dt, n_steps=n_steps, block=block)


@functools.lru_cache(maxsize=4)
def _plain_batch_wide(vector_width: int):
    """`_plain_batch` compiled with XLA:CPU's ``xla_cpu_prefer_vector_width`` (default 256)."""
    return jax.jit(_plain_batch.__wrapped__, static_argnames=("n_steps", "block"), donate_argnums=(0,),
                   compiler_options={"xla_cpu_prefer_vector_width": int(vector_width)})


def _args_key(args: ClosedLoop):
    """A hashable copy of concrete ``args`` (tree structure + every leaf's shape and values)."""
    leaves, tree = jax.tree_util.tree_flatten(args)
    return tree, tuple((np.shape(x), tuple(np.asarray(x, np.float64).ravel().tolist())) for x in leaves)


#: XLA:CPU options of the specialised plain kernel (`_plain_specialised`): XLA's thread pool off (the cache
#: blocks run on one core anyway), 512-bit vectors where the CPU has them, and LLVM allowed to contract
#: ``a * b + c`` into one fused multiply-add and to reassociate (``xla_cpu_enable_fast_math``), as gcc does for
#: the C reference. NaN and inf keep their meaning, divisions stay IEEE and the library functions exact (the
#: four ``honor`` options), so a start that blows up still ends NONFINITE. Measured: 0.52 -> 0.59 of the C
#: limit in wall time (docs/performance_fastpath.md); final states move by float32 rounding.
PLAIN_CPU_OPTIONS = {
    "xla_cpu_multi_thread_eigen": False,
    "xla_cpu_prefer_vector_width": 512,
    "xla_cpu_enable_fast_math": True,
    "xla_cpu_fast_math_honor_nans": True,
    "xla_cpu_fast_math_honor_infs": True,
    "xla_cpu_fast_math_honor_division": True,
    "xla_cpu_fast_math_honor_functions": True,
}


@functools.lru_cache(maxsize=16)
def _plain_specialised(key, n_steps: int, block, dtype):
    """`_plain_batch` compiled for one plant and one set of gains: their values are constants of the
    program, so XLA folds the per-run arithmetic (masses, their reciprocals, gain products) out of
    the step, as a C program compiled for them would; and it is built with `PLAIN_CPU_OPTIONS`.
    Final states agree with `_plain_batch` to float32 rounding.
    Compiled once per (plant, gains, steps), kept for the 16 most recent."""
    tree, leaves = key
    args = jax.tree_util.tree_unflatten(tree, [np.asarray(v, dtype).reshape(shape) for shape, v in leaves])

    def kernel(y, dt):
        return run_plain(y, args, dt, n_steps=n_steps, block=block)

    return jax.jit(kernel, donate_argnums=(0,), compiler_options=PLAIN_CPU_OPTIONS)


@functools.lru_cache(maxsize=8)
def _plain_sharded(mesh, n_steps: int, block):
    """`_plain_batch` with the batch axis split over ``mesh``'s devices: each device runs
    its own cache blocks (no communication); jitted once per mesh and number of steps."""
    spec = PartitionSpec(None, "batch")

    def local(y, args, dt):
        return run_plain(y, args, dt, n_steps=n_steps, block=block)

    return jax.jit(jax.shard_map(local, mesh=mesh, in_specs=(spec, PartitionSpec(), PartitionSpec()), out_specs=spec),
                   donate_argnums=(0,))


def _plain_program(args: ClosedLoop, dt, dtype, *, mesh, block, vector_width, specialise, kernel):
    """The program of `drive_plain` (see there): ``(program, auto_kernel)``, ``program(y, k)`` taking ``k`` plain
    steps of a batch-last state; ``auto_kernel``: the one-kernel path was chosen by ``kernel="auto"``."""
    try:
        key = _args_key(args) if specialise else None
    except (TypeError, jax.errors.ConcretizationTypeError):        # traced args: the generic kernel
        specialise, key = False, None
    cpu = jax.default_backend() == "cpu"
    fits = specialise and mesh is None and gpu_plain.supported(args)
    auto = isinstance(kernel, str) and kernel == "auto"
    if auto:
        kernel = fits and jax.default_backend() in ("gpu", "cuda", "rocm")
    elif kernel and not fits:
        raise ValueError("kernel=True runs the paper's law with a built-in damping model, concrete "
                         "parameters and no mesh")
    dtj = jnp.asarray(dt, dtype)
    if kernel:
        return (lambda y, k: gpu_plain.run_plain_kernel(y, dt, n_steps=k, key=key, interpret=cpu)), auto
    if mesh is not None:
        return (lambda y, k: _plain_sharded(mesh, k, block)(y, args, dtj)), False
    if vector_width is not None and cpu:
        return (lambda y, k: _plain_batch_wide(vector_width)(y, args, dtj, k, block)), False
    if specialise and cpu:
        return (lambda y, k: _plain_specialised(key, k, block, np.dtype(dtype).name)(y, dtj)), False
    return (lambda y, k: _plain_batch(y, args, dtj, k, block)), False


def drive_plain(y0w, status0, args: ClosedLoop, horizon: Horizon, *, segment: int = 1000, progress=None,
                mesh=None, block="auto", vector_width=None, specialise: bool = True, kernel="auto"):
    """Plain fixed-step RK4 to the horizon, final state only; returns ``(y (N, 5), status (N,))``.

    Status is judged at the end: ``NONFINITE`` if the state is not finite, ``CROSSED_SINGULAR`` if
    theta ends with the other sign (an even number of crossings goes unseen; the stepper's
    per-step checks and summaries cost about 2x on CPU: ``run_ensemble``'s default, ``SaveAt(summaries=True)``).

    The kernel steps cache blocks of ``block`` trajectories (`run_plain`;
    ``None``: the whole batch per step, the earlier form; both give bitwise the same states for
    batch sizes that are multiples of 8). XLA:CPU runs it on one core. ``"auto"`` (default):
    `PLAIN_BLOCK` on CPU, the whole batch on an accelerator (blocks would run one after another
    there: ``lax.map`` is a sequential loop, and a GPU wants every lane of the batch in each step).
    ``mesh`` (a 1-D mesh with axis ``"batch"``, see `batch_mesh`; ``"auto"``: every device of
    ``jax.devices()``) splits the batch over devices, e.g. the host devices of
    ``XLA_FLAGS=--xla_force_host_platform_device_count=2``; the batch is padded with
    harmless starts to a multiple of the device count. Sharded results agree with one device to
    float32 rounding (not bitwise: XLA compiles the sharded program's arithmetic slightly
    differently). The studies do not use it: `jaxsleigh.studies.ensemble` cuts each chunk into parts
    that run on one device each (`jaxsleigh.cores`), bitwise the same on any number of cores.

    ``vector_width`` (CPU only, one device; e.g. 512 on AVX-512 machines) compiles the kernel with
    that preferred SIMD width: ~15% less CPU time on the test machine, final states within ~1e-5
    (relative, after 10^4 steps) of the default build instead of bitwise equal; ``None`` keeps
    XLA's default (256).

    ``specialise`` (default, CPU, one device) compiles the kernel for this run's plant and gains
    (`_plain_specialised`): their values become constants of the program (~1.4x less CPU time than
    the generic kernel on the test machine) and LLVM may fuse multiply-adds (`PLAIN_CPU_OPTIONS`,
    another ~1.13x; experiments/performance/bench_c_limit.py), final states within float32 rounding of the generic
    kernel; a new plant or new gains compile again (a second or two).

    ``kernel`` (``"auto"``: on a GPU, where `jaxsleigh.integrate.gpu_plain.supported`) runs the steps
    as one Pallas kernel in which every lane keeps its state in registers
    (`jaxsleigh.integrate.gpu_plain`); ``False`` keeps XLA's loop of kernels, ``True`` asks for it
    on any backend (through Pallas' interpreter off a GPU: slow, for tests)."""
    dtype = y0w.dtype
    n = y0w.shape[0]
    if isinstance(block, str) and block == "auto":
        block = PLAIN_BLOCK if jax.default_backend() == "cpu" else None
    if isinstance(mesh, str) and mesh == "auto":
        mesh = batch_mesh()
    y = np.where(np.asarray(status0)[:, None] == Status.OK, np.asarray(y0w), [1.0, 0, 0, 0, 0])
    if mesh is not None:
        y = np.concatenate([y, np.tile([[1.0, 0, 0, 0, 0]], (-n % mesh.size, 1))])
    y = jnp.asarray(y, dtype).T
    if mesh is not None:
        y = shard_batch(y, mesh)
    program, auto_kernel = _plain_program(args, horizon.dt, dtype, mesh=mesh, block=block, vector_width=vector_width,
                                          specialise=specialise, kernel=kernel)
    done = 0
    while done < horizon.n_steps:
        k = min(segment, horizon.n_steps - done)
        try:
            y = program(y, k)
        except Exception as e:      # noqa: BLE001 - a GPU whose compiler refuses the kernel
            if not auto_kernel or done:
                raise
            warnings.warn(f"the one-kernel fixed-step path failed on this GPU ({type(e).__name__}: {e}); "
                          f"running XLA's loop of kernels instead (drive_plain(kernel=False))", stacklevel=2)
            program, auto_kernel = _plain_program(args, horizon.dt, dtype, mesh=mesh, block=block,
                                                  vector_width=vector_width, specialise=specialise, kernel=False)
            continue
        done += k
        if progress is not None:
            progress.update(done / horizon.n_steps)
    y = np.asarray(y).T[:n]
    status = np.array(status0, np.int32)
    ok = status == Status.OK
    finite = np.all(np.isfinite(y), axis=1)
    status[ok & ~finite] = Status.NONFINITE
    if chart_for(args.controller).singular:
        status[ok & finite & (np.sign(y[:, 0]) != np.sign(np.asarray(y0w)[:, 0]))] = Status.CROSSED_SINGULAR
    return y, status

