"""Shared fixtures of the jaxsleigh test suite.

* ``x64``: runs the test inside ``jax.enable_x64(True)`` (identity checks are done in float64).
* ``rng``: a NumPy generator with a fixed seed (every test is deterministic).
* ``sample_q`` / ``sample_w`` / ``sample_states`` / ``sample_gains``: random points away from the
  singular set ``theta = w1 = 0`` and random admissible gains.
* ``paper_args``: the paper's plant and gains (eq. 31-32) as a ``ClosedLoop``.

The suite sets JAX up as the command line does (``import jaxsleigh`` leaves that to the program): one CPU device
per core, and the persistent compilation cache (`jaxsleigh.enable_compilation_cache`), so that the tests reuse
what earlier runs compiled. The Python programs the tests start inherit the cache through JAX's own environment
variables (a program that calls `jaxsleigh.enable_compilation_cache` itself, or the command line, sets its own).

Tiers: ``python -m pytest -q`` runs every test (what CI runs); ``python -m pytest -q -m "not slow"`` is the quick
tier, for every change. A test is slow if it carries ``@pytest.mark.slow`` or is listed in ``tests/slow.txt``
(measured: ``python tests/tiers.py DURATIONS.txt`` rewrites that list from the output of a full run with
``--durations=0``).
"""
from __future__ import annotations

import gc
import os
from pathlib import Path

import jax
import numpy as np
import pytest

import jaxsleigh as js

SEED = 20240611

js.cores.configure()
_CACHE = js.enable_compilation_cache()
if _CACHE is not None:
    os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(_CACHE))
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "0")
    os.environ.setdefault("JAX_COMPILATION_CACHE_MAX_SIZE", str(js.cache.CACHE_MAX_BYTES))

#: tests measured slow (node ids without parameters: every case of a listed test is slow)
SLOW = frozenset(line.split("#")[0].strip() for line in (Path(__file__).parent / "slow.txt").read_text().splitlines()
                 if line.split("#")[0].strip())


def _memory_maps() -> int:
    """How many memory mappings this process holds (Linux's ``/proc/self/maps``; 0 where there is none)."""
    try:
        with open("/proc/self/maps", "rb") as f:
            return f.read().count(b"\n")
    except OSError:
        return 0


def _max_memory_maps() -> int:
    """The kernel's bound on one process's memory mappings (``vm.max_map_count``, 65,530 by default)."""
    try:
        return int(Path("/proc/sys/vm/max_map_count").read_text())
    except (OSError, ValueError):
        return 65530


#: drop JAX's compiled programs once a worker holds half the kernel's bound on mappings
_MAPS_LIMIT = _max_memory_maps() // 2


@pytest.fixture(autouse=True)
def _bounded_memory_maps():
    """Every program XLA compiles on the CPU keeps about three memory mappings until it is freed, and a test
    worker compiles thousands: past ``vm.max_map_count`` the next mapping fails and XLA dies of a segmentation
    fault (seen at 90-97% of cold full runs, while serialising a program for the persistent cache; the cost per
    program: ``python experiments/performance/memory_maps.py``). After a
    test that leaves a worker over half the bound, JAX's in-memory caches are dropped (later tests read their
    programs back from the persistent cache, or compile them again)."""
    yield
    if _memory_maps() > _MAPS_LIMIT:
        jax.clear_caches()
        gc.collect()


#: ``JAXSLEIGH_TEST_COMPILES=FILE``: every XLA program the test processes compile or read from the persistent cache,
#: as JSON lines of ``[test, program, seconds, from_cache]`` in ``FILE.<worker>``. JAX reports a program read from the
#: cache with the same duration event as a compiled one (its seconds then the load's), right after a cache-hit event
#: of the same thread: that is how the two are told apart.
_COMPILES_TO = os.environ.get("JAXSLEIGH_TEST_COMPILES")
_COMPILES: list = []
_CURRENT_TEST = ["(collection)"]

if _COMPILES_TO:
    import threading

    _HIT = threading.local()

    def _on_event(event, **kw):
        if event == "/jax/compilation_cache/cache_hits":
            _HIT.pending = True

    def _on_compile(event, duration, **kw):
        if event == "/jax/core/compile/backend_compile_duration":
            hit, _HIT.pending = getattr(_HIT, "pending", False), False
            _COMPILES.append((_CURRENT_TEST[0], str(kw.get("fun_name", "?")), round(float(duration), 3), hit))

    jax.monitoring.register_event_listener(_on_event)
    jax.monitoring.register_event_duration_secs_listener(_on_compile)


def pytest_runtest_logstart(nodeid, location):
    _CURRENT_TEST[0] = nodeid


def pytest_sessionfinish(session):
    if _COMPILES_TO:
        import json
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        with open(f"{_COMPILES_TO}.{worker}", "w") as f:
            f.writelines(json.dumps(row) + "\n" for row in _COMPILES)


def pytest_collection_modifyitems(config, items):
    """Mark the tests of `SLOW` slow, so that ``-m "not slow"`` leaves them out of the quick tier."""
    for item in items:
        if item.nodeid.split("[")[0] in SLOW:
            item.add_marker(pytest.mark.slow)


@pytest.fixture
def x64():
    """Compute in float64 for the duration of the test."""
    with jax.enable_x64(True):
        yield


@pytest.fixture
def rng():
    return np.random.default_rng(SEED)


def _signed_away_from_zero(rng, n, lo, hi):
    return rng.choice([-1.0, 1.0], size=n) * rng.uniform(lo, hi, size=n)


@pytest.fixture
def sample_q(rng):
    """``sample_q(n)`` -> (n, 3) configurations with ``0.2 <= |theta| <= 2.8``."""

    def make(n, theta_lo=0.2, theta_hi=2.8, scale=3.0):
        xy = rng.uniform(-scale, scale, size=(n, 2))
        th = _signed_away_from_zero(rng, n, theta_lo, theta_hi)
        return np.column_stack([xy, th])

    return make


@pytest.fixture
def sample_w(rng):
    """``sample_w(n)`` -> (n, 3) w-chart points with ``0.2 <= |w1| <= 2``."""

    def make(n, w1_lo=0.2, w1_hi=2.0, scale=3.0):
        w1 = _signed_away_from_zero(rng, n, w1_lo, w1_hi)
        return np.column_stack([w1, rng.uniform(-scale, scale, size=(n, 2))])

    return make


@pytest.fixture
def sample_states(sample_q, rng):
    """``sample_states(n)`` -> (n, 5) physical states ``(x, y, theta, p1, p2)``."""

    def make(n, p_scale=2.0, **kw):
        return np.column_stack([sample_q(n, **kw), rng.normal(scale=p_scale, size=(n, 2))])

    return make


@pytest.fixture
def sample_gains(rng):
    """``sample_gains()`` -> validated random gains: L > 0, k > 0, D_hat symmetric PD (non-diagonal)."""

    def make():
        L = rng.uniform(0.1, 5.0, size=3)
        k = rng.uniform(0.01, 2.0)
        A = rng.normal(size=(2, 2))
        D_hat = A @ A.T + rng.uniform(0.05, 3.0) * np.eye(2)
        return js.gains(L, k, D_hat)

    return make


@pytest.fixture
def paper_args():
    return js.ClosedLoop(js.paper_plant(), js.paper_gains())
