r"""Where a default basin's time goes on CPU: its parts, its tails, and what a small batch's step costs.

    python experiments/performance/basin_tails.py [--n 100000] [--chunks 16384,65536,131072] [--out docs/figures/basin_tails.json]

1. ``timeline``: the default basin of ``--n`` starts (`jaxsleigh.sample_starts`, seed 0, 100 s, adaptive, float32),
   warm, with the start and end, in seconds from the call, of every call of the engine's
   `jaxsleigh.integrate.engine.drive_final` that the ensemble makes: once per part of a chunk (``what: "part"``,
   the parts of a chunk run at once, one per core, until at most ``TAIL_LANES`` of their lanes are still active)
   and once per chunk's tail batch (``what: "tail"``: the parts' stiff stragglers gathered and run to the horizon
   on one core, in the background while the next chunk's parts run). ``parts_s_sum`` is the time during which
   some part ran (the chunks' parts, the cores together), ``tails_s_sum`` the tail batches' times summed.
2. ``small_batches``: the 24 / 48 / 96 starts of that sample nearest theta = 0 (nearly all of them use their
   whole budget, status 4) as a basin of their own on one core (``JAXSLEIGH_CORES=1`` in a fresh process):
   microseconds per attempted step of the batch (wall over the largest step count).
3. ``chunk_sizes``: the same basin with ``chunk_size`` ``--chunks``: wall time and a digest of
   (T_eps, status, steps, final q, energy), to show whether the chunk size changes the bits.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]

SMALL = r"""
import json, sys, time
import numpy as np, jaxsleigh as js
s = js.sample_starts(int(sys.argv[1]), seed=0)
order = np.argsort(np.abs(s.ics[:, 2]), kind="stable")
out = {}
for n in map(int, sys.argv[2:]):
    ics = s.ics[order[:n]]
    js.run_basin(ics, t_final=5.0, run=js.RunOptions(progress=False))                   # compile
    t0 = time.perf_counter()
    r = js.run_basin(ics, t_final=100.0, run=js.RunOptions(progress=False))
    w = time.perf_counter() - t0
    out[n] = {"wall_s": w, "max_steps": int(r.n_steps.max()), "status4": int((r.status == 4).sum()),
              "us_per_step": 1e6 * w / int(r.n_steps.max())}
print(json.dumps(out))
"""


def digest(r) -> str:
    arrays = (r.T_eps, r.status, r.n_steps, r.q_final, r.u_energy)
    return hashlib.sha256(b"".join(np.ascontiguousarray(np.asarray(a)).tobytes() for a in arrays)).hexdigest()[:16]


def _covered(intervals) -> float:
    """The length of the union of ``(from, to)`` intervals: the time during which at least one ran."""
    total, end = 0.0, float("-inf")
    for lo, hi in sorted(intervals):
        if hi > end:
            total += hi - max(lo, end)
            end = hi
    return total


def timeline(js, starts) -> dict:
    """The basin run with every engine call of the ensemble timed: `drive_final` as
    `jaxsleigh.studies.ensemble` calls it, given ``y0w`` for a part of a chunk and ``state`` (the parts'
    still-active lanes, idle padding lanes marked ``INVALID_INPUT``) for a chunk's tail batch."""
    import jaxsleigh.studies.ensemble as ens

    t0, events = [0.0], []
    drive = ens.drive_final

    def timed(y0w, status0, *args, state=None, **kw):
        t = time.perf_counter()
        out = drive(y0w, status0, *args, state=state, **kw)
        status = np.asarray(status0 if state is None else state.status)
        events.append({"what": "part" if state is None else "tail",
                       "lanes": int((status != js.Status.INVALID_INPUT).sum()),
                       "from_s": t - t0[0], "to_s": time.perf_counter() - t0[0]})
        return out

    ens.drive_final = timed
    try:
        t0[0] = time.perf_counter()
        r = js.run_basin(starts, run=js.RunOptions(progress=False))
        wall = time.perf_counter() - t0[0]
    finally:
        ens.drive_final = drive
    events.sort(key=lambda e: e["from_s"])
    parts = [(e["from_s"], e["to_s"]) for e in events if e["what"] == "part"]
    tails = [e["to_s"] - e["from_s"] for e in events if e["what"] == "tail"]
    return {"wall_s": wall, "status4": int((r.status == 4).sum()), "mean_steps": float(r.n_steps.mean()),
            "parts": len(parts), "tail_batches": len(tails), "parts_s_sum": _covered(parts),
            "tails_s_sum": float(sum(tails)), "events": events}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--chunks", default="16384,65536,131072")
    ap.add_argument("--small", default="24,48,96")
    ap.add_argument("--out", default="docs/figures/basin_tails.json")
    a = ap.parse_args(argv)
    log = lambda *m: print(*m, file=sys.stderr, flush=True)  # noqa: E731
    import jaxsleigh as js
    from jaxsleigh.cores import available_cores

    res = {"command": "python experiments/performance/basin_tails.py " + " ".join(sys.argv[1:] if argv is None else argv),
           "cores": available_cores(), "dtype": "float32", "load_before": [round(x, 2) for x in os.getloadavg()]}
    js.run_basin(js.sample_starts(2048, seed=1), run=js.RunOptions(progress=False))   # compile, not timed
    starts = js.sample_starts(a.n, seed=0)
    res["timeline"] = timeline(js, starts)
    log(f"timeline: wall {res['timeline']['wall_s']:.1f} s, parts {res['timeline']['parts_s_sum']:.1f} s, "
        f"tails {res['timeline']['tails_s_sum']:.1f} s (summed)")
    env = {**os.environ, "JAXSLEIGH_CORES": "1", "PYTHONPATH": f"{ROOT}:{os.environ.get('PYTHONPATH', '')}"}
    p = subprocess.run([sys.executable, "-c", SMALL, str(a.n), *a.small.split(",")], capture_output=True, text=True,
                       env=env, check=True, cwd=str(Path(__file__).resolve().parent))
    res["small_batches"] = json.loads(p.stdout.strip().splitlines()[-1])
    log("small batches:", json.dumps(res["small_batches"]))
    res["chunk_sizes"] = {}
    for c in map(int, a.chunks.split(",")):
        t0 = time.perf_counter()
        r = js.run_basin(starts, run=js.RunOptions(chunk_size=c, progress=False))
        res["chunk_sizes"][c] = {"wall_s": time.perf_counter() - t0, "digest": digest(r),
                                 "mean_steps": float(r.n_steps.mean())}
        log(f"chunk_size {c}:", json.dumps(res["chunk_sizes"][c]))
    res["load_after"] = [round(x, 2) for x in os.getloadavg()]
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(res, indent=1) + "\n")
    log(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
