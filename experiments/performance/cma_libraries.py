r"""The hand-written CMA-ES against well-kept libraries, at an equal budget of evaluations.

    python experiments/performance/cma_libraries.py [--seeds 10] [--out docs/figures/cma_libraries.json] [--quick]

Compared, with the same start, step size, population and number of objective evaluations:

* ``hand``: ``jaxsleigh.tuning.cmaes`` (``cma_init`` / ``cma_ask`` / ``cma_tell``; NumPy, Hansen's
  tutorial constants, positive recombination weights only, ``numpy.random.Generator`` per seed);
* ``cmaes``: the ``cmaes`` package (CyberAgent, pure NumPy, ``cmaes.CMA``; active CMA with negative
  weights; one ``ask()`` per candidate, ``tell`` with the population's (x, value) pairs; ``seed=``);
* ``evosax``: ``evosax.algorithms.CMA_ES`` (JAX, jitted ask / tell, float64 via ``jax_enable_x64``,
  a ``jax.random.key`` per seed), only when a Python with evosax is given (``--evosax-python`` or
  ``$EVOSAX_PYTHON``: a separate environment, e.g. ``python3 -m venv venv-evosax && venv-evosax/bin/pip install
  evosax==0.3.2``, since evosax pulls in flax, orbax-checkpoint and tensorstore). That part runs in a subprocess of that Python (this file with
  ``--worker-evosax``); if it is missing or fails, the JSON says why.

Objectives (minimised, dimensions 7 and 15, the sizes of the two gain families the library tunes):
sphere; ellipsoid \(\sum_i 10^{6 i/(n-1)} x_i^2\) (condition 1e6); Rosenbrock; Rastrigin; and
``median_step``, \(\operatorname{median}_j \lfloor 20\,|x-a_j|^2 \rfloor / 20\) over 64 fixed shifts
\(a_j \sim N(0, 0.25 I)\): a median of plateau (step) functions, like the median of hard convergence
times the library's search minimises. Start \(x_0 = 3\cdot\mathbf 1\), \(\sigma_0 \in \{0.3, 1.0\}\)
(0.3 is what the library's studies use), population 12, budgets of 120 and 600 evaluations (10 and 50
generations). None of the three takes the budget as an argument, so one run of 600 evaluations per
seed gives both budgets: the best value among its first 120 and among all 600 evaluations; the
determinism check confirms that a separate 120-evaluation run is exactly that prefix.

Recorded per (library, function, dim, budget, sigma0): median and 25th / 75th percentiles over the
seeds of the best value found, the values per seed, and the ask + tell wall time per generation
(median over generations and seeds, the objective excluded; evosax compiles its ask / tell in a
3-generation warm-up run per dimension before the timed runs, whose time is reported apart). Per
library: determinism (the same seed twice gives bit-identical candidates, and the 120-evaluation run
is the prefix of the 600 one) and checkpoint / resume (stop after 5 generations, serialise, restore
into a fresh object, go on: bit-identical to an uninterrupted run, and the largest difference of the
candidates). The hand-written one is saved as ``jaxsleigh.tuning.cma_search`` does (``np.savez`` of the
state's arrays and the generator's state); ``cmaes`` by ``pickle`` alone (which drops its
``RandomState``) and by ``pickle`` plus ``RandomState.get_state()``; evosax as NumPy copies of its
state's leaves and of its key.
Run it single-threaded (e.g. ``taskset -c 1``): the timings are of one core.
"""
from __future__ import annotations

import argparse
import io
import json
import math
import os
import pickle
import platform
import subprocess
import sys
import time
from importlib import metadata

import numpy as np

FUNCTIONS = ("sphere", "ellipsoid", "rosenbrock", "rastrigin", "median_step")
POPULATION = 12
X0_VALUE = 3.0


def _version(name):
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def _shifts(n):
    return np.random.default_rng(1000 + n).normal(0.0, 0.5, (64, n))


