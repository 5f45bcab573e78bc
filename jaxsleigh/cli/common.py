"""What every subcommand of the command line shares: exit codes, output-path checks, how warnings,
statuses and failures are reported; the parser class and value converters (`jaxsleigh.cli.values`) and
the option groups (`jaxsleigh.cli.options`) are re-exported here.

Exit codes: `EXIT_CODES`, each with what it means (``jaxsleigh --help`` lists them).
"""
from __future__ import annotations

import sys
import textwrap
from pathlib import Path
from typing import Optional

import numpy as np

from ..cache import compilation_cache_dir, enable_compilation_cache  # noqa: F401  (re-exported)
from ..files.workers import EXIT_CLUSTER
from ..files.run import COMMAND_WORDS, Run
from ..files.runlock import settings_fingerprint
from .options import (add_workers_options, add_horizon_options, add_model_options,  # noqa: F401
                      add_progress_option, add_sampler_options, add_tolerance_options, check_bound_fits,
                      check_delay, check_tolerance_flags, law_kwargs, model_from_args,
                      sampler_from_args)
from .values import Parser, UsageError, ics_from_args, number, parse_ic, parse_triple, whole  # noqa: F401
from ..status import Status, converged, counts_in_words, describe
from ..validate import writable_dir, writable_path

__all__ = ["PROG", "say_failure", "EXIT_OK", "EXIT_USAGE", "EXIT_NONE_OK", "EXIT_DISK_FULL", "EXIT_LOCKED",
           "EXIT_CLUSTER", "EXIT_INTERRUPTED", "EXIT_CODES", "FLAGS", "check_outputs", "check_figure", "claim_output",
           "figure_formats", "report_warnings", "status_line", "settled_text", "exit_code", "status_epilog"]

PROG = "jaxsleigh"

EXIT_OK = 0
EXIT_USAGE = 2
EXIT_NONE_OK = 3
EXIT_DISK_FULL = 4
EXIT_LOCKED = 5
EXIT_INTERRUPTED = 130
EXIT_CODES = {EXIT_OK: "done; at least one trajectory ended OK",
              EXIT_USAGE: "bad input; nothing was computed (the message says what to change)",
              EXIT_NONE_OK: "the run finished but no trajectory ended OK (see the status counts; compare: every "
                            "start of a law failed), or tune --search "
                            "found no feasible gains (its history is written), or tune's result does not meet "
                            "--energy-budget (the file is written, flagged)",
              EXIT_DISK_FULL: "the disk or quota is full (the file is named; --resume continues a chunked run "
                              "once there is space)",
              EXIT_LOCKED: "another run is writing the same output or checkpoint folder (it is named); nothing "
                           "was computed",
              EXIT_CLUSTER: "the cluster failed: no Dask worker came, none is left, or a task killed several in "
                            "turn (the message says which); finished chunks are kept (--resume)",
              EXIT_INTERRUPTED: "interrupted (Ctrl-C); finished work is kept (--resume continues)"}

#: Keyword -> flag, so that messages of the shared validation name the flag the user typed.
FLAGS = {"t_final": "--t-final", "dt": "--dt", "save_every": "--save-every", "method": "--method",
         "max_steps": "--max-steps", "x64": "--x64", "eps": "--eps", "rtol": "--rtol", "atol": "--atol",
         "chunk_size": "--chunk-size", "seed": "--seed"}


# ---------------------------------------------------------------------------------------------
# outputs, warnings, statuses
# ---------------------------------------------------------------------------------------------

def check_outputs(*paths, folders=(), named=None, figures=None, suffix=None) -> None:
    """Before any work: every output file can be written (its folder is created if needed) and is not
    a folder, device, named pipe or socket (`jaxsleigh.validate.writable_path`), and every output folder
    is writable. Raises ``ValueError`` naming the path and what it is.

    ``named`` (``{flag: path}``): output files named by their flag in the messages (``--out``), as the
    user typed them: with ``suffix`` (``".npz"``), the extension the command appends to a name without
    it, both that name and the name given are checked; ``figures`` (``{flag: path}``): figure files
    (``--plot``), whose extension must also be a format matplotlib writes (`check_figure`). ``None``
    paths are skipped.
    """
    for flag, p in (figures or {}).items():
        if p is not None:
            check_figure(p, flag)
    for flag, p in (named or {}).items():
        if p is not None:
            writable_path(p, what=f"{flag} file", suffix=suffix)
    for p in paths:
        if p is not None:
            writable_path(p)
    for d in folders:
        if d is not None:
            writable_dir(d)


