r"""What a segment of the pool of stragglers costs at each batch size, and which sizes give a lane the same bits.

    python experiments/performance/pool_batches.py [--repeats 5] [--out docs/figures/pool_batches.json]

Eight stiff starts near theta = 0 (theta0 from 1e-3 to 5e-3 rad, the stragglers of the default basin) are stepped by
the adaptive engine's segment (`jaxsleigh.integrate.engine.advance_lanes`: 1,000 attempts, then the certificate) in
batches of 8 to 1,024 lanes, the eight real lanes first and idle copies after, as the pool pads its batches. For each
size: the median milliseconds per segment (warm, one device, ``--repeats`` segments; as many microseconds per
attempted step) and per lane-attempt, and whether the eight lanes end bitwise as in the batch of 64
(`jaxsleigh.studies.ensemble.TAIL_MIN`). Sizes that round alike form a class; the pool uses one class only, so that a
lane's result never depends on which lanes shared its batch or when it joined. Float32, the paper's gains.
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import ROOT, load, machine  # noqa: E402

SIZES = (8, 16, 32, 64, 128, 256, 1024)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", type=Path, default=ROOT / "docs/figures/pool_batches.json")
    a = ap.parse_args()
    info = machine()
    import jax
    import jax.numpy as jnp

    import jaxsleigh as js
    from jaxsleigh.integrate.engine import advance_lanes, check_ics, drive_final, initial_w, take_lanes_of
    from jaxsleigh.model.closed_loop import ClosedLoop
    from jaxsleigh.studies.config import solve_config

    cfg = solve_config(t_final=100.0)
    step = cfg.stepsize
    args = ClosedLoop(cfg.plant, cfg.law)
    theta = np.geomspace(1e-3, 5e-3, 8) * np.array([1, -1] * 4)
    starts = np.column_stack([np.linspace(-2.5, 2.5, 8), np.linspace(2.0, -2.0, 8), theta])
    ics5, st0 = check_ics(starts, np.float32)
    y0w = np.asarray(initial_w(ics5, st0, np.float32))
    rows, ends = [], {}
    load_start = load()
    for size in SIZES:
        fill = np.concatenate([np.arange(8), np.zeros(size - 8, int)])
        status = np.where(np.arange(size) < 8, st0[fill], js.Status.INVALID_INPUT).astype(np.int32)
        with jax.default_device(jax.devices()[0]):
            s = drive_final(jnp.asarray(y0w[fill]), status, args, cfg.horizon, step, eps=0.05, stop_at=size,
                            finish=False)
            s = advance_lanes(s, args, cfg.horizon, step, eps=0.05)             # compiles
            times = []
            for _ in range(a.repeats):
                t0 = time.perf_counter()
                s = advance_lanes(s, args, cfg.horizon, step, eps=0.05)
                times.append(time.perf_counter() - t0)
        ends[size] = [np.asarray(x) for x in jax.tree_util.tree_leaves(take_lanes_of(s, np.arange(8)))]
        ms = float(np.median(times)) * 1e3
        rows.append({"lanes": size, "ms_per_segment": round(ms, 2), "us_per_lane_attempt": round(ms / size, 4)})
        print(rows[-1], flush=True)
    for r in rows:
        r["bits_as_64"] = all(np.array_equal(x, y, equal_nan=True) for x, y in zip(ends[r["lanes"]], ends[64]))
    res = {"command": "python experiments/performance/pool_batches.py " + " ".join(sys.argv[1:]),
           "dtype": "float32", "machine": {**info, "processor": platform.processor()}, "load_start": load_start,
           "load_end": load(), "segment_attempts": 1000, "rows": rows}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(res, indent=1) + "\n")
    print(json.dumps(rows), "->", a.out)


if __name__ == "__main__":
    main()
