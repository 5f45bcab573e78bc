r"""What a 3x3 exponential block on (w2, p1, p2) would cost per step, against the step it would replace.

    python experiments/performance/block3_cost.py [--n 4096] [--repeats 5] [--out docs/figures/block3_cost.json]

The previous `balanced` gains' next limit after the adopted exponential step is the coupling of w2 and p2
(docs/evidence/settled-phase.md); an exponential step that took it would need, per lane and step, functions of a 3x3
matrix M = h J: e^M and phi1, phi2, phi3 of M (Cox & Matthews' coefficients), at h and h / 2. One core
(``JAXSLEIGH_CORES=1``), float32, a batch of ``--n`` random 3x3 matrices (normal, scale 0.5, seed 0). It times, per
lane, in CPU time, median of ``--repeats``:

- ``expm_3x3``: ``jax.scipy.linalg.expm`` of the 3x3 matrices (e^M alone);
- ``expm_12x12``: ``expm`` of the augmented 12x12 matrix [[M, I, 0, 0], [0, 0, I, 0], [0, 0, 0, I], [0, 0, 0, 0]],
  whose first block row is (e^M, phi1(M), phi2(M), phi3(M)) (Al-Mohy & Higham's construction);
- ``library_step``: the library's whole adaptive step today (`run_ensemble`, default method, summaries on), on the
  benchmark workload of the same size over 100 s: CPU time / (lanes x mean attempted steps).

The JSON records the machine, jax version, load average and command.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import load  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=4096)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default="docs/figures/block3_cost.json")
    a = ap.parse_args(argv)
    os.environ["JAXSLEIGH_CORES"] = "1"
    import jax
    import jax.numpy as jnp
    import numpy as np

    import jaxsleigh
    from jaxsleigh.studies.bench import machine, workload

    def augmented(m):
        n, eye = m.shape[0], jnp.broadcast_to(jnp.eye(3, dtype=m.dtype), m.shape)
        z = jnp.zeros((n, 12, 12), m.dtype).at[:, :3, :3].set(m)
        return z.at[:, :3, 3:6].set(eye).at[:, 3:6, 6:9].set(eye).at[:, 6:9, 9:12].set(eye)

    expm = jax.vmap(jax.scipy.linalg.expm)
    programs = {"expm_3x3": jax.jit(expm), "expm_12x12": jax.jit(lambda m: expm(augmented(m)))}
    m = jnp.asarray(np.random.default_rng(0).normal(size=(a.n, 3, 3)) * 0.5, jnp.float32)
    rows = {}
    for name, f in programs.items():
        jax.block_until_ready(f(m))
        ts = []
        for r in range(a.repeats):
            x = m * (1.0 + 0.01 * r)
            t = time.process_time()
            jax.block_until_ready(f(x))
            ts.append(time.process_time() - t)
        rows[name] = {"us_per_lane": float(np.median(ts)) / a.n * 1e6, "cpu_s": ts}
    ics = workload(a.n, 0)
    jaxsleigh.run_ensemble(ics, t_final=100.0, run=jaxsleigh.RunOptions(progress=False))
    ts, attempts = [], None
    for r in range(a.repeats):
        t = time.process_time()
        res = jaxsleigh.run_ensemble(ics, t_final=100.0, run=jaxsleigh.RunOptions(progress=False))
        ts.append(time.process_time() - t)
        attempts = float(np.mean(res.n_steps + res.n_rejected))
    rows["library_step"] = {"us_per_lane": float(np.median(ts)) / (a.n * attempts) * 1e6, "cpu_s": ts,
                            "mean_attempts": attempts}
    for name, row in rows.items():
        ratio = row["us_per_lane"] / rows["library_step"]["us_per_lane"]
        row["of_library_step"] = ratio
        print(f"{name:13s} {row['us_per_lane']:8.3f} us per lane  ({ratio:.2f} x the library's whole step)")
    out = {"command": "python experiments/performance/block3_cost.py " + " ".join(sys.argv[1:] if argv is None else argv),
           "machine": machine(), "load_average": load(), "dtype": "float32",
           "cores": 1, "n": a.n, "repeats": a.repeats, "rows": rows}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {a.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
