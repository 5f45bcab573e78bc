"""Where the starts that a literature law "does not settle" end: Aicardi et al.'s law (issue 21, item 6).

    python experiments/heading_wrap.py [--n 2048] [--out docs/figures/heading_wrap.json]

`jaxsleigh.controllers.aicardi.AicardiLaw` sees the heading only through angles wrapped into (-pi, pi], so it
steers theta to 0 modulo 2 pi. The settling time T_0.05 (`jaxsleigh.integrate.observers.ConvergenceTime`) uses
|q| = |(x, y, theta)| with theta as integrated, so a start that reaches the goal with theta = +-2 pi (the same
physical heading) never settles by that measure. This script runs the law's defaults and the paper's gains on the
README's held-out starts (`experiments/preset_effort.py`'s, 2048) over 100 s and reports, for the starts that did
not settle, how many end within 1e-6 of the goal's position with theta within 0.05 of a non-zero multiple of 2 pi.
float32, CPU; records machine and command.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "experiments"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=2048)
    ap.add_argument("--out", default=str(ROOT / "docs/figures/heading_wrap.json"))
    args = ap.parse_args(argv)

    import jax
    import jaxsleigh as js
    from jaxsleigh.controllers.aicardi import AicardiLaw
    from preset_effort import readme_starts

    ics = readme_starts(args.n)
    out = {"command": ["python", "experiments/heading_wrap.py"] + list(argv if argv is not None else sys.argv[1:]),
           "dtype": "float32", "machine": {"arch": platform.machine(), "cpu_count": os.cpu_count(),
                                           "jax_backend": jax.default_backend(), "jax": jax.__version__},
           "n": int(ics.shape[0]), "t_final": 100.0, "eps": 0.05, "laws": {}}
    for name, kw in (("paper", {"gains": js.paper_gains()}), ("aicardi", {"controller": AicardiLaw()})):
        r = js.run_ensemble(ics, t_final=100.0, eps=0.05, progress=False, **kw)
        un = (r.status == 0) & ~np.isfinite(r.T_eps)
        q = r.q_final[un]
        turns = np.round(q[:, 2] / (2 * np.pi))
        at_goal_turned = (np.max(np.abs(q[:, :2]), axis=1) <= 1e-6) & (turns != 0) \
            & (np.abs(q[:, 2] - 2 * np.pi * turns) <= 0.05)
        out["laws"][name] = {"settled_fraction": float(np.mean(np.isfinite(r.T_eps))), "not_settled": int(un.sum()),
                             "failed": int(np.sum(r.status != 0)),
                             "not_settled_at_goal_with_theta_2pi_multiple": int(at_goal_turned.sum()),
                             "turns": {str(int(k)): int(c) for k, c in zip(*np.unique(turns[at_goal_turned],
                                                                                       return_counts=True))}}
        print(name, out["laws"][name], flush=True)
    path = Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
