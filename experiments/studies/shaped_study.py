"""A law family tuned by gradient and by CMA-ES on the same objective: the shaped-energy family, the
paper's own 7 gains, or a literature law.

    python experiments/studies/shaped_study.py [--family shaped|paper|aicardi] [--n 1024] [--steps 40] [--cma-factor 3]
                                               [--multiplier-every 0] [--out docs/figures/<family>_study.json]
                                               [--write-preset]

Objective (`jaxsleigh.tuning.hard_time`): median + 0.5 x 90th percentile of the hard settling time T_0.05 over
100 s, with budgets of the paper's gains' control energy at the 25th, 50th, 75th and 90th percentiles on the
same starts, and no fewer starts settled. Training starts: ``--n`` starts, half `UniformStarts` (seed 11), half
`WideStarts` (seed 12). Families (``--family``, coordinates of `jaxsleigh.tuning.law.law_coordinates`):

* ``shaped``: `jaxsleigh.ShapedGains`, 15 positive parameters in logarithm, started from the paper's gains with a
  negligible pseudo-Huber part (B = 0.001, C = 1, s = 1); ``--write-preset`` writes the preset ``shaped``;
* ``paper``: the paper's `jaxsleigh.Gains` in their 7 admissible coordinates, started from the paper's gains;
* ``aicardi``: `jaxsleigh.controllers.aicardi.AicardiLaw`'s 4 positive gains in logarithm, from its defaults
  (its plant model is not tuned).

* gradient: Adam (lr 0.05, momentum b1 = 0.5) on the implicit-function derivative (`jaxsleigh.tuning.event_time`), ``--steps``
  evaluations; with ``--multiplier-every m`` the budgets' multipliers are updated every m evaluations (the method of
  multipliers of `jaxsleigh.tuning.hard_time`), else the penalty alone;
* CMA-ES (`jaxsleigh.tuning.cmaes`, population 12, sigma0 0.3): ``--cma-factor`` x as many evaluations; its best
  within the gradient's budget is reported too.

Each evaluation simulates every training start over the horizon (the budget in trajectory-seconds). The best
feasible law of each is then judged by ``experiments/studies/preset_effort.py``'s figures on 2048 held-out starts of two
distributions. The JSON is rewritten after every evaluation (an interrupted run keeps what it did). float32,
CPU; records machine and command.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))        # preset_effort
sys.path.insert(0, str(ROOT / "experiments"))
from common import machine  # noqa: E402  (experiments/common.py)


def host(law):
    """The law with its array leaves as float64 NumPy arrays (what run_ensemble takes from a user)."""
    import jax

    return jax.tree_util.tree_map(lambda a: np.asarray(a, np.float64), law)


def law_dict(law) -> dict:
    """``{leaf name: value}`` of a law's numeric leaves (JSON-ready)."""
    from jaxsleigh.model.controller import law_leaf_names

    return {k: np.asarray(v, np.float64).tolist() for k, v in law_leaf_names(host(law)).items()}


