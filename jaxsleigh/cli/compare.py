"""``jaxsleigh controllers`` (the laws, with their citations) and ``jaxsleigh compare`` (them, side by side)."""
from __future__ import annotations

import json
import math
import sys
import time

import jax

from ..studies.audit import COST, audit_line, without_cost
from .chunked import audit_from_args
from .common import (EXIT_NONE_OK, PROG, add_progress_option, add_sampler_options, add_tolerance_options,
                     check_outputs, claim_output, number, sampler_from_args, whole)
from ..files.npz import atomic_write_text
from ..files.runner import run_record, write_sidecar
from ..integrate.stepsize import StepSizeController

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


#: Most starts per distribution: each start's T_eps and energy are kept in the JSON (about 40 bytes a start, law
#: and distribution), and the starts of one distribution are integrated together.
MAX_SAMPLES = 100_000


#: ``--equal-energy``'s default training starts and tuner iterations per law (the experiment's: enough for every
#: literature law to reach the budget).
DEFAULT_TRAIN, DEFAULT_STEPS = 16, 60


def add_compare(subparsers) -> None:
    from ..controllers.registry import controller_names
    from ..studies.compare import START_DISTRIBUTIONS

    every = ",".join(controller_names())
    p = subparsers.add_parser(
        "compare", help="run several laws from the same starts and measure them the same way (one row each)",
        description="Each law runs from N held-out starts of each distribution ("
                    + "; ".join(f"{k}: {v}" for k, v in START_DISTRIBUTIONS.items())
                    + ") on the same plant, and gets one row per distribution: the settled share (starts whose "
                      "T_eps is within the horizon), median and 90th-percentile T_eps, energy percentiles (50, 75, "
                      "90) of the integral of |u|^2 dt [N^2 s, (N m)^2 s], peak |u|, closest approach to theta = 0, "
                      "and each start's T_eps and energy (per_start). The JSON is strict: null stands for a value "
                      "that is not a number: a T_eps or percentile of starts that did not settle within the horizon, "
                      "an energy of a start whose integration failed. Laws are compared at their default gains, or "
                      "with --equal-energy at one energy budget.")
    p.add_argument("--controllers", default=None, metavar="A,B,..",
                   help=f"laws to compare (default: all that jaxsleigh controllers lists, {every})")
    p.add_argument("--samples", type=whole("--samples", "256", maximum=MAX_SAMPLES), default=256, metavar="N",
                   help=f"starts per distribution (default 256, at most {MAX_SAMPLES}: each start's numbers are "
                        f"kept in the JSON; for more, run several --seed values)")
    p.add_argument("--starts", default="near,uniform,wide", metavar="D1,D2,..",
                   help="start distributions (default: near,uniform,wide)")
    p.add_argument("--seed", type=whole("--seed", "0", minimum=0, maximum=2**62), default=0, metavar="S",
                   help="seed of the starts (and of --noise and of the training starts of --equal-energy)")
    p.add_argument("--t-final", type=number("--t-final", "100"), default=100.0, metavar="T",
                   help="horizon in seconds (default 100)")
    p.add_argument("--eps", type=number("--eps", "0.05"), default=0.05, metavar="EPS",
                   help="radius of the ball |q| <= EPS of T_eps (default 0.05)")
    p.add_argument("--x64", action="store_true", help="compute in float64 (default: float32)")
    add_tolerance_options(p)
    p.add_argument("--saturation", type=number("--saturation", "50"), default=None, metavar="U",
                   help="actuator saturation: clip each component of u to |u_i| <= U (N, N m)")
    add_sampler_options(p, seed=False)
    # compare has no --dt: its --sample-period help says how the plant is integrated between samples
    next(a for a in p._actions if a.dest == "sample_period").help = (
        "zero-order hold at period TS: the law evaluated once per sample and held, the plant integrated in between "
        "by the adaptive RK4 to --rtol/--atol, landing on each sample instant; --t-final must be a whole number of "
        "periods")
    g = p.add_argument_group(
        "equal energy", "tune each literature law to one energy budget before comparing: the paper's training "
                        "energy (geometric mean of the integral of |u|^2 dt over 30 s on the tuner's training "
                        "starts); the paper's gains stay as published and a law with a tuned preset (shaped) "
                        "keeps it. The tuned laws and the budget are recorded in the JSON (equal_energy). With the "
                        "defaults, tuning takes about a minute on 2 CPU cores.")
    g.add_argument("--equal-energy", action="store_true", help="tune the literature's laws to the budget first")
    g.add_argument("--train", type=whole("--train", "16", maximum=4096), default=None, metavar="N",
                   help=f"training starts (default {DEFAULT_TRAIN})")
    g.add_argument("--steps", type=whole("--steps", "60", maximum=10_000), default=None, metavar="K",
                   help=f"tuner iterations per law (default {DEFAULT_STEPS})")
    p.add_argument("--audit-rows", type=whole("--audit-rows", "64", minimum=0, maximum=4096), default=None, metavar="K",
                   help="accuracy audit of every law and start set: K rows (the unresolved ones first) re-run in "
                        "float64 at rtol = atol = 1e-10 (default: 1%% of the rows, at most 64, from 500 starts on, as "
                        "many as fit 10%% of the run's time; 0: none)")
    p.add_argument("--out", required=True, metavar="TABLE.json", help="the rows, with what made them")
    p.add_argument("--plot", default=None, metavar="FIG.png",
                   help="draw the laws side by side: per start distribution, the distribution over the starts "
                        "of T_eps (settled fraction against time) and of the control energy")
    add_progress_option(p)
    p.set_defaults(func=_cmd_compare)


