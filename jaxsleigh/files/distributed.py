"""Several processes (and hosts) share one chunked run through ``jax.distributed``.

The design needs no cross-process computation, only JAX's multi-controller runtime for what it is
good at: discovering the processes (``jax.distributed.initialize``, with automatic detection under
SLURM and Open MPI), its key-value store and its barriers. The work itself is divided through the
chunk checkpoint folder that `jaxsleigh.studies.ensemble.run_ensemble` already writes (every chunk
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

Nothing hangs silently. Every process says what it waits for (the coordinator, the others) and
for how long (``--cluster-timeout``); process 0 checks that the coordinator's port is free and binds
the given address. Every process leaves a sign of life in the key-value store every second, and
the waits watch them instead of JAX's heartbeat (whose failure aborts the process): a process
silent for ``--cluster-timeout`` seconds is declared dead. A peer that dies while the chunks are
computed is named, process 0 computes its missing chunks and writes the output; a failure before
that, or of process 0 itself, stops every process with a `ClusterError` (exit code 6, the finished
chunks are kept: ``--resume`` recomputes exactly the missing ones, with any number of processes).
Where JAX's runtime still aborts a process (process 0's coordinator gone, the processes not all
joined in time), a ``SIGABRT`` handler prints what this process was waiting for and exits with 4.

`start` initialises the runtime (or returns ``None`` for a plain single-process run) and
`run_shared` runs steps 1-4; the command line wraps both in
`jaxsleigh.files.runner.run_to_file`.
"""
from __future__ import annotations

import json
import os
import re
import signal
import socket
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable, Optional

import jax

__all__ = ["Cluster", "ClusterError", "start", "cluster_env", "parse_coordinator", "run_shared",
           "CHECK_TIMEOUT_S", "WORK_TIMEOUT_S", "CLUSTER_TIMEOUT_S", "EXIT_CLUSTER"]

#: How long a process waits for the others to finish checking their input (seconds).
CHECK_TIMEOUT_S = 600
#: How long a process waits for the others to finish their share of the chunks (seconds; the
#: runtime's heartbeat stops everyone much earlier if a process dies). Under the 2^31 ms that the
#: runtime accepts.
WORK_TIMEOUT_S = 20 * 24 * 3600

#: Default of ``--cluster-timeout``: how long a process waits for a peer that shows no sign of life
#: (the coordinator, the others joining, a silent process during the run), in seconds.
CLUSTER_TIMEOUT_S = 120
#: Exit code of a process whose cluster failed (a peer died or never came; see `ClusterError`).
EXIT_CLUSTER = 6
#: Seconds between two signs of life of a process.
HEARTBEAT_S = 1.0

_PREFIX = "jaxsleigh"


class ClusterError(RuntimeError):
    """The processes of a multi-process run could not work together (the coordinator never came,
    its port is in use, a peer died or never joined); the message says which and what to do. The
    command line exits with `EXIT_CLUSTER`; the finished chunks are kept."""


def _say(index, count, msg: str) -> None:
    """One progress line on stderr, at once (a waiting process is never silent)."""
    print(f"jaxsleigh: process {index} of {count}: {msg}", file=sys.stderr, flush=True)


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


def _flag_value(key: str, value) -> str:
    """``--seed 7``, ``--resume``, ``no --resume``: an option as the user typed it."""
    flag = "--" + key.replace("_", "-")
    if value is True:
        return flag
    if value is None or value is False:
        return f"no {flag}"
    return f"{flag} {value if isinstance(value, (str, int, float)) else json.dumps(value)}"


