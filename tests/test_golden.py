"""Golden outputs: the numbers of a handful of runs (simulate in float32 and float64, an ensemble with
the default observers, the plain fixed-step path, a basin, a sweep, three iterations of the gradient
tuner), recorded by ``tests/golden/make_golden.py`` and re-recorded only for a documented change of arithmetic
(the exponential RK4 step with a PI controller in the w chart; the settled phase's (w2, p1) oscillation in that step;
the tuner's control energy by the engine's RK4-weighted quadrature instead of a trapezoid sum: ``tune/energy`` only,
0.5% lower, the tuner's gains and losses unchanged).

They must hold on every x86-64 CPU, so they are bitwise only where the arithmetic is: statuses equal; step counts
within a step or two (1%) per lane and 0.5% in total; float32 results within 1e-4 relative plus 3e-4 of each field's
scale, the run's own accuracy (on an AVX-512 Xeon the basin's start (-2, -2, 0.5), still on its way at 20 s, ends
with p2 -0.125795 against the recorded -0.125738, 1.6e-4 of the field's scale apart, and both within 1.2e-4 of a
float64 run at rtol = atol = 1e-10, -0.125680); float64 runs within 1e-10 relative. XLA:CPU's code depends on the instruction set
(vector width, FMA, the polynomial of each transcendental): on an AVX-512 EPYC the plain path's final states moved
by 1e-5 and a float64 peak |u| by 1.2e-12 relative; compiled for SSE4.2 only
(``XLA_FLAGS=--xla_cpu_max_isa=SSE4_2``), two of simulate_f32's three step counts move by two steps.
`test_golden_runs_hold_on_another_instruction_set` reruns them so. A change of the method, the policy or the
observers moves them by far more (`test_the_tolerances_catch_a_changed_method`).
"""
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent / "golden"))
from make_golden import golden_runs  # noqa: E402

GOLDEN = np.load(Path(__file__).parent / "data" / "golden.npz")


@pytest.fixture(scope="module")
def runs():
    return golden_runs()


def _mismatch(key: str, want: np.ndarray, got: np.ndarray):
    """Why ``got`` differs from the golden ``want`` beyond the stated tolerances, or ``None``."""
    if got.shape != want.shape:
        return f"shape {got.shape} != {want.shape}"
    try:
        if np.issubdtype(want.dtype, np.integer) and not key.endswith(("n_steps", "n_rejected")):
            np.testing.assert_array_equal(got, want)
        elif np.issubdtype(want.dtype, np.integer):
            # step counts: a step-size decision near the acceptance threshold may go the other way on another
            # instruction set (SSE4.2 moved 2 of 3 lanes of simulate_f32 by 2 steps); each lane within a step or
            # two (1%), the total within 0.5%: a change of method or policy moves them by far more
            np.testing.assert_allclose(got, want, rtol=0.01, atol=2)
            assert abs(int(got.sum()) - int(want.sum())) <= 0.005 * int(want.sum()) + 2, "total steps moved"
        elif want.dtype == np.float64 and "f64" in key:
            np.testing.assert_allclose(got, want, rtol=1e-10, atol=0, equal_nan=True)
        else:
            finite = np.abs(want[np.isfinite(want)])
            scale = finite.max() if finite.size else 0.0
            np.testing.assert_allclose(got, want, rtol=1e-4, atol=3e-4 * scale, equal_nan=True)
    except AssertionError as e:
        return str(e).strip().splitlines()[-1] if str(e).strip() else "differs"
    return None


def test_golden_runs_are_unchanged(runs):
    now = {f"{run}/{field}": np.asarray(v) for run, fields in runs.items() for field, v in fields.items()}
    assert sorted(now) == sorted(GOLDEN.files)
    moved = {key: why for key in GOLDEN.files if (why := _mismatch(key, GOLDEN[key], now[key])) is not None}
    assert not moved, "golden outputs moved beyond their tolerances:\n" + "\n".join(f"{k}: {v}" for k, v in moved.items())


def test_the_tolerances_catch_a_changed_method():
    """The rule is not vacuous: a step count off by 3%, a float32 state off by 1e-3 of its scale, a float64 one by
    1e-9, a status changed, each fails it."""
    steps = GOLDEN["ensemble/n_steps"]
    assert _mismatch("ensemble/n_steps", steps, (steps * 1.03).astype(steps.dtype)) is not None
    q = GOLDEN["ensemble/q"]
    assert _mismatch("ensemble/q", q, q + 1e-3 * np.abs(q).max()) is not None
    q64 = GOLDEN["simulate_f64/q"]
    assert _mismatch("simulate_f64/q", q64, q64 * (1 + 1e-9)) is not None
    status = GOLDEN["basin/status"]
    assert _mismatch("basin/status", status, status + 1) is not None
    assert _mismatch("ensemble/n_steps", steps, steps) is None


@pytest.mark.slow
def test_golden_runs_hold_on_another_instruction_set(tmp_path):
    """The same runs compiled for another instruction set (SSE4.2: no AVX, no FMA, narrower vectors, other
    polynomials), in a fresh process: within the same tolerances. CI's machines differ in exactly this way."""
    import os
    import subprocess

    out = tmp_path / "golden_sse42.npz"
    code = ("import sys, numpy as np; sys.path[:0] = [sys.argv[2], sys.argv[3]]; from make_golden import golden_runs; "
            "r = golden_runs(); np.savez(sys.argv[1], **{f'{k}/{f}': np.asarray(v) for k, fs in r.items() "
            "for f, v in fs.items()})")
    here = Path(__file__).parent
    env = {**os.environ, "XLA_FLAGS": (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_max_isa=SSE4_2").strip(),
           "JAX_PLATFORMS": "cpu"}
    subprocess.run([sys.executable, "-c", code, str(out), str(here / "golden"), str(here)], check=True, env=env,
                   timeout=900)
    other = np.load(out)
    moved = {key: why for key in GOLDEN.files if (why := _mismatch(key, GOLDEN[key], other[key])) is not None}
    assert not moved, "moved on SSE4.2:\n" + "\n".join(f"{k}: {v}" for k, v in moved.items())
