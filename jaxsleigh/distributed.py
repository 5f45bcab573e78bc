"""Several processes (and hosts) share one chunked run through ``jax.distributed``.

The design needs no cross-process computation, only JAX's multi-controller runtime for what it is
good at: discovering the processes (``jax.distributed.initialize``, with automatic detection under
SLURM and Open MPI), its key-value store and its barriers. The work itself is divided through the
chunk checkpoint folder that `jaxsleigh.ensemble.run_ensemble` already writes (every chunk
atomically, tagged with the run's fingerprint):

1. every process checks its input and the output paths; the verdicts are exchanged, so that a bad
   option or a stale checkpoint folder (without ``--resume``) is refused by *every* process
   before *any* process writes;
2. every process computes the chunks ``i`` with ``i % count == index`` that the folder does not
   hold yet (``shard=(index, count)``, ``resume=True``) on its own devices and writes them;
3. after a barrier, process 0 assembles the result from the chunks (``resume=True``, no
   ``shard``) and writes the output: the same file, byte for byte, as a single-process run,
   because the chunks and their order do not depend on who computed them;
4. process 0 tells the others its exit code, and every process returns it.

A process that dies takes its unfinished chunk with it (JAX's runtime then stops the others after
its heartbeat timeout, by default 100 s; what they finished is on disk). ``--resume``, by any number
of processes, recomputes exactly the chunks that are missing.

`start` initialises the runtime (or returns ``None`` for a plain single-process run) and
`run_shared` runs steps 1-4; the command line wraps both in
`jaxsleigh.cli.common.run_distributed`.
"""
from __future__ import annotations

import json
import os
import re
import sys
from pathlib import Path
from typing import Any, Callable, Optional

__all__ = ["Cluster", "start", "cluster_env", "parse_coordinator", "run_shared", "CHECK_TIMEOUT_S",
           "WORK_TIMEOUT_S"]

#: How long a process waits for the others to finish checking their input (seconds).
CHECK_TIMEOUT_S = 600
#: How long a process waits for the others to finish their share of the chunks (seconds; the
#: runtime's heartbeat stops everyone much earlier if a process dies). Under the 2^31 ms that the
#: runtime accepts.
WORK_TIMEOUT_S = 20 * 24 * 3600

_PREFIX = "jaxsleigh"


def parse_coordinator(text: str) -> str:
    """``HOST:PORT`` (``[v6addr]:PORT`` for IPv6), checked; returns it unchanged."""
    m = re.fullmatch(r"(\[[0-9A-Fa-f:.]+\]|[^\s:\[\]]+):(\d+)", str(text).strip())
    if m is None:
        raise ValueError(f"--coordinator must be HOST:PORT (the address of process 0 and a free port), got "
                         f"{text!r} (e.g. --coordinator 10.0.0.1:12345 or --coordinator 127.0.0.1:12345)")
    port = int(m.group(2))
    if not 1 <= port <= 65535:
        raise ValueError(f"--coordinator {text!r}: the port must be 1..65535, got {port}")
    return str(text).strip()


def cluster_env() -> Optional[str]:
    """``"slurm"`` or ``"ompi"`` when this process is one of several tasks that SLURM (``srun``) or
    Open MPI (``mpirun``) started, so that JAX can detect the cluster itself; else ``None``.

    A single task (``SLURM_NTASKS=1``, a plain ``sbatch`` script, ``salloc`` shells) is not a
    cluster: the run stays single-process.
    """
    env = os.environ

    def many(var):
        try:
            return int(env.get(var, "1")) > 1
        except ValueError:
            return False

    if all(v in env for v in ("SLURM_JOB_ID", "SLURM_STEP_NODELIST", "SLURM_NTASKS", "SLURM_PROCID",
                              "SLURM_LOCALID")) and many("SLURM_NTASKS"):
        return "slurm"
    if "OMPI_MCA_orte_hnp_uri" in env and many("OMPI_COMM_WORLD_SIZE"):
        return "ompi"
    return None


