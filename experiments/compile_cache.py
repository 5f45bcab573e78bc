"""First and second fresh-process run of the README's `simulate` example, with JAX's persistent
compilation cache (which the command line turns on) and without it.

    python experiments/compile_cache.py [--repeats 3]

Each run is a new process (`python -m jaxsleigh.cli simulate ...`) with an empty or a warm cache in
a temporary folder (JAXSLEIGH_CACHE_DIR), so nothing of this machine's own cache is used. Prints
a Markdown table of wall times (median of the repeats) and the import time of jaxsleigh alone.
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time

CMD = ["simulate", "--ic=-3,-2,pi/8", "--ic", "1,1,0.5", "--t-final", "100", "--dt", "0.01", "--save-every", "10"]


def timed(args, env) -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, *args], env=env, check=True, capture_output=True)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args()
    rows = {"import jaxsleigh (no work)": [], "cache off": [], "cache on, first process (empty cache)": [],
            "cache on, second process (warm cache)": []}
    for _ in range(a.repeats):
        with tempfile.TemporaryDirectory() as d:
            env = {**os.environ, "JAX_PLATFORMS": "cpu", "JAXSLEIGH_CACHE_DIR": os.path.join(d, "cache")}
            out = ["--out", os.path.join(d, "run.npz")]
            rows["import jaxsleigh (no work)"].append(timed(["-c", "import jaxsleigh"], env))
            rows["cache off"].append(timed(["-m", "jaxsleigh.cli", "--no-compile-cache", *CMD, *out], env))
            rows["cache on, first process (empty cache)"].append(timed(["-m", "jaxsleigh.cli", *CMD, *out], env))
            rows["cache on, second process (warm cache)"].append(timed(["-m", "jaxsleigh.cli", *CMD, *out], env))
    print(f"`jaxsleigh {' '.join(CMD)} --out run.npz`, {a.repeats} repeats, median wall [s], "
          f"os.cpu_count() = {os.cpu_count()}\n")
    print("| run | wall [s] | all repeats |\n|---|---|---|")
    for k, v in rows.items():
        print(f"| {k} | {statistics.median(v):.2f} | {', '.join(f'{x:.2f}' for x in v)} |")
    first, second = (statistics.median(rows[k]) for k in list(rows)[2:])
    print(f"\nsecond / first fresh process: {second / first:.2f} ({first / second:.1f}x faster)")


if __name__ == "__main__":
    main()