def objective(name, n):
    """A function of a (k, n) array of candidates returning (k,) values."""
    if name == "sphere":
        return lambda X: np.sum(X * X, axis=1)
    if name == "ellipsoid":
        c = 1e6 ** (np.arange(n) / (n - 1))
        return lambda X: (X * X) @ c
    if name == "rosenbrock":
        return lambda X: np.sum(100.0 * (X[:, 1:] - X[:, :-1] ** 2) ** 2 + (1.0 - X[:, :-1]) ** 2, axis=1)
    if name == "rastrigin":
        return lambda X: 10.0 * n + np.sum(X * X - 10.0 * np.cos(2 * np.pi * X), axis=1)
    if name == "median_step":
        a = _shifts(n)
        return lambda X: np.median(np.floor(20.0 * np.sum((X[:, None, :] - a[None]) ** 2, axis=2)) / 20.0, axis=1)
    raise ValueError(name)


# ----------------------------------------------------------------------------------------------------
# One run per library: returns all candidates (gens*pop, n), their values, ask+tell seconds per generation.

def run_hand(f, x0, sigma0, pop, gens, seed, resume_at=None):
    from jaxsleigh.tuning.cmaes import CMAState, cma_ask, cma_init, cma_tell
    rng = np.random.default_rng(seed)
    state = cma_init(x0, sigma0)
    xs_all, vals, dt = [], [], []
    for g in range(gens):
        if resume_at is not None and g == resume_at:
            # what jaxsleigh.tuning.cma_search checkpoints: the state's arrays and the generator's state
            buf = io.BytesIO()
            np.savez(buf, rng=np.array(json.dumps(rng.bit_generator.state)),
                     **{f"cma/{k}": np.asarray(v) for k, v in state._asdict().items()})
            buf.seek(0)
            with np.load(buf, allow_pickle=False) as z:
                state = CMAState(*(z[f"cma/{k}"] for k in CMAState._fields))
                rng = np.random.default_rng()
                rng.bit_generator.state = json.loads(str(z["rng"]))
        t0 = time.perf_counter()
        xs, ys = cma_ask(state, rng, pop)
        t1 = time.perf_counter()
        v = f(xs)
        t2 = time.perf_counter()
        state = cma_tell(state, ys, v)
        dt.append(time.perf_counter() - t2 + t1 - t0)
        xs_all.append(xs)
        vals.append(v)
    return np.concatenate(xs_all), np.concatenate(vals), np.array(dt)


def run_cmaes(f, x0, sigma0, pop, gens, seed, resume_at=None, resume_rng=True):
    from cmaes import CMA
    opt = CMA(mean=np.array(x0, dtype=float), sigma=sigma0, seed=seed, population_size=pop)
    xs_all, vals, dt = [], [], []
    for g in range(gens):
        if resume_at is not None and g == resume_at:
            blob = pickle.dumps(opt)
            rng_state = opt._rng.get_state()  # pickle drops the RandomState (see CMA.__getstate__)
            opt = pickle.loads(blob)
            if resume_rng:
                opt._rng.set_state(rng_state)
        t0 = time.perf_counter()
        xs = np.array([opt.ask() for _ in range(pop)])
        t1 = time.perf_counter()
        v = f(xs)
        t2 = time.perf_counter()
        opt.tell([(xs[i], float(v[i])) for i in range(pop)])
        dt.append(time.perf_counter() - t2 + t1 - t0)
        xs_all.append(xs)
        vals.append(v)
    return np.concatenate(xs_all), np.concatenate(vals), np.array(dt)


_EVOSAX = {}  # one CMA_ES object per (n, population): its jitted ask / tell compile once, not once per run


def run_evosax(f, x0, sigma0, pop, gens, seed, resume_at=None):
    import jax
    import jax.numpy as jnp
    from evosax.algorithms import CMA_ES
    n = len(x0)
    if (n, pop) not in _EVOSAX:
        _EVOSAX[n, pop] = CMA_ES(population_size=pop, solution=jnp.zeros(n))
    es = _EVOSAX[n, pop]
    params = es.default_params.replace(std_init=jnp.asarray(sigma0))
    key = jax.random.key(seed)
    key, k0 = jax.random.split(key)
    state = es.init(k0, jnp.asarray(x0, dtype=jnp.float64), params)
    xs_all, vals, dt = [], [], []
    for g in range(gens):
        if resume_at is not None and g == resume_at:
            leaves, tree = jax.tree.flatten(state)
            saved = [np.asarray(x) for x in leaves]
            key_data = np.asarray(jax.random.key_data(key))
            state = jax.tree.unflatten(tree, [jnp.asarray(x) for x in saved])
            key = jax.random.wrap_key_data(jnp.asarray(key_data))
        key, ka, kt = jax.random.split(key, 3)
        t0 = time.perf_counter()
        xs, state = es.ask(ka, state, params)
        xs = np.asarray(jax.block_until_ready(xs))
        t1 = time.perf_counter()
        v = f(xs)
        t2 = time.perf_counter()
        state, _ = es.tell(kt, jnp.asarray(xs), jnp.asarray(v), state, params)
        jax.block_until_ready(state)
        dt.append(time.perf_counter() - t2 + t1 - t0)
        xs_all.append(xs)
        vals.append(v)
    return np.concatenate(xs_all), np.concatenate(vals), np.array(dt)


