"""Runs own their output: one lock per process, which a killed process never leaves stale.

Each process that writes an output file or a checkpoint folder holds an exclusive ``fcntl.flock``
on its own lock file there (``.lock.<host>.<pid>`` in a folder, ``.<name>.lock.<host>.<pid>`` next
to a file), which records the run's fingerprint, host, pid and start time. The operating system
drops a ``flock`` when its process ends, however it ends (``kill -9`` included), so a newcomer
tells live runs from dead ones by trying a non-blocking *shared* ``flock`` on every lock file it finds
(shared, so that two newcomers probing one dead run's file at the same moment never take each other
for its owner; an owner holds its file exclusively from before its name appears):

* it gets the lock: the run that wrote the file is gone; the file is removed (never stale);
* the lock is held with the newcomer's fingerprint: the same run (the processes of one
  multi-process run share a checkpoint folder): allowed;
* held with another fingerprint: refused at once with `RunLockedError` naming the other run;
* held with the same fingerprint by a lock that is not ``shared`` (a single-process command: its
  fingerprint is its settings, so the same command started twice is told the same run is in
  progress, not that a run with other settings is).

One run holds one lock: the lock of a run's output covers the folder of its chunks (``covers``), and the chunk store
of that folder shares it (`RunLock.over`) instead of taking a second one; a chunk store used on its own (a
``checkpoint_dir`` outside a run that owns an output) locks its folder itself. So that such a store in another
process sees a run that covers its folder, the run leaves a mark there (``.covered.<host>.<pid>``, held and released
with its lock, never stale): the store is refused while the run lives, and a run is refused a folder that a live
store of another run holds.

A newcomer publishes its own lock *before* it looks at the others, so of two runs started at the
same moment at least one is refused: never both accepted. Where the filesystem has no ``flock``
(some network filesystems), a `RunLockWarning` says so and the run goes on unguarded.
"""
from __future__ import annotations

import hashlib
import json
import os
import platform
import time
import warnings
from pathlib import Path
from typing import Optional

from ..errors import RunLockedError, RunLockWarning
from ..validate import host_label


def settings_fingerprint(settings) -> str:
    """What identifies a run to its lock when its settings define it: ``settings`` as sorted JSON (values JSON cannot
    write as their ``str``), SHA-256 in hex. Equal settings, equal fingerprints in every process, so the same run
    started twice is told it is in progress."""
    return hashlib.sha256(json.dumps(settings, sort_keys=True, default=str).encode()).hexdigest()

__all__ = ["RunLock", "RunLockWarning", "settings_fingerprint"]

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None


def _host() -> str:
    return host_label() or "host"


#: Locks this process holds, by lock-file path: a second claim from the same process (the command
#: line's lock on FILE.npz and the library's on FILE.npz.chunks/ are different files, but a library
#: call inside another one is not) shares the lock instead of fighting over it.
_HELD: dict = {}

#: The name of a run's mark in a folder its lock covers (``.covered.<host>.<pid>``): a lock taken in that folder by
#: another process sees it as a live run's lock.
COVERED = ".covered."

#: Folders covered by a lock this process holds (`RunLock` ``covers``): resolved folder -> the lock's key in `_HELD`.
_COVERED: dict = {}


