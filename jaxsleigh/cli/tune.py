"""``jaxsleigh tune``: tune the controller's gains and write them as a gains JSON file.

    jaxsleigh tune --out gains.json [--steps N] [--batch B] [--seed S] [--lr LR] [--t-final T] [--dt DT]
                   [--tune L,k,D_hat] [--robust] [--x64] [--history FILE.npz] [--validate N]
                   [--energy-budget E]
    jaxsleigh tune --pareto N --out front.json [--front-method warm|vmap] [--budgets LO:HI]
                   [--warm-steps N] [--baseline] [--plot front.png] [--validate N] ...
    jaxsleigh tune --search --out gains.json [--steps G] [--batch B] [--population P]
                   [--energy-margin F | --energy-budget E] [--energy-percentiles 50,75,90] [--rtol R] [--atol A]
                   [--history FILE.npz] [--validate N]

    jaxsleigh tune --controller NAME | --saturation U | --sample-period TS --out law.json [--steps N] [--batch B]
                   [--lr LR] [--energy-budget E] [--history FILE.npz] [--resume]

The file is accepted by ``jaxsleigh simulate --gains gains.json``; a tuned law's (`jaxsleigh.tuning.law_file`) by
``--controller law.json``, the paper's law behind an actuator by ``--gains law.json``. Register the subcommand with
`add_tune` (it is a thin layer over `jaxsleigh.tuning.tune`).
"""
from __future__ import annotations

import argparse
import functools
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from .common import (EXIT_INTERRUPTED, EXIT_NONE_OK, PROG, add_model_options, add_progress_option, add_sampler_options,
                     add_tolerance_options, check_outputs, model_from_args, number, whole)

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

--energy-budget E adds a budget on the batch's geometric-mean control energy int |u|^2 dt
(augmented Lagrangian). With a budget, train over the validation horizon and let lanes run on after
converging (--t-final 100 --stop-fraction 0.001), so the energy spent while settling counts; there
the paper's gains spend about 19 on 32 starts. Tuned gains that do not meet the budget are written
all the same, with "energy_budget_met": false, and the command says so and exits 3.
--pareto N computes N such tunings for budgets from a quarter of the paper's gains' training energy
to twice the 'tuned' preset's (or --budgets LO:HI), re-evaluates each on --validate held-out starts
(seed --seed + 1000) with the accurate engine over 100 s and writes front.json: per point the gains
(gains-file format) and median T_0.05 +- s.e., converged fraction, median energy, median peak |u|,
mean adaptive steps; with the paper's and 'tuned' gains as references and, with --baseline, a
random search spending the same number of objective evaluations.

--search replaces the gradient descent by a derivative-free search (CMA-ES)
on the figures the accurate engine reports over 100 s: the shortest median T_0.05 on --batch training
starts subject to median control energy <= --energy-margin x the --gains' on the same starts (or
--energy-budget E, an absolute median energy; --energy-percentiles 50,75,90: at each of those
percentiles), no fewer converged and no start failing or crossing theta = 0. Each generation's
--population candidates run as one ensemble (gains per trajectory). Use --atol 1e-8 when effort
matters: float32's default 1e-6 does not resolve energy spent after settling. The 'balanced' preset
is its result (experiments/studies/balanced_search.py: two such searches in a row, at --atol 1e-8 with
--energy-percentiles 50,75,90).

--controller NAME (a law of jaxsleigh controllers), --saturation U and --sample-period TS tune that
law's gains by Adam (--steps, --lr, --batch, --energy-budget as above; Ctrl-C keeps the best law so far
and --resume continues) and write the tuned law: its every parameter and the actuator it was tuned
behind, to give with --controller FILE.json; the paper's law behind an actuator is written as a gains
file (--gains FILE.json; give --saturation / --sample-period again).

examples:
  jaxsleigh tune --out gains.json
  jaxsleigh tune --search --out mine.json --steps 60 --energy-percentiles 50,75,90 --atol 1e-8 --history search.npz
  jaxsleigh tune --out eco.json --energy-budget 19 --t-final 100 --stop-fraction 0.001 --n-attempts 6000
  jaxsleigh tune --pareto 5 --out front.json --plot front.png --baseline --t-final 100 --stop-fraction 0.001
  jaxsleigh tune --out gains.json --tune k,D_hat --steps 60 --history history.npz
  jaxsleigh tune --out robust.json --robust --steps 200
  jaxsleigh simulate --ic=-3,-2,pi/8 --gains gains.json --out run.npz
"""


def _percentiles(text: str) -> tuple:
    """argparse ``type=`` of ``--energy-percentiles``: distinct numbers in (0, 100), comma-separated."""
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        vals = ()
    if not vals or len(set(vals)) != len(vals) or not all(0 < v < 100 for v in vals):
        raise argparse.ArgumentTypeError(f"--energy-percentiles must be distinct percentiles in (0, 100), comma-"
                                         f"separated, got {text!r} (e.g. --energy-percentiles 50,75,90)")
    return vals


def _add_optimiser_options(p) -> None:
    """--steps, --batch, --seed, --lr, --tune, --robust, --mode."""
    g = p.add_argument_group("optimiser")
    g.add_argument("--steps", type=whole("--steps", "150"), default=None, metavar="N",
                   help="optimiser iterations (default 150; with --search: generations, default 100)")
    g.add_argument("--batch", type=whole("--batch", "256"), default=None, metavar="B",
                   help="training starts (default 256; with --search 128)")
    g.add_argument("--seed", type=whole("--seed", "0", minimum=0, maximum=2**62), default=0, metavar="S",
                   help="seed of the training starts (default 0)")
    g.add_argument("--lr", type=number("--lr", "0.05"), default=0.05, metavar="LR",
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


def _add_objective_options(p) -> None:
    """The gradient tuner's surrogate: horizon, steps, budgets."""
    h = p.add_argument_group("objective")
    h.add_argument("--t-final", type=number("--t-final", "30"), default=30.0, metavar="T",
                   help="training horizon in seconds (default 30)")
    h.add_argument("--dt", type=number("--dt", "0.01"), default=0.01, metavar="DT",
                   help="first step of the adaptive RK4; steps never exceed 10 DT (default 0.01)")
    h.add_argument("--n-attempts", type=whole("--n-attempts", "4000"), default=4000, metavar="N",
                   help="budget of attempted steps per lane; a lane that needs more rejects the candidate "
                        "(default 4000)")
    h.add_argument("--probe-budget", type=whole("--probe-budget", "100000"), default=100000, metavar="N",
                   help="most attempted steps any training start may need to simulate 100 s with the tuned "
                        "gains (the engine's default budget is 200180; default 100000)")
    h.add_argument("--stop-fraction", type=number("--stop-fraction", "0.001"), default=0.5, metavar="F",
                   help="a training lane stops once |q| <= F x 0.05 (default 0.5; 0.001 lets lanes run on so the "
                        "energy spent while settling counts)")
    h.add_argument("--energy-budget", type=number("--energy-budget", "29"), default=None, metavar="E",
                   help="budget on the training batch's geometric-mean control energy int |u|^2 dt "
                        "(default: none, the fastest gains the step budget allows)")


