r"""The stiff stragglers of a basin on a GPU: what one adaptive loop iteration costs when the batch is small.

    python experiments/performance/gpu_tail.py [--n 1024] [--t-final 10] [--variants default,no_graphs,graph_loops,cpu]
                                               [--out out/gpu_tail.json]

A default basin of 10^6 starts (`jaxsleigh.sample_starts`, seed 0, 100 s) took 54 s on one H100, where its
10^4-base-step work alone takes ~3 s: ~900 starts near theta = 0 use up their budget (20x the base steps) and
the GPU then runs ~2e5 loop iterations on a batch of a few hundred lanes, each iteration a sequence of small
kernels. Here the ``--n`` starts of `sample_starts(10**6, seed=0)` nearest theta = 0 (all stragglers) run
with `run_basin`'s defaults over ``--t-final`` seconds, warm (a first call compiles), in a fresh process per
variant:

* ``default``: as JAX ships it;
* ``no_graphs``: ``XLA_FLAGS=--xla_gpu_enable_command_buffer=`` (no CUDA graphs);
* ``graph_loops``: command buffers for loops and conditionals too (``...,WHILE,CONDITIONAL``,
  ``--xla_gpu_graph_min_graph_size=1``);
* ``cpu``: ``JAX_PLATFORMS=cpu``, the same batch on the host's cores (jaxsleigh's parts of 1024 starts);
* ``cpu_parts64``: the same with parts of 64 starts (`jaxsleigh.studies.ensemble.PART_SIZE` patched). It does
  not spread the stragglers over the cores: a part of at most ``TAIL_LANES`` (128) active lanes hands them all
  to the chunk's one tail batch, so this measures one core again (kept as measured on the H100).

Each prints wall time, the mean / max steps and microseconds per iteration (wall / max steps).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

VARIANTS = {
    "default": {},
    "no_graphs": {"XLA_FLAGS": "--xla_gpu_enable_command_buffer="},
    "graph_loops": {"XLA_FLAGS": "--xla_gpu_enable_command_buffer=FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,CUDNN,"
                                 "WHILE,CONDITIONAL --xla_gpu_graph_min_graph_size=1"},
    "cpu": {"JAX_PLATFORMS": "cpu"},
    "cpu_parts64": {"JAX_PLATFORMS": "cpu", "EXP_PART_SIZE": "64"},
}

CHILD = r"""
import json, sys, time
import os
import numpy as np, jax, jaxsleigh as js
if os.environ.get("EXP_PART_SIZE"):
    import jaxsleigh.studies.ensemble as ens
    ens.PART_SIZE = int(os.environ["EXP_PART_SIZE"])
n, t_final = int(sys.argv[1]), float(sys.argv[2])
s = js.sample_starts(10**6, seed=0)
ics = s.ics[np.argsort(np.abs(s.ics[:, 2]), kind="stable")[:n]]
js.run_basin(ics, t_final=t_final, run=js.RunOptions(progress=False))    # compile
t0 = time.perf_counter()
r = js.run_basin(ics, t_final=t_final, run=js.RunOptions(progress=False))
w = time.perf_counter() - t0
print(json.dumps({"wall_s": w, "mean_steps": float(np.mean(r.n_steps)), "max_steps": int(np.max(r.n_steps)),
                  "us_per_iteration": 1e6 * w / max(1, int(np.max(r.n_steps))),
                  "statuses": {int(k): int(c) for k, c in zip(*np.unique(r.status, return_counts=True))},
                  "min_abs_theta0": float(np.min(np.abs(ics[:, 2]))), "max_abs_theta0": float(np.max(np.abs(ics[:, 2]))),
                  "device": str(jax.devices()[0].device_kind), "devices": len(jax.devices())}))
"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=1024)
    ap.add_argument("--t-final", type=float, default=10.0)
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--timeout", type=float, default=90.0)
    ap.add_argument("--out", default="out/gpu_tail.json")
    a = ap.parse_args(argv)
    root = Path(__file__).resolve().parents[2]
    res = {"command": "python experiments/performance/gpu_tail.py " + " ".join(sys.argv[1:] if argv is None else argv),
           "n": a.n, "t_final": a.t_final, "dtype": "float32", "host_cores": os.cpu_count(), "variants": {}}
    for name in a.variants.split(","):
        env = {**os.environ, "PYTHONPATH": f"{root}:{os.environ.get('PYTHONPATH', '')}", **VARIANTS[name]}
        t0 = time.perf_counter()
        try:
            p = subprocess.run([sys.executable, "-c", CHILD, str(a.n), str(a.t_final)], capture_output=True,
                               text=True, env=env, timeout=a.timeout)
            out = json.loads(p.stdout.strip().splitlines()[-1]) if p.returncode == 0 else \
                {"failed": p.stderr.strip().splitlines()[-3:]}
        except subprocess.TimeoutExpired:
            out = {"failed": f"timed out after {a.timeout} s"}
        out["process_s"] = time.perf_counter() - t0
        res["variants"][name] = {"env": VARIANTS[name], **out}
        print(name, json.dumps(out), flush=True)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(res, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
