"""Basins of attraction at scale: two 2-D slices and a Monte-Carlo box, timed; the README figures.

    python experiments/studies/basin_study.py [--n 512] [--n-xy 256] [--samples 65536] [--t-final 100]
                                              [--out out/basin] [--figures docs/figures]

1. x-theta slice at y0 = 1: x in [-3, 3], theta in [-pi, pi], n x n starts at rest (the timed run: it
   crosses the singular set theta = 0, where starts are the most expensive);
2. x-y slice at the paper's heading theta0 = pi/8, n_xy x n_xy starts;
3. Monte-Carlo: uniform in |x|, |y| <= 3, theta in (-pi, pi).

Each run goes through :func:`jaxsleigh.studies.basin.run_basin` with chunk checkpoints next to its ``.npz``
(rerunning the script after an interruption resumes them; the chunks are deleted once the
``.npz`` is written). Wall time, CPU time of this process, machine load (load averages before and
after) and the summaries go to ``basin_study.json``; figures ``basin_xtheta.png``, ``basin_xy.png``,
``basin_mc.png`` go to ``--figures``. The machine should be otherwise idle for the timings.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import sys
import time
from pathlib import Path

import jax

from jaxsleigh import RunOptions
from jaxsleigh.studies.basin import grid_starts, run_basin, sample_starts, save_basin
from jaxsleigh.plots.basin import plot_basin
from jaxsleigh.plots.paper_figures import save_figure


def _load():
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:  # pragma: no cover
        return []


def _cpu():
    """CPU seconds used by this process (all threads): with wall time, how much of the machine it got."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def study(name, starts, out: Path, *, t_final, progress):
    """Run (resuming from chunks if an earlier run was interrupted), save, time."""
    npz = out / f"{name}.npz"
    chunks = out / f"{name}.npz.chunks"
    reused = len(list(chunks.glob("chunk_*.npz"))) if chunks.is_dir() else 0
    load0 = _load()
    cpu0 = _cpu()
    t0 = time.perf_counter()
    res = run_basin(starts, eps=0.05, t_final=t_final,
                    run=RunOptions(checkpoint_dir=chunks, resume=True, progress=progress))
    wall = time.perf_counter() - t0
    cpu = _cpu() - cpu0
    save_basin(npz, res)
    shutil.rmtree(chunks, ignore_errors=True)
    n = int(res.status.size)
    steps = int(res.n_steps.sum() + res.n_rejected.sum())
    info = {"n": n, "wall_s": wall, "cpu_s": cpu, "chunks_reused": reused, "loadavg_before": load0, "loadavg_after": _load(),
            "attempted_steps": steps, "trajectory_steps_per_s": steps / wall, "settings_dtype": res.settings["dtype"],
            "method": res.settings["method"], "chunk_size": res.settings["chunk_size"],
            "devices": (res.run_info or {}).get("devices"), "summary": res.summary()}
    print(f"{name}: N = {n}, {wall:.1f} s wall ({wall / n * 1e3:.2f} ms per start, {steps / wall:.3g} attempted "
          f"steps/s; {cpu:.0f} s CPU = {cpu / wall:.2f} cores), load {load0} -> {info['loadavg_after']}{' (RESUMED chunks: timing invalid)' if reused else ''}")
    print("  " + res.describe().replace("\n", "\n  "), flush=True)
    return res, info


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=512, help="x-theta slice: n x n starts (default 512)")
    parser.add_argument("--n-xy", type=int, default=256, help="x-y slice: n x n starts (default 256)")
    parser.add_argument("--samples", type=int, default=65536, help="Monte-Carlo starts (default 65536)")
    parser.add_argument("--t-final", type=float, default=100.0, help="horizon [s] (default 100)")
    parser.add_argument("--out", default="out/basin", help="folder of the .npz files and basin_study.json")
    parser.add_argument("--figures", default="docs/figures", help="folder of the figures (default docs/figures)")
    parser.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                        help="progress bars (default: on a terminal)")
    args = parser.parse_args(argv)
    out, figs = Path(args.out), Path(args.figures)
    out.mkdir(parents=True, exist_ok=True)
    report = {"machine": {"cpu_count": os.cpu_count(), "jax_backend": jax.default_backend(),
                          "devices": [str(d) for d in jax.devices()]},
              "t_final": args.t_final, "eps": 0.05, "runs": {}}

    n = args.n
    xt, info = study(f"xtheta_{n}", grid_starts(x=f"-3:3:{n}", y=1.0, theta=f"-pi:pi:{n}"), out,
                     t_final=args.t_final, progress=args.progress)
    report["runs"][f"xtheta_{n}"] = info
    save_figure(plot_basin(xt), figs / "basin_xtheta.png")

    m = args.n_xy
    xy, info = study(f"xy_{m}", grid_starts(x=f"-3:3:{m}", y=f"-3:3:{m}", theta="pi/8"), out,
                     t_final=args.t_final, progress=args.progress)
    report["runs"][f"xy_{m}"] = info
    save_figure(plot_basin(xy), figs / "basin_xy.png")

    mc, info = study(f"mc_{args.samples}", sample_starts(args.samples, seed=1), out, t_final=args.t_final,
                     progress=args.progress)
    report["runs"][f"mc_{args.samples}"] = info
    save_figure(plot_basin(mc), figs / "basin_mc.png")

    (out / "basin_study.json").write_text(json.dumps(report, indent=1, default=str) + "\n")
    print(f"wrote {out / 'basin_study.json'} and {figs}/basin_xtheta.png, basin_xy.png, basin_mc.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