class Cluster:
    """The processes of one run: this one's ``index`` among ``count``; waits and a small key-value
    exchange through JAX's distributed runtime (no device computation), watching the others' signs
    of life: a process silent for ``silent_s`` seconds is declared dead (`ClusterError`)."""

    def __init__(self, client, index: int, count: int, silent_s: float = CLUSTER_TIMEOUT_S):
        self.client = client
        self.index = int(index)
        self.count = int(count)
        self.silent_s = float(silent_s)
        self.phase = "starting"          # what this process does now, for the abort handler's message
        self.lost: list = []             # peers declared dead (process 0 finished their share)
        self.synced = False              # every survivor has the result: leave without JAX's shutdown
        self._n = 0
        self._seen: dict = {}            # process -> (last sign of life, local time it changed)
        self._stop = threading.Event()

    @property
    def main(self) -> bool:
        """Process 0: the one that assembles and writes the output."""
        return self.index == 0

    def _name(self, what: str) -> str:
        self._n += 1
        return f"{_PREFIX}/{self._n}/{what}"

    def start_heartbeat(self) -> None:
        """Leave a sign of life every `HEARTBEAT_S` seconds (a daemon thread) until `stop`."""
        def beat():
            k = 0
            while not self._stop.is_set():
                try:
                    self.client.key_value_set(f"{_PREFIX}/alive/{self.index}", str(k), allow_overwrite=True)
                except Exception:  # the coordinator is gone: the waits (or JAX) say so
                    return
                k += 1
                self._stop.wait(HEARTBEAT_S)

        threading.Thread(target=beat, name="jaxsleigh-heartbeat", daemon=True).start()

    def stop(self) -> None:
        """Stop the heartbeat."""
        self._stop.set()

    def _dead(self, among) -> list:
        """The processes of ``among`` silent for more than ``silent_s`` seconds."""
        now = time.monotonic()
        try:
            alive = dict(self.client.key_value_dir_get(f"{_PREFIX}/alive/"))
        except Exception as e:
            raise ClusterError(f"process {self.index} of {self.count}: lost the coordinator (process 0) while "
                               f"{self.phase} ({str(e).splitlines()[0]})") from None
        dead = []
        for i in among:
            sign = alive.get(f"{_PREFIX}/alive/{i}")
            last = self._seen.get(i)
            if last is None or last[0] != sign:
                self._seen[i] = (sign, now)
            elif now - last[1] > self.silent_s:
                dead.append(i)
        return dead

    def _collect(self, name: str, among, *, allow_lost: bool = False) -> dict:
        """Wait until every process of ``among`` has set ``name/<index>``; returns index -> value.
        A process silent for ``silent_s`` raises `ClusterError` naming it, or with ``allow_lost`` is
        left out (and recorded in ``lost``)."""
        among = [i for i in among if i not in self.lost]
        while True:
            try:
                got = {int(k.rsplit("/", 1)[1]): v for k, v in self.client.key_value_dir_get(name + "/")}
            except Exception as e:  # JaxRuntimeError: the coordinator (process 0) is gone
                raise ClusterError(f"process {self.index} of {self.count}: lost the coordinator (process 0) while "
                                   f"{self.phase} ({str(e).splitlines()[0]}); the finished chunks are kept: run the "
                                   f"same command with --resume") from None
            missing = [i for i in among if i not in got]
            if not missing:
                return got
            dead = self._dead(missing)
            if dead:
                names = ", ".join(map(str, dead))
                if not allow_lost:
                    raise ClusterError(
                        f"process {names} of {self.count} stopped answering (no sign of life for "
                        f"{self.silent_s:g} s: killed, crashed or its host is down) while {self.phase}; the finished "
                        f"chunks are kept: run the same command with --resume (any number of processes)")
                self.lost += dead
                among = [i for i in among if i not in dead]
            time.sleep(0.05)

    def barrier(self, what: str, timeout_s: float = CHECK_TIMEOUT_S) -> None:
        """Wait until every process has reached the same barrier (`ClusterError` if one died)."""
        self.gather(what, None)

    def gather(self, what: str, value: Any, timeout_s: float = CHECK_TIMEOUT_S) -> list:
        """Every process's ``value`` (JSON), in process order; a barrier (`ClusterError` if a process
        died on the way)."""
        name = self._name(what)
        self.phase = f"waiting for the others at '{what}'"
        self.client.key_value_set(f"{name}/{self.index}", json.dumps(value))
        got = self._collect(name, range(self.count))
        return [json.loads(got[i]) for i in range(self.count)]

    def agree(self, what: str, error: Optional[str], *, exit_code: Optional[int] = None, **facts) -> None:
        """Exchange verdicts: raise `Refused` (a ``ValueError``) in *every* process if any process had an
        ``error`` (with its ``exit_code``, e.g. 5 for an output in use) or if the processes' ``facts`` (e.g.
        their options) differ; a difference is named (``--seed 0`` vs ``--seed 7``), not printed as whole
        dictionaries."""
        _refuse(self.gather(what, {"error": error, "exit_code": exit_code, **facts}), self.index, self.count, facts)

    def report(self, what: str, value: Any) -> Optional[list]:
        """Every process posts ``value``; process 0 waits for them and returns them in process order,
        ``None`` for a peer that died on the way (it is named in ``lost``); the others return ``None``
        at once (they wait for process 0 with `share`)."""
        name = self._name(what)
        self.client.key_value_set(f"{name}/{self.index}", json.dumps(value))
        if not self.main:
            return None
        self.phase = f"waiting for the others at '{what}'"
        got = self._collect(name, range(self.count), allow_lost=True)
        return [json.loads(got[i]) if i in got else None for i in range(self.count)]

    def share(self, what: str, value: Any = None, timeout_s: float = WORK_TIMEOUT_S) -> Any:
        """Process 0's ``value``, in every process (JSON); the others wait while process 0 lives."""
        name = self._name(what)
        if self.main:
            self.client.key_value_set(f"{name}/0", json.dumps(value))
            return value
        self.phase = "waiting for process 0 to write the output"
        return json.loads(self._collect(name, [0])[0])


