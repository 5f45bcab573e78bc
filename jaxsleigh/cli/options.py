"""The option groups the subcommands share (model, digital controller, horizon, tolerances, progress,
workers) and what they build: the plant and the law (`model_from_args`), the sampler, the workers."""
from __future__ import annotations

import argparse
from typing import Optional

import numpy as np

from .values import number, parse_triple, whole
from ..controllers.actuators import sampled, sampler, saturate
from ..files.workers import EXIT_CLUSTER, WORKERS_TIMEOUT_S, Workers
from ..integrate.sampled import sample_count
from ..integrate.stepsize import StepSizeController
from ..model.params import Gains, load_gains, plant_params, preset_names

__all__ = ["add_model_options", "model_from_args", "check_bound_fits", "add_sampler_options", "sampler_from_args",
           "check_delay", "law_kwargs", "add_horizon_options", "add_tolerance_options", "check_tolerance_flags",
           "add_progress_option", "add_workers_options", "workers_from_args"]


# ---------------------------------------------------------------------------------------------
# option groups
# ---------------------------------------------------------------------------------------------

def add_model_options(parser) -> None:
    """--gains, --params, --damping, --x64."""
    names = preset_names()
    g = parser.add_argument_group("model")
    g.add_argument("--gains", default="paper", metavar="FILE.json|" + "|".join(names),
                   help='controller gains: a JSON file {"L": [l1, l2, l3], "k": k, "D_hat": [d1, d2] or '
                        '[[a, b], [c, d]]} (every key required) or a preset: ' + ", ".join(names)
                        + " (default: paper = L diag(2, .5, .8), k 0.1, D_hat diag(4, 8))")
    g.add_argument("--params", default="2,1,1", metavar="M,J,L",
                   help="plant mass m [kg], inertia J [kg m^2] about the centre of mass and offset l [m] "
                        "of the centre of mass from the contact point (default: 2,1,1, the paper's)")
    g.add_argument("--damping", default="coulomb", choices=["coulomb", "viscous", "none"],
                   help="open-loop friction of the plant (default: coulomb, the paper's "
                        "D = diag(1/sqrt(0.1 + p_i^2)))")
    g.add_argument("--x64", action="store_true", help="compute in float64 (default: float32)")
    g.add_argument("--controller", default="paper", metavar="NAME",
                   help="the feedback law: paper (default, with --gains), a law from the literature "
                        "(jaxsleigh controllers lists them, with what of the plant each must know), or FILE.json "
                        "written by jaxsleigh tune --controller NAME (the law; give its actuator flags again)")
    g.add_argument("--saturation", type=number("--saturation", "50"), default=None, metavar="U",
                   help="actuator saturation: clip each component of u to |u_i| <= U (N, N m)")


def model_from_args(args):
    """(plant, law) from the options of `add_model_options` (and `add_sampler_options` where the command has them):
    ``law`` is the paper's `Gains` (``--gains``) unless ``--controller`` names another law, or ``--saturation`` or
    ``--sample-period`` wrap it in an actuator (then a law ``u = law(q, v)``)."""
    from ..controllers.registry import check_not_controller, make_controller

    m, J, l = parse_triple(args.params, "--params", "2,1,1")
    plant = plant_params(m, J, l, damping=args.damping)
    name = getattr(args, "controller", "paper")
    check_not_controller(str(args.gains), "--gains")          # --gains shaped: the way to --controller shaped
    if name != "paper" and args.gains != "paper":
        raise ValueError(f"--gains sets the paper's law; it does not apply to --controller {name}")
    if name.endswith(".json"):                   # a law written by `jaxsleigh tune --controller NAME --out F.json`
        from ..tuning.law_file import load_controller_record

        law = load_controller_record(name)
    else:
        law = make_controller(name, load_gains(args.gains)) if name == "paper" else make_controller(name)
    u_max = getattr(args, "saturation", None)
    if u_max is not None:
        check_bound_fits(u_max, args.x64)
        try:
            law = saturate(law, u_max)
        except ValueError as e:
            raise ValueError(f"--saturation: {e}") from None
    smp = sampler_from_args(args) if hasattr(args, "sample_period") else None
    if smp is not None:
        law = sampled(law, *smp)
    return plant, law