def _add_search_options(p) -> None:
    """--search and what only it uses."""
    d = p.add_argument_group("derivative-free search (the balanced preset's method)")
    d.add_argument("--search", action="store_true",
                   help="instead of gradient descent on the surrogate, search (CMA-ES) for the gains with the "
                        "shortest median T_0.05 on the training starts whose median control energy is at most "
                        "--energy-margin x the --gains' (or --energy-budget), with no fewer converged and no start "
                        "failing or crossing theta = 0, all measured by the accurate engine over 100 s")
    d.add_argument("--population", type=whole("--population", "16", minimum=2), default=16, metavar="P",
                   help="candidates per generation, run together in one ensemble (default 16)")
    d.add_argument("--energy-margin", type=number("--energy-margin", "0.95"), default=0.95, metavar="F",
                   help="energy budget as a fraction of the starting gains' median energy on the training "
                        "starts (default 0.95: room for the median's sampling noise on other starts)")
    d.add_argument("--energy-percentiles", type=_percentiles, default=(50.0,), metavar="P,P,...",
                   help="hold the energy within --energy-margin x the --gains' at each of these percentiles over the "
                        "training starts, not only the median (e.g. 50,75,90: the energy is bimodal, and a median "
                        "budget lets the upper half grow several-fold)")


def _add_pareto_options(p) -> None:
    """--pareto and what only the front uses."""
    f = p.add_argument_group("Pareto front")
    f.add_argument("--pareto", type=whole("--pareto", "6"), default=None, metavar="N",
                   help="compute N points (at most 100) of the time-effort front instead of one set of gains")
    f.add_argument("--front-method", choices=["warm", "vmap"], default="warm",
                   help="warm: budgets in turn, each from the last point's gains (default); vmap: every budget "
                        "at once, the optimiser vmapped over budgets")
    f.add_argument("--budgets", default=None, metavar="LO:HI",
                   help="energy budgets (geometric spacing; default: paper's training energy / 4 to tuned's x 2)")
    f.add_argument("--warm-steps", type=whole("--warm-steps", "40"), default=None, metavar="N",
                   help="iterations of each warm-started point after the first (default --steps / 2)")
    f.add_argument("--baseline", action="store_true",
                   help="also run a random search with the same number of objective evaluations")
    f.add_argument("--plot", default=None, metavar="FILE.png", help="draw the front")


def add_tune(subparsers) -> None:
    """Register ``tune`` on an ``argparse`` subparsers object."""
    p = subparsers.add_parser(
        "tune", help="tune the gains for fast convergence (gradients through the integrator)",
        description="Tune the controller's gains (L, k, D_hat) by gradient descent (optax Adam) on a smooth "
                    "surrogate of the convergence time, differentiating through the integrator, and write "
                    "the best valid gains as a gains JSON file.",
        epilog=_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, metavar="FILE.json",
                   help="output gains file (with --pareto: the front's JSON file)")
    p.add_argument("--resume", action="store_true",
                   help="continue an interrupted run from its checkpoint FILE.json.ckpt.npz (same options; with "
                        "--pareto: from the finished points kept in FILE.json)")
    for add in (_add_optimiser_options, _add_objective_options, _add_search_options, _add_pareto_options):
        add(p)
    add_model_options(p)
    add_sampler_options(p, seed=False)          # --seed (above) also seeds the measurement noise
    p.add_argument("--history", default=None, metavar="FILE.npz",
                   help="also write the history (loss, gains, gradient norm per iteration)")
    p.add_argument("--validate", type=whole("--validate", "256", minimum=0), default=256, metavar="N",
                   help="held-out starts for the final check with the accurate engine (0: skip; default 256)")
    # --rtol, --atol: the accurate engine's, in the held-out check (every mode) and in every run of --search
    add_tolerance_options(p.add_argument_group("the accurate engine's tolerances (held-out check; --search)"))
    add_progress_option(p)
    p.set_defaults(func=_cmd_tune)


def _checkpoint_path(out) -> Path:
    out = Path(out)
    return out.with_name(out.name + ".ckpt.npz")


def _checked_checkpoint(args, what: str) -> Path:
    """The run's checkpoint ``FILE.json.ckpt.npz``, after checking the outputs and that ``--resume`` matches
    whether an interrupted ``what`` left one."""
    ckpt = _checkpoint_path(args.out)
    check_outputs(args.out, args.history, ckpt)
    if ckpt.exists() and not args.resume:
        raise ValueError(f"{str(ckpt)!r} holds the state of an earlier, interrupted {what} for {args.out!r}; add "
                         f"--resume (with the same options) to continue it, or delete it to start afresh")
    if args.resume and not ckpt.exists():
        raise ValueError(f"--resume: no checkpoint {str(ckpt)!r} to continue from; run without --resume")
    return ckpt