class Refused(ValueError):
    """A run refused in every process (`Cluster.agree`); ``exit_code``: that of the first failing process's error
    where it had one (`jaxsleigh.cli.common.EXIT_CODES`: 5 for an output in use), else the usual 2."""

    def __init__(self, message: str, exit_code: Optional[int] = None):
        super().__init__(message)
        if exit_code is not None:
            self.exit_code = int(exit_code)


def _refuse(got: list, index: int, count: int, facts) -> None:
    """Raise the `Refused` of `Cluster.agree` for the verdicts ``got`` (one dict per process)."""
    bad = [(i, g["error"], g.get("exit_code")) for i, g in enumerate(got) if g and g.get("error")]
    if bad:
        i, msg, code = bad[0]
        more = f" (and {len(bad) - 1} more process(es))" if len(bad) > 1 else ""
        raise Refused(msg if i == index else f"process {i} of {count}{more}: {msg}", code)
    def same(x, y):  # as JSON: True and 1 differ
        return json.dumps(x, sort_keys=True) == json.dumps(y, sort_keys=True)

    for key in facts:
        j = next((i for i, g in enumerate(got) if not same(g[key], got[0][key])), None)
        if j is None:
            continue
        a, b = got[0][key], got[j][key]
        if isinstance(a, dict) and isinstance(b, dict):   # the options: name each one that differs
            diff = [k for k in sorted(set(a) | set(b)) if not same(a.get(k), b.get(k))]
            pairs = [f"{_flag_value(k, a.get(k))} vs {_flag_value(k, b.get(k))}" for k in diff]
            more = f" (and {len(pairs) - 1} more: {', '.join(pairs[1:])})" if len(pairs) > 1 else ""
            raise ValueError(f"the {count} processes were given different options: process 0 has "
                             f"{pairs[0].replace(' vs ', f', process {j} ')}{more}; start every process with the "
                             f"same command (only --process-id differs)")
        raise ValueError(f"the {count} processes have different {key.replace('_', ' ')}: process 0 has {a!r}, "
                         f"process {j} {b!r}")


