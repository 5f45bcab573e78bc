"""Reproduce the simulation of the paper's Section 5 (Figs. 2-5 and H_d(t)).

    python experiments/studies/paper_figures.py [--out out/paper] [--x64] [--dt 0.01]

Thin wrapper around :func:`jaxsleigh.plots.paper_run.run_paper` (the same as ``jaxsleigh paper``).
"""
from __future__ import annotations

import argparse
import sys

from jaxsleigh.plots.paper_run import run_paper, summary_table


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/paper", help="output folder (default out/paper)")
    parser.add_argument("--x64", action="store_true", help="compute in float64 (default float32)")
    parser.add_argument("--dt", type=float, default=0.01, help="base step [s] (default 0.01)")
    args = parser.parse_args(argv)
    paths = run_paper(args.out, x64=args.x64, dt=args.dt, progress=None,
                      command=["experiments/studies/paper_figures.py", *(sys.argv[1:] if argv is None else argv)])
    print(summary_table(paths["npz"]))
    for name, path in paths.items():
        print(f"{name}: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
