r"""Every core, start-up, sweeps against basins: the figures side by side in one run.

    python experiments/performance/bench_cores.py [--basin-n 100000] [--baseline 2fa58a2] [--repeats 2]
                                                  [--skip c,basin,startup,sweep] [--out docs/figures/bench_cores.json]

1. **The fixed-step path against C** (`jaxsleigh.studies.bench.c_limit`): ``run_ensemble(stepsize=StepSizeController(
   method="rk4", check_passivity=False), saveat=SaveAt(summaries=False))`` on the benchmark workload (4096 starts, 100 s, float32) against
   the hand-vectorised C RK4 on as many OpenMP threads as JAX uses cores, interleaved; wall and CPU ratios.
2. **A default basin run** of ``--basin-n`` starts (`jaxsleigh.sample_starts`, seed 0, 100 s, adaptive,
   float32) by this tree and by ``--baseline`` (a ``git worktree`` of that commit, imported through
   ``PYTHONPATH``), each in a fresh process, alternating, ``--repeats`` times; a warm-up run of 2048 other
   starts compiles first (not timed). Throughput = starts per wall second; the mean steps and a digest of
   ``T_eps`` say whether the two computed the same thing.
3. **Start-up**: two fresh processes of ``jaxsleigh simulate --ic=-3,-2,pi/8 --ic 1,1,0.5 --t-final 100``
   and of ``jaxsleigh paper`` with a new compilation-cache folder: the first compiles, the second loads.
4. **Sweeps against basins**: ``sweep`` of 8 values of ``k`` x 2048 starts against ``run_basin`` of the same
   16,384 (start, k) rows' starts, 30 s horizon, warm, in one process.

Every figure records the load average before and after it; run on an idle machine.
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

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import ROOT, baseline_tree, load, run_py  # noqa: E402

BASIN = r"""
import hashlib, json, sys, time
import numpy as np, jax, jaxsleigh as js
n = int(sys.argv[1])
where = js.__file__
# a baseline tree older than the option objects takes the keyword
quiet = {"run": js.RunOptions(progress=False)} if hasattr(js, "RunOptions") else {"progress": False}
js.run_basin(js.sample_starts(2048, seed=1), **quiet)                    # compile, not timed
starts = js.sample_starts(n, seed=0)
t0, c0 = time.perf_counter(), time.process_time()
r = js.run_basin(starts, **quiet)
w, c = time.perf_counter() - t0, time.process_time() - c0
print(json.dumps({"wall_s": w, "cpu_s": c, "starts_per_s": n / w, "devices": len(jax.devices()),
                  "settled": float(np.mean(r.converged)),
                  "mean_steps": float(np.mean(r.n_steps)),
                  "T_eps_sha": hashlib.sha256(np.ascontiguousarray(r.T_eps).tobytes()).hexdigest()[:16], "module": where}))
"""

SWEEP = r"""
import json, time
import numpy as np, jaxsleigh as js
ks = [0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0]
starts = js.sample_starts(2048, seed=0)
rows = np.tile(starts.ics, (len(ks), 1))
def sweep():
    return js.sweep(starts, {"k": ks}, t_final=30.0, run=js.RunOptions(progress=False))
def basin():
    return js.run_basin(rows, t_final=30.0, run=js.RunOptions(progress=False))
sweep(); basin()                                                          # compile
out = {"sweep_s": [], "basin_s": []}
for _ in range(3):
    for name, fn in (("sweep_s", sweep), ("basin_s", basin)):
        t0 = time.perf_counter(); fn(); out[name].append(time.perf_counter() - t0)
