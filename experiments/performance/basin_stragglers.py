r"""The default basin's stragglers near theta = 0, answered: this tree against an earlier commit, side by side.

    python experiments/performance/basin_stragglers.py [--n 100000] [--seed 5] [--t-final 100] [--baseline 96855ab]
        [--new HEAD] [--repeats 1] [--warmup N] [--radau 4] [--out docs/figures/basin_stragglers.json]

1. ``runs``: ``jaxsleigh basin --samples N --seed S --t-final T`` (2 cores, float32, the defaults) in a fresh process
   of each tree, a git worktree of ``--baseline`` and one of ``--new`` (``HEAD`` by default, so that uncommitted
   work in the folder does not enter the figure), each warmed first by one untimed run of the same command
   (``--warmup N``: a basin of N starts instead; a small one does not compile the programs that only the full
   basin's stragglers need, so a tree's first timed run would compile them), then timed in turn ``--repeats`` times
   (interleaved), with the load average before and after each run: wall time, starts per second, the status counts,
   the attempted steps: the steady state of a command run again, with every program compiled and cached.
2. ``agreement``: of the last runs of both trees, the starts that settle in both (same status? the largest
   difference of T_eps), and the share of starts without an answer (status 4, budget exhausted) in each. A start
   whose T_eps differ by more than 1e-3 s is run again in float64 at rtol = atol = 1e-10: each tree's error.
3. ``certified``: the ``--radau`` starts of the new run that were certified not to settle (status 9) with the
   largest ``|theta0|`` (the cheapest for the reference), integrated by SciPy's Radau in float64
   (rtol = atol = 1e-8, physical chart) to the horizon: whether each is outside the ball ``|q| <= eps`` there (it must
   be, for the certificate to be right).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import ROOT, baseline_tree, load  # noqa: E402

CLI = "import sys; from jaxsleigh.cli import run; sys.argv[0] = 'jaxsleigh'; run()"


def basin(tree: Path, out: Path, n: int, seed: int, t_final: float) -> dict:
    """One ``jaxsleigh basin`` in a fresh process of ``tree``: wall time (the whole process) and the load."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    cmd = [sys.executable, "-c", CLI, "basin", "--samples", str(n), "--seed", str(seed), "--t-final", str(t_final),
           "--out", str(out), "--no-progress"]
    before = load()
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=tempfile.gettempdir(), timeout=3600)
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        raise RuntimeError(r.stderr[-3000:])
    d = np.load(out)
    st = d["status"]
    codes, counts = np.unique(st, return_counts=True)
    return {"wall_s": round(wall, 2), "starts_per_s": round(n / wall, 1), "load_before": before, "load_after": load(),
            "status_counts": {int(c): int(k) for c, k in zip(codes, counts)},
            "attempted_steps": int((d["n_steps"] + d["n_rejected"]).sum()),
            "settled": int((np.isfinite(d["T_eps"]) & (st == 0)).sum()), "stdout_tail": r.stdout.strip()[-400:]}


def agreement(a_path: Path, b_path: Path) -> dict:
    a, b = np.load(a_path), np.load(b_path)
    sa, sb, ta, tb = a["status"], b["status"], a["T_eps"], b["T_eps"]
    settled_a, settled_b = np.isfinite(ta) & (sa == 0), np.isfinite(tb) & (sb == 0)
    both = settled_a & settled_b
    n = sa.size
    return {"settled_baseline": int(settled_a.sum()), "settled_new": int(settled_b.sum()),
            "settled_both": int(both.sum()), "same_status_where_settled_in_both": bool(np.all(sa[both] == sb[both])),
            "max_T_eps_diff_s": float(np.max(np.abs(ta[both] - tb[both]))) if both.any() else None,
            "T_eps_diff_over_1e-3": int(np.sum(np.abs(ta[both] - tb[both]) > 1e-3)),
            "status4_baseline": int((sa == 4).sum()), "status4_new": int((sb == 4).sum()),
            "status4_share_baseline": float((sa == 4).mean()), "status4_share_new": float((sb == 4).mean()),
            "transitions": {f"{x}->{y}": int(np.sum((sa == x) & (sb == y)))
                            for x in np.unique(sa) for y in np.unique(sb) if np.any((sa == x) & (sb == y))},
            "n": n}


def reference_check(a_path: Path, b_path: Path, t_final: float, over: float = 1e-3) -> list:
    """The starts that settle in both runs with T_eps more than ``over`` apart, run again in float64 at
    rtol = atol = 1e-10 (`jaxsleigh.run_basin`, the reference): each run's T_eps error against it."""
    import jaxsleigh as js

    a, b = np.load(a_path), np.load(b_path)
    ta, tb = a["T_eps"], b["T_eps"]
    both = np.isfinite(ta) & np.isfinite(tb) & (a["status"] == 0) & (b["status"] == 0)
    rows = np.flatnonzero(both & (np.abs(np.where(both, ta - tb, 0.0)) > over))
    if rows.size == 0:
        return []
    ref = js.run_basin(b["ics"][rows], t_final=t_final, x64=True,
                       stepsize=js.StepSizeController(rtol=1e-10, atol=1e-10),
                       run=js.RunOptions(progress=False, audit=False)).T_eps
    return [{"row": int(i), "start": b["ics"][i].tolist(), "T_eps_baseline": float(ta[i]), "T_eps_new": float(tb[i]),
             "T_eps_float64_reference": float(r), "error_baseline_s": float(ta[i] - r), "error_new_s": float(tb[i] - r)}
            for i, r in zip(rows, np.asarray(ref))]


