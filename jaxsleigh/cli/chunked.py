"""The command line's chunked runs (``jaxsleigh basin``, ``jaxsleigh sweep``, ``jaxsleigh optimum``): the library's
host runner (`jaxsleigh.files.runner.run_to_file`) with the command's options, words, warnings and exit codes.

Exit codes: a refusal before any work 2 (5 for an output another run owns), a full disk 4, a failed cluster
6, Ctrl-C 130 (the finished chunks are kept: ``--resume`` continues); otherwise the command's own.
"""
from __future__ import annotations

import argparse
import json
import sys
import warnings
from typing import Any, Callable

import numpy as np

from ..files.run import COMMAND_WORDS
from ..files.runner import chunk_dir, run_to_file, sidecar
from ..files.workers import ClusterError
from .common import PROG, check_outputs, exit_code, report_warnings, say_failure, status_line
from .options import add_workers_options, workers_from_args
from .values import whole
from ..cache import enable_compilation_cache
from ..errors import FlaggedStartsWarning
from ..studies.audit import Audit, audit_line

__all__ = ["CLI_WORDS", "add_run_options", "run_chunked_command", "shared_options", "how_it_ran"]

#: How the runner's messages name the options on the command line.
CLI_WORDS = COMMAND_WORDS

#: Options that say how the run is computed, not what (a later ``--resume`` may change them).
_HOW = {"cluster_timeout", "progress", "no_compile_cache", "func", "workers", "scheduler"}


def shared_options(args) -> dict:
    """The options that define the run's result, as JSON (what a fresh run records for a later ``--resume``)."""
    options = {k: v for k, v in sorted(vars(args).items())
               if k not in _HOW and not k.startswith("_") and not callable(v)}
    return json.loads(json.dumps(options, default=str))


def add_run_options(p, *, chunk_example: str, chunk_default, chunk_help: str, plot_help: str, audit: bool,
                    keep_help: str = "keep FILE.npz.chunks/ after the .npz is written") -> None:
    """The option groups that end the parser of every chunked command: the run (``--chunk-size``, ``--resume``,
    ``--keep-chunks``, ``--progress``, ``--audit-rows`` with ``audit``), the output (``--out``, ``--plot``) and the
    workers (`jaxsleigh.cli.options.add_workers_options`); the help texts that differ are given."""
    r = p.add_argument_group("run")
    r.add_argument("--chunk-size", type=whole("--chunk-size", chunk_example, minimum=1, maximum=2**31 - 1),
                   default=chunk_default, metavar="N", help=chunk_help)
    r.add_argument("--resume", action="store_true",
                   help="continue an interrupted run from the chunks in FILE.npz.chunks/ (same options)")
    r.add_argument("--keep-chunks", action="store_true", help=keep_help)
    r.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                   help="progress bar with ETA on stderr (default: only on a terminal)")
    if audit:
        r.add_argument("--audit-rows", type=whole("--audit-rows", "64", minimum=0, maximum=4096), default=None,
                       metavar="K", help="accuracy audit: re-run K rows (the unresolved ones first, then random ones) in "
                                         "float64 at rtol = atol = 1e-10 and report the worst differences (default: 1%% "
                                         "of the rows, at most 64, from 500 rows on, as many as fit 10%% of the run's "
                                         "time; 0: no audit)")
    o = p.add_argument_group("output")
    o.add_argument("--out", required=True, metavar="FILE.npz", help="results and settings")
    o.add_argument("--plot", metavar="FILE.png", help=plot_help)
    add_workers_options(p)


