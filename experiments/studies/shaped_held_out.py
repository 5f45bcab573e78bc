"""Judge a family study's laws again on its held-out starts, at another tolerance (shaped and paper families).

    python experiments/studies/shaped_held_out.py [--study docs/figures/shaped_study.json] [--atol 1e-8]

`experiments/studies/shaped_study.py` tunes a law family by gradient and by CMA-ES (34 min on 2 cores) and
judges the best laws on 2048 held-out starts of two distributions at float32's default tolerance, which does not
resolve the energy spent after settling (docs/evidence/settled-phase.md). This script takes the laws from the
study's JSON (no tuning), runs the same judgement (`preset_effort.py`'s figures: paper's gains, the start law,
the gradient's and CMA-ES's best) with ``StepSizeController(atol=--atol)`` and writes it into the same JSON as
``held_out_atol`` (``{"atol": A, "command": ..., "readme": ..., "wide": ...}``). float32, CPU.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--study", default=str(ROOT / "docs/figures/shaped_study.json"))
    ap.add_argument("--atol", type=float, default=1e-8)
    a = ap.parse_args(argv)

    import jaxsleigh as js
    from jaxsleigh.model.params import gains, paper_gains
    from jaxsleigh.model.shaped_law import ShapedGains, shaped_from_gains, shaped_gains
    from shaped_study import judge

    path = Path(a.study)
    study = json.loads(path.read_text())
    family = study.get("family", "shaped")         # the first shaped study predates the field
    if family not in ("shaped", "paper"):
        ap.error(f"--study: a {family!r} study; this script judges the shaped and paper families")
    laws = {"paper": {"gains": paper_gains()}}
    if family == "shaped":                          # the study's start law (the paper's family starts at the paper)
        laws["start"] = {"controller": shaped_from_gains(paper_gains(), B=(1e-3, 1e-3, 1e-3))}
    for key in ("gradient", "cma"):
        law = (study.get(key) or {}).get("law")
        if law is None:
            continue
        laws[key] = ({"controller": shaped_gains(**{k: law[k] for k in ShapedGains._fields})} if family == "shaped"
                     else {"gains": gains(**law)})
    out = {"atol": a.atol, "command": ["python", "experiments/studies/shaped_held_out.py", *(sys.argv[1:] if argv is None
                                                                                    else argv)],
           **judge(laws, stepsize=js.StepSizeController(atol=a.atol))}
    study["held_out_atol"] = out
    path.write_text(json.dumps(study, indent=1, default=float) + "\n")
    print(f"wrote {path} (held_out_atol)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
