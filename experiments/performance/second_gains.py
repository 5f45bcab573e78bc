"""A second `run_ensemble` call with other gains: what it compiles, from a fresh process with an empty cache.

    XDG_CACHE_HOME=$(mktemp -d) python experiments/performance/second_gains.py [--n 2000] [--t-final 100]
                                                                                [--basin N] [--repeats 3] [--save F]

Calls `jaxsleigh.run_ensemble` on ``--n`` of the README's starts (x, y ~ U(-3, 3), theta0 ~ U(0.3, 3), at rest)
for ``--t-final`` seconds, first with the paper's gains, then with the README's other gains
(``L = (4, 1, 1.6), k = 0.2, D_hat = diag(4, 8)``), and prints per call its seconds, the XLA programs it compiled
(JAX's ``/jax/core/compile/backend_compile_duration`` events) and their seconds. With ``--basin N``, then times
the default basin (`jaxsleigh.run_basin` of ``jaxsleigh.sample_starts(N)``, its defaults) ``--repeats`` times,
warm, in the same process, and with ``--save`` writes its statuses, T_eps and final states to an ``.npz`` (to
compare two trees' bytes). ``--n 0`` skips the ensemble's calls.
"""
from __future__ import annotations

import argparse
import collections
import threading
import time

import numpy as np

EVENT = "/jax/core/compile/backend_compile_duration"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=2000)
    ap.add_argument("--t-final", type=float, default=100.0)
    ap.add_argument("--basin", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--save", default=None)
    a = ap.parse_args()

    import jax

    import jaxsleigh as js
    lock, events = threading.Lock(), []

    def on_duration(event, duration, **kw):
        if event == EVENT:
            with lock:
                events.append((str(kw.get("fun_name", "?")), float(duration)))

    jax.monitoring.register_event_duration_secs_listener(on_duration)
    js.enable_compilation_cache()
    starts = np.random.default_rng(0).uniform([-3, -3, 0.3], [3, 3, 3], (a.n, 3))
    quiet = js.RunOptions(progress=False)
    calls = [("paper gains", js.paper_gains()),
             ("README's other gains", js.gains(L=(4.0, 1.0, 1.6), k=0.2, D_hat=(4.0, 8.0)))] if a.n else []
    for name, g in calls:
        mark, t0 = len(events), time.perf_counter()
        r = js.run_ensemble(starts, gains=g, t_final=a.t_final, run=quiet)
        wall = time.perf_counter() - t0
        ev = events[mark:]
        names = collections.Counter(n for n, _ in ev)
        print(f"{name}: {wall:.2f} s, {len(ev)} programs compiled ({sum(s for _, s in ev):.2f} s): "
              f"{dict(names)}; "
              f"statuses {dict(zip(*np.unique(r.status, return_counts=True)))}", flush=True)
    if a.basin:
        ics = js.sample_starts(a.basin, seed=0)
        js.run_basin(ics, run=quiet)                                    # warm
        times = []
        for _ in range(a.repeats):
            t0 = time.perf_counter()
            b = js.run_basin(ics, run=quiet)
            times.append(time.perf_counter() - t0)
        print(f"basin of {a.basin}: warm {['%.2f' % t for t in times]} s; statuses "
              f"{dict(zip(*np.unique(b.status, return_counts=True)))}", flush=True)
        if a.save:
            np.savez(a.save, status=b.status, T_eps=b.T_eps, q_final=b.q_final, n_steps=b.n_steps)


if __name__ == "__main__":
    main()
