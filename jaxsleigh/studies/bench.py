"""Benchmarks of jaxsleigh's own ensemble runs (``jaxsleigh bench``); peers: ``experiments/``.

Every figure is measured warm (a first run on the same shapes compiles), on whatever JAX sees
as its devices; the JSON says which, and the dtype. Correctness is judged against a float64
reference: the adaptive method at rtol = atol = 1e-11, which ``tests/test_reference.py`` and
``tests/test_engine.py`` check against scipy's Radau/DOP853 (agreement ~1e-8).
"""
from __future__ import annotations

import ctypes
import functools
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np

from ..integrate.stepsize import StepSizeController
from .ensemble import run_ensemble
from .options import RunOptions, SaveAt
from ..status import Status
from ..cores import available_cores, workers
from ..integrate.engine import check_ics, drive_plain, initial_w, make_horizon
from ..model.closed_loop import ClosedLoop
from ..model.params import paper_gains, paper_plant
from ..validate import BYTES_PER_START, check_count, check_memory, real, whole

__all__ = ["workload", "reference_final", "final_state_error", "bench", "peak_rss_mb", "machine",
           "C_REFERENCE_SOURCE", "C_VARIANTS", "build_c_reference", "c_reference_run", "c_limit"]

CORRECT_TOL = 1e-3


def workload(n: int, seed: int = 0) -> np.ndarray:
    """The benchmark workload: x, y ~ U(-3, 3), |theta0| ~ U(0.3, pi) with random
    sign, zero momentum. Shape (n, 3)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-3.0, 3.0, (n, 2))
    th = rng.uniform(0.3, np.pi, n) * rng.choice([-1.0, 1.0], n)
    return np.column_stack([xy, th])


def reference_final(ics, *, t_final: float = 100.0, cache_dir=None) -> np.ndarray:
    """Float64 high-accuracy final states ``(N, 5)`` (adaptive, rtol = atol = 1e-11), cached."""
    ics = np.asarray(ics, np.float64)
    path = None
    if cache_dir is not None:
        import hashlib
        key = hashlib.sha256(ics.tobytes() + repr(t_final).encode()).hexdigest()[:16]
        path = Path(cache_dir) / f"reference_{key}.npy"
        if path.exists():
            return np.load(path)
    r = run_ensemble(ics, t_final=t_final, x64=True,
                     stepsize=StepSizeController(rtol=1e-11, atol=1e-11, max_steps=2_000_000),
                     run=RunOptions(progress=False))
    if np.any(r.status != Status.OK):
        raise RuntimeError(f"reference failed on {(r.status != 0).sum()} starts")
    out = np.concatenate([r.q_final, r.p_final], axis=1)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.save(path, out)
    return out


def final_state_error(q, p, ref) -> np.ndarray:
    """Max-norm final-state error per trajectory; ``inf`` where the state is not finite."""
    err = np.max(np.abs(np.concatenate([q, p], axis=1) - ref), axis=1)
    return np.where(np.isfinite(err), err, np.inf)


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (MiB)."""
    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kb / 1024.0 if sys.platform != "darwin" else kb / 1024.0 ** 2


def machine() -> dict:
    return {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(), "jax": jax.__version__,
            "devices": [f"{d.platform}:{getattr(d, 'device_kind', '')}" for d in jax.devices()]}


def _timed(fn, repeats: int = 1):
    fn()                                   # compile and warm up on the same shapes
    best, out = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out



# ---------------------------------------------------------------------------------------------------
# The C limit: a hand-vectorised C RK4 of the same w-chart closed loop, timed against the
# plain fixed-step path in one interleaved run.