def check_bound_fits(u_max: float, x64: bool) -> None:
    """Refuse a ``--saturation`` bound that the working dtype cannot hold (it would overflow to inf when cast)."""
    dtype = np.float64 if x64 else np.float32
    top = float(np.finfo(dtype).max)
    if u_max > top:
        more = "" if x64 else ", or add --x64 (float64 holds bounds up to 1.8e+308)"
        raise ValueError(f"--saturation {u_max:g} does not fit {np.dtype(dtype).name} (largest {top:.3g}): give a "
                         f"bound of at most {top:.3g}{more}")


def add_sampler_options(parser, *, seed: bool = True) -> None:
    """--sample-period, --delay, --noise[, --seed]: the law behind a digital controller."""
    a = parser.add_argument_group("digital controller")
    a.add_argument("--sample-period", type=number("--sample-period", "0.01"), default=None, metavar="TS",
                   help="zero-order hold at period TS: the law evaluated once per sample and held, the plant "
                        "integrated in between by the adaptive RK4 to --rtol/--atol, landing on each sample instant "
                        "(with --method rk4: fixed steps of at most --dt); --t-final must be a whole number of "
                        "periods")
    a.add_argument("--delay", type=whole("--delay", "1", minimum=0), default=0, metavar="K",
                   help="delay of K whole samples (needs --sample-period)")
    a.add_argument("--noise", type=number("--noise", "0.01", positive=False, nonnegative=True), default=0.0,
                   metavar="SIGMA", help="Gaussian measurement noise on q and v, standard deviation SIGMA, seeded "
                                         "by --seed (needs --sample-period)")
    if seed:
        a.add_argument("--seed", type=whole("--seed", "0", minimum=0, maximum=2**62), default=0, metavar="S",
                       help="seed of the measurement noise (default 0)")


def sampler_from_args(args):
    """The `jaxsleigh.controllers.actuators.Sampler` of `add_sampler_options` (``None`` without --sample-period),
    checked against the horizon before any work."""
    if args.sample_period is None:
        if args.delay or args.noise:
            raise ValueError("--delay and --noise belong to the digital controller: add --sample-period TS")
        return None

    try:
        samples = sample_count(args.t_final, args.sample_period)
    except ValueError as e:
        raise ValueError(f"--t-final / --sample-period: {e}") from None
    check_delay(args.delay, samples, args.t_final, args.sample_period)
    return sampler(args.sample_period, args.delay, args.noise, args.seed or 0)


def check_delay(delay: int, samples: int, t_final: float, period: float) -> None:
    """Refuse a ``--delay`` of as many samples as the horizon holds, or more: the held input would be zero
    from start to end (and a huge delay would only fill the memory before saying so)."""
    if delay >= samples:
        raise ValueError(f"--delay {delay} is not shorter than the horizon: --t-final {t_final:g} at --sample-period "
                         f"{period:g} holds {samples} samples, so the plant would get zero control throughout; give "
                         f"--delay below {samples} (or a longer --t-final)")


def law_kwargs(law) -> dict:
    """``{"gains": law}`` for the paper's law, else ``{"controller": law}``: the keyword a front takes it by."""
    return {"gains": law} if isinstance(law, Gains) else {"controller": law}


def add_horizon_options(parser, *, t_final: float = 100.0, dt: float = 0.01, save_every: Optional[int] = 10,
                        method: bool = True) -> None:
    """--t-final, --dt[, --save-every][, --method, --max-steps]."""
    g = parser.add_argument_group("integration")
    g.add_argument("--t-final", type=number("--t-final", "100"), default=t_final, metavar="T",
                   help=f"horizon in seconds (a whole multiple of --dt; default {t_final:g})")
    g.add_argument("--dt", type=number("--dt", "0.01"), default=dt, metavar="DT",
                   help=f"base step in seconds (default {dt:g}): the step of --method rk4; the adaptive "
                        "method starts with it and grows its step up to 100 DT where the error allows")
    if save_every is not None:
        g.add_argument("--save-every", type=whole("--save-every", "10"), default=save_every, metavar="K",
                       help=f"keep every K-th base step (default {save_every}; t-final/dt must be a multiple of K)")
    if method:
        g.add_argument("--method", choices=["adaptive", "rk4"], default="adaptive",
                       help="adaptive: RK4 with per-trajectory error control, steps from DT up to 100 DT, accurate "
                            "near theta = 0 (default); rk4: classical fixed-step RK4 at --dt (fast, but it can be "
                            "wrong or unstable for stiff starts and strong gains, e.g. the tuned preset needs "
                            "--dt 0.001)")
        g.add_argument("--max-steps", type=whole("--max-steps", "2000000"), default=None, metavar="N",
                       help="budget of attempted steps per trajectory (default: 20x (float32) or 30x (float64) the base steps for "
                            "adaptive; at most 2147483646); a run that exhausts it gets status 4")
        add_tolerance_options(g)


