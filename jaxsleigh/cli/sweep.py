"""``jaxsleigh sweep``: convergence over a range (or a grid) of gains or plant parameters.

Registered by `add_sweep`::

    jaxsleigh sweep --param k=0.01:1:9:log --samples 512 --out k.npz --plot k.png
    jaxsleigh sweep --param m=0.5:8:5:log --param l=0:2:5 --samples 256 --out ml.npz --plot ml.png
    jaxsleigh sweep --param coulomb_scale=0:4:5 --ics starts.npy --x64 --out friction.npz

Every start runs under every value (set) as one chunked, checkpointed ensemble
(`jaxsleigh.studies.sweep.sweep`); chunks go to ``FILE.npz.chunks/`` and ``--resume`` continues an
interrupted run, ending with the same ``.npz``, byte for byte. Wall time, devices and the command
go to ``FILE.run.json``. With ``--workers N`` or ``--scheduler ADDRESS`` the workers of a Dask cluster
compute the chunks, as for ``jaxsleigh basin`` (`jaxsleigh.files.runner.run_to_file`), and the command writes
the same ``.npz``.
"""
from __future__ import annotations

import argparse
import math

import numpy as np

from ..studies.options import RunOptions
from .basin import starts_from_args, add_study_options
from .chunked import audit_from_args, run_chunked_command, say_flagged, say_study_done
from .common import FLAGS, check_tolerance_flags, law_kwargs, model_from_args, status_epilog
from .options import stepsize_from_args
from ..files.npz import npz_path
from ..model.controller import law_leaf_names
from ..model.params import Gains
from ..studies.config import solve_config
from ..studies.sweep import PARAM_NAMES, apply_params, check_rows, param_grid, parse_param, save_sweep, sweep

__all__ = ["add_sweep", "run_sweep_command"]

#: starts when none are given: Monte-Carlo samples in basin's default box
DEFAULT_SAMPLES = 256


def _epilog() -> str:
    return (
        "parameters (--param NAME=LO:HI:P[:log], once or twice; two make a P1 x P2 grid):\n"
        f"  NAME: {', '.join(PARAM_NAMES)}\n"
        "  gains k, l1..l3 (diag L), d11, d22, d12 (D_hat); plant m, J, l (l = 0: the knife edge);\n"
        "  coulomb_eps, coulomb_scale (with --damping coulomb), c1, c2 (with --damping viscous).\n"
        "  P values from LO to HI (ends included), evenly spaced, or log-spaced with ':log' (LO > 0).\n"
        "  What is not swept comes from --gains, --params, --damping. Inadmissible values (m <= 0,\n"
        "  k <= 0, D_hat not positive definite, ...) are refused before anything runs.\n\n"
        "starts (as in 'jaxsleigh basin'): a grid --x/--y/--theta, --samples N [--seed S] in the\n"
        f"  --x/--y/--theta box, or --ics FILE.npy; none given: --samples {DEFAULT_SAMPLES} --seed 0.\n\n"
        "output .npz keys: names (n_params,), values (P, n_params), grid_shape, ics (N, 5),\n"
        "  T_eps (P, N) [inf: not settled by --t-final, nan: failed], status (P, N), n_steps,\n"
        "  min_abs_theta, Hd0 (P, N), fraction, fraction_se [sqrt(S(1-S)/N) over the valid starts],\n"
        "  n_valid, n_converged (P,), T_eps_percentiles (P, 5) at T_eps_percentile_levels,\n"
        "  status_counts (P, K) for status_codes (K,), control effort u_energy [int |u|^2 dt],\n"
        "  u_abs_int, u_norm_peak (P, N) and u_energy_median, u_norm_peak_median (P,) [medians over\n"
        "  the converged starts], axis_<NAME> and axis_log (the grid's axes),\n"
        "  settings_json, eps, t_final, dt, method, dtype, max_steps, gains_L, gains_k, gains_D_hat,\n"
        "  params (m,J,l), damping (the base values of what is not swept).\n"
        "  Sidecar FILE.run.json: wall time, devices, load, command.\n\n"
        + status_epilog() + "\n\n"
        "examples:\n"
        "  jaxsleigh sweep --param k=0.01:1:9:log --samples 512 --out k.npz --plot k.png\n"
        "  jaxsleigh sweep --param m=0.5:8:5:log --param l=0:2:5 --out ml.npz --plot ml.png\n"
        "  jaxsleigh sweep ... --resume      (continue an interrupted run; same options)\n"
        "  jaxsleigh sweep ... --workers 4   (4 worker processes compute the chunks; pip install "
        "\"jaxsleigh[cluster]\")")


def add_sweep(subparsers) -> argparse.ArgumentParser:
    """Register the ``sweep`` subcommand; returns its parser."""
    p = subparsers.add_parser(
        "sweep", help="fraction converged and T_eps over a range or grid of gains / plant parameters",
        description="Run a set of starts under every value of one parameter (or every pair of two) as one "
                    "chunked, checkpointed ensemble, and summarise per value: the fraction of valid starts "
                    "that converged within --t-final (+- its standard error), the T_eps percentiles and the "
                    "statuses. --resume continues an interrupted run.",
        epilog=_epilog(), formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--param", action="append", required=True, metavar="NAME=LO:HI:P[:log]",
                   help="parameter and its values (repeat once for a 2-D grid)")
    add_study_options(p, theta_help="theta range or fixed theta [rad]", samples_example="256",
                      samples_help=f"N Monte-Carlo starts, uniform in the --x/--y/--theta box (default {DEFAULT_SAMPLES} "
                                   "when no starts are given)",
                      chunk_help="rows (start x value) integrated and checkpointed at once (default 16384 "
                                 "per CPU device, 2^22 per accelerator); bounds the memory",
                      plot_help="also draw the fraction and T_eps percentiles against the parameter (a heat map "
                                "for two)")
    p.set_defaults(func=run_sweep_command)
    return p