out["ratio"] = float(np.median(out["sweep_s"]) / np.median(out["basin_s"]))
print(json.dumps(out))
"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--basin-n", type=int, default=100_000)
    ap.add_argument("--baseline", default="2fa58a2")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--skip", default="")
    ap.add_argument("--out", default="docs/figures/bench_cores.json")
    a = ap.parse_args(argv)
    skip = set(a.skip.split(",")) - {""}
    log = lambda *m: print(*m, file=sys.stderr, flush=True)  # noqa: E731
    import jaxsleigh  # noqa: F401  (one JAX device per core)
    from jaxsleigh.cores import available_cores

    res = {"command": "python experiments/performance/bench_cores.py " + " ".join(sys.argv[1:] if argv is None else argv),
           "machine": {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
                       "cores": available_cores()},
           "dtype": "float32"}
    if "c" not in skip:
        from jaxsleigh.studies.bench import c_limit, workload

        os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
        before = load()
        c = c_limit(workload(4096, 0), repeats=5, log=log)
        if c.get("available"):
            res["fixed_vs_c"] = {k: c[k] for k in ("ratio_wall", "ratio_cpu", "c_threads", "jax_cores", "n_ics",
                                                     "steps", "jax_traj_steps_per_wall_s",
                                                     "c_traj_steps_per_wall_s")}
        else:
            res["fixed_vs_c"] = {"available": False, "reason": c.get("reason")}
        res["fixed_vs_c"]["load_before_after"] = [before, load()]
        log("fixed path / C:", json.dumps(res["fixed_vs_c"])[:400])
    if "basin" not in skip:
        base = baseline_tree(a.baseline)
        trees = {"this": ROOT, a.baseline: base}
        runs = {k: [] for k in trees}
        before = load()
        for rep in range(a.repeats):
            order = list(trees.items()) if rep % 2 == 0 else list(trees.items())[::-1]
            for name, tree in order:
                r = run_py(BASIN, [a.basin_n], env={"PYTHONPATH": str(tree)})
                runs[name].append(r)
                log(f"basin {a.basin_n} ({name}): {r['wall_s']:.1f} s, {r['starts_per_s']:.0f} starts/s, "
                    f"{r['devices']} device(s), mean steps {r['mean_steps']:.0f}")
        best = {k: max(r["starts_per_s"] for r in v) for k, v in runs.items()}
        res["basin"] = {"n": a.basin_n, "runs": runs, "speedup": best["this"] / best[a.baseline],
                        "load_before_after": [before, load()]}
        subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(base)], capture_output=True)
        log(f"basin speed-up over {a.baseline}: {res['basin']['speedup']:.2f}x")
    if "startup" not in skip:
        res["startup"] = {}
        for name, cmd in (("simulate", ["simulate", "--ic=-3,-2,pi/8", "--ic", "1,1,0.5", "--t-final", "100"]),
                          ("paper", ["paper"])):
            with tempfile.TemporaryDirectory() as d:
                walls = []
                before = load()
                for i in range(2):
                    out = Path(d) / f"out{i}"
                    args = [*cmd, "--out", str(out) + (".npz" if name == "simulate" else "")]
                    t0 = time.perf_counter()
                    subprocess.run([sys.executable, "-m", "jaxsleigh.cli", *args], check=True, capture_output=True,
                                   env={**os.environ, "JAXSLEIGH_CACHE_DIR": str(Path(d) / "cache"),
                                        "MPLBACKEND": "Agg"})
                    walls.append(time.perf_counter() - t0)
                programs = len([p for p in (Path(d) / "cache").rglob("*") if p.is_file()])
            res["startup"][name] = {"first_s": walls[0], "second_s": walls[1], "ratio": walls[0] / walls[1],
                                    "cached_programs": programs, "load_before_after": [before, load()]}
            log(f"start-up {name}: {walls[0]:.2f} s then {walls[1]:.2f} s ({walls[0] / walls[1]:.2f}x), "
                f"{programs} cached programs")
    if "sweep" not in skip:
        before = load()
        res["sweep"] = {**run_py(SWEEP), "load_before_after": [before, load()]}
        log(f"sweep 8 x 2048 / basin 16384: {res['sweep']['ratio']:.2f}")
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(res, indent=1) + "\n")
    log(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