#: the C reference (a repository checkout has it; an installed package may not)
C_REFERENCE_SOURCE = Path(__file__).resolve().parent / "c_reference" / "rk4_w.c"
#: compiler flags: -O3 -march=native, no -ffast-math; -fno-math-errno only lets gcc vectorise sqrtf
#: (its argument eps + p^2 is never negative, so no result changes); -fopenmp: its blocks on several
#: threads (``c_threads``), as the JAX path's parts on several cores; without OpenMP it builds serial
C_FLAGS = ("-O3", "-march=native", "-fno-math-errno", "-fopenmp", "-shared", "-fPIC")
#: variants of the C reference (preprocessor macros of rk4_w.c), timed only on request: the literal
#: 6-division form, one shared division, and XLA's rsqrt (estimate + Newton step); the default build
#: (3 IEEE divisions + 2 IEEE square roots per evaluation) is the reference of ``c_limit_ratio``
C_VARIANTS = {"strict": ("RK4W_STRICT",), "shared_recip": ("RK4W_SHARED_RECIP",), "rsqrt_nr": ("RK4W_RSQRT_NR",)}


class _CParams(ctypes.Structure):
    _fields_ = [(name, ctypes.c_float) for name in
                ("m", "J", "l", "d_eps", "d_scale", "L1", "L2", "L3", "k", "D11", "D12", "D21", "D22")]


def build_c_reference(out_dir=None, source=None, defines=()):
    """Compile the C reference into a shared library; returns ``(path, None)`` or ``(None, reason)``.
    ``defines``: preprocessor macros selecting a variant (see `C_VARIANTS`)."""
    source = Path(source) if source is not None else C_REFERENCE_SOURCE
    if not source.exists():
        return None, f"C reference source not found ({source}); run from a repository checkout"
    cc = os.environ.get("CC") or shutil.which("gcc") or shutil.which("cc")
    if cc is None:
        return None, "no C compiler (gcc or cc) on PATH"
    out_dir = Path(out_dir) if out_dir is not None else Path(tempfile.mkdtemp(prefix="jaxsleigh_c_"))
    out_dir.mkdir(parents=True, exist_ok=True)
    lib = out_dir / ("librk4_w" + "".join(f"_{d.lower()}" for d in defines) + ".so")
    cmd = [cc, *C_FLAGS, *(f"-D{d}" for d in defines), str(source), "-o", str(lib), "-lm"]
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    except (OSError, subprocess.SubprocessError) as e:
        return None, f"C build failed to run: {e}"
    if r.returncode != 0 and "-fopenmp" in cmd:        # a compiler without OpenMP: the serial build
        cmd.remove("-fopenmp")
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    if r.returncode != 0:
        return None, f"C build failed ({' '.join(cmd)}): {r.stderr.strip()[:400]}"
    return lib, None


def _c_params(args) -> _CParams:
    plant, g = args.plant, args.gains
    d = plant.damping
    if type(d).__name__ != "CoulombDamping":
        raise NotImplementedError("the C reference implements the paper's Coulomb damping only")
    L = np.asarray(g.L, np.float64)
    D = np.asarray(g.D_hat, np.float64).ravel()
    return _CParams(float(plant.m), float(plant.J), float(plant.l), float(d.eps), float(d.scale),
                    *(float(v) for v in L), float(g.k), *(float(v) for v in D))


def c_reference_run(lib, y0w, args, dt, n_steps, n_threads: int = 1):
    """Run the C reference on w-chart starts ``y0w`` (N, 5) float32; returns the final (N, 5).
    ``lib``: a path from `build_c_reference` or a loaded ``ctypes.CDLL``."""
    if not isinstance(lib, ctypes.CDLL):
        lib = ctypes.CDLL(str(lib))
    fn = lib.rk4w_run
    fn.restype = ctypes.c_int
    fn.argtypes = [ctypes.c_void_p, ctypes.c_long, ctypes.c_long, ctypes.c_float, ctypes.POINTER(_CParams),
                   ctypes.c_int]
    y = np.ascontiguousarray(np.asarray(y0w, np.float32).T)          # (5, N) structure of arrays
    params = _c_params(args)
    fn(y.ctypes.data, y.shape[1], int(n_steps), float(dt), ctypes.byref(params), int(n_threads))
    return y.T.copy()