#: Flags that change how a run looks, not what it writes: left out of its fingerprint (`run_fingerprint`).
_NOT_SETTINGS = {"progress", "cores", "no_compile_cache", "func"}


def run_fingerprint(args) -> str:
    """What identifies a command's run: its parsed flags (the command's name included; those of
    `_NOT_SETTINGS` and private ones left out), hashed. Equal settings, equal fingerprints in every process."""
    settings = {k: v for k, v in vars(args).items() if not k.startswith("_") and k not in _NOT_SETTINGS
                and (v is None or isinstance(v, (str, int, float, bool, list, tuple)))}
    return settings_fingerprint(settings)


def claim_output(path, args=None, *, folder: bool = False) -> Run:
    """The run of a command on its ``--out`` file (or ``folder``), to hold in a ``with`` while it runs
    (`jaxsleigh.files.run.Run`, the lifecycle of every run that writes): meanwhile another run writing there is
    refused (exit code 5), as "the same run is in progress" when its settings (``args``, `run_fingerprint`) are
    these, else as a run with other settings."""
    return Run(path, run_fingerprint(args) if args is not None else None, folder=folder, words=COMMAND_WORDS)


def figure_formats() -> list:
    """The file extensions matplotlib saves figures as (``png``, ``pdf``, ``svg``, ...)."""
    from matplotlib.backend_bases import FigureCanvasBase

    return sorted(FigureCanvasBase.get_supported_filetypes())


def check_figure(path, flag: str = "--plot") -> Path:
    """Before any work: the figure file ``path`` (given with ``flag``) has an extension matplotlib
    writes (it picks the format from it) and can be written. Raises ``ValueError`` naming ``flag``."""
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
    n = int(np.size(status))
    counts = counts_in_words(status).replace(" ok", " integrated")
    line = f"{n} trajector{'y' if n == 1 else 'ies'}: {counts}"
    if T_eps is None:
        return line
    return f"{line}; {settled_text(status, T_eps, eps)}"


def settled_text(status, T_eps, eps: Optional[float] = None) -> str:
    """``'0 settled (T_0.05 = inf)'``, ``'5 settled (median T_0.05 = 3.1 s)'``: how many trajectories settled in
    the ball ``|q| <= eps`` within the horizon (`jaxsleigh.status.converged`) and how fast."""
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
    """`EXIT_OK` if any trajectory ended OK (or certified not to settle: an answer too), else `EXIT_NONE_OK` (with a
    message)."""
    if np.any(np.isin(np.asarray(status), (Status.OK, Status.NOT_SETTLING))):
        return EXIT_OK
    print(f"{PROG}: error: no trajectory ended OK ({status_line(status, T_eps, eps)}); see the status "
          f"codes in --help (exit code {EXIT_NONE_OK})", file=sys.stderr)
    return EXIT_NONE_OK


def status_epilog() -> str:
    """The status codes and exit codes, formatted for a ``--help`` epilog."""
    codes = "\n".join(textwrap.fill(line, width=96, initial_indent="  ", subsequent_indent="      ")
                      for line in describe().splitlines())
    exits = "\n".join(f"  {c} = {t}" for c, t in EXIT_CODES.items())
    return f"status codes (one per trajectory):\n{codes}\n\nexit codes:\n{exits}"


def say_failure(e: BaseException) -> int:
    """Say on stderr why a command stopped (a typed error: ``jaxsleigh: error: ...``; Ctrl-C:
    ``jaxsleigh: interrupted``) and return its exit code: the error's own ``exit_code`` (`EXIT_CODES`),
    else 2 (bad input), 130 for Ctrl-C."""
    if isinstance(e, KeyboardInterrupt):
        print(f"{PROG}: interrupted", file=sys.stderr, flush=True)
        return EXIT_INTERRUPTED
    print(f"{PROG}: error: {e}", file=sys.stderr, flush=True)
    return int(getattr(e, "exit_code", EXIT_USAGE))       # typed errors carry their own (EXIT_CODES)