def judge(laws: dict, **engine) -> dict:
    """``{"readme": ..., "wide": ...}``: `preset_effort.py`'s figures of each law (``{name: run_ensemble keywords}``,
    one of them ``"paper"``) on 2048 held-out starts of each distribution over 100 s, energy also as a ratio to the
    paper's at each percentile; ``engine``: more `run_ensemble` keywords (e.g. ``stepsize``)."""
    import jaxsleigh as js
    from preset_effort import figures, readme_starts, wide_starts

    held = {}
    for dist, draw in (("readme", readme_starts), ("wide", wide_starts)):
        ics = draw(2048)
        res = {name: figures(js.run_ensemble(ics, t_final=100.0, eps=0.05, run=js.RunOptions(progress=False), **kw,
                                             **engine))
               for name, kw in laws.items()}
        for name in res:
            res[name]["energy_ratio_to_paper"] = {q: res[name]["energy"][q] / res["paper"]["energy"][q]
                                                  for q in res[name]["energy"]}
        held[dist] = res
        print(dist, {k: (v["T_median"], v["energy_ratio_to_paper"]) for k, v in res.items()}, flush=True)
    return held


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--family", choices=("shaped", "paper", "aicardi"), default="shaped")
    ap.add_argument("--n", type=int, default=1024)
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--cma-factor", type=int, default=3)
    ap.add_argument("--out", default=None, help="default docs/figures/<family>_study.json")
    ap.add_argument("--multiplier-every", type=int, default=0)
    ap.add_argument("--write-preset", action="store_true")
    args = ap.parse_args(argv)
    if args.write_preset and args.family != "shaped":
        ap.error("--write-preset writes the shaped preset: use it with --family shaped")
    args.out = args.out or str(ROOT / f"docs/figures/{args.family}_study.json")

    from jaxsleigh.model.params import paper_gains
    from jaxsleigh.model.shaped_law import shaped_from_gains
    from jaxsleigh.tuning.hard_time import HardTimeConfig, hard_time_problem, tune_by_cma, tune_by_gradient
    from jaxsleigh.tuning.law import law_coordinates
    from jaxsleigh.tuning.starts import UniformStarts, WideStarts

    half = args.n // 2
    uni = UniformStarts()(np.random.default_rng(11), half)
    starts = np.concatenate([np.column_stack([uni, np.zeros((half, 2))]),
                             WideStarts()(np.random.default_rng(12), args.n - half)])
    if args.family == "shaped":
        law0 = shaped_from_gains(paper_gains(), B=(1e-3, 1e-3, 1e-3))
    elif args.family == "paper":
        law0 = paper_gains()
    else:
        from jaxsleigh.controllers.registry import make_controller
        law0 = make_controller(args.family)
    coords = law_coordinates(law0)
    cfg = HardTimeConfig(energy_margin=1.0)
    out = {"command": ["python", "experiments/studies/shaped_study.py"] + list(argv if argv is not None else sys.argv[1:]),
           "dtype": "float32", "machine": machine(),
           "family": args.family, "config": {**cfg._asdict(), "stepsize": cfg.stepsize._asdict()}, "n_train": args.n,
           "multiplier_every": args.multiplier_every,
           "coordinates": list(coords.names), "x0": coords.x0.tolist()}
    path = Path(args.out)

    def save():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(out, indent=1, default=float) + "\n")

    t0 = time.perf_counter()
    prob = hard_time_problem(law0, starts, cfg=cfg)
    out["budgets"] = prob.budgets.tolist()
    out["settled_floor"] = prob.settled_floor
    out["setup_wall_s"] = time.perf_counter() - t0
    save()

    def logger(key):
        def log(i, row):
            out.setdefault(key, {"history": []})["history"].append(row)
            if i % 5 == 0:
                print(f"{key} {i}: f={row['value']:.4f} feasible={row['feasible']} T={np.round(row['T_quantiles'], 2)} "
                      f"E={np.round(row['energy_quantiles'], 2)} wall={row['wall_s']:.0f}s", flush=True)
                save()
        return log

    runs = {}
    runs["gradient"] = tune_by_gradient(prob, steps=args.steps, multiplier_every=args.multiplier_every,
                                        progress=logger("gradient"))
    n_cma = args.cma_factor * args.steps
    runs["cma"] = tune_by_cma(prob, evaluations=n_cma, progress=logger("cma"))
    # CMA-ES's best within the gradient's budget (the first --steps evaluations)
    hist = out["cma"]["history"]
    within = [(r["value"], i) for i, r in enumerate(hist[:args.steps]) if r["feasible"]]
    out["cma"]["best_within_gradient_budget"] = min(within)[0] if within else None
    for key, run in runs.items():
        out[key].update(best_value=run.value, best_figures=run.figures,
                        x=None if run.x is None else np.asarray(run.x).tolist(),
                        law=None if run.x is None else law_dict(prob.law_of(run.x)),
                        trajectory_seconds=out[key]["history"][-1]["trajectory_seconds"],
                        wall_s=out[key]["history"][-1]["wall_s"])
    save()

    # held-out judgement
    laws = {"paper": {"gains": paper_gains()}}
    if args.family != "paper":
        laws["start"] = {"controller": law0}
    for key, run in runs.items():
        if run.x is not None:
            laws[key] = {"controller": host(prob.law_of(run.x))}
    out["held_out"] = judge(laws)
    save()
    if args.write_preset:
        cands = [k for k in runs if out[k]["law"] is not None]
        best = min(cands, key=lambda k: out[k]["best_value"])
        d = dict(out[best]["law"])
        d["meta"] = {"how": f"experiments/studies/shaped_study.py ({best})", "command": out["command"],
                     "held_out": {dist: out["held_out"][dist][best] for dist in out["held_out"]}}
        p = ROOT / "jaxsleigh/presets/controllers/shaped.json"
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(json.dumps(d, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