def _names(args):
    """The ``--controllers`` (default: every law) and ``--starts`` lists, each checked against what it may name."""
    from ..controllers.registry import controller_names
    from ..studies.compare import START_DISTRIBUTIONS

    given = ",".join(controller_names()) if args.controllers is None else args.controllers
    names = [n.strip() for n in given.split(",") if n.strip()]
    dists = [n.strip() for n in args.starts.split(",") if n.strip()]
    for flag, got, known in (("--controllers", names, controller_names()), ("--starts", dists, list(START_DISTRIBUTIONS))):
        bad = [n for n in got if n not in known]
        if bad or not got:
            raise ValueError(f"{flag}: unknown {bad or got!r}; choose from {', '.join(known)}")
    return names, dists


def _tuning(args) -> tuple:
    """``(train, steps)`` of ``--equal-energy``; ``--train`` / ``--steps`` without it are refused."""
    if not args.equal_energy:
        given = " and ".join(f for f, v in (("--train", args.train), ("--steps", args.steps)) if v is not None)
        if given:
            raise ValueError(f"{given} set the tuning of --equal-energy: add --equal-energy, or drop {given}")
        return None, None
    return (DEFAULT_TRAIN if args.train is None else args.train), (DEFAULT_STEPS if args.steps is None else args.steps)


def _record(args, rows, names, dists, *, dt, equal=None) -> dict:
    """What `jaxsleigh compare --out` writes: the rows, the command and every setting that made them (the wall time
    and devices, which vary between runs, go to its sidecar ``TABLE.run.json``)."""
    from ..studies.compare import START_DISTRIBUTIONS

    return {"rows": rows, "command": [PROG, *getattr(args, "_argv", [])],
            "settings": {"controllers": names, "starts": {d: START_DISTRIBUTIONS[d] for d in dists},
                         "samples": args.samples, "seed": args.seed, "t_final": args.t_final, "eps": args.eps,
                         "dtype": "float64" if args.x64 else "float32",
                         "method": "adaptive" if args.sample_period is None else "sampled", "dt": dt,
                         "saturation": args.saturation, "sample_period": args.sample_period, "delay": args.delay,
                         "noise": args.noise, "rtol": args.rtol, "atol": args.atol,
                         "equal_energy": bool(args.equal_energy)},
            "equal_energy": None if equal is None else equal.record()}


def _tuning_wall(equal) -> dict:
    """``{"tuning_wall_s": {law: seconds}}`` of ``--equal-energy``'s tuned laws (their records in the table leave it
    out); ``{}`` without it."""
    if equal is None:
        return {}
    return {"tuning_wall_s": {k: v["wall_s"] for k, v in equal.laws_info.items() if "wall_s" in v}}


def _audit_cost(rows) -> tuple:
    """``(rows without their audit's cost (`jaxsleigh.studies.audit.COST`), {"LAW on STARTS": that cost})``: the
    table's rows and the sidecar's."""
    kept, cost = [], {}
    for r in rows:
        audit = r.get("audit")
        if isinstance(audit, dict):
            cost[f"{r['controller']} on {r['starts']}"] = {k: audit[k] for k in COST if k in audit}
            r = {**r, "audit": without_cost(audit)}
        kept.append(r)
    return kept, cost


def _time(v: float, t_final: float) -> str:
    """A percentile of T_eps in seconds; ``'>T s'`` when that share of the starts did not settle by the horizon."""
    return f"{v:.3g} s" if math.isfinite(v) else f">{t_final:g} s"


def _amount(v: float) -> str:
    """A number (``'inf'`` for a start that diverged), ``'n/a'`` when not defined (no start ran)."""
    return "n/a" if math.isnan(v) else f"{v:.3g}"


def _failed(r) -> str:
    """``'  failed 16/16 (16 nonfinite)'``: how many starts of a row did not reach the horizon, by status;
    ``''`` when none."""
    if not r.get("failed"):
        return ""
    by = r.get("failed_statuses") or {}
    return f"  failed {r['failed']}/{r['n']}" + (f" ({', '.join(f'{k} {n}' for n, k in by.items())})" if by else "")


