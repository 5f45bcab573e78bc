r"""Why the plain fixed-step kernel stays near 0.6-0.7 of the C program per core.

    python experiments/performance/xla_kernel_structure.py [--n-ics 4096] [--steps 10000] [--repeats 7]
                                                           [--out docs/figures/xla_kernel_structure.json]

One core (``JAXSLEIGH_CORES=1`` is set before jaxsleigh is imported), float32, the benchmark workload
(`jaxsleigh.studies.bench.workload`, seed 0), dt = 0.01, final state only. In one interleaved run (the order of the
variants flips every repetition, compilation and warm-up excluded) it times, per CPU second:

- ``c``: the C reference (`jaxsleigh/studies/c_reference/rk4_w.c`) on one thread, if a compiler is present;
- ``library``: the library's specialised plain kernel, built as `drive_plain` builds it on CPU: the library's
  `jaxsleigh.integrate.stepper.run_plain` with the run's plant and gains as constants of the program, compiled
  with `PLAIN_CPU_OPTIONS` (cache blocks of 256), and the same kernel with blocks of 128 and 512 (``block_128``,
  ``block_512``);
- ``rebuilt``: the library's step built by this script (dt a constant of the program), the baseline of the
  three variants below;
- ``shared_reciprocal``: the same step with the damping's ``k / w1**2`` written ``(k * (1 / w1)) * (1 / w1)``,
  which takes one division per evaluation away if the divider were the bound;
- ``inline_step``: the stage points written row by row (``stack([y[r] + c k[r] ...])``), which lets XLA put
  the whole step into one loop fusion;
- ``stage_in_field``: the stage points written row by row and the slopes k1, k2, k3 materialised
  (``optimization_barrier``): XLA fuses each stage point into the evaluation that reads it, 4 kernels per step;
- ``rows_carry``: the state carried as a tuple of five rows instead of one (5, B) array;
- ``run_ensemble`` and ``drive_plain``: the library's front door and engine around the same kernel.

For each kernel it records the fusions (kernels) per step in XLA's optimised program (the innermost while
body), the division instructions in the HLO of that body, and the final states' largest relative difference
from ``library`` (for ``drive_plain`` too: 0 when ``library`` is the very kernel the engine runs). The JSON
records the machine, jax version, load average and command.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import load  # noqa: E402


def _inner_body(hlo: str) -> str:
    """The text of the innermost while body of an optimised HLO module (the one that calls no while)."""
    comps = re.split(r"\n(?=%|ENTRY)", hlo)
    bodies = set(re.findall(r"body=(%[\w.\-]+)", hlo))
    inner = [c for c in comps if c.split(" ", 1)[0] in bodies and " while(" not in c]
    return max(inner, key=lambda c: c.count(" fusion(")) if inner else ""


def _structure(hlo: str) -> dict:
    """Array kernels (fusions; the loop counter's scalar ones left out) per step, and the divisions their HLO
    holds (a concatenating fusion computes each row on its own, so a division shared by rows runs once per row)."""
    body = _inner_body(hlo)
    comps = {c.split(" ", 1)[0]: c for c in re.split(r"\n(?=%|ENTRY)", hlo)}
    kernels = [ln for ln in body.splitlines() if re.search(r"= f(32|64)\[\d[^\]]*\]\S* fusion\(", ln)]
    calls = [re.search(r"calls=(%[\w.\-]+)", ln).group(1) for ln in kernels]
    return {"kernels_per_step": len(kernels),
            "hlo_divides_per_step": sum(comps.get(n, "").count(" divide(") for n in calls)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n-ics", type=int, default=4096)
    ap.add_argument("--steps", type=int, default=10000)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--out", default="docs/figures/xla_kernel_structure.json")
    a = ap.parse_args(argv)
    os.environ["JAXSLEIGH_CORES"] = "1"
    import jax
    import jax.numpy as jnp
    import numpy as np

    import jaxsleigh
    import jaxsleigh.model.paper_law as paper_law
    from jaxsleigh.integrate import engine
    from jaxsleigh.integrate.stepper import run_plain
    from jaxsleigh.model.charts import chart_for
    from jaxsleigh.model.closed_loop import ClosedLoop
    from jaxsleigh.studies.bench import build_c_reference, c_reference_run, machine, workload

    log = lambda *m: print(*m, file=sys.stderr, flush=True)  # noqa: E731
    ics = workload(a.n_ics, 0)
    t_final = a.steps * 0.01
    horizon = engine.make_horizon(t_final, 0.01)
    args0 = ClosedLoop(jaxsleigh.paper_plant(), jaxsleigh.paper_gains())
    ics5, status0 = engine.check_ics(ics)
    y0w = engine.initial_w(ics5, status0, jnp.float32)
    leaves, tree = jax.tree_util.tree_flatten(args0)                    # the plant and gains in float32
    args = jax.tree_util.tree_unflatten(tree, [np.asarray(v, np.float32) for v in leaves])
    dt = jnp.float32(0.01)
    y0 = np.asarray(y0w).T.copy()                                       # batch-last (5, N)

    def builder(step, block=256, rows=False):
        def scan(b):
            if rows:
                c = jax.lax.scan(lambda c, _: (step(c), None), tuple(b[r] for r in range(5)), None, length=a.steps)[0]
                return jnp.stack(c)
            return jax.lax.scan(lambda c, _: (step(c), None), b, None, length=a.steps)[0]

        def run(y):
            n = y.shape[-1]
            yb = y.reshape(5, n // block, block).transpose(1, 0, 2)
            return jax.lax.map(scan, yb).transpose(1, 0, 2).reshape(5, n)
        return jax.jit(run, compiler_options=engine.PLAIN_CPU_OPTIONS)

    def specialised(block):
        """The library's kernel as `drive_plain` compiles it on CPU: `run_plain` with ``args`` (this run's plant and
        gains) as constants of the program, built with `PLAIN_CPU_OPTIONS`; dt is an argument."""
        return jax.jit(lambda y, dt: run_plain(y, args, dt, n_steps=a.steps, block=block), donate_argnums=(0,),
                       compiler_options=engine.PLAIN_CPU_OPTIONS)

    field = lambda y: chart_for(args.controller).field(0.0, y, args)  # noqa: E731
    h = 0.01

    def rk4(stage, keep=lambda k: k):
        def step(y):
            k1 = keep(field(y))
            k2 = keep(field(stage(y, 0.5 * h, k1)))
            k3 = keep(field(stage(y, 0.5 * h, k2)))
            k4 = field(stage(y, h, k3))
            return y + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        return step

    whole = lambda y, c, k: y + c * k                                   # noqa: E731
    by_row = lambda y, c, k: jnp.stack([y[r] + c * k[r] for r in range(5)])  # noqa: E731

    def rows_step(rows):
        f = lambda r: tuple(field(jnp.stack(r)))                        # noqa: E731
        k1 = f(rows)
        k2 = f([y + (0.5 * h) * k for y, k in zip(rows, k1)])
        k3 = f([y + (0.5 * h) * k for y, k in zip(rows, k2)])
        k4 = f([y + h * k for y, k in zip(rows, k3)])
        return tuple(y + (h / 6.0) * (b1 + 2.0 * b2 + 2.0 * b3 + b4) for y, b1, b2, b3, b4 in zip(rows, k1, k2, k3, k4))

    def shared_reciprocal(w, v, gains):
        inv = 1.0 / w[0]
        D = gains.D_hat
        return (D[0, 0] * v[0] + D[0, 1] * v[1], D[1, 0] * v[0] + (D[1, 1] + (gains.k * inv) * inv) * v[1])

    y0j = jnp.asarray(y0)
    kernels, structure = {}, {}

    def add(name, jitted, *extra):
        """Compile ``jitted`` once (now: the shared-reciprocal variant is traced while its law is patched); the
        timed program and the counted one are that executable. ``extra``: the library's kernel also takes dt."""
        exe = jitted.lower(y0j, *extra).compile()
        kernels[name] = lambda y: exe(y, *extra)
        structure[name] = _structure(exe.as_text())

    for name, block in (("library", 256), ("block_128", 128), ("block_512", 512)):
        add(name, specialised(block), dt)
    add("rebuilt", builder(rk4(whole)))
    original = paper_law.damping_injection_components
    paper_law.damping_injection_components = shared_reciprocal
    try:
        add("shared_reciprocal", builder(rk4(whole)))
    finally:
        paper_law.damping_injection_components = original
    add("inline_step", builder(rk4(by_row)))
    add("stage_in_field", builder(rk4(by_row, jax.lax.optimization_barrier)))
    add("rows_carry", builder(rows_step, rows=True))
    compiled = set(kernels)
    plain = dict(stepsize=jaxsleigh.StepSizeController(method="rk4", check_passivity=False),
                 saveat=jaxsleigh.SaveAt(summaries=False), run=jaxsleigh.RunOptions(progress=False))
    kernels["run_ensemble"] = lambda y: jaxsleigh.run_ensemble(ics, t_final=t_final, dt=0.01, **plain)
    kernels["drive_plain"] = lambda y: engine.drive_plain(y0w, status0, args0, horizon)
    lib, reason = build_c_reference("out/c_reference")
    if lib is not None:
        import ctypes
        clib = ctypes.CDLL(str(lib))
        kernels["c"] = lambda y: c_reference_run(clib, y0w, args0, 0.01, a.steps, 1)

    finals = {}
    for name, fn in kernels.items():                                    # compile and warm up
        out = fn(jnp.asarray(y0))
        if name in compiled:
            finals[name] = np.asarray(out)
        elif name == "drive_plain":                 # the engine's own kernel, against ``library`` built as it builds it
            finals[name] = np.asarray(out[0]).T
        log(f"warm: {name}")
    ref = finals["library"]
    scale = np.abs(ref).max(axis=0)
    times = {k: [] for k in kernels}
    names = list(kernels)
    for r in range(a.repeats):
        for name in (names if r % 2 == 0 else names[::-1]):
            y = jnp.asarray(y0)
            t = time.process_time()
            out = kernels[name](y)
            jax.block_until_ready(out)
            times[name].append(time.process_time() - t)
        log(f"repetition {r + 1}: " + ", ".join(f"{k} {v[-1]:.3f}" for k, v in times.items()))
    work = a.n_ics * a.steps
    rows = {}
    c_rate = work / float(np.median(times["c"])) if "c" in times else None
    for name, ts in times.items():
        rate = work / float(np.median(ts))
        rows[name] = {"cpu_s_median": float(np.median(ts)), "cpu_s": ts, "traj_steps_per_cpu_s": rate,
                      "of_c": rate / c_rate if c_rate else None, **structure.get(name, {})}
        if name in finals:
            rows[name]["max_rel_diff_vs_library"] = float(np.max(np.abs(finals[name] - ref) / scale))
        of_c = f", {rows[name]['of_c']:.3f} of C" if c_rate else ""
        kps = f", {rows[name]['kernels_per_step']} kernels per step" if name in structure else ""
        print(f"{name:18s} {rate:.3e} traj-steps per CPU s{of_c}{kps}")
    out = {"command": "python experiments/performance/xla_kernel_structure.py " + " ".join(sys.argv[1:] if argv is None else argv),
           "machine": machine(), "load_average": load(), "dtype": "float32",
           "cores": 1, "n_ics": a.n_ics, "steps": a.steps, "repeats": a.repeats, "c_reason": reason, "rows": rows}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(out, indent=1) + "\n")
    log(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
