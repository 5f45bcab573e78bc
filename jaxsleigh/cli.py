"""The ``jaxsleigh`` command line.

Subcommands::

    jaxsleigh simulate --ic=-3,-2,pi/8 --ic 3,2,-pi/2 --t-final 100 --out run.npz
    jaxsleigh paper --out out/paper

Adding a subcommand ``name``: write ``_add_<name>(subparsers)`` that creates its parser with
``subparsers.add_parser("name", ...)``, adds its options (the shared groups :func:`_add_model_options`
and :func:`_add_horizon_options` are there to reuse) and ends with
``parser.set_defaults(func=handler)``, where ``handler(args) -> int`` is the exit code; then append
``_add_<name>`` to :data:`_SUBCOMMANDS`. Handlers report bad input by raising ``ValueError`` with a
message that says what to change: :func:`main` prints it as ``jaxsleigh: error: ...`` and returns 2.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import textwrap
import time
import warnings
from collections import Counter
from typing import Optional, Sequence

import numpy as np

from .io import parse_number as _number
from .io import load_ics, write_npz

__all__ = ["main", "build_parser", "parse_ic"]

PROG = "jaxsleigh"


class _UsageError(ValueError):
    """An argparse usage error, reported like any other bad input."""


class _Parser(argparse.ArgumentParser):
    """ArgumentParser that raises instead of exiting, so :func:`main` returns an exit code."""

    def error(self, message):
        raise _UsageError(f"{message} (see '{self.prog} --help')")


# ---------------------------------------------------------------------------------------------
# parsing of values
# ---------------------------------------------------------------------------------------------

def parse_ic(text: str) -> list[float]:
    """``'X,Y,THETA'`` or ``'X,Y,THETA,P1,P2'`` -> list of floats (entries may use ``pi``)."""
    hint = ("expected X,Y,THETA or X,Y,THETA,P1,P2 separated by commas, e.g. --ic=-3,-2,pi/8 "
            "(write --ic=... when the first number is negative)")
    parts = [s for s in text.split(",")]
    if len(parts) not in (3, 5):
        raise ValueError(f"could not parse --ic {text!r}: got {len(parts)} entries; {hint}")
    try:
        vals = [_number(s) for s in parts]
    except ValueError as e:
        raise ValueError(f"could not parse --ic {text!r}: {e}; {hint}") from None
    if not all(math.isfinite(v) for v in vals):
        raise ValueError(f"--ic {text!r} has a non-finite entry; give finite numbers, e.g. --ic 1,1,0.5")
    return vals


def _parse_triple(text: str, flag: str, example: str) -> tuple[float, float, float]:
    parts = text.split(",")
    try:
        if len(parts) != 3:
            raise ValueError(f"got {len(parts)} entries")
        return tuple(_number(s) for s in parts)
    except ValueError as e:
        raise ValueError(f"could not parse {flag} {text!r}: {e}; expected three comma-separated "
                         f"numbers, e.g. {flag} {example}") from None


def _positive_float(flag: str, example: str):
    def conv(text):
        try:
            v = _number(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{flag} must be a number, got {text!r} (e.g. {flag} {example})")
        if not (math.isfinite(v) and v > 0):
            raise argparse.ArgumentTypeError(f"{flag} must be a finite number > 0, got {text!r} "
                                             f"(e.g. {flag} {example})")
        return v
    return conv


def _positive_int(flag: str, example: str):
    def conv(text):
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{flag} must be a whole number, got {text!r} (e.g. {flag} {example})")
        if v < 1:
            raise argparse.ArgumentTypeError(f"{flag} must be >= 1, got {v} (e.g. {flag} {example})")
        return v
    return conv


def _ics_from_args(args) -> np.ndarray:
    if args.ics is not None:
        return load_ics(args.ics, hint="use --ic X,Y,THETA")
    rows = [parse_ic(s) for s in args.ic]
    width = max(len(r) for r in rows)
    rows = [r + [0.0] * (width - len(r)) for r in rows]
    return np.asarray(rows, dtype=np.float64)


# ---------------------------------------------------------------------------------------------
# shared option groups (reused by other subcommands)
# ---------------------------------------------------------------------------------------------

def _add_model_options(parser) -> None:
    """--gains, --params, --damping, --x64."""
    g = parser.add_argument_group("model")
    g.add_argument("--gains", default="paper", metavar="FILE.json|paper|tuned",
                   help='controller gains: a JSON file {"L": [l1, l2, l3], "k": k, "D_hat": [d1, d2] or '
                        '[[a, b], [c, d]]} or a preset (default: paper = L diag(2, .5, .8), k 0.1, '
                        'D_hat diag(4, 8))')
    g.add_argument("--params", default="2,1,1", metavar="M,J,L",
                   help="plant mass m [kg], inertia J [kg m^2] about the centre of mass and offset l [m] "
                        "of the centre of mass from the contact point (default: 2,1,1, the paper's)")
    g.add_argument("--damping", default="coulomb", choices=["coulomb", "viscous", "none"],
                   help="open-loop friction of the plant (default: coulomb, the paper's "
                        "D = diag(1/sqrt(0.1 + p_i^2)))")
    g.add_argument("--x64", action="store_true", help="compute in float64 (default: float32)")


def _model_from_args(args):
    """(plant, gains) from the options of :func:`_add_model_options`."""
    from .params import load_gains, plant_params

    m, J, l = _parse_triple(args.params, "--params", "2,1,1")
    plant = plant_params(m, J, l, damping=args.damping)
    gains = load_gains(args.gains)
    return plant, gains


def _add_horizon_options(parser, *, t_final: float = 100.0, dt: float = 0.01, save_every: Optional[int] = 10,
                         method: bool = True) -> None:
    """--t-final, --dt[, --save-every][, --method, --max-steps]."""
    g = parser.add_argument_group("integration")
    g.add_argument("--t-final", type=_positive_float("--t-final", "100"), default=t_final, metavar="T",
                   help=f"horizon in seconds (a whole multiple of --dt; default {t_final:g})")
    g.add_argument("--dt", type=_positive_float("--dt", "0.01"), default=dt, metavar="DT",
                   help=f"base step in seconds (default {dt:g}); the adaptive method never steps further")
    if save_every is not None:
        g.add_argument("--save-every", type=_positive_int("--save-every", "10"), default=save_every, metavar="K",
                       help=f"keep every K-th base step (default {save_every}; t-final/dt must be a multiple of K)")
    if method:
        g.add_argument("--method", choices=["adaptive", "rk4"], default="adaptive",
                       help="adaptive: RK4 with error control, never above --dt, accurate near theta = 0 "
                            "(default); rk4: classical fixed-step RK4 at --dt")
        g.add_argument("--max-steps", type=_positive_int("--max-steps", "2000000"), default=None, metavar="N",
                       help="budget of attempted steps per trajectory (default: 20x the base steps for "
                            "adaptive); a run that exhausts it gets status 4")


def _add_progress_option(parser) -> None:
    parser.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                        help="progress bar on stderr (default: only on a terminal)")


# ---------------------------------------------------------------------------------------------
# output file
# ---------------------------------------------------------------------------------------------

def _status_counts(status) -> str:
    from .status import Status

    counts = Counter(int(s) for s in np.asarray(status))
    return ", ".join(f"{n} {Status(c).name.lower() if c in Status._value2member_map_ else c}"
                     for c, n in sorted(counts.items()))


# ---------------------------------------------------------------------------------------------
# simulate
# ---------------------------------------------------------------------------------------------

def _simulate_epilog() -> str:
    from .status import describe

    codes = "\n".join(textwrap.fill(line, width=96, initial_indent="  ", subsequent_indent="      ")
                      for line in describe().splitlines())
    return ("status codes (one per initial condition, key 'status' of the output):\n" + codes
            + "\n\noutput .npz keys: t (T,), q (N,T,3), p (N,T,2), u (N,T,2), Hd (N,T), status (N,),\n"
              "  n_steps (N,), n_rejected (N,), ics (N,5), settings_json, dt, t_final, save_every,\n"
              "  method, dtype, gains_L, gains_k, gains_D_hat, params (m,J,l), damping\n\n"
              "examples:\n"
              "  jaxsleigh simulate --ic=-3,-2,pi/8 --ic 3,2,-pi/2 --out run.npz\n"
              "  jaxsleigh simulate --ics starts.npy --t-final 50 --x64 --gains my_gains.json --out run.npz\n"
              "\nA single start with theta0 = 0 (the singular set) or a non-finite entry is an error;\n"
              "in a batch such starts are flagged (status 1 or 2, outputs NaN) and the rest is simulated.")


def _add_simulate(subparsers) -> None:
    p = subparsers.add_parser(
        "simulate", help="simulate the closed loop from initial conditions and save an .npz",
        description="Simulate the Chaplygin sleigh under the discontinuous energy-shaping controller "
                    "(paper eq. 13) from one or more initial conditions; save decimated trajectories "
                    "and the settings that produced them.",
        epilog=_simulate_epilog(), formatter_class=argparse.RawDescriptionHelpFormatter)
    src = p.add_argument_group("initial conditions (one of)").add_mutually_exclusive_group(required=True)
    src.add_argument("--ics", metavar="FILE.npy",
                     help="array of shape (N, 3) [x, y, theta] or (N, 5) [x, y, theta, p1, p2]")
    src.add_argument("--ic", action="append", metavar="X,Y,THETA[,P1,P2]",
                     help="one start (repeatable); entries may use pi, e.g. --ic=-3,-2,pi/8; "
                          "momentum is zero unless P1,P2 are given")
    _add_horizon_options(p)
    _add_model_options(p)
    _add_progress_option(p)
    p.add_argument("--out", required=True, metavar="FILE.npz", help="output file")
    p.set_defaults(func=_cmd_simulate)


def _check_horizon(args) -> None:
    """Say which flag to change when --t-final, --dt and --save-every do not fit together."""
    n_steps = round(args.t_final / args.dt)
    if n_steps < 1 or abs(n_steps * args.dt - args.t_final) > 1e-9 * max(1.0, args.t_final):
        raise ValueError(f"--t-final {args.t_final:g} is not a whole multiple of --dt {args.dt:g}; "
                         f"use e.g. --t-final {max(1, n_steps) * args.dt:g}")
    k = getattr(args, "save_every", None)
    if k is not None and n_steps % k:
        raise ValueError(f"the {n_steps} steps (--t-final / --dt) are not a multiple of --save-every {k}; "
                         f"use a --save-every that divides {n_steps} (e.g. 1)")


def _cmd_simulate(args) -> int:
    from .simulate import simulate
    from .status import Status

    _check_horizon(args)
    ics = _ics_from_args(args)
    plant, gains = _model_from_args(args)
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sol = simulate(ics, plant=plant, gains=gains, t_final=args.t_final, dt=args.dt,
                       save_every=args.save_every, method=args.method, max_steps=args.max_steps,
                       x64=args.x64, progress=args.progress)
    wall = time.perf_counter() - t0
    n = ics.shape[0]
    flagged = int(np.sum(np.isin(sol.status, (Status.SINGULAR_START, Status.INVALID_INPUT))))
    for w in caught:
        text = str(w.message)
        if flagged and "initial conditions are invalid" in text:
            text = text.split("; first: ", 1)[-1]      # the count is printed below
            print(f"{PROG}: warning: first flagged start: {text}", file=sys.stderr)
        else:
            print(f"{PROG}: warning: {text}", file=sys.stderr)
    if flagged:
        print(f"{PROG}: warning: {flagged} of {n} initial conditions flagged and not integrated "
              f"(status 1 = theta0 on the singular set, 2 = non-finite; outputs NaN)", file=sys.stderr)
    out = write_npz(args.out, sol, ics=ics, command=[PROG, *args._argv])
    print(f"{PROG} simulate: N={n}, status: {_status_counts(sol.status)}; "
          f"{wall:.2f} s wall ({sol.settings['dtype']}, {sol.settings['method']}); wrote {out}")
    return 0


# ---------------------------------------------------------------------------------------------
# paper
# ---------------------------------------------------------------------------------------------

def _add_paper(subparsers) -> None:
    p = subparsers.add_parser(
        "paper", help="reproduce the simulation of the paper's Section 5 (Figs. 2-5 and H_d)",
        description="Simulate the paper's setting (m = 2, J = 1, l = 1, Coulomb damping; L = diag(2, 0.5, 0.8), "
                    "k = 0.1, D_hat = diag(4, 8); 100 s) from six starts including (-3, -2, pi/8), and write "
                    "fig2_paths.png, fig3_configuration.png, fig4_momentum.png, fig5_control.png, "
                    "fig_hamiltonian.png and paper.npz into --out.")
    p.add_argument("--out", default="out/paper", metavar="DIR", help="output folder (default out/paper)")
    p.add_argument("--x64", action="store_true", help="compute in float64 (default: float32)")
    p.add_argument("--dt", type=_positive_float("--dt", "0.01"), default=0.01, metavar="DT",
                   help="base step in seconds (default 0.01)")
    # shorter horizon for tests and quick looks; the paper's figures use 100 s
    p.add_argument("--t-final", type=_positive_float("--t-final", "100"), default=100.0, help=argparse.SUPPRESS)
    _add_progress_option(p)
    p.set_defaults(func=_cmd_paper)


def _cmd_paper(args) -> int:
    from .paper import run_paper, summary_table

    t0 = time.perf_counter()
    paths = run_paper(args.out, x64=args.x64, dt=args.dt, t_final=args.t_final, progress=args.progress,
                      command=[PROG, *args._argv])
    wall = time.perf_counter() - t0
    print(summary_table(paths["npz"]))
    print(f"{PROG} paper: {wall:.1f} s wall; wrote " + ", ".join(str(p) for p in paths.values()))
    return 0


# ---------------------------------------------------------------------------------------------
# entry point
# ---------------------------------------------------------------------------------------------

def _add_bench(subparsers) -> None:
    p = subparsers.add_parser(
        "bench", help="measure jaxsleigh's own throughput and accuracy (JSON)",
        description=("Benchmark jaxsleigh on the measured workload (x, y ~ U(-3, 3), |theta0| ~ U(0.3, pi), "
                     "zero momentum): fixed-step RK4 throughput (final state only), correct trajectories per "
                     "second of the default adaptive method (final-state error <= 1e-3 against a float64 "
                     "reference), wrong or non-finite counts, peak memory. Compile time is excluded. "
                     "Peers (plain vmap, NumPy, diffrax, scipy) are compared by experiments/bench_peers.py."))
    p.add_argument("--json", action="store_true", help="print one JSON object (default: a short table)")
    p.add_argument("--n-ics", type=int, default=4096, help="number of initial conditions (default 4096)")
    p.add_argument("--t-final", type=float, default=100.0, help="horizon in s (default 100)")
    p.add_argument("--dt", type=float, default=0.01, help="base step in s (default 0.01)")
    p.add_argument("--x64", action="store_true", help="float64 (default float32)")
    p.add_argument("--seed", type=int, default=0, help="seed of the workload (default 0)")
    p.add_argument("--repeats", type=int, default=1, help="timed repeats, best kept (default 1)")
    p.add_argument("--cache", default=None, help="directory to cache the float64 reference in")
    p.set_defaults(func=_cmd_bench)


def _cmd_bench(args) -> int:
    from .bench import bench

    if args.n_ics < 1:
        raise ValueError(f"--n-ics must be >= 1, got {args.n_ics}")
    res = bench(n_ics=args.n_ics, t_final=args.t_final, dt=args.dt, x64=args.x64, seed=args.seed,
                repeats=args.repeats, cache_dir=args.cache)
    if args.json:
        print(json.dumps(res))
    else:
        for k, v in res.items():
            if k != "machine":
                print(f"{k:40s} {v:.4g}" if isinstance(v, float) else f"{k:40s} {v}")
    return 0


def _optional_subcommands():
    """Subcommands living in their own modules (basins, tuning), registered when present."""
    out = []
    for mod, fn in (("cli_basin", "add_basin"), ("cli_tune", "add_tune")):
        try:
            module = __import__(f"{__package__}.{mod}", fromlist=[fn])
        except ModuleNotFoundError as e:
            if e.name != f"{__package__}.{mod}":
                raise
            continue
        out.append(getattr(module, fn))
    return out


_SUBCOMMANDS = [_add_simulate, _add_paper, _add_bench, *_optional_subcommands()]


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser with every registered subcommand."""
    from . import __version__

    parser = _Parser(prog=PROG, description="Chaplygin sleigh under discontinuous energy-shaping control (JAX).",
                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for add in _SUBCOMMANDS:
        add(sub)
    return parser


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


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run the command line; returns the exit code (0 ok, 2 bad input)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        parser = build_parser()
        args = parser.parse_args(_join_negative_values(argv))
        if getattr(args, "func", None) is None:
            parser.print_help(sys.stderr)
            return 2
        args._argv = argv
        return int(args.func(args) or 0)
    except SystemExit as e:              # --help, --version
        return e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    except ValueError as e:
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
