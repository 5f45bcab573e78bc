"""Start-up: the compile budget a user meets first, per entry point, from a fresh process with an empty cache.

    python experiments/performance/cold_start.py [--only NAME[,NAME]] [--quick] [--each] [--x64]
                                                 [--no-compile-cache] [--out docs/figures/cold_start.json]

Each entry point runs in a new Python process (this script again, ``--child NAME``) with a new, empty
``XDG_CACHE_HOME`` (so jaxsleigh's cache folder, `jaxsleigh.cache.compilation_cache_dir`, is empty) and without
``JAXSLEIGH_CACHE_DIR``, ``JAX_COMPILATION_CACHE_DIR`` or any other ``JAX_PERSISTENT_*`` setting: nothing compiled
on this machine before is used. The Python entries call `jaxsleigh.enable_compilation_cache` first, as the README
does (the command line turns it on itself); ``--no-compile-cache`` runs every entry with
``JAXSLEIGH_NO_COMPILE_CACHE=1`` instead. Per entry it prints and records:

``first_s``          seconds from the process's first line (imports included) to the first result in hand;
``programs``         XLA programs compiled for it (JAX's ``/jax/core/compile/backend_compile_duration`` events,
                     `jax.monitoring`; ``cache_hits`` of them were found in the persistent cache, which this
                     process itself filled), ``compile_s`` the sum of their seconds, ``compiled_first`` their names;
``second_s``         seconds of a second call in the same process with other numbers of the same shapes (other
                     starts, gains, horizon and tolerances at once, ``second_changes``; for the command line and the
                     notebooks: the same command, or every cell, again), and ``second_programs`` what it compiled;
``second_each``      with ``--each``: a call per number changed alone (to a third value), its seconds and programs:
                     which of them makes the entry compile again.

Entries (``--only``; ``notebooks`` names all five; sizes with ``--quick`` in brackets, a smoke test):

``diffrax``     the peer: diffrax ``Tsit5`` + ``PIDController(rtol=1e-5, atol=1e-6)``, ``jit(vmap(diffeqsolve))``
                of `jaxsleigh.vector_field` (physical chart) over the ``ensemble`` entry's starts at rest; starts,
                gains, horizon and tolerances are arguments of the one jitted function [64 starts, 10 s];
``paper``       ``jaxsleigh paper`` (the command line's `main` in the instrumented process);
``simulate``    `jaxsleigh.simulate` of one start, 100 s [10 s];
``ensemble``    `jaxsleigh.run_ensemble` of 2,000 starts (the README's), 100 s [64 starts, 10 s];
``basin``       `jaxsleigh.run_basin` of 10^5 starts (`jaxsleigh.sample_starts`), 100 s [256 starts, 10 s];
``solve_grad``  the README's ``jax.grad`` of ``js.solve(...).summaries["u_energy"]`` in k, 10 s [2 s];
``optimum``     `jaxsleigh.optimum` of one start at 4 horizons, its defaults [2 horizons];
``sweep``       `jaxsleigh.sweep` of 8 values of k x 2,048 starts, 100 s [4 x 32, 10 s];
``tune``, ``search``, ``pareto``, ``tune_law``: one short run of each tuner (`jaxsleigh.tuning.tune`,
                ``search``, ``pareto_front`` with two budgets, ``tune_law`` on Aicardi's law); a search this short
                may end without a feasible candidate, which counts as its result (recorded in ``notes``);
``compare``     `jaxsleigh.studies.compare.compare` of every registered law on 256 starts of each distribution,
                100 s, as ``jaxsleigh compare`` by default [two laws, 16 uniform starts, 10 s];
``notebook_*``  each notebook (a copy of ``notebooks/`` in a temporary folder) in a fresh ``python3`` kernel
                (nbclient); the kernel start is in ``first_s``; the kernel counts the programs itself; its second
                call is every cell again in the same kernel [the notebooks as they are].

Printed: a Markdown table with the ratios of ``first_s`` and of the programs to the diffrax peer's (when it
ran). Written to ``--out``: the machine (CPU model, cores), JAX's version, the dtype, the command line, the commit,
the load average and every entry. Timings are only worth recording on a quiet machine.
"""
from __future__ import annotations

