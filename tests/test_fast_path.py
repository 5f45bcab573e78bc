"""The plain fixed-step path (``run_ensemble(stepsize=StepSizeController(method="rk4"), saveat=SaveAt(summaries=False))``)
in cache blocks.

``run_plain`` steps blocks of ``PLAIN_BLOCK`` trajectories through all steps before moving on.
These tests hold it to the earlier form (one scan over the whole batch, ``block=None``):
the same final states, bitwise, and the same status logic; to the per-step stepper path
(``summaries=True``) to float32 rounding; and, where a C compiler exists, to the C reference.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import jax.numpy as jnp
import numpy as np
import pytest

from jaxsleigh.model.closed_loop import ClosedLoop
from jaxsleigh.integrate.engine import check_ics, drive_plain, initial_w, make_horizon
from jaxsleigh.integrate.stepsize import StepSizeController
from jaxsleigh.studies.ensemble import run_ensemble
from jaxsleigh.studies.options import RunOptions, SaveAt
from jaxsleigh.model.params import paper_gains, paper_plant
from jaxsleigh.status import Status
from jaxsleigh.integrate.stepper import PLAIN_BLOCK, run_plain

ARGS = ClosedLoop(paper_plant(), paper_gains())


def _tame(n, seed):
    """The benchmark's kind of start, away from theta = 0 (|theta0| >= 0.8), zero momentum."""
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-3, 3, (n, 2)), rng.uniform(0.8, np.pi, n) * rng.choice([-1.0, 1.0], n)])


def _w(ics):
    a, st = check_ics(ics)
    return np.asarray(initial_w(a, st, jnp.float32)), st


def _rel(a, b):
    return np.max(np.abs(a - b), axis=1) / np.maximum(np.max(np.abs(b), axis=1), 1.0)


@pytest.mark.parametrize("n", [3, PLAIN_BLOCK, 2 * PLAIN_BLOCK + 40])
def test_blocks_match_the_whole_batch_result(n):
    """One block, whole blocks and a padded last block against the whole batch stepped at once: the
    same status and the same final states to float32 rounding. (They were bit for bit the same until
    the specialised kernel let LLVM contract and reassociate, `PLAIN_CPU_OPTIONS`, which it may do
    differently in loops of other lengths; a start's result still does not depend on its batch, see
    the next test.)"""
    y0, st = _w(_tame(n, seed=n))
    hz = make_horizon(3.0, 0.01)
    y_blk, s_blk = drive_plain(y0, st, ARGS, hz, segment=120)            # 300 steps: 120 + 120 + 60
    y_all, s_all = drive_plain(y0, st, ARGS, hz, segment=300, block=None)
    np.testing.assert_array_equal(s_blk, s_all)
    assert np.all(s_blk == Status.OK)
    assert np.all(np.isfinite(y_blk)) and np.max(_rel(y_blk, y_all)) < 1e-5


def test_blocked_result_does_not_depend_on_the_batch():
    """XLA:CPU compiles a whole batch of an odd size (549) with slightly different rounding
    (~1e-7 relative on some lanes) than one of a multiple of 8; the blocked path always steps
    blocks of the same shape, so a start's result no longer depends on the batch it is in."""
    ics = _tame(1031, seed=2)
    hz = make_horizon(3.0, 0.01)
    y_big, _ = drive_plain(*_w(ics), ARGS, hz)
    y_small, _ = drive_plain(*_w(ics[:549]), ARGS, hz)
    np.testing.assert_array_equal(y_small, y_big[:549])
    y_old, _ = drive_plain(*_w(ics[:549]), ARGS, hz, block=None)
    assert np.max(_rel(y_small, y_old)) < 1e-5


def test_run_plain_pads_and_drops_the_partial_block():
    y0, _ = _w(_tame(PLAIN_BLOCK + 5, seed=1))
    y = jnp.asarray(y0.T)
    out = run_plain(y, ARGS, jnp.float32(0.01), n_steps=7)
    assert out.shape == y.shape
    np.testing.assert_array_equal(np.asarray(out), np.asarray(run_plain(y, ARGS, jnp.float32(0.01), n_steps=7,
                                                                        block=None)))


