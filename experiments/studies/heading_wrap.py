"""Where the starts of a literature law that winds end, and what the heading modulo 2 pi changes: Aicardi et al.'s law.

    python experiments/studies/heading_wrap.py [--n 2048] [--out docs/figures/heading_wrap.json]

`jaxsleigh.controllers.aicardi.AicardiLaw` sees the heading only through angles wrapped into (-pi, pi], so it
steers theta to 0 modulo 2 pi. Its chart (`jaxsleigh.model.charts.PhysicalChart`, ``heading_modulo=True``) measures
|q| = |(x, y, theta)| with theta modulo 2 pi, so T_0.05 counts a start that reaches the goal with theta = +-2 pi
(the same physical pose) as settled. This script runs the law's defaults and the paper's gains on the README's
held-out starts (`experiments/studies/preset_effort.py`'s, 2048) over 100 s and reports the settled fraction as the engine
measures it, how many starts end at the goal (|x|, |y| <= 1e-6) with theta within 0.05 of a non-zero multiple of
2 pi, and the fraction that would settle with theta as integrated (a start settled modulo 2 pi that ends at
theta ~ 0: after T_0.05 it stays within 0.05 of one multiple of 2 pi, so both measures give the same T there).
float32, CPU; records machine and command.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(ROOT / "experiments"))
from common import machine  # noqa: E402  (experiments/common.py)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=2048)
    ap.add_argument("--out", default=str(ROOT / "docs/figures/heading_wrap.json"))
    args = ap.parse_args(argv)

    import jaxsleigh as js
    from jaxsleigh.controllers.aicardi import AicardiLaw
    from preset_effort import readme_starts

    ics = readme_starts(args.n)
    out = {"command": ["python", "experiments/studies/heading_wrap.py"] + list(argv if argv is not None else sys.argv[1:]),
           "dtype": "float32", "machine": machine(),
           "n": int(ics.shape[0]), "t_final": 100.0, "eps": 0.05, "laws": {}}
    for name, kw in (("paper", {"gains": js.paper_gains()}), ("aicardi", {"controller": AicardiLaw()})):
        r = js.run_ensemble(ics, t_final=100.0, eps=0.05, run=js.RunOptions(progress=False), **kw)
        settled = np.isfinite(r.T_eps) & (r.status == 0)
        q = r.q_final
        turns = np.round(q[:, 2] / (2 * np.pi))
        at_goal_turned = (np.max(np.abs(q[:, :2]), axis=1) <= 1e-6) & (turns != 0) \
            & (np.abs(q[:, 2] - 2 * np.pi * turns) <= 0.05)
        out["laws"][name] = {"settled_fraction": float(np.mean(settled)),
                             "settled_fraction_theta_as_integrated": float(np.mean(settled & (turns == 0))),
                             "median_T": float(np.median(np.where(settled, r.T_eps, np.inf))),
                             "failed": int(np.sum(r.status != 0)),
                             "at_goal_with_theta_2pi_multiple": int(at_goal_turned.sum()),
                             "turns": {str(int(k)): int(c) for k, c in zip(*np.unique(turns[at_goal_turned],
                                                                                       return_counts=True))}}
        print(name, out["laws"][name], flush=True)
    path = Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
