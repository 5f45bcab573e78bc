"""What every subcommand of the command line shares: the parser class, value converters, option
groups, output-path checks, how warnings and statuses are reported, exit codes and the
compilation cache.

Exit codes (`EXIT_CODES`): 0 done (at least one trajectory ended OK); 2 bad input (nothing
was computed); 3 the run finished but no trajectory ended OK; 4 the disk (or quota) is full (the
message names the file; ``--resume`` continues a chunked command once there is space); 5 another
run is writing the same output (the message names it); 6 the processes of a multi-process
run failed together (a peer died or never came; finished chunks are kept); 130 interrupted (Ctrl-C; what was
finished is kept, see ``--resume``).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import textwrap
import warnings
from pathlib import Path
from typing import Optional

import numpy as np

from ..files.distributed import CLUSTER_TIMEOUT_S, EXIT_CLUSTER
from ..files.npz import load_ics
from ..files.npz import parse_number as _number

__all__ = ["PROG", "say_failure", "EXIT_OK", "EXIT_USAGE", "EXIT_NONE_OK", "EXIT_DISK_FULL", "EXIT_LOCKED", "EXIT_CLUSTER",
           "EXIT_INTERRUPTED", "EXIT_CODES", "UsageError", "own_output",
           "Parser", "number", "whole", "parse_ic", "parse_triple", "ics_from_args", "add_model_options",
           "model_from_args", "law_kwargs", "add_sampler_options", "sampler_from_args", "add_horizon_options", "add_tolerance_options", "check_tolerance_flags", "add_progress_option", "FLAGS", "check_outputs",
           "check_figure", "figure_formats",
           "report_warnings", "status_line", "settled_text", "exit_code", "status_epilog", "enable_compilation_cache",
           "add_distributed_options", "run_distributed"]

PROG = "jaxsleigh"

EXIT_OK = 0
EXIT_USAGE = 2
EXIT_NONE_OK = 3
EXIT_DISK_FULL = 4
EXIT_LOCKED = 5
EXIT_INTERRUPTED = 130
EXIT_CODES = {EXIT_OK: "done; at least one trajectory ended OK",
              EXIT_USAGE: "bad input; nothing was computed (the message says what to change)",
              EXIT_NONE_OK: "the run finished but no trajectory ended OK (see the status counts), or tune --search "
                            "found no feasible gains (its history is written), or tune's result does not meet "
                            "--energy-budget (the file is written, flagged)",
              EXIT_DISK_FULL: "the disk or quota is full (the file is named; --resume continues a chunked run "
                              "once there is space)",
              EXIT_LOCKED: "another run is writing the same output or checkpoint folder (it is named); nothing "
                           "was computed",
              EXIT_CLUSTER: "the cluster failed: a process of a multi-process run died, never came or could not "
                            "start the coordinator (the message names it); finished chunks are kept (--resume)",
              EXIT_INTERRUPTED: "interrupted (Ctrl-C); finished work is kept (--resume continues)"}

#: Keyword -> flag, so that messages of the shared validation name the flag the user typed.
FLAGS = {"t_final": "--t-final", "dt": "--dt", "save_every": "--save-every", "method": "--method",
         "max_steps": "--max-steps", "x64": "--x64", "eps": "--eps", "rtol": "--rtol", "atol": "--atol",
         "chunk_size": "--chunk-size", "seed": "--seed"}


class UsageError(ValueError):
    """An argparse usage error, reported like any other bad input."""


class Parser(argparse.ArgumentParser):
    """ArgumentParser that raises instead of exiting, so ``main`` returns an exit code."""

    def error(self, message):
        raise UsageError(f"{message} (see '{self.prog} --help')")


# ---------------------------------------------------------------------------------------------
# values
# ---------------------------------------------------------------------------------------------

def number(flag: str, example: str, *, positive: bool = True, nonnegative: bool = False):
    """argparse ``type=``: a finite number (may use ``pi``), ``> 0`` by default."""
    def conv(text):
        try:
            v = _number(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{flag} must be a number, got {text!r} (e.g. {flag} {example})")
        if not math.isfinite(v) or (positive and not v > 0) or (nonnegative and v < 0):
            need = "> 0" if positive else ">= 0" if nonnegative else "finite"
            raise argparse.ArgumentTypeError(f"{flag} must be a finite number {need}, got {text!r} "
                                             f"(e.g. {flag} {example})")
        return v
    return conv


def whole(flag: str, example: str, minimum: int = 1, maximum: int = 2**31 - 2):
    """argparse ``type=``: a whole number in ``[minimum, maximum]``."""
    def conv(text):
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{flag} must be a whole number, got {text!r} (e.g. {flag} {example})")
        if v < minimum:
            raise argparse.ArgumentTypeError(f"{flag} must be >= {minimum}, got {v} (e.g. {flag} {example})")
        if v > maximum:
            raise argparse.ArgumentTypeError(f"{flag} must be <= {maximum}, got {v} (e.g. {flag} {example})")
        return v
    return conv


def parse_ic(text: str) -> list[float]:
    """``'X,Y,THETA'`` or ``'X,Y,THETA,P1,P2'`` -> list of floats (entries may use ``pi``)."""
    hint = ("expected X,Y,THETA or X,Y,THETA,P1,P2 separated by commas, e.g. --ic=-3,-2,pi/8 "
            "(write --ic=... when the first number is negative)")
    parts = text.split(",")
    if len(parts) not in (3, 5):
        raise ValueError(f"could not parse --ic {text!r}: got {len(parts)} entries; {hint}")
    try:
        vals = [_number(s) for s in parts]
    except ValueError as e:
        raise ValueError(f"could not parse --ic {text!r}: {e}; {hint}") from None
    if not all(math.isfinite(v) for v in vals):
        raise ValueError(f"--ic {text!r} has a non-finite entry; give finite numbers, e.g. --ic 1,1,0.5")
    return vals


def parse_triple(text: str, flag: str, example: str) -> tuple[float, float, float]:
    parts = text.split(",")
    try:
        if len(parts) != 3:
            raise ValueError(f"got {len(parts)} entries")
        return tuple(_number(s) for s in parts)
    except ValueError as e:
        raise ValueError(f"could not parse {flag} {text!r}: {e}; expected three comma-separated "
                         f"numbers, e.g. {flag} {example}") from None


def ics_from_args(args) -> np.ndarray:
    """Starts from ``--ics FILE`` or repeated ``--ic X,Y,THETA[,P1,P2]``."""
    if args.ics is not None:
        return load_ics(args.ics, hint="use --ic X,Y,THETA")
    rows = [parse_ic(s) for s in args.ic]
    width = max(len(r) for r in rows)
    rows = [r + [0.0] * (width - len(r)) for r in rows]
    return np.asarray(rows, dtype=np.float64)


# ---------------------------------------------------------------------------------------------
# option groups
# ---------------------------------------------------------------------------------------------

def add_model_options(parser) -> None:
    """--gains, --params, --damping, --x64."""
    from ..model.params import preset_names

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
    from ..controllers.registry import make_controller
    from ..model.params import load_gains, plant_params

    m, J, l = parse_triple(args.params, "--params", "2,1,1")
    plant = plant_params(m, J, l, damping=args.damping)
    name = getattr(args, "controller", "paper")
    if name != "paper" and args.gains != "paper":
        raise ValueError(f"--gains sets the paper's law; it does not apply to --controller {name}")
    if name.endswith(".json"):                   # a law written by `jaxsleigh tune --controller NAME --out F.json`
        from ..tuning.law_file import load_controller_record

        law = load_controller_record(name)
    else:
        law = make_controller(name, load_gains(args.gains)) if name == "paper" else make_controller(name)
    u_max = getattr(args, "saturation", None)
    if u_max is not None:
        from ..controllers.actuators import saturate

        check_bound_fits(u_max, args.x64)
        try:
            law = saturate(law, u_max)
        except ValueError as e:
            raise ValueError(f"--saturation: {e}") from None
    smp = sampler_from_args(args) if hasattr(args, "sample_period") else None
    if smp is not None:
        from ..controllers.actuators import sampled

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
                        "integrated by RK4 substeps of at most --dt in between; --t-final must be a whole number of "
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
    from ..controllers.actuators import sampler
    from ..integrate.sampled import sample_count

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
    from ..model.params import Gains

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


# ---------------------------------------------------------------------------------------------
# outputs, warnings, statuses
# ---------------------------------------------------------------------------------------------

def check_outputs(*paths, folders=(), named=None, figures=None) -> None:
    """Before any work: every output file can be written (its folder is created if needed) and
    every output folder is writable. Raises ``ValueError`` naming the path.

    ``named`` (``{flag: path}``): output files named by their flag in the messages (``--out``);
    ``figures`` (``{flag: path}``): figure files (``--plot``), whose extension must also be a format
    matplotlib writes (`check_figure`). ``None`` paths are skipped.
    """
    from ..validate import writable_dir, writable_path

    for flag, p in (figures or {}).items():
        if p is not None:
            check_figure(p, flag)
    for flag, p in (named or {}).items():
        if p is not None:
            writable_path(p, what=f"{flag} file")
    for p in paths:
        if p is not None:
            writable_path(p)
    for d in folders:
        if d is not None:
            writable_dir(d)


def figure_formats() -> list:
    """The file extensions matplotlib saves figures as (``png``, ``pdf``, ``svg``, ...)."""
    from matplotlib.backend_bases import FigureCanvasBase

    return sorted(FigureCanvasBase.get_supported_filetypes())


def check_figure(path, flag: str = "--plot") -> Path:
    """Before any work: the figure file ``path`` (given with ``flag``) has an extension matplotlib
    writes (it picks the format from it) and can be written. Raises ``ValueError`` naming ``flag``."""
    from ..validate import writable_path

    p = Path(path)
    ext = p.suffix.lower().lstrip(".")
    formats = figure_formats()
    if ext not in formats:
        got = f"the extension .{ext}" if ext else "no extension"
        raise ValueError(f"{flag} {str(path)!r} has {got}, which is not a figure format; name the file with one of "
                         f".{', .'.join(formats)} (e.g. {flag} {str(p.with_suffix('.png'))!r})")
    return writable_path(p, what=f"{flag} file")


def report_warnings(caught, *, skip=()) -> None:
    """Print caught warnings as ``jaxsleigh: warning: ...``; warnings of the types in ``skip`` are
    left out (the caller reports them its own way)."""
    for w in caught:
        if isinstance(w.message, tuple(skip)):
            continue
        print(f"{PROG}: warning: {w.message}", file=sys.stderr)


def status_line(status, T_eps=None, eps: Optional[float] = None) -> str:
    """``'3 trajectories: 2 integrated, 1 singular_start; 1 settled (median T_0.05 = 4.2 s)'``.

    "integrated" counts the trajectories that reached the horizon (status OK), the other statuses are named;
    with ``T_eps`` (and the run's ``eps``) the line also says how many settled in the ball within the horizon:
    for one trajectory its ``T_eps`` (``inf``: it did not settle), for several the median over the settled ones.
    """
    from ..status import counts_in_words

    n = int(np.size(status))
    counts = counts_in_words(status).replace(" ok", " integrated")
    line = f"{n} trajector{'y' if n == 1 else 'ies'}: {counts}"
    if T_eps is None:
        return line
    return f"{line}; {settled_text(status, T_eps, eps)}"


def settled_text(status, T_eps, eps: Optional[float] = None) -> str:
    """``'0 settled (T_0.05 = inf)'``, ``'5 settled (median T_0.05 = 3.1 s)'``: how many trajectories settled in
    the ball ``|q| <= eps`` within the horizon (`jaxsleigh.status.converged`) and how fast."""
    from ..status import converged

    T = np.asarray(T_eps, np.float64).ravel()
    ok = np.asarray(converged(np.asarray(status).ravel(), T))
    sym = f"T_{eps:g}" if eps is not None else "T_eps"
    if T.size == 1:
        value = f"{T[0]:.3g} s" if ok[0] else ("inf" if not np.isnan(T[0]) else "nan")
        return f"{int(ok.sum())} settled ({sym} = {value})"
    if not ok.any():
        return f"0 settled ({sym} = inf for all)"
    return f"{int(ok.sum())} settled (median {sym} = {float(np.median(T[ok])):.3g} s)"


def exit_code(status, T_eps=None, eps: Optional[float] = None) -> int:
    """`EXIT_OK` if any trajectory ended OK, else `EXIT_NONE_OK` (with a message)."""
    from ..status import Status

    if np.any(np.asarray(status) == Status.OK):
        return EXIT_OK
    print(f"{PROG}: error: no trajectory ended OK ({status_line(status, T_eps, eps)}); see the status "
          f"codes in --help (exit code {EXIT_NONE_OK})", file=sys.stderr)
    return EXIT_NONE_OK


def status_epilog() -> str:
    """The status codes and exit codes, formatted for a ``--help`` epilog."""
    from ..status import describe

    codes = "\n".join(textwrap.fill(line, width=96, initial_indent="  ", subsequent_indent="      ")
                      for line in describe().splitlines())
    exits = "\n".join(f"  {c} = {t}" for c, t in EXIT_CODES.items())
    return f"status codes (one per trajectory):\n{codes}\n\nexit codes:\n{exits}"


# ---------------------------------------------------------------------------------------------
# chunked, checkpointed subcommands (basin, sweep)
# ---------------------------------------------------------------------------------------------

def run_chunked(command: str, chunks, fn):
    """Call ``fn()`` of a chunked, checkpointed subcommand, recording its warnings: a Ctrl-C says where
    the finished chunks are and how to continue; the warnings (but flagged rows, which the command
    reports its own way) are printed. Returns ``(fn(), caught warnings)``."""
    from ..errors import FlaggedStartsWarning

    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            result = fn()
    except KeyboardInterrupt:
        print(f"{PROG} {command}: interrupted; the finished chunks are in {chunks}/ - run the same command with "
              f"--resume to continue", file=sys.stderr)
        raise
    report_warnings(caught, skip=(FlaggedStartsWarning,))
    return result, caught


def compute_share(command: str, chunks, out, shard: tuple, fn) -> None:
    """One process's share ``shard = (index, count)`` of a multi-process run: ``fn(shard)`` writes its
    chunks (see :func:`run_chunked`); processes other than 0 say so when they are done."""
    import time

    t0 = time.perf_counter()
    run_chunked(command, chunks, lambda: fn(shard))
    if shard[0] != 0:
        print(f"{PROG} {command}: process {shard[0]} of {shard[1]}: share of the chunks done in "
              f"{time.perf_counter() - t0:.1f} s; process 0 writes {out}", file=sys.stderr)


def load_average() -> list:
    """The machine's load averages (1, 5, 15 min), recorded next to timings; [] where unknown."""
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:  # pragma: no cover - not on every platform
        return []


def finish_chunked(command: str, st: dict, res, *, multi: bool, wall: float, path, extra: dict,
                   plot=None) -> tuple[list, str]:
    """The end of a chunked subcommand: the sidecar ``FILE.run.json`` (what varies between runs:
    command, wall time, devices, chunks resumed, load, processes; plus ``extra``), the chunk folder
    removed unless ``--keep-chunks``, the plot (``plot(res)`` -> Figure) if ``--plot``. Returns the
    paths written and the run's description for the summary line (dtype, method, processes, resumed)."""
    import json
    import shutil

    from ..files.npz import atomic_write_text

    args = st["args"]
    argv = list(getattr(args, "_argv", None) or [])
    # several processes: every chunk is read back here; "resumed" counts those of an earlier run
    n_reused = st["had"] if multi else int((res.run_info or {}).get("chunks_reused") or 0)
    info = {"command": [PROG, *argv] if argv else None, "wall_s": wall,
            "devices": (res.run_info or {}).get("devices"), "chunks_reused": n_reused,
            "loadavg_start": st["load_start"], "loadavg_end": load_average(), "cpu_count": os.cpu_count(), **extra}
    if multi:
        import jax

        info["processes"] = jax.process_count()
    atomic_write_text(st["side"], json.dumps(info, indent=1, default=str) + "\n")
    written = [str(path), str(st["side"])]
    if args.plot and plot is not None:          # before the chunks go: a full disk here leaves --resume to finish
        from ..plots.base import save_figure

        written.append(str(save_figure(plot(res), args.plot)))
    if not args.keep_chunks:
        shutil.rmtree(st["chunks"], ignore_errors=True)
    how = (f"{res.settings['dtype']}, {res.settings['method']}"
           + (f", {info['processes']} processes" if multi else "")
           + (f", {n_reused} chunk(s) resumed" if n_reused else ""))
    return written, how


#: Options that do not change the chunks (left out of the checkpoint's recorded options).
_NOT_RESULT = {"out", "plot", "resume", "keep_chunks"}


def _result_options(args) -> dict:
    return {k: v for k, v in json.loads(json.dumps(
        {k: v for k, v in sorted(vars(args).items()) if not callable(v)}, default=str)).items()
        if k not in _PER_PROCESS and k not in _NOT_RESULT and not k.startswith("_")}


def own_output(out, chunks, args) -> tuple:
    """Claim ``out`` and its chunk folder for this run, before looking at the folder: a lock next to
    ``out`` (`jaxsleigh.files.runlock.RunLock`; `RunLockedError` names another live run), then refuse a
    folder that holds chunks without ``--resume``. Returns ``(lock, the chunk files found)``;
    `run_distributed` releases the lock (and records the options, see `_record_options`)."""
    from ..files.runlock import RunLock

    lock = RunLock(out, getattr(args, "_run_id", None) or _single_run_id(), what="output",
                   hint="choose another --out").acquire()
    try:
        have = sorted(Path(chunks).glob("chunk_*.npz")) if Path(chunks).is_dir() else []
        if have and not args.resume:
            raise ValueError(f"{str(chunks)!r} holds the chunks of an earlier, unfinished run for {str(out)!r}; add "
                             f"--resume (with the same options) to continue it, or delete or move that folder (or "
                             f"choose another --out) to start afresh")
    except BaseException:
        lock.release()
        raise
    return lock, have


def _record_options(state, args) -> None:
    """A fresh run records its options in ``chunks/options.json``, so that a refused ``--resume``
    can name the options that differ (after the checks: a refused run writes nothing)."""
    from ..files.npz import atomic_write_text

    chunks = state.get("chunks") if isinstance(state, dict) else None
    if chunks is None:
        return
    rec = Path(chunks) / "options.json"
    if not args.resume or not rec.exists():
        atomic_write_text(rec, json.dumps(_result_options(args), indent=1, sort_keys=True) + "\n")


def _single_run_id() -> str:
    """A single-process run is its own run: no other process shares its output."""
    import platform
    import time

    return f"{platform.node()}:{os.getpid()}:{time.time_ns()}"


def _options_differ(chunks, args) -> str:
    """``'--seed 3 in the checkpoint vs --seed 4 now; ...'`` from ``chunks/options.json``; '' if unknown."""
    try:
        old = json.loads((Path(chunks) / "options.json").read_text())
    except (OSError, ValueError):
        return ""
    if not isinstance(old, dict):
        return ""
    new = _result_options(args)

    def show(k, v):
        flag = "--" + k.replace("_", "-")
        if v is None or v is False:
            return f"no {flag}"
        if v is True:
            return flag
        return f"{flag} {' '.join(map(str, v)) if isinstance(v, list) else v}"

    diffs = [f"{show(k, old.get(k))} in the checkpoint vs {show(k, new.get(k))} now"
             for k in sorted(set(old) | set(new)) if old.get(k) != new.get(k)]
    return "; ".join(diffs)


# ---------------------------------------------------------------------------------------------
# compilation cache
# ---------------------------------------------------------------------------------------------

# compilation_cache_dir and enable_compilation_cache live in jaxsleigh.cache (also public as
# jaxsleigh.enable_compilation_cache); re-exported here for the subcommands and older imports
from ..cache import compilation_cache_dir, enable_compilation_cache  # noqa: E402,F401


# ---------------------------------------------------------------------------------------------
# several processes (jax.distributed)
# ---------------------------------------------------------------------------------------------

def add_distributed_options(parser) -> None:
    """--coordinator HOST:PORT, --num-processes N, --process-id I (all three or none; see
    `run_distributed`)."""
    g = parser.add_argument_group(
        "processes", "several processes or hosts share the run through jax.distributed; start the same command "
                     "in every process (only --process-id differs). Give all three options, or none under "
                     "SLURM (srun) / Open MPI (mpirun), where they are detected. The checkpoint folder must be on "
                     "a filesystem that every process sees; process 0 writes the output.")
    g.add_argument("--coordinator", metavar="HOST:PORT",
                   help="address of process 0 and a free port for the coordinator (e.g. 10.0.0.1:12345)")
    g.add_argument("--num-processes", type=whole("--num-processes", "2"), metavar="N",
                   help="number of processes in the run")
    g.add_argument("--process-id", type=whole("--process-id", "0", minimum=0), metavar="I",
                   help="this process's id, 0..N-1 (0 runs the coordinator and writes the output)")
    g.add_argument("--cluster-timeout", type=number("--cluster-timeout", "60"), default=CLUSTER_TIMEOUT_S,
                   metavar="S", help=f"seconds to wait for a process that shows no sign of life: the coordinator "
                                     f"and the others at the start, a silent process during the run (then declared "
                                     f"dead; exit code {EXIT_CLUSTER}) (default {CLUSTER_TIMEOUT_S})")


#: Options that may differ between the processes of one run (everything else must be equal).
_PER_PROCESS = {"coordinator", "num_processes", "process_id", "cluster_timeout", "progress", "no_compile_cache",
                "func", "_argv", "_run_id"}


def _cluster_run_id(args, cluster) -> str:
    """The fingerprint that the processes of one run share (their output and chunk folder are one): from
    their coordinator (or the SLURM / Open MPI job) and their count; options that differ between them
    are refused with a message of their own."""
    import hashlib

    where = getattr(args, "coordinator", None) or os.environ.get("SLURM_JOB_ID") or os.environ.get(
        "OMPI_MCA_orte_hnp_uri", "")
    return hashlib.sha256(json.dumps([where, cluster.count], default=str).encode()).hexdigest()


def _explained(e, state, args):
    """A full disk or a refused checkpoint told with what to do (where the finished chunks are, which
    options differ from the interrupted run's); ``None`` where there is nothing to add."""
    from ..errors import CheckpointError, DiskFullError, RunLockedError

    chunks = state.get("chunks") if isinstance(state, dict) else None
    if isinstance(e, DiskFullError):
        if "(resume=True)" in str(e):           # the library's words for Python; the command line's alone
            return DiskFullError(e.errno, str(e).replace(" (resume=True)", ""), path=e.path)
        if chunks is None or "--resume" in str(e):
            return None
        return DiskFullError(e.errno, f"{e}; the finished chunks are kept in {str(chunks)!r}: once there is space, "
                                      f"the same command with --resume continues", path=e.path)
    why = _options_differ(chunks, args) if chunks is not None else ""
    if not why or isinstance(e, RunLockedError):
        return None
    # the flags first, in the user's terms: the library's own account of the settings is left out
    return CheckpointError(f"{why}: {str(chunks)!r} holds the chunks of a run with other options; to continue it, "
                           f"give its options with --resume, or delete or move {str(chunks)!r} (or choose another "
                           f"--out) to start afresh")


def run_distributed(args, *, check, compute, assemble, prepare=None, shared_dirs=None) -> int:
    """Run a chunked subcommand in one process or, with the options of
    `add_distributed_options` (or under SLURM / Open MPI), in several; returns the exit code.

    Call it first thing in the handler, before any JAX computation (it starts
    ``jax.distributed``). The subcommand provides:

    * ``check()``: validate the input and the outputs, refuse a checkpoint folder that holds chunks
      without ``--resume`` (raise ``ValueError``; write nothing besides creating folders); return a
      state passed to the other steps;
    * ``compute(state, (index, count))``: write this process's share of the chunks
      (``run_basin(..., checkpoint_dir=..., resume=True, shard=(index, count))``);
    * ``assemble(state, multi)``: write the outputs and return the exit code. ``multi`` is
      ``True`` when several processes computed the chunks: read them with ``resume=True``; it
      is ``False`` in a single-process run, which does all the work here as before;
    * ``prepare(state)`` (optional): run by process 0 only, after every process has passed
      ``check``, before anyone computes (e.g. remove the stale manifest of a fresh run);
    * ``shared_dirs(state)`` (optional): the checkpoint folders, checked to be shared.

    In a multi-process run every process checks, the verdicts are exchanged (a refusal anywhere is
    reported by every process, before any chunk is written, with its exit code: 2, or 5 for an output in
    use), every process computes its share, process 0 assembles and writes, and every process returns
    process 0's exit code (a full disk while it writes: 4 in every process; Ctrl-C there: 130 in process
    0). The options (except the three above and ``--progress``) must be equal in every process.
    """
    from ..files.distributed import ClusterError
    from ..errors import CheckpointError, DiskFullError

    try:
        cluster = _start_cluster(args)
    except ClusterError as e:
        say_failure(e)
        return EXIT_CLUSTER
    options = _shared_options(args)
    if cluster is not None:
        args._run_id = _cluster_run_id(args, cluster)
    held = {}

    def checked():
        held["state"] = state = check()
        return state

    try:
        try:
            if cluster is None:
                return _run_single(args, checked, assemble)
            code = _run_processes(cluster, args, options, checked=checked, compute=compute, assemble=assemble,
                                  prepare=prepare, shared_dirs=shared_dirs)
        except (DiskFullError, CheckpointError) as e:
            better = _explained(e, held.get("state"), args)
            if better is None:
                raise
            raise better from None
        finally:
            _release_lock(held.get("state"))
    except (ValueError, OSError, KeyboardInterrupt) as e:
        if cluster is None or not cluster.synced:
            raise                                   # one process, or a refusal before any work: as usual
        # process 0 failed while writing (a full disk, Ctrl-C): the others have left already, so JAX's
        # shutdown would wait for them and abort; say it as a single process would, and leave
        code = say_failure(e)
    return _leave(cluster, code)


def _shared_options(args) -> dict:
    """The options that must be equal in every process (as JSON: what the processes compare)."""
    options = {k: v for k, v in sorted(vars(args).items()) if k not in _PER_PROCESS and not callable(v)}
    return json.loads(json.dumps(options, default=str))


def _run_single(args, checked, assemble) -> int:
    """A single-process run: check, record the options, do all the work in ``assemble``."""
    state = checked()
    _record_options(state, args)
    return int(assemble(state, False))


def say_failure(e: BaseException) -> int:
    """Say on stderr why a command stopped (a typed error: ``jaxsleigh: error: ...``; Ctrl-C:
    ``jaxsleigh: interrupted``) and return its exit code: the error's own ``exit_code`` (`EXIT_CODES`),
    else 2 (bad input), 130 for Ctrl-C."""
    if isinstance(e, KeyboardInterrupt):
        print(f"{PROG}: interrupted", file=sys.stderr, flush=True)
        return EXIT_INTERRUPTED
    print(f"{PROG}: error: {e}", file=sys.stderr, flush=True)
    return int(getattr(e, "exit_code", EXIT_USAGE))       # typed errors carry their own (EXIT_CODES)


def _start_cluster(args):
    """`jaxsleigh.files.distributed.start` with the options of `add_distributed_options`: the
    `Cluster` of a multi-process run, ``None`` for a single process."""
    from ..files.distributed import start

    return start(getattr(args, "coordinator", None), getattr(args, "num_processes", None),
                 getattr(args, "process_id", None),
                 timeout_s=getattr(args, "cluster_timeout", None) or CLUSTER_TIMEOUT_S)


def _run_processes(cluster, args, options, *, checked, compute, assemble, prepare, shared_dirs) -> int:
    """`jaxsleigh.files.distributed.run_shared` for a subcommand: process 0 records the options
    after ``prepare``; a failed cluster is exit code 6, a refusal after every process has read the
    result the refusal's exit code (process 0's: 4 for a full disk; else 2). A refusal before any work
    is raised: JAX shuts down as usual."""
    from ..files.distributed import ClusterError, run_shared

    def prepared(state):
        if prepare is not None:
            prepare(state)
        _record_options(state, args)

    try:
        return run_shared(cluster, check=checked, compute=compute, assemble=lambda state: assemble(state, True),
                          prepare=prepared, shared_dirs=shared_dirs or (lambda state: []), options=options)
    except ClusterError as e:
        say_failure(e)
        return EXIT_CLUSTER
    except ValueError as e:
        if not cluster.synced:
            raise                               # a refusal before any work: JAX shuts down as usual
        return say_failure(e)                   # process 0's exit code, e.g. 4 for a full disk


def _release_lock(state) -> None:
    """Release the output's lock that ``check`` took (`own_output`), if it got that far."""
    lock = state.get("lock") if isinstance(state, dict) else None
    if lock is not None:
        lock.release()


def _leave(cluster, code: int) -> int:
    """Stop this process's heartbeat and return ``code``; a process whose cluster failed, or that has
    process 0's result, exits here at once instead."""
    if code == EXIT_CLUSTER or cluster.synced:
        # JAX's shutdown would wait at its shutdown barrier for a process that died, then abort: leave
        # now (every file is written, atomically, already; every survivor has process 0's result)
        cluster.stop()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    cluster.stop()
    return code
