"""The flags of ``jaxsleigh tune`` as what the tuners take: the run that owns ``--out``
(`jaxsleigh.tuning.runs.TuningRun`), the settings of each mode, the held-out check, and the checks that refuse a flag
its mode would ignore (`ValueError` naming the flag, before any work)."""
from __future__ import annotations

import math
import re

from .common import PROG, check_outputs
from .chunked import CLI_WORDS
from ..integrate.stepsize import StepSizeController
from ..validate import check_count, check_memory

__all__ = ["LAW_FLAGS", "GRADIENT_FLAGS", "SEARCH_FLAGS", "tuning_run", "tune_config", "loss_config",
           "search_config", "held_out", "stepsize", "check_search", "check_sizes", "check_pareto", "front_budgets", "in_flags",
           "PARETO_FLAGS"]

#: The flags that determine a run of each mode, in the order a refused ``--resume`` names them (``--steps`` is
#: left out where a resumed run may go on for more steps: a law's and a search's).
LAW_FLAGS = ("controller", "gains", "saturation", "sample_period", "delay", "noise", "params", "damping", "tune",
             "seed", "batch", "lr", "t_final", "dt", "stop_fraction", "energy_budget", "n_attempts", "x64")
GRADIENT_FLAGS = ("gains", "params", "damping", "robust", "tune", "seed", "batch", "steps", "lr", "mode", "t_final",
                  "dt", "n_attempts", "probe_budget", "stop_fraction", "energy_budget", "x64")
PARETO_FLAGS = ("gains", "params", "damping", "tune", "seed", "batch", "steps", "lr", "mode", "t_final", "dt",
                "n_attempts", "probe_budget", "stop_fraction", "x64", "front_method", "budgets", "pareto")
SEARCH_FLAGS = ("gains", "params", "damping", "tune", "seed", "batch", "population", "energy_margin",
                "energy_budget", "energy_percentiles", "rtol", "atol", "x64", "frontier")

#: Options that only --search uses, with their defaults.
SEARCH_ONLY = {"population": 16, "energy_margin": 0.95, "energy_percentiles": (50.0,), "frontier": None}
#: Options of the gradient tuner that a search does not use, with their defaults.
_GRADIENT_ONLY = {"pareto": None, "robust": False, "lr": 0.05, "mode": "forward", "t_final": 30.0, "dt": 0.01,
                  "n_attempts": 4000, "probe_budget": 100000, "stop_fraction": 0.5, "front_method": "warm",
                  "budgets": None, "warm_steps": None, "baseline": False, "plot": None}


def tuning_run(args, flags=None, *, history: bool = True):
    """The `TuningRun` that owns ``--out`` (``--history``, ``--resume``; the values of ``flags`` recorded in the
    checkpoint, so that a refused ``--resume`` names the flag; the command line recorded in the files)."""
    from ..tuning.runs import TuningRun

    options = None if flags is None else {k: getattr(args, k, None) for k in flags}
    return TuningRun(args.out, history=args.history if history else None, resume=args.resume, options=options,
                     command=recorded_command(getattr(args, "_argv", _canonical_argv(args))), words=CLI_WORDS)


def recorded_command(argv) -> list:
    """The command line a tuner's files record: ``--resume`` left out, since a resumed run writes what the
    uninterrupted one does (its sidecar ``FILE.run.json`` says how the run went)."""
    return [PROG, *(str(a) for a in argv if str(a) != "--resume")]


def tune_config(args):
    """The gradient optimiser's settings (`jaxsleigh.tuning.TuneConfig`)."""
    from ..tuning import TuneConfig

    return TuneConfig(steps=args.steps, batch=args.batch, seed=args.seed, lr=args.lr, mode=args.mode,
                      n_attempts=args.n_attempts, probe_budget=args.probe_budget)


def loss_config(args):
    """The surrogate's settings (`jaxsleigh.tuning.LossConfig`); no --energy-budget: none (inf)."""
    from ..tuning import TRAINING_STEPSIZE, LossConfig

    return LossConfig(t_final=args.t_final, dt=args.dt, stepsize=TRAINING_STEPSIZE._replace(max_step=10 * args.dt),
                      stop_fraction=args.stop_fraction,
                      energy_budget=math.inf if args.energy_budget is None else args.energy_budget)


def search_config(args):
    """The search's settings (`jaxsleigh.tuning.SearchConfig`)."""
    from ..tuning import SearchConfig

    return SearchConfig(generations=args.steps, population=args.population, batch=args.batch, seed=args.seed,
                        energy_margin=args.energy_margin, energy_percentiles=args.energy_percentiles,
                        objective="time" if getattr(args, "frontier", None) is None else "gap")


def stepsize(args):
    """The accurate engine's step-size controller from --rtol / --atol (``None`` without them: the defaults, and the
    fingerprints of earlier runs unchanged); refused where nothing would use it."""
    if args.rtol is None and args.atol is None:
        return None
    if not args.search and not args.validate:
        used = " and ".join(f for f, v in (("--rtol", args.rtol), ("--atol", args.atol)) if v is not None)
        raise ValueError(f"{used} set the tolerance of the held-out check, and --validate 0 skips it: drop {used} "
                         f"or --validate 0")

    return StepSizeController(rtol=args.rtol, atol=args.atol)


def held_out(args):
    """The ``--validate N`` check (`jaxsleigh.tuning.runs.HeldOut`): N starts drawn with seed ``--seed + 1000``."""
    from ..tuning.runs import HeldOut

    return HeldOut(args.validate, args.seed + 1000, stepsize(args)).check("--validate")


