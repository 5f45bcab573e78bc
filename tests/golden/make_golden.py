"""Golden outputs: a handful of runs whose numbers must not change when the code is reorganised.

``python tests/golden/make_golden.py`` writes ``tests/data/golden.npz`` (small: a few hundred
numbers per run). ``tests/test_golden.py`` reruns the same calls and compares every array: integer
fields (status, step counts) exactly, floating-point fields to within a few ulps of float64 or float32.
Regenerate only for a documented change of arithmetic, and say so in the commit.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).parent
sys.path.insert(0, str(HERE.parent))
from laws import OLD_BALANCED  # noqa: E402


def _flat(prefix: str, obj) -> dict:
    out = {}
    if isinstance(obj, dict):
        for k, v in obj.items():
            out.update(_flat(f"{prefix}.{k}", v))
    elif obj is not None and not isinstance(obj, (str, list)):
        a = np.asarray(obj)
        if a.dtype != object:
            out[prefix] = a
    return out


def golden_runs() -> dict:
    """name -> {field: array} of every golden run (each one cheap: CI runs them all)."""
    import jaxsleigh as js

    runs = {}
    ics = np.array([[-3.0, -2.0, np.pi / 8, 0.0, 0.0], [1.0, 1.0, 0.5, 0.0, 0.0], [2.0, -1.0, -1.0, 0.3, -0.2]])
    for x64 in (False, True):
        sol = js.simulate(ics, t_final=20.0, dt=0.01, x64=x64, saveat=js.SaveAt(every=100))
        tag = "f64" if x64 else "f32"
        runs[f"simulate_{tag}"] = {"t": sol.t, "q": sol.q, "p": sol.p, "u": sol.u, "Hd": sol.Hd,
                                   "status": sol.status, "n_steps": sol.n_steps, "n_rejected": sol.n_rejected,
                                   **_flat("effort", sol.effort)}
    starts = np.random.default_rng(7).uniform([-3, -3, 0.3], [3, 3, 3], (48, 3))
    # the gains the "balanced" preset had when this was recorded (it was re-derived in 2026-11)
    res = js.run_ensemble(starts, t_final=30.0, gains=js.gains(**OLD_BALANCED))
    # the golden file's keys are the 0.2 names: "q" / "p" there are the final state (now q_final / p_final)
    runs["ensemble"] = {"q": res.q_final, "p": res.p_final}
    runs["ensemble"].update({k: getattr(res, k) for k in ("T_eps", "min_abs_theta", "max_excursion", "Hd0",
                                                      "Hd_final", "t_reached", "n_steps", "n_rejected", "status",
                                                      "u_peak", "u_norm_peak", "u_energy", "u_abs_int")})
    fast = js.run_ensemble(starts, t_final=30.0, stepsize=js.StepSizeController(method="rk4", check_passivity=False),
                           saveat=js.SaveAt(summaries=False))
    runs["ensemble_plain"] = {"q": fast.q_final, "p": fast.p_final, "status": fast.status, "Hd_final": fast.Hd_final}
    basin = js.run_basin(js.grid_starts(x=(-2, 2, 4), y=(-2, 2, 3), theta=0.5), t_final=20.0)
    runs["basin"] = {k: v for k, v in basin._asdict().items()
                     if isinstance(v, np.ndarray) and v.dtype != object}
    sw = js.sweep(starts[:8], ["k=0.05:0.2:2"], t_final=20.0)
    runs["sweep"] = {k: v for k, v in sw._asdict().items()
                     if isinstance(v, np.ndarray) and v.dtype != object and k not in sw.effort}
    runs["sweep"].update(_flat("effort", sw.effort))
    runs.update(golden_tune())
    return runs


def golden_tune() -> dict:
    """A short gradient tuning run (3 iterations on 8 starts, 10 s horizon, eps = 0.5): its gains and history."""
    from jaxsleigh.tuning import LossConfig, TuneConfig, tune

    res = tune("paper", config=TuneConfig(steps=3, batch=8, seed=3, probe=0, verify=0, lr=0.1),
               loss=LossConfig(t_final=10.0, guard_t_final=2.0, eps=0.5), guard=np.zeros((0, 3)), progress=False)
    h = res.history
    return {"tune": {"L": np.asarray(res.gains.L), "k": np.asarray(res.gains.k), "D_hat": np.asarray(res.gains.D_hat),
                     "loss": np.asarray(h.loss), "grad_norm": np.asarray(h.grad_norm),
                     "energy": np.asarray(h.energy)}}


def main() -> int:
    if "--tune-only" in sys.argv:              # add the tuning run to an existing golden file
        old = dict(np.load(HERE.parent / "data" / "golden.npz"))
        runs = golden_tune()
        arrays = {**old, **{f"{run}/{field}": np.asarray(v) for run, fields in runs.items()
                            for field, v in fields.items()}}
        np.savez_compressed(HERE.parent / "data" / "golden.npz", **arrays)
        print(f"added {sorted(runs)} to the golden file")
        return 0
    runs = golden_runs()
    arrays = {f"{run}/{field}": np.asarray(v) for run, fields in runs.items() for field, v in fields.items()}
    np.savez_compressed(HERE.parent / "data" / "golden.npz", **arrays)
    print(f"wrote {HERE.parent / 'data' / 'golden.npz'}: {len(arrays)} arrays from {len(runs)} runs")
    return 0


if __name__ == "__main__":
    sys.exit(main())
