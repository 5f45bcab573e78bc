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
`add_tune`. It parses the flags (`jaxsleigh.cli.tune_options`, `jaxsleigh.cli.tune_flags`), runs the tuner as a run
that owns ``--out`` (`jaxsleigh.tuning.runs`: lock, checkpoint, resume, the files written) and says what happened.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

from .common import EXIT_INTERRUPTED, EXIT_NONE_OK, PROG, model_from_args
from .tune_flags import (GRADIENT_FLAGS, LAW_FLAGS, PARETO_FLAGS, SEARCH_FLAGS, SEARCH_ONLY, check_pareto, check_search,
                         check_sizes, front_budgets, held_out, in_flags, loss_config, search_config, stepsize, tune_config,
                         tuning_run)
from .tune_options import EPILOG, add_tune_options
from ..model.params import Gains
from ..files.npz import npz_path
from ..studies.optimum import load_optimum

__all__ = ["add_tune"]


def add_tune(subparsers) -> None:
    """Register ``tune`` on an ``argparse`` subparsers object."""
    p = subparsers.add_parser(
        "tune", help="tune the gains for fast convergence (gradients through the integrator)",
        description="Tune the controller's gains (L, k, D_hat) by gradient descent (optax Adam) on a smooth "
                    "surrogate of the convergence time, differentiating through the integrator, and write "
                    "the best valid gains as a gains JSON file.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_tune_options(p)
    p.set_defaults(func=_cmd_tune)


def _cmd_tune(args) -> int:
    """``jaxsleigh tune``: `_tune_mode`, its refusals in terms of the flags (`in_flags`)."""
    try:
        return _tune_mode(args)
    except ValueError as e:
        if type(e) is not ValueError:          # a typed error keeps its own exit code and words
            raise
        raise ValueError(in_flags(str(e))) from None


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
    if args.batch is None and getattr(args, "frontier", None) is None:
        args.batch = 128 if search else 256
    if search:
        return _cmd_search(args)
    used = ["--" + k.replace("_", "-") for k, v in SEARCH_ONLY.items() if getattr(args, k) != v]
    if used:
        verb, them = ("belongs", "it") if len(used) == 1 else ("belong", "them")   # --frontier belongs to --search
        raise ValueError(f"{', '.join(used)} {verb} to --search; add --search or drop {them}")
    stepsize(args)
    check_sizes(args)
    if args.pareto is not None:
        return _cmd_pareto(args)
    if args.plot is not None:         # refused now, not silently ignored after the run
        raise ValueError("--plot draws the Pareto front; add --pareto N, or drop --plot")
    return _cmd_gradient(args)


def _cmd_gradient(args) -> int:
    """Gradient descent on the surrogate (`jaxsleigh.tuning.runs.tune_run`), or `_cmd_law` for another law."""
    from ..tuning import PlantDistribution
    from ..tuning.runs import tune_run

    if args.robust and (args.params != "2,1,1" or args.damping != "coulomb"):
        raise ValueError("--robust samples the plants itself; drop --params / --damping (or drop --robust)")
    plant, gains0 = model_from_args(args)
    if not isinstance(gains0, Gains):
        return _cmd_law(args, plant, gains0)
    try:
        o = tune_run(tuning_run(args, GRADIENT_FLAGS), gains0, config=tune_config(args), loss=loss_config(args),
                     tune=args.tune, plant=plant, robust=PlantDistribution() if args.robust else None, x64=args.x64,
                     progress=args.progress, held_out=held_out(args))
    except RuntimeError as e:          # no candidate passed the final check: say what to change
        raise ValueError(str(e)) from None
    if o.interrupted:
        return _interrupted(o, "any valid candidate", lambda r: (
            f"{r.settings['iterations_run']} iterations; wrote the best valid gains so far (loss {r.best_loss:.4f}, "
            f"not re-checked) to {', '.join(map(str, o.written))}"))
    res = o.result
    print(f"{PROG} tune: loss {res.initial_loss:.4f} -> {res.best_loss:.4f} (iteration {res.best_iteration} of "
          f"{res.settings['iterations_run']}), {o.wall_s:.1f} s wall ({res.settings['dtype']}, {args.mode} mode)")
    if args.history:
        print(f"{PROG} tune: wrote history {o.written[1]}")
    _print_held_out(o)
    _print_written_gains(args, res.gains)
    return _budget_exit(args, o)


def _cmd_law(args, plant, law) -> int:
    """``jaxsleigh tune --controller NAME`` (or the paper's law behind ``--saturation`` / ``--sample-period``): Adam on
    the tuner's objective over the law's gains (`jaxsleigh.tuning.runs.law_run`); writes the tuned law."""
    from ..tuning import gain_names
    from ..tuning.law import InvalidStartingLaw
    from ..tuning.runs import law_run

    names = gain_names(law) if args.tune == "L,k,D_hat" else [n.strip() for n in args.tune.split(",")]
    try:
        o = law_run(tuning_run(args, LAW_FLAGS), law, args.controller, batch=args.batch, seed=args.seed, tune=names,
                    plant=plant, loss=loss_config(args), steps=args.steps, lr=args.lr, x64=args.x64,
                    n_attempts=args.n_attempts, held_out=held_out(args))
    except InvalidStartingLaw:
        raise ValueError(_invalid_law_message(args)) from None
    if o.interrupted:
        return _interrupted(o, "any valid candidate", lambda r: (
            f"{len(r.history['loss'])} steps; wrote the best valid law so far (training loss {r.loss:.4g}) to "
            + " and ".join(map(str, o.written))))
    res = o.result
    print(f"{PROG} tune --controller {args.controller}: tuned {', '.join(names)} in {len(res.history['loss'])} "
          f"steps ({o.wall_s:.1f} s wall); training loss {res.loss:.4g}, energy {res.energy:.4g}; wrote "
          + " and ".join(map(str, o.written)))
    _print_held_out(o)
    return _budget_exit(args, o)


def _cmd_search(args) -> int:
    """``jaxsleigh tune --search``: CMA-ES on the held-out figures themselves (`jaxsleigh.tuning.runs.search_run`)."""
    from ..tuning.cma_search import NoFeasibleCandidate
    from ..tuning.runs import search_run

    frontier = _frontier(args)
    check_search(args)
    plant, gains0 = model_from_args(args)
    run = tuning_run(args, SEARCH_FLAGS)
    try:
        o = search_run(run, gains0, config=search_config(args), energy_budget=args.energy_budget, tune=args.tune,
                       plant=plant, x64=args.x64, stepsize=stepsize(args), progress=args.progress,
                       held_out=held_out(args), frontier=frontier)
    except NoFeasibleCandidate as e:
        # the run finished: its history and checkpoint are kept (more generations resume it); name the flags
        print(_no_feasible_message(args, e, run.history), file=sys.stderr)
        return EXIT_NONE_OK
    except RuntimeError as e:
        raise ValueError(str(e)) from None
    if o.interrupted:
        return _interrupted(o, "any feasible candidate", lambda r: (
            f"{r.settings['generations_run']} generations; wrote the best feasible gains so far (not checked on "
            f"the guard starts) to {args.out}"))
    res, f, r = o.result, o.result.figures, o.result.reference
    print(f"{PROG} tune --search: median T_0.05 {r['median_T']:.2f} s -> {f['median_T']:.2f} s on the {args.batch} "
          f"training starts, median energy {r['median_energy']:.4g} -> {f['median_energy']:.4g} (budget "
          f"{r['energy_budget']:.4g}), converged {r['frac_converged']:.3f} -> {f['frac_converged']:.3f}; "
          f"generation {res.best_generation} of {res.settings['generations_run']}, {o.wall_s:.1f} s wall")
    if frontier is not None:
        print(f"{PROG} tune --search: median gap to the optimum T_0.05 / T*(E) "
              f"{r.get('median_gap', math.inf):.3g} -> {f['median_gap']:.3g} (1 is the optimum; a start whose ratio "
              f"the frontier's horizons only bound counts as inf)")
    _print_held_out(o)
    _print_written_gains(args, res.gains)
    return 0


def _frontier(args):
    """``--frontier FILE``: the optimum result whose starts are the training starts (``--batch`` is their count)."""
    if getattr(args, "frontier", None) is None:
        return None

    if not (Path(args.frontier).exists() or npz_path(args.frontier).exists()):    # as a reader finds it (.npz added)
        raise ValueError(f"--frontier {args.frontier}: no such file; write one with 'jaxsleigh optimum --out "
                         f"{args.frontier}'")
    try:
        res = load_optimum(args.frontier)
    except ValueError as e:           # the reader's message names the file and what is wrong with it
        raise ValueError(f"--frontier: {e}") from None
    except (OSError, KeyError) as e:
        raise ValueError(f"--frontier {args.frontier} is not a file written by 'jaxsleigh optimum' "
                         f"({type(e).__name__}: {e})") from None
    n = int(res.starts.shape[0])
    if args.batch is not None and args.batch != n:
        raise ValueError(f"--frontier: its {n} starts are the training starts; drop --batch {args.batch}")
    args.batch = n
    return res


def _cmd_pareto(args) -> int:
    """``jaxsleigh tune --pareto N``: the time-effort front, kept after every point, checked on held-out starts
    (`jaxsleigh.tuning.runs.front_run`)."""
    from ..tuning.runs import front_run

    check_pareto(args)
    plant, gains0 = model_from_args(args)
    o = front_run(tuning_run(args, PARETO_FLAGS, history=False), front_budgets(args), method=args.front_method,
                  gains0=gains0, config=tune_config(args), loss=loss_config(args), warm_steps=args.warm_steps,
                  tune=args.tune, plant=plant, x64=args.x64, progress=args.progress, held_out=held_out(args),
                  baseline=args.baseline, plot=args.plot)
    if o.interrupted and o.result is None:
        print(f"{PROG} tune: interrupted before the first point of the front was finished; nothing written",
              file=sys.stderr)
        return EXIT_INTERRUPTED
    if o.interrupted:
        return _interrupted(o, "", lambda front: (
            f"{front.settings['iterations_run']} of {args.steps} iterations; wrote the best candidate so far of "
            f"{len(front.points)} of {args.pareto} budgets to {args.out} (\"interrupted\": true, not checked)"
            if front.method == "vmap" else f"{len(front.points)} of {args.pareto} points; wrote them to {args.out} "
            f"(\"interrupted\": true, not evaluated on held-out starts)"))
    front = o.result
    print(f"{PROG} tune: {len(front.points)} points ({args.front_method}) in {front.wall_s:.1f} s, "
          f"{front.evaluations} objective evaluations")
    _print_held_out(o)
    print(f"{PROG} tune: wrote " + " and ".join(map(str, o.written)))
    return 0


def _interrupted(outcome, before: str, after) -> int:
    """Ctrl-C: what the run kept (``after(partial result)``; nothing before ``before``) and how to continue."""
    said = (f"interrupted before {before}; nothing written. Continue" if outcome.result is None
            else f"interrupted after {after(outcome.result)}; continue")
    print(f"{PROG} tune: {said} with the same command and --resume", file=sys.stderr)
    return EXIT_INTERRUPTED


def _print_held_out(outcome) -> None:
    """The held-out check's table (nothing without one)."""
    if outcome.held_out:
        from ..tuning import markdown_table

        print(markdown_table(outcome.held_out))


def _print_written_gains(args, g) -> None:
    """The closing line of a run that wrote one set of gains."""
    print(f"{PROG} tune: wrote {args.out}: L = {np.round(g.L, 4).tolist()}, k = {float(g.k):.4g}, "
          f"D_hat = {np.round(g.D_hat, 4).tolist()}")


def _budget_exit(args, outcome) -> int:
    """The exit code of a finished run: 0, or `EXIT_NONE_OK` with a line on stderr when ``--energy-budget`` was not
    met (the file is written all the same, with ``"energy_budget_met": false``)."""
    if outcome.energy_budget_met in (None, True):
        return 0
    print(f"{PROG} tune: the tuned gains do not meet --energy-budget {args.energy_budget:g}: their training energy is "
          f"{outcome.energy:.4g}; {args.out} is written with \"energy_budget_met\": false. Raise --energy-budget, or "
          f"run more --steps (exit code {EXIT_NONE_OK})", file=sys.stderr)
    return EXIT_NONE_OK


def _invalid_law_message(args) -> str:
    """What to do when the starting law is not a valid candidate, in command-line terms."""
    actuator = " ".join(f"--{k.replace('_', '-')} {getattr(args, k)}" for k in ("saturation", "sample_period")
                        if getattr(args, k, None) is not None)
    return (f"the starting law ({args.controller}{', ' + actuator if actuator else ''}) is not a valid candidate: a "
            f"training start failed or ran out of its step budget, or the loss is not finite; see which with "
            f"{PROG} simulate --controller {args.controller}{' ' + actuator if actuator else ''} --ic X,Y,THETA "
            f"--t-final {args.t_final:g} --out run.npz, then raise --n-attempts, shorten --t-final or choose "
            f"another --controller")


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
