r"""What bounds the default basin's wall time on CPU: the chunks' parts, then the pool of stragglers alone.

    python experiments/performance/pool_timeline.py [--n 100000] [--seed 5] [--compile-cache]
        [--out docs/figures/pool_timeline.json]

The default basin (``--n`` starts of `jaxsleigh.sample_starts`, seed ``--seed``, 100 s, adaptive, float32, every
core), warm (a basin of 4,000 starts first compiles and caches the programs; with ``--compile-cache`` the
persistent cache, as the command line has it, so that a second run compiles nothing, not even the programs that only
the full basin's stragglers need, such as the implicit step's), with every call of the engine that the ensemble
makes timed, in seconds from the call of `jaxsleigh.run_basin`:

* ``parts``: `jaxsleigh.integrate.engine.drive_final`, once per part of a chunk (the parts run at once, one per
  core, until at most 128 of their 1,024 lanes are still active); ``parts_end_s`` is when the last one ended;
* ``pool``: `jaxsleigh.integrate.engine.advance_lanes`, once per batch and segment of the run's pool of stragglers
  (1,000 attempted steps of 64 to 256 lanes, on one core, in the background): its real lanes (the others idle) and
  their most attempts so far.

``after_parts`` is what the pool did once the parts had ended, when it is the only work left: its segments, their
seconds, the real lanes of its first and largest batches, the most attempts a lane had taken in a batch that began
before the parts ended and in the last batch (the budget is 20 times the base steps: 200,000 here). ``status`` counts
the basin's outcomes; ``pool_segments`` lists every batch's start and end (s), real lanes and most attempts.
"""
from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import ROOT, load, machine  # noqa: E402


def timed_basin(ics, calls: list):
    """`jaxsleigh.run_basin` of ``ics`` with the ensemble's engine calls appended to ``calls`` as
    ``(what, start_s, end_s, real_lanes, most_attempts)``; returns ``(result, wall_s)``."""
    import jaxsleigh as js
    import jaxsleigh.integrate.engine as engine
    import jaxsleigh.studies.ensemble as ens

    # the parts call drive_final from the ensemble; the pool's batches call advance_lanes from engine.advance_pool
    drive, advance, lock = ens.drive_final, engine.advance_lanes, threading.Lock()
    t0 = time.perf_counter()

    def part(*a, **k):
        s = time.perf_counter() - t0
        out = drive(*a, **k)
        with lock:
            calls.append(("part", s, time.perf_counter() - t0, 0, 0))
        return out

    def segment(state, *a, **k):
        real = np.asarray(state.status) == js.Status.OK
        attempts = np.asarray(state.n_accept) + np.asarray(state.n_reject)
        s = time.perf_counter() - t0
        out = advance(state, *a, **k)
        with lock:
            calls.append(("pool", s, time.perf_counter() - t0, int(real.sum()),
                          int(attempts[real].max()) if real.any() else 0))
        return out

    ens.drive_final, engine.advance_lanes = part, segment
    try:
        t0 = time.perf_counter()
        res = js.run_basin(ics, run=js.RunOptions(progress=False, audit=False))
        return res, time.perf_counter() - t0
    finally:
        ens.drive_final, engine.advance_lanes = drive, advance


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--out", type=Path, default=ROOT / "docs/figures/pool_timeline.json")
    ap.add_argument("--compile-cache", action="store_true",
                    help="use the persistent compilation cache, as the command line does (run twice: the second run "
                         "compiles nothing, not even the programs that only the full basin's stragglers need)")
    a = ap.parse_args()
    info = machine()
    import jaxsleigh as js

    if a.compile_cache:
        js.enable_compilation_cache()

    js.run_basin(js.sample_starts(4000, seed=a.seed).ics, run=js.RunOptions(progress=False, audit=False))
    load_start = load()
    calls: list = []
    res, wall = timed_basin(js.sample_starts(a.n, seed=a.seed).ics, calls)
    parts = [c for c in calls if c[0] == "part"]
    pool = sorted((c for c in calls if c[0] == "pool"), key=lambda c: c[1])
    parts_end = max(c[2] for c in parts)
    after = [c for c in pool if c[1] >= parts_end]
    first = after[0] if after else None
    status, counts = np.unique(np.asarray(res.status), return_counts=True)
    out = {"command": "python experiments/performance/pool_timeline.py " + " ".join(sys.argv[1:]),
           "dtype": "float32", "machine": info, "load_start": load_start, "load_end": load(),
           "workload": f"jaxsleigh.run_basin(jaxsleigh.sample_starts({a.n}, seed={a.seed}).ics), 100 s, defaults",
           "wall_s": round(wall, 2), "parts": len(parts), "parts_end_s": round(parts_end, 2),
           "pool": {"segments": len(pool), "first_s": round(pool[0][1], 2) if pool else None,
                    "end_s": round(max(c[2] for c in pool), 2) if pool else None,
                    "busy_s": round(sum(c[2] - c[1] for c in pool), 2)},
           "after_parts": {"segments": len(after), "seconds": round(after[-1][2] - parts_end, 2) if after else 0.0,
                           "busy_s": round(sum(c[2] - c[1] for c in after), 2),
                           "ms_per_segment_median": round(1e3 * float(np.median([c[2] - c[1] for c in after])), 1)
                           if after else None,
                           "lanes_first_batch": first[3] if first else 0,
                           "most_lanes_in_a_batch": max(c[3] for c in after) if after else 0,
                           "most_attempts_before_parts_end": max((c[4] for c in pool if c[1] < parts_end), default=0),
                           "most_attempts_last_batch": after[-1][4] if after else 0,
                           "share_of_wall": round((after[-1][2] - parts_end) / wall, 3) if after else 0.0},
           "status": {int(s): int(c) for s, c in zip(status, counts)},
           "pool_segments": [[round(c[1], 3), round(c[2], 3), c[3], c[4]] for c in pool]}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps(out, indent=1), "->", a.out)


if __name__ == "__main__":
    main()
