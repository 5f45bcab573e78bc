"""The README does what it says: its Python example runs, its shell commands run as written.

Every line of the README's ``bash`` blocks is executed in a scratch directory exactly as written,
except the two ``pip install`` steps, which the test environment has already done (the quick start's
``jaxsleigh paper`` part after ``&&`` is run; the test command is the one ``.ci/run`` runs).
"""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
TEXT = README.read_text()

QUICK_START = "pip install -e . && jaxsleigh paper --out out/paper"
TEST_COMMAND = 'pip install -e ".[test]" && python -m pytest -q'


def _blocks(lang):
    return re.findall(rf"```{lang}\n(.*?)```", TEXT, re.S)


def _command_lines():
    return [ln.strip() for block in _blocks("bash") for ln in block.splitlines() if ln.strip()]


def _run(line: str, cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    """Run one README line in bash, with this interpreter's ``bin`` first on PATH (so ``jaxsleigh``
    and ``python`` are the ones installed with the package under test, as after ``pip install``)."""
    env = dict(os.environ)
    env["PATH"] = str(Path(sys.executable).parent) + os.pathsep + env.get("PATH", "")
    proc = subprocess.run(["bash", "-euo", "pipefail", "-c", line], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=timeout)
    assert proc.returncode == 0, f"README command failed (exit {proc.returncode}): {line}\n{proc.stderr[-3000:]}"
    return proc


def test_readme_python_example_runs():
    blocks = _blocks("python")
    assert len(blocks) == 1, "README should have exactly one Python example"
    # its enable_compilation_cache() turns on the cache that tests/conftest.py turned on already (the same folder,
    # the same settings), so it changes nothing for the later tests, and the example reuses the programs they kept
    # (tests/test_compilation_cache.py checks the call in a process of its own)
    exec(compile(blocks[0], "README.md", "exec"), {})


def test_readme_has_only_commands_that_are_tested():
    """Every shell line is either one of the two install commands or a command run below."""
    lines = _command_lines()
    assert lines.count(QUICK_START) == 1 and lines.count(TEST_COMMAND) == 1, lines
    for line in lines:
        if line in (QUICK_START, TEST_COMMAND):
            continue
        assert line.startswith(("jaxsleigh ", "python -c ")), f"README line is not run by the tests: {line}"


def test_readme_test_command_is_the_one_ci_runs():
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    assert TEST_COMMAND in [ln.strip() for ln in ci], ".ci/run must run the README's test command verbatim"


@pytest.mark.slow
def test_readme_quick_start_runs(tmp_path):
    """``pip install -e .`` is what produced this environment; run the rest of the line as written."""
    assert (ROOT / "pyproject.toml").exists()
    _run(QUICK_START.split(" && ", 1)[1], tmp_path)
    out = tmp_path / "out" / "paper"
    figures = sorted(p.name for p in out.glob("*.png"))
    assert figures == ["fig2_paths.png", "fig3_configuration.png", "fig4_momentum.png", "fig5_control.png",
                       "fig_hamiltonian.png"], figures
    for p in out.glob("*.png"):
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with np.load(out / "paper.npz") as run:
        assert run["q"].shape[0] == 6 and np.all(run["status"] == 0)
        hd = run["Hd"]
        assert np.all(np.diff(hd, axis=1) <= 1e-4 * hd[:, :1])       # H_d never increases


@pytest.mark.slow
def test_readme_cli_block_runs_as_written(tmp_path):
    lines = [ln for ln in _command_lines() if ln not in (QUICK_START, TEST_COMMAND)]
    assert any(ln.startswith("jaxsleigh simulate") for ln in lines)
    for line in lines:
        _run(line, tmp_path)

    with np.load(tmp_path / "run.npz") as run:                       # two starts, 100 s, every 10th step
        assert run["q"].shape == (2, 1001, 3) and np.all(run["status"] == 0)
        assert np.all(np.linalg.norm(run["q"][:, -1], axis=-1) < 0.1)
    with np.load(tmp_path / "run_tuned.npz") as run:                 # the 'tuned' preset, float64
        settings = json.loads(str(run["settings_json"]))
        assert settings["dtype"] == "float64" and np.all(run["status"] == 0)
        assert run["q"].shape[0] == 3 and np.all(np.isfinite(run["q"]))
        assert np.all(np.linalg.norm(run["q"][:, -1], axis=-1) < 0.05)   # tuned gains settle well within 100 s
    with np.load(tmp_path / "basin.npz") as b:
        assert b["T_eps"].size == 32 * 32 and np.all(b["status"] == 0)
        assert 0.0 < float(b["fraction"]) < 1.0                      # some starts settle within 100 s, some not
    assert (tmp_path / "basin.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_readme_links_resolve():
    for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", TEXT):
        if "://" in target:
            continue
        assert (ROOT / target).exists(), f"README links to {target}, which does not exist"


def test_readme_fits_on_two_screens():
    assert len(TEXT.splitlines()) <= 100, len(TEXT.splitlines())
    assert len(TEXT.split()) <= 900, len(TEXT.split())


def test_readme_comparison_quotes_the_equal_energy_command():
    """The Findings' numbers are those of ``jaxsleigh compare --equal-energy`` as committed in
    docs/figures/compare_equal_energy.json (the command the README names)."""
    d = json.loads((ROOT / "docs" / "figures" / "compare_equal_energy.json").read_text())
    assert d["command"][1:3] == ["compare", "--equal-energy"] and d["settings"]["samples"] == 256
    assert d["settings"]["dtype"] == "float32" and "jaxsleigh compare --equal-energy --out" in TEXT
    row = {(r["controller"], r["starts"]): r for r in d["rows"]}
    ast, pap, aic = row["astolfi", "uniform"], row["paper", "uniform"], row["aicardi", "uniform"]
    quoted = [f"median {ast['median_T']:.1f} s (paper: {pap['median_T']:.1f} s)",
              f"at {ast['energy_p50'] / pap['energy_p50']:.1f}x the paper's median energy",
              f"all near θ = 0 (paper: {100 * row['paper', 'near']['settled']:.0f}%)",
              f"Aicardi's in {aic['median_T']:.1f} s at {aic['energy_p50'] / pap['energy_p50']:.1f}x"]
    flat = " ".join(TEXT.split())
    for text in quoted:
        assert text in flat, text
    assert row["astolfi", "near"]["settled"] == 1.0
