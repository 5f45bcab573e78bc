"""A second call with other numbers of the same shapes compiles nothing: the engine's batch shapes do not depend on
how fast the lanes settle (a part runs at its own size, its last lanes in the pool of stragglers' one size), counted
from JAX's own compile events."""
from __future__ import annotations

import threading

import jax
import numpy as np

import jaxsleigh as js

#: JAX's events for a program compiled, and for one found in the persistent compilation cache instead
COMPILED, CACHE_HIT = "/jax/core/compile/backend_compile_duration", "/jax/compilation_cache/cache_hits"


class _Programs:
    """Counts the programs compiled or read from the persistent cache while it is open (from any thread)."""

    def __init__(self, events=(COMPILED, CACHE_HIT)):
        self.events = events

    def __enter__(self):
        self.count, self._lock = 0, threading.Lock()
        jax.monitoring.register_event_duration_secs_listener(self._duration)
        jax.monitoring.register_event_listener(self._event)
        return self

    def __exit__(self, *exc):
        jax.monitoring.unregister_event_duration_listener(self._duration)
        jax.monitoring.unregister_event_listener(self._event)

    def _duration(self, event, duration, **kw):
        self._event(event)

    def _event(self, event, **kw):
        if event in self.events:
            with self._lock:
                self.count += 1


def test_an_ensemble_with_other_gains_compiles_nothing_more():
    """64 starts for 50 s: the paper's gains settle every lane within the first segment, the README's other gains
    leave a few lanes working for several (which the engine once compacted to batches of 16 and 8 lanes, shapes the
    first call never made). The second call compiles nothing and reads nothing from the cache."""
    starts = np.random.default_rng(0).uniform([-3, -3, 0.3], [3, 3, 3], (64, 3))
    run = js.RunOptions(progress=False, audit=False)
    jax.clear_caches()                       # what earlier tests compiled must not hide what the first call needs
    with _Programs() as first:
        a = js.run_ensemble(starts, gains=js.paper_gains(), t_final=50.0, run=run)
    with _Programs() as second:
        b = js.run_ensemble(starts, gains=js.gains(L=(4.0, 1.0, 1.6), k=0.2, D_hat=(4.0, 8.0)), t_final=50.0, run=run)
    assert first.count > 0                   # the count sees what a call compiles
    assert np.median(b.n_steps) > 1.5 * np.median(a.n_steps)    # the second gains do keep lanes working longer
    assert second.count == 0


def test_a_validation_compiles_only_the_programs_it_steps_with():
    """`jaxsleigh.tuning.validate` of 16 starts for 30 s: the float32 run and the audit's float64 reference of the same
    starts. Each run compiles its first state, step and summaries (chart change, H_d) at its batch size, the chart
    change of the starts once: 9 programs. The host's own work between segments compiles nothing (which lanes still
    step, read on the host; the states copied to the device without `jnp.asarray`, which compiled a copy per array
    shape: 19 programs before). Counted as programs compiled or loaded from the persistent cache (one compile event
    each, either way). The tuned preset's gains then compile one: the reference's step at 4 lanes, where its last
    stragglers were gathered (its batches are the rows' own, so its bits, and the audit's figures, hang on them)."""
    from jaxsleigh import tuning as tu

    held = tu.UniformStarts()(np.random.default_rng(4), 16)
    jax.clear_caches()
    with _Programs(events=(COMPILED,)) as first:
        v = tu.validate("paper", held, t_final=30.0, progress=False)
    with _Programs(events=(COMPILED,)) as second:
        w = tu.validate(js.load_gains("tuned"), held, t_final=30.0, progress=False)
    assert v.audit["rows"] == w.audit["rows"] == 16 and v.audit["passed"] and w.audit["passed"]
    assert 0 < first.count <= 9
    assert second.count <= 1