def run_sweep_command(args) -> int:
    """Handler of ``jaxsleigh sweep``; returns the exit code. Run as `jaxsleigh.cli.basin.run_basin_command` is, in
    one process or several (process 0 writes the output, the same bytes as one process)."""
    out = npz_path(args.out)
    st = {}

    def study(checkpoint_dir, resume, shard):
        run = RunOptions(chunk_size=args.chunk_size, progress=args.progress, checkpoint_dir=checkpoint_dir,
                         resume=resume, shard=shard, audit=audit_from_args(args))
        return sweep(st["starts"], st["axes"], plant=st["plant"], **law_kwargs(st["law"]), eps=args.eps,
                     t_final=args.t_final, dt=args.dt, x64=args.x64, stepsize=stepsize_from_args(args), run=run,
                     labels=st["labels"])

    def finish(res, written, record, caught) -> int:
        say_flagged(int((~res.valid[0]).sum()), res.ics.shape[0], why=" (theta0 = 0 or not finite)",
                    fraction="fractions")
        if args.plot:
            from ..plots.base import save_figure
            from ..plots.sweep import plot_sweep

            written.append(str(save_figure(plot_sweep(res), args.plot)))
        print(res.table())
        return say_study_done("sweep", res, record, written, args.eps,
                              head=f"{res.values.shape[0]} values x {res.ics.shape[0]} starts, ")

    def info(res) -> dict:
        S, se = res.fractions()
        return {"fraction": S.tolist(), "fraction_se": se.tolist(), "audit": res.run_info.get("audit")}

    return run_chunked_command(args, "sweep", out, check=lambda: st.update(_check(args)), study=study,
                               save=save_sweep, info=info, finish=finish)


def _check(args) -> dict:
    """Validate everything before any work (a bad range names its --param); nothing is written."""
    if len(args.param) > 2:
        raise ValueError(f"--param may be given once or twice (a line or a 2-D grid), got {len(args.param)}")
    plant, law = model_from_args(args)
    law_names = law_parameter_names(law)
    for s in args.param:
        check_param_name(s, args, law_names)
    axes = [parse_param(s, law_names=law_names) for s in args.param]          # eager: a bad range names its --param
    labels = {a.name: f"--param {s}" for a, s in zip(axes, args.param)}
    if args.ics is None and args.samples is None and args.x is None and args.y is None and args.theta is None:
        args.samples = DEFAULT_SAMPLES
    starts = starts_from_args(args)
    # values x starts, from the counts alone: refused before any value set or row is built
    check_rows(math.prod(a.n for a in axes), starts.ics.shape[0], "jaxsleigh sweep")
    names, values, _ = param_grid(axes, law_names)
    apply_params(names, values, plant, labels=labels, **law_kwargs(law))
    check_tolerance_flags(args)
    solve_config(plant=plant, **law_kwargs(law), t_final=args.t_final, dt=args.dt,
                 stepsize=stepsize_from_args(args), x64=args.x64, eps=args.eps, flags=FLAGS)
    return {"axes": axes, "labels": labels, "plant": plant, "law": law, "starts": starts}


def law_parameter_names(law) -> tuple:
    """The scalar parameters of a ``--controller`` law other than the paper's (its numeric leaves, as
    `jaxsleigh.model.controller.law_leaf_names` names them: ``K``, ``p2``, ``model.m``, ...), which ``--param``
    may sweep; ``()`` for the paper's law, whose gains are `jaxsleigh.studies.sweep.PARAM_NAMES`."""
    if isinstance(law, Gains):
        return ()
    return tuple(n for n, v in law_leaf_names(law).items() if np.ndim(v) == 0)


def sweepable_names(args, law_names: tuple) -> list:
    """What ``--param`` may name with these options: the paper's gains and the plant's parameters under the
    paper's law; the plant's parameters and the law's own under another ``--controller``."""
    ok = [n for n, (where, _, _) in PARAM_NAMES.items() if where.startswith("plant.") or not law_names]
    return ok + [n for n in law_names if n not in ok]


def check_param_name(spec: str, args, law_names: tuple) -> None:
    """Refuse a ``--param NAME=...`` whose NAME these options cannot sweep, listing the names they can."""
    name = spec.split("=", 1)[0].strip() if "=" in spec else None
    if name is None:
        return                                   # parse_param says what is missing
    allowed = sweepable_names(args, law_names)
    if name in allowed:
        return
    law = getattr(args, "controller", "paper")
    whose = f"under --controller {law}" if law_names else "under the paper's law"
    raise ValueError(f"--param {spec}: {name!r} cannot be swept {whose}; choose one of {', '.join(allowed)} "
                     f"(e.g. --param {law_names[0] if law_names else 'k'}=LO:HI:P)")
