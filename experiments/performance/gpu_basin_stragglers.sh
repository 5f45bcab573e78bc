#!/usr/bin/env bash
# The default basin of 10^6 starts on one GPU: this tree against commit 96855ab (stragglers near theta = 0 run to
# their budget there; here those that cannot settle stop early, NOT_SETTLING), side by side on the same machine.
#
#     OUT=out/gpu_stragglers bash experiments/performance/gpu_basin_stragglers.sh
#
# The machine needs JAX with its GPU plugin (as for bench_accelerator.sh) but no network: the baseline's package is
# taken from BASE_TREE, a folder holding 96855ab's `jaxsleigh/`, made beforehand on a machine with the repository:
#
#     echo /.base96855ab/ >> .git/info/exclude
#     mkdir -p .base96855ab && git archive 96855ab jaxsleigh | tar -x -C .base96855ab
#
# (carry .base96855ab along). Where this folder is a git checkout and BASE_TREE is missing, it is made here.
# Writes to $OUT: device.txt, new.json / base.json (each run's wall time, status counts, steps), compare.json (the
# agreement of the two: statuses and T_eps of the starts that settle in both, the shares without an answer) and
# all.log. Each run is a fresh process, warmed by a basin of 10^4 starts (compilation) first, without the accuracy
# audit (this tree's float64 re-run of 64 rows, which 96855ab does not have); about 4-5 minutes in
# all on one H100 (a 10^6 basin took 54 s at 19a8d57), each step capped by `timeout` to fit in 6 minutes.
set -u
OUT=${OUT:-out/gpu_stragglers}
PY=${PYTHON:-python3}
N=${N:-1000000}
BASE_TREE=${BASE_TREE:-.base96855ab}
HERE=$PWD
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
LOG="$OUT/all.log"
touch "$LOG"
step() { echo "== $(date -u +%H:%M:%S) $*" | tee -a "$LOG"; }

if [ ! -d "$BASE_TREE/jaxsleigh" ] && git rev-parse --git-dir >/dev/null 2>&1; then
    mkdir -p "$BASE_TREE" && git archive 96855ab jaxsleigh | tar -x -C "$BASE_TREE"
fi
[ -d "$BASE_TREE/jaxsleigh" ] || { echo "no baseline tree in $BASE_TREE (see the header)" | tee -a "$LOG"; exit 2; }
BASE_TREE=$(cd "$BASE_TREE" && pwd)
mkdir -p "$OUT" && OUT=$(cd "$OUT" && pwd)
RUNDIR=$(mktemp -d)        # python -c puts its folder first on sys.path: run it where no jaxsleigh/ is

step device
{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv 2>&1
  $PY -c "import jax, jaxlib; print('jax', jax.__version__, 'jaxlib', jaxlib.__version__, jax.devices())"
  echo "host cores: $(nproc)"; uptime; } >"$OUT/device.txt" 2>&1
tee -a "$LOG" <"$OUT/device.txt"

# one basin in a fresh process of the tree $1: wall time, statuses, steps -> $OUT/$2.json (the arrays in /tmp)
RUN='
import json, sys, time
import numpy as np
import jaxsleigh as js
n, name, out = int(sys.argv[1]), sys.argv[2], sys.argv[3]
# the same work in both trees: the accuracy audit (float64 re-runs of 64 rows, this tree only) is left out
ro = js.RunOptions(progress=False, **({"audit": False} if "audit" in js.RunOptions._fields else {}))
js.run_basin(js.sample_starts(10000, seed=1), run=ro)          # compile
s = js.sample_starts(n, seed=0)
t0 = time.perf_counter()
r = js.run_basin(s, run=ro)
wall = time.perf_counter() - t0
np.savez(f"/tmp/{name}_basin.npz", status=r.status, T_eps=r.T_eps, n_steps=r.n_steps, n_rejected=r.n_rejected)
codes, counts = np.unique(r.status, return_counts=True)
rec = {"name": name, "n": n, "wall_s": wall, "starts_per_s": n / wall, "device": str(r.run_info["devices"]),
       "status_counts": {int(c): int(k) for c, k in zip(codes, counts)}, "fraction": float(r.fraction),
       "attempted_steps": int((r.n_steps + r.n_rejected).sum()), "max_steps": int((r.n_steps + r.n_rejected).max())}
json.dump(rec, open(out, "w"), indent=1)
print(json.dumps(rec))
'
step "this tree: basin of $N starts"
(cd "$RUNDIR" && PYTHONPATH="$HERE" timeout 170 $PY -c "$RUN" "$N" new "$OUT/new.json") 2>&1 | tail -n 5 | tee -a "$LOG"
step "96855ab: basin of $N starts"
(cd "$RUNDIR" && PYTHONPATH="$BASE_TREE" timeout 170 $PY -c "$RUN" "$N" base "$OUT/base.json") 2>&1 | tail -n 5 | tee -a "$LOG"

step compare
timeout 30 $PY - "$OUT" <<'EOF' 2>&1 | tee -a "$LOG"
import json, sys
import numpy as np
out = sys.argv[1]
a, b = np.load("/tmp/base_basin.npz"), np.load("/tmp/new_basin.npz")
sa, sb, ta, tb = a["status"], b["status"], a["T_eps"], b["T_eps"]
both = np.isfinite(ta) & (sa == 0) & np.isfinite(tb) & (sb == 0)
base, new = json.load(open(f"{out}/base.json")), json.load(open(f"{out}/new.json"))
rec = {"throughput_ratio": base["wall_s"] / new["wall_s"], "settled_both": int(both.sum()),
       "settled_base": int((np.isfinite(ta) & (sa == 0)).sum()), "settled_new": int((np.isfinite(tb) & (sb == 0)).sum()),
       "same_status_where_settled_in_both": bool(np.all(sa[both] == sb[both])),
       "max_T_eps_diff_s": float(np.abs(ta[both] - tb[both]).max()) if both.any() else None,
       "status4_base": int((sa == 4).sum()), "status4_new": int((sb == 4).sum())}
json.dump(rec, open(f"{out}/compare.json", "w"), indent=1)
print(json.dumps(rec))
EOF
