r"""How large is one attempted step as an XLA program, and which part makes it large?

    python experiments/performance/step_program.py [--x64] [--out out/step_program.json]

One attempt of the engine's stepper (`jaxsleigh.integrate.stepper.attempt`) for one trajectory of the paper's
closed loop (the paper's start (1, 1, 0.5), the default observers), lowered and compiled on its own, in four
variants: the adaptive explicit step (exponential RK4 of the settled phase, `jaxsleigh.integrate.etd`), the
linearly implicit step of stiff flights (`jaxsleigh.integrate.rosenbrock`), both behind the flight switch
(`jaxsleigh.integrate.stepper.FlightSwitch`: what `jaxsleigh.solve` and every traced loss compile), and classical
fixed-step RK4. Each forward and under reverse mode (``jax.grad`` of the new state's sum with respect to the gain
``k``). Per variant: StableHLO lines, seconds to trace and lower, seconds to compile (JAX's persistent cache off,
so every program compiles), median of ``--repeats`` fresh lowerings. Prints a table and writes JSON.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

os.environ.setdefault("JAX_ENABLE_COMPILATION_CACHE", "false")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

import jaxsleigh as js  # noqa: E402
from jaxsleigh.integrate import stepper  # noqa: E402
from jaxsleigh.model.charts import chart_for  # noqa: E402


def variants():
    return {"explicit (adaptive)": dict(adaptive=True, implicit=False),
            "implicit (Rosenbrock)": dict(adaptive=True, implicit=True),
            "flight switch (both)": dict(adaptive=True, implicit=stepper.FlightSwitch()),
            "fixed-step RK4": dict(adaptive=False, implicit=False)}


def one_step(how, dtype):
    ss = js.StepSizeController(method="adaptive" if how["adaptive"] else "rk4")
    ctl = stepper.controls(ss, dtype, dt=0.01, eps=0.05, max_steps=10_000)

    def new_state(k):
        args = js.ClosedLoop(js.paper_plant(), js.paper_gains()._replace(k=k))
        y0 = chart_for(args.controller).to_chart(jnp.asarray([1.0, 1.0, 0.5, 0.0, 0.0], dtype))
        s = stepper.init_state(y0, jnp.int32(0), args, ctl)
        return stepper.attempt(s, jnp.asarray(100.0, dtype), args, ctl, **how).y.sum()
    return new_state


def measure(fn, k, repeats):
    lower, comp, lines = [], [], 0
    for _ in range(repeats):
        t = time.perf_counter()
        low = jax.jit(fn).lower(k)
        lower.append(time.perf_counter() - t)
        lines = low.as_text().count("\n")
        t = time.perf_counter()
        low.compile()
        comp.append(time.perf_counter() - t)
    return {"lines": lines, "lower_s": round(statistics.median(lower), 3), "compile_s": round(statistics.median(comp), 3)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--x64", action="store_true")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default="out/step_program.json")
    a = ap.parse_args(argv)
    if a.x64:
        jax.config.update("jax_enable_x64", True)
    dtype = jnp.float64 if a.x64 else jnp.float32
    k = jnp.asarray(js.paper_gains().k, dtype)
    rows = {}
    print(f"{'variant':24s} {'mode':8s} {'lines':>7s} {'lower s':>8s} {'compile s':>9s}")
    for name, how in variants().items():
        fn = one_step(how, dtype)
        for mode, f in (("forward", fn), ("reverse", jax.grad(fn))):
            r = measure(f, k, a.repeats)
            rows[f"{name} / {mode}"] = r
            print(f"{name:24s} {mode:8s} {r['lines']:7d} {r['lower_s']:8.2f} {r['compile_s']:9.2f}", flush=True)
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"rows": rows, "dtype": str(jnp.dtype(dtype)), "jax": jax.__version__,
                               "machine": platform.machine(), "cores": os.cpu_count(),
                               "load": os.getloadavg(), "command": "python experiments/performance/step_program.py"
                               + (" --x64" if a.x64 else "")}, indent=1))


if __name__ == "__main__":
    main()
