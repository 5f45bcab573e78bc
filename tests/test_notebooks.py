"""The notebooks are committed executed (the docs show their outputs), and they still run and still
produce those outputs.

* Fast checks on the committed files: every code cell was run, top to bottom in one session, with no
  error; the figures are there; the key printed results are there.
* ``@slow``: each notebook is executed again from scratch in a fresh ``python3`` kernel with
  ``nbclient`` (working directory ``notebooks/``); every cell must produce the same kinds of output as
  the committed one (the same number of figures, printed text where there was printed text), and
  the key results must hold again. New notebooks are picked up by the glob and need an entry in
  ``KEY_RESULTS``.

To refresh the committed outputs after a change:
``jupyter nbconvert --to notebook --execute --inplace notebooks/*.ipynb``.
"""
from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))
TIMEOUT_S = 600          # per cell; a whole notebook takes one to three minutes from a fresh kernel on 2 cores


def _float(pattern, text):
    m = re.search(pattern, text)
    assert m, f"no match for {pattern!r} in the notebook's printed output"
    return [float(g) for g in m.groups()]


def _paper(text):
    rise, = _float(r"largest relative increase of H_d between samples: (\S+)", text)
    assert rise < 1e-4                                     # H_d does not increase (eq. 18)
    assert len(re.findall(r"H_d\(0\) = +[\d.e+]+ +T_eps = ", text)) == 6   # the six paper starts
    t_ratio, e_ratio = _float(r"time ratio T_eps / T\*\(E\) >?= (\S+), energy ratio E / E\*\(T_eps\) >?= (\S+)", text)
    assert t_ratio >= 1.0 and e_ratio >= 1.0                # no feedback law beats the open-loop optimum


def _singular(text):
    e11, = _float(r"\(1, 1\): H_d\(0\) ~ \S+ theta0\^\((-?[\d.]+) \+-", text)
    e10, = _float(r"\(1, 0\): H_d\(0\) ~ \S+ theta0\^\((-?[\d.]+) \+-", text)
    assert -4.1 < e11 < -3.95 and -2.05 < e10 < -1.95       # H_d(0) ~ theta0^-4, and ^-2 on y0 = 0
    assert "status 4 BUDGET_EXHAUSTED" in text and "status 0 OK" in text


def _basins(text):
    assert "identical files: True" in text                 # a resumed run writes the same bytes
    s, se = _float(r"S = ([\d.]+) \+- ([\d.]+)", text)
    assert 0.5 < s < 1.0 and 0 < se < 0.05


def _tuning(text):
    before, after = _float(r"loss ([\d.]+) -> ([\d.]+); valid candidates", text)
    assert after <= before
    fwd_rev = re.findall(r"loss (\S+) \(forward\) (\S+) \(reverse\)", text)
    assert fwd_rev and float(fwd_rev[0][0]) == pytest.approx(float(fwd_rev[0][1]), rel=1e-5)


def _floats(pattern, text):
    """The numbers (``nan`` included) of the line that ``pattern`` starts."""
    m = re.search(pattern + r"(.*)", text)
    assert m, f"no match for {pattern!r} in the notebook's printed output"
    return [float(v) for v in re.findall(r"nan|[-+]?[\d.]+(?:e[-+]?\d+)?", m.group(1))]


def _sweeps(text):
    import numpy as np

    S = np.array(_floats(r"fraction converged against k: ", text))
    T = np.array(_floats(r"median T_eps against k: ", text))
    assert S.size == T.size == 7 and np.all((S >= 0) & (S <= 1))
    assert np.all(np.diff(S) <= 0.05)                      # fewer settle within T as k grows ...
    assert S[0] >= 0.9 and S[-1] <= 0.1                    # ... all at small k, (almost) none at k = 1
    t = T[np.isfinite(T)]
    assert t.size >= 5 and np.all(np.diff(t) > 0)          # and those that do settle later
    assert np.all(np.isnan(T[S == 0]))
    knife = np.array(_floats(r"knife edge l = 0: fraction converged ", text))
    assert knife.size == 4 and np.all(knife >= 0.9)        # the knife edge converges like l > 0
    lo, hi = _float(r"l > 0: fraction converged ([\d.]+) \.\. ([\d.]+); every start status OK: True", text)
    assert 0.8 <= lo <= hi <= 1
    e = np.array(_floats(r"median control energy at m = \S+ kg against l: ", text))
    assert e.size == 5 and np.all(e > 0) and e[-1] > 5 * e[0]   # a large offset costs more effort
    plants = [float(v) for v in re.findall(r"eps [\d.]+:  S = ([\d.]+) \+-", text)]
    assert len(plants) == 8 and all(0 <= v <= 1 for v in plants)
    assert plants[0] >= 0.9 and plants[-1] <= 0.5           # sorted by friction: strong friction degrades
    assert "sampled plants: every start status OK: True" in text


