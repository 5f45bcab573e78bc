r"""jaxsleigh's plain fixed-step path against a hand-vectorised C RK4 of the same closed loop.

    python experiments/performance/bench_c_limit.py [--n-ics 4096] [--t-final 100] [--dt 0.01] [--seed 0]
                                                    [--repeats 7] [--cores N] [--c-threads N] [--whole-batch] [--vector-width 512]
                                                    [--c-variants strict,shared_recip,rsqrt_nr]
                                                    [--out out/bench_c_limit.json]

Builds ``jaxsleigh/studies/c_reference/rk4_w.c`` with ``gcc -O3 -march=native -fno-math-errno`` (no
-ffast-math) if a compiler is present, else prints why and exits 0 with ``available: false``. Then,
in ONE interleaved timing run (C and JAX repetitions alternate, their order flips every repetition,
compile and warm-up excluded) on the workload of :func:`jaxsleigh.studies.bench.workload` (x, y ~ U(-3, 3),
|theta0| ~ U(0.3, pi) with random sign, zero momentum; float32, final state only) it reports
trajectory-steps/s of both per CPU second (``time.process_time``: every thread of the process) and
per wall second, the ratio JAX / C, and the agreement of the final states (w chart); the JSON records the
load average before and after.

The C program runs on as many OpenMP threads as the JAX call uses cores (``--c-threads`` to choose). The JAX call timed is
``run_ensemble(ics, t_final, dt, stepsize=StepSizeController(method="rk4", check_passivity=False),
saveat=SaveAt(summaries=False), run=RunOptions(progress=False))``.
By default the JAX call uses every core (`jaxsleigh.cores`); ``--cores 1`` sets ``JAXSLEIGH_CORES=1``
before jaxsleigh is imported (the one-core run); the JSON records the cores and threads.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import load  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n-ics", type=int, default=4096)
    ap.add_argument("--t-final", type=float, default=100.0)
    ap.add_argument("--dt", type=float, default=0.01)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=7, help="interleaved C/JAX repetitions (default 7)")
    ap.add_argument("--c-threads", type=int, default=None,
                    help="OpenMP threads of the C program (default: the cores the JAX call uses)")
    ap.add_argument("--cores", type=int, default=None, help="cores for JAX (sets JAXSLEIGH_CORES; default: all)")
    ap.add_argument("--whole-batch", action="store_true",
                    help="also time the earlier kernel (one scan over the whole batch) in the same rotation")
    ap.add_argument("--vector-width", type=int, default=None,
                    help="also time drive_plain(vector_width=...) (XLA:CPU preferred SIMD width) in the rotation")
    ap.add_argument("--c-variants", default="",
                    help="comma-separated builds of the C program also timed in the rotation: "
                         "strict (literal 6 divisions), shared_recip, rsqrt_nr (XLA's rsqrt); see rk4_w.c")
    ap.add_argument("--build-dir", default="out/c_reference", help="where the C library is built")
    ap.add_argument("--out", default="out/bench_c_limit.json")
    a = ap.parse_args(argv)
    if a.cores is not None:
        os.environ["JAXSLEIGH_CORES"] = str(a.cores)
    # OpenMP's threads would otherwise spin after each C run and take the JAX run's cores
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    import jaxsleigh  # noqa: F401  (first: one JAX device per core)
    import jax

    from jaxsleigh.studies.bench import build_c_reference, c_limit, machine, workload

    log = lambda *m: print(*m, file=sys.stderr, flush=True)  # noqa: E731
    lib, reason = build_c_reference(a.build_dir)
    mach = machine()
    mach["os_cpu_count"] = os.cpu_count()
    mach["xla_flags"] = os.environ.get("XLA_FLAGS", "")
    mach["jaxsleigh_cores"] = os.environ.get("JAXSLEIGH_CORES", "")
    mach["load_average_before"] = load()
    if lib is None:
        print(f"C limit skipped: {reason}")
        res = {"available": False, "reason": reason}
    else:
        log(f"C reference built: {lib}; JAX on {jax.devices()}; {a.repeats} interleaved repetitions ...")
        res = c_limit(workload(a.n_ics, a.seed), t_final=a.t_final, dt=a.dt, repeats=a.repeats, lib=lib, log=log,
                      whole_batch=a.whole_batch, c_variants=[v for v in a.c_variants.split(",") if v],
                      variants={f"jax_vw{a.vector_width}": {"vector_width": a.vector_width}} if a.vector_width else None,
                      c_threads=a.c_threads)
        c, j = res["c_traj_steps_per_cpu_s"], res["jax_traj_steps_per_cpu_s"]
        cw, jw = res["c_traj_steps_per_wall_s"], res["jax_traj_steps_per_wall_s"]
        rc, rw = res["ratio_cpu"], res["ratio_wall"]
        ag = res["agreement"]
        print(f"C reference: {res['c_divider_ops_per_evaluation']} divisions + square roots per evaluation")
        print(f"workload: {res['n_ics']} starts (seed {a.seed}), {res['steps']} steps of dt = {a.dt:g}, float32, "
              f"final state only; JAX cores: {res['jax_cores']}; "
              f"C: {res['c_threads']} thread(s), {res['c_flags']}")
        print("trajectory-steps/s, median [min, max] over the interleaved repetitions:")
        print(f"  C    per CPU s {c['median']:.3e} [{c['min']:.3e}, {c['max']:.3e}]   "
              f"wall {cw['median']:.3e} [{cw['min']:.3e}, {cw['max']:.3e}]")
        print(f"  JAX  per CPU s {j['median']:.3e} [{j['min']:.3e}, {j['max']:.3e}]   "
              f"wall {jw['median']:.3e} [{jw['min']:.3e}, {jw['max']:.3e}]")
        extra = (["whole_batch"] if a.whole_batch else []) + ([f"vw{a.vector_width}"] if a.vector_width else [])
        for v in extra:
            ow, oc = res[f"jax_{v}_traj_steps_per_wall_s"], res[f"jax_{v}_traj_steps_per_cpu_s"]
            print(f"  JAX {v:12s} per CPU s {oc['median']:.3e} [{oc['min']:.3e}, {oc['max']:.3e}]"
                  f"   wall {ow['median']:.3e} [{ow['min']:.3e}, {ow['max']:.3e}]")
        for cv in [v for v in a.c_variants.split(",") if v]:
            o = res[f"c_{cv}_traj_steps_per_cpu_s"]
            r0 = res[f"ratio_cpu_vs_c_{cv}"]
            print(f"  C {cv:12s} per CPU s {o['median']:.3e} [{o['min']:.3e}, {o['max']:.3e}]   "
                  f"({res[f'c_{cv}_divider_ops_per_evaluation']} divider ops / evaluation; JAX / it: CPU time "
                  f"{r0['median']:.3f} [{r0['min']:.3f}, {r0['max']:.3f}]; final states vs the C reference: median "
                  f"{ag[f'c_{cv}_vs_c_rel_median_tame']:.2e}, max {ag[f'c_{cv}_vs_c_rel_max_tame']:.2e})")
        print(f"  JAX / C: CPU time {rc['median']:.3f} [{rc['min']:.3f}, {rc['max']:.3f}], "
              f"wall {rw['median']:.3f} [{rw['min']:.3f}, {rw['max']:.3f}]")
        for v in extra:
            r0, w0 = res[f"ratio_cpu_{v}"], res[f"ratio_wall_{v}"]
            print(f"  JAX {v} / C: CPU time {r0['median']:.3f} [{r0['min']:.3f}, {r0['max']:.3f}], "
                  f"wall {w0['median']:.3f} [{w0['min']:.3f}, {w0['max']:.3f}]")
        print(f"agreement of the final states (w chart, relative to each state's largest component), "
              f"{ag['n_tame']} tame starts: C vs JAX median {ag['c_vs_jax_rel_median_tame']:.2e}, "
              f"p99 {ag['c_vs_jax_rel_p99_tame']:.2e}, max {ag['c_vs_jax_rel_max_tame']:.2e}; "
              f"float32 vs float64 (same scheme) median {ag['float32_vs_float64_rel_median_tame']:.2e}, "
              f"max {ag['float32_vs_float64_rel_max_tame']:.2e}; finiteness mismatches "
              f"{ag['finiteness_mismatch']}, bitwise-equal rows {ag['bitwise_equal_rows']}")
    mach["load_average_after"] = load()
    res["machine"] = mach
    res["command"] = "python experiments/performance/bench_c_limit.py " + " ".join(sys.argv[1:] if argv is None else argv)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(res, indent=1) + "\n")
    log(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