def _cmd_tune_law(args, plant, law) -> int:
    """``jaxsleigh tune --controller NAME`` (or the paper's law behind ``--saturation`` / ``--sample-period``): Adam on
    the tuner's objective over the law's gains (`jaxsleigh.tuning.tune_law`), under ``--energy-budget``, checkpointed
    after every step; writes the tuned law as a controller file (`jaxsleigh.tuning.law_file`)."""
    from .. import tuning
    from ..tuning.law import InvalidStartingLaw

    ckpt = _checked_checkpoint(args, "tuning run")
    options = _flag_values(args, _LAW_FLAGS)
    if args.resume:
        _check_resumed_options(ckpt, options, _LAW_FLAGS)
    names = tuning.gain_names(law) if args.tune == "L,k,D_hat" else [n.strip() for n in args.tune.split(",")]
    starts = tuning.draw_starts(tuning.UniformStarts(), args.batch, args.seed)
    t0 = time.perf_counter()
    try:
        res = tuning.tune_law(law, starts, tune=names, plant=plant, loss=_loss_config(args), steps=args.steps,
                              lr=args.lr, x64=args.x64, n_attempts=args.n_attempts, checkpoint=ckpt,
                              resume=args.resume, options=options)
    except InvalidStartingLaw:
        raise ValueError(_invalid_law_message(args)) from None
    except tuning.TuningInterrupted as stop:
        return _law_interrupted(args, stop.partial, names)
    wall = time.perf_counter() - t0
    met = _budget_met(args, res.energy)
    _write_law(args, res, names, wall_s=wall, **({} if met is None else {"energy_budget_met": met}))
    ckpt.unlink(missing_ok=True)
    print(f"{PROG} tune --controller {args.controller}: tuned {', '.join(names)} in {len(res.history['loss'])} "
          f"steps; training loss {res.loss:.4g}, energy {res.energy:.4g}; wrote {args.out}"
          + (f" and {args.history}" if args.history else ""))
    return _budget_exit(args, res.energy, met)


#: The flags that determine a run of each mode, in the order a refused ``--resume`` names them (``--steps`` is
#: left out where a resumed run may go on for more steps: a law's and a search's).
_LAW_FLAGS = ("controller", "gains", "saturation", "sample_period", "delay", "noise", "params", "damping", "tune",
              "seed", "batch", "lr", "t_final", "dt", "stop_fraction", "energy_budget", "n_attempts", "x64")
_GRADIENT_FLAGS = ("gains", "params", "damping", "robust", "tune", "seed", "batch", "steps", "lr", "mode", "t_final",
                   "dt", "n_attempts", "probe_budget", "stop_fraction", "energy_budget", "x64")
_SEARCH_FLAGS = ("gains", "params", "damping", "tune", "seed", "batch", "population", "energy_margin",
                 "energy_budget", "energy_percentiles", "rtol", "atol", "x64")


def _flag_values(args, names) -> dict:
    """``{flag: value}`` of the options ``names``, recorded in the checkpoint."""
    return {"--" + k.replace("_", "-"): _jsonable(getattr(args, k, None)) for k in names}


def _check_resumed_options(ckpt, options: dict, order) -> None:
    """Refuse ``--resume`` when a flag differs from the one the checkpoint was written with, naming the first that
    differs (in ``order``) with both values. A checkpoint that records no flags is left to the tuner's own check."""
    from ..tuning.checkpoint import checkpoint_options

    old = checkpoint_options(ckpt)
    if old is None:
        return
    for flag in ("--" + k.replace("_", "-") for k in order):
        a, b = old.get(flag), _jsonable(options.get(flag))
        if a != b:
            raise ValueError(f"{flag} differs from the checkpoint's ({_shown(a)} in the checkpoint vs {_shown(b)} "
                             f"now): rerun with the same flags and --resume to continue it, or choose another --out "
                             f"to start afresh")


def _jsonable(v):
    """``v`` as it reads back from the checkpoint's JSON (tuples as lists)."""
    return json.loads(json.dumps(v, default=str))


def _shown(v) -> str:
    """A flag's value in a message: ``none`` when unset, ``on`` / ``off`` for a switch."""
    if v is None:
        return "none"
    if isinstance(v, bool):
        return "on" if v else "off"
    return ",".join(map(str, v)) if isinstance(v, list) else str(v)


def _invalid_law_message(args) -> str:
    """What to do when the starting law is not a valid candidate, in command-line terms."""
    actuator = " ".join(f"--{k.replace('_', '-')} {getattr(args, k)}" for k in ("saturation", "sample_period")
                        if getattr(args, k, None) is not None)
    return (f"the starting law ({args.controller}{', ' + actuator if actuator else ''}) is not a valid candidate: a "
            f"training start failed or ran out of its step budget, or the loss is not finite; see which with "
            f"{PROG} simulate --controller {args.controller}{' ' + actuator if actuator else ''} --ic X,Y,THETA "
            f"--t-final {args.t_final:g} --out run.npz, then raise --n-attempts, shorten --t-final or choose "
            f"another --controller")


def _budget_met(args, energy: float):
    """Whether the training energy is within ``--energy-budget`` (``None`` without one)."""
    if args.energy_budget is None:
        return None
    return bool(math.isfinite(energy) and energy <= args.energy_budget)


def _budget_exit(args, energy: float, met) -> int:
    """The exit code of a finished run: 0, or `EXIT_NONE_OK` with a line on stderr when ``--energy-budget`` was not
    met (the file is written all the same, with ``"energy_budget_met": false``)."""
    if met is None or met:
        return 0
    print(f"{PROG} tune: the tuned gains do not meet --energy-budget {args.energy_budget:g}: their training energy is "
          f"{energy:.4g}; {args.out} is written with \"energy_budget_met\": false. Raise --energy-budget, or run "
          f"more --steps (exit code {EXIT_NONE_OK})", file=sys.stderr)
    return EXIT_NONE_OK


