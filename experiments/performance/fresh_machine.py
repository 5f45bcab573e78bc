"""What a new machine pays: the README's times, each from a fresh clone of this commit with an empty compilation cache.

    python experiments/performance/fresh_machine.py [--only quick,full,example,basin,compare] [--out FILE.json]

Every entry runs in a new process, in a new ``git clone`` of ``HEAD`` (uncommitted changes are not measured), with
``XDG_CACHE_HOME`` at a new empty folder and no ``JAX_COMPILATION_CACHE_DIR`` / ``JAXSLEIGH_CACHE_DIR``: nothing
compiled on the machine before is used, as on a machine that compiled nothing. The clone's package is imported
through ``PYTHONPATH`` by this interpreter, which must have the test extras (``pip install -e ".[test]"``).

``quick``    ``python -m pytest -q -m "not slow"`` (the quick tier; pytest's own options, two workers);
``full``     ``python -m pytest -q`` (every test: what ``.ci/run`` runs after installing);
``example``  the README's Python block, run as a script;
``basin``    the README's ``jaxsleigh basin --x -3:3:32 --y -3:3:32 --theta 0.5 --t-final 100 ...``;
``compare``  the README's ``jaxsleigh compare --equal-energy ...``.

Prints one line per entry (wall seconds, and for the tiers pytest's last line) and the machine (CPU model, cores,
load), and writes them as JSON (``--out``, default ``docs/figures/fresh_machine.json``). float32 throughout (the
README's commands and tests as written). Times stretch with the load: quote them from an idle machine.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import ROOT, load  # noqa: E402

ENTRIES = ("quick", "full", "example", "basin", "compare")
BASIN = "jaxsleigh basin --x -3:3:32 --y -3:3:32 --theta 0.5 --t-final 100 --out basin.npz --plot basin.png"
COMPARE = "jaxsleigh compare --equal-energy --out compare.json --plot compare.png"


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "unknown CPU"


def command(entry: str, clone: Path) -> list:
    """The command of ``entry``, run in ``clone``."""
    if entry == "quick":
        return [sys.executable, "-m", "pytest", "-q", "-m", "not slow", "-p", "no:cacheprovider"]
    if entry == "full":
        return [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider"]
    if entry == "example":
        block = re.findall(r"```python\n(.*?)```", (clone / "README.md").read_text(), re.S)[0]
        (clone / "readme_example.py").write_text(block)
        return [sys.executable, "readme_example.py"]
    line = {"basin": BASIN, "compare": COMPARE}[entry]
    assert line in (clone / "README.md").read_text(), f"the README no longer has: {line}"
    return [str(Path(sys.executable).parent / "jaxsleigh"), *line.split()[1:]]


def measure(entry: str) -> dict:
    """``entry`` in a fresh clone with an empty cache: its wall seconds, exit code and last line."""
    work = Path(tempfile.mkdtemp(prefix="jaxsleigh_fresh_"))
    try:
        clone = work / "clone"
        subprocess.run(["git", "clone", "-q", str(ROOT), str(clone)], check=True)
        env = {k: v for k, v in os.environ.items()
               if not k.startswith(("JAX_COMPILATION_CACHE", "JAX_PERSISTENT_CACHE", "JAXSLEIGH_"))}
        env.update(XDG_CACHE_HOME=str(work / "cache"), PYTHONPATH=str(clone), MPLBACKEND="Agg")
        t0 = time.perf_counter()
        r = subprocess.run(command(entry, clone), cwd=clone, env=env, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        lines = [ln for ln in (r.stdout + r.stderr).splitlines() if ln.strip()]
        last = next((ln for ln in reversed(lines) if re.search(r"\d+ passed|\d+ failed", ln)), lines[-1] if lines
                    else "")
        return {"wall_s": round(wall, 1), "returncode": r.returncode, "last_line": last.strip()}
    finally:
        shutil.rmtree(work, ignore_errors=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default=",".join(ENTRIES), help=f"comma-separated of {', '.join(ENTRIES)}")
    ap.add_argument("--out", default=str(ROOT / "docs" / "figures" / "fresh_machine.json"))
    a = ap.parse_args()
    only = [e.strip() for e in a.only.split(",") if e.strip()]
    bad = sorted(set(only) - set(ENTRIES))
    if bad:
        ap.error(f"unknown entries {bad}; choose from {', '.join(ENTRIES)}")
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True).stdout.strip()
    machine = {"cpu": cpu_model(), "cores": os.cpu_count()}
    print(f"{machine['cpu']}, {machine['cores']} cores, float32, commit {head}, empty compilation cache", flush=True)
    results = {}
    for entry in only:
        before = load()
        results[entry] = {**measure(entry), "load_before": before, "load_after": load()}
        r = results[entry]
        print(f"{entry:8s} {r['wall_s']:8.1f} s  exit {r['returncode']}  {r['last_line'][:100]}  (load {before[0]} -> "
              f"{r['load_after'][0]})", flush=True)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps({"command": " ".join(["python", *sys.argv]), "commit": head,
                                       "machine": machine, "dtype": "float32", "entries": results}, indent=1) + "\n")
    print(f"wrote {a.out}")
    return 0 if all(r["returncode"] == 0 for r in results.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
