"""Every core of the machine: one JAX CPU device per core, and batches split over them.

XLA:CPU runs one program on one core (apart from the threads it splits a whole-batch loop over).
jaxsleigh therefore asks JAX for one CPU device per core this process may use
(``len(os.sched_getaffinity(0))``) when its first run begins (`configure`; ``import jaxsleigh`` changes
no JAX setting), and only if JAX has not started yet; its studies cut every chunk of starts into parts that
run concurrently, one thread per device, each part on its own device (`run_parts`). The parts are the same
whatever the number of cores (`PART_SIZE` starts each), and a lane's arithmetic does not depend on the other
lanes of its part; the parts' few stiff stragglers are gathered into one batch per chunk in the parts'
order. Results are therefore **byte-identical whatever the number of cores**, a one-core run included.
(On an accelerator each chunk is cut into one part per device instead: large batches are what a GPU is
for.) A result's ``run_info["devices"]`` names the devices its run used.

Settings, in order of precedence:

* ``JAXSLEIGH_CORES=N`` (environment): use at most ``N`` cores; ``1`` is the one-core run.
* a device count the program chose itself (``JAX_NUM_CPU_DEVICES``, ``jax_num_cpu_devices`` or
  ``XLA_FLAGS=--xla_force_host_platform_device_count``) is left as it is;
* ``cores=`` in `jaxsleigh.RunOptions` (``--cores`` on the command line) limits one run.

When JAX had started before jaxsleigh's first run (a JAX operation of the program ran first), its CPU
device count can no longer change; jaxsleigh then says so once, with how to get every core.
"""
from __future__ import annotations

import os
import queue
import threading
import warnings
from typing import Callable, Optional, Sequence

import jax

__all__ = ["available_cores", "configure", "workers", "run_parts", "default_chunk_size", "PART_SIZE", "CPU_CHUNK",
           "ACCELERATOR_CHUNK"]

#: lanes per part: every chunk is cut into parts of this many starts (the last padded), whatever the
#: number of cores. XLA:CPU compiles a batch's loops differently for different batch sizes (it splits
#: large ones over its threads), and the rounding can follow; with one part size, every start meets the
#: same compiled program on any number of cores (tests/test_cores.py).
PART_SIZE = 1024

#: starts per chunk on CPU, for `run_ensemble`, basins and sweeps alike. Measured on the default basin of 10^5
#: starts (2 cores, float32, `experiments/performance/basin_tails.py`): 51-53 s with chunks of 16384 against 66-78 s with
#: 4096-8192 and 59-84 s with 65536-131072 (each chunk's tail batch finishes its few stiff stragglers on one core
#: behind the next chunk's parts); on the benchmark's tame starts 65536 and 16384 ran alike (scratch).
CPU_CHUNK = 16384

#: starts per chunk and device on an accelerator. Measured on one NVIDIA H200 (jax 0.11.2, float32,
#: 10^6 starts of the benchmark workload over 100 s, `experiments/performance/bench_accelerator.sh`): the adaptive
#: default ran at 0.95e9, 3.7e9 and 4.1e9 equivalent trajectory-steps/s with chunks of 2^18, 2^20 and
#: 2^22 starts, and did not finish in 45 s with 2^16 (each chunk pays its stiff stragglers' few thousand
#: steps, one loop iteration at a time, whatever its size); fixed-step RK4 was the same from 2^20 up.
ACCELERATOR_CHUNK = 1 << 22

_state = {"configured": None, "warned": False}
_configure_lock = threading.Lock()


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):       # not on Linux
        return max(1, os.cpu_count() or 1)


def _env_limit() -> Optional[int]:
    raw = os.environ.get("JAXSLEIGH_CORES", "").strip()
    if not raw:
        return None
    try:
        n = int(raw)
    except ValueError:
        n = 0
    if n < 1:
        warnings.warn(f"JAXSLEIGH_CORES={raw!r} is not a whole number >= 1; it is ignored", stacklevel=3)
        return None
    return n


def _user_chose() -> bool:
    """Whether the program set JAX's CPU device count itself."""
    if os.environ.get("JAX_NUM_CPU_DEVICES", "").strip():
        return True
    if "xla_force_host_platform_device_count" in os.environ.get("XLA_FLAGS", ""):
        return True
    return jax.config.jax_num_cpu_devices != -1