def _host_port(coordinator: str) -> tuple:
    host, port = coordinator.rsplit(":", 1)
    return host.strip("[]"), int(port)


def _is_address(host: str) -> bool:
    """An IP address literal (or ``localhost``): the coordinator binds exactly that. A host name
    is not bound as such, since it may resolve differently on process 0's own host (e.g. Debian
    maps a machine's own name to 127.0.1.1): then the coordinator listens on every address."""
    if host == "localhost":
        return True
    for family in (socket.AF_INET, socket.AF_INET6):
        try:
            socket.inet_pton(family, host)
            return True
        except OSError:
            pass
    return False


def _check_port(coordinator: str) -> None:
    """Process 0: `ClusterError` if the coordinator's port cannot be bound on its host (in use,
    or the host is not this machine), before JAX tries and fails with an RPC error."""
    host, port = _host_port(coordinator)
    bind = host if _is_address(host) else ""
    try:
        infos = socket.getaddrinfo(bind or None, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except OSError as e:
        raise ClusterError(f"--coordinator {coordinator}: cannot resolve {host!r} ({e})") from None
    family, _, _, _, addr = infos[0]
    with socket.socket(family, socket.SOCK_STREAM) as s:
        # as the coordinator's gRPC server does: a port in TIME_WAIT after an earlier run is free
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(addr)
        except OSError as e:
            import errno

            if e.errno == errno.EADDRINUSE:
                raise ClusterError(f"--coordinator {coordinator}: port {port} is in use on {host} (another program, "
                                   f"or an earlier run still running); start every process with another free port"
                                   ) from None
            raise ClusterError(f"--coordinator {coordinator}: process 0 cannot listen on {host} port {port} ({e}); "
                               f"run process 0 on the host named in --coordinator") from None


def _wait_for_coordinator(coordinator: str, index: int, count: int, timeout_s: float) -> None:
    """Processes other than 0: wait until the coordinator's port accepts connections, so that a
    coordinator that never comes is reported here (`ClusterError`) instead of by JAX's abort."""
    host, port = _host_port(coordinator)
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with socket.create_connection((host, port), timeout=1.0):
                return
        except OSError:
            if time.monotonic() > deadline:
                raise ClusterError(
                    f"process {index} of {count}: no coordinator at {coordinator} after {timeout_s:g} s; start "
                    f"process 0 (--process-id 0) with the same --coordinator on that host, or give it more time "
                    f"with --cluster-timeout") from None
            time.sleep(0.2)


_ABORT = {"cluster": None, "handler": None}


def _install_abort_handler(cluster_info: dict) -> None:
    """JAX's distributed runtime aborts the process when the coordinator goes away or the
    processes do not all join in time (``LOG(FATAL)``, no Python exception). Catch ``SIGABRT``
    to say what this process was doing and exit with `EXIT_CLUSTER` instead of 134 (best effort:
    without ctypes or libc's ``signal`` the abort stays)."""
    import ctypes

    def on_abort(signum):
        c = _ABORT["cluster"]
        where = c.phase if c is not None else cluster_info["phase"]
        index, count = cluster_info["index"], cluster_info["count"]
        try:
            why = ("most likely process 0, which runs the coordinator, died; the finished chunks are kept: run "
                   "the same command with --resume" if c is not None else
                   "not every process joined in time: start them all with the same --coordinator and "
                   "--num-processes, or give them more time with --cluster-timeout; nothing was computed")
            print(f"jaxsleigh: error: process {index} of {count}: the cluster failed while {where}: JAX's "
                  f"distributed runtime stopped this process (its message is above; {why})",
                  file=sys.stderr, flush=True)
            sys.stdout.flush()
        finally:
            os._exit(EXIT_CLUSTER)

    try:
        kind = ctypes.CFUNCTYPE(None, ctypes.c_int)
        handler = kind(on_abort)
        libc = ctypes.CDLL(None)
        libc.signal.restype = ctypes.c_void_p
        libc.signal.argtypes = [ctypes.c_int, kind]
        libc.signal(signal.SIGABRT, handler)
        _ABORT["handler"] = handler          # keep the C callback alive
    except (OSError, AttributeError, TypeError):  # pragma: no cover - no libc signal()
        pass


def start(coordinator: Optional[str] = None, num_processes: Optional[int] = None,
          process_id: Optional[int] = None, *, timeout_s: float = CLUSTER_TIMEOUT_S) -> Optional[Cluster]:
    """Join the processes of a multi-process run: ``jax.distributed.initialize``.

    Give all three of ``coordinator`` (``HOST:PORT`` of process 0), ``num_processes`` and
    ``process_id``, or none: then the cluster is detected under SLURM / Open MPI
    (`cluster_env`), and without one the run is single-process and ``None`` is returned.
    Must be called before any JAX computation in this process. ``ValueError`` for bad arguments;
    `ClusterError` when the port is in use or the coordinator does not come within ``timeout_s``
    seconds (also how long a silent peer is given later, see `Cluster`). Says on stderr what it
    waits for.
    """
    given = [v is not None for v in (coordinator, num_processes, process_id)]
    _check_start_options(given, timeout_s)

    # JAX's own heartbeat would abort every process when one dies: make it never fire and watch
    # the signs of life ourselves (Cluster._dead), which can name the process and keep the others.
    kw = dict(heartbeat_timeout_seconds=WORK_TIMEOUT_S)
    if all(given):
        coordinator, n, i, given_kw = _given_cluster(coordinator, num_processes, process_id)
        kw.update(given_kw)
    elif cluster_env() is not None:
        n, i = None, None
    else:
        return None
    from ..jax_private import distributed_client

    if distributed_client() is None:
        _initialize(coordinator, n, i, timeout_s, kw)
    client = distributed_client()
    if client is None or not hasattr(client, "key_value_dir_get"):  # pragma: no cover - other JAX versions
        raise RuntimeError("this JAX version's distributed runtime has no key-value store (client.key_value_dir_get); "
                           "jaxsleigh was tested with jax 0.10")
    return _joined(Cluster(client, jax.process_index(), jax.process_count(), silent_s=timeout_s), timeout_s)


def _check_start_options(given: list, timeout_s) -> None:
    """``ValueError`` unless the three cluster options are all given or none (``given``: which are),
    and ``timeout_s`` is a number of seconds in range."""
    if any(given) and not all(given):
        missing = [f for f, g in zip(("--coordinator", "--num-processes", "--process-id"), given) if not g]
        raise ValueError(f"--coordinator, --num-processes and --process-id go together: give all three (e.g. "
                         f"--coordinator 127.0.0.1:12345 --num-processes 2 --process-id 0) or none (under SLURM "
                         f"or Open MPI the cluster is detected); missing {', '.join(missing)}")
    if not (isinstance(timeout_s, (int, float)) and 0 < timeout_s <= CHECK_TIMEOUT_S * 100):
        raise ValueError(f"--cluster-timeout must be a number of seconds in (0, {CHECK_TIMEOUT_S * 100}], "
                         f"got {timeout_s!r}")


def _given_cluster(coordinator: str, num_processes, process_id) -> tuple:
    """The cluster the user named: ``(coordinator, count, index, keywords of jax.distributed.initialize)``,
    checked (``ValueError``)."""
    coordinator = parse_coordinator(coordinator)
    n, i = int(num_processes), int(process_id)
    if n < 1:
        raise ValueError(f"--num-processes must be >= 1, got {n}")
    if not 0 <= i < n:
        raise ValueError(f"--process-id must be 0..{n - 1} (one per process, 0 runs the coordinator), got {i}")
    kw = {"coordinator_address": coordinator, "num_processes": n, "process_id": i}
    if _is_address(_host_port(coordinator)[0]):
        kw["coordinator_bind_address"] = coordinator      # not JAX's default [::]:PORT
    return coordinator, n, i, kw


def _initialize(coordinator: Optional[str], n: Optional[int], i: Optional[int], timeout_s: float, kw: dict) -> None:
    """Start JAX's distributed runtime for process ``i`` of ``n`` (``None``: detected by JAX), saying
    on stderr what it waits for, with the abort handler in place; `ClusterError` if it fails."""
    info = {"index": "?" if i is None else i, "count": "?" if n is None else n, "phase": ""}
    if coordinator is not None and i == 0:
        _check_port(coordinator)
        info["phase"] = f"waiting for the other {n - 1} process(es) to join (up to {timeout_s:g} s)"
        _say(i, n, f"starting the coordinator at {coordinator}; {info['phase']}")
    elif coordinator is not None:
        _say(i, n, f"waiting for the coordinator at {coordinator} (up to {timeout_s:g} s)")
        _wait_for_coordinator(coordinator, i, n, timeout_s)
        info["phase"] = f"waiting for all {n} processes to join (up to {timeout_s:g} s)"
    else:
        info["phase"] = f"joining the cluster detected by JAX (up to {timeout_s:g} s)"
    _install_abort_handler(info)
    try:
        jax.distributed.initialize(initialization_timeout=max(1, int(timeout_s)), **kw)
    except RuntimeError as e:
        raise ClusterError(f"could not join the other processes ({str(e).splitlines()[0]}); start every "
                           f"process with the same --coordinator and --num-processes within "
                           f"{timeout_s:g} s of each other (--cluster-timeout)") from None


def _joined(cluster: Cluster, timeout_s: float) -> Cluster:
    """``cluster`` is this process's now: the abort handler names its phase, its heartbeat starts,
    and it says so."""
    _ABORT["cluster"] = cluster
    cluster.phase = "starting the run"
    cluster.start_heartbeat()
    _say(cluster.index, cluster.count, "joined; a process silent for "
         f"{timeout_s:g} s is declared dead (--cluster-timeout)")
    return cluster


def _publish(cluster: Cluster, result: dict) -> None:
    """Process 0: share the run's ``result`` (and the dead peers) and wait until the others have
    read it: then every process leaves without JAX's shutdown barrier (``synced``), which would
    wait for a process that died after its share, then abort."""
    cluster.share("result", {**result, "lost": cluster.lost})
    cluster.phase = "waiting for the others to read the result"
    cluster.report("read", True)
    cluster.synced = True
    time.sleep(0.5)                   # the others leave right after saying so


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

    Every process raises the same ``ValueError`` when any process's ``check`` or ``compute`` failed,
    and `ClusterError` when a process dies before the chunks are computed. A process that dies
    while computing is named; process 0 computes its missing chunks in ``assemble`` (the dead
    processes are in ``cluster.lost`` in every survivor).
    """
    state = _check_everywhere(cluster, check, options)
    cluster.phase = "preparing the run"
    if cluster.main and prepare is not None:
        prepare(state)
    cluster.barrier("prepared")
    error = _compute_share(cluster, state, compute, shared_dirs)
    cluster.phase = "telling process 0 that its share is done"
    got = cluster.report("computed", {"error": error})
    if cluster.main:
        return _write_output(cluster, state, got, assemble, shared_dirs)
    return _read_result(cluster)


def _check_everywhere(cluster: Cluster, check: Callable[[], Any], options: Any) -> Any:
    """Step 1 of `run_shared`: ``check()`` here, then the verdicts, options and devices of every
    process exchanged (`Cluster.agree`); returns this process's state."""
    state, error, code = None, None, None
    try:
        state = check()
    except (ValueError, OSError) as e:
        error, code = str(e), getattr(e, "exit_code", None)
    try:  # the first use of the backend: it exchanges the processes' devices
        devices = f"{jax.default_backend()} x {len(jax.local_devices())}"
    except RuntimeError as e:
        raise ClusterError(f"process {cluster.index} of {cluster.count}: the processes could not exchange their "
                           f"devices ({str(e).splitlines()[0]}); nothing was computed") from None
    cluster.agree("checked", error, exit_code=code, options=options, local_devices=devices)
    return state


def _compute_share(cluster: Cluster, state: Any, compute: Callable[[Any, tuple], None],
                   shared_dirs: Callable[[Any], list]) -> Optional[str]:
    """Step 2 of `run_shared`: leave this process's marker in the shared folders and compute its share
    of the chunks; returns what failed (``None`` if nothing), for process 0."""
    cluster.phase = "computing its share of the chunks"
    try:
        for d in shared_dirs(state):
            Path(d).mkdir(parents=True, exist_ok=True)
            _marker(d, cluster.index).write_text(f"{os.uname().nodename} {os.getpid()}\n")
        compute(state, (cluster.index, cluster.count))
    except (ValueError, OSError) as e:
        return f"{type(e).__name__}: {e}" if isinstance(e, OSError) else str(e)
    return None


def _write_output(cluster: Cluster, state: Any, got: list, assemble: Callable[[Any], int],
                  shared_dirs: Callable[[Any], list]) -> int:
    """Step 3 of `run_shared`, process 0: refuse if a share failed (``got``: the reports of every
    process), else assemble and write the output; the result (or the failure) is published to the
    others either way. Returns the exit code."""
    try:
        _refuse([g or {} for g in got], cluster.index, cluster.count, {})
        if cluster.lost:
            names = ", ".join(map(str, cluster.lost))
            print(f"jaxsleigh: warning: process {names} of {cluster.count} stopped answering (no sign of life "
                  f"for {cluster.silent_s:g} s: killed, crashed or its host is down); process 0 computes its "
                  f"missing chunks and writes the output", file=sys.stderr, flush=True)
        cluster.phase = "writing the output"
        for d in shared_dirs(state):
            _collect_markers(cluster, d)
        code = int(assemble(state))
    except (ValueError, OSError) as e:         # the others say it too, with its exit code (4: disk full)
        _publish(cluster, {"code": getattr(e, "exit_code", None), "error": str(e)})
        raise
    except BaseException:
        _publish(cluster, {"code": None, "error": "process 0 failed while writing the output"})
        raise
    _publish(cluster, {"code": code, "error": None})
    return code


def _collect_markers(cluster: Cluster, folder) -> None:
    """Process 0: warn when a live process's marker is missing from ``folder`` (not shared with it:
    process 0 computes its chunks itself), then remove every marker."""
    missing = [i for i in range(cluster.count) if not _marker(folder, i).exists() and i not in cluster.lost]
    if missing:
        print(f"jaxsleigh: warning: {str(folder)!r} is not shared with process(es) "
              f"{', '.join(map(str, missing))} (their marker is missing): process 0 computes their "
              f"chunks itself; put the checkpoint folder on a filesystem every process sees",
              file=sys.stderr)
    for i in range(cluster.count):
        _marker(folder, i).unlink(missing_ok=True)


def _read_result(cluster: Cluster) -> int:
    """Step 4 of `run_shared`, processes other than 0: wait for process 0's result and return its exit
    code (its error raised here too, as `Refused` with its exit code); say which dead peers process 0 stood in
    for."""
    got = cluster.share("result")
    cluster.lost = list(got.get("lost") or [])
    cluster.report("read", True)
    cluster.synced = True
    if cluster.lost:
        _say(cluster.index, cluster.count, f"process {', '.join(map(str, cluster.lost))} stopped answering; "
                                           f"process 0 computed its missing chunks")
    if got["error"]:
        raise Refused(f"process 0 of {cluster.count}: {got['error']}", got.get("code"))
    return int(got["code"])
