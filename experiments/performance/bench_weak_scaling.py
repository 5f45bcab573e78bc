"""Weak scaling of basin runs on P local Dask workers, each with the same share of starts.

For every P in --procs it runs ``jaxsleigh basin --samples P*W --workers P`` (P = 1 is a plain single-process
run, without workers) and times it from launch to its exit (start-up, the workers' start and compilation,
integration, assembly and the .npz).
Weak-scaling efficiency per process: E(P) = T(1) / T(P) (1 = perfect: P times the work in the same
time). Also the throughput in starts/s and the machine's load average before and after.

    python experiments/performance/bench_weak_scaling.py --per-process 4096 --t-final 20 --procs 1,2,4 \
        --json out/weak_scaling.json

On a machine with C cores, P > C processes share the cores, so E(P) can be at most about C / P.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def run(p: int, per: int, t_final: float, chunk: int, folder: Path, method: str) -> dict:
    out = folder / f"weak_p{p}.npz"
    base = [sys.executable, "-m", "jaxsleigh.cli", "basin", "--samples", str(p * per), "--seed", "1",
            "--t-final", str(t_final), "--chunk-size", str(chunk), "--method", method, "--out", str(out)]
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    cmds = [base] if p == 1 else [base + ["--workers", str(p)]]
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    procs = [subprocess.Popen(c, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for c in cmds]
    res = [pr.communicate() for pr in procs]
    wall = time.perf_counter() - t0
    for pr, (o, e) in zip(procs, res):
        if pr.returncode not in (0, 3):
            raise SystemExit(f"P={p}: a process exited {pr.returncode}\n{o}\n{e[-2000:]}")
    info = json.loads(out.with_name(out.stem + ".run.json").read_text())
    return {"processes": p, "starts": p * per, "wall_s": wall, "process0_wall_s": info["wall_s"],
            "starts_per_s": p * per / wall, "loadavg_before": [round(v, 2) for v in load0],
            "loadavg_after": [round(v, 2) for v in os.getloadavg()]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--per-process", type=int, default=4096, help="starts per process (default 4096)")
    ap.add_argument("--t-final", type=float, default=20.0, help="horizon in s (default 20)")
    ap.add_argument("--chunk-size", type=int, default=512, help="chunk size (default 512)")
    ap.add_argument("--method", default="adaptive", choices=["adaptive", "rk4"])
    ap.add_argument("--procs", default="1,2,4", help="process counts (default 1,2,4)")
    ap.add_argument("--repeats", type=int, default=1, help="runs per process count; the fastest is kept")
    ap.add_argument("--json", help="write the results here")
    a = ap.parse_args(argv)
    procs = [int(s) for s in a.procs.split(",")]
    rows = []
    with tempfile.TemporaryDirectory() as d:
        folder = Path(d)
        run(1, 64, a.t_final, a.chunk_size, folder, a.method)           # fill process 0's compilation cache
        for p in procs:
            best = min((run(p, a.per_process, a.t_final, a.chunk_size, folder, a.method) for _ in range(a.repeats)),
                       key=lambda r: r["wall_s"])
            rows.append(best)
            print(f"P={p}: {best['starts']} starts in {best['wall_s']:.1f} s ({best['starts_per_s']:.0f} starts/s; "
                  f"load {best['loadavg_before'][0]} -> {best['loadavg_after'][0]})", flush=True)
    t1 = next((r["wall_s"] for r in rows if r["processes"] == 1), None)
    for r in rows:
        r["efficiency"] = None if t1 is None else t1 / r["wall_s"]
    print("\n| processes | starts | wall [s] | starts/s | efficiency per process T(1)/T(P) |")
    print("|---|---|---|---|---|")
    for r in rows:
        eff = "" if r["efficiency"] is None else f"{r['efficiency']:.2f}"
        print(f"| {r['processes']} | {r['starts']} | {r['wall_s']:.1f} | {r['starts_per_s']:.0f} | {eff} |")
    result = {"per_process": a.per_process, "t_final": a.t_final, "chunk_size": a.chunk_size, "method": a.method,
              "cpu_count": os.cpu_count(), "machine": platform.platform(), "processor": platform.processor(),
              "rows": rows}
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
