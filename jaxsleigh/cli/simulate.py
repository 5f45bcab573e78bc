"""``jaxsleigh simulate``: decimated trajectories from a few starts, with the settings that made them. The run owns
its ``--out`` while it runs (`jaxsleigh.files.runlock.RunLock`): another run on the same file is refused, exit code 5."""
from __future__ import annotations

import argparse
import time
import warnings

from ..errors import FlaggedStartsWarning
from ..studies.options import RunOptions, SaveAt
from .common import (FLAGS, PROG, add_horizon_options, add_model_options, add_progress_option, add_sampler_options,
                     check_outputs, check_tolerance_flags, claim_output, exit_code, ics_from_args, law_kwargs,
                     model_from_args, report_warnings, status_epilog, status_line)
from .options import stepsize_from_args
from ..files.npz import npz_path, write_npz
from ..files.runner import run_record, write_sidecar
from ..studies.config import solve_config
from ..studies.simulate import check_saves, simulate

__all__ = ["add_simulate"]

#: ``--save-every`` when not given.
DEFAULT_SAVE_EVERY = 10


def _epilog() -> str:
    return (status_epilog()
            + "\n\noutput .npz keys: t (T,), q (N,T,3), p (N,T,2), u (N,T,2), Hd (N,T), status (N,),\n"
              "  n_steps (N,), n_rejected (N,), ics (N,5), settings_json, dt, t_final, save_every\n"
              "  (base steps per saved point; 1 with --sample-period: every sample instant),\n"
              "  method, dtype, gains_L, gains_k, gains_D_hat, params (m,J,l), damping\n\n"
              "examples:\n"
              "  jaxsleigh simulate --ic=-3,-2,pi/8 --ic 3,2,-pi/2 --out run.npz\n"
              "  jaxsleigh simulate --ics starts.npy --t-final 50 --x64 --gains my_gains.json --out run.npz\n"
              "\nA single start with theta0 = 0 (the singular set) or a non-finite entry is an error;\n"
              "in a batch such starts are flagged (status 1, 2 or 8, outputs NaN), named in a warning,\n"
              "and the rest is simulated.")


def add_simulate(subparsers) -> None:
    p = subparsers.add_parser(
        "simulate", help="simulate the closed loop from initial conditions and save an .npz",
        description="Simulate the Chaplygin sleigh under the discontinuous energy-shaping controller "
                    "(paper eq. 13) from one or more initial conditions; save decimated trajectories "
                    "and the settings that produced them.",
        epilog=_epilog(), formatter_class=argparse.RawDescriptionHelpFormatter)
    src = p.add_argument_group("initial conditions (one of)").add_mutually_exclusive_group(required=True)
    src.add_argument("--ics", metavar="FILE.npy",
                     help="array of shape (N, 3) [x, y, theta] or (N, 5) [x, y, theta, p1, p2] "
                          "(.npy, or .csv / .txt tables)")
    src.add_argument("--ic", action="append", metavar="X,Y,THETA[,P1,P2]",
                     help="one start (repeatable); entries may use pi, e.g. --ic=-3,-2,pi/8; "
                          "momentum is zero unless P1,P2 are given")
    add_horizon_options(p, save_every=DEFAULT_SAVE_EVERY)
    p.set_defaults(save_every=None)         # given or not: a sampled run refuses an explicit --save-every
    add_model_options(p)
    add_sampler_options(p)
    add_progress_option(p)
    p.add_argument("--out", required=True, metavar="FILE.npz", help="output file")
    p.set_defaults(func=_cmd_simulate)


def _save_every(args) -> int:
    """``--save-every`` (default 10). A sampled run saves the state at every sample instant: an explicit
    ``--save-every`` with ``--sample-period`` is refused rather than ignored."""
    if args.save_every is None:
        return DEFAULT_SAVE_EVERY
    if args.sample_period is not None:
        raise ValueError(f"--save-every {args.save_every} does not apply with --sample-period: a sampled run saves "
                         f"the state at every sample instant (every {args.sample_period:g} s); drop --save-every, "
                         f"or choose a longer --sample-period for fewer saved points")
    return args.save_every


def _cmd_simulate(args) -> int:
    plant, law = model_from_args(args)
    check_tolerance_flags(args)
    save_every = _save_every(args)
    stepsize = stepsize_from_args(args)
    cfg = solve_config(plant=plant, **law_kwargs(law), t_final=args.t_final, dt=args.dt, save_every=save_every,
                       stepsize=stepsize, x64=args.x64, flags=FLAGS)
    ics = ics_from_args(args)
    check_saves(ics, cfg, {"ics": "--ics" if args.ics else "--ic", "t_final": "--t-final",
                           "every": "--sample-period" if args.sample_period is not None else "--save-every"})
    check_outputs(named={"--out": args.out}, suffix=".npz")
    with claim_output(npz_path(args.out), args):
        t0 = time.perf_counter()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            sol = simulate(ics, plant=plant, **law_kwargs(law), t_final=args.t_final, dt=args.dt, x64=args.x64,
                           stepsize=stepsize, saveat=SaveAt(every=save_every), run=RunOptions(progress=args.progress))
        wall = time.perf_counter() - t0
        report_warnings(caught)
        out = write_npz(args.out, sol, ics=ics, command=[PROG, *args._argv])
        side = write_sidecar(out, run_record([PROG, *args._argv], wall, (sol.run_info or {}).get("devices")))
    n_flag = sum(len(w.message.rows) for w in caught if isinstance(w.message, FlaggedStartsWarning))
    print(f"{PROG} simulate: {status_line(sol.status, sol.T_eps, cfg.eps)}"
          f"{f' ({n_flag} flagged, not integrated)' if n_flag else ''}; "
          f"{wall:.2f} s wall ({sol.settings['dtype']}, {sol.settings['method']}); wrote {out} "
          f"(wall time and devices: {side.name})")
    return exit_code(sol.status, sol.T_eps, cfg.eps)
