r"""jaxsleigh's throughput and peak memory against the number of starts N and the horizon.

    python experiments/performance/bench_scaling.py [--sizes 1000,10000,100000,1000000] [--t-final 100] [--dt 0.01]
                                                    [--horizons 10,30,100] [--horizon-n 4096] [--modes rk4,plain,adaptive]
                                                    [--chunk-size 65536] [--x64] [--rk4-check] [--warmup chunk|full|none]
                                                    [--timeout S] [--out out/bench_scaling.json]

Three modes on the measured workload (:func:`jaxsleigh.studies.bench.workload`), all through
:func:`jaxsleigh.run_ensemble` with its default ``chunk_size`` (65536 on CPU, 2^22 on an accelerator) and ``segment``:

``rk4``       fixed-step RK4 at ``--dt`` through the stepper, with its on-line summaries (T_eps,
              excursion, ...; ``check_passivity=False`` unless ``--rk4-check``);
``plain``     the plain fixed-step path (``summaries=False``: final state only, no per-step checks;
              on a GPU one kernel, `jaxsleigh.integrate.gpu_plain`): the throughput figure;
``adaptive``  ``run_ensemble``'s default (adaptive, passivity-checked, all on-line summaries:
              T_eps, min |theta|, max excursion, H_d(0), H_d(T), steps, status), final states and
              summaries only.

Sweeps: N over ``--sizes`` at ``--t-final``; the horizon over ``--horizons`` (default: 0.1, 0.3 and 1
times ``--t-final``, i.e. 10, 30, 100 s) at N = ``--horizon-n``. Every (mode, N, horizon) runs in a
fresh Python subprocess, so its peak RSS (``ru_maxrss``) is its own. In the subprocess the compile
is kept out of the timing: a warm-up run on the first ``min(N, chunk_size)`` starts (``--warmup chunk``:
the same chunk shape; ``full``: all N starts; ``none``), then the timed run; XLA compile time that still
falls inside the timed run (new compaction buckets) is measured with ``jax.monitoring`` and reported
(``compile_in_timed_s``; ``wall_s`` includes it, ``wall_net_s`` does not).

The target "10^6 initial conditions over 10^4 steps with summaries only: peak memory under 2 GB" is
the ``adaptive`` run at N = 1000000, t_final = 100, dt = 0.01 (the default sweep includes it); the
table states whether it was measured and passed (2 GB = 2e9 bytes = 1907 MiB).
Rough duration of the default sweep on 2 CPU cores: an hour or more (N = 10^6 at 10^4 steps dominates).
Progress goes to stderr; the table to stdout; everything to ``--out`` as JSON.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

TARGET_BYTES = 2e9
TARGET_MIB = TARGET_BYTES / 2 ** 20


def log(*a):
    print(*a, file=sys.stderr, flush=True)


def current_rss_mb():
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return None


# ---------------------------------------------------------------------------------------------------
# worker: one (mode, N, horizon) in this process

def worker(spec: dict) -> dict:
    import jax
    import numpy as np

    compile_s = {"total": 0.0}

    def listener(name, dur, **kw):
        if name.endswith("backend_compile_duration") or name.endswith("jaxpr_to_mlir_module_duration") \
                or name.endswith("jaxpr_trace_duration"):
            compile_s["total"] += dur

    jax.monitoring.register_event_duration_secs_listener(listener)
    from jaxsleigh.studies.bench import machine, peak_rss_mb, workload
    from jaxsleigh import RunOptions, SaveAt, StepSizeController
    from jaxsleigh.studies.ensemble import run_ensemble
    from jaxsleigh.status import Status

    rss_import = current_rss_mb()
    n, mode = spec["n"], spec["mode"]
    ics = workload(n, spec["seed"])
    kw = dict(t_final=spec["t_final"], dt=spec["dt"], x64=spec["x64"],
              run=RunOptions(chunk_size=spec["chunk_size"], progress=False))
    if mode == "rk4":
        kw.update(stepsize=StepSizeController(method="rk4", check_passivity=spec["rk4_check"]))
    elif mode == "plain":
        kw.update(stepsize=StepSizeController(method="rk4", check_passivity=False), saveat=SaveAt(summaries=False))
    elif mode != "adaptive":
        raise ValueError(f"unknown mode {mode!r}")
    from jaxsleigh.cores import default_chunk_size

    chunk = spec["chunk_size"] or default_chunk_size()
    warm_n = {"chunk": min(n, chunk), "full": n, "none": 0}[spec["warmup"]]
    t0 = time.perf_counter()
    if warm_n:
        run_ensemble(ics[:warm_n], **kw)
    warm_s = time.perf_counter() - t0
    warm_compile = compile_s["total"]
    rss_before = current_rss_mb()
    compile_s["total"] = 0.0
    t0 = time.perf_counter()
    r = run_ensemble(ics, **kw)
    wall = time.perf_counter() - t0
    in_timed = compile_s["total"]
    steps = int(round(spec["t_final"] / spec["dt"]))
    status = np.asarray(r.status)
    counts = {Status(int(s)).name: int(c) for s, c in zip(*np.unique(status, return_counts=True))}
    out = dict(spec)
    out.update({
        "steps": steps, "wall_s": wall, "compile_in_timed_s": in_timed, "wall_net_s": max(wall - in_timed, 1e-12),
        "traj_steps_per_s": n * steps / wall, "traj_steps_per_s_net": n * steps / max(wall - in_timed, 1e-12),
        "warmup_n": warm_n, "warmup_s": warm_s, "warmup_compile_s": warm_compile,
        "mean_steps": float(np.mean(r.n_steps)), "max_steps_taken": int(np.max(r.n_steps)),
        "mean_rejected": float(np.mean(r.n_rejected)),
        "not_ok": int(np.sum(status != Status.OK)), "status_counts": counts,
        "converged": int(np.sum(r.converged)) if mode == "adaptive" else None,
        "dtype": r.settings["dtype"], "chunk_size_effective": r.settings["chunk_size"],
        "rss_after_import_mb": rss_import, "rss_before_timed_mb": rss_before, "peak_rss_mb": peak_rss_mb(),
        "machine": machine(),
    })
    return out


def run_worker(spec: dict, timeout) -> dict:
    cmd = [sys.executable, os.path.abspath(__file__), "--worker", json.dumps(spec)]
    log(f"  {spec['mode']:8s} N = {spec['n']:>8d}  t_final = {spec['t_final']:g} ...")
    t0 = time.perf_counter()
    try:
        p = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=None, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        log(f"    timed out after {timeout} s")
        return dict(spec, error=f"timed out after {timeout} s")
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("{")]
    if p.returncode != 0 or not lines:
        log(f"    failed (exit {p.returncode})")
        return dict(spec, error=f"worker exited {p.returncode}")
    res = json.loads(lines[-1])
    log(f"    wall {res['wall_s']:.2f} s, {res['traj_steps_per_s']:.3g} traj-steps/s, peak RSS "
        f"{res['peak_rss_mb']:.0f} MiB (subprocess total {time.perf_counter() - t0:.1f} s)")
    return res


# ---------------------------------------------------------------------------------------------------

def fmt(x, spec=".3g"):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return format(x, spec)


def table(rows) -> str:
    lines = ["| sweep | mode | N | t_final | steps | wall [s] | traj-steps / s | (net of compile) | steps mean / max "
             "| not OK | peak RSS [MiB] | RSS before run [MiB] | compile in timed run [s] |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['sweep']} | {r['mode']} | {r['n']} | {r['t_final']:g} | | failed: {r['error']} "
                         "| | | | | | | |")
            continue
        sm = f"{r['mean_steps']:.0f} / {r['max_steps_taken']}"
        lines.append(f"| {r['sweep']} | {r['mode']} | {r['n']} | {r['t_final']:g} | {r['steps']} | {fmt(r['wall_s'])} "
                     f"| {fmt(r['traj_steps_per_s'])} | {fmt(r['traj_steps_per_s_net'])} | {sm} | {r['not_ok']} "
                     f"| {r['peak_rss_mb']:.0f} | {fmt(r['rss_before_timed_mb'], '.0f')} "
                     f"| {r['compile_in_timed_s']:.2f} |")
    return "\n".join(lines)


def target_line(rows) -> tuple[str, dict]:
    hits = [r for r in rows if r["mode"] == "adaptive" and r["n"] == 1_000_000 and "error" not in r
            and math.isclose(r["t_final"], 100.0) and math.isclose(r["dt"], 0.01) and not r["x64"]]
    if not hits:
        return ("Target (10^6 starts, 10^4 steps, summaries only, peak < 2 GB): not measured in this run "
                "(needs --sizes with 1000000, --t-final 100, --dt 0.01, mode adaptive, float32).",
                {"measured": False})
    r = hits[0]
    ok = r["peak_rss_mb"] < TARGET_MIB
    return (f"Target (10^6 starts, 10^4 steps, summaries only, peak < 2 GB = {TARGET_MIB:.0f} MiB): peak RSS "
            f"{r['peak_rss_mb']:.0f} MiB -> {'PASS' if ok else 'FAIL'} (wall {r['wall_s']:.0f} s, "
            f"chunk_size {r['chunk_size_effective']}).",
            {"measured": True, "passed": ok, "peak_rss_mb": r["peak_rss_mb"], "limit_mib": TARGET_MIB})


def main(argv=None) -> int:
    if argv is None and len(sys.argv) > 2 and sys.argv[1] == "--worker":
        print(json.dumps(worker(json.loads(sys.argv[2])), default=float), flush=True)
        return 0
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="1000,10000,100000,1000000", help="comma list of N ('' to skip)")
    ap.add_argument("--t-final", type=float, default=100.0, help="horizon of the N sweep")
    ap.add_argument("--dt", type=float, default=0.01)
    ap.add_argument("--horizons", default=None,
                    help="comma list of horizons for the horizon sweep ('' to skip); default 0.1, 0.3, 1 x --t-final")
    ap.add_argument("--horizon-n", type=int, default=4096, help="N of the horizon sweep")
    ap.add_argument("--modes", default="rk4,adaptive")
    ap.add_argument("--chunk-size", type=int, default=None,
                    help="run_ensemble chunk_size (default: its default, 65536 on CPU, 2^22 on an accelerator)")
    ap.add_argument("--x64", action="store_true")
    ap.add_argument("--rk4-check", action="store_true", help="passivity check on in the rk4 mode")
    ap.add_argument("--warmup", choices=("chunk", "full", "none"), default="chunk")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--timeout", type=float, default=None, help="seconds per subprocess")
    ap.add_argument("--out", default="out/bench_scaling.json")
    a = ap.parse_args(argv)

    chunk = a.chunk_size        # None: run_ensemble's default, resolved in the worker (not here: on a GPU this
    #                             process would take the device's memory from its workers)

    def floats(s):
        return [float(v) for v in s.split(",") if v.strip()]

    sizes = [int(v) for v in floats(a.sizes)]
    horizons = ([round(f * a.t_final, 10) for f in (0.1, 0.3, 1.0)] if a.horizons is None else floats(a.horizons))
    modes = [m.strip() for m in a.modes.split(",") if m.strip()]
    if set(modes) - {"rk4", "plain", "adaptive"}:
        ap.error("--modes takes rk4, plain and/or adaptive")
    for t in [a.t_final, *horizons]:
        if not math.isclose(round(t / a.dt) * a.dt, t, rel_tol=1e-9):
            ap.error(f"horizon {t} is not a whole number of steps dt = {a.dt}")
    base = dict(dt=a.dt, x64=a.x64, chunk_size=chunk, rk4_check=a.rk4_check, warmup=a.warmup, seed=a.seed)
    plan = [dict(base, sweep="N", mode=m, n=n, t_final=a.t_final) for n in sizes for m in modes]
    plan += [dict(base, sweep="horizon", mode=m, n=a.horizon_n, t_final=t) for m in modes for t in horizons]
    log(f"{len(plan)} runs, each in a fresh subprocess")
    rows = []
    for s in plan:      # the rows so far go to --out after each run: a run cut short keeps what it measured
        rows.append(run_worker(s, a.timeout))
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps({"partial": True, "results": rows}, indent=1, default=float) + "\n")

    from jaxsleigh.studies.bench import machine
    mach = next((r["machine"] for r in rows if "machine" in r), machine())
    mach["os_cpu_count"] = os.cpu_count()
    dtype = "float64" if a.x64 else "float32"
    print("## jaxsleigh scaling\n")
    print(f"Workload: jaxsleigh.studies.bench.workload (seed {a.seed}), dt = {a.dt:g}, dtype {dtype}, "
          f"chunk_size {chunk or 'run_ensemble default'}, "
          f"rk4 = fixed-step RK4 through the stepper with its on-line summaries (passivity check "
          f"{'on' if a.rk4_check else 'off'}), plain = the plain fixed-step path (summaries=False), "
          f"adaptive = run_ensemble default with summaries. Compile excluded (warm-up: {a.warmup}). "
          f"One fresh subprocess per row; peak RSS = its ru_maxrss.\n"
          f"Machine: {mach['processor']}, {mach['platform']}, os.cpu_count() = {mach['os_cpu_count']}, "
          f"jax {mach['jax']} on {', '.join(mach['devices'])}.\n")
    print(table(rows))
    line, target = target_line(rows)
    print("\n" + line)
    out = {"sizes": sizes, "horizons": horizons, "horizon_n": a.horizon_n, "t_final": a.t_final, "dt": a.dt,
           "dtype": dtype, "chunk_size": chunk, "modes": modes, "warmup": a.warmup, "machine": mach,
           "target_1e6_under_2GB": target, "results": rows}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(out, indent=1, default=float) + "\n")
    log(f"wrote {a.out}")
    return 0 if not any("error" in r for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