def _write_law(args, res, names, **extra) -> None:
    """Write the tuned law (`jaxsleigh.tuning.law_file.save_law`) with how it was found, and its ``--history``."""
    from ..tuning.law_file import save_law

    save_law(res.law, args.controller, args.out, how="jaxsleigh tune --controller: Adam on the soft convergence "
             "time" + ("" if args.energy_budget is None else f" under a training energy budget {args.energy_budget:g}"),
             command=_command(args), tuned=list(names), training_loss=res.loss, training_energy=res.energy,
             energy_budget=args.energy_budget, seed=args.seed, batch=args.batch, x64=bool(args.x64),
             plant={"params": args.params, "damping": args.damping},
             history={k: np.asarray(v).tolist() for k, v in res.history.items()}, **extra)
    _write_law_history(args, res.history)


def _write_law_history(args, history) -> None:
    """``--history FILE.npz``: the loss, training energy and validity per step."""
    if args.history:
        from ..files.npz import atomic_write

        hist = args.history if str(args.history).endswith(".npz") else str(args.history) + ".npz"
        atomic_write(hist, lambda fh: np.savez(fh, **{k: np.asarray(v) for k, v in history.items()}))


def _law_interrupted(args, partial, names) -> int:
    """Ctrl-C during ``tune --controller``: write the best valid law so far (if any) and say how to continue."""
    if partial is None:
        print(f"{PROG} tune: interrupted before any valid candidate; nothing written. Continue with the same "
              f"command and --resume", file=sys.stderr)
        return EXIT_INTERRUPTED
    _write_law(args, partial, names, interrupted=True)
    print(f"{PROG} tune: interrupted after {len(partial.history['loss'])} steps; wrote the best valid law so far "
          f"(training loss {partial.loss:.4g}) to {args.out}" + (f" and {args.history}" if args.history else "")
          + "; continue with the same command and --resume", file=sys.stderr)
    return EXIT_INTERRUPTED


#: Options that only --search uses, with their defaults.
_SEARCH_ONLY = {"population": 16, "energy_margin": 0.95, "energy_percentiles": (50.0,)}


def _check_stepsize(args):
    """The accurate engine's step-size controller from --rtol / --atol (``None`` without them: the
    defaults, and the fingerprints of earlier runs unchanged); refused where nothing would use it."""
    if args.rtol is None and args.atol is None:
        return None
    if not args.search and not args.validate:
        used = " and ".join(f for f, v in (("--rtol", args.rtol), ("--atol", args.atol)) if v is not None)
        raise ValueError(f"{used} set the tolerance of the held-out check, and --validate 0 skips it: drop {used} "
                         f"or --validate 0")
    from ..integrate.stepsize import StepSizeController

    return StepSizeController(rtol=args.rtol, atol=args.atol)


def _cmd_tune(args) -> int:
    """``jaxsleigh tune``: `_tune_mode`, its refusals in terms of the flags (`_in_flags`)."""
    try:
        return _tune_mode(args)
    except ValueError as e:
        if type(e) is not ValueError:          # a typed error keeps its own exit code and words
            raise
        raise ValueError(_in_flags(str(e))) from None


#: The tuners' keywords and phrases as the command line's flags, in the order they are replaced.
_KEYWORD_FLAGS = (("probe_budget = ", "--probe-budget "), ("probe_budget", "--probe-budget"),
                  ("n_attempts", "--n-attempts"), ("t_final", "--t-final"), ("energy_budget", "--energy-budget"),
                  ("energy_margin", "--energy-margin"), ("energy_percentiles", "--energy-percentiles"),
                  ("resume=True", "--resume"), ("a smaller learning rate", "a smaller --lr"),
                  ("fewer steps", "fewer --steps"), ("start from other gains", "start from other --gains"))


def _in_flags(message: str) -> str:
    """A tuner's message with its keywords (``n_attempts``) as the flags that set them (``--n-attempts``); words
    inside paths and flags are left alone."""
    import re

    for word, flag in _KEYWORD_FLAGS:
        tail = r"(?!\w)" if word[-1].isalnum() else ""
        message = re.sub(r"(?<![\w/.\-])" + re.escape(word) + tail, flag, message)
    return message


def _tune_mode(args) -> int:
    """``jaxsleigh tune``: the search, the front, or gradient descent, as the flags say."""
    search = args.search
    if (getattr(args, "controller", "paper") != "paper" or getattr(args, "saturation", None) is not None
            or getattr(args, "sample_period", None) is not None):
        for flag, on in (("--search", search), ("--pareto", args.pareto is not None), ("--robust", args.robust)):
            if on:
                raise ValueError(f"{flag} tunes only the paper's law without an actuator: drop {flag}, or drop "
                                 f"--controller / --saturation / --sample-period")
    if args.steps is None:
        args.steps = 100 if search else 150
    if args.batch is None:
        args.batch = 128 if search else 256
    if search:
        return _cmd_search(args)
    used = ["--" + k.replace("_", "-") for k, v in _SEARCH_ONLY.items() if getattr(args, k) != v]
    if used:
        raise ValueError(f"{', '.join(used)} belong to --search; add --search or drop them")
    _check_stepsize(args)
    if args.pareto is not None:
        return _cmd_pareto(args)
    if args.plot is not None:         # refused now, not silently ignored after the run
        raise ValueError("--plot draws the Pareto front; add --pareto N, or drop --plot")
    return _cmd_gradient(args)