def _divider_ops(lib):
    """Divisions + square roots per field evaluation of a C build (None for an older source)."""
    try:
        fn = lib.rk4w_divider_ops
    except AttributeError:
        return None
    fn.restype = ctypes.c_int
    return int(fn())


def _summary(xs):
    xs = np.asarray(xs, np.float64)
    return {"median": float(np.median(xs)), "min": float(xs.min()), "max": float(xs.max()),
            "values": [float(x) for x in xs]}


def c_limit(ics, *, t_final: float = 100.0, dt: float = 0.01, repeats: int = 5, lib=None, build_dir=None,
            log=None, whole_batch: bool = False, variants: Optional[dict] = None,
            c_variants: Optional[list] = None, c_threads: Optional[int] = None) -> dict:
    """The plain fixed-step path against the C reference in ONE interleaved timing run.

    Each repetition times the C program (via ctypes, on ``c_threads`` OpenMP threads; default: as many
    as the cores the JAX call uses, `jaxsleigh.cores.workers`; on an accelerator, every core of the host) and
    ``run_ensemble(ics, stepsize=StepSizeController(method="rk4", check_passivity=False),
    saveat=SaveAt(summaries=False), ...)`` back to back,
    alternating which goes first; compile and warm-up runs are not timed. Throughput is
    trajectory-steps per second of wall time and per second of CPU time (``time.process_time``:
    all threads of this process, so a JAX run on two cores is charged for both). ``ratio_cpu`` is
    JAX / C per CPU second, per repetition (median and range reported). Agreement: final states
    (w chart) of C and of the JAX path from the same float32 starts, relative to each state's
    largest component, on the tame starts (those whose float32 and float64 fixed-step results
    agree to 1e-3, i.e. where rounding is not amplified). ``whole_batch`` also times, in the same
    rotation, the same call with the earlier kernel (one scan over the whole batch,
    ``drive_plain(block=None)``) as ``jax_whole_batch``: a before/after in one run. ``variants``
    (``{name: drive_plain keyword arguments}``, e.g. ``{"jax_vw512": {"vector_width": 512}}``) times
    more such variants of the call the same way. ``c_variants`` (names from `C_VARIANTS`)
    times those builds of the C program in the same rotation (``c_<name>_...`` throughputs and
    ``ratio_cpu_vs_c_<name>``: JAX / that build). Returns a dict;
    ``available`` False with ``reason`` when the C program cannot be built (float64 runs are not
    compared either)."""
    log = log or (lambda *a: None)
    if jnp.zeros(()).dtype != jnp.float32:
        return {"available": False, "reason": "the C reference is float32; run without x64"}
    lib, c_libs, reason = _load_c_programs(lib, build_dir, c_variants)
    if lib is None:
        return {"available": False, "reason": reason}
    ics = np.asarray(ics, np.float64)
    n = ics.shape[0]
    horizon, args, status0, y0w = _w_chart_starts(ics, t_final, dt)
    steps = horizon.n_steps
    kw = dict(t_final=t_final, dt=dt, stepsize=StepSizeController(method="rk4", check_passivity=False),
              saveat=SaveAt(summaries=False), run=RunOptions(progress=False))
    cores = len(workers())
    if c_threads is None:       # on an accelerator the C program gets every core of the host
        c_threads = cores if jax.default_backend() == "cpu" else available_cores()
    c_threads = int(c_threads)

    def run_c(c_lib=lib, n_threads=c_threads):
        return c_reference_run(c_lib, y0w, args, dt, steps, n_threads)

    variants = dict(variants or {})
    if whole_batch:
        variants["jax_whole_batch"] = {"block": None}
    rec = _rotation(_contestants(run_c, c_libs, ics, kw, variants), repeats, log)
    out = {"available": True, "reason": None, "n_ics": n, "steps": steps, "dt": dt, "dtype": "float32",
           "repeats": repeats, "c_flags": " ".join(C_FLAGS), "c_threads": c_threads, "jax_cores": cores,
           "c_divider_ops_per_evaluation": _divider_ops(lib),
           "timed_call": "run_ensemble(ics, stepsize=StepSizeController(method='rk4', check_passivity=False), "
                         f"saveat=SaveAt(summaries=False), t_final={t_final:g}, dt={dt:g}, "
                         "run=RunOptions(progress=False))"}
    out.update(_rates(rec, n * steps, c_libs, variants))
    out["agreement"] = _agreement(run_c(), {cv: run_c(vl, 1) for cv, vl in c_libs.items()},
                                  y0w, status0, args, horizon)
    return out


