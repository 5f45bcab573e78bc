"""The settled oscillation's damping along real trajectories: where the guard acts, for which gains, at what frequency.

    python experiments/studies/pair_damping.py [--n 16] [--out docs/figures/pair_damping.json]

For the paper's gains, the presets ``balanced``, ``tuned`` and ``shaped``, and the 0.2 release's ``balanced`` gains
(``balanced_0.2``, whose settled phase oscillates), ``--n`` of the README's held-out starts
(`experiments/studies/preset_effort.py`) are integrated over 100 s in float64 at rtol = atol = 1e-9, saving every
50th base step. At every saved state within 4 eps = 0.2 of the target (the guard's ``NEAR``), the complex pair
sigma +- i omega of the Jacobian block on (w2, p1, p2) is computed as the guard computes it
(`jaxsleigh.integrate.guard.pair_damping`). Printed and written as JSON per law: the number of such states, the
share where the pair is weak (sigma > -0.75/s: the guard caps the step at 0.5/omega there), sigma's 10/50/90th
percentiles and largest value, and omega's 10/50/90th percentiles where the pair is weak. float64, CPU; records
machine and command.
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
from default_accuracy import BALANCED_02  # noqa: E402
from preset_effort import readme_starts  # noqa: E402

LAWS = ("paper", "balanced", "tuned", "shaped", "balanced_0.2")


def law_spec(name: str):
    """``(controller object for ClosedLoop, keywords for simulate)`` of a law of `LAWS`."""
    import jaxsleigh as js

    if name == "shaped":
        law = js.load_shaped("shaped")
        return law, {"controller": law}
    g = js.gains(**BALANCED_02) if name == "balanced_0.2" else js.load_gains(name)
    return g, {"gains": g}


def pair_along(name: str, ics: np.ndarray, eps: float = 0.05) -> dict:
    """The pair's figures on the saved states of ``ics`` under law ``name`` that lie within the guard's reach."""
    import jax
    import jax.numpy as jnp

    import jaxsleigh as js
    from jaxsleigh.integrate.guard import DAMPING, NEAR, pair_damping
    from jaxsleigh.model.charts import WChart

    law, kw = law_spec(name)
    s = js.simulate(ics, t_final=100.0, dt=0.01, saveat=js.SaveAt(every=50), x64=True,
                    stepsize=js.StepSizeController(rtol=1e-9, atol=1e-9), **kw)
    states = np.concatenate([np.asarray(s.q), np.asarray(s.p)], axis=2)          # (N, T, 5)
    states = states[np.all(np.isfinite(states), axis=2)]
    chart, args = WChart(), js.ClosedLoop(js.paper_plant(), law)
    with jax.enable_x64(True):
        w = jax.vmap(chart.to_chart, in_axes=1, out_axes=1)(jnp.asarray(states.T))
        sigma, omega2 = (np.asarray(a) for a in pair_damping(chart.field, 0.0, w, args))
        near = np.asarray(chart.q_norm2(w)) <= (NEAR * eps) ** 2
    sigma, omega2 = sigma[near], omega2[near]
    weak = (omega2 > 0) & (sigma > -DAMPING)
    omega = np.sqrt(omega2[weak])
    pct = lambda a: [float(v) for v in np.percentile(a, [10, 50, 90])] if a.size else None  # noqa: E731
    return {"states_near": int(near.sum()), "share_weak": float(weak.mean()) if weak.size else 0.0,
            "sigma_p10_p50_p90": pct(sigma), "sigma_max": float(sigma.max()) if sigma.size else None,
            "omega_weak_p10_p50_p90": pct(omega)}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=16, help="README starts per law (default 16)")
    ap.add_argument("--laws", default=",".join(LAWS))
    ap.add_argument("--out", default=str(ROOT / "docs" / "figures" / "pair_damping.json"))
    args = ap.parse_args(argv)
    out = {"command": "python experiments/studies/pair_damping.py" + "".join(f" {a}" for a in (argv or sys.argv[1:])),
           "dtype": "float64, rtol = atol = 1e-9, every 50th base step saved", "machine": machine(),
           "n": args.n, "laws": {}}
    ics = readme_starts(args.n)
    for name in args.laws.split(","):
        row = out["laws"][name] = pair_along(name, ics)
        print(f"{name:13s} near {row['states_near']:5d}  weak {100 * row['share_weak']:5.1f}%  sigma p10/50/90 "
              f"{row['sigma_p10_p50_p90']}  max {row['sigma_max']}  omega where weak {row['omega_weak_p10_p50_p90']}",
              flush=True)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