class Cluster:
    """The processes of one run: this one's ``index`` among ``count``; barriers and a small
    key-value exchange through JAX's distributed runtime (no device computation)."""

    def __init__(self, client, index: int, count: int):
        self.client = client
        self.index = int(index)
        self.count = int(count)
        self._n = 0

    @property
    def main(self) -> bool:
        """Process 0: the one that assembles and writes the output."""
        return self.index == 0

    def _name(self, what: str) -> str:
        self._n += 1
        return f"{_PREFIX}/{self._n}/{what}"

    def barrier(self, what: str, timeout_s: float = CHECK_TIMEOUT_S) -> None:
        """Wait until every process has reached the same barrier."""
        name = self._name(what)
        try:
            self.client.wait_at_barrier(name, int(timeout_s * 1000))
        except Exception as e:  # JaxRuntimeError: timeout or a process failed
            raise RuntimeError(f"process {self.index} of {self.count}: not every process reached '{what}' "
                               f"within {timeout_s:g} s ({str(e).splitlines()[0]})") from None

    def gather(self, what: str, value: Any, timeout_s: float = CHECK_TIMEOUT_S) -> list:
        """Every process's ``value`` (JSON), in process order; a barrier."""
        name = self._name(what)
        self.client.key_value_set(f"{name}/{self.index}", json.dumps(value))
        try:
            self.client.wait_at_barrier(name + "/barrier", int(timeout_s * 1000))
        except Exception as e:
            raise RuntimeError(f"process {self.index} of {self.count}: not every process reached '{what}' "
                               f"within {timeout_s:g} s ({str(e).splitlines()[0]})") from None
        got = dict(self.client.key_value_dir_get(name + "/"))
        return [json.loads(got[f"{name}/{i}"]) for i in range(self.count)]

    def agree(self, what: str, error: Optional[str], **facts) -> None:
        """Exchange verdicts: raise ``ValueError`` in *every* process if any process had an
        ``error`` or if the processes' ``facts`` (e.g. their options) differ."""
        got = self.gather(what, {"error": error, **facts})
        bad = [(i, g["error"]) for i, g in enumerate(got) if g["error"]]
        if bad:
            i, msg = bad[0]
            more = f" (and {len(bad) - 1} more process(es))" if len(bad) > 1 else ""
            raise ValueError(msg if i == self.index else f"process {i} of {self.count}{more}: {msg}")
        for key in facts:
            seen = {json.dumps(g[key], sort_keys=True) for g in got}
            if len(seen) > 1:
                which = [i for i, g in enumerate(got) if g[key] != got[0][key]]
                raise ValueError(f"the {self.count} processes were given different {key.replace('_', ' ')}: "
                                 f"process 0 has {got[0][key]!r}, process {which[0]} {got[which[0]][key]!r}; "
                                 f"start every process with the same command (only the process id differs)")

    def share(self, what: str, value: Any = None, timeout_s: float = WORK_TIMEOUT_S) -> Any:
        """Process 0's ``value``, in every process (JSON)."""
        name = self._name(what)
        if self.main:
            self.client.key_value_set(name, json.dumps(value))
            return value
        return json.loads(self.client.blocking_key_value_get(name, int(timeout_s * 1000)))


def start(coordinator: Optional[str] = None, num_processes: Optional[int] = None,
          process_id: Optional[int] = None, *, timeout_s: int = 300) -> Optional[Cluster]:
    """Join the processes of a multi-process run: ``jax.distributed.initialize``.

    Give all three of ``coordinator`` (``HOST:PORT`` of process 0), ``num_processes`` and
    ``process_id``, or none: then the cluster is detected under SLURM / Open MPI
    (`cluster_env`), and without one the run is single-process and ``None`` is returned.
    Must be called before any JAX computation in this process. ``ValueError`` for bad arguments.
    """
    given = [v is not None for v in (coordinator, num_processes, process_id)]
    if any(given) and not all(given):
        missing = [f for f, g in zip(("--coordinator", "--num-processes", "--process-id"), given) if not g]
        raise ValueError(f"--coordinator, --num-processes and --process-id go together: give all three (e.g. "
                         f"--coordinator 127.0.0.1:12345 --num-processes 2 --process-id 0) or none (under SLURM "
                         f"or Open MPI the cluster is detected); missing {', '.join(missing)}")
    import jax

    if all(given):
        coordinator = parse_coordinator(coordinator)
        n, i = int(num_processes), int(process_id)
        if n < 1:
            raise ValueError(f"--num-processes must be >= 1, got {n}")
        if not 0 <= i < n:
            raise ValueError(f"--process-id must be 0..{n - 1} (one per process, 0 runs the coordinator), got {i}")
        kw = dict(coordinator_address=coordinator, num_processes=n, process_id=i)
    elif cluster_env() is not None:
        kw = {}
    else:
        return None
    from jax._src import distributed as _dist

    if _dist.global_state.client is None:
        try:
            jax.distributed.initialize(initialization_timeout=int(timeout_s), **kw)
        except RuntimeError as e:
            raise ValueError(f"could not join the other processes ({str(e).splitlines()[0]}); start every "
                             f"process with the same --coordinator and --num-processes within "
                             f"{int(timeout_s)} s of each other") from None
    client = _dist.global_state.client
    if client is None or not hasattr(client, "wait_at_barrier"):  # pragma: no cover - other JAX versions
        raise RuntimeError("this JAX version's distributed runtime has no barrier (client.wait_at_barrier); "
                           "jaxsleigh was tested with jax 0.10")
    return Cluster(client, jax.process_index(), jax.process_count())