RUNNERS = {"hand": run_hand, "cmaes": run_cmaes, "evosax": run_evosax}


def sweep(library, seeds, dims, sigmas, budgets, pop):
    """Raw results: per (function, dim, sigma0) the per-seed best at each budget and the timings."""
    run = RUNNERS[library]
    gens = max(budgets) // pop
    out, warmup = [], {}
    for n in dims:  # evosax compiles ask / tell in its first two generations (init state, then told state)
        t0 = time.perf_counter()
        run(objective("sphere", n), np.full(n, X0_VALUE), 0.3, pop, 3, 12345)
        warmup[n] = time.perf_counter() - t0
    for fname in FUNCTIONS:
        for n in dims:
            f = objective(fname, n)
            x0 = np.full(n, X0_VALUE)
            for s0 in sigmas:
                best = {b: [] for b in budgets}
                dts = {b: [] for b in budgets}
                first = []
                for seed in range(seeds):
                    xs, v, dt = run(f, x0, s0, pop, gens, seed)
                    first.append(float(dt[0]))
                    for b in budgets:
                        best[b].append(float(np.min(v[:b])))
                        dts[b].extend(dt[:b // pop].tolist())
                out.append({"function": fname, "dim": n, "sigma0": s0, "best": best, "dt": dts,
                            "first_generation_s_median": float(np.median(first)), "warmup_3_generations_s": warmup[n]})
    return out


def checks(library, dims, sigmas, budgets, pop):
    """Determinism (same seed twice; short run = prefix of the long one) and checkpoint / resume."""
    run = RUNNERS[library]
    gl, gs = max(budgets) // pop, min(budgets) // pop
    res = {"same_seed_identical": True, "short_run_is_prefix": True, "resume_identical": True,
           "resume_max_abs_diff_candidates": 0.0, "resume_cases_best_differs_rel_1e-9": 0, "cases": 0}
    if library == "cmaes":
        res["resume_plain_pickle_identical"] = True
        res["resume_plain_pickle_max_abs_diff_candidates"] = 0.0
    for fname in FUNCTIONS:
        for n in dims:
            f, x0 = objective(fname, n), np.full(n, X0_VALUE)
            for s0 in sigmas:
                seed = 0
                a = run(f, x0, s0, pop, gl, seed)
                b = run(f, x0, s0, pop, gl, seed)
                c = run(f, x0, s0, pop, gs, seed)
                r = run(f, x0, s0, pop, gl, seed, resume_at=min(5, gl - 1))
                res["cases"] += 1
                res["same_seed_identical"] &= bool(np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]))
                res["short_run_is_prefix"] &= bool(np.array_equal(a[0][:gs * pop], c[0]))
                res["resume_identical"] &= bool(np.array_equal(a[0], r[0]))
                res["resume_max_abs_diff_candidates"] = max(res["resume_max_abs_diff_candidates"],
                                                            float(np.max(np.abs(a[0] - r[0]))))
                res["resume_cases_best_differs_rel_1e-9"] += int(not np.isclose(np.min(a[1]), np.min(r[1]), rtol=1e-9, atol=0))
                if library == "cmaes":
                    p = run(f, x0, s0, pop, gl, seed, resume_at=min(5, gl - 1), resume_rng=False)
                    res["resume_plain_pickle_identical"] &= bool(np.array_equal(a[0], p[0]))
                    res["resume_plain_pickle_max_abs_diff_candidates"] = max(
                        res["resume_plain_pickle_max_abs_diff_candidates"], float(np.max(np.abs(a[0] - p[0]))))
    return res