def _cmd_gradient(args) -> int:
    """Gradient descent on the surrogate (`jaxsleigh.tuning.tune`), or `_cmd_tune_law` for another law."""
    from .. import tuning
    from ..model.params import Gains, save_gains

    if args.robust and (args.params != "2,1,1" or args.damping != "coulomb"):
        raise ValueError("--robust samples the plants itself; drop --params / --damping (or drop --robust)")
    plant, gains0 = model_from_args(args)
    if not isinstance(gains0, Gains):
        return _tune_other_law(args, plant, gains0)
    names = tuning.parse_tune(args.tune)
    ckpt = _checked_checkpoint(args, "tuning run")
    options = _flag_values(args, _GRADIENT_FLAGS)
    if args.resume:
        _check_resumed_options(ckpt, options, _GRADIENT_FLAGS)
    config, loss = _tune_config(args), _loss_config(args)
    robust = tuning.PlantDistribution() if args.robust else None
    command = _command(args)
    t0 = time.perf_counter()
    try:
        res = tuning.tune(gains0, config=config, loss=loss, tune=names, plant=None if args.robust else plant,
                          robust=robust, x64=args.x64, progress=args.progress, checkpoint=ckpt, resume=args.resume,
                          options=options)
    except RuntimeError as e:          # no candidate passed the final check: say what to change
        raise ValueError(str(e)) from None
    except tuning.TuningInterrupted as stop:
        return _gradient_interrupted(args, stop.partial, command)
    wall = time.perf_counter() - t0
    meta = _gradient_record(args, res, names, command, plant, wall)
    energy = float(res.history.energy[res.best_iteration])
    met = _budget_met(args, energy)
    if met is not None:
        meta.update(energy_budget=args.energy_budget, training_energy=energy, energy_budget_met=met)
    print(f"{PROG} tune: loss {res.initial_loss:.4f} -> {res.best_loss:.4f} (iteration {res.best_iteration} of "
          f"{res.settings['iterations_run']}), {wall:.1f} s wall ({res.settings['dtype']}, {args.mode} mode)")
    save_gains(res.gains, args.out, **meta)   # written before the validation, so it cannot be lost
    _save_tuned_history(args, res.history)
    ckpt.unlink(missing_ok=True)
    if args.validate:
        _validate_tuned(args, res, plant, meta)
    _print_written_gains(args, res.gains)
    return _budget_exit(args, energy, met)


def _save_tuned_history(args, history) -> None:
    """``--history FILE.npz`` after gradient descent: write it and say where."""
    if args.history:
        from .. import tuning

        print(f"{PROG} tune: wrote history {tuning.save_history(history, args.history)}")


def _tune_other_law(args, plant, law) -> int:
    """``tune --controller NAME``: `_cmd_tune_law`, after refusing --rtol / --atol (it runs no held-out check)."""
    if args.rtol is not None or args.atol is not None:
        raise ValueError("--rtol / --atol set the tolerance of the held-out check, which tune --controller "
                         "does not run: drop them")
    return _cmd_tune_law(args, plant, law)


def _tune_config(args):
    """The gradient optimiser's settings from the flags (`jaxsleigh.tuning.TuneConfig`)."""
    from .. import tuning

    return tuning.TuneConfig(steps=args.steps, batch=args.batch, seed=args.seed, lr=args.lr, mode=args.mode,
                             n_attempts=args.n_attempts, probe_budget=args.probe_budget)


def _loss_config(args):
    """The surrogate's settings from the flags (`jaxsleigh.tuning.LossConfig`); no --energy-budget: none (inf)."""
    from .. import tuning

    return tuning.LossConfig(t_final=args.t_final, dt=args.dt, max_step=10 * args.dt, stop_fraction=args.stop_fraction,
                             energy_budget=math.inf if args.energy_budget is None else args.energy_budget)


def _command(args) -> list:
    """The command line recorded in the written files: the caller's argv, else `_canonical_argv`."""
    return [PROG, *getattr(args, "_argv", _canonical_argv(args))]


def _held_out_starts(args) -> np.ndarray:
    """The ``--validate`` held-out starts (seed ``--seed + 1000``)."""
    from .. import tuning

    return tuning.UniformStarts()(np.random.default_rng(args.seed + 1000), args.validate)


def _held_out_rows(args, res, plant, stepsize, label) -> dict:
    """The initial and the found gains of ``res`` measured on the held-out starts with the accurate engine."""
    from .. import tuning

    ics = _held_out_starts(args)
    return {"initial": tuning.validate(res.initial, ics, plant=plant, x64=args.x64, stepsize=stepsize),
            label: tuning.validate(res.gains, ics, plant=plant, x64=args.x64, stepsize=stepsize)}


def _print_written_gains(args, g) -> None:
    """The closing line of a run that wrote one set of gains."""
    print(f"{PROG} tune: wrote {args.out}: L = {np.round(g.L, 4).tolist()}, k = {float(g.k):.4g}, "
          f"D_hat = {np.round(g.D_hat, 4).tolist()}")


def _gradient_record(args, res, names, command, plant, wall) -> dict:
    """What a gradient-tuned gains file records beside the gains: how and from what they were found."""
    from ..model.params import gains_to_dict

    return {
        "how": f"jaxsleigh tune: {res.settings['method']}",
        "command": command, "tuned": list(names), "initial_gains": gains_to_dict(res.initial),
        "initial_loss": res.initial_loss, "best_loss": res.best_loss, "best_iteration": res.best_iteration,
        "iterations_run": res.settings["iterations_run"], "seed": args.seed, "batch": args.batch,
        "dtype": res.settings["dtype"], "plant": "sampled (robust)" if args.robust else
        {"m": float(plant.m), "J": float(plant.J), "l": float(plant.l), "damping": args.damping},
        "objective": res.settings["loss"], "wall_s": wall,
    }


def _validate_tuned(args, res, plant, meta) -> None:
    """``--validate N`` after gradient descent: print the held-out table and rewrite the file with it in ``meta``."""
    from .. import tuning
    from ..model.params import save_gains

    rows = _held_out_rows(args, res, plant, _check_stepsize(args), "tuned")
    meta["validation"] = {k: {"n": v.n, "seed": args.seed + 1000, "rtol": args.rtol, "atol": args.atol,
                              "median_T_0.05": _num(v.median),
                              "median_se": _num(v.median_se), "frac_converged_100s": v.frac_converged,
                              "frac_se": v.frac_se, "n_failed": v.n_failed}
                          for k, v in rows.items()}
    print(tuning.markdown_table(rows))
    save_gains(res.gains, args.out, **meta)


