"""How long the energy-optimal frontier takes: 256 starts x 4 horizons on this machine.

    python experiments/performance/optimum_bench.py [--n 256] [--horizons 5,10,20,40] [--chunk-size 256]
        [--out docs/figures/optimum_bench.json]

Starts: x, y ~ U(-3, 3), |theta0| ~ U(0.3, pi) with a random sign, at rest (`jaxsleigh.tuning.starts.UniformStarts`,
seed 1). `jaxsleigh.optimum` with its defaults (float64, 24 intervals, 2 guesses, 20 rounds x 30 L-BFGS
iterations at most). Printed and written as JSON: the wall time (compilation included, one fresh process), the
share of problems per status (converged, not stationary, infeasible), the median E*(T) per horizon, the load
average before and after, the machine and the command.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import ROOT, load, machine  # noqa: E402

sys.path.insert(0, str(ROOT))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=256)
    ap.add_argument("--horizons", default="5,10,20,40")
    ap.add_argument("--chunk-size", type=int, default=256)
    ap.add_argument("--out", default=str(ROOT / "docs" / "figures" / "optimum_bench.json"))
    args = ap.parse_args(argv)
    horizons = tuple(float(v) for v in args.horizons.split(","))


    from jaxsleigh import RunOptions, optimum
    from jaxsleigh.tuning.starts import UniformStarts

    starts = UniformStarts()(np.random.default_rng(1), args.n)
    load_start = load()
    t0 = time.perf_counter()
    res = optimum(starts, horizons, run=RunOptions(chunk_size=args.chunk_size))
    wall = time.perf_counter() - t0
    counts = res.counts()
    out = {"command": "python experiments/performance/optimum_bench.py" + "".join(f" {a}" for a in (argv or sys.argv[1:])),
           "dtype": "float64", "starts": args.n, "horizons": list(horizons), "problems": int(res.status.size),
           "options": res.settings["options"], "chunk_size": args.chunk_size, "wall_s": round(wall, 1),
           "counts": counts, "share_converged": counts["converged"] / res.status.size,
           "share_solved": (counts["converged"] + counts["not_stationary"]) / res.status.size,
           "median_energy": [float(np.nanmedian(c)) for c in res.energy.T],
           "loadavg_start": load_start, "loadavg_end": load(),
           "machine": machine()}
    print(json.dumps(out, indent=1))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