def run_chunked_command(args, command: str, out, *, check: Callable[[], None], study: Callable[..., Any], save,
                        info: Callable[[Any], dict], finish: Callable[[Any, list, dict, list], int]) -> int:
    """Run ``study(checkpoint_dir=, resume=, shard=)`` into ``out`` with the options of ``args`` (`run_to_file`);
    returns the exit code.

    ``check()`` validates before anything is written, then the outputs are checked (``out``, its sidecar and chunk
    folder, ``--plot``: `jaxsleigh.cli.common.check_outputs`); ``finish(result, written, record, caught)`` (process 0)
    draws and prints and returns the exit code (``caught``: the run's warnings, for the command to report its
    own way). A Ctrl-C says where the finished chunks are and how to continue; the run's other warnings are
    printed as ``jaxsleigh: warning: ...``.
    """
    chunks, caught = chunk_dir(out), []

    def observed(**kw):
        if not getattr(args, "no_compile_cache", True):     # in a Dask worker too: the programs compiled before are reused
            enable_compilation_cache()
        try:
            with warnings.catch_warnings(record=True) as got:
                warnings.simplefilter("always")
                result = study(**kw)
        except KeyboardInterrupt:
            print(f"{PROG} {command}: interrupted; the finished chunks are in {chunks}/ - run the same command "
                  f"with --resume to continue", file=sys.stderr)
            raise
        report_warnings(got, skip=(FlaggedStartsWarning,))
        caught[:] = got
        return result

    def checked() -> None:
        check()
        check_outputs(sidecar(out), named={"--out": args.out}, figures={"--plot": args.plot}, folders=[chunks],
                      suffix=out.suffix or None)

    workers = workers_from_args(args)
    argv = list(getattr(args, "_argv", None) or [])
    try:
        done = run_to_file(out, observed, save, options=shared_options(args), resume=args.resume,
                           keep_chunks=args.keep_chunks, check=checked, info=info, workers=workers,
                           finish=lambda res, written, record: finish(res, written, record, caught),
                           command=[PROG, *argv] if argv else None, words=CLI_WORDS)
    except ClusterError as e:                   # no worker came or none is left: exit code 6, the chunks kept
        return say_failure(e)
    return done.code


def how_it_ran(res, record: dict) -> str:
    """The run's description for the summary line: dtype, method, workers, chunks resumed."""
    n = record.get("chunks_reused") or 0
    return (f"{res.settings['dtype']}, {res.settings['method']}"
            + (f", {record['workers']} worker{'s' if record['workers'] != 1 else ''}"
               if isinstance(record.get("workers"), int) else "")
            + (f", {len(record['lost_workers'])} worker(s) lost" if record.get("lost_workers") else "")
            + (f", {n} chunk(s) resumed" if n else ""))


def audit_from_args(args):
    """The accuracy audit of ``--audit-rows`` (`jaxsleigh.Audit`; ``False`` for 0; the default audit without it)."""
    rows = getattr(args, "audit_rows", None)
    return None if rows is None else (False if rows == 0 else Audit(rows=rows))


def say_flagged(n_flagged: int, n_starts: int, *, why: str = "", fraction: str = "fraction", caught=()) -> None:
    """``jaxsleigh: warning: K of N starts flagged and not integrated{why}; they are left out of the {fraction}`` on
    stderr, with the reason the first `FlaggedStartsWarning` in ``caught`` gives; nothing when none is flagged."""
    if n_flagged:
        first = next((w.message for w in caught if isinstance(w.message, FlaggedStartsWarning)), None)
        print(f"{PROG}: warning: {n_flagged} of {n_starts} starts flagged and not integrated{why}; they are left out "
              f"of the {fraction}" + (f": {str(first).split(': ', 1)[-1]}" if first is not None else ""),
              file=sys.stderr)


def say_study_done(command: str, res, record: dict, written: list, eps: float, head: str = "") -> int:
    """A study's last words and its exit code: the summary line (``head``, the statuses and who settled, the wall
    time, `how_it_ran`, the files written) and the audit's line on stdout (a failed audit's warning, with what to
    do, is on stderr already); `jaxsleigh.cli.common.exit_code`."""
    print(f"{PROG} {command}: {head}{status_line(res.status, res.T_eps, eps)}; {record['wall_s']:.1f} s wall "
          f"({how_it_ran(res, record)}); wrote {', '.join(written)}")
    rec = (res.run_info or {}).get("audit")
    print(f"{PROG} {command}: {audit_line(rec, flag='--audit-rows')}")
    flags = getattr(res, "unresolved", None)
    if not rec and flags is not None and np.any(flags):        # no audit: the flags are still the run's own
        print(f"{PROG} {command}: {int(np.sum(flags))} rows unresolved (settled oscillation grew: the file's "
              f"'unresolved')")
    return exit_code(res.status, res.T_eps, eps)
