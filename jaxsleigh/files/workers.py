"""A chunked run's chunks computed by the workers of a Dask cluster, one process (the driver) owning the run.

The chunks of a study never talk to each other: the run is a task map. Dask's distributed scheduler
(``pip install "jaxsleigh[cluster]"``) is made for that, and its fault handling is what the run relies on:

* the driver alone checks the input, claims the output (`jaxsleigh.files.runner.own_output`) and decides whether
  to resume: bad input is refused before any worker starts, and no two processes can disagree about options;
* it submits ``shares`` tasks, share ``k`` computing the chunks ``i`` with ``i % shares == k`` of the study
  (``shard=(k, shares)``) into the chunk folder, which every worker must see at the same path (a shared
  filesystem, or one host); JAX runs inside each worker, one thread each;
* a worker that dies (killed, crashed, its host down) is noticed by the scheduler, which runs its unfinished
  tasks again on the others; the rerun skips the chunks already written (``resume=True``), so only the dead
  worker's unfinished chunks are computed twice. The driver names the lost worker (address and pid) on stderr
  and in the run's record (``lost_workers``);
* the driver then assembles the output from the chunks, as one process does (a chunk that is still missing is
  computed there): the same file, byte for byte, on any number of workers. If everything dies, the chunks on
  disk are kept and ``--resume`` computes exactly the missing ones.

`Workers` says which cluster (a local one of ``count`` worker processes, or an existing scheduler's address), and
`compute_shares` runs the tasks.
"""
from __future__ import annotations

import logging
import os
import re
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

__all__ = ["Workers", "ClusterError", "compute_shares", "require_dask", "SHARES_PER_WORKER", "WORKERS_TIMEOUT_S",
           "EXIT_CLUSTER"]

#: Tasks submitted per worker: enough that a dead worker's tasks spread over the others and a slow one
#: holds up little, few enough that the study's set-up per task stays small.
SHARES_PER_WORKER = 4
#: How long the driver waits for a worker (at the start, or when every worker is gone), in seconds.
WORKERS_TIMEOUT_S = 120

#: Exit code of a run whose cluster failed (`ClusterError`).
EXIT_CLUSTER = 6

_INSTALL = 'pip install "jaxsleigh[cluster]"'


class ClusterError(RuntimeError):
    """The workers could not finish the run (none came, none is left, or a task killed several in turn); the
    message says which and what to do. The command line exits with `EXIT_CLUSTER`; the finished chunks are kept."""

    exit_code = EXIT_CLUSTER


def require_dask() -> None:
    """``ValueError`` saying what to install when Dask's distributed scheduler is missing."""
    try:
        import distributed  # noqa: F401
    except ImportError:
        raise ValueError(f"--workers and --scheduler run the chunks on Dask's distributed scheduler, which is not "
                         f"installed: {_INSTALL} (or pip install \"distributed>=2024.1\")") from None


@dataclass(frozen=True)
class Workers:
    """Where a run's chunks are computed: ``count`` worker processes on this machine (a local Dask cluster,
    started and stopped by the run), or the workers of the Dask scheduler at ``scheduler``
    (``tcp://HOST:PORT``, started with ``dask scheduler`` and ``dask worker``); one of the two.
    ``timeout_s``: how long to wait for a worker (at the start, or when none is left)."""

    count: Optional[int] = None
    scheduler: Optional[str] = None
    timeout_s: float = WORKERS_TIMEOUT_S

    def __post_init__(self):
        if (self.count is None) == (self.scheduler is None):
            raise ValueError("give --workers N (worker processes on this machine) or --scheduler ADDRESS (an "
                             "existing Dask cluster), not both")
        if self.count is not None and (isinstance(self.count, bool) or not isinstance(self.count, int)
                                       or not 1 <= self.count <= 4096):
            raise ValueError(f"--workers must be a whole number 1..4096 (e.g. --workers 4), got {self.count!r}")
        if self.scheduler is not None and not re.fullmatch(r"(tcp|tls|inproc|ucx|ws|wss)://\S+:\d+",
                                                           str(self.scheduler)):
            raise ValueError(f"--scheduler must be a Dask scheduler's address PROTOCOL://HOST:PORT (e.g. "
                             f"--scheduler tcp://10.0.0.1:8786), got {self.scheduler!r}")
        if not (isinstance(self.timeout_s, (int, float)) and 0 < self.timeout_s <= 86400):
            raise ValueError(f"--cluster-timeout must be a number of seconds in (0, 86400], got {self.timeout_s!r}")

    def describe(self) -> str:
        """``'4 local worker(s)'`` or ``'the Dask cluster at tcp://...'``, for messages."""
        return f"{self.count} local worker(s)" if self.scheduler is None else f"the Dask cluster at {self.scheduler}"


def _say(msg: str) -> None:
    print(f"jaxsleigh: {msg}", file=sys.stderr, flush=True)