def _load_c_programs(lib, build_dir, c_variants):
    """The C reference (``lib``, else built in ``build_dir``) and the builds ``c_variants`` beside it, loaded:
    ``(CDLL, {name: CDLL}, None)``, or ``(None, {}, reason)`` when the reference cannot be built."""
    if lib is None:
        lib, reason = build_c_reference(build_dir)
        if lib is None:
            return None, {}, reason
    lib_path = Path(str(lib))
    lib = ctypes.CDLL(str(lib))
    c_libs = {}
    for cv in c_variants or []:
        vlib, vreason = build_c_reference(lib_path.parent, defines=C_VARIANTS[cv])
        if vlib is None:
            raise RuntimeError(f"C variant {cv}: {vreason}")
        c_libs[cv] = ctypes.CDLL(str(vlib))
    return lib, c_libs, None


def _w_chart_starts(ics, t_final, dt):
    """``(horizon, closed loop, status0, float32 w-chart starts)`` of the paper's loop from ``ics`` (N, 3)."""
    horizon = make_horizon(t_final, dt)
    args = ClosedLoop(paper_plant(), paper_gains())
    ics5, status0 = check_ics(ics)
    y0w = initial_w(ics5, status0, jnp.float32)
    return horizon, args, status0, y0w


def _contestants(run_c, c_libs: dict, ics, kw, variants: dict) -> list:
    """``[(name, fn)]`` timed by `c_limit`: the C reference, the JAX call, the C builds ``c_libs``
    (``run_c(lib)``) and the kernel variants ``{name: drive_plain keywords}``."""
    contestants = [("c", run_c), ("jax", lambda: run_ensemble(ics, **kw))]
    for cv, vl in c_libs.items():
        contestants.append((f"c_{cv}", functools.partial(run_c, vl)))
    for vname, vkw in variants.items():
        contestants.append((vname, functools.partial(_run_variant, ics, kw, vkw)))
    return contestants


def _rates(rec: dict, work: int, c_libs: dict, variants: dict) -> dict:
    """Trajectory-steps (``work``) per CPU and per wall second of each contestant in ``rec``, then the
    per-repetition throughput ratios (a C program's time over a JAX call's): JAX / C, JAX / each C build in
    ``c_libs`` (with its divider ops), and each kernel variant / C."""
    def ratio(c_name, jax_name, kind):
        return _summary([c / j for c, j in zip(rec[c_name][kind], rec[jax_name][kind])])

    out = {}
    for name in rec:
        out[f"{name}_traj_steps_per_cpu_s"] = _summary([work / c for c in rec[name]["cpu"]])
        out[f"{name}_traj_steps_per_wall_s"] = _summary([work / w for w in rec[name]["wall"]])
    out.update(ratio_cpu=ratio("c", "jax", "cpu"), ratio_wall=ratio("c", "jax", "wall"))
    for cv, vl in c_libs.items():
        out[f"c_{cv}_divider_ops_per_evaluation"] = _divider_ops(vl)
        out[f"ratio_cpu_vs_c_{cv}"] = ratio(f"c_{cv}", "jax", "cpu")
        out[f"ratio_wall_vs_c_{cv}"] = ratio(f"c_{cv}", "jax", "wall")
    for vname in variants:
        suffix = vname[len("jax_"):] if vname.startswith("jax_") else vname
        out[f"ratio_cpu_{suffix}"] = ratio("c", vname, "cpu")
        out[f"ratio_wall_{suffix}"] = ratio("c", vname, "wall")
    return out


