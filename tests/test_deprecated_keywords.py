"""The fronts take their options as objects only: each keyword of jaxsleigh 0.1 given to `simulate`,
`run_ensemble`, `run_basin`, `sweep` or `optimum` is a ``TypeError`` that names the object and field that hold it
now (or says that the front has no use for it); `jaxsleigh.solve`'s ``method=`` and ``max_attempts=`` likewise name
the `StepSizeController` field. The library itself (its code, its experiments, the README, the pages and the
notebooks) passes none of them."""
from __future__ import annotations

import ast
import inspect
import json
import re
import warnings
from pathlib import Path

import numpy as np
import pytest

import jaxsleigh as js
from jaxsleigh.integrate.sampled import SAMPLED_KEYWORDS
from jaxsleigh.integrate.solve import SOLVE_KEYWORDS, solve
from jaxsleigh.tuning.event_time import SETTLING_KEYWORDS
from jaxsleigh.tuning.hard_time import HardTimeConfig
from jaxsleigh.tuning.objective import LOSS_KEYWORDS, LossConfig

ROOT = Path(__file__).resolve().parents[1]
START = np.array([[1.0, 1.0, 0.5]])
#: each keyword of jaxsleigh 0.1 and the object and field that hold it now
NOW = {**{k: ("stepsize", "StepSizeController", k) for k in ("rtol", "atol", "method", "max_steps", "max_step",
                                                             "check_passivity")},
       "save_every": ("saveat", "SaveAt", "every"), "summaries": ("saveat", "SaveAt", "summaries"),
       **{k: ("run", "RunOptions", k) for k in ("chunk_size", "segment", "devices", "cores", "checkpoint_dir",
                                                "resume", "progress", "shard")}}
OLD_KEYWORDS = frozenset(NOW)
#: the keywords each front took: its own removed ones (a call of the library with one fails), and solve's
#: deprecated ones
FRONTS = {"simulate": OLD_KEYWORDS, "run_ensemble": OLD_KEYWORDS, "run_basin": OLD_KEYWORDS,
          "sweep": OLD_KEYWORDS, "optimum": frozenset({"chunk_size", "progress", "checkpoint_dir", "resume", "shard"}),
          "solve": frozenset(SOLVE_KEYWORDS)}
#: the traced doors' removed keywords too (the library's own calls are scanned for them)
SCANNED = {**FRONTS, "settling": frozenset(SETTLING_KEYWORDS), "solve_sampled": frozenset(SAMPLED_KEYWORDS),
           "LossConfig": frozenset(LOSS_KEYWORDS), "HardTimeConfig": frozenset({"max_steps"})}
#: the fields of the objects each front has a use for (the others: "has no use for")
USED = {"simulate": {"rtol", "atol", "method", "max_steps", "max_step", "save_every", "progress"},
        "run_ensemble": set(OLD_KEYWORDS),
        "run_basin": set(OLD_KEYWORDS) - {"save_every", "summaries", "segment"},
        "sweep": set(OLD_KEYWORDS) - {"save_every", "summaries", "segment"},
        "optimum": set(FRONTS["optimum"])}


def _front(name):
    return {"simulate": js.simulate, "run_ensemble": js.run_ensemble, "run_basin": js.run_basin,
            "sweep": lambda s, **kw: js.sweep(s, ["k=0.1:0.2:2"], **kw), "optimum": js.optimum,
            "solve": lambda s, **kw: solve(js.paper_gains(), s[0], **kw)}[name]


#: a value of the right kind for each keyword (refused by its name, not by its value)
VALUE = {"rtol": 1e-7, "atol": 1e-7, "method": "rk4", "max_steps": 1000, "max_step": 0.5, "check_passivity": False,
         "save_every": 5, "summaries": False, "chunk_size": 4, "segment": 100, "devices": None, "cores": 1,
         "checkpoint_dir": None, "resume": False, "progress": False, "shard": None}


@pytest.mark.parametrize("name, keyword", [(n, k) for n in sorted(USED) for k in sorted(FRONTS[n])])
def test_each_old_keyword_is_a_type_error_naming_its_object_and_field(name, keyword):
    """Before anything runs (a horizon that cannot run would be refused next) and without a warning."""
    home, cls, field = NOW[keyword]
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        with pytest.raises(TypeError) as e:
            _front(name)(START, t_final=-1.0, **{keyword: VALUE[keyword]}) if name != "optimum" else \
                js.optimum(START, horizons=(-1.0,), **{keyword: VALUE[keyword]})
    msg = str(e.value)
    assert msg.startswith(f"{name}() got an unexpected keyword argument {keyword!r}: "), msg
    if keyword in USED[name]:
        assert f"pass {home}=jaxsleigh.{cls}({field}=...)" in msg, msg
    else:
        assert f"{name}() has no use for jaxsleigh.{cls}.{field}" in msg, msg
    assert "removed in 0.4" in msg


