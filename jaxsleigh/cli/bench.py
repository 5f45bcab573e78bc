"""``jaxsleigh bench``: jaxsleigh's own throughput and accuracy, as a table or JSON."""
from __future__ import annotations

import json
import sys

from .common import FLAGS, PROG, check_outputs, number, whole
from ..studies.config import solve_config

__all__ = ["add_bench"]


def add_bench(subparsers) -> None:
    p = subparsers.add_parser(
        "bench", help="measure jaxsleigh's own throughput and accuracy (JSON)",
        description=("Benchmark jaxsleigh on the measured workload (x, y ~ U(-3, 3), |theta0| ~ U(0.3, pi), "
                     "zero momentum): fixed-step RK4 throughput (final state only), correct trajectories per "
                     "second of the default adaptive method (final-state error <= 1e-3 against a float64 "
                     "reference), wrong or non-finite counts, peak memory. Compile time is excluded. "
                     "Peers (plain vmap, NumPy, diffrax, scipy) are compared by experiments/performance/bench_peers.py."))
    p.add_argument("--json", action="store_true", help="print one JSON object (default: a short table)")
    p.add_argument("--n-ics", type=whole("--n-ics", "4096"), default=4096,
                   help="number of initial conditions (default 4096)")
    p.add_argument("--t-final", type=number("--t-final", "100"), default=100.0, help="horizon in s (default 100)")
    p.add_argument("--dt", type=number("--dt", "0.01"), default=0.01, help="base step in s (default 0.01)")
    p.add_argument("--x64", action="store_true", help="float64 (default float32)")
    p.add_argument("--seed", type=whole("--seed", "0", minimum=0), default=0, help="seed of the workload (default 0)")
    p.add_argument("--repeats", type=whole("--repeats", "3"), default=1, help="timed repeats, best kept (default 1)")
    p.add_argument("--cache", default=None, help="directory to cache the float64 reference in")
    p.set_defaults(func=_cmd_bench)


def _cmd_bench(args) -> int:
    from ..studies.bench import bench, check_bench_sizes

    solve_config(t_final=args.t_final, dt=args.dt, x64=args.x64, flags=FLAGS)
    check_bench_sizes(args.n_ics, args.t_final, args.dt, {"n_ics": "--n-ics", "t_final": "--t-final", "dt": "--dt"})
    check_outputs(folders=[args.cache] if args.cache else [])
    print(f"{PROG} bench: compiling, then timing {args.n_ics} starts over {args.t_final:g} s "
          f"(a float64 reference first; about a minute on 2 CPU cores)...", file=sys.stderr, flush=True)
    res = bench(n_ics=args.n_ics, t_final=args.t_final, dt=args.dt, x64=args.x64, seed=args.seed,
                repeats=args.repeats, cache_dir=args.cache)
    if args.json:
        print(json.dumps(res))
    else:
        for k, v in res.items():
            if k != "machine":
                print(f"{k:40s} {v:.4g}" if isinstance(v, float) else f"{k:40s} {v}")
    return 0
