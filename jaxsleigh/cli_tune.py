"""``jaxsleigh tune``: tune the controller's gains and write them as a gains JSON file.

    jaxsleigh tune --out gains.json [--steps N] [--batch B] [--seed S] [--lr LR] [--t-final T] [--dt DT]
                   [--tune L,k,D_hat] [--robust] [--x64] [--history FILE.npz] [--validate N]

The file is accepted by ``jaxsleigh simulate --gains gains.json``. Register the subcommand with
:func:`add_tune` (it is a thin layer over :func:`jaxsleigh.tuning.tune`).
"""
from __future__ import annotations

import argparse
import math
import time

import numpy as np

__all__ = ["add_tune"]

_EPILOG = """\
The objective is the soft time spent outside |q| <= 0.05 (a smooth surrogate of the convergence
time T_0.05), averaged over --batch starts with |x|, |y| <= 3 and |theta0| in (0.3, pi), integrated
by adaptive RK4 in the w chart with gradients through the integrator. Every candidate is checked:
a training lane or a guard start (|theta0| = 0.05, 0.1) that fails or runs out of its step budget,
a non-finite loss or gradient, or a training start that needs more than --probe-budget steps to
simulate 100 s (faster convergence makes the loop stiffer after it) rejects it and the optimiser
backtracks; the best valid gains that also pass a final 100 s check of every training and guard
start with the accurate engine are written. --validate N then measures T_0.05 with the accurate
ensemble engine on N held-out starts (seed --seed + 1000) for the initial and the tuned gains.

examples:
  jaxsleigh tune --out gains.json
  jaxsleigh tune --out gains.json --tune k,D_hat --steps 60 --history history.npz
  jaxsleigh tune --out robust.json --robust --steps 200
  jaxsleigh simulate --ic=-3,-2,pi/8 --gains gains.json --out run.npz
"""


def add_tune(subparsers) -> None:
    """Register ``tune`` on an ``argparse`` subparsers object."""
    from .cli import _add_model_options, _add_progress_option, _positive_float, _positive_int

    p = subparsers.add_parser(
        "tune", help="tune the gains for fast convergence (gradients through the integrator)",
        description="Tune the controller's gains (L, k, D_hat) by gradient descent (optax Adam) on a smooth "
                    "surrogate of the convergence time, differentiating through the integrator, and write "
                    "the best valid gains as a gains JSON file.",
        epilog=_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, metavar="FILE.json", help="output gains file")
    g = p.add_argument_group("optimiser")
    g.add_argument("--steps", type=_positive_int("--steps", "150"), default=150, metavar="N",
                   help="optimiser iterations (default 150)")
    g.add_argument("--batch", type=_positive_int("--batch", "256"), default=256, metavar="B",
                   help="training starts (default 256)")
    g.add_argument("--seed", type=int, default=0, metavar="S", help="seed of the training starts (default 0)")
    g.add_argument("--lr", type=_positive_float("--lr", "0.05"), default=0.05, metavar="LR",
                   help="peak learning rate of Adam on the log-gains (default 0.05)")
    g.add_argument("--tune", default="L,k,D_hat", metavar="L,k,D_hat",
                   help="the gains to tune, a comma-separated subset of L, k, D_hat; the others stay at "
                        "their --gains values (default: all)")
    g.add_argument("--robust", action="store_true",
                   help="average the objective over sampled plants (m in 1-4, J in 0.5-2, l in 0.5-1.5, "
                        "Coulomb / viscous / no damping) instead of the --params/--damping plant")
    g.add_argument("--mode", choices=["forward", "reverse"], default="forward",
                   help="gradients: forward mode (default; fastest for the 7 gain parameters) or reverse "
                        "mode with checkpointed segments")
    h = p.add_argument_group("objective")
    h.add_argument("--t-final", type=_positive_float("--t-final", "30"), default=30.0, metavar="T",
                   help="training horizon in seconds (default 30)")
    h.add_argument("--dt", type=_positive_float("--dt", "0.01"), default=0.01, metavar="DT",
                   help="first step of the adaptive RK4; steps never exceed 10 DT (default 0.01)")
    h.add_argument("--n-attempts", type=_positive_int("--n-attempts", "4000"), default=4000, metavar="N",
                   help="budget of attempted steps per lane; a lane that needs more rejects the candidate "
                        "(default 4000)")
    h.add_argument("--probe-budget", type=_positive_int("--probe-budget", "100000"), default=100000, metavar="N",
                   help="most attempted steps any training start may need to simulate 100 s with the tuned "
                        "gains (the engine's default budget is 200180; default 100000)")
    _add_model_options(p)
    p.add_argument("--history", default=None, metavar="FILE.npz",
                   help="also write the history (loss, gains, gradient norm per iteration)")
    p.add_argument("--validate", type=int, default=256, metavar="N",
                   help="held-out starts for the final check with the accurate engine (0: skip; default 256)")
    _add_progress_option(p)
    p.set_defaults(func=_cmd_tune)