def test_status_logic_unchanged_on_failing_starts():
    """Starts that blow up (dt far too large near theta = 0), a singular and a non-finite start:
    the blocked path flags exactly what the whole-batch path flags, and outputs NaN for them."""
    rng = np.random.default_rng(7)
    stiff = np.column_stack([rng.uniform(-3, 3, (40, 2)), rng.uniform(0.02, 0.3, 40) * rng.choice([-1.0, 1.0], 40)])
    ics = np.vstack([_tame(300, seed=3), stiff, [[1.0, 1.0, 0.0]], [[np.nan, 0.0, 1.0]]])
    with pytest.warns(UserWarning):
        a, st = check_ics(ics)
    y0 = np.asarray(initial_w(a, st, jnp.float32))
    hz = make_horizon(5.0, 0.25)
    y_blk, s_blk = drive_plain(y0, st, ARGS, hz, specialise=False)
    y_all, s_all = drive_plain(y0, st, ARGS, hz, block=None, specialise=False)
    np.testing.assert_array_equal(s_blk, s_all)
    np.testing.assert_array_equal(y_blk, y_all)                      # NaN where not finite, equal_nan
    # the kernel specialised to the run's plant and gains (the default) flags the same starts and
    # agrees to float32 rounding where the tame starts are
    y_sp, s_sp = drive_plain(y0, st, ARGS, hz)
    np.testing.assert_array_equal(s_sp, s_blk)
    assert np.max(_rel(y_sp[:300], y_blk[:300])) < 1e-5
    flagged = set(np.unique(s_blk).tolist())
    assert {Status.SINGULAR_START, Status.INVALID_INPUT} <= flagged
    assert flagged & {Status.NONFINITE, Status.CROSSED_SINGULAR}, flagged

    # the same through the public call: status and NaN outputs where flagged
    with pytest.warns(UserWarning):
        r = run_ensemble(ics, t_final=5.0, dt=0.25, stepsize=StepSizeController(method="rk4", check_passivity=False),
                         saveat=SaveAt(summaries=False), run=RunOptions(progress=False))
    np.testing.assert_array_equal(r.status, s_blk)
    assert np.all(np.isnan(r.q_final[r.status != Status.OK]))
    assert np.all(np.isfinite(r.q_final[r.status == Status.OK]))


def test_near_the_singular_set_the_specialised_kernel_flags_what_blows_up():
    """Starts a hair off theta = 0 overflow within a step or two (k / w1^2 ~ 1e35 and more): the
    specialised kernel, whose arithmetic LLVM may contract and reassociate (`PLAIN_CPU_OPTIONS`), keeps
    inf and NaN (the ``honor`` options), so each such start ends flagged with NaN outputs, as in
    the generic kernel, and never OK with a non-finite state."""
    ics = np.vstack([_tame(13, seed=21), [[1.0, 1.0, 1e-6], [-2.0, 0.5, -1e-12], [0.5, -2.0, 3e-18]]])
    y0, st = _w(ics)
    hz = make_horizon(2.0, 0.05)
    y_sp, s_sp = drive_plain(y0, st, ARGS, hz)
    y_gen, s_gen = drive_plain(y0, st, ARGS, hz, specialise=False)
    np.testing.assert_array_equal(s_sp, s_gen)
    assert np.all(s_sp[:13] == Status.OK) and np.all(np.isfinite(y_sp[:13]))
    assert np.all(s_sp[13:] != Status.OK), s_sp[13:]
    assert not np.any(~np.isfinite(y_sp) & (s_sp == Status.OK)[:, None])
    assert np.max(_rel(y_sp[:13], y_gen[:13])) < 1e-5


def test_specialised_kernel_in_float64_keeps_float64_accuracy(x64):
    """`PLAIN_CPU_OPTIONS` (contraction and reassociation) apply to float64 runs as well: the
    specialised kernel stays a float64 computation, agreeing with the generic float64 kernel to
    float64 rounding (far below float32's ~1e-7 per step, so a kernel that quietly ran in float32
    or lost digits to reassociation would fail), and flags a near-singular start as in float32."""
    ics = np.vstack([_tame(40, seed=5), [[1.0, 1.0, 1e-12]]])
    a, st = check_ics(ics)
    y0 = np.asarray(initial_w(a, st, jnp.float64))
    assert y0.dtype == np.float64
    hz = make_horizon(10.0, 0.01)
    y_sp, s_sp = drive_plain(y0, st, ARGS, hz)
    y_gen, s_gen = drive_plain(y0, st, ARGS, hz, specialise=False)
    assert y_sp.dtype == np.float64
    np.testing.assert_array_equal(s_sp, s_gen)
    assert np.all(s_sp[:40] == Status.OK) and s_sp[40] != Status.OK
    rel = _rel(y_sp[:40], y_gen[:40])
    assert np.max(rel) < 1e-11, np.max(rel)
    y32, _ = drive_plain(np.asarray(y0, np.float32), st, ARGS, hz)
    assert np.median(_rel(y32[:40], y_gen[:40])) > 100 * np.max(rel)     # float32 really is coarser