def radau_check(path: Path, k: int, t_final: float, eps: float = 0.05) -> list:
    """The ``k`` certified starts with the largest |theta0|, integrated by Radau in float64 to ``t_final``."""
    import jax
    from scipy.integrate import solve_ivp

    import jaxsleigh as js
    from jaxsleigh.model.closed_loop import ClosedLoop, vector_field

    d = np.load(path)
    st, ics = d["status"], d["ics"]
    idx = np.flatnonzero(st == 9)
    idx = idx[np.argsort(-np.abs(ics[idx, 2]))][:k]
    out = []
    with jax.enable_x64(True):
        args = ClosedLoop(js.paper_plant(), js.paper_gains())
        y, t = jax.numpy.zeros(5), jax.numpy.zeros(())
        fc = jax.jit(lambda t, y: vector_field(t, y, args)).lower(t, y).compile()
        jc = jax.jit(jax.jacfwd(lambda t, y: vector_field(t, y, args), argnums=1)).lower(t, y).compile()
        for i in idx:
            t0 = time.perf_counter()
            sol = solve_ivp(lambda t, y: np.asarray(fc(np.float64(t), y)), (0.0, t_final), np.r_[ics[i], 0.0, 0.0],
                            method="Radau", rtol=1e-8, atol=1e-8,
                            jac=lambda t, y: np.asarray(jc(np.float64(t), y)))
            qT = float(np.linalg.norm(sol.y[:3, -1]))
            out.append({"row": int(i), "start": ics[i].tolist(), "radau_status": int(sol.status),
                        "radau_t": float(sol.t[-1]), "radau_abs_q_T": qT, "outside_ball": bool(qT > eps),
                        "t_stopped": float(d["t_reached"][i]) if "t_reached" in d.files else None,
                        "nfev": int(sol.nfev), "wall_s": round(time.perf_counter() - t0, 1)})
            print(json.dumps(out[-1]), flush=True)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--t-final", type=float, default=100.0)
    ap.add_argument("--baseline", default="96855ab")
    ap.add_argument("--new", default="HEAD", help="commit of the new tree (default HEAD); 'working' for this folder")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--warmup", type=int, default=0, help="starts of the untimed warm-up basin (0: --n, the same command)")
    ap.add_argument("--radau", type=int, default=4, help="certified starts checked by Radau (0: none)")
    ap.add_argument("--out", default="docs/figures/basin_stragglers.json")
    a = ap.parse_args()
    trees = {"baseline": baseline_tree(a.baseline), "new": ROOT if a.new == "working" else baseline_tree(a.new)}
    work = Path(tempfile.mkdtemp(prefix="basin_stragglers_"))
    res = {"command": "python experiments/performance/basin_stragglers.py " + " ".join(sys.argv[1:]),
           "dtype": "float32", "machine": {"platform": platform.platform(), "processor": platform.processor(),
                                           "cores": os.cpu_count()},
           "baseline": a.baseline, "new": a.new,
           "new_commit": subprocess.run(["git", "-C", str(trees["new"]), "rev-parse", "--short", "HEAD"],
                                        capture_output=True, text=True).stdout.strip(),
           "workload": f"jaxsleigh basin --samples {a.n} --seed {a.seed} --t-final {a.t_final:g}",
           "load_start": load(), "warmup": {}, "runs": {"baseline": [], "new": []}}
    try:
        for name, tree in trees.items():          # compile and cache each tree's programs
            res["warmup"][name] = basin(tree, work / f"warm_{name}.npz", a.warmup or a.n, a.seed,
                                        a.t_final)["wall_s"]
        for r in range(a.repeats):
            for name, tree in trees.items():
                rec = basin(tree, work / f"{name}.npz", a.n, a.seed, a.t_final)
                res["runs"][name].append(rec)
                print(name, json.dumps({k: v for k, v in rec.items() if k != "stdout_tail"}), flush=True)
        walls = {k: [r["wall_s"] for r in v] for k, v in res["runs"].items()}
        res["throughput_ratio"] = [round(b / n, 3) for b, n in zip(walls["baseline"], walls["new"])]
        res["agreement"] = agreement(work / "baseline.npz", work / "new.npz")
        res["agreement"]["T_eps_over_1e-3_against_float64"] = reference_check(work / "baseline.npz",
                                                                             work / "new.npz", a.t_final)
        print(json.dumps(res["agreement"]), flush=True)
        if a.radau:
            res["certified"] = radau_check(work / "new.npz", a.radau, a.t_final)
        res["load_end"] = load()
    finally:
        for tree in trees.values():
            if tree != ROOT:
                subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)],
                               capture_output=True)
    out = ROOT / a.out
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1) + "\n")
    print("throughput ratio (baseline wall / new wall):", res["throughput_ratio"], "->", out)


if __name__ == "__main__":
    main()