#: what each notebook must print (its own print statements, not the library's wording)
KEY_RESULTS = {
    "01_paper_reproduction.ipynb": _paper,
    "02_singular_set.ipynb": _singular,
    "03_basins.ipynb": _basins,
    "04_gain_tuning.ipynb": _tuning,
    "05_parameter_sweeps.ipynb": _sweeps,
}


def _code_cells(nb):
    return [c for c in nb.cells if c.cell_type == "code"]


def _signature(nb):
    """Per code cell: (figures, printed something on stdout, errors)."""
    sig = []
    for cell in _code_cells(nb):
        outs = cell.get("outputs", [])
        sig.append((sum("image/png" in o.get("data", {}) for o in outs),
                    any(o.output_type == "stream" and o.name == "stdout" for o in outs),
                    sum(o.output_type == "error" for o in outs)))
    return sig


def _stdout(nb):
    return "".join(o.text for c in _code_cells(nb) for o in c.get("outputs", [])
                   if o.output_type == "stream" and o.name == "stdout")


def test_every_notebook_has_key_results():
    assert len(NOTEBOOKS) >= 4
    assert sorted(KEY_RESULTS) == [p.name for p in NOTEBOOKS]


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_is_committed_executed(path):
    nbformat = pytest.importorskip("nbformat")
    nb = nbformat.read(path, as_version=4)
    cells = _code_cells(nb)
    counts = [c.execution_count for c in cells]
    assert counts == list(range(1, len(cells) + 1)), \
        f"{path.name}: not executed top to bottom in one session (execution counts {counts}); re-execute it"
    sig = _signature(nb)
    assert not any(err for *_, err in sig), f"{path.name} is committed with an error output"
    assert sum(n for n, *_ in sig) >= 1, f"{path.name} is committed without figures"
    for c in cells:
        for o in c.outputs:
            if o.output_type == "stream" and o.name == "stderr":
                assert "Traceback" not in o.text, f"{path.name}: a traceback on stderr"
    KEY_RESULTS[path.name](_stdout(nb))


def _why_not_runnable():
    for mod in ("nbclient", "nbformat", "ipykernel"):
        if importlib.util.find_spec(mod) is None:
            return f"{mod} is not installed (pip install -e '.[test]' installs it)"
    from jupyter_client.kernelspec import KernelSpecManager, NoSuchKernel

    try:
        KernelSpecManager().get_kernel_spec("python3")
    except NoSuchKernel:
        return "no 'python3' Jupyter kernel (python -m ipykernel install --user)"
    return None


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_runs_and_reproduces_its_outputs(path):
    why = _why_not_runnable()
    if why:
        pytest.skip(why)
    import nbformat
    from nbclient import NotebookClient

    committed = nbformat.read(path, as_version=4)
    fresh = nbformat.read(path, as_version=4)
    for cell in _code_cells(fresh):
        cell.outputs, cell.execution_count = [], None
    NotebookClient(fresh, timeout=TIMEOUT_S, kernel_name="python3", record_timing=False,
                   resources={"metadata": {"path": str(path.parent)}}).execute()
    got, want = _signature(fresh), _signature(committed)
    diff = [(i, g, w) for i, (g, w) in enumerate(zip(got, want)) if g != w]
    assert not diff, (f"{path.name}: outputs differ from the committed ones (code cell, (figures, stdout, "
                      f"errors) now, committed): {diff}; re-execute the notebook and commit it")
    KEY_RESULTS[path.name](_stdout(fresh))
