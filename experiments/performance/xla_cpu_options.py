r"""XLA:CPU compile options on top of `PLAIN_CPU_OPTIONS`, on the specialised plain kernel, against the C reference
(is there an option that makes XLA write a faster kernel?).

    python experiments/performance/xla_cpu_options.py [--n-ics 4096] [--steps 2000] [--repeats 5] [--out out/xla_cpu_options.json]

One core (``JAXSLEIGH_CORES=1``), float32, the benchmark workload (`jaxsleigh.studies.bench.workload`, seed 0), dt = 0.01.
Each option set runs in a fresh process (compiled with ``jax.jit(..., compiler_options=PLAIN_CPU_OPTIONS + extra)``,
the compilation cache off) and times, alternating, the compiled kernel and the C reference on one thread
(``time.process_time``, median of ``--repeats``). Reports per option set: the CPU ratio C / JAX (the kernel's share of
the C program's speed on one core), the largest relative difference of the final states from C, whether they are
bit-equal to the first row's (the option changed nothing), or the error text when XLA refuses the option. Options
that XLA takes only as ``XLA_FLAGS`` are given as ``{"XLA_FLAGS": "--flag=value"}``.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

#: the option sets measured (2026-11-26); the first is the kernel as it is
OPTION_SETS = [
    {},
    {"xla_cpu_experimental_enable_tiling_propagation": True},
    {"xla_cpu_copy_insertion_use_region_analysis": True},
    {"xla_cpu_use_xnnpack": True},
    {"xla_cpu_enable_concurrency_optimized_scheduler": False},
    {"xla_cpu_use_fusion_emitters": False},
    {"XLA_FLAGS": "--xla_cpu_use_thunk_runtime=false"},
    {"xla_cpu_use_multi_output_fusion": True},
    {"xla_cpu_enable_mlir_tiling_and_fusion": True},
    {"xla_cpu_flatten_after_fusion": True},
    {"xla_cpu_disable_loop_unrolling": True},
]

ONE = r"""
import hashlib, json, sys, time
import numpy as np, jax, jax.numpy as jnp
from jaxsleigh.studies import bench as B
from jaxsleigh.integrate import engine as E
from jaxsleigh.integrate.stepper import run_plain, PLAIN_BLOCK
from jaxsleigh.model.closed_loop import ClosedLoop
from jaxsleigh.model.params import paper_gains, paper_plant
extra, n, steps, repeats, build = json.loads(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
dt = 0.01
args = ClosedLoop(paper_plant(), paper_gains())
ics5, status0 = E.check_ics(B.workload(n, 0))
y0w = E.initial_w(ics5, status0, jnp.float32)
lib, reason = B.build_c_reference(build)
if lib is None:
    print(json.dumps({"error": reason})); sys.exit(0)
import ctypes; lib = ctypes.CDLL(str(lib))
f = jax.jit(lambda y, h: run_plain(y, args, h, n_steps=steps, block=PLAIN_BLOCK),
            compiler_options={**E.PLAIN_CPU_OPTIONS, **extra})
y = jnp.asarray(np.asarray(y0w).T)
c = f.lower(y, jnp.float32(dt)).compile()
out = np.asarray(c(y, jnp.float32(dt)).block_until_ready()).T
jt, ct = [], []
for _ in range(repeats):
    t0 = time.process_time(); c(y, jnp.float32(dt)).block_until_ready(); jt.append(time.process_time() - t0)
    t0 = time.process_time(); yc = B.c_reference_run(lib, y0w, args, dt, steps, 1); ct.append(time.process_time() - t0)
rel = np.nanmax(np.abs(out - yc) / (np.abs(yc).max(1, keepdims=True) + 1e-30))
print(json.dumps({"jax_cpu_s": float(np.median(jt)), "c_cpu_s": float(np.median(ct)),
                  "ratio_cpu": float(np.median(ct) / np.median(jt)), "max_rel_diff_vs_c": float(rel),
                  "final_sha": hashlib.sha256(out.tobytes()).hexdigest()[:16]}))
"""


def run_one(extra: dict, args) -> dict:
    env = dict(os.environ, JAXSLEIGH_CORES="1", JAXSLEIGH_NO_COMPILE_CACHE="1",
               PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    extra = dict(extra)
    if "XLA_FLAGS" in extra:
        env["XLA_FLAGS"] = extra.pop("XLA_FLAGS")
    r = subprocess.run([sys.executable, "-c", ONE, json.dumps(extra), str(args.n_ics), str(args.steps),
                        str(args.repeats), args.build_dir], capture_output=True, text=True, env=env)
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("{")]
    if r.returncode == 0 and lines:
        return json.loads(lines[-1])
    err = (r.stderr.strip().splitlines() or ["(no output)"])[-1]
    return {"error": err[:300]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n-ics", type=int, default=4096)
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--build-dir", default="out/c_reference")
    ap.add_argument("--out", default="out/xla_cpu_options.json")
    args = ap.parse_args(argv)
    rows, first = [], None
    for extra in OPTION_SETS:
        res = run_one(extra, args)
        if "final_sha" in res:
            first = first or res["final_sha"]
            res["same_kernel_as_first"] = res["final_sha"] == first
        rows.append({"options": extra, **res})
        print(json.dumps(rows[-1]), flush=True)
    doc = {"command": "python experiments/performance/xla_cpu_options.py " + " ".join(argv or sys.argv[1:]), "dtype": "float32",
           "cores": 1, "n_ics": args.n_ics, "steps": args.steps, "repeats": args.repeats,
           "load_average": os.getloadavg(), "cpu_count": os.cpu_count(), "rows": rows}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(doc, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