import time

_T0 = time.perf_counter()                 # the child's origin: before any import of JAX or jaxsleigh

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))
PYTHON_ENTRIES = ("diffrax", "paper", "simulate", "ensemble", "basin", "solve_grad", "optimum", "sweep", "tune",
                  "search", "pareto", "tune_law", "compare")
ENTRIES = PYTHON_ENTRIES + tuple(f"notebook_{p.stem}" for p in NOTEBOOKS)
BACKEND_COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"
CACHE_HIT_EVENT = "/jax/compilation_cache/cache_hits"
MARK = "COLD_START_JSON "


# --- the child: one entry point in this fresh process ------------------------------------------------------------

class Compiles:
    """Every XLA program compiled in this process (JAX's monitoring events), thread-safe: jaxsleigh's runs compile
    from worker threads too."""

    def __init__(self):
        self.lock = threading.Lock()
        self.events = []                  # (program name, seconds)
        self.hits = 0

    def install(self):
        import jax

        def on_duration(event, duration, **kw):
            if event == BACKEND_COMPILE_EVENT:
                with self.lock:
                    self.events.append((str(kw.get("fun_name", "?")), float(duration)))

        def on_event(event, **kw):
            if event == CACHE_HIT_EVENT:
                with self.lock:
                    self.hits += 1

        jax.monitoring.register_event_duration_secs_listener(on_duration)
        jax.monitoring.register_event_listener(on_event)

    def mark(self):
        with self.lock:
            return len(self.events), self.hits

    def between(self, mark, end=None):
        """What was compiled from ``mark`` to ``end`` (default: now)."""
        with self.lock:
            end = end or (len(self.events), self.hits)
            ev, hits = self.events[mark[0]:end[0]], end[1] - mark[1]
        names: dict = {}
        for name, s in ev:
            n, t = names.get(name, (0, 0.0))
            names[name] = (n + 1, t + s)
        return {"programs": len(ev), "compile_s": sum(s for _, s in ev), "cache_hits": hits,
                "compiled": {k: [n, round(t, 3)] for k, (n, t) in sorted(names.items(), key=lambda kv: -kv[1][1])}}


def _starts(n: int, seed: int):
    """The README's starts: x, y ~ U(-3, 3), theta0 ~ U(0.3, 3), at rest."""
    import numpy as np

    return np.random.default_rng(seed).uniform([-3, -3, 0.3], [3, 3, 3], (n, 3))


#: the numbers a second call changes; each takes value 0 in the first call, 1 in the second (all at once) and 2 in
#: the calls of ``--each`` (one at a time: a value neither call used, so nothing is found compiled by chance)
KNOBS = ("starts", "gains", "horizon", "tolerances")
#: what an entry's calls want said beside their figures
NOTES: list = []


