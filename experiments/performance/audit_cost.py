r"""Where a validation's time goes: the run itself against its accuracy audit's float64 reference.

    python experiments/performance/audit_cost.py [--gains tuned] [--n 64] [--seed 4] [--out out/audit_cost.json]

`jaxsleigh.tuning.validate` runs ``n`` held-out starts (`jaxsleigh.tuning.UniformStarts`, ``seed``) over 100 s in
float32 and audits 16 of them: those rows again in float64 at rtol = atol = 1e-10 with a budget of 100 base steps
per base step (`jaxsleigh.studies.audit`). Every figure is warm (each call is made once before it is timed):

* ``validate_s``: the whole validation; ``run_s``: the same ensemble with ``audit=False``; ``audit_s``: the audit's
  own ``wall_s`` in that validation (its reference's seconds included, though they overlap the run's end);
* ``reference_s``: the 16 rows as a plain float64 ensemble at 1e-10 (whose compaction keeps every lane's bits, so
  its last straggler steps in a batch of 32; the audit's own reference gathers it down to one lane), with each
  row's status and attempts;
* ``rows``: for each audited row, its float32 steps and its reference's steps and status; a reference row that
  ends BUDGET_EXHAUSTED is not judged by the audit (``reference_unfinished``), however long it ran;
* ``hardest_alone_s``: the reference of the row with the most float32 steps, run as a batch of its own.

The settled phase of a law whose theta keeps shrinking after it settles grows stiffer without end (the damping
injection ``k / theta^2``). Before the flight rule scaled with the tolerance, the 1e-10 reference of such a row
(row 31 here) moved to the implicit step and used its whole budget by t = 58 s: the validation took 68.7 s and left
that row unjudged.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import machine  # noqa: E402


def timed(fn):
    fn()                                   # compile (and fill JAX's caches) first: every figure is warm
    t = time.perf_counter()
    out = fn()
    return time.perf_counter() - t, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--gains", default="tuned")
    ap.add_argument("--n", type=int, default=64)
    ap.add_argument("--seed", type=int, default=4)
    ap.add_argument("--out", default="out/audit_cost.json")
    a = ap.parse_args()
    info = machine()

    import jaxsleigh as js
    from jaxsleigh import tuning as tu
    from jaxsleigh.studies.audit import audit_sample

    gains = js.load_gains(a.gains)
    ics = tu.UniformStarts()(np.random.default_rng(a.seed), a.n)
    quiet = js.RunOptions(progress=False, audit=False)
    validate_s, v = timed(lambda: tu.validate(gains, ics))
    run_s, r = timed(lambda: js.run_ensemble(ics, gains=gains, t_final=100.0, run=quiet))
    rows = audit_sample(js.Audit(rows=min(16, a.n)), a.n)
    ref_kw = dict(gains=gains, t_final=100.0, x64=True, run=quiet,
                  stepsize=js.StepSizeController(rtol=1e-10, atol=1e-10, max_steps=100 * 10_000 + 1000))
    reference_s, ref = timed(lambda: js.run_ensemble(ics[rows], **ref_kw))
    hardest = int(rows[np.argmax(r.n_steps[rows])])
    alone_s, alone = timed(lambda: js.run_ensemble(ics[hardest:hardest + 1], **ref_kw))
    doc = {"command": " ".join(sys.argv), "machine": info, "dtype": "float32 (the run), float64 (the reference)",
           "gains": a.gains, "n": a.n, "seed": a.seed, "validate_s": round(validate_s, 2), "run_s": round(run_s, 2), "audit_s": v.audit["wall_s"],
           "reference_s": round(reference_s, 2), "hardest_row": hardest, "hardest_start": ics[hardest].tolist(),
           "hardest_alone_s": round(alone_s, 2), "hardest_alone_steps": int(alone.n_steps[0]),
           "audit": v.audit,
           "rows": [{"row": int(i), "float32_steps": int(r.n_steps[i]), "reference_steps": int(ref.n_steps[j]),
                     "reference_status": js.Status(int(ref.status[j])).name} for j, i in enumerate(rows)]}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(doc, indent=1, default=str) + "\n")
    print(json.dumps({k: doc[k] for k in ("validate_s", "run_s", "audit_s", "reference_s", "hardest_row", "hardest_alone_s",
                                          "hardest_alone_steps")}))
    print("unfinished reference rows:", [x for x in doc["rows"] if x["reference_status"] != "OK"])


if __name__ == "__main__":
    main()
