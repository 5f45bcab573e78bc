"""One vocabulary: every trajectory front's result carries the same names for the same things, and they agree."""
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsleigh as js
from jaxsleigh import RunOptions, StepSizeController

#: what every result of simulate, run_ensemble, run_basin, sweep and solve carries
NAMES = ("q_final", "p_final", "status", "converged", "T_eps", "u_energy", "Hd0", "Hd_final", "n_steps", "n_rejected",
         "run_info")
STARTS = np.array([[1.0, 1.0, 0.5], [-1.0, 2.0, 1.0]])


@pytest.fixture(scope="module")
def results():
    kw = dict(t_final=20.0)
    return {
        "simulate": js.simulate(STARTS, **kw),
        "run_ensemble": js.run_ensemble(STARTS, **kw),
        "run_basin": js.run_basin(STARTS, **kw),
        "sweep": js.sweep(STARTS, {"k": np.array([0.1])}, **kw, run=RunOptions(progress=False)),
        "solve": [js.solve(js.paper_gains(), jnp.asarray(y), stepsize=StepSizeController(), **kw) for y in STARTS],
    }


@pytest.mark.parametrize("front", ["simulate", "run_ensemble", "run_basin", "sweep", "solve"])
def test_every_front_carries_the_common_names(results, front):
    for res in (results[front] if front == "solve" else [results[front]]):
        missing = [n for n in NAMES if not hasattr(res, n)]
        assert not missing, f"{front}'s {type(res).__name__} lacks {missing}"
        assert all(getattr(res, n) is not None for n in NAMES if n != "run_info")


def test_the_common_names_mean_the_same_in_every_front(results):
    ens = results["run_ensemble"]
    rows = {"simulate": results["simulate"], "run_basin": results["run_basin"]}
    sw = results["sweep"]
    solved = results["solve"]
    for name in ("q_final", "p_final", "T_eps", "u_energy", "Hd0", "Hd_final"):
        want = np.asarray(getattr(ens, name), np.float64)
        for front, res in rows.items():
            np.testing.assert_allclose(np.asarray(getattr(res, name), np.float64), want, rtol=2e-3, atol=1e-4,
                                       err_msg=f"{front}.{name}")
        np.testing.assert_allclose(np.asarray(getattr(sw, name), np.float64)[0], want, rtol=2e-3, atol=1e-4,
                                   err_msg=f"sweep.{name}")
        got = np.stack([np.asarray(getattr(o, name), np.float64) for o in solved])
        np.testing.assert_allclose(got, want, rtol=2e-3, atol=1e-4, err_msg=f"solve.{name}")
    for name in ("status", "converged"):
        want = np.asarray(getattr(ens, name))
        assert np.array_equal(np.asarray(getattr(sw, name))[0], want)
        assert np.array_equal(np.stack([np.asarray(getattr(o, name)) for o in solved]), want)
    assert np.array_equal(results["simulate"].t_reached, np.full(2, 20.0))