def _cmd_tune(args) -> int:
    from . import tuning
    from .cli import PROG, _model_from_args
    from .params import gains_to_dict, save_gains

    names = tuning.parse_tune(args.tune)
    if args.validate < 0:
        raise ValueError(f"--validate must be >= 0, got {args.validate}")
    if args.robust and (args.params != "2,1,1" or args.damping != "coulomb"):
        raise ValueError("--robust samples the plants itself; drop --params / --damping (or drop --robust)")
    plant, gains0 = _model_from_args(args)
    config = tuning.TuneConfig(steps=args.steps, batch=args.batch, seed=args.seed, lr=args.lr, mode=args.mode,
                               n_attempts=args.n_attempts, probe_budget=args.probe_budget)
    loss = tuning.LossConfig(t_final=args.t_final, dt=args.dt, max_step=10 * args.dt)
    robust = tuning.PlantDistribution() if args.robust else None
    t0 = time.perf_counter()
    try:
        res = tuning.tune(gains0, config=config, loss=loss, tune=names, plant=None if args.robust else plant,
                          robust=robust, x64=args.x64, progress=args.progress)
    except RuntimeError as e:          # no candidate passed the final check: say what to change
        raise ValueError(str(e)) from None
    wall = time.perf_counter() - t0
    command = [PROG, *getattr(args, "_argv", _canonical_argv(args))]
    meta = {
        "how": f"jaxsleigh tune: {res.settings['method']}",
        "command": command, "tuned": list(names), "initial_gains": gains_to_dict(res.initial),
        "initial_loss": res.initial_loss, "best_loss": res.best_loss, "best_iteration": res.best_iteration,
        "iterations_run": res.settings["iterations_run"], "seed": args.seed, "batch": args.batch,
        "dtype": res.settings["dtype"], "plant": "sampled (robust)" if args.robust else
        {"m": float(plant.m), "J": float(plant.J), "l": float(plant.l), "damping": args.damping},
        "objective": res.settings["loss"], "wall_s": wall,
    }
    print(f"{PROG} tune: loss {res.initial_loss:.4f} -> {res.best_loss:.4f} (iteration {res.best_iteration} of "
          f"{res.settings['iterations_run']}), {wall:.1f} s wall ({res.settings['dtype']}, {args.mode} mode)")
    if args.validate:
        ics = tuning.UniformStarts()(np.random.default_rng(args.seed + 1000), args.validate)
        rows = {"initial": tuning.validate(res.initial, ics, plant=plant, x64=args.x64),
                "tuned": tuning.validate(res.gains, ics, plant=plant, x64=args.x64)}
        meta["validation"] = {k: {"n": v.n, "seed": args.seed + 1000, "median_T_0.05": _num(v.median),
                                  "median_se": _num(v.median_se), "frac_converged_100s": v.frac_converged,
                                  "frac_se": v.frac_se, "n_failed": v.n_failed}
                              for k, v in rows.items()}
        print(tuning.markdown_table(rows))
    save_gains(res.gains, args.out, **meta)
    if args.history:
        path = tuning.save_history(res.history, args.history)
        print(f"{PROG} tune: wrote history {path}")
    g = res.gains
    print(f"{PROG} tune: wrote {args.out}: L = {np.round(g.L, 4).tolist()}, k = {float(g.k):.4g}, "
          f"D_hat = {np.round(g.D_hat, 4).tolist()}")
    return 0


def _canonical_argv(args) -> list:
    """The options that determine the result, as a command line (when the caller's argv is unknown)."""
    argv = ["tune", "--out", str(args.out), "--steps", str(args.steps), "--batch", str(args.batch),
            "--seed", str(args.seed), "--lr", repr(args.lr), "--tune", args.tune, "--mode", args.mode,
            "--t-final", repr(args.t_final), "--dt", repr(args.dt), "--n-attempts", str(args.n_attempts),
            "--probe-budget", str(args.probe_budget),
            "--gains", str(args.gains), "--params", args.params, "--damping", args.damping]
    return argv + (["--robust"] if args.robust else []) + (["--x64"] if args.x64 else [])


def _num(x: float):
    return x if math.isfinite(x) else str(x)
