"""Compilation while exploring: one fresh process runs ensembles and saved trajectories at several horizons,
this tree against a baseline, and counts what it compiled.

    python experiments/performance/compile_horizons.py [--repeats 3] [--baseline 8d27cd5]
                                                       [--out docs/figures/compile_horizons.json]

The program (`EXPLORE`, public API only) is what a notebook user runs while exploring: 600 starts (20 of them
near theta = 0, so batches are compacted) at horizons of 3, 8 and 30 s and in float64 at 4 s, then trajectories
saved at 100 s (every 10 base steps), 7.3 s (every 73) and 0.5 s (every step). Each run is a new process with no
compilation cache (`JAXSLEIGH_NO_COMPILE_CACHE=1`, JAX's cache variables removed), so every program it needs is
compiled in it; JAX's own log (`JAX_LOG_COMPILES=1`) gives the programs compiled and their compile seconds. The
baseline runs from a git worktree of ``--baseline`` (PYTHONPATH), interleaved with this tree repeat by repeat, in
alternating order. Both print a SHA-256 of every output field: the trees must agree byte for byte. Prints a
Markdown table of medians and writes every run, the machine and the load average to ``--out``.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import ROOT, baseline_tree, load, machine  # noqa: E402
EXPLORE = """
import hashlib, numpy as np, jaxsleigh as js
rng = np.random.default_rng(4)
ics = np.column_stack([rng.uniform(-3, 3, (600, 2)), rng.uniform(0.3, 3, 600) * rng.choice([-1, 1], 600)])
ics[:20, 2] = np.geomspace(2e-3, 0.1, 20)
h = hashlib.sha256()
quiet = js.RunOptions(progress=False)
for t_final, x64 in [(3.0, False), (8.0, False), (30.0, False), (4.0, True)]:
    r = js.run_ensemble(ics[:100] if x64 else ics, t_final=t_final, x64=x64, run=quiet)
    for f in ("q_final", "p_final", "T_eps", "n_steps", "n_rejected", "u_energy", "status"):
        h.update(np.ascontiguousarray(getattr(r, f)).tobytes())
for t_final, every in [(100.0, 10), (7.3, 73), (0.5, 1)]:
    s = js.simulate(ics[:40], t_final=t_final, saveat=js.SaveAt(every=every), run=quiet)
    for f in ("t", "q", "p", "u", "Hd", "status", "n_steps", "T_eps", "u_energy"):
        h.update(np.ascontiguousarray(getattr(s, f)).tobytes())
print("digest", h.hexdigest())
"""
_COMPILED = re.compile(r"Finished XLA compilation of (\S+) in ([0-9.e+-]+) sec")


def explore(tree: Path) -> dict:
    """One fresh process of `EXPLORE` with ``tree`` on the path: wall time, programs compiled, compile seconds and
    the digest of its outputs."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_COMPILATION_CACHE", "JAX_PERSISTENT"))}
    env.update(JAX_PLATFORMS="cpu", JAXSLEIGH_NO_COMPILE_CACHE="1", JAX_LOG_COMPILES="1", PYTHONPATH=str(tree))
    with tempfile.TemporaryDirectory() as d:     # from an empty folder: `-c` puts it first on sys.path
        t0 = time.perf_counter()
        r = subprocess.run([sys.executable, "-c", EXPLORE], env=env, capture_output=True, text=True, cwd=d)
        wall = time.perf_counter() - t0
    if r.returncode:
        raise SystemExit(f"the program failed with {tree} on the path:\n{r.stderr[-2000:]}")
    compiled = [(name, float(s)) for name, s in _COMPILED.findall(r.stderr)]
    engine = [s for name, s in compiled if name in ("jit(_segment_batch)", "jit(_saving_batch)")]
    return {"wall_s": wall, "programs": len(compiled), "compile_s": sum(s for _, s in compiled),
            "engine_programs": len(engine), "engine_compile_s": sum(engine),
            "digest": r.stdout.split("digest", 1)[-1].strip()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--baseline", default=None, help="a git revision to measure beside this tree")
    ap.add_argument("--out", default=None, help="JSON file for every run")
    a = ap.parse_args()
    if a.repeats < 1:
        ap.error("--repeats >= 1")
    trees = {"this tree": ROOT, **({a.baseline: baseline_tree(a.baseline)} if a.baseline else {})}
    runs, loads = {t: [] for t in trees}, [load()]
    try:
        for r in range(a.repeats):          # interleaved, in alternating order: both trees see the same machine
            for t in (list(trees) if r % 2 == 0 else list(trees)[::-1]):
                runs[t].append(explore(trees[t]))
                x = runs[t][-1]
                print(f"{t}: {x['wall_s']:.1f} s, {x['programs']} programs compiled in {x['compile_s']:.1f} s",
                      file=sys.stderr)
            loads.append(load())
    finally:
        if a.baseline:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(trees[a.baseline])],
                           capture_output=True)
    same = len({x["digest"] for v in runs.values() for x in v}) == 1
    table = {t: {k: statistics.median(x[k] for x in v)
                 for k in ("wall_s", "programs", "compile_s", "engine_programs", "engine_compile_s")}
             for t, v in runs.items()}
    one_min = [x[0] for x in loads]
    print(f"{a.repeats} repeats, medians of fresh processes without a cache; {machine()}, 1-min load average "
          f"{min(one_min):.1f}-{max(one_min):.1f}; outputs {'identical in every run' if same else 'DIFFER'}\n")
    print("| tree | wall [s] | programs compiled | compile [s] | of them the engine's segments and save blocks |\n"
          "|---|---|---|---|---|")
    for t, m in table.items():
        print(f"| {t} | {m['wall_s']:.1f} | {m['programs']:.0f} | {m['compile_s']:.1f} | "
              f"{m['engine_programs']:.0f} in {m['engine_compile_s']:.1f} s |")
    if a.out:
        head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True).stdout.strip()
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps({
            "command": "python experiments/performance/compile_horizons.py " + " ".join(sys.argv[1:]), "head": head,
            "machine": machine(), "dtype": "float32 (one run in float64)", "load_average": loads,
            "identical_outputs": same, "runs": runs, "medians": table}, indent=1) + "\n")


if __name__ == "__main__":
    main()
