"""``jaxsleigh basin``: convergence over a grid, Monte-Carlo samples or a file of starts.

Registered by `add_basin` (``jaxsleigh.cli`` lists it among its subcommands)::

    jaxsleigh basin --x -3:3:128 --y -3:3:128 --theta pi/8 --out xy.npz --plot xy.png
    jaxsleigh basin --x -3:3:128 --y 1 --theta -pi:pi:128 --out xtheta.npz
    jaxsleigh basin --samples 100000 --seed 1 --out mc.npz
    jaxsleigh basin --ics starts.npy --eps 0.05 --t-final 100 --x64 --out mine.npz

Results are written chunk by chunk to ``FILE.npz.chunks/``; an interrupted run (Ctrl-C, a killed
process) continues from the finished chunks when the same command is given again with
``--resume``, and ends with the same ``.npz``, byte for byte. Wall time, devices, machine load and
the command line go to a sidecar ``FILE.run.json``, never into the ``.npz``.
"""
from __future__ import annotations

import argparse
import math
import re

from ..files.npz import load_ics, npz_path, parse_number as _number
from ..studies.options import RunOptions
from .chunked import add_run_options, audit_from_args, run_chunked_command, say_flagged, say_study_done
from .common import (FLAGS, add_horizon_options, add_model_options, add_sampler_options, check_tolerance_flags,
                     law_kwargs, model_from_args, number, status_epilog, whole)
from .options import stepsize_from_args
from ..studies.basin import array_starts, grid_starts, parse_axis, run_basin, sample_starts, save_basin
from ..studies.config import solve_config
from ..validate import check_memory

__all__ = ["add_basin", "run_basin_command"]


def _epilog() -> str:
    return (
        "starts (one of):\n"
        "  grid     --x/--y/--theta, each LO:HI:N (N points, ends included) or one value (held fixed);\n"
        "           none given: --x -3:3:64 --y -3:3:64 --theta pi/4; a coordinate not given is held at\n"
        "           x = 1, y = 1, theta = pi/4. Values may use pi. Grid points with theta = 0 (the\n"
        "           singular set) are flagged (status 1), not integrated, and left out of the fraction.\n"
        "  samples  --samples N [--seed S]: uniform in the box given by --x/--y/--theta (LO:HI[:N], N\n"
        "           ignored; default |x|, |y| <= 3, theta in (-pi, pi)).\n"
        "  file     --ics FILE.npy: shape (N, 3) [x, y, theta] or (N, 5) [x, y, theta, p1, p2].\n"
        "A negative range may follow its flag directly (--x -3:3:64) or with '=' (--x=-3:3:64).\n\n"
        "output .npz keys: ics (N,3|5), T_eps (N,) [inf: not settled by --t-final, nan: failed],\n"
        "  status (N,), Hd0, Hd_final, min_abs_theta, max_excursion, n_steps, n_rejected (N,),\n"
        "  q_final (N,3), p_final (N,2), converged, valid (N,) bool, fraction, fraction_se\n"
        "  [sqrt(S(1-S)/N) over the valid starts], n_valid, n_converged, T_eps_percentiles (at\n"
        "  T_eps_percentile_levels), kind, grid_shape, grid_axes, axis_x/axis_y/axis_theta (grids) or\n"
        "  box/seed (samples), settings_json, eps, t_final, dt, method, dtype, max_steps, gains_L,\n"
        "  gains_k, gains_D_hat, params (m,J,l), damping. Grid arrays reshape to grid_shape (slowest\n"
        "  axis first); grid_axes lists the varying coordinates, fastest first.\n"
        "  Sidecar FILE.run.json: wall time, devices, load, command (things that vary between runs).\n"
        "The map shows which starts SETTLED within --t-final (|q| <= --eps from T_eps on), not a basin of\n"
        "attraction in the control sense: the paper argues convergence from every start off theta = 0, and\n"
        "grey means 'not settled by --t-final', not 'diverges'.\n\n"
        + status_epilog() + "\n\n"
        "examples:\n"
        "  jaxsleigh basin --x -3:3:128 --y -3:3:128 --theta pi/8 --out xy.npz --plot xy.png\n"
        "  jaxsleigh basin --x -3:3:256 --y 1 --theta -pi:pi:256 --out xt.npz --plot xt.png\n"
        "  jaxsleigh basin --samples 100000 --seed 1 --theta 0.05:pi --out mc.npz\n"
        "  jaxsleigh basin ... --resume      (continue an interrupted run; same options)")


