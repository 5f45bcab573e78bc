"""Start-up: the first and the second fresh process of the README's commands, this tree against a baseline.

    python experiments/performance/compile_cache.py [--repeats 3] [--baseline f036c14] [--commands simulate,basin,x64]
                                                    [--out docs/figures/compile_cache.json]

Each run is a new process (`python -m jaxsleigh.cli ...`) with an empty cache folder for the first and the
same, now warm, folder for the second (JAXSLEIGH_CACHE_DIR in a temporary folder: nothing of this machine's own
cache is used). The baseline runs from a git worktree of ``--baseline`` (PYTHONPATH), interleaved with this
tree repeat by repeat, in alternating order, so that both see the same machine. Prints a Markdown table of
median wall times and writes every run, the machine and the load average to ``--out``.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
COMMANDS = {
    "simulate": ["simulate", "--ic=-3,-2,pi/8", "--ic", "1,1,0.5", "--t-final", "100", "--dt", "0.01",
                 "--save-every", "10", "--out", "{d}/run.npz"],
    "x64": ["simulate", "--ic=-3,-2,pi/8", "--ic", "1,1,0.5", "--t-final", "100", "--x64", "--out", "{d}/run.npz"],
    "basin": ["basin", "--x", "-3:3:32", "--y", "-3:3:32", "--theta", "0.5", "--t-final", "100",
              "--out", "{d}/basin.npz"],
    "paper": ["paper", "--out", "{d}/paper"],
}


def timed(args, env, cwd) -> float:
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, *args], env=env, capture_output=True, text=True, cwd=cwd)
    if r.returncode:
        raise SystemExit(f"{' '.join(args)} failed:\n{r.stderr[-2000:]}")
    return time.perf_counter() - t0


def pair(tree: Path, cmd: list) -> tuple:
    """(first, second) fresh-process wall times of ``cmd`` with ``tree`` on the path, sharing a new cache."""
    with tempfile.TemporaryDirectory() as d:
        env = {**os.environ, "JAX_PLATFORMS": "cpu", "JAXSLEIGH_CACHE_DIR": os.path.join(d, "cache"),
               "MPLBACKEND": "Agg", "PYTHONPATH": str(tree)}
        env.pop("JAXSLEIGH_NO_COMPILE_CACHE", None)
        args = ["-m", "jaxsleigh.cli", *(c.replace("{d}", d) for c in cmd)]
        # from the empty folder: `python -m` puts the working folder first on sys.path, before PYTHONPATH
        return timed(args, env, d), timed(args, env, d)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--baseline", default=None, help="a git revision to measure beside this tree")
    ap.add_argument("--commands", default="simulate,basin,x64", help=f"of {', '.join(COMMANDS)}")
    ap.add_argument("--out", default=None, help="JSON file for every run")
    a = ap.parse_args()
    names = [c.strip() for c in a.commands.split(",") if c.strip()]
    unknown = sorted(set(names) - set(COMMANDS))
    if unknown or a.repeats < 1:
        ap.error(f"unknown commands {unknown} (known: {', '.join(COMMANDS)})" if unknown else "--repeats >= 1")
    trees = {"this tree": ROOT}
    tmp = None
    if a.baseline:
        tmp = tempfile.mkdtemp()
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", f"{tmp}/base", a.baseline],
                       check=True, capture_output=True)
        trees[a.baseline] = Path(tmp) / "base"
    runs = {t: {n: [] for n in names} for t in trees}
    loads = [os.getloadavg()[0]]
    try:
        for r in range(a.repeats):
            for n in names:
                order = list(trees) if r % 2 == 0 else list(trees)[::-1]
                for t in order:
                    runs[t][n].append(pair(trees[t], COMMANDS[n]))
                    print(f"{n} ({t}): {runs[t][n][-1][0]:.2f} s then {runs[t][n][-1][1]:.2f} s", file=sys.stderr)
            loads.append(os.getloadavg()[0])
    finally:
        if tmp:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", f"{tmp}/base"],
                           capture_output=True)
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True).stdout.strip()
    print(f"{a.repeats} repeats, median wall [s] of fresh processes; {platform.machine()}, "
          f"os.cpu_count() = {os.cpu_count()}, 1-min load average {min(loads):.1f}-{max(loads):.1f}\n")
    print("| command | tree | first | second | first / second |\n|---|---|---|---|---|")
    table = {}
    for n in names:
        for t in trees:
            first = statistics.median(x[0] for x in runs[t][n])
            second = statistics.median(x[1] for x in runs[t][n])
            table[f"{n} | {t}"] = {"first_s": first, "second_s": second, "ratio": first / second}
            print(f"| `jaxsleigh {' '.join(COMMANDS[n][:1])}` ({n}) | {t} | {first:.2f} | {second:.2f} | "
                  f"**{first / second:.2f}x** |")
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps({
            "command": "python experiments/performance/compile_cache.py " + " ".join(sys.argv[1:]), "head": head,
            "machine": f"{platform.machine()} {platform.processor()}".strip(), "cpu_count": os.cpu_count(),
            "load_average_1min": loads, "commands": {n: "jaxsleigh " + " ".join(COMMANDS[n]) for n in names},
            "runs": {t: {n: [list(x) for x in v] for n, v in d.items()} for t, d in runs.items()},
            "medians": table}, indent=1) + "\n")


if __name__ == "__main__":
    main()