def test_fast_path_matches_the_per_step_path():
    """The issue's call against the stepper's fixed-step path (per-step checks and summaries):
    the same RK4, so the same final states to float32 rounding, and the same status."""
    ics = _tame(600, seed=11)
    kw = dict(stepsize=StepSizeController(method="rk4", check_passivity=False), t_final=20.0, dt=0.01,
              run=RunOptions(progress=False))
    fast = run_ensemble(ics, **kw, saveat=SaveAt(summaries=False))
    slow = run_ensemble(ics, **kw, saveat=SaveAt(summaries=True))
    np.testing.assert_array_equal(fast.status, slow.status)
    assert np.all(fast.status == Status.OK)
    rel = _rel(np.hstack([fast.q_final, fast.p_final]), np.hstack([slow.q_final, slow.p_final]))
    assert np.max(rel) < 1e-4 and np.median(rel) < 1e-6, (np.max(rel), np.median(rel))
    assert fast.settings["summaries"] is False and np.all(np.isnan(fast.T_eps))


_SHARD_SCRIPT = textwrap.dedent("""
    import json, sys, numpy as np, jax, jax.numpy as jnp
    from jaxsleigh.model.closed_loop import ClosedLoop
    from jaxsleigh.integrate.engine import check_ics, drive_plain, initial_w, make_horizon
    from jaxsleigh.model.params import paper_gains, paper_plant
    assert jax.device_count() == 2, jax.devices()
    a, st = check_ics(np.array(json.loads(sys.argv[1])))
    y0 = initial_w(a, st, jnp.float32)
    args, hz = ClosedLoop(paper_plant(), paper_gains()), make_horizon(3.0, 0.01)
    one, s1 = drive_plain(y0, st, args, hz)
    two, s2 = drive_plain(y0, st, args, hz, mesh="auto")
    print("RESULT" + json.dumps({"one": one.tolist(), "two": two.tolist(), "s1": s1.tolist(), "s2": s2.tolist()}))
""")


def test_two_host_devices_agree_to_rounding():
    """The batch split over two (forced) host devices, an odd count padded: same to float32 rounding."""
    ics = _tame(301, seed=5)
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2", JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, "-c", _SHARD_SCRIPT, json.dumps(ics.tolist())], env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.split("RESULT", 1)[1])
    assert out["s1"] == out["s2"]
    assert np.max(_rel(np.array(out["two"]), np.array(out["one"]))) < 1e-5


def _cpu_has_avx512() -> bool:
    """Whether the CPU reports AVX-512 Foundation (Linux ``/proc/cpuinfo``; elsewhere assumed yes, so
    the build's own message is the skip reason)."""
    try:
        with open("/proc/cpuinfo") as f:
            return " avx512f" in f.read()
    except OSError:
        return True


@pytest.mark.parametrize("variant", [None, "strict", "shared_recip", "rsqrt_nr"])
def test_c_reference_agrees_to_rounding(tmp_path, variant):
    """The C reference of experiments/ (built when a compiler exists) against the fast path; the
    default build (fewer divisions) and the measured variants (jaxsleigh.studies.bench.C_VARIANTS) alike
    (rsqrt_nr needs AVX-512: without it the build fails and the case is skipped)."""
    from jaxsleigh.studies.bench import C_VARIANTS, build_c_reference, c_reference_run

    lib, reason = build_c_reference(tmp_path, defines=C_VARIANTS[variant] if variant else ())
    if lib is None:
        if variant == "rsqrt_nr" and not _cpu_has_avx512():
            pytest.skip("rsqrt_nr needs AVX-512 (avx512f), which this CPU lacks")
        pytest.skip(reason)
    y0, st = _w(_tame(300, seed=9))
    hz = make_horizon(10.0, 0.01)
    y_jax, _ = drive_plain(y0, st, ARGS, hz)
    y_c = c_reference_run(lib, y0, ARGS, 0.01, hz.n_steps)
    rel = _rel(y_c, y_jax)
    assert np.max(rel) < 1e-4 and np.median(rel) < 1e-6, (np.max(rel), np.median(rel))


def test_wider_vectors_agree_to_rounding():
    """``vector_width=512`` (opt-in, CPU): not bitwise, but the same status and final states to
    float32 rounding."""
    y0, st = _w(_tame(2 * PLAIN_BLOCK, seed=13))
    hz = make_horizon(10.0, 0.01)
    y_def, s_def = drive_plain(y0, st, ARGS, hz)
    y_wide, s_wide = drive_plain(y0, st, ARGS, hz, vector_width=512)
    np.testing.assert_array_equal(s_wide, s_def)
    assert np.max(_rel(y_wide, y_def)) < 1e-5
