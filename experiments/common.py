"""What the scripts of both folders share: the repository's root, the machine and its load, a fresh Python process
that prints one JSON line, and a git worktree of an earlier commit to run against.

Import it from a script of ``studies/`` or ``performance/`` with

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from common import ROOT, baseline_tree, load, machine, run_py
"""
from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

#: the repository's root (the folder that holds ``jaxsleigh/`` and ``experiments/``)
ROOT = Path(__file__).resolve().parents[1]


def load() -> list:
    """The machine's load averages over 1, 5 and 15 minutes, rounded: recorded next to every timing."""
    return [round(x, 2) for x in os.getloadavg()]


def machine() -> dict:
    """What ran a figure: the architecture, the cores, Python's and JAX's versions and JAX's backend. It starts
    JAX, after giving it one CPU device per core as the command line does (`jaxsleigh.cores`)."""
    import jax

    import jaxsleigh

    jaxsleigh.cores.configure()

    return {"arch": platform.machine(), "cpu_count": os.cpu_count(), "python": platform.python_version(),
            "jax": jax.__version__, "jax_backend": jax.default_backend()}


def run_py(code: str, args=(), env=None) -> dict:
    """Run ``code`` in a fresh ``python -c`` with ``args`` and ``env`` added to this process's environment;
    returns the JSON of its last printed line (raises with its stderr's tail if it fails)."""
    # from an empty folder: `python -c` puts the working folder first on sys.path, which would shadow PYTHONPATH
    with tempfile.TemporaryDirectory() as cwd:
        r = subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True,
                           env={**os.environ, **(env or {})}, timeout=3600, cwd=cwd)
    if r.returncode != 0:
        raise RuntimeError(r.stderr[-3000:])
    return json.loads(r.stdout.strip().splitlines()[-1])


def baseline_tree(commit: str) -> Path:
    """A detached ``git worktree`` of ``commit`` in a new temporary folder (put it on ``PYTHONPATH`` to import
    that commit's jaxsleigh; remove it with ``git worktree remove --force``)."""
    d = Path(tempfile.mkdtemp(prefix="jaxsleigh_base_")) / "tree"
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-f", str(d), commit], check=True,
                   capture_output=True)
    return d