def add_basin(subparsers) -> argparse.ArgumentParser:
    """Register the ``basin`` subcommand on an ``argparse`` subparsers object; returns its parser."""
    p = subparsers.add_parser(
        "basin", help="which starts settle within the horizon, and how fast: a grid, samples or a file of starts",
        description="Integrate the closed loop (paper eq. 13) from many starts at rest and record, per start, "
                    "the convergence time T_eps (the first time after which |q| <= --eps holds up to "
                    "--t-final), the status, H_d(0), min |theta|, max |q| and the steps used; summarise the "
                    "fraction converged (+- its standard error) and the distribution of T_eps. Chunks are "
                    "checkpointed next to --out; --resume continues an interrupted run.",
        epilog=_epilog(), formatter_class=argparse.RawDescriptionHelpFormatter)
    add_study_options(p, theta_help="theta range or fixed theta [rad] (e.g. -pi:pi:128)", samples_example="100000",
                      samples_help="N Monte-Carlo starts, uniform in the --x/--y/--theta box",
                      chunk_help="starts integrated (and checkpointed) at once (default 16384 per CPU device, "
                                 "2^22 per accelerator)",
                      keep_help="keep FILE.npz.chunks/ after the .npz is written (default: delete it)",
                      plot_help="also draw the convergence-time map, the fraction against theta0 and the T_eps "
                                "distribution")
    p.set_defaults(func=run_basin_command)
    return p


def add_study_options(p, *, theta_help: str, samples_example: str, samples_help: str, **run_help) -> None:
    """The option groups `jaxsleigh basin` and `jaxsleigh sweep` share: the starts (a grid, samples or a file;
    the seed), the ball of T_eps, the horizon, the model and the sampler, then the run, the output and the
    processes (`jaxsleigh.cli.chunked.add_run_options`); the help texts that differ between the two are given."""
    # "--x -3:3:64", "--theta -pi/2:pi/2:64": values, not options (argparse would read them as flags)
    p._negative_number_matcher = re.compile(r"^-(\d|\.\d|pi)")
    g = p.add_argument_group("starts")
    g.add_argument("--x", metavar="LO:HI:N|X", help="x range or fixed x [m]")
    g.add_argument("--y", metavar="LO:HI:N|Y", help="y range or fixed y [m]")
    g.add_argument("--theta", metavar="LO:HI:N|THETA", help=theta_help)
    src = g.add_mutually_exclusive_group()
    src.add_argument("--ics", metavar="FILE.npy", help="starts from a file, shape (N, 3) or (N, 5)")
    src.add_argument("--samples", type=whole("--samples", samples_example, maximum=2**62), metavar="N",
                     help=samples_help)
    g.add_argument("--seed", type=whole("--seed", "1", minimum=0, maximum=2**63 - 1), metavar="S",
                   help="seed of --samples and of --noise (default 0)")
    c = p.add_argument_group("convergence")
    c.add_argument("--eps", type=number("--eps", "0.05"), default=0.05, metavar="EPS",
                   help="radius of the ball |q| <= EPS that defines T_eps (default 0.05)")
    add_horizon_options(p, save_every=None)
    add_model_options(p)
    add_sampler_options(p, seed=False)          # --seed (above) also seeds the measurement noise
    add_run_options(p, chunk_example="16384", chunk_default=None, audit=True, **run_help)


