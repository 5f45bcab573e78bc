"""Memory mappings held by compiled XLA:CPU programs, and what `jax.clear_caches` gives back.

Linux caps one process at ``vm.max_map_count`` mappings (65,530 by default); past it the next mapping fails and
XLA dies of a segmentation fault. A test worker compiles thousands of programs, which is why the test suite drops
JAX's in-memory caches once a worker holds half the cap (``tests/conftest.py``). This script measures the cost per
program: it compiles ``--programs`` distinct small functions, counts ``/proc/self/maps`` before, after, and after
``jax.clear_caches()``, and prints the mappings per program. Linux only.

    python experiments/performance/memory_maps.py --programs 200 [--json FILE]
"""
from __future__ import annotations

import argparse
import gc
import json
import os
import platform
from pathlib import Path


def maps() -> int:
    """Mappings this process holds now."""
    with open("/proc/self/maps", "rb") as f:
        return f.read().count(b"\n")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--programs", type=int, default=200, help="distinct programs to compile (default 200)")
    ap.add_argument("--json", type=Path, help="also write the figures here")
    a = ap.parse_args()
    if a.programs < 1:
        ap.error("--programs must be >= 1")
    if not Path("/proc/self/maps").exists():
        ap.error("needs Linux (/proc/self/maps)")
    import jax
    import jax.numpy as jnp

    start = maps()
    kept = []
    for i in range(a.programs):
        f = jax.jit(lambda x, i=i: jnp.sin(x) * i + jnp.cos(x * i))   # a new function: a new program
        f(jnp.ones(3)).block_until_ready()
        kept.append(f)
    compiled = maps()
    jax.clear_caches()
    gc.collect()
    cleared = maps()
    out = {"programs": a.programs, "maps_start": start, "maps_compiled": compiled, "maps_cleared": cleared,
           "maps_per_program": round((compiled - start) / a.programs, 2),
           "max_map_count": int(Path("/proc/sys/vm/max_map_count").read_text()),
           "jax": jax.__version__, "machine": f"{platform.machine()}, {os.cpu_count()} CPUs",
           "backend": jax.default_backend(), "command": "python experiments/performance/memory_maps.py "
                                                         f"--programs {a.programs}"}
    print(f"{start} mappings at the start, {compiled} after {a.programs} programs "
          f"({out['maps_per_program']} each), {cleared} after jax.clear_caches(); the cap is {out['max_map_count']}")
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