def _marker(folder: Path, index: int) -> Path:
    return Path(folder) / f".jaxsleigh-process-{index}"


def run_shared(cluster: Cluster, *, check: Callable[[], Any], compute: Callable[[Any, tuple], None],
               assemble: Callable[[Any], int], prepare: Optional[Callable[[Any], None]] = None,
               shared_dirs: Callable[[Any], list] = lambda state: [], options: Any = None) -> int:
    """Run one command in every process of ``cluster``; returns the exit code of process 0.

    Args:
      check: validates the input and the outputs, refusing a stale checkpoint folder (no writes
        besides creating folders); returns the command's state, raises ``ValueError``.
      prepare: run by process 0 after every process has passed ``check`` and before anyone
        computes (e.g. remove a stale manifest of a fresh run).
      compute: ``compute(state, (index, count))`` writes this process's share of the chunks
        (``resume=True``, since other processes write into the same folder meanwhile).
      assemble: run by process 0 after everyone has computed: reads the chunks (computing any
        that are missing), writes the outputs, returns the exit code.
      shared_dirs: the checkpoint folders of ``state``: each process leaves a marker there, so that
        process 0 can tell when a folder is not shared (then it computes the missing chunks itself,
        with a warning).
      options: what must be equal in every process (the command's options): a difference is refused.

    Every process raises the same ``ValueError`` when any process's ``check`` or ``compute`` failed.
    """
    import jax

    state, error = None, None
    try:
        state = check()
    except (ValueError, OSError) as e:
        error = str(e)
    devices = f"{jax.default_backend()} x {len(jax.local_devices())}"
    cluster.agree("checked", error, options=options, local_devices=devices)
    if cluster.main and prepare is not None:
        prepare(state)
    cluster.barrier("prepared")
    error = None
    try:
        for d in shared_dirs(state):
            Path(d).mkdir(parents=True, exist_ok=True)
            _marker(d, cluster.index).write_text(f"{os.uname().nodename} {os.getpid()}\n")
        compute(state, (cluster.index, cluster.count))
    except (ValueError, OSError) as e:
        error = f"{type(e).__name__}: {e}" if isinstance(e, OSError) else str(e)
    cluster.agree("computed", error)
    code = None
    if cluster.main:
        try:
            for d in shared_dirs(state):
                missing = [i for i in range(cluster.count) if not _marker(d, i).exists()]
                if missing:
                    print(f"jaxsleigh: warning: {str(d)!r} is not shared with process(es) "
                          f"{', '.join(map(str, missing))} (their marker is missing): process 0 computes their "
                          f"chunks itself; put the checkpoint folder on a filesystem every process sees",
                          file=sys.stderr)
                for i in range(cluster.count):
                    _marker(d, i).unlink(missing_ok=True)
            code = int(assemble(state))
        except (ValueError, OSError) as e:
            cluster.share("result", {"code": None, "error": str(e)})
            raise
        except BaseException:
            cluster.share("result", {"code": 1, "error": "process 0 failed while writing the output"})
            raise
        cluster.share("result", {"code": code, "error": None})
        return code
    got = cluster.share("result")
    if got["error"]:
        raise ValueError(f"process 0 of {cluster.count}: {got['error']}")
    return int(got["code"])