def add_tolerance_options(group) -> None:
    """--rtol, --atol: the adaptive method's tolerances (``None``: the dtype's defaults)."""
    group.add_argument("--rtol", type=number("--rtol", "1e-6"), default=None, metavar="R",
                       help="relative tolerance of the adaptive method (default 1e-6 in float32, 1e-8 in float64)")
    group.add_argument("--atol", type=number("--atol", "1e-8"), default=None, metavar="A",
                       help="absolute tolerance of the adaptive method (default 1e-6 in float32, 1e-8 in float64). "
                            "Control energy and final states after settling need 1e-8 in float32 for gains whose "
                            "settled starts oscillate (the settled-phase page of the docs)")


def stepsize_from_args(args):
    """The `jaxsleigh.StepSizeController` of ``--method``, ``--max-steps``, ``--rtol`` and ``--atol`` (``None``: the
    library's defaults)."""
    return StepSizeController(method=args.method, max_steps=args.max_steps, rtol=args.rtol, atol=args.atol)


def check_tolerance_flags(args) -> None:
    """``--rtol`` / ``--atol`` belong to the adaptive method: refuse them with ``--method rk4`` (unused there)."""
    used = " and ".join(f for f, v in (("--rtol", args.rtol), ("--atol", args.atol)) if v is not None)
    if used and args.method == "rk4":
        verb = "set" if " and " in used else "sets"
        raise ValueError(f"{used} {verb} the adaptive method's error control; --method rk4 takes fixed steps of --dt: "
                         f"drop {used} or use --method adaptive")


def add_progress_option(parser) -> None:
    parser.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                        help="progress bar on stderr (default: only on a terminal)")


def add_workers_options(parser) -> None:
    """--workers N (a local Dask cluster) or --scheduler ADDRESS (an existing one), --cluster-timeout S (see
    `jaxsleigh.files.workers`)."""
    g = parser.add_argument_group(
        "workers", "the chunks computed by the workers of a Dask cluster (pip install \"jaxsleigh[cluster]\"); "
                   "this process checks the input and writes the output. A lost worker's chunks are computed by "
                   "the others; the checkpoint folder must be on a filesystem that every worker sees.")
    w = g.add_mutually_exclusive_group()
    w.add_argument("--workers", type=whole("--workers", "4"), metavar="N",
                   help="start N worker processes on this machine (one thread each) for the run")
    w.add_argument("--scheduler", metavar="ADDRESS",
                   help="the address of a running Dask scheduler whose workers compute the chunks (e.g. "
                        "tcp://10.0.0.1:8786; start it with 'dask scheduler' and 'dask worker ADDRESS')")
    g.add_argument("--cluster-timeout", type=number("--cluster-timeout", "60"), default=WORKERS_TIMEOUT_S,
                   metavar="S", help=f"seconds to wait for a worker: at the start, and when none is left (then the "
                                     f"run stops with exit code {EXIT_CLUSTER}, its chunks kept) (default "
                                     f"{WORKERS_TIMEOUT_S})")
    for flag in ("--coordinator", "--num-processes", "--process-id"):
        g.add_argument(flag, action=_Removed, help=argparse.SUPPRESS)


class _Removed(argparse.Action):
    """A flag of jaxsleigh 0.3's processes sharing a run: refused with what replaces it."""

    def __call__(self, parser, namespace, values, option_string=None):
        parser.error(f"{option_string} was removed in jaxsleigh 0.4: one command runs the whole study and its chunks "
                     f"go to Dask workers, --workers N on this machine or --scheduler ADDRESS for a cluster "
                     f"(e.g. --workers 2)")


def workers_from_args(args):
    """The `jaxsleigh.files.workers.Workers` of `add_workers_options` (``None``: neither given: this process
    computes the chunks)."""
    n, at = getattr(args, "workers", None), getattr(args, "scheduler", None)
    if n is None and at is None:
        return None
    return Workers(n, at, getattr(args, "cluster_timeout", None) or WORKERS_TIMEOUT_S)