def _share(study: Callable, out: str, chunks: str, run_id: str, shard: tuple) -> int:
    """One task, in a worker: compute the chunks of ``shard`` into ``chunks`` under the run's lock (shared with the
    driver and the other workers: the same fingerprint ``run_id``); returns the worker's pid."""
    from .run import Run

    with Run(out, run_id, resume=True, covers=(chunks,), shared=True):
        study(checkpoint_dir=Path(chunks), resume=True, shard=tuple(shard))
    return os.getpid()


def _held(value):
    """A task that returns its argument: the study is sent once and fetched by each share (and made again by the
    scheduler if the worker that held it dies)."""
    return value


def _check_sendable(study: Callable) -> None:
    """``ValueError`` before any worker starts when ``study`` cannot be sent to them (Dask pickles it with
    cloudpickle: a closure over an open file, a lock or a generator cannot be)."""
    import cloudpickle

    try:
        cloudpickle.dumps(study)
    except Exception as e:
        raise ValueError(f"the study cannot be sent to the workers ({type(e).__name__}: {e}); give run_to_file a "
                         f"study that pickles (plain data, functions and arrays), or run it without workers") from None


def _start(workers: Workers):
    """``(client, local cluster or None)``: a local cluster of ``workers.count`` processes (one thread each), or a
    client of the scheduler; `ClusterError` if none comes within ``timeout_s``."""
    require_dask()
    from distributed import Client, LocalCluster

    t0 = time.perf_counter()
    local = None
    try:
        if workers.scheduler is None:
            local = LocalCluster(n_workers=workers.count, processes=True, threads_per_worker=1, memory_limit=0,
                                 dashboard_address=None, silence_logs=logging.CRITICAL)
            client = Client(local, timeout=workers.timeout_s)
        else:
            client = Client(workers.scheduler, timeout=workers.timeout_s)
        client.wait_for_workers(1, timeout=workers.timeout_s)
    except (OSError, TimeoutError) as e:
        if local is not None:
            local.close()
        raise ClusterError(f"no Dask worker at {workers.describe()} within {workers.timeout_s:g} s "
                           f"({str(e).splitlines()[0] if str(e) else type(e).__name__}); start the scheduler and its "
                           f"workers (dask scheduler; dask worker ADDRESS) or give them more time with "
                           f"--cluster-timeout; nothing was computed") from None
    _say(f"{workers.describe()} ready in {time.perf_counter() - t0:.1f} s")
    return client, local


def _pids(client, addresses) -> dict:
    """``address -> 'address (pid N)'`` for the workers at ``addresses`` (those that answer)."""
    try:
        got = client.run(os.getpid, workers=list(addresses), on_error="ignore")
    except Exception:                      # a worker that left meanwhile: named by its address alone
        got = {}
    return {a: f"{a} (pid {got[a]})" if a in got else a for a in addresses}


def compute_shares(workers: Workers, study: Callable, *, out, chunks, run_id: str) -> list:
    """Compute every chunk of ``study`` on ``workers`` (module docstring); returns the lost workers' names.

    ``study(checkpoint_dir=, resume=True, shard=(k, shares))`` writes share ``k``'s chunks into ``chunks``;
    ``run_id``: the fingerprint of the run's lock, which the workers share. A task's error (a ``ValueError``,
    a full disk) is raised here as it was raised there; `ClusterError` when no worker is left for ``timeout_s``
    or a task killed several workers in turn. The finished chunks stay either way.
    """
    _check_sendable(study)
    client, local = _start(workers)
    try:
        return _run(client, workers, study, out=str(out), chunks=str(chunks), run_id=run_id)
    finally:
        client.close()
        if local is not None:
            local.close()


def _run(client, workers: Workers, study: Callable, *, out: str, chunks: str, run_id: str) -> list:
    from distributed import KilledWorker

    known = _pids(client, client.scheduler_info(n_workers=-1)["workers"])
    shares = SHARES_PER_WORKER * len(known)
    _say(f"{len(known)} worker(s): {', '.join(known.values())}; {shares} tasks")
    held = client.submit(_held, study, pure=False)
    tasks = [client.submit(_share, held, out, chunks, run_id, (k, shares), pure=False, retries=0)
             for k in range(shares)]
    lost: list = []
    alone_since = None
    while not all(t.done() for t in tasks):
        time.sleep(0.5)
        now = set(client.scheduler_info(n_workers=-1)["workers"])
        for a in [a for a in known if a not in now and known[a] not in lost]:
            lost.append(known[a])
            _say(f"warning: worker {known[a]} was lost (killed, crashed or its host is down); the other workers "
                 f"finish its chunks")
        known.update(_pids(client, [a for a in now if a not in known]))
        if now:
            alone_since = None
        elif alone_since is None:
            alone_since = time.monotonic()
        elif time.monotonic() - alone_since > workers.timeout_s:
            raise ClusterError(f"no Dask worker left for {workers.timeout_s:g} s (lost: {', '.join(lost) or '?'}); "
                               f"the finished chunks are kept: run the same command with --resume")
    try:
        client.gather(tasks)
    except KilledWorker as e:
        raise ClusterError(f"a task killed {len(lost) or 'several'} worker(s) in turn ({e}); the finished chunks "
                           f"are kept: run the same command with --resume") from None
    return lost
