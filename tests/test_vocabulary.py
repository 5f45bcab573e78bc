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


# ------------------------------------------------------------------------------------------------------------
# one name for one quantity, one quantity for one name, across every public result type
# ------------------------------------------------------------------------------------------------------------

#: each quantity the results report: its one name, and names it went by in some result before (none may return)
QUANTITIES = {
    "accepted steps": ("n_steps", {"n_accept", "n_accepted"}),
    "rejected steps": ("n_rejected", {"n_reject"}),
    "settling time": ("T_eps", {"T", "settling_time", "t_settle"}),
    "median settling time": ("median_T", {"median", "median_T_eps", "median_time"}),
    "time reached": ("t_reached", {"t_end"}),
    "control energy": ("u_energy", {"energy_u", "effort_energy"}),
    "the starts": ("starts", {"ics0", "y0s"}),
}


def _result_types():
    """Every public result type: the NamedTuples and dataclasses of `jaxsleigh` and `jaxsleigh.tuning` whose name says
    it holds results."""
    import dataclasses
    import inspect
    import re

    from jaxsleigh import tuning

    found = {}
    for mod in (js, tuning):
        for name in getattr(mod, "__all__", None) or [n for n in dir(mod) if not n.startswith("_")]:
            obj = getattr(mod, name, None)
            if (inspect.isclass(obj) and (hasattr(obj, "_fields") or dataclasses.is_dataclass(obj))
                    and re.search(r"Result|Output|Solution|Summary|Validation|Figures|Point|Front", name)):
                found[name] = obj
    return found


def _names(cls) -> dict:
    """name -> what it is (``field``, ``property``, ``method``) of a result type."""
    import dataclasses

    out = {f: "field" for f in getattr(cls, "_fields", ())}
    if dataclasses.is_dataclass(cls):
        out.update({f.name: "field" for f in dataclasses.fields(cls)})
    for klass in cls.__mro__:
        if klass.__module__.startswith("jaxsleigh"):
            for k, v in vars(klass).items():
                if not k.startswith("_") and k not in out:
                    out[k] = "property" if isinstance(v, property) else "method" if callable(v) else "attribute"
    return out


def test_the_result_types_are_the_ones_this_test_knows():
    """A new public result type is read by the checks below: the list is found, not written by hand; it has at least
    the trajectory sets and the studies on them."""
    assert {"SolveOutput", "Solution", "EnsembleResult", "BasinResult", "SweepResult", "OptimumResult",
            "LaneSummary", "Validation"} <= set(_result_types())


@pytest.mark.parametrize("quantity", sorted(QUANTITIES))
def test_no_result_calls_a_quantity_by_another_name(quantity):
    name, others = QUANTITIES[quantity]
    used = {t: sorted(others & set(_names(cls))) for t, cls in _result_types().items()}
    used = {t: n for t, n in used.items() if n}
    assert not used, f"{quantity} is {name!r} in every result; {used} call it otherwise"


def test_converged_means_settled_wherever_it_is_a_name():
    """``converged``: ended OK and settled in the ball within the horizon, per start: only on results that have the
    start's ``status`` and ``T_eps``, never a method (an optimiser's convergence is another quantity)."""
    bad = {t: kind for t, cls in _result_types().items() for n, kind in _names(cls).items()
           if n == "converged" and (kind == "method" or not {"status", "T_eps"} <= set(_names(cls)))}
    assert not bad, f"'converged' means something else in {bad}"


def test_t_is_the_save_times_wherever_it_is_a_name():
    """``t``: the times a trajectory was saved at, beside the states ``q`` there (the time a run reached is
    ``t_reached``)."""
    bad = [t for t, cls in _result_types().items() if "t" in _names(cls) and "q" not in _names(cls)]
    assert not bad, f"'t' without a trajectory in {bad}: the time reached is t_reached"