def _entry(name: str, quick: bool, x64: bool, scratch: Path):
    """``(call, knobs)``: ``call(**{knob: 0, 1 or 2})`` runs the entry ``name`` and returns its result in hand;
    ``knobs`` are the `KNOBS` it takes (none: a second call is the same call again)."""
    import jax
    import numpy as np

    import jaxsleigh as js

    T = 10.0 if quick else 100.0
    horizon = (1.0, 0.8, 0.9)                                          # x the first call's horizon
    quiet = js.RunOptions(progress=False)
    gains = (js.paper_gains(), js.gains(L=(4.0, 1.0, 1.6), k=0.2, D_hat=(4.0, 8.0)),   # the README's other gains
             js.gains(L=(3.0, 0.8, 1.2), k=0.15, D_hat=(5.0, 6.0)))
    tol = (1e-8 if x64 else 1e-6) * np.array([1.0, 3.0, 2.0])         # the dtype's default, then 3x and 2x it
    stepsize = (None, js.StepSizeController(rtol=tol[1], atol=tol[1]), js.StepSizeController(rtol=tol[2], atol=tol[2]))
    ics = (np.array([-3.0, -2.0, np.pi / 8]), np.array([1.0, 1.0, 0.5]), np.array([2.0, -1.0, -1.0]))
    if name == "diffrax":
        import diffrax
        import jax.numpy as jnp

        n = 64 if quick else 2000
        term, solver = diffrax.ODETerm(js.vector_field), diffrax.Tsit5()

        def one(y0, args, t1, rtol, atol):
            sol = diffrax.diffeqsolve(term, solver, 0.0, t1, 0.01, y0, args=args,
                                      stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
                                      saveat=diffrax.SaveAt(t1=True), max_steps=100_000, throw=False)
            return sol.ys[-1], sol.result == diffrax.RESULTS.successful

        f = jax.jit(jax.vmap(one, in_axes=(0, None, None, None, None)))
        dtype = np.float64 if x64 else np.float32

        def run(starts=0, gains_=0, horizon_=0, tolerances=0):
            y0 = np.zeros((n, 5), dtype)
            y0[:, :3] = _starts(n, starts)
            rtol, atol = (1e-5, 1e-6) if tolerances == 0 else (2e-5, 2e-6) if tolerances == 1 else (3e-5, 3e-6)
            with jax.enable_x64(x64):                  # float64 arrays stay float64 only with x64 on
                args = jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype),
                                              js.ClosedLoop(js.paper_plant(), gains[gains_]))
                out = jax.block_until_ready(f(jnp.asarray(y0), args, jnp.asarray(T * horizon[horizon_], dtype),
                                              jnp.asarray(rtol, dtype), jnp.asarray(atol, dtype)))
            if out[0].dtype != dtype:
                raise RuntimeError(f"the diffrax peer ran in {out[0].dtype}, not {np.dtype(dtype).name}")
            return out

        return _knobs(run), KNOBS
    if name == "paper":
        from jaxsleigh.cli import main

        calls = []

        def paper():
            calls.append(1)
            rc = main(["paper", "--out", str(scratch / f"paper{len(calls)}"), "--no-progress",
                       *(["--x64"] if x64 else [])])
            if rc:
                raise RuntimeError(f"jaxsleigh paper exited with {rc}")

        return paper, ()
    if name == "simulate":
        return _knobs(lambda starts=0, gains_=0, horizon_=0, tolerances=0: js.simulate(
            ics[starts], gains=gains[gains_], t_final=T * horizon[horizon_], x64=x64, stepsize=stepsize[tolerances],
            run=quiet)), KNOBS
    if name in ("ensemble", "basin", "sweep"):
        n = {"ensemble": (64, 2000), "basin": (256, 100_000), "sweep": (32, 2048)}[name][0 if quick else 1]
        p = 4 if quick else 8

        def run(starts=0, gains_=0, horizon_=0, tolerances=0):
            kw = dict(gains=gains[gains_], t_final=T * horizon[horizon_], x64=x64, stepsize=stepsize[tolerances],
                      run=quiet)
            if name == "ensemble":
                return js.run_ensemble(_starts(n, starts), **kw)
            if name == "basin":
                return js.run_basin(js.sample_starts(n, seed=starts), **kw)
            return js.sweep(js.sample_starts(n, seed=starts), {"k": np.geomspace(0.02, 1.0, p)}, **kw)

        return _knobs(run), KNOBS
    if name == "solve_grad":
        t1 = 2.0 if quick else 10.0
        solve_ics = (ics[1], ics[0], ics[2])                           # the README's ics[1] first
        dtype = np.float64 if x64 else np.float32

        def grad(starts=0, gains_=0, horizon_=0, tolerances=0):
            with jax.enable_x64(x64):
                loss = lambda k: js.solve(gains[gains_]._replace(k=k), solve_ics[starts].astype(dtype),
                                          t_final=t1 * horizon[horizon_],
                                          stepsize=stepsize[tolerances]).summaries["u_energy"]
                return jax.block_until_ready(jax.grad(loss)(0.1 + 0.05 * gains_))

        return _knobs(grad), KNOBS
    if name == "optimum":
        h = (5.0, 10.0) if quick else (5.0, 10.0, 20.0, 40.0)
        scale = (1.0, 1.2, 1.1)
        return _knobs(lambda starts=0, horizon_=0: js.optimum(ics[starts][None], tuple(v * scale[horizon_] for v in h))), \
            ("starts", "horizon")
    import jaxsleigh.tuning as tu

    loss = tu.LossConfig(t_final=5.0, guard_t_final=2.0, probe_t_final=10.0) if quick else tu.LossConfig()
    ltol = (1.0, 2.0, 3.0)                                             # x LossConfig's tolerances

    def loss_of(horizon_, tolerances):
        ss = loss.stepsize
        return loss._replace(t_final=loss.t_final * horizon[horizon_],
                             stepsize=ss._replace(rtol=ss.rtol * ltol[tolerances], atol=ss.atol * ltol[tolerances]))

    config = (tu.TuneConfig(steps=2, batch=8, probe=2, verify=1, n_attempts=1000) if quick
              else tu.TuneConfig(steps=5, batch=64, probe=4, verify=1))
    gains0 = ("paper", gains[1], gains[2])
    if name == "tune":
        return _knobs(lambda starts=0, gains_=0, horizon_=0, tolerances=0: tu.tune(
            gains0[gains_], config=config._replace(seed=starts), loss=loss_of(horizon_, tolerances), x64=x64,
            progress=False)), KNOBS
    if name == "search":
        from jaxsleigh.tuning.cma_search import NoFeasibleCandidate

        # energy_margin > 1: the paper's gains are feasible; the horizon is the search's own 100 s even with --quick
        # (in 10 s too few of the few starts settle for any candidate to be feasible)
        sc = (tu.SearchConfig(generations=1, population=4, batch=8, verify=1, energy_margin=1.2) if quick
              else tu.SearchConfig(generations=3, population=8, batch=32, verify=1, energy_margin=1.2))

        def search(starts=0, gains_=0, horizon_=0, tolerances=0):
            try:
                return tu.search(gains0[gains_], config=sc._replace(seed=starts, t_final=sc.t_final * horizon[horizon_]),
                                 x64=x64, stepsize=stepsize[tolerances], progress=False)
            except NoFeasibleCandidate as e:           # it ran to its end: a result for the compile budget
                NOTES.append(f"search ended without a feasible candidate: {e}")

        return _knobs(search), KNOBS
    if name == "pareto":
        budgets = []

        def front(starts=0, gains_=0, horizon_=0, tolerances=0):
            if not budgets:
                budgets.append(tu.default_budgets(2))
            return tu.pareto_front(budgets[0], gains0=gains0[gains_], config=config._replace(seed=starts),
                                   loss=loss_of(horizon_, tolerances), warm_steps=1, x64=x64, progress=False)

        return _knobs(front), KNOBS
    if name == "tune_law":
        from jaxsleigh.controllers.registry import make_controller

        law = make_controller("aicardi")
        scale = (1.0, 1.2, 1.1)
        n, steps = (8, 2) if quick else (64, 5)
        return _knobs(lambda starts=0, gains_=0, horizon_=0, tolerances=0: tu.tune_law(
            law._replace(gamma=law.gamma * scale[gains_], k=law.k * scale[gains_]), _starts(n, starts),
            loss=loss_of(horizon_, tolerances), steps=steps, x64=x64)), KNOBS
    if name == "compare":
        from jaxsleigh.controllers.registry import controller_names, make_controller
        from jaxsleigh.studies.compare import START_DISTRIBUTIONS, compare, draw_compare_starts

        names = ["paper", "aicardi"] if quick else list(controller_names())
        dists = ["uniform"] if quick else list(START_DISTRIBUTIONS)
        n = 16 if quick else 256

        def run(starts=0, gains_=0, horizon_=0, tolerances=0):          # other gains: the paper's law's
            laws = {c: make_controller(c, gains=gains[gains_]) if c == "paper" else make_controller(c)
                    for c in names}
            return compare(laws, {d: draw_compare_starts(d, n, starts) for d in dists}, t_final=T * horizon[horizon_],
                           x64=x64, stepsize=stepsize[tolerances])

        return _knobs(run), KNOBS
    raise SystemExit(f"unknown entry {name!r}")