def _gradient_interrupted(args, part, command) -> int:
    """Ctrl-C during gradient descent: write the best valid gains so far (if any) and say how to continue."""
    from .. import tuning
    from ..model.params import save_gains

    if part is None:
        print(f"{PROG} tune: interrupted before any valid candidate; nothing written. Continue with the same "
              f"command and --resume", file=sys.stderr)
        return EXIT_INTERRUPTED
    save_gains(part.gains, args.out, how="jaxsleigh tune, INTERRUPTED: the best valid candidate so far, "
               "not re-checked with the accurate engine", command=command, interrupted=True,
               best_loss=part.best_loss, best_iteration=part.best_iteration,
               iterations_run=part.settings["iterations_run"])
    written = [str(args.out)]
    if args.history:
        written.append(str(tuning.save_history(part.history, args.history)))
    print(f"{PROG} tune: interrupted after {part.settings['iterations_run']} iterations; wrote the best valid "
          f"gains so far (loss {part.best_loss:.4f}, not re-checked) to {', '.join(written)}; continue with "
          f"the same command and --resume", file=sys.stderr)
    return EXIT_INTERRUPTED


#: Options of the gradient tuner that a search does not use, with their defaults.
_GRADIENT_ONLY = {"pareto": None, "robust": False, "lr": 0.05, "mode": "forward", "t_final": 30.0, "dt": 0.01,
                  "n_attempts": 4000, "probe_budget": 100000, "stop_fraction": 0.5, "front_method": "warm",
                  "budgets": None, "warm_steps": None, "baseline": False, "plot": None}


def _check_search(args) -> None:
    """Every flag of ``--search`` checked before any work (`ValueError` naming the flag)."""
    used = [k for k, v in _GRADIENT_ONLY.items() if getattr(args, k) != v]
    if used:
        raise ValueError("--search measures 100 s with the accurate engine and has no gradient optimiser: drop "
                         + ", ".join("--" + k.replace("_", "-") for k in used))
    if args.energy_budget is not None and args.energy_margin != 0.95:
        raise ValueError("give the budget once: --energy-budget E (absolute) or --energy-margin F (relative), not both")
    if not 0 < args.energy_margin <= 10:
        raise ValueError(f"--energy-margin must be in (0, 10], got {args.energy_margin}")
    from ..tuning.cma_search import MAX_GENERATIONS, MAX_POPULATION
    from ..validate import check_count, check_memory

    check_count("--steps (generations of --search)", args.steps, maximum=MAX_GENERATIONS,
                reason="each generation runs the whole population on the training starts over 100 s (100 take "
                       "about an hour)", fix="search in stages: a later run with a larger --steps and --resume continues")
    check_count("--population", args.population, maximum=MAX_POPULATION,
                reason="a generation is one ensemble of --population x --batch trajectories",
                fix="use a smaller --population (16 is the default)")
    check_memory(args.population * args.batch, "--population x --batch", unit="trajectories per generation",
                 fix="use a smaller --population or --batch")


def _no_feasible_message(args, e, hist) -> str:
    """What to change when a search finished without feasible gains (`NoFeasibleCandidate` ``e``)."""
    r = e.reference
    if e.reason == "infeasible":
        budget = (f"--energy-budget {args.energy_budget:g}" if args.energy_budget is not None
                  else f"--energy-margin {args.energy_margin:g}")
        at = r.get("energy_budgets", {"p50": r["energy_budget"]})
        budgets = ", ".join(f"{v:.4g} at the {k[1:]}th percentile" for k, v in at.items())
        fix = (f"no candidate had energy <= {budgets} ({budget}) with converged >= {r['converged_floor']:.3f}; raise "
               f"{budget.split()[0]}, or run more generations (the same command with a larger --steps and --resume)")
    else:
        fix = (f"{str(e).split('search: ', 1)[-1]}; run more generations (the same command with a larger --steps "
               f"and --resume) or a larger --population")
    return (f"{PROG}: error: tune --search found no feasible gains in {e.settings['generations_run']} generations: "
            f"{fix}. Nothing written to {args.out}" + (f"; wrote the history {hist}" if hist else ""))


def _search_record(args, res, names, command, plant, **extra) -> dict:
    """What a ``--search`` gains file records beside the gains: how and from what they were found."""
    from ..model.params import gains_to_dict

    return {"how": "jaxsleigh tune --search: CMA-ES on the accurate engine's median T_0.05 under a "
                   "control-energy budget at the percentiles " + ", ".join(f"{q:g}" for q in args.energy_percentiles),
            "command": command, "tuned": list(names), "rtol": args.rtol, "atol": args.atol,
            "initial_gains": gains_to_dict(res.initial), "training_figures": res.figures,
            "reference_figures": res.reference, "best_generation": res.best_generation,
            "generations_run": res.settings["generations_run"], "seed": args.seed, "batch": args.batch,
            "population": args.population, "plant": {"m": float(plant.m), "J": float(plant.J),
                                                     "l": float(plant.l), "damping": args.damping},
            "x64": bool(args.x64), **extra}


def _write_search_history(args, history):
    """``--history FILE.npz``: the search's generations; returns the path written (``None`` without it)."""
    if not args.history:
        return None
    from ..files.npz import atomic_write

    hist = args.history if str(args.history).endswith(".npz") else str(args.history) + ".npz"
    atomic_write(hist, lambda fh: np.savez(fh, **history))
    return hist


def _cmd_search(args) -> int:
    """``jaxsleigh tune --search``: CMA-ES on the held-out figures themselves (`jaxsleigh.tuning.search`)."""
    from .. import tuning
    from ..tuning.cma_search import NoFeasibleCandidate

    _check_search(args)
    plant, gains0 = model_from_args(args)
    ckpt = _checked_checkpoint(args, "search")
    options = _flag_values(args, _SEARCH_FLAGS)
    if args.resume:
        _check_resumed_options(ckpt, options, _SEARCH_FLAGS)
    names, config = tuning.parse_tune(args.tune), _search_config(args)
    stepsize = _check_stepsize(args)
    command = _command(args)
    t0 = time.perf_counter()
    write = functools.partial(_write_search, args, names, command, plant)   # write(res, **extra)
    try:
        res = tuning.search(gains0, config=config, reference=gains0,
                            energy_budget=args.energy_budget, tune=names, plant=plant, x64=args.x64,
                            stepsize=stepsize, progress=args.progress, checkpoint=ckpt, resume=args.resume,
                            options=options)
    except NoFeasibleCandidate as e:
        # the run finished: keep its history and checkpoint (more generations resume it), name the flags
        print(_no_feasible_message(args, e, _write_search_history(args, e.history)), file=sys.stderr)
        return EXIT_NONE_OK
    except RuntimeError as e:
        raise ValueError(str(e)) from None
    except tuning.TuningInterrupted as stop:
        return _search_interrupted(args, stop.partial, write)
    wall = time.perf_counter() - t0
    _print_search_summary(args, res, wall)
    write(res, wall_s=wall)
    ckpt.unlink(missing_ok=True)
    if args.validate:
        _validate_searched(args, res, plant, stepsize, write, wall)
    _print_written_gains(args, res.gains)
    return 0


