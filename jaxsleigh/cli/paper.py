"""``jaxsleigh paper``: the simulation of the paper's Section 5 and its figures."""
from __future__ import annotations

import argparse
import time

from .common import PROG, add_progress_option, check_outputs, claim_output, number

__all__ = ["add_paper"]


def add_paper(subparsers) -> None:
    p = subparsers.add_parser(
        "paper", help="reproduce the simulation of the paper's Section 5 (Figs. 2-5 and H_d)",
        description="Simulate the paper's setting (m = 2, J = 1, l = 1, Coulomb damping; L = diag(2, 0.5, 0.8), "
                    "k = 0.1, D_hat = diag(4, 8); 100 s) from six starts including (-3, -2, pi/8), and write "
                    "fig2_paths.png, fig3_configuration.png, fig4_momentum.png, fig5_control.png, "
                    "fig_hamiltonian.png and paper.npz into --out.")
    p.add_argument("--out", default="out/paper", metavar="DIR", help="output folder (default out/paper)")
    p.add_argument("--x64", action="store_true", help="compute in float64 (default: float32)")
    p.add_argument("--dt", type=number("--dt", "0.01"), default=0.01, metavar="DT",
                   help="base step in seconds (default 0.01)")
    # shorter horizon for tests and quick looks; the paper's figures use 100 s
    p.add_argument("--t-final", type=number("--t-final", "100"), default=100.0, help=argparse.SUPPRESS)
    p.add_argument("--no-stamp", dest="stamp", action="store_false",
                   help="leave the provenance line (dtype, method, step, device, version) off the figures, "
                        "for a publication; the data file still records it")
    add_progress_option(p)
    p.set_defaults(func=_cmd_paper)


def _cmd_paper(args) -> int:
    from ..plots.paper_run import run_paper, summary_table

    check_outputs(folders=[args.out])
    t0 = time.perf_counter()
    with claim_output(args.out, args, folder=True):
        paths = run_paper(args.out, x64=args.x64, dt=args.dt, t_final=args.t_final, progress=args.progress,
                          command=[PROG, *args._argv], stamp=args.stamp)
    wall = time.perf_counter() - t0
    print(summary_table(paths["npz"]))
    print(f"{PROG} paper: {wall:.1f} s wall simulating and drawing (start-up and imports: see the total on "
          f"stderr); wrote " + ", ".join(str(p) for p in paths.values()))
    return 0