@pytest.mark.parametrize("call, says", [
    (lambda: js.run_basin(START, rtol=1e-6, chunk_size=4096),
     "run_basin() got unexpected keyword arguments 'rtol', 'chunk_size': pass "
     "stepsize=jaxsleigh.StepSizeController(rtol=...), run=jaxsleigh.RunOptions(chunk_size=...)"),
    (lambda: js.run_ensemble(START, progress=False, summaries=True, method="rk4", max_steps=10),
     "run_ensemble() got unexpected keyword arguments 'progress', 'summaries', 'method', 'max_steps': pass "
     "stepsize=jaxsleigh.StepSizeController(method=..., max_steps=...), saveat=jaxsleigh.SaveAt(summaries=...), "
     "run=jaxsleigh.RunOptions(progress=...)"),
    (lambda: js.simulate(START, save_every=5, chunk_size=4),
     "simulate() got unexpected keyword arguments 'save_every', 'chunk_size': pass saveat=jaxsleigh.SaveAt(every=...); "
     "simulate() has no use for jaxsleigh.RunOptions.chunk_size"),
    (lambda: js.optimum(START, chunk_size=8, resume=True),
     "optimum() got unexpected keyword arguments 'chunk_size', 'resume': pass "
     "run=jaxsleigh.RunOptions(chunk_size=..., resume=...)"),
])
def test_one_message_names_every_old_keyword_of_a_call_by_object(call, says):
    with pytest.raises(TypeError) as e:
        call()
    assert str(e.value).startswith(says), str(e.value)


@pytest.mark.parametrize("name", sorted(USED))
def test_the_fronts_take_no_loose_keywords(name):
    """No ``**options``: a keyword that is no parameter and no keyword of jaxsleigh 0.1 gets Python's own error."""
    front = getattr(js, name)
    assert not [p for p in inspect.signature(front).parameters.values() if p.kind is p.VAR_KEYWORD]
    assert "run" in inspect.signature(front).parameters
    with pytest.raises(TypeError, match=rf"^{name}\(\) got an unexpected keyword argument 'rtoll'$"):
        _front(name)(START, rtoll=1e-6)


@pytest.mark.parametrize("run, says", [
    (js.RunOptions(segment=500), "optimum() has no use for run.segment = 500"),
    (js.RunOptions(audit=False), "optimum() has no use for run.audit = False"),
    (js.RunOptions(cores=1), "optimum() has no use for run.cores = 1"),
    (js.RunOptions(chunk_size=0), "chunk_size must be a whole number >= 1"),
    ({"chunk_size": 4}, "run must be a jaxsleigh.RunOptions, got dict"),
])
def test_optimum_refuses_what_it_has_no_use_for(run, says):
    with pytest.raises(ValueError, match=re.escape(says)):
        js.optimum(START, run=run)


def test_solve_refuses_its_removed_keywords_naming_the_field():
    """Refused before anything runs (a horizon that cannot run is not what is reported)."""
    with pytest.raises(TypeError, match=re.escape(
            "solve() got unexpected keyword arguments 'method', 'max_attempts': pass stepsize=jaxsleigh."
            "StepSizeController(method=..., max_steps=...)")):
        _front("solve")(START, t_final=-1.0, method="rk4", max_attempts=50)


def _settling(**kw):
    import jax.numpy as jnp

    from jaxsleigh.tuning.event_time import settling
    return settling(js.paper_gains(), jnp.ones((1, 5)), js.paper_plant(), **kw)


def _solve_sampled(**kw):
    from jaxsleigh.controllers.actuators import Sampler
    from jaxsleigh.integrate.sampled import solve_sampled
    return solve_sampled(js.paper_gains(), None, START, t_final=1.0, sampler=Sampler(0.1), **kw)


