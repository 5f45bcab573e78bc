"""Golden outputs: the numbers of a handful of runs (simulate in float32 and float64, an ensemble with
the default observers, the plain fixed-step path, a basin, a sweep, three iterations of the gradient
tuner) are those recorded before the upper floors were rebuilt (``tests/golden/make_golden.py``, recorded at commit 2fa58a2).

Integers (status, step counts) must be equal; floating-point results equal to a few ulps (on the machine
that recorded them they are bitwise equal; another CPU may round transcendental functions differently).
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
        if np.issubdtype(want.dtype, np.integer):
            np.testing.assert_array_equal(got, want, err_msg=key)
        else:
            rtol = 1e-12 if want.dtype == np.float64 and "f64" in key else 2e-6
            np.testing.assert_allclose(got, want, rtol=rtol, atol=0, equal_nan=True, err_msg=key)
