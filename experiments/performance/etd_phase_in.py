r"""From which frequency on the exponential step should integrate the settled oscillation: steps against accuracy.

    python experiments/performance/etd_phase_in.py [--samples 20000] [--freqs 20,10,5] [--law paper]
                                                   [--out docs/figures/etd_phase_in.json]

The exponential RK4 step (`jaxsleigh.integrate.etd`) integrates the \((w_2, p_1)\) oscillation exactly where its
frequency is at least ``OSCILLATION_PHASE_IN`` (20 rad/s, the default); below, classical RK4 steps the pair and its
accuracy caps the step (about 0.1 s in the settled phase of the default basin). For each frequency the default
basin (``jaxsleigh basin --samples N --seed 5 --t-final 100``: `sample_starts`, paper gains, float32, adaptive)
(or ``--law``: the ``tuned`` or ``balanced`` gains, or the ``shaped`` law's preset) runs in a fresh process with the
constant set there (no persistent compilation cache, so the programs are traced
with it): the attempted steps, the wall time (compilation included, so compare the steps), the statuses, and,
against the default frequency's run, the largest change of ``T_eps`` and of the control energy on the starts that
settle in both; with the accuracy audit of 64 rows against float64 at rtol = atol = 1e-10 (worst ``T_eps`` and
energy errors).
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import ROOT, load, machine, run_py  # noqa: E402

RUN = r"""
import json, sys, tempfile, time
import numpy as np
import jaxsleigh.integrate.etd as etd
etd.OSCILLATION_PHASE_IN = float(sys.argv[1])
import jaxsleigh as js
starts = js.sample_starts(int(sys.argv[2]), seed=5)
law = sys.argv[4]
kw = {} if law == "paper" else {"controller": js.ShapedGains.preset()} if law == "shaped" else {"gains": law}
t0 = time.perf_counter()
r = js.run_basin(starts, t_final=100.0, eps=0.05, run=js.RunOptions(progress=False), **kw)
wall = time.perf_counter() - t0
out = sys.argv[3]
np.savez(out, T_eps=r.T_eps, u_energy=r.u_energy, status=r.status)
a = r.run_info["audit"]
print(json.dumps({"wall_s": round(wall, 2), "attempted_steps": int((r.n_steps + r.n_rejected).sum()),
                  "status_counts": {str(k): int(v) for k, v in zip(*np.unique(r.status, return_counts=True))},
                  "settled": int(np.isfinite(r.T_eps).sum()),
                  "audit": {k: a.get(k) for k in ("passed", "worst_T_eps_s", "worst_energy_rel", "status_mismatch")}}))
"""


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--samples", type=int, default=20000)
    ap.add_argument("--freqs", default="20,10,5", help="phase-in frequencies [rad/s]; the first is the reference")
    ap.add_argument("--law", choices=("paper", "tuned", "balanced", "shaped"), default="paper")
    ap.add_argument("--out", type=Path, default=None, help="default docs/figures/etd_phase_in[_LAW].json")
    a = ap.parse_args()
    freqs = [float(f) for f in a.freqs.split(",")]
    a.out = a.out or ROOT / "docs/figures" / ("etd_phase_in.json" if a.law == "paper" else f"etd_phase_in_{a.law}.json")
    record = {"command": "python experiments/performance/etd_phase_in.py " + " ".join(sys.argv[1:]),
              "dtype": "float32", "machine": machine(), "law": a.law, "samples": a.samples, "load_start": load(),
              "runs": []}
    ref = None
    with tempfile.TemporaryDirectory() as tmp:
        for f in freqs:
            path = Path(tmp) / f"phase_in_{f:g}.npz"
            row = {"phase_in_rad_s": f,
                   **run_py(RUN, [f, a.samples, path, a.law], env={"JAXSLEIGH_NO_COMPILE_CACHE": "1"})}
            d = np.load(path)
            if ref is None:
                ref = d
            both = np.isfinite(ref["T_eps"]) & np.isfinite(d["T_eps"])
            row["vs_first"] = {
                "settled_both": int(both.sum()),
                "same_status": bool(np.array_equal(ref["status"], d["status"])),
                "max_T_eps_change_s": float(np.abs(ref["T_eps"][both] - d["T_eps"][both]).max(initial=0.0)),
                "max_energy_change_rel": float(np.abs(d["u_energy"][both] / ref["u_energy"][both] - 1)
                                               .max(initial=0.0)),
                "steps_ratio": None}
            record["runs"].append(row)
            print(json.dumps(row), flush=True)
    first = record["runs"][0]["attempted_steps"]
    for row in record["runs"]:
        row["vs_first"]["steps_ratio"] = round(row["attempted_steps"] / first, 4)
    record["load_end"] = load()
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(record, indent=1) + "\n")
    print("wrote", a.out)


if __name__ == "__main__":
    main()