def failed_laws(rows) -> list:
    """The laws every start of whose every row failed (no start reached the horizon)."""
    laws = dict.fromkeys(r["controller"] for r in rows)
    return [law for law in laws if all(r.get("failed", 0) >= r["n"] for r in rows if r["controller"] == law)]


def row_lines(rows, *, eps: float, t_final: float) -> list:
    """One line per row: the law, the distribution, the settled share ('settled 241/256 (94.1%) by 100 s'),
    median and 90th-percentile T_eps, energy percentiles and peak |u|, and the starts that failed, by status
    ('failed 3/256 (3 budget_exhausted)')."""
    width = max(len(r["controller"]) for r in rows)
    swidth = max(len(r["starts"]) for r in rows)
    lines = []
    for r in rows:
        n = r["n"]
        k = int(round(r["settled"] * n))
        lines.append(f"{r['controller']:{width}s} {r['starts']:{swidth}s}  settled {k}/{n} ({100 * r['settled']:.1f}%) "
                     f"by {t_final:g} s  median T_{eps:g} {_time(r['median_T'], t_final)}  p90 T_{eps:g} "
                     f"{_time(r['p90_T'], t_final)}  energy p50/p90 {_amount(r['energy_p50'])} / "
                     f"{_amount(r['energy_p90'])} N² s  peak |u| {_amount(r['u_peak_max'])}{_failed(r)}")
    return lines


def _cmd_compare(args) -> int:
    from ..studies.compare import check_horizon

    names, dists = _names(args)
    train, steps = _tuning(args)
    sampler = sampler_from_args(args)
    dt = check_horizon(args.t_final, sampler, flag="--t-final")
    figures = {"--plot": args.plot} if args.plot else {}
    check_outputs(named={"--out": args.out}, figures=figures)
    with claim_output(args.out, args):
        return _run_compare(args, names, dists, train, steps, sampler, dt)


def _run_compare(args, names, dists, train, steps, sampler, dt) -> int:
    from ..controllers.registry import make_controller
    from ..studies.compare import compare, draw_compare_starts, json_ready
    from ..tuning.budget import budget_note, tune_to_budget

    t0 = time.perf_counter()
    equal = None
    if args.equal_energy:
        equal = tune_to_budget(names, train=train, steps=steps, seed=args.seed, log=print)
        print(f"equal energy: budget {equal.budget:.4g} N² s, the paper's training energy (geometric mean over "
              f"{train} training starts, 30 s)", flush=True)
        laws = equal.laws
    else:
        laws = {n: make_controller(n) for n in names}
    starts = {d: draw_compare_starts(d, args.samples, args.seed) for d in dists}
    stepsize = StepSizeController(rtol=args.rtol, atol=args.atol)
    rows = compare(laws, starts, t_final=args.t_final, eps=args.eps, saturation=args.saturation, sampler=sampler,
                   x64=args.x64, stepsize=stepsize, audit=audit_from_args(args))
    steady_rows, audit_cost = _audit_cost(rows)
    record = _record(args, steady_rows, names, dists, dt=dt, equal=equal)
    devices = [str(d) for d in jax.devices()]
    if args.plot:
        from ..plots.compare import plot_compare_ecdf

        # the figure names the devices it was computed on, as every figure does; the record leaves them out
        plot_compare_ecdf({**json_ready(record), "run_info": {"devices": devices}}, args.plot,
                          title="Controllers on the same plant and starts"
                                + (", at the paper's training energy" if equal is not None else ""))
    # the record last: where it is, the run finished (an interrupted one leaves none)
    atomic_write_text(args.out, json.dumps(json_ready(record), indent=1, allow_nan=False))
    side = write_sidecar(args.out, run_record(record["command"], time.perf_counter() - t0, devices,
                                                         audit_cost=audit_cost, **_tuning_wall(equal)))
    print("\n".join(row_lines(rows, eps=args.eps, t_final=args.t_final)))
    for r in rows:
        if (r.get("audit") or {}).get("rows"):
            print(f"{PROG} compare: {r['controller']} on {r['starts']}: {audit_line(r['audit'], flag='--audit-rows')}")
    if equal is not None:
        for name, info in equal.laws_info.items():
            if info.get("budget_reached") is False:
                print(f"{PROG} compare: {name}: not at equal energy: its training energy is "
                      f"{info['energy_ratio']:.2f}x the budget{budget_note(info['energy_ratio'])}")
    print(f"{PROG} compare: wrote {args.out}" + (f" and {args.plot}" if args.plot else "")
          + f" in {time.perf_counter() - t0:.1f} s wall (wall time and devices: {side.name})")
    dead = failed_laws(rows)
    if dead:
        print(f"{PROG}: error: every start of {', '.join(dead)} failed (see the statuses above and in --help); "
              f"exit code {EXIT_NONE_OK}", file=sys.stderr)
        return EXIT_NONE_OK
    return 0