def _search_config(args):
    """The search's settings from the flags (`jaxsleigh.tuning.SearchConfig`)."""
    from .. import tuning

    return tuning.SearchConfig(generations=args.steps, population=args.population, batch=args.batch,
                               seed=args.seed, energy_margin=args.energy_margin,
                               energy_percentiles=args.energy_percentiles)


def _validate_searched(args, res, plant, stepsize, write, wall) -> None:
    """``--validate N`` after the search: print the held-out table and rewrite the file (``write``) with it."""
    from .. import tuning

    rows = _held_out_rows(args, res, plant, stepsize, "searched")
    print(tuning.markdown_table(rows))
    write(res, wall_s=wall, validation={k: tuning.validation_dict(v, seed=args.seed + 1000) for k, v in rows.items()})


def _write_search(args, names, command, plant, res, **extra) -> None:
    """Write the search's gains file (with `_search_record`) and its ``--history``."""
    from ..model.params import save_gains

    save_gains(res.gains, args.out, **_search_record(args, res, names, command, plant, **extra))
    _write_search_history(args, res.history)


def _search_interrupted(args, partial, write) -> int:
    """Ctrl-C during the search: write the best feasible gains so far (if any) and say how to continue."""
    if partial is None:
        print(f"{PROG} tune: interrupted before any feasible candidate; nothing written. Continue with the "
              f"same command and --resume", file=sys.stderr)
        return EXIT_INTERRUPTED
    write(partial, interrupted=True)
    print(f"{PROG} tune: interrupted after {partial.settings['generations_run']} generations; wrote the "
          f"best feasible gains so far (not checked on the guard starts) to {args.out}; continue with the same "
          f"command and --resume", file=sys.stderr)
    return EXIT_INTERRUPTED


def _print_search_summary(args, res, wall) -> None:
    """The search's training figures, reference -> found."""
    f, r = res.figures, res.reference
    print(f"{PROG} tune --search: median T_0.05 {r['median_T']:.2f} s -> {f['median_T']:.2f} s on the {args.batch} "
          f"training starts, median energy {r['median_energy']:.4g} -> {f['median_energy']:.4g} (budget "
          f"{r['energy_budget']:.4g}), converged {r['frac_converged']:.3f} -> {f['frac_converged']:.3f}; "
          f"generation {res.best_generation} of {res.settings['generations_run']}, {wall:.1f} s wall")


def _earlier_front(args):
    """Every flag of ``--pareto`` checked before any work (`ValueError` naming the flag); returns the
    interrupted front that ``--resume`` continues (its JSON document), or ``None``."""
    from .. import tuning
    from ..tuning.pareto import MAX_FRONT_POINTS
    from ..validate import check_count

    if args.robust or args.history or args.energy_budget is not None:
        raise ValueError("--pareto computes its own budgets and has no history file: drop --robust, "
                         "--history and --energy-budget")
    check_count("--pareto", args.pareto, maximum=MAX_FRONT_POINTS,
                reason="every point is a whole tuning run (seconds to minutes each; 1000 points took about 50 "
                       "minutes), and a front is drawn well by a few dozen",
                fix="give fewer points, or compute several fronts over narrower --budgets ranges")
    if args.front_method != "warm" and args.resume:
        raise ValueError("--front-method vmap computes every point at once and keeps no finished points to resume: "
                         "use --front-method warm to continue an interrupted front, or drop --resume")
    if args.plot and not args.validate:
        raise ValueError("--plot draws the front validated on the held-out starts; drop --validate 0 or drop --plot")
    check_outputs(args.out, figures={"--plot": args.plot})
    earlier = None
    if Path(args.out).is_file():
        try:
            earlier = tuning.load_front(args.out)
        except ValueError:
            earlier = None
        earlier = earlier if isinstance(earlier, dict) and earlier.get("interrupted") else None
    if earlier is not None and not args.resume:
        raise ValueError(f"{args.out!r} holds the finished points of an interrupted front; add --resume (with the "
                         f"same options) to continue it, or delete it to start afresh")
    if args.resume and earlier is None:
        raise ValueError(f"--resume: {args.out!r} is not an interrupted front to continue; run without --resume")
    return earlier


def _front_budgets(args, kw) -> np.ndarray:
    """``--budgets LO:HI`` spaced geometrically over ``--pareto`` points, else the default span."""
    from .. import tuning

    if not args.budgets:
        return tuning.default_budgets(args.pareto, **kw)
    try:
        lo, hi = (float(x) for x in args.budgets.split(":"))
    except ValueError:
        raise ValueError(f"--budgets must be LO:HI (e.g. --budgets 7:2400), got {args.budgets!r}") from None
    return tuning.budgets_between(lo, hi, args.pareto)


def _validated_front(args, front, budgets, kw):
    """The held-out check of a finished front: ``(front, references, baseline)``, evaluated on
    ``--validate`` starts with the accurate engine (``--rtol`` / ``--atol``); printed as a table."""
    from .. import tuning

    if not args.validate:
        return front, {}, None
    ics = _held_out_starts(args)
    ss = {"plant": kw["plant"], "x64": args.x64, "stepsize": _check_stepsize(args)}
    front = tuning.evaluate_front(front, ics, **ss)
    refs = {"paper": tuning.validate("paper", ics, **ss), "tuned": tuning.validate("tuned", ics, **ss)}
    baseline = None
    if args.baseline:
        baseline = tuning.random_search(budgets, front.evaluations, seed=args.seed, progress=args.progress, **kw)
        baseline = tuning.evaluate_front(baseline, ics, **ss)
    print(tuning.markdown_table({**refs, **{f"budget {p.budget:.3g}": p.evaluation for p in front.points}}))
    return front, refs, baseline