@pytest.mark.parametrize("call, says", [
    (lambda: _settling(rtol=1e-6, atol=1e-8, max_steps=2000),
     "settling() got unexpected keyword arguments 'rtol', 'atol', 'max_steps': pass "
     "stepsize=jaxsleigh.StepSizeController(rtol=..., atol=..., max_steps=...) (settling's rtol=, atol= and "
     "max_steps= were removed in jaxsleigh 0.4)"),
    (lambda: _settling(max_steps=2000, stepsize=js.StepSizeController(max_steps=9)),
     "settling() got an unexpected keyword argument 'max_steps': pass "
     "stepsize=jaxsleigh.StepSizeController(max_steps=...)"),
    (lambda: LossConfig(t_final=5.0, rtol=1e-8, max_step=0.1),
     "LossConfig() got unexpected keyword arguments 'rtol', 'max_step': pass "
     "stepsize=jaxsleigh.StepSizeController(rtol=..., max_step=...) (LossConfig's rtol=, atol= and max_step= were "
     "removed in jaxsleigh 0.4)"),
    (lambda: HardTimeConfig(max_steps=20_000),
     "HardTimeConfig() got an unexpected keyword argument 'max_steps': pass "
     "stepsize=jaxsleigh.StepSizeController(max_steps=...)"),
    (lambda: _solve_sampled(atol=1e-8),
     "solve_sampled() got an unexpected keyword argument 'atol': pass stepsize=jaxsleigh.StepSizeController(atol=...) "
     "(solve_sampled's rtol= and atol= were removed in jaxsleigh 0.4)"),
])
def test_the_traced_doors_refuse_their_removed_keywords_naming_the_field(call, says):
    """`jaxsleigh.tuning.event_time.settling`, `jaxsleigh.integrate.sampled.solve_sampled` and the tuners'
    `jaxsleigh.tuning.LossConfig` and `HardTimeConfig` take their step policy as a `StepSizeController`, as `solve` does; refused before
    anything is traced."""
    with pytest.raises(TypeError) as e:
        call()
    assert str(e.value).startswith(says), str(e.value)


def test_settling_refuses_fixed_steps_and_a_traced_horizon_without_a_budget():
    """Its entry time is read off the adaptive step's dense output; the default budget needs t_final / dt."""
    import jax

    with pytest.raises(ValueError, match="stepsize.method must be 'adaptive'"):
        _settling(stepsize=js.StepSizeController(method="rk4"))
    with pytest.raises(ValueError, match=re.escape("give stepsize=jaxsleigh.StepSizeController(max_steps=...)")):
        jax.jit(lambda t: _settling(t_final=t).T)(1.0)


@pytest.mark.parametrize("name", sorted(FRONTS))
def test_arguments_that_are_not_options_are_taken(name):
    """``t_final``, ``dt``, ``eps``, ``x64``, ``plant``, ``gains``, ``labels`` and the objects themselves: taken, and
    checked (the horizon that cannot run is what is refused), with no warning."""
    physics = {"t_final": -1.0, "dt": 0.01, "plant": js.paper_plant(), "stepsize": js.StepSizeController(rtol=1e-7)}
    if name != "simulate":
        physics["eps"] = 0.05
    if name not in ("solve", "optimum"):
        physics.update(x64=False, gains=js.paper_gains())
    if name == "sweep":
        physics["labels"] = {"k": "--param k"}
    if name == "optimum":
        physics = {"horizons": (-1.0,), "plant": js.paper_plant(), "eps": 0.05, "run": js.RunOptions(progress=False)}
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        with pytest.raises(ValueError, match="t_final|horizons"):
            _front(name)(START, **physics)


@pytest.mark.parametrize("call, err, match", [
    (lambda: solve(js.paper_gains(), START[0], rtol=1e-6), TypeError, "unexpected keyword argument 'rtol'"),
    (lambda: solve(js.paper_gains(), START[0], max_attempts=7, stepsize=js.StepSizeController(max_steps=9)),
     TypeError, re.escape("pass stepsize=jaxsleigh.StepSizeController(max_steps=...)")),
    (lambda: solve(js.paper_gains(), START[0], stepsize={"method": "rk4"}), ValueError, "StepSizeController"),
    (lambda: solve(js.paper_gains(), START[0], stepsize=js.StepSizeController(method="euler")), ValueError,
     "stepsize.method must be 'adaptive' or 'rk4'"),
    (lambda: solve(js.paper_gains(), START[0], stepsize=js.StepSizeController(max_steps=2.5)), ValueError,
     "stepsize.max_steps must be a whole number"),
])
def test_solve_names_what_is_wrong(call, err, match):
    """An unknown keyword, a removed one, an object of the wrong kind or with a wrong field."""
    with pytest.raises(err, match=match):
        call()


