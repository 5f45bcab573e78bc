"""The ``jaxsleigh`` command line.

Subcommands (one module each; shared helpers in `jaxsleigh.cli.common`)::

    jaxsleigh simulate --ic=-3,-2,pi/8 --ic 3,2,-pi/2 --t-final 100 --out run.npz
    jaxsleigh paper --out out/paper
    jaxsleigh basin --x -3:3:128 --y -3:3:128 --theta pi/8 --out xy.npz --plot xy.png
    jaxsleigh tune --out gains.json
    jaxsleigh bench --json
    jaxsleigh controllers
    jaxsleigh compare --samples 256 --seed 0 --out table.json --plot table.png

Adding a subcommand ``name``: a module with ``add_<name>(subparsers)`` that creates its parser
(``subparsers.add_parser("name", ...)``), adds its options (the shared groups of
`common` are there to reuse) and ends with ``parser.set_defaults(func=handler)``,
where ``handler(args) -> int`` is the exit code; then list it in `SUBCOMMANDS`. Handlers report
bad input by raising ``ValueError`` with a message that says what to change: `main` prints it
as ``jaxsleigh: error: ...`` and returns 2. Exit codes: `EXIT_CODES`.
"""
from __future__ import annotations

import argparse
import atexit
import os
import sys
import threading
from pathlib import Path
from typing import Optional, Sequence

from . import clock  # first: its fallback origin is the earliest moment of the command line
from .. import __version__, cores
from ..cache import compilation_cache_dir, enable_compilation_cache
from .basin import add_basin
from .optimum import add_optimum
from .bench import add_bench
from .compare import add_compare, add_controllers
from .common import EXIT_CODES, EXIT_USAGE, PROG, Parser, parse_ic, say_failure
from .paper import add_paper
from .simulate import add_simulate
from .sweep import add_sweep
from .tune import add_tune

__all__ = ["main", "build_parser", "parse_ic", "SUBCOMMANDS"]

SUBCOMMANDS = [add_simulate, add_paper, add_bench, add_basin, add_tune, add_sweep, add_controllers, add_compare,
               add_optimum]


def build_parser() -> Parser:
    """The top-level parser with every registered subcommand."""
    parser = Parser(prog=PROG, description="Chaplygin sleigh under discontinuous energy-shaping control (JAX).",
                    epilog="exit codes:\n" + "\n".join(f"  {c} = {t}" for c, t in EXIT_CODES.items())
                    + "\n\n" + _cache_help(),
                    formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    parser.add_argument("--no-compile-cache", action="store_true",
                        help="do not use the persistent compilation cache (every process compiles afresh)")
    parser.add_argument("--cores", type=_cores, default=None, metavar="N",
                        help="use at most N cores (default: every core; as JAXSLEIGH_CORES=N). The results do "
                             "not depend on it")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    for add in SUBCOMMANDS:
        add(sub)
    return parser


def _cache_help() -> str:
    """Where compiled programs are kept, as this process's environment has it (`jaxsleigh.cache.compilation_cache_dir`:
    JAXSLEIGH_CACHE_DIR, XDG_CACHE_HOME or ~/.cache)."""
    where = compilation_cache_dir()
    if where is None:
        return ("Compiled programs are not cached: JAXSLEIGH_NO_COMPILE_CACHE is set (unset it to keep them in\n"
                "JAXSLEIGH_CACHE_DIR or $XDG_CACHE_HOME/jaxsleigh/jax).")
    home = str(Path.home())
    shown = "~" + str(where)[len(home):] if str(where).startswith(home + os.sep) else str(where)
    return (f"Compiled programs are cached in {shown} (JAXSLEIGH_CACHE_DIR to move it,\n"
            f"JAXSLEIGH_NO_COMPILE_CACHE=1 or --no-compile-cache to turn it off).")


def _cores(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be a whole number of cores >= 1, e.g. --cores 2 (got {text!r})")
    return n


def _join_negative_values(argv: list[str]) -> list[str]:
    """``--ic -3,-2,0.4`` -> ``--ic=-3,-2,0.4`` (argparse would read ``-3,...`` as an option)."""
    out, i = [], 0
    while i < len(argv):
        a = argv[i]
        if a in ("--ic", "--params") and i + 1 < len(argv) and argv[i + 1].startswith("-") \
                and "," in argv[i + 1]:
            out.append(f"{a}={argv[i + 1]}")
            i += 2
        else:
            out.append(a)
            i += 1
    return out


def run() -> None:
    """The ``jaxsleigh`` program: `main`, then exit without tearing the interpreter down.

    Python's teardown of a process that used JAX (its modules, compiled programs and CPU client) takes
    ~0.25 s, a sixth of a command that found its programs kept. Nothing of the command is left by then:
    its threads are joined and the exit handlers run (logging flushes, a multi-process run disconnects)
    exactly as at a normal exit, and only the freeing of memory is skipped.
    """
    rc = main()
    shutdown = getattr(threading, "_shutdown", None)      # what the interpreter runs first at exit
    if shutdown is None:
        sys.exit(rc)
    shutdown()
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):                    # a closed pipe: nothing more can be said
            pass
    os._exit(rc)


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run the command line; returns the exit code (`jaxsleigh.cli.common.EXIT_CODES`)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        parser = build_parser()
        args = parser.parse_args(_join_negative_values(argv))
        if getattr(args, "func", None) is None:
            parser.print_help(sys.stderr)
            return EXIT_USAGE
        if args.cores is not None:
            os.environ["JAXSLEIGH_CORES"] = str(args.cores)     # read by every run (jaxsleigh.cores.workers)
        # a program may set JAX up as it starts (the library leaves that to its first run, and to the user):
        # one CPU device per core, and the compiled programs of earlier processes
        cores.configure()
        if not args.no_compile_cache:
            enable_compilation_cache()
        args._argv = argv
        rc = int(args.func(args) or 0)
        # the commands' own "... s wall" leave out start-up and imports; the whole wait goes to stderr
        # (stdout may be machine-read, e.g. bench --json)
        sys.stdout.flush()           # the command's own output first, whole, where both go to one stream
        print(clock.whole_wall_line(PROG, args.command), file=sys.stderr)
        return rc
    except SystemExit as e:              # --help, --version
        return e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    except (ValueError, OSError, KeyboardInterrupt) as e:
        return say_failure(e)