def _cmd_pareto(args) -> int:
    """``jaxsleigh tune --pareto N``: the time-effort front, kept after every point, checked on held-out starts."""
    from .. import tuning
    from ..model.params import gains_to_dict, load_gains

    earlier = _earlier_front(args)
    plant, gains0 = model_from_args(args)
    names = tuning.parse_tune(args.tune)
    config, loss = _tune_config(args), _loss_config(args)   # --pareto refused --energy-budget: none here
    kw = dict(config=config, loss=loss, plant=plant, x64=args.x64)
    budgets = _front_budgets(args, kw)
    command = _command(args)
    done = None if earlier is None else _resumed_points(args, earlier, budgets, kw, gains0, names)
    initial = {"initial_gains": gains_to_dict(load_gains(gains0))}

    def keep(part):
        # after every point: the finished points, so that Ctrl-C (or a crash) loses at most the current one
        tuning.save_front(part, args.out, command=command, interrupted=True, **initial)

    try:
        front = tuning.pareto_front(budgets, method=args.front_method, gains0=gains0, warm_steps=args.warm_steps,
                                    tune_names=names, progress=args.progress, on_point=keep, done=done, **kw)
    except tuning.TuningInterrupted as stop:
        return _front_interrupted(args, stop.partial, len(budgets), keep)
    print(f"{PROG} tune: {len(front.points)} points ({args.front_method}) in {front.wall_s:.1f} s, "
          f"{front.evaluations} objective evaluations")
    front, refs, baseline = _validated_front(args, front, budgets, kw)
    _save_front(args, front, refs, baseline, command, initial)
    print(f"{PROG} tune: wrote {args.out}" + (f" and {args.plot}" if args.plot and args.validate else ""))
    return 0


def _resumed_points(args, earlier, budgets, kw, gains0, names):
    """The points of the interrupted front ``earlier`` that ``--resume`` keeps (those computed as this run would)."""
    from .. import tuning
    from ..tuning.pareto import _front_settings, finished_points

    config = kw["config"]
    warm = max(1, config.steps // 2) if args.warm_steps is None else int(args.warm_steps)
    return finished_points(earlier, _front_settings("warm", np.sort(budgets), config, kw["loss"], warm, args.x64,
                                                    gains0, names, tuning.UniformStarts()))


def _front_interrupted(args, partial, n_budgets, keep) -> int:
    """Ctrl-C during the front: keep the finished points (if any) and say how to continue."""
    if partial is None:
        print(f"{PROG} tune: interrupted before the first point of the front was finished; nothing written",
              file=sys.stderr)
    else:
        keep(partial)
        print(f"{PROG} tune: interrupted after {len(partial.points)} of {n_budgets} points; wrote them "
              f"to {args.out} (\"interrupted\": true, not evaluated on held-out starts); continue with the same "
              f"command and --resume", file=sys.stderr)
    return EXIT_INTERRUPTED


def _save_front(args, front, refs, baseline, command, initial) -> None:
    """Write the finished front (references, held-out settings, baseline) and, with ``--plot``, its figure."""
    from .. import tuning

    meta = {"command": command, "held_out": {"n": args.validate, "seed": args.seed + 1000, "rtol": args.rtol,
                                             "atol": args.atol, "starts": repr(tuning.UniformStarts())}, **initial}
    if baseline is not None:
        meta["baseline"] = tuning.front_dict(baseline)
    tuning.save_front(front, args.out, references=refs, **meta)
    if args.plot and args.validate:
        from ..plots import tuning as tp

        doc = tuning.load_front(args.out)
        tp.save_figure(tp.plot_front(doc, baseline=doc.get("baseline")), args.plot)


def _canonical_argv(args) -> list:
    """The options that determine the result, as a command line (when the caller's argv is unknown)."""
    if getattr(args, "search", False):
        return ["tune", "--search", "--out", str(args.out), "--steps", str(args.steps), "--batch", str(args.batch),
                "--seed", str(args.seed), "--population", str(args.population), "--energy-margin",
                repr(args.energy_margin), "--tune", args.tune, "--gains", str(args.gains), "--params", args.params,
                "--damping", args.damping] + (["--energy-budget", repr(args.energy_budget)]
                                              if args.energy_budget is not None else []) + (
            ["--energy-percentiles", ",".join(f"{q:g}" for q in args.energy_percentiles)]
            if args.energy_percentiles != (50.0,) else []) + [
            a for flag in ("rtol", "atol") if getattr(args, flag) is not None
            for a in (f"--{flag}", repr(getattr(args, flag)))] + (["--x64"] if args.x64 else [])
    argv = ["tune", "--out", str(args.out), "--steps", str(args.steps), "--batch", str(args.batch),
            "--seed", str(args.seed), "--lr", repr(args.lr), "--tune", args.tune, "--mode", args.mode,
            "--t-final", repr(args.t_final), "--dt", repr(args.dt), "--n-attempts", str(args.n_attempts),
            "--probe-budget", str(args.probe_budget),
            "--gains", str(args.gains), "--params", args.params, "--damping", args.damping]
    if getattr(args, "stop_fraction", 0.5) != 0.5:
        argv += ["--stop-fraction", repr(args.stop_fraction)]
    if getattr(args, "energy_budget", None) is not None:
        argv += ["--energy-budget", repr(args.energy_budget)]
    if getattr(args, "pareto", None) is not None:
        argv += ["--pareto", str(args.pareto), "--front-method", args.front_method]
        argv += ["--budgets", args.budgets] if args.budgets else []
        argv += ["--warm-steps", str(args.warm_steps)] if args.warm_steps else []
        argv += ["--baseline"] if args.baseline else []
    return argv + (["--robust"] if args.robust else []) + (["--x64"] if args.x64 else [])


def _num(x: float):
    return x if math.isfinite(x) else str(x)