def test_solve_with_a_static_stepsize_jits_and_differentiates():
    """The object is a static argument of ``jit`` (or a constant of the traced function); the gradient through
    the steps matches central differences (float64)."""
    import jax
    import jax.numpy as jnp

    ss = js.StepSizeController(method="rk4", max_steps=400)
    with jax.enable_x64(True):
        y0 = jnp.asarray([1.0, 1.0, 0.5])

        def energy(k, stepsize):
            return solve(js.paper_gains()._replace(k=k), y0, t_final=2.0, stepsize=stepsize).summaries["u_energy"]

        value = jax.jit(energy, static_argnames=("stepsize",))
        grad = jax.jit(jax.grad(energy), static_argnames=("stepsize",))(0.1, stepsize=ss)
        h = 1e-5
        fd = (value(0.1 + h, stepsize=ss) - value(0.1 - h, stepsize=ss)) / (2 * h)
    assert float(grad) != 0.0
    np.testing.assert_allclose(float(grad), float(fd), rtol=1e-6)


# ------------------------------------------------------------------------------------------------------------
# the library itself passes none
# ------------------------------------------------------------------------------------------------------------

def _calls_with_old_keywords(source: str, where: str) -> list:
    """``where:line front(keyword=...)`` for each call of a front with a keyword of `FRONTS` in ``source``; a
    ``**name`` whose dict (``name = dict(...)`` or ``{...}`` in the same source) holds one counts too."""
    tree = ast.parse(source)
    dicts = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name):
            v = node.value
            if isinstance(v, ast.Call) and isinstance(v.func, ast.Name) and v.func.id == "dict":
                dicts[node.targets[0].id] = {k.arg for k in v.keywords if k.arg}
            elif isinstance(v, ast.Dict):
                dicts[node.targets[0].id] = {k.value for k in v.keys if isinstance(k, ast.Constant)}
    found = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        f = node.func
        name = f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else None
        if name not in SCANNED:
            continue
        given = {k.arg for k in node.keywords if k.arg}
        for k in node.keywords:
            if k.arg is None and isinstance(k.value, ast.Name):
                given |= dicts.get(k.value.id, set())
        bad = sorted(given & SCANNED[name])
        if bad:
            found.append(f"{where}:{node.lineno} {name}({', '.join(b + '=' for b in bad)})")
    return found


def _sources():
    """``(where, python source)``: every module of jaxsleigh and experiments, the README's and the pages'
    python blocks, the notebooks' code cells (their IPython magics left out)."""
    for path in sorted([*(ROOT / "jaxsleigh").rglob("*.py"), *(ROOT / "experiments").rglob("*.py")]):
        yield str(path.relative_to(ROOT)), path.read_text()
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md")), *sorted((ROOT / "experiments").rglob("*.md"))]:
        for i, block in enumerate(re.findall(r"```python\n(.*?)```", path.read_text(), re.S)):
            yield f"{path.relative_to(ROOT)} (python block {i + 1})", block
    for path in sorted((ROOT / "notebooks").glob("*.ipynb")):
        for i, cell in enumerate(json.loads(path.read_text())["cells"]):
            if cell["cell_type"] == "code":
                lines = "".join(cell["source"]).splitlines()
                yield f"{path.relative_to(ROOT)} (cell {i})", "\n".join(
                    ln for ln in lines if not ln.lstrip().startswith(("%", "!")))


def test_the_scan_finds_what_it_should():
    code = ("RUN = dict(t_final=1.0, chunk_size=4)\nGOOD = dict(t_final=1.0)\n"
            "js.sweep(s, p, **RUN)\njs.sweep(s, p, **GOOD)\nrun_basin(s, progress=False)\n"
            "solve(g, y, method='rk4')\nsolve(g, y, stepsize=ss)\nsettling(c, y, p, rtol=1e-9)\nsimulate(s, t_final=1.0, dt=0.01, x64=True)\n"
            "m.run_ensemble(s, run=RunOptions(chunk_size=4), stepsize=StepSizeController(method='rk4'))\n")
    assert _calls_with_old_keywords(code, "x") == ["x:3 sweep(chunk_size=)", "x:5 run_basin(progress=)",
                                                   "x:6 solve(method=)", "x:8 settling(rtol=)"]


def test_no_code_or_page_of_the_library_passes_a_deprecated_keyword():
    sources = list(_sources())
    assert any(w.startswith("notebooks") for w, _ in sources) and any("README" in w for w, _ in sources)
    found = [hit for where, source in sources for hit in _calls_with_old_keywords(source, where)]
    assert not found, "pass the option objects instead:\n" + "\n".join(found)
