r"""The settled-phase step adopted: steps and accuracy before and after, side by side.

    python experiments/studies/settled_phase_adopted.py [--baseline af0756c] [--also 72f4f8f] [--n 4096] [--n-fast 256]
                                                        [--out docs/figures/settled_phase_adopted.json]

Runs the default adaptive method (float32, 100 s, eps = 0.05) of this tree and of ``--baseline`` (a
``git worktree`` of the commit before the exponential step, classical RK4 with the I controller) on the
benchmark workload (`jaxsleigh.studies.bench.workload`, seed 0): ``--n`` starts under the paper's gains and
``--n-fast`` under the ``balanced`` and ``tuned`` presets (``balanced``: the gains it had until 2026-11,
``OLD_BALANCED`` of tests/laws.py, the same in every tree, as when these figures were measured; ``balanced_now``:
the present preset's gains, jaxsleigh/presets/balanced.json, also given to every tree as a gains file, so the
stepper is compared on the same gains). Each is compared with a float64 reference
computed by the *baseline* (classical RK4, rtol = atol = 1e-11, T_eps on the dense output with 8 samples and
30 bisections), so the reference does not share the new scheme. Reports the mean accepted steps and attempts,
the wrong final states (max-norm error > 1e-3, as ``jaxsleigh bench``), the final-state error quantiles and
the T_eps error quantiles (starts that settle in both), and the wall time. ``--also COMMIT`` measures that
commit too, in the same run and against the same reference (column ``also``; e.g. the exponential step on p2
alone, before the (w2, p1) oscillation was added to it).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import ROOT, baseline_tree, load, run_py  # noqa: E402
sys.path.insert(0, str(ROOT / "tests"))
from laws import OLD_BALANCED  # noqa: E402

RUN = r"""
import json, sys, time
import numpy as np, jaxsleigh as js
from jaxsleigh.studies.bench import workload
from jaxsleigh.integrate.observers import ClosestApproach, ControlEffort, ConvergenceTime, Excursion
gains, n, ref = sys.argv[1], int(sys.argv[2]), sys.argv[3] == "ref"
ics = workload(n, seed=0)
g = None if gains == "paper" else gains
kw = dict(x64=True, stepsize=js.StepSizeController(rtol=1e-11, atol=1e-11, max_steps=20_000_000),
          observers=(ConvergenceTime(samples=8, bisections=30), ClosestApproach(), Excursion(), ControlEffort())) \
    if ref else {}
quiet = js.RunOptions(progress=False)
js.run_ensemble(ics[:64], gains=g, run=quiet, **kw)
t0 = time.perf_counter()
r = js.run_ensemble(ics, gains=g, run=quiet, **kw)
w = time.perf_counter() - t0
print(json.dumps({"wall_s": w, "final": np.column_stack([r.q_final, r.p_final]).tolist(), "T_eps": r.T_eps.tolist(),
                  "n_steps": float(np.mean(r.n_steps)), "attempts": float(np.mean(r.n_steps + r.n_rejected)),
                  "status_not_ok": int(np.sum(r.status != 0))}))
"""


def compare(run: dict, ref: dict) -> dict:
    import numpy as np

    fin, fin_ref = np.array(run["final"]), np.array(ref["final"])
    err = np.max(np.abs(fin - fin_ref), axis=1)
    T, Tr = np.array(run["T_eps"], float), np.array(ref["T_eps"], float)
    both = np.isfinite(T) & np.isfinite(Tr)
    dT = np.abs(T - Tr)[both]
    return {"mean_steps": run["n_steps"], "mean_attempts": run["attempts"], "wall_s": run["wall_s"],
            "wrong": int(np.sum(~(err <= 1e-3))), "final_error_median": float(np.median(err)),
            "final_error_p99": float(np.quantile(err, 0.99)),
            "T_eps_error_median": float(np.median(dT)), "T_eps_error_p99": float(np.quantile(dT, 0.99)),
            "T_eps_error_max": float(dT.max()), "settled_mismatch": int(np.sum(np.isfinite(T) != np.isfinite(Tr))),
            "status_not_ok": run["status_not_ok"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--baseline", default="af0756c")
    ap.add_argument("--also", default=None, help="a commit measured in between (column 'also')")
    ap.add_argument("--n", type=int, default=4096)
    ap.add_argument("--n-fast", type=int, default=256)
    ap.add_argument("--out", default="docs/figures/settled_phase_adopted.json")
    a = ap.parse_args(argv)
    log = lambda *m: print(*m, file=sys.stderr, flush=True)  # noqa: E731
    base = baseline_tree(a.baseline)
    trees = [("before", base)]
    if a.also:
        trees.append(("also", baseline_tree(a.also)))
    trees.append(("after", ROOT))
    out = {"command": "python experiments/studies/settled_phase_adopted.py " + " ".join(sys.argv[1:] if argv is None else argv),
           "baseline": a.baseline, "also": a.also, "dtype": "float32", "t_final": 100.0, "load_before": load(),
           "gains": {}}
    files = Path(tempfile.mkdtemp())                                     # gains files every tree reads
    (files / "old_balanced.json").write_text(json.dumps(OLD_BALANCED))
    present = json.loads((ROOT / "jaxsleigh" / "presets" / "balanced.json").read_text())
    (files / "balanced_now.json").write_text(json.dumps({k: present[k] for k in ("L", "k", "D_hat")}))
    specs = {"balanced": str(files / "old_balanced.json"), "balanced_now": str(files / "balanced_now.json")}
    try:
        for gains, n in (("paper", a.n), ("balanced", a.n_fast), ("balanced_now", a.n_fast), ("tuned", a.n_fast)):
            spec = specs.get(gains, gains)
            ref = run_py(RUN, [spec, n, "ref"], env={"PYTHONPATH": str(base)})
            row = {}
            for name, tree in trees:
                row[name] = compare(run_py(RUN, [spec, n, "run"], env={"PYTHONPATH": str(tree)}), ref)
            row["steps_ratio"] = row["before"]["mean_steps"] / row["after"]["mean_steps"]
            if a.also:
                row["steps_ratio_also"] = row["also"]["mean_steps"] / row["after"]["mean_steps"]
            out["gains"][gains] = {"n": n, **row}
            log(f"{gains} ({n} starts): steps {row['before']['mean_steps']:.0f} -> {row['after']['mean_steps']:.0f} "
                f"({row['steps_ratio']:.2f}x fewer), wrong {row['before']['wrong']} -> {row['after']['wrong']}, "
                f"T_eps error max {row['before']['T_eps_error_max']:.1e} -> {row['after']['T_eps_error_max']:.1e} s")
    finally:
        for name, tree in trees[:-1]:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)], capture_output=True)
    out["load_after"] = load()
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(out, indent=1) + "\n")
    log(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