def starts_from_args(args):
    """The `jaxsleigh.studies.basin.BasinStarts` the flags ask for (a grid, samples or an ``--ics`` file)."""
    coords = {"x": args.x, "y": args.y, "theta": args.theta}
    if args.seed is not None and args.samples is None and not args.noise:
        raise ValueError("--seed seeds --samples and --noise only; add one of them or drop --seed")
    if args.ics is not None:
        given = [f"--{k}" for k, v in coords.items() if v is not None]
        if given:
            verb = "defines" if len(given) == 1 else "define"
            raise ValueError(f"{' and '.join(given)} {verb} a grid or the --samples box and cannot be combined "
                             f"with --ics; drop {'it' if len(given) == 1 else 'them'} or drop --ics")
        return array_starts(load_ics(args.ics, hint="use a grid (--x/--y/--theta) or --samples N"),
                            source=str(args.ics))
    if args.samples is not None:
        for k, v in coords.items():
            if v is not None:
                _check_box(v, f"--{k}")
        check_memory(args.samples, "--samples")
        return sample_starts(args.samples, seed=0 if args.seed is None else args.seed, **coords)
    given = {k: parse_axis(v, f"--{k}") for k, v in coords.items() if v is not None}  # grid_starts' checks, flagged
    if given:
        check_memory(math.prod(a.n for a in given.values()), " x ".join(f"--{k} {coords[k]}" for k in given),
                     fix="use a coarser grid or split the study into several runs")
    return grid_starts(**coords)


def _check_box(text: str, flag: str) -> None:
    """An interval LO:HI (or LO:HI:N, N ignored) or one value, for the --samples box."""
    parts = text.split(":")
    hint = f"write LO:HI (e.g. {flag} {'-pi:pi' if flag == '--theta' else '-3:3'}) or one value to hold it fixed"
    if len(parts) not in (1, 2, 3):
        raise ValueError(f"could not parse {flag} {text!r}; {hint}")
    try:
        vals = [_number(s) for s in parts[:2]]
    except ValueError as e:
        raise ValueError(f"could not parse {flag} {text!r}: {e}; {hint}") from None
    if not all(math.isfinite(v) for v in vals):
        raise ValueError(f"{flag} {text!r} has a non-finite bound; {hint}")
    if len(vals) == 2 and not vals[0] < vals[1]:
        raise ValueError(f"{flag} {text!r}: LO must be below HI; write e.g. {flag} "
                         f"{min(vals):g}:{max(vals):g}")


def run_basin_command(args) -> int:
    """Handler of ``jaxsleigh basin`` (``args`` from the parser of `add_basin`); returns the exit code.

    The run is `jaxsleigh.files.runner.run_to_file` (`jaxsleigh.cli.chunked.run_chunked_command`): with
    ``--workers N`` or ``--scheduler ADDRESS`` the workers of a Dask cluster compute the chunks and this
    process writes the output.
    """
    out = npz_path(args.out)
    st = {}

    def check() -> None:
        """Validate the options before any work (`run_chunked_command` then checks the outputs); nothing is written."""
        st["plant"], st["law"] = plant, law = model_from_args(args)
        check_tolerance_flags(args)
        solve_config(plant=plant, **law_kwargs(law), t_final=args.t_final, dt=args.dt,
                     stepsize=stepsize_from_args(args), x64=args.x64, eps=args.eps, flags=FLAGS)
        st["starts"] = starts_from_args(args)

    def study(checkpoint_dir, resume, shard):
        run = RunOptions(chunk_size=args.chunk_size, progress=args.progress, checkpoint_dir=checkpoint_dir,
                         resume=resume, shard=shard, audit=audit_from_args(args))
        return run_basin(st["starts"], eps=args.eps, t_final=args.t_final, dt=args.dt, plant=st["plant"],
                         **law_kwargs(st["law"]), x64=args.x64, stepsize=stepsize_from_args(args), run=run)

    def finish(res, written, record, caught) -> int:
        say_flagged(int((~res.valid).sum()), res.status.size, caught=caught)
        if args.plot:
            from ..plots.basin import plot_basin
            from ..plots.base import save_figure

            written.append(str(save_figure(plot_basin(res), args.plot)))
        print(res.describe() if res.converged.any() else res.describe().splitlines()[0])
        return say_study_done("basin", res, record, written, args.eps)

    return run_chunked_command(args, "basin", out, check=check, study=study, save=save_basin,
                               info=lambda res: {"summary": res.summary(), "audit": res.run_info.get("audit")},
                               finish=finish)