def _run_variant(ics, kw, vkw):
    """``run_ensemble(ics, **kw)`` with `drive_plain` given the keywords ``vkw`` (a variant of the kernel)."""
    from . import ensemble as _ensemble

    orig = _ensemble.drive_plain
    _ensemble.drive_plain = functools.partial(orig, **vkw)
    try:
        return run_ensemble(ics, **kw)
    finally:
        _ensemble.drive_plain = orig


def _rotation(contestants, repeats: int, log) -> dict:
    """Each ``(name, fn)`` warmed up once, then timed ``repeats`` times in turn, the order reversed every
    other repetition; ``{name: {"wall": [...], "cpu": [...]}}`` (seconds)."""
    for _, fn in contestants:
        fn()                                             # compile and warm up; not timed
    rec = {name: {"wall": [], "cpu": []} for name, _ in contestants}
    for r in range(max(1, repeats)):
        order = contestants if r % 2 == 0 else contestants[::-1]
        for name, fn in order:
            w0, c0 = time.perf_counter(), time.process_time()
            fn()
            rec[name]["wall"].append(time.perf_counter() - w0)
            rec[name]["cpu"].append(time.process_time() - c0)
        log(f"  repetition {r + 1}: " + ", ".join(f"{name} {v['cpu'][-1]:.3f} s cpu / {v['wall'][-1]:.3f} s wall"
                                                   for name, v in rec.items()))
    return rec


def _agreement(yc, yc_var: dict, y0w, status0, args, horizon) -> dict:
    """Final states (w chart) of the C program ``yc`` (and its variants ``yc_var``) against the JAX path's
    from the same float32 starts, relative to each state's largest component, on the tame starts (float32
    and float64 fixed-step results within 1e-3)."""
    yj, st = drive_plain(y0w, status0, args, horizon)
    with jax.enable_x64(True):
        y64, _ = drive_plain(jnp.asarray(np.asarray(y0w), jnp.float64), status0, args, horizon)
    scale = np.maximum(np.max(np.abs(y64), axis=1), 1e-30)
    tame = (status0 == 0) & np.all(np.isfinite(yj), axis=1) & (np.max(np.abs(yj - y64), axis=1) / scale <= 1e-3)
    rel_cj = np.max(np.abs(yc - yj), axis=1) / scale
    rel_32 = np.max(np.abs(yj - y64), axis=1) / scale
    fin = np.all(np.isfinite(yc), axis=1) == np.all(np.isfinite(yj), axis=1)
    agreement = {
        "n_tame": int(tame.sum()),
        "c_vs_jax_rel_max_tame": float(rel_cj[tame].max()) if tame.any() else None,
        "c_vs_jax_rel_median_tame": float(np.median(rel_cj[tame])) if tame.any() else None,
        "c_vs_jax_rel_p99_tame": float(np.quantile(rel_cj[tame], 0.99)) if tame.any() else None,
        "float32_vs_float64_rel_median_tame": float(np.median(rel_32[tame])) if tame.any() else None,
        "float32_vs_float64_rel_max_tame": float(rel_32[tame].max()) if tame.any() else None,
        "bitwise_equal_rows": int(np.all(yc == yj, axis=1).sum()),
        "finiteness_mismatch": int((~fin).sum()),
        "c_vs_jax_rel_max_all_finite": float(np.nanmax(np.where(np.isfinite(rel_cj), rel_cj, np.nan))),
    }
    for cv, yv in yc_var.items():
        rel_v = np.max(np.abs(yv - yc), axis=1) / scale
        agreement[f"c_{cv}_vs_c_rel_median_tame"] = float(np.median(rel_v[tame])) if tame.any() else None
        agreement[f"c_{cv}_vs_c_rel_max_tame"] = float(rel_v[tame].max()) if tame.any() else None
    return agreement


