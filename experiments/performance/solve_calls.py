r"""What a call of `jaxsleigh.solve` costs, this tree against an earlier commit, each in fresh processes.

    python experiments/performance/solve_calls.py [--base 5e61e26] [--repeats 2] [--out docs/figures/solve_calls.json]

Three figures per process, float32, the paper's gains, 100 s (40,032 attempted steps of the scan):

* ``first_s``: a first call outside ``jit`` (compilation included), start (1, 1, 0.5);
* ``second_s``: a second call, from another start with another ``k`` of the same type: what a notebook pays per call;
* ``vmap64_s``: ``jax.jit(jax.vmap(...))`` of the control energy over 64 starts of `jaxsleigh.sample_starts`
  (seed 3), the second call (compiled); ``vmap64_compile_s`` the first.

Both trees' processes alternate (``--repeats`` pairs); the energies of the two trees are recorded (they agree to
float32 rounding: the jitted loop fuses differently).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import ROOT, baseline_tree, load, machine, run_py  # noqa: E402

CODE = r"""
import json, time
import jax, jax.numpy as jnp
import jaxsleigh as js
g = js.paper_gains()
y0, y1 = jnp.asarray([1.0, 1.0, 0.5], jnp.float32), jnp.asarray([-1.0, 2.0, -0.4], jnp.float32)
def timed(f):
    t = time.perf_counter(); out = jax.block_until_ready(f()); return time.perf_counter() - t, out
first, a = timed(lambda: js.solve(g, y0, t_final=100.0).u_energy)
second, b = timed(lambda: js.solve(g._replace(k=g.k * 2), y1, t_final=100.0).u_energy)
f = jax.jit(jax.vmap(lambda y: js.solve(g, y, t_final=100.0).u_energy))
ys = jnp.asarray(js.sample_starts(64, seed=3).ics, jnp.float32)
compile_, _ = timed(lambda: f(ys))
vmap, e = timed(lambda: f(ys))
print(json.dumps({"first_s": first, "second_s": second, "vmap64_compile_s": compile_, "vmap64_s": vmap,
                  "energy_first": float(a), "energy_second": float(b), "energy_vmap_sum": float(e.sum())}))
"""


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--base", default="5e61e26")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--out", type=Path, default=ROOT / "docs/figures/solve_calls.json")
    a = ap.parse_args()
    info = machine()
    base = baseline_tree(a.base)
    runs = {"base": [], "new": []}
    try:
        for _ in range(a.repeats):
            for name, tree in (("base", base), ("new", ROOT)):
                # no persistent cache: each process compiles what it runs
                env = {"PYTHONPATH": str(tree), "JAXSLEIGH_NO_COMPILE_CACHE": "1"}
                runs[name].append({**run_py(CODE, env=env), "load": load()})
                print(name, json.dumps(runs[name][-1]), flush=True)
    finally:
        subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(base)], capture_output=True)
    best = {k: {f: round(min(r[f] for r in v), 3) for f in ("first_s", "second_s", "vmap64_compile_s", "vmap64_s")}
            for k, v in runs.items()}
    out = {"command": "python experiments/performance/solve_calls.py " + " ".join(sys.argv[1:]), "dtype": "float32",
           "machine": info, "base": a.base, "best_of_repeats": best, "runs": runs}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps(best, indent=1), "->", a.out)


if __name__ == "__main__":
    main()
