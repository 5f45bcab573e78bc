"""``jaxsleigh optimum``: the energy-optimal open-loop frontier E*(T) per start (`jaxsleigh.optimum`).

Registered by `add_optimum`::

    jaxsleigh optimum --samples 16 --seed 1 --horizons 5,10,20,40 --out opt.npz --plot opt.png
    jaxsleigh optimum --ics starts.npy --horizons 10,20 --intervals 32 --out mine.npz
    jaxsleigh optimum ... --resume      (continue an interrupted run; same options)

Results are written chunk by chunk to ``FILE.npz.chunks/`` (the host runner of ``jaxsleigh basin``); an
interrupted run continues from the finished chunks with ``--resume``. Wall time, load and the command go to
the sidecar ``FILE.run.json``.
"""
from __future__ import annotations

import argparse
import re
import sys

import numpy as np

from ..files.npz import load_ics, npz_path
from .chunked import add_run_options, run_chunked_command
from .common import PROG
from .common import number as _number
from .common import whole as _whole
from ..studies.optimum import (OPTIMUM_CHUNK, OptimumOptions, OptimumStatus, as_horizons, check_sizes, optimum,
                               save_optimum)
from ..studies.options import RunOptions

__all__ = ["add_optimum", "run_optimum_command"]

EPILOG = """\
problem: per start and horizon T, the least energy int_0^T |u|^2 dt of an input held constant on
  --intervals equal intervals that brings the plant (the paper's, Coulomb damping: the laws' plant) to
  rest (|p(T)| <= --p-tol) inside the ball |q(T)| <= --eps. Float64, augmented Lagrangian + L-BFGS
  through the RK4 simulation, from --guesses turn-drive-turn manoeuvres; the best one found is kept.
status per problem: 0 converged, 1 not stationary (energy achievable, maybe not least), 2 infeasible
  (energy NaN), 3 nonfinite, 4 invalid input.
output .npz keys: starts (S,5), horizons (H,), eps, energy (S,H), frontier (S,H) [non-increasing in T],
  u (S,H,N,2), status (S,H), q_final (S,H,3), p_final (S,H,2), kkt (S,H), guess (S,H), settings_json, kind.
exit codes: 0 done (at least one problem solved), 2 bad input, 3 nothing solved, 5 output in use.

examples:
  jaxsleigh optimum --samples 16 --seed 1 --horizons 5,10,20,40 --out opt.npz --plot opt.png
  jaxsleigh optimum --ics starts.npy --horizons 10,20 --out mine.npz --resume"""


def _horizons(text: str):
    """--horizons 5,10,20,40: increasing numbers > 0."""
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"could not parse --horizons {text!r}; write increasing horizons in "
                                         f"seconds, e.g. --horizons 5,10,20,40") from None
    try:
        return tuple(float(v) for v in as_horizons(values))
    except ValueError as e:
        raise argparse.ArgumentTypeError(f"--horizons {text!r}: {e}") from None