def _knobs(run):
    """``run`` called with the knobs' names (its keywords end in ``_`` where they would shadow a name)."""
    import inspect

    own = set(inspect.signature(run).parameters)
    return lambda **k: run(**{(n if n in own else n + "_"): v for n, v in k.items()})


#: what the notebook's kernel runs before its first cell and after its last (it counts its own compilations)
KERNEL_SETUP = f"""
import builtins, threading, time, jax
builtins._cold_start = {{"events": [], "hits": 0, "lock": threading.Lock()}}
def _cold_start_duration(event, duration, **kw):
    if event == {BACKEND_COMPILE_EVENT!r}:
        with builtins._cold_start["lock"]:
            builtins._cold_start["events"].append(float(duration))
def _cold_start_event(event, **kw):
    if event == {CACHE_HIT_EVENT!r}:
        with builtins._cold_start["lock"]:
            builtins._cold_start["hits"] += 1
jax.monitoring.register_event_duration_secs_listener(_cold_start_duration)
jax.monitoring.register_event_listener(_cold_start_event)
"""
KERNEL_REPORT = f"""
import builtins, json
with builtins._cold_start["lock"]:
    print({MARK!r} + json.dumps({{"programs": len(builtins._cold_start["events"]),
        "compile_s": sum(builtins._cold_start["events"]), "cache_hits": builtins._cold_start["hits"]}}))
"""