#: The most trajectory-steps (starts x base steps) of one benchmark: the default 4,096 starts x 10,000 steps take
#: about a minute on 2 CPU cores (a float64 reference and four timed runs), so this bound about four hours.
MAX_BENCH_WORK = 2**20 * 10_000


def check_bench_sizes(n_ics, t_final, dt, names: dict | None = None) -> int:
    """``n_ics`` checked before any work: the starts, the float64 reference and the results of the four timed runs
    in host memory (5 x `jaxsleigh.validate.BYTES_PER_START` per start), and at most `MAX_BENCH_WORK`
    trajectory-steps (``n_ics x t_final / dt``). ``names`` maps ``n_ics``, ``t_final`` and ``dt`` to the keywords
    or flags the messages name. Returns ``n_ics``."""
    w = {"n_ics": "n_ics", "t_final": "t_final", "dt": "dt", **(names or {})}
    n = whole(w["n_ics"], n_ics, example=4096)
    steps = round(real(w["t_final"], t_final, positive=True) / real(w["dt"], dt, positive=True))
    check_memory(n, w["n_ics"], bytes_per_start=5 * BYTES_PER_START,
                 fix=f"use a smaller {w['n_ics']} (4096 is the default)")
    check_count(f"{w['n_ics']} {n:,} x {steps:,} base steps ({w['t_final']} / {w['dt']}): the trajectory-steps",
                n * steps, maximum=MAX_BENCH_WORK,
                reason="the default 4,096 x 10,000 take about a minute on 2 CPU cores, so this bound about four hours",
                fix=f"use a smaller {w['n_ics']} or a shorter {w['t_final']}")
    return n


def bench(n_ics: int = 4096, t_final: float = 100.0, dt: float = 0.01, x64: bool = False, seed: int = 0,
          repeats: int = 1, cache_dir: Optional[str] = None) -> dict:
    """jaxsleigh's own figures on the workload: see the module docstring and the README. Sizes that do not fit
    are refused before any work (`check_bench_sizes`)."""
    n_ics = check_bench_sizes(n_ics, t_final, dt)
    ics = workload(n_ics, seed)
    steps = int(round(t_final / dt))
    ref = reference_final(ics, t_final=t_final, cache_dir=cache_dir)
    common = dict(t_final=t_final, dt=dt, x64=x64, run=RunOptions(chunk_size=max(n_ics, 1), progress=False))
    figures, r_acc = _timed_runs(ics, common, repeats, ref, n_ics * steps)
    lim = _bench_c_limit(ics, t_final=t_final, dt=dt, x64=x64, repeats=repeats)
    ok_lim = lim.get("available", False)
    return {
        "n_ics": n_ics, "steps": steps, "t_final": t_final, "dt": dt,
        "dtype": r_acc.settings["dtype"], "device": machine()["devices"][0], "n_devices": jax.device_count(),
        # the cores the runs used (jaxsleigh.cores) and the C reference's threads in the same comparison
        "cores": len(r_acc.run_info["devices"]), "c_threads": lim.get("c_threads") if ok_lim else None,
        "load_average": [round(x, 2) for x in os.getloadavg()],
        **figures,
        "peak_rss_mb": peak_rss_mb(),
        **_c_limit_figures(lim),
        "c_limit": lim,
        "machine": machine(),
    }