def worker_evosax(cfg):
    import jax
    jax.config.update("jax_enable_x64", True)
    info = {"versions": {k: _version(k) for k in ("evosax", "jax", "jaxlib", "numpy", "optax", "flax")},
            "evosax_requires": metadata.requires("evosax"), "x64": True, "backend": jax.default_backend()}
    raw = sweep("evosax", cfg["seeds"], cfg["dims"], cfg["sigmas"], cfg["budgets"], cfg["pop"])
    chk = checks("evosax", cfg["dims"], cfg["sigmas"], cfg["budgets"], cfg["pop"])
    return {"info": info, "raw": raw, "checks": chk}


def summarise(library, raw, budgets, pop, seeds):
    rows = []
    for r in raw:
        for b in budgets:
            v = np.array(r["best"][b] if b in r["best"] else r["best"][str(b)])
            dt = np.array(r["dt"][b] if b in r["dt"] else r["dt"][str(b)])
            row = {"library": library, "function": r["function"], "dim": r["dim"], "budget": b,
                   "sigma0": r["sigma0"], "population": pop, "seeds": seeds,
                   "median": float(np.median(v)), "p25": float(np.percentile(v, 25)), "p75": float(np.percentile(v, 75)),
                   "best_per_seed": v.tolist(),
                   "ask_tell_s_per_generation_median": float(np.median(dt)),
                   "ask_tell_s_per_generation_mean": float(np.mean(dt))}
            if library == "evosax":
                row["warmup_3_generations_s_incl_compile"] = r["warmup_3_generations_s"]
            rows.append(row)
    return rows