class RunLock:
    """An exclusive claim of ``target`` (an output file or a folder) by this process.

    Args:
      target: the output file, or the folder (``folder=True``) the run writes.
      fingerprint: identifies the run; processes with equal fingerprints may share ``target``.
      what: how messages call it ("output", "checkpoint folder").
      hint: what the refused run should do instead (appended to the refusal).
      shared: another process with the same fingerprint may hold ``target`` too (the processes of one
        multi-process run); ``False``: it is refused as the same run, in progress.
      covers: folders the run writes besides ``target`` (its chunks), held with it: the code that writes there shares
        this lock (`over`) rather than taking its own.
    """

    def __init__(self, target, fingerprint: str, *, folder: bool = False, what: str = "output", hint: str = "",
                 shared: bool = True, covers=()):
        self.target = Path(target)
        self.fingerprint = str(fingerprint)
        self.shared = bool(shared)
        self.what = what
        self.hint = hint
        if folder:
            self.dir, self.prefix = self.target, ".lock."
        else:
            self.dir, self.prefix = self.target.parent, f".{self.target.name}.lock."
        self.path = self.dir / f"{self.prefix}{_host()}.{os.getpid()}"
        self.covers = tuple(str(Path(c).resolve()) for c in covers)
        self._fd: Optional[int] = None
        self._marks: list = []          # (path, fd) of the marks in the folders it covers
        self._shared: Optional[RunLock] = None

    # -- acquire / release ---------------------------------------------------------------------

    def acquire(self) -> "RunLock":
        """Claim ``target``; `RunLockedError` if another live run with another fingerprint holds it."""
        if self._fd is not None or self._shared is not None:
            return self
        if fcntl is None:  # pragma: no cover
            return self
        key = str(self.path.resolve())
        mine = _HELD.get(key)
        if mine is not None:
            if mine[0].fingerprint != self.fingerprint:
                raise RunLockedError(f"{self.what} {str(self.target)!r} is in use by another run in this process "
                                     f"(pid {os.getpid()}){self._tail()}", path=self.target,
                                     holder=mine[0]._record())
            mine[1] += 1
            self._shared = mine[0]
            return self
        self.dir.mkdir(parents=True, exist_ok=True)
        if not self._publish():
            return self
        try:
            self._check_others()
            self._mark_covers()
        except BaseException:
            self._drop()
            raise
        _HELD[key] = [self, 1]
        _COVERED.update(dict.fromkeys(self.covers, key))
        return self

    @classmethod
    def over(cls, folder) -> Optional["RunLock"]:
        """The lock of the run in this process whose output's lock covers ``folder`` (``covers``), shared like a
        nested claim (release it when done; the run's own release gives the lock back); ``None`` where no run
        covers it."""
        entry = _HELD.get(_COVERED.get(str(Path(folder).resolve()), ""))
        if entry is None:
            return None
        held = entry[0]
        mine = cls(held.target, held.fingerprint, what=held.what, hint=held.hint, shared=held.shared)
        mine.dir, mine.prefix, mine.path = held.dir, held.prefix, held.path
        return mine.acquire()

    def release(self) -> None:
        """Give ``target`` back (removes the lock file). Safe to call twice."""
        if self._shared is not None:
            entry = _HELD.get(str(self._shared.path.resolve()))
            self._shared = None
            if entry is not None:
                entry[1] -= 1
                if entry[1] <= 0:
                    entry[0].release()
            return
        if self._fd is None:
            return
        key = str(self.path.resolve())
        _HELD.pop(key, None)
        for folder in [f for f, k in _COVERED.items() if k == key]:
            del _COVERED[folder]
        self._drop()

    def __enter__(self) -> "RunLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()

    # -- internals -----------------------------------------------------------------------------

    def _record(self) -> dict:
        return {"fingerprint": self.fingerprint, "host": platform.node(), "pid": os.getpid(),
                "started": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "target": str(self.target)}

    def _publish(self) -> bool:
        """Create this process's lock file, locked and complete before its name appears (`_locked_file`)."""
        fd = self._locked_file(self.path)
        if fd is None:
            return False
        self._fd = fd
        return True

    def _locked_file(self, path: Path) -> Optional[int]:
        """The descriptor of ``path``, held with an exclusive ``flock`` and holding this lock's record, written under a
        temporary name, then renamed (a reader never sees a half-written record); ``None`` (with a `RunLockWarning`)
        where the filesystem has no ``flock``."""
        tmp = path.parent / f".tmplock.{_host()}.{os.getpid()}"
        fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            os.close(fd)
            tmp.unlink(missing_ok=True)
            warnings.warn(RunLockWarning(f"could not lock {str(self.target)!r} ({e}); this filesystem has no "
                                         f"flock, so another run writing the same {self.what} is not detected"),
                          stacklevel=5)
            return None
        try:
            os.write(fd, (json.dumps(self._record()) + "\n").encode())
            os.fsync(fd)
            os.replace(tmp, path)
        except BaseException:
            os.close(fd)
            tmp.unlink(missing_ok=True)
            raise
        return fd

    def _mark_covers(self) -> None:
        """Leave a mark of this run in every folder it covers (``.covered.<host>.<pid>``, held like its lock file), so
        that a chunk store used there on its own by another process is refused while the run lives: first refuse a
        live store of another run already there (its own lock, in the folder)."""
        for folder in self.covers:
            folder = Path(folder)
            folder.mkdir(parents=True, exist_ok=True)
            RunLock(folder, self.fingerprint, folder=True, what="checkpoint folder", hint=self.hint,
                    shared=self.shared)._check_others(folder, ".lock.")
            fd = self._locked_file(folder / f"{COVERED}{_host()}.{os.getpid()}")
            if fd is not None:
                self._marks.append((folder / f"{COVERED}{_host()}.{os.getpid()}", fd))

    def _drop(self) -> None:
        marks, self._marks = self._marks, []
        for path, mark in marks:
            try:
                path.unlink(missing_ok=True)
            finally:
                os.close(mark)
        fd, self._fd = self._fd, None
        if fd is None:
            return
        # remove the name first, then let go of the lock: a newcomer never finds our file unlocked
        try:
            self.path.unlink(missing_ok=True)
        finally:
            os.close(fd)

    def _check_others(self, folder: Optional[Path] = None, prefix: Optional[str] = None) -> None:
        """Refuse a live lock of another run among the lock files ``prefix*`` in ``folder`` (default: this lock's);
        a folder lock also looks at the marks of runs that cover the folder (`COVERED`). Stale files are removed."""
        folder = self.dir if folder is None else folder
        names = [prefix or self.prefix] + ([COVERED] if prefix is None and self.dir == self.target else [])
        for other in sorted(p for name in names for p in folder.glob(name + "*")):
            if other == self.path:
                continue
            try:
                fd = os.open(other, os.O_RDONLY)
            except FileNotFoundError:   # released meanwhile
                continue
            try:
                try:
                    fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
                except BlockingIOError:
                    rec = _read(fd)
                    if rec.get("fingerprint") != self.fingerprint or not self.shared:
                        raise self._refusal(other, rec) from None
                    continue
                # acquirable: its process is gone (killed, crashed); the file is stale
                other.unlink(missing_ok=True)
            finally:
                os.close(fd)

    def _refusal(self, other: Path, rec: dict) -> RunLockedError:
        who = (f"host {rec.get('host', '?')}, pid {rec.get('pid', '?')}, started {rec.get('started', '?')}"
               if rec else f"lock file {other.name}")
        if rec.get("fingerprint") == self.fingerprint:
            return RunLockedError(f"the same run is in progress: {self.what} {str(self.target)!r} is being written by "
                                  f"a run with the same settings ({who}); wait for it to finish (or stop it)"
                                  f"{self._tail()}", path=self.target, holder=rec)
        return RunLockedError(f"{self.what} {str(self.target)!r} is being written by another run ({who}) with "
                              f"other settings; two runs never write the same {self.what}: wait for that run to "
                              f"finish (or stop it){self._tail()}", path=self.target, holder=rec)

    def _tail(self) -> str:
        return f", or {self.hint}" if self.hint else ""


def _read(fd: int) -> dict:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        rec = json.loads(os.read(fd, 65536).decode() or "{}")
        return rec if isinstance(rec, dict) else {}
    except (OSError, ValueError, UnicodeDecodeError):
        return {}
