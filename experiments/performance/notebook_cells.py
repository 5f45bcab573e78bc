"""Per cell of a notebook: seconds and XLA programs, in one fresh process with an empty compilation cache.

    XDG_CACHE_HOME=$(mktemp -d) MPLBACKEND=Agg python experiments/performance/notebook_cells.py \
        notebooks/04_gain_tuning.ipynb [--json out.json]

The code cells run in order in this process (IPython's ``%`` lines left out), as a fresh kernel runs them;
programs are counted from JAX's ``/jax/core/compile/backend_compile_duration`` events (`jax.monitoring`), one per
program compiled or read from the persistent cache, with their seconds. Run it with an empty ``XDG_CACHE_HOME``
(the cache `jaxsleigh.enable_compilation_cache` fills) for the cold figures.
"""
from __future__ import annotations

import time

_T0 = time.perf_counter()

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import threading  # noqa: E402
from pathlib import Path  # noqa: E402

EVENT = "/jax/core/compile/backend_compile_duration"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("notebook")
    ap.add_argument("--json", default=None, help="write the per-cell figures here")
    a = ap.parse_args(argv)
    nb = json.loads(Path(a.notebook).read_text())
    import jax

    events, lock = [], threading.Lock()

    def on(event, duration, **kw):
        if event == EVENT:
            with lock:
                events.append(float(duration))

    jax.monitoring.register_event_duration_secs_listener(on)
    os.chdir(Path(a.notebook).resolve().parent)
    scope: dict = {"__name__": "__main__"}
    rows = []
    for i, cell in enumerate(nb["cells"]):
        if cell["cell_type"] != "code":
            continue
        src = "".join(cell["source"])
        code = "\n".join(line for line in src.splitlines() if not line.lstrip().startswith("%"))
        k, t = len(events), time.perf_counter()
        exec(compile(code, f"<cell {i}>", "exec"), scope)
        with lock:
            ev = events[k:]
        rows.append({"cell": i, "first_line": src.splitlines()[0][:60] if src else "", "s": time.perf_counter() - t,
                     "programs": len(ev), "compile_s": sum(ev)})
        r = rows[-1]
        print(f"cell {i:2d}  {r['s']:7.1f} s  {r['programs']:3d} programs  {r['compile_s']:6.1f} s compiling  "
              f"{r['first_line']}", flush=True)
    total = {"s": time.perf_counter() - _T0, "programs": len(events), "compile_s": sum(events)}
    print(f"all     {total['s']:7.1f} s  {total['programs']:3d} programs  {total['compile_s']:6.1f} s compiling "
          f"(imports included; load {os.getloadavg()[0]:.1f})")
    if a.json:
        Path(a.json).write_text(json.dumps({"notebook": a.notebook, "cells": rows, "total": total}, indent=1))


if __name__ == "__main__":
    main()
