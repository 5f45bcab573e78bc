"""``jaxsleigh controllers`` (the laws, with their citations) and ``jaxsleigh compare`` (them, side by side)."""
from __future__ import annotations

import json
import time

from .common import (PROG, add_progress_option, add_sampler_options, add_tolerance_options, check_outputs, number,
                     sampler_from_args, whole)

__all__ = ["add_controllers", "add_compare"]


def add_controllers(subparsers) -> None:
    p = subparsers.add_parser(
        "controllers", help="list the feedback laws (--controller NAME), with what each must know and its citation",
        description="One line per law: its name (for --controller and compare --controllers), what of the plant "
                    "it must know, and the paper it comes from.")
    p.set_defaults(func=_cmd_controllers)


def _cmd_controllers(args) -> int:
    from ..controllers.registry import describe_controllers

    print("\n".join(describe_controllers()))
    return 0


def add_compare(subparsers) -> None:
    from ..studies.compare import START_DISTRIBUTIONS

    p = subparsers.add_parser(
        "compare", help="run several laws from the same starts and measure them the same way (one row each)",
        description="Each law runs from N held-out starts of each distribution ("
                    + "; ".join(f"{k}: {v}" for k, v in START_DISTRIBUTIONS.items())
                    + ") on the same plant, and gets one row per distribution: median and 90th-percentile "
                      "T_eps, fraction settled, energy percentiles (50, 75, 90), peak |u|, closest approach to "
                      "theta = 0. Laws are compared as they are (their default gains); experiments/"
                      "compare_controllers.py tunes them to one energy budget first.")
    p.add_argument("--controllers", default="paper,aicardi,astolfi,samson", metavar="A,B,..",
                   help="laws to compare (default: all; jaxsleigh controllers lists them)")
    p.add_argument("--samples", type=whole("--samples", "256"), default=256, metavar="N",
                   help="starts per distribution (default 256)")
    p.add_argument("--starts", default="near,uniform,wide", metavar="D1,D2,..",
                   help="start distributions (default: near,uniform,wide)")
    p.add_argument("--seed", type=whole("--seed", "0", minimum=0, maximum=2**62), default=0, metavar="S",
                   help="seed of the starts (and of --noise)")
    p.add_argument("--t-final", type=number("--t-final", "100"), default=100.0, metavar="T",
                   help="horizon in seconds (default 100)")
    p.add_argument("--eps", type=number("--eps", "0.05"), default=0.05, metavar="EPS",
                   help="radius of the ball |q| <= EPS of T_eps (default 0.05)")
    p.add_argument("--x64", action="store_true", help="compute in float64 (default: float32)")
    add_tolerance_options(p)
    p.add_argument("--saturation", type=number("--saturation", "50"), default=None, metavar="U",
                   help="actuator saturation: clip each component of u to |u_i| <= U")
    add_sampler_options(p, seed=False)
    p.add_argument("--out", required=True, metavar="TABLE.json", help="the rows, with what made them")
    p.add_argument("--plot", default=None, metavar="FIG.png", help="draw the table as a figure")
    add_progress_option(p)
    p.set_defaults(func=_cmd_compare)


def _names(args):
    """The ``--controllers`` and ``--starts`` lists, each checked against what it may name."""
    from ..controllers.registry import controller_names
    from ..studies.compare import START_DISTRIBUTIONS

    names = [n.strip() for n in args.controllers.split(",") if n.strip()]
    dists = [n.strip() for n in args.starts.split(",") if n.strip()]
    for flag, got, known in (("--controllers", names, controller_names()), ("--starts", dists, list(START_DISTRIBUTIONS))):
        bad = [n for n in got if n not in known]
        if bad or not got:
            raise ValueError(f"{flag}: unknown {bad or got!r}; choose from {', '.join(known)}")
    return names, dists


def _record(args, rows, names, dists, wall_s) -> dict:
    """What `jaxsleigh compare --out` writes: the rows, the command and every setting that made them."""
    import jax

    from ..studies.compare import START_DISTRIBUTIONS

    return {"rows": rows, "command": [PROG, *getattr(args, "_argv", [])],
            "settings": {"controllers": names, "starts": {d: START_DISTRIBUTIONS[d] for d in dists},
                         "samples": args.samples, "seed": args.seed, "t_final": args.t_final, "eps": args.eps,
                         "dtype": "float64" if args.x64 else "float32", "saturation": args.saturation,
                         "sample_period": args.sample_period, "delay": args.delay, "noise": args.noise,
                         "rtol": args.rtol, "atol": args.atol},
            "run_info": {"wall_s": wall_s, "devices": [str(d) for d in jax.devices()]}}


def _cmd_compare(args) -> int:
    from ..controllers.registry import make_controller
    from ..files.npz import atomic_write_text
    from ..integrate.stepsize import StepSizeController
    from ..studies.compare import compare, draw_compare_starts

    names, dists = _names(args)
    sampler = sampler_from_args(args)
    figures = {"--plot": args.plot} if args.plot else {}
    check_outputs(named={"--out": args.out}, figures=figures)
    laws = {n: make_controller(n) for n in names}
    starts = {d: draw_compare_starts(d, args.samples, args.seed) for d in dists}
    t0 = time.perf_counter()
    stepsize = StepSizeController(rtol=args.rtol, atol=args.atol)
    rows = compare(laws, starts, t_final=args.t_final, eps=args.eps, saturation=args.saturation, sampler=sampler,
                   x64=args.x64, stepsize=stepsize)
    record = _record(args, rows, names, dists, time.perf_counter() - t0)
    atomic_write_text(args.out, json.dumps(record, indent=1, default=float))
    if args.plot:
        from ..plots.compare import plot_compare_table

        plot_compare_table(record, args.plot)
    width = max(len(n) for n in names)
    for r in rows:
        print(f"{r['controller']:{width}s} {r['starts']:8s} settled {100 * r['settled']:5.1f}%  median T "
              f"{r['median_T']:8.3g} s  p90 T {r['p90_T']:8.3g} s  energy p50/p90 {r['energy_p50']:9.3g} / "
              f"{r['energy_p90']:9.3g}  peak |u| {r['u_peak_max']:9.3g}")
    print(f"{PROG} compare: wrote {args.out}" + (f" and {args.plot}" if args.plot else ""))
    return 0