def add_optimum(subparsers) -> argparse.ArgumentParser:
    """Register the ``optimum`` subcommand; returns its parser."""
    p = subparsers.add_parser(
        "optimum", help="the least control energy that brings each start to rest in the ball by T (E*(T))",
        description="Solve, per start and horizon, the energy-optimal open-loop control that ends at rest in the "
                    "ball |q| <= --eps: the frontier E*(T) that the feedback laws are measured against.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    g = p.add_argument_group("starts (one of)")
    src = g.add_mutually_exclusive_group(required=True)
    src.add_argument("--ics", metavar="FILE.npy", help="starts from a file, shape (S, 3) or (S, 5)")
    src.add_argument("--samples", type=_whole("--samples", "16", minimum=1), metavar="N",
                     help="N starts: x, y ~ U(-3, 3), |theta0| ~ U(0.3, pi) with a random sign, at rest")
    g.add_argument("--seed", type=_whole("--seed", "1", minimum=0, maximum=2**63 - 1), default=0, metavar="S",
                   help="seed of --samples (default 0)")
    c = p.add_argument_group("problem")
    c.add_argument("--horizons", type=_horizons, default=(5.0, 10.0, 20.0, 40.0), metavar="T1,T2,...",
                   help="increasing horizons [s] (default 5,10,20,40)")
    c.add_argument("--eps", type=_number("--eps", "0.05"), default=0.05, metavar="EPS",
                   help="radius of the terminal ball (default 0.05, that of the laws' T_eps)")
    c.add_argument("--intervals", type=_whole("--intervals", "24", minimum=1, maximum=4096), default=24,
                   metavar="N", help="intervals of the piecewise-constant input (default 24)")
    c.add_argument("--p-tol", type=_number("--p-tol", "1e-3"), default=1e-3, metavar="TOL",
                   help="at rest: |p(T)| <= TOL (default 1e-3)")
    s = p.add_argument_group("solver")
    s.add_argument("--outer", type=_whole("--outer", "20", minimum=1, maximum=10000), default=20, metavar="K",
                   help="augmented-Lagrangian rounds (default 20)")
    s.add_argument("--inner", type=_whole("--inner", "30", minimum=1, maximum=100000), default=30, metavar="K",
                   help="L-BFGS iterations per round (default 30)")
    s.add_argument("--guesses", type=_whole("--guesses", "2", minimum=1, maximum=4), default=2, metavar="K",
                   help="turn-drive-turn initial guesses per problem, 1 to 4 (default 2)")
    add_run_options(p, chunk_example="64", chunk_default=64, audit=False,
                    chunk_help="starts solved (and checkpointed) at once (default 64)",
                    plot_help="also draw the frontier E*(T) of every start")
    p._negative_number_matcher = re.compile(r"^-(\d|\.\d)")
    p.set_defaults(func=run_optimum_command)
    return p


def _plot(res, path):
    from ..plots.base import save_figure
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    fr = res.frontier()
    for i in range(min(fr.shape[0], 50)):
        ax.loglog(res.horizons, fr[i], "o-", lw=1, ms=3, alpha=0.6)
    ax.set_xlabel("horizon T [s]")
    ax.set_ylabel(r"least energy $E^*(T) = \int_0^T |u|^2 dt$")
    ax.set_title(f"energy-optimal frontier, at rest in |q| <= {res.eps:g} by T")
    ax.grid(True, which="both", alpha=0.3)
    return save_figure(fig, path)


def run_optimum_command(args) -> int:
    """Handler of ``jaxsleigh optimum``; returns the exit code."""
    out = npz_path(args.out)
    st = {}

    def check() -> None:
        if args.eps <= 0 or args.p_tol <= 0:
            raise ValueError("--eps and --p-tol must be > 0, e.g. --eps 0.05 --p-tol 1e-3")
        st["options"] = OptimumOptions(intervals=args.intervals, p_tol=args.p_tol, outer=args.outer,
                                       inner=args.inner, guesses=args.guesses).check()
        if args.ics is not None:
            st["starts"] = load_ics(args.ics, hint="or use --samples N")
        flags = {"starts": "--samples" if args.ics is None else f"--ics {args.ics}", "horizons": "--horizons",
                 "intervals": "--intervals", "guesses": "--guesses", "outer": "--outer", "inner": "--inner",
                 "chunk_size": "--chunk-size"}
        n = args.samples if args.ics is None else st["starts"].shape[0]
        check_sizes(n, args.horizons, st["options"], args.chunk_size or OPTIMUM_CHUNK, flags)   # before the draw
        if args.ics is None:
            from ..tuning.starts import UniformStarts

            st["starts"] = UniformStarts()(np.random.default_rng(args.seed), args.samples)

    def study(checkpoint_dir, resume, shard):
        return optimum(st["starts"], args.horizons, eps=args.eps, options=st["options"],
                       run=RunOptions(chunk_size=args.chunk_size, progress=args.progress,
                                      checkpoint_dir=checkpoint_dir, resume=resume, shard=shard))

    def finish(res, written, record, caught) -> int:
        if args.plot:
            written.append(str(_plot(res, args.plot)))
        print(res.describe())
        print(f"{PROG} optimum: {int(res.certified.sum())} of {res.status.size} problems converged (certified optima); "
              f"{record['wall_s']:.1f} s wall; wrote {', '.join(written)}")
        if not np.any(res.status <= OptimumStatus.NOT_STATIONARY):
            print(f"{PROG}: error: no problem was solved; raise --outer/--inner or the horizons", file=sys.stderr)
            return 3
        return 0

    return run_chunked_command(args, "optimum", out, check=check, study=study, save=save_optimum,
                               info=lambda res: {"counts": res.counts()}, finish=finish)
