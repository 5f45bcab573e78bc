r"""Where a default basin's wall time goes, segment by segment: written for a GPU, where one chunk holds every
start and a loop iteration costs about the same whatever the batch's size, so the tail's segments set the time.

    python experiments/performance/basin_segments.py [--n 1000000] [--seed 0] [--out basin_segments.json]

The default basin (``--n`` starts of `jaxsleigh.sample_starts`, seed ``--seed``, 100 s, adaptive, float32, without
the accuracy audit), warm (a basin of 10,000 starts first compiles the programs), with every segment of the engine
recorded. A segment is ``segment`` (1,000) attempted steps of one batch; the engine calls
`jaxsleigh.integrate.engine.flying` once at its start, to choose each lane's step (explicit, or the linearly
implicit step of a stiff flight). The script wraps that call and records, in seconds from the call of
`jaxsleigh.run_basin`: when the segment began, the batch's lanes, those still stepping (OK), those of them on the
implicit step, and the most attempts a stepping lane has taken. A segment whose stepping lanes are of both kinds is
stepped twice (`_by_kind`): ``mixed``. The time between one segment's start and the next is the segment's wall
time, host work (compaction, the certificate of `jaxsleigh.integrate.stragglers`) included.

The summary splits the time after the first segment whose batch is below 1/8 of the starts (the tail) by kind:
explicit only, implicit only, mixed; and counts the lanes that end NOT_SETTLING and their attempts.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import load, machine  # noqa: E402


def recorded_basin(ics):
    """`jaxsleigh.run_basin` of ``ics`` with one row per segment (see the module's docstring); ``(result, wall_s,
    rows)``, rows ``(start_s, lanes, ok, implicit, most_attempts)``."""
    import jaxsleigh as js
    import jaxsleigh.integrate.engine as engine

    rows, flying, t0 = [], engine.flying, [time.perf_counter()]

    def recorded(state, ctl, stiff_after):
        ok = np.asarray(state.status) == js.Status.OK
        n = np.asarray(state.n_accept) + np.asarray(state.n_reject)
        flies = flying(state, ctl, stiff_after)
        rows.append((time.perf_counter() - t0[0], int(ok.size), int(ok.sum()), int((ok & flies).sum()),
                     int(n[ok].max()) if ok.any() else 0))
        return flies

    engine.flying = recorded
    try:
        t0[0] = time.perf_counter()
        res = js.run_basin(ics, run=js.RunOptions(progress=False, audit=False))
        return res, time.perf_counter() - t0[0], rows
    finally:
        engine.flying = flying


def summary(rows: list, wall: float, n: int) -> dict:
    """The tail's seconds by kind of segment (see the module's docstring)."""
    ends = [r[0] for r in rows[1:]] + [wall]
    kind = ["implicit" if r[3] == r[2] and r[3] else "mixed" if r[3] else "explicit" for r in rows]
    tail = next((i for i, r in enumerate(rows) if r[1] < n / 8), len(rows))
    out = {"segments": len(rows), "tail_starts_s": round(rows[tail][0], 2) if tail < len(rows) else None,
           "before_tail_s": round(rows[tail][0] if tail < len(rows) else wall, 2)}
    for k in ("explicit", "implicit", "mixed"):
        sel = [i for i in range(tail, len(rows)) if kind[i] == k]
        secs = [ends[i] - rows[i][0] for i in sel]
        out[k] = {"segments": len(sel), "seconds": round(sum(secs), 2),
                  "ms_per_segment_median": round(1e3 * float(np.median(secs)), 1) if secs else None,
                  "lanes_median": int(np.median([rows[i][1] for i in sel])) if sel else None}
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("basin_segments.json"))
    a = ap.parse_args()
    info = machine()
    import jax

    import jaxsleigh as js

    js.run_basin(js.sample_starts(10_000, seed=1).ics, run=js.RunOptions(progress=False, audit=False))
    load_start = load()
    res, wall, rows = recorded_basin(js.sample_starts(a.n, seed=a.seed).ics)
    status = np.asarray(res.status)
    attempts = np.asarray(res.n_steps) + np.asarray(res.n_rejected)
    codes, counts = np.unique(status, return_counts=True)
    ns = status == js.Status.NOT_SETTLING
    out = {"command": "python experiments/performance/basin_segments.py " + " ".join(sys.argv[1:]),
           "dtype": "float32", "machine": info, "device": str(jax.devices()[0].device_kind),
           "load_start": load_start, "load_end": load(),
           "workload": f"jaxsleigh.run_basin(jaxsleigh.sample_starts({a.n}, seed={a.seed}).ics), 100 s, defaults",
           "wall_s": round(wall, 2), "status": {int(c): int(k) for c, k in zip(codes, counts)},
           "attempts": {"sum": int(attempts.sum()), "max": int(attempts.max()),
                        "not_settling_median": int(np.median(attempts[ns])) if ns.any() else None},
           "summary": summary(rows, wall, a.n),
           "rows": [[round(r[0], 4), *r[1:]] for r in rows]}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps({k: v for k, v in out.items() if k != "rows"}, indent=1), "->", a.out)


if __name__ == "__main__":
    main()