def _notebook(name: str, scratch: Path) -> dict:
    """Run a notebook twice in one fresh kernel (all its cells, then all again); programs counted in the kernel."""
    import nbformat
    from nbclient import NotebookClient

    folder = scratch / "notebooks"
    shutil.copytree(ROOT / "notebooks", folder)
    nb = nbformat.read(folder / f"{name[len('notebook_'):]}.ipynb", as_version=4)
    cells = [c for c in nb.cells if c.cell_type == "code"]
    setup, report = nbformat.v4.new_code_cell(KERNEL_SETUP), nbformat.v4.new_code_cell(KERNEL_REPORT)
    nb.cells = [setup, *nb.cells, report]
    client = NotebookClient(nb, timeout=3600, kernel_name="python3", record_timing=False,
                            resources={"metadata": {"path": str(folder)}})

    def counts():
        report.outputs = []
        client.execute_cell(report, len(nb.cells) - 1)
        text = "".join(o.get("text", "") for o in report.outputs if o.get("output_type") == "stream")
        return json.loads(text.split(MARK, 1)[1].splitlines()[0])

    out = {}
    with client.setup_kernel():
        client.execute_cell(setup, 0)                  # imports JAX in the kernel: part of the first result
        for i, c in enumerate(cells):
            client.execute_cell(c, i + 1)
        out["first_s"] = time.perf_counter() - _T0
        first = counts()
        t0 = time.perf_counter()
        try:
            for i, c in enumerate(cells):
                client.execute_cell(c, i + 1)
            out["second_s"] = time.perf_counter() - t0
            second = counts()
            out.update(second_programs=second["programs"] - first["programs"],
                       second_compile_s=second["compile_s"] - first["compile_s"])
        except Exception as e:                         # a notebook that cannot run twice in one kernel
            out["second_error"] = f"{type(e).__name__}: {str(e)[-300:]}"
    out.update(programs=first["programs"], compile_s=first["compile_s"], cache_hits=first["cache_hits"],
               cells=len(cells), second_changes="none: every cell again")
    return out