def _timed_runs(ics, common: dict, repeats: int, ref, work: int):
    """The calls `bench` times, each warm and best of ``repeats``, and their figures: throughput (``work``
    trajectory-steps over the best wall time) and wrong counts of the fixed-step runs; correct trajectories per
    second (status OK, final-state error <= `CORRECT_TOL`), error and step counts of the adaptive run.
    Returns ``(figures, adaptive result)``."""
    def fixed(check, summaries=True):
        return lambda: run_ensemble(ics, stepsize=StepSizeController(method="rk4", check_passivity=check),
                                    saveat=SaveAt(summaries=summaries), **common)

    def wrong(r):
        return final_state_error(r.q_final, r.p_final, ref) > CORRECT_TOL

    wall_rk4, r_rk4 = _timed(fixed(False, summaries=False), repeats)      # plain RK4, final state only
    wall_rk4s, _ = _timed(fixed(False), repeats)                          # + per-step summaries
    wall_rk4m, r_rk4m = _timed(fixed(True), repeats)                      # + passivity monitor
    wall_acc, r_acc = _timed(lambda: run_ensemble(ics, **common), repeats)
    err_acc = final_state_error(r_acc.q_final, r_acc.p_final, ref)
    correct = (r_acc.status == Status.OK) & (err_acc <= CORRECT_TOL)
    return {
        "traj_steps_per_s": work / wall_rk4,
        "traj_steps_per_s_with_summaries": work / wall_rk4s,
        "traj_steps_per_s_with_passivity_check": work / wall_rk4m,
        "rk4_wrong_or_nonfinite": int(np.sum(wrong(r_rk4))),
        "rk4_checked_wrong_or_nonfinite": int(np.sum(wrong(r_rk4m))),
        "rk4_checked_flagged": int(np.sum(r_rk4m.status != Status.OK)),
        "rk4_checked_wall_s": wall_rk4m,
        "correct_traj_per_s": float(correct.sum() / wall_acc),
        "wrong_or_nonfinite": int(np.sum(~correct)),
        "accurate_max_error": float(err_acc.max()),
        "accurate_mean_steps": float(r_acc.n_steps.mean()),
        "accurate_max_steps": int(r_acc.n_steps.max()),
        "accurate_wall_s": wall_acc,
        "rk4_wall_s": wall_rk4,
    }, r_acc


def _bench_c_limit(ics, *, t_final, dt, x64, repeats) -> dict:
    """`c_limit` for `bench`; ``available`` False with a reason under x64 or when it fails."""
    # the plain fixed-step path against the C reference, one interleaved run (float32 only)
    if x64:
        return {"available": False, "reason": "the C reference is float32; run without --x64"}
    try:
        return c_limit(ics, t_final=t_final, dt=dt, repeats=max(3, repeats))
    except Exception as e:                      # a broken toolchain must not lose the other figures
        return {"available": False, "reason": f"{type(e).__name__}: {e}"}


def _c_limit_figures(lim: dict) -> dict:
    """`bench`'s summary of the `c_limit` result ``lim`` (all None when it is not available)."""
    ok_lim = lim.get("available", False)
    return {
        # JAX / C trajectory-steps per CPU second (median over interleaved repetitions), or None
        "c_limit_ratio": lim["ratio_cpu"]["median"] if ok_lim else None,
        "c_limit_ratio_range": [lim["ratio_cpu"]["min"], lim["ratio_cpu"]["max"]] if ok_lim else None,
        "c_limit_ratio_wall": lim["ratio_wall"]["median"] if ok_lim else None,
        "c_limit_ratio_wall_range": [lim["ratio_wall"]["min"], lim["ratio_wall"]["max"]] if ok_lim else None,
        "c_limit_traj_steps_per_cpu_s": lim["c_traj_steps_per_cpu_s"]["median"] if ok_lim else None,
        "traj_steps_per_cpu_s": lim["jax_traj_steps_per_cpu_s"]["median"] if ok_lim else None,
        "c_limit_reason": None if ok_lim else lim.get("reason"),
    }