def compare(rows, a="hand", b="cmaes"):
    """Per configuration: median ratio b/a and a two-sided Mann-Whitney p-value over seeds."""
    try:
        from scipy.stats import mannwhitneyu
    except ImportError:  # pragma: no cover
        mannwhitneyu = None
    idx = {(r["library"], r["function"], r["dim"], r["budget"], r["sigma0"]): r for r in rows}
    out, tally = [], {"b_better_p<0.05": 0, "a_better_p<0.05": 0, "no_significant_difference": 0}
    for (lib, fn, n, bud, s0), ra in idx.items():
        if lib != a or (b, fn, n, bud, s0) not in idx:
            continue
        rb = idx[(b, fn, n, bud, s0)]
        va, vb = np.array(ra["best_per_seed"]), np.array(rb["best_per_seed"])
        p = 1.0
        if mannwhitneyu is not None and not np.array_equal(np.sort(va), np.sort(vb)):
            p = float(mannwhitneyu(va, vb, alternative="two-sided").pvalue)
            p = 1.0 if math.isnan(p) else p
        ratio = rb["median"] / ra["median"] if ra["median"] > 0 else (1.0 if rb["median"] == ra["median"] else math.inf)
        if p < 0.05:
            tally["b_better_p<0.05" if rb["median"] < ra["median"] else "a_better_p<0.05"] += 1
        else:
            tally["no_significant_difference"] += 1
        out.append({"function": fn, "dim": n, "budget": bud, "sigma0": s0, "median_ratio": ratio, "mannwhitney_p": p})
    return {"a": a, "b": b, "per_config": out, "tally": tally}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/figures/cma_libraries.json")
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--quick", action="store_true", help="2 seeds, dimension 7, budgets 24 and 48")
    ap.add_argument("--evosax-python", default=os.environ.get("EVOSAX_PYTHON", ""),
                    help="a Python with evosax installed (default: $EVOSAX_PYTHON; none: evosax is skipped)")
    ap.add_argument("--worker-evosax", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.worker_evosax:
        json.dump(worker_evosax(json.loads(a.worker_evosax)), sys.stdout)
        return
    t_start = time.perf_counter()
    seeds = 2 if a.quick else a.seeds
    dims = [7] if a.quick else [7, 15]
    budgets = [24, 48] if a.quick else [120, 600]
    sigmas = [0.3, 1.0]
    cfg = {"seeds": seeds, "dims": dims, "sigmas": sigmas, "budgets": budgets, "pop": POPULATION}

    rows, chk, lib_times = [], {}, {}
    for lib in ("hand", "cmaes"):
        t0 = time.perf_counter()
        rows += summarise(lib, sweep(lib, seeds, dims, sigmas, budgets, POPULATION), budgets, POPULATION, seeds)
        chk[lib] = checks(lib, dims, sigmas, budgets, POPULATION)
        lib_times[lib] = time.perf_counter() - t0

    evosax = {"status": "not run"}
    if not a.evosax_python or not os.path.exists(a.evosax_python):
        evosax["status"] = f"not comparable: no Python with evosax at {a.evosax_python}"
    else:
        env = dict(os.environ, JAX_PLATFORMS="cpu", JAX_ENABLE_X64="1",
                   XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")
        t0 = time.perf_counter()
        p = subprocess.run([a.evosax_python, os.path.abspath(__file__), "--worker-evosax", json.dumps(cfg)],
                           env=env, capture_output=True, text=True)
        lib_times["evosax"] = time.perf_counter() - t0
        if p.returncode != 0:
            evosax["status"] = "not comparable: worker failed: " + p.stderr[-2000:]
        else:
            w = json.loads(p.stdout)
            rows += summarise("evosax", w["raw"], budgets, POPULATION, seeds)
            chk["evosax"] = w["checks"]
            evosax = {"status": "compared", **w["info"],
                      "same_core_versions_as_main_env": all(
                          w["info"]["versions"][k] == _version(k) for k in ("jax", "jaxlib", "numpy", "optax"))}

    comparisons = [compare(rows, "hand", "cmaes")]
    if evosax["status"] == "compared":
        comparisons.append(compare(rows, "hand", "evosax"))
    wall = time.perf_counter() - t_start
    doc = {
        "command": " ".join([os.path.basename(sys.executable)] + sys.argv),
        "description": __doc__.split("\n\n")[2].strip() if len(__doc__.split("\n\n")) > 2 else "",
        "machine": {"platform_machine": platform.machine(), "cpu_count": os.cpu_count(),
                    "affinity": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
                    "python": platform.python_version(),
                    "versions": {k: _version(k) for k in ("numpy", "cmaes", "jax", "jaxlib", "scipy")}},
        "settings": {"x0": f"{X0_VALUE} * ones(n)", "population": POPULATION, "budgets": budgets, "sigma0": sigmas,
                     "dims": dims, "seeds": seeds, "functions": list(FUNCTIONS),
                     "median_step": "median_j floor(20 |x - a_j|^2) / 20, a_j ~ N(0, 0.25 I), 64 shifts, rng seed 1000 + n"},
        "evosax": evosax,
        "checks": chk,
        "comparisons": comparisons,
        "results": rows,
        "wall_s_per_library": lib_times,
        "wall_s": wall,
    }
    os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
    with open(a.out, "w") as fh:
        json.dump(doc, fh, indent=1)

    libs = [l for l in ("hand", "cmaes", "evosax") if any(r["library"] == l for r in rows)]
    idx = {(r["library"], r["function"], r["dim"], r["budget"], r["sigma0"]): r for r in rows}
    print(f"{'function':<12}{'n':>3}{'s0':>5}{'evals':>6}" + "".join(f"{l + ' median [p25, p75]':>34}" for l in libs))
    for fn in FUNCTIONS:
        for n in dims:
            for s0 in sigmas:
                for b in budgets:
                    cells = "".join(
                        f"{'%.3g [%.3g, %.3g]' % (idx[(l, fn, n, b, s0)]['median'], idx[(l, fn, n, b, s0)]['p25'], idx[(l, fn, n, b, s0)]['p75']):>34}"
                        for l in libs)
                    print(f"{fn:<12}{n:>3}{s0:>5}{b:>6}{cells}")
    for l in libs:
        dts = [r["ask_tell_s_per_generation_median"] for r in rows if r["library"] == l]
        print(f"{l}: ask+tell per generation, median over configs {1e6 * float(np.median(dts)):.0f} us; checks {chk.get(l)}")
    for c in comparisons:
        print(f"{c['b']} vs {c['a']} (Mann-Whitney over seeds, per config): {c['tally']}")
    print(f"evosax: {evosax['status'][:200]}")
    print(f"wall {wall:.1f} s; wrote {a.out}")


if __name__ == "__main__":
    main()