def child(name: str, quick: bool, x64: bool, each: bool) -> None:
    """Run one entry in this (fresh) process and print its figures as one JSON line after ``MARK``."""
    scratch = Path(tempfile.mkdtemp(prefix="cold_start_run_"))
    try:
        if name.startswith("notebook_"):
            out = _notebook(name, scratch)
        else:
            import jax

            compiles = Compiles()
            compiles.install()
            import jaxsleigh as js

            if os.environ.get("JAXSLEIGH_NO_COMPILE_CACHE", "").strip() in ("", "0") and name != "paper":
                js.enable_compilation_cache()          # as the README does (the command line does it itself)
            import_s = time.perf_counter() - _T0
            call, knobs = _entry(name, quick, x64, scratch)
            m0 = compiles.mark()
            call(**{k: 0 for k in knobs})
            out = {"first_s": time.perf_counter() - _T0, "import_s": import_s}
            m1 = compiles.mark()
            t0 = time.perf_counter()
            call(**{k: 1 for k in knobs})
            out["second_s"] = time.perf_counter() - t0
            a, b = compiles.between(m0, m1), compiles.between(m1)
            out.update(programs=a["programs"], compile_s=a["compile_s"], cache_hits=a["cache_hits"],
                       second_programs=b["programs"], second_compile_s=b["compile_s"], compiled_first=a["compiled"],
                       compiled_second=b["compiled"], second_changes=list(knobs) or "none: the same call again",
                       jax=jax.__version__, backend=jax.default_backend())
            if each:
                out["second_each"] = {}
                for k in knobs:
                    m, t0 = compiles.mark(), time.perf_counter()
                    call(**{j: 2 if j == k else 0 for j in knobs})
                    c = compiles.between(m)
                    out["second_each"][k] = {"s": time.perf_counter() - t0, "programs": c["programs"],
                                             "compile_s": c["compile_s"], "compiled": c["compiled"]}
        if NOTES:
            out["notes"] = NOTES
        print(MARK + json.dumps(out), flush=True)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


# --- the parent: one fresh process per entry ----------------------------------------------------------------------

def fresh_env(cache_home: Path, no_cache: bool) -> dict:
    """This process's environment without any compilation cache setting, with a new empty XDG_CACHE_HOME."""
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("JAX_COMPILATION_CACHE", "JAX_PERSISTENT_CACHE", "JAXSLEIGH_CACHE_DIR",
                                "JAXSLEIGH_NO_COMPILE_CACHE"))}
    env.update(XDG_CACHE_HOME=str(cache_home), MPLBACKEND="Agg",     # the notebooks' kernel: this Python's
               PATH=os.pathsep.join([str(Path(sys.executable).parent), env.get("PATH", "")]),
               PYTHONPATH=os.pathsep.join([str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])]))
    if no_cache:
        env["JAXSLEIGH_NO_COMPILE_CACHE"] = "1"
    return env