def configure() -> Optional[int]:
    """Ask JAX for one CPU device per available core (at most ``JAXSLEIGH_CORES``), if JAX has not
    started yet and the program did not choose a count itself; the first call decides, later ones
    return its answer. Every run calls it before its first JAX operation, where it checks its starts
    (`jaxsleigh.integrate.engine.check_ics`) or its law (`jaxsleigh.model.controller.as_controller`), in
    `jaxsleigh.solve`, `workers` and `default_chunk_size`; the command line calls it when it starts;
    ``import jaxsleigh`` does not. Returns the count asked for (``None``: left as it was).

    JAX refuses the setting once it has started (``jax.config.update`` raises ``RuntimeError``; no
    private name of JAX is read to know it, and tests/test_cores.py fails if JAX ever accepts it): the
    count is then left as it is, and `workers` says so once."""
    with _configure_lock:
        if _state["configured"] is None:
            _state["configured"] = _ask_for_cores()
    return _state["configured"] or None


def _ask_for_cores() -> int:
    """`configure`'s request: the count set, or 0 where the program chose one or JAX had started."""
    if _user_chose():
        return 0
    n = min(available_cores(), _env_limit() or available_cores())
    try:
        jax.config.update("jax_num_cpu_devices", n)
    except RuntimeError:                       # JAX has started: its device count is fixed now
        return 0
    return n


def workers(devices: Optional[Sequence] = None, cores: Optional[int] = None) -> list:
    """The devices a run splits its batches over: ``devices`` if given, else every local device of
    JAX's default backend (on CPU, one per core), limited to ``cores`` and ``JAXSLEIGH_CORES``.
    On CPU with fewer devices than cores (JAX started before jaxsleigh's first run), warns once."""
    configure()                                # a run begins: before the first device is asked for
    if devices is not None:
        devs = list(devices)
        if not devs:
            raise ValueError("devices is empty; give at least one device (or None for every core)")
    else:
        devs = list(jax.local_devices())
        if jax.default_backend() == "cpu" and cores is None and _env_limit() is None:
            have = available_cores()
            if len(devs) < have and not _state["warned"] and not _user_chose():
                _state["warned"] = True
                warnings.warn(
                    f"JAX runs on {len(devs)} of this machine's {have} cores: it had started before jaxsleigh's "
                    f"first run, and its CPU device count is fixed once it starts. Run jaxsleigh before any other "
                    f"JAX operation, or set JAX_NUM_CPU_DEVICES={have} in the environment (or call "
                    f"jax.config.update('jax_num_cpu_devices', {have}) before JAX starts), to use every core.",
                    stacklevel=3)
    limit = min(x for x in (cores, _env_limit(), len(devs)) if x is not None)
    return devs[:max(1, limit)]


def default_chunk_size(cpu: int = CPU_CHUNK, devices: Optional[Sequence] = None) -> int:
    """Starts per chunk when the caller gives none: ``cpu`` on CPU (the cores split each chunk, so the
    chunks, and a checkpoint's files, do not depend on how many there are); on an accelerator
    `ACCELERATOR_CHUNK` per device (``devices``, default every local device)."""
    configure()                                # a run begins: before JAX is asked for its backend
    if jax.default_backend() == "cpu":
        return int(cpu)
    n_dev = len(jax.local_devices()) if devices is None else len(list(devices))
    return ACCELERATOR_CHUNK * max(1, n_dev)


def run_parts(fn: Callable, parts: Sequence, devices: Sequence) -> list:
    """``[fn(part) for part in parts]``, the parts run concurrently, one thread per device, each
    call under ``jax.default_device`` of the device that takes
    it (the next free one). With one device it is a plain loop on that device. The
    first exception is raised again (the other threads finish the part they hold and stop)."""
    parts = list(parts)
    if not parts:
        return []
    if len(devices) == 1 or len(parts) == 1:
        with jax.default_device(devices[0]):
            return [fn(p) for p in parts]
    todo: queue.Queue = queue.Queue()
    for i in range(len(parts)):
        todo.put(i)
    out: list = [None] * len(parts)
    errors: list = []

    def work(dev):
        with jax.default_device(dev):
            while not errors:
                try:
                    i = todo.get_nowait()
                except queue.Empty:
                    return
                try:
                    out[i] = fn(parts[i])
                except BaseException as e:      # noqa: BLE001 - raised again in the caller's thread
                    errors.append(e)

    threads = [threading.Thread(target=work, args=(d,), daemon=True) for d in devices[:len(parts)]]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if errors:
        raise errors[0]
    return out
