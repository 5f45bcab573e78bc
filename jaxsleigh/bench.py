"""Benchmarks of jaxsleigh's own ensemble runs (``jaxsleigh bench``); peers: ``experiments/``.

Every figure is measured warm (a first run on the same shapes compiles), on whatever JAX sees
as its devices; the JSON says which, and the dtype. Correctness is judged against a float64
reference: the adaptive method at rtol = atol = 1e-11, which ``tests/test_reference.py`` and
``tests/test_engine.py`` check against scipy's Radau/DOP853 (agreement ~1e-8).
"""
from __future__ import annotations

import platform
import resource
import sys
import time
from pathlib import Path
from typing import Optional

import jax
import numpy as np

from .ensemble import run_ensemble
from .status import Status

__all__ = ["workload", "reference_final", "final_state_error", "bench", "peak_rss_mb", "machine"]

CORRECT_TOL = 1e-3


def workload(n: int, seed: int = 0) -> np.ndarray:
    """The measured workload (MEASURED.md): x, y ~ U(-3, 3), |theta0| ~ U(0.3, pi) with random
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
    r = run_ensemble(ics, t_final=t_final, x64=True, rtol=1e-11, atol=1e-11, max_steps=2_000_000,
                     progress=False)
    if np.any(r.status != Status.OK):
        raise RuntimeError(f"reference failed on {(r.status != 0).sum()} starts")
    out = np.concatenate([r.q, r.p], axis=1)
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
    import os
    return {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(), "jax": jax.__version__,
            "devices": [f"{d.platform}:{getattr(d, 'device_kind', '')}" for d in jax.devices()]}


def _timed(fn, repeats: int = 1):
    fn()                                   # compile and warm up on the same shapes
    best = np.inf
    out = None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def bench(n_ics: int = 4096, t_final: float = 100.0, dt: float = 0.01, x64: bool = False, seed: int = 0,
          repeats: int = 1, cache_dir: Optional[str] = None) -> dict:
    """jaxsleigh's own figures on the workload: see the module docstring and the README."""
    ics = workload(n_ics, seed)
    steps = int(round(t_final / dt))
    ref = reference_final(ics, t_final=t_final, cache_dir=cache_dir)
    chunk = max(n_ics, 1)
    common = dict(t_final=t_final, dt=dt, x64=x64, chunk_size=chunk, progress=False)

    def fixed(check, summaries=True):
        return lambda: run_ensemble(ics, method="rk4", check_passivity=check, summaries=summaries, **common)

    wall_rk4, r_rk4 = _timed(fixed(False, summaries=False), repeats)      # plain RK4, final state only
    wall_rk4s, r_rk4s = _timed(fixed(False), repeats)                     # + per-step summaries
    wall_rk4m, r_rk4m = _timed(fixed(True), repeats)                      # + passivity monitor
    wall_acc, r_acc = _timed(lambda: run_ensemble(ics, **common), repeats)
    err_acc = final_state_error(r_acc.q, r_acc.p, ref)
    correct = (r_acc.status == Status.OK) & (err_acc <= CORRECT_TOL)
    err_rk4 = final_state_error(r_rk4.q, r_rk4.p, ref)
    return {
        "n_ics": n_ics, "steps": steps, "t_final": t_final, "dt": dt,
        "dtype": r_acc.settings["dtype"], "device": machine()["devices"][0], "n_devices": jax.device_count(),
        "traj_steps_per_s": n_ics * steps / wall_rk4,
        "traj_steps_per_s_with_summaries": n_ics * steps / wall_rk4s,
        "traj_steps_per_s_with_passivity_check": n_ics * steps / wall_rk4m,
        "rk4_wrong_or_nonfinite": int(np.sum(err_rk4 > CORRECT_TOL)),
        "rk4_checked_wrong_or_nonfinite": int(np.sum(final_state_error(r_rk4m.q, r_rk4m.p, ref) > CORRECT_TOL)),
        "rk4_checked_flagged": int(np.sum(r_rk4m.status != Status.OK)),
        "rk4_checked_wall_s": wall_rk4m,
        "correct_traj_per_s": float(correct.sum() / wall_acc),
        "wrong_or_nonfinite": int(np.sum(~correct)),
        "accurate_max_error": float(err_acc.max()),
        "accurate_mean_steps": float(r_acc.n_steps.mean()),
        "accurate_max_steps": int(r_acc.n_steps.max()),
        "accurate_wall_s": wall_acc, "rk4_wall_s": wall_rk4,
        "peak_rss_mb": peak_rss_mb(),
        "machine": machine(),
    }
