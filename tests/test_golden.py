"""Golden outputs: the numbers of a handful of runs (simulate in float32 and float64, an ensemble with
the default observers, the plain fixed-step path, a basin, a sweep, three iterations of the gradient
tuner), recorded by ``tests/golden/make_golden.py`` at 2fa58a2 and re-recorded when the adaptive step
became the exponential RK4 with a PI controller in the w chart (issue 20), and again when the (w2, p1)
oscillation joined that step (issue 20, the settled phase).

Statuses must be equal, step counts equal to a step or two (at most 1% of them), floating-point results
equal to float32 rounding as a stiff run grows it (1e-4 of each field's scale), float64 runs to 1e-10 relative.
They are not bitwise: another CPU rounds XLA's transcendental functions differently (the plain path's final
states moved by 1e-5 on an AVX-512 EPYC; a float64 peak |u| by 1.2e-12 relative between that EPYC and a CPU
without AVX-512). A change of the method, the policy or the observers moves them by far more.
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


def test_golden_runs_are_unchanged(runs):
    now = {f"{run}/{field}": np.asarray(v) for run, fields in runs.items() for field, v in fields.items()}
    assert sorted(now) == sorted(GOLDEN.files)
    for key in GOLDEN.files:
        want, got = GOLDEN[key], now[key]
        assert got.shape == want.shape, key
        if np.issubdtype(want.dtype, np.integer) and not key.endswith(("n_steps", "n_rejected")):
            np.testing.assert_array_equal(got, want, err_msg=key)
        elif np.issubdtype(want.dtype, np.integer):        # step counts: a step-size decision may move
            moved = got != want
            assert moved.mean() <= 0.25, key
            np.testing.assert_allclose(got, want, rtol=0.01, atol=2, err_msg=key)
        elif want.dtype == np.float64 and "f64" in key:
            np.testing.assert_allclose(got, want, rtol=1e-10, atol=0, equal_nan=True, err_msg=key)
        else:
            finite = np.abs(want[np.isfinite(want)])
            scale = finite.max() if finite.size else 0.0
            np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4 * scale, equal_nan=True, err_msg=key)