def run_entry(name: str, a) -> dict:
    with tempfile.TemporaryDirectory(prefix="cold_start_") as d:
        cache_home = Path(d) / "xdg_cache"
        cache_home.mkdir()
        args = [sys.executable, str(Path(__file__).resolve()), "--child", name,
                *(["--quick"] if a.quick else []), *(["--x64"] if a.x64 else []), *(["--each"] if a.each else [])]
        t0 = time.perf_counter()
        r = subprocess.run(args, env=fresh_env(cache_home, a.no_compile_cache), capture_output=True, text=True,
                           cwd=d, timeout=a.timeout)
        wall = time.perf_counter() - t0
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith(MARK)]
    if r.returncode or not lines:
        return {"error": f"exit {r.returncode}: {(r.stderr or r.stdout)[-1500:]}", "process_s": wall}
    return {**json.loads(lines[-1][len(MARK):]), "process_s": wall}


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _fmt(v, f="{:.1f}"):
    return "-" if v is None else f.format(v)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default=None, help=f"comma-separated entries of {', '.join(ENTRIES)}, or 'notebooks'")
    ap.add_argument("--quick", action="store_true", help="small sizes: a smoke test, not a measurement")
    ap.add_argument("--x64", action="store_true", help="float64 (default float32; optimum is always float64)")
    ap.add_argument("--no-compile-cache", action="store_true",
                    help="JAXSLEIGH_NO_COMPILE_CACHE=1 in every process (default: jaxsleigh's cache on, empty)")
    ap.add_argument("--each", action="store_true",
                    help="also a call per number changed alone (starts, gains, horizon, tolerances): which recompiles")
    ap.add_argument("--timeout", type=float, default=3600, help="seconds per entry's process (default 3600)")
    ap.add_argument("--out", default=str(ROOT / "docs" / "figures" / "cold_start.json"))
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        return child(a.child, a.quick, a.x64, a.each)
    names = list(ENTRIES)
    if a.only:
        asked = [n.strip() for n in a.only.split(",") if n.strip()]
        names = []
        for n in asked:
            names += [e for e in ENTRIES if e.startswith("notebook_")] if n == "notebooks" else [n]
        unknown = sorted(set(names) - set(ENTRIES))
        if unknown:
            ap.error(f"unknown entries {unknown} (known: {', '.join(ENTRIES)}, notebooks)")
    loads = [[round(x, 2) for x in os.getloadavg()]]
    results = {}
    for n in names:
        print(f"{n} ...", file=sys.stderr, flush=True)
        results[n] = r = run_entry(n, a)
        print(f"  {r.get('error') or ''}" if "error" in r else
              f"  first {r['first_s']:.1f} s ({r['programs']} programs, {r['compile_s']:.1f} s compiling), "
              f"second {_fmt(r.get('second_s'))} s ({r.get('second_programs', '-')} programs)",
              file=sys.stderr, flush=True)
        loads.append([round(x, 2) for x in os.getloadavg()])
    peer = results.get("diffrax", {})
    title = ("SMOKE TEST (--quick): small sizes, not a measurement; " if a.quick else "") + \
        f"{cpu_model()}, {os.cpu_count()} cores, {'float64' if a.x64 else 'float32'}, 1-min load " \
        f"{min(x[0] for x in loads):.1f}-{max(x[0] for x in loads):.1f}"
    print(f"{title}\n")
    print("| entry | first result [s] | programs | compile [s] | second call [s] | its programs | first / diffrax's |"
          " programs / diffrax's |\n|---|---|---|---|---|---|---|---|")
    for n, r in results.items():
        if "error" in r:
            print(f"| {n} | failed: {r['error'].strip().splitlines()[-1][:120]} | | | | | | |")
            continue
        ratio = r["first_s"] / peer["first_s"] if peer.get("first_s") else None
        pratio = r["programs"] / peer["programs"] if peer.get("programs") else None
        print(f"| {n} | {r['first_s']:.1f} | {r['programs']} | {r['compile_s']:.1f} | {_fmt(r.get('second_s'), '{:.2f}')}"
              f" | {r.get('second_programs', r.get('second_error', '-'))} | {_fmt(ratio, '{:.2f}x')} "
              f"| {_fmt(pratio, '{:.1f}x')} |")
    for r in results.values():
        if peer.get("first_s") and "first_s" in r:
            r["first_over_diffrax"] = r["first_s"] / peer["first_s"]
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True).stdout.strip()
    dirty = bool(subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--untracked-files=no"],
                                capture_output=True, text=True).stdout.strip())
    jax_version = next((r["jax"] for r in results.values() if "jax" in r), None)
    record = {"command": "python experiments/performance/cold_start.py " + " ".join(sys.argv[1:]),
              "smoke_test": a.quick, "head": head + ("+dirty" if dirty else ""),
              "machine": {"cpu": cpu_model(), "cores": os.cpu_count(), "arch": platform.machine(),
                          "python": platform.python_version(), "jax": jax_version,
                          "jax_backend": next((r["backend"] for r in results.values() if "backend" in r), None)},
              "dtype": "float64" if a.x64 else "float32", "compile_cache": not a.no_compile_cache,
              "load_average": loads, "entries": results}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(record, indent=1) + "\n")
    each = {n: r["second_each"] for n, r in results.items() if r.get("second_each")}
    if each:
        print("\nPrograms compiled by a call that changes one number (seconds in brackets):\n")
        print("| entry | " + " | ".join(KNOBS) + " |\n|---|" + "---|" * len(KNOBS))
        for n, e in each.items():
            print(f"| {n} | " + " | ".join(f"{e[k]['programs']} ({e[k]['s']:.2f})" if k in e else "-" for k in KNOBS)
                  + " |")
    print(f"\nwrote {a.out}", file=sys.stderr)


if __name__ == "__main__":
    main()