#: The tuners' size keywords as flags (`jaxsleigh.tuning.optimizer.check_sizes`).
SIZE_FLAGS = {"steps": "--steps", "batch": "--batch", "t_final": "--t-final", "max_step": "the step cap (10 x --dt)",
              "n_attempts": "--n-attempts"}


def check_sizes(args) -> None:
    """The sizes of a gradient run, a front or a law's tuning (``--steps``, ``--warm-steps``, ``--batch``,
    ``--t-final`` against ``--n-attempts``) and of the held-out check (``--validate``), checked before any work."""
    from ..tuning.optimizer import check_sizes as check

    vmap = args.pareto is not None and args.front_method == "vmap"
    batch = args.batch * (args.pareto if vmap else 1)
    check(args.steps, batch, args.t_final, 10 * args.dt, args.n_attempts,
          names={**SIZE_FLAGS, "batch": "--batch x --pareto" if vmap else "--batch"})
    if getattr(args, "warm_steps", None) is not None:
        check(args.warm_steps, args.batch, args.t_final, 10 * args.dt, args.n_attempts,
              names={**SIZE_FLAGS, "steps": "--warm-steps"})
    held_out(args)


def check_search(args) -> None:
    """Every flag of ``--search`` checked before any work."""
    used = [k for k, v in _GRADIENT_ONLY.items() if getattr(args, k) != v]
    if used:
        raise ValueError("--search measures 100 s with the accurate engine and has no gradient optimiser: drop "
                         + ", ".join("--" + k.replace("_", "-") for k in used))
    if args.energy_budget is not None and args.energy_margin != 0.95:
        raise ValueError("give the budget once: --energy-budget E (absolute) or --energy-margin F (relative), not both")
    if not 0 < args.energy_margin <= 10:
        raise ValueError(f"--energy-margin must be in (0, 10], got {args.energy_margin}")
    from ..tuning.cma_search import MAX_GENERATIONS, MAX_POPULATION

    check_count("--steps (generations of --search)", args.steps, maximum=MAX_GENERATIONS,
                reason="each generation runs the whole population on the training starts over 100 s (100 take "
                       "about an hour)",
                fix="search in stages: a later run with a larger --steps and --resume continues")
    check_count("--population", args.population, maximum=MAX_POPULATION,
                reason="a generation is one ensemble of --population x --batch trajectories",
                fix="use a smaller --population (16 is the default)")
    check_memory(args.population * args.batch, "--population x --batch", unit="trajectories per generation",
                 fix="use a smaller --population or --batch")


def check_pareto(args) -> None:
    """Every flag of ``--pareto`` checked before any work."""
    from ..tuning.pareto import MAX_FRONT_POINTS

    if args.robust or args.history or args.energy_budget is not None:
        raise ValueError("--pareto computes its own budgets and has no history file: drop --robust, "
                         "--history and --energy-budget")
    check_count("--pareto", args.pareto, maximum=MAX_FRONT_POINTS,
                reason="every point is a whole tuning run (seconds to minutes each; 1000 points took about 50 "
                       "minutes), and a front is drawn well by a few dozen",
                fix="give fewer points, or compute several fronts over narrower --budgets ranges")
    if args.plot and not args.validate:
        raise ValueError("--plot draws the front validated on the held-out starts; drop --validate 0 or drop --plot")
    check_outputs(args.out, figures={"--plot": args.plot})


def front_budgets(args):
    """``--budgets LO:HI`` spaced geometrically over ``--pareto`` points, else the number of points (the tuner's
    default span)."""
    from ..tuning import budgets_between

    if not args.budgets:
        return args.pareto
    try:
        lo, hi = (float(x) for x in args.budgets.split(":"))
    except ValueError:
        raise ValueError(f"--budgets must be LO:HI (e.g. --budgets 7:2400), got {args.budgets!r}") from None
    return budgets_between(lo, hi, args.pareto)


#: The tuners' keywords and phrases as the command line's flags, in the order they are replaced.
_KEYWORD_FLAGS = (("probe_budget = ", "--probe-budget "), ("probe_budget", "--probe-budget"),
                  ("n_attempts", "--n-attempts"), ("t_final", "--t-final"), ("energy_budget", "--energy-budget"),
                  ("energy_margin", "--energy-margin"), ("energy_percentiles", "--energy-percentiles"),
                  ("resume=True", "--resume"), ("a smaller learning rate", "a smaller --lr"),
                  ("fewer steps", "fewer --steps"), ("start from other gains", "start from other --gains"))


def in_flags(message: str) -> str:
    """A tuner's message with its keywords (``n_attempts``) as the flags that set them (``--n-attempts``); words
    inside paths and flags are left alone."""
    for word, flag in _KEYWORD_FLAGS:
        tail = r"(?!\w)" if word[-1].isalnum() else ""
        message = re.sub(r"(?<![\w/.\-])" + re.escape(word) + tail, flag, message)
    return message


def _canonical_argv(args) -> list:
    """The options that determine the result, as a command line (when the caller's argv is unknown)."""
    if getattr(args, "search", False):
        return ["tune", "--search", "--out", str(args.out), "--steps", str(args.steps), "--batch", str(args.batch),
                "--seed", str(args.seed), "--population", str(args.population), "--energy-margin",
                repr(args.energy_margin), "--tune", args.tune, "--gains", str(args.gains), "--params", args.params,
                "--damping", args.damping] + (["--energy-budget", repr(args.energy_budget)]
                                              if args.energy_budget is not None else []) + (
            ["--energy-percentiles", ",".join(f"{q:g}" for q in args.energy_percentiles)]
            if args.energy_percentiles != (50.0,) else []) + (
            ["--frontier", str(args.frontier)] if getattr(args, "frontier", None) is not None else []) + [
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
