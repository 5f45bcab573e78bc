"""The lane pool: which batch size a set of lanes runs in, and the pool of stragglers' loop.

Every batch that sheds finished lanes (the engine's compaction, `jaxsleigh.integrate.engine.drive_final`; the
optimum's problems, `jaxsleigh.studies.optimum`; the run's pool of stragglers, `StragglerPool`) picks its size from
one `Ladder`: powers of two between a floor and a ceiling, a batch shrinking once at most a quarter of it is still
working. Each user keeps its own numbers (chosen so that a lane's bits do not depend on the
batch it runs in: `jaxsleigh.integrate.engine.min_batch`, the ensemble's ``TAIL_MIN``), so the bytes do not change.
Padding is always copies of the first working lane (`padded`): it never reads a finished lane's state.
"""
from __future__ import annotations

import threading
from typing import Callable, List, NamedTuple, Optional

import jax
import numpy as np

__all__ = ["bucket", "Ladder", "padded", "take_lanes_of", "put_lanes", "Waiting", "StragglerPool"]


def bucket(n: int) -> int:
    """The batch size ``n`` lanes are padded to: the next power of two (few shapes compile)."""
    return 1 << max(0, (n - 1).bit_length())


class Ladder(NamedTuple):
    """Batch sizes of a pool: ``bucket(max(n, floor))`` for ``n`` working lanes, at most ``ceiling`` lanes a batch
    (None: no limit; more lanes are cut into several batches, `groups`). A batch of ``size`` lanes shrinks when it
    holds at least ``shrink_from`` (None: ``floor + 1``) and at most a quarter of them still work (`shrinks`)."""
    floor: int = 1
    ceiling: Optional[int] = None
    shrink_from: Optional[int] = None

    def size(self, n: int) -> int:
        """The batch ``n`` working lanes run in (``n`` at most ``ceiling``)."""
        return bucket(max(n, self.floor))

    def shrinks(self, size: int, n: int) -> bool:
        """Whether a batch of ``size`` lanes, ``n`` of them still working, moves them into a smaller one."""
        start = self.floor + 1 if self.shrink_from is None else self.shrink_from
        return size >= start and n <= size // 4

    def groups(self, lanes: np.ndarray) -> List[np.ndarray]:
        """``lanes`` cut, in order, into runs of at most ``ceiling``."""
        step = lanes.size if self.ceiling is None else self.ceiling
        return [lanes[g:g + step] for g in range(0, lanes.size, max(step, 1))]


def padded(keep: np.ndarray, size: int) -> np.ndarray:
    """Indices of a batch of ``size`` lanes: ``keep``, then copies of its first lane."""
    keep = np.asarray(keep)
    return np.concatenate([keep, np.repeat(keep[:1], size - keep.size)])


def take_lanes_of(full, rows: np.ndarray):
    """Lanes ``rows`` of a batch-last host pytree (a state, per-lane parameters)."""
    return jax.tree_util.tree_map(lambda a: np.asarray(a)[..., rows], full)


def put_lanes(full, rows: np.ndarray, part):
    """``full`` with its lanes ``rows`` replaced by those of ``part`` (in order); a row -1 (padding) is skipped."""
    return jax.tree_util.tree_map(lambda f, h: _scatter(f, np.asarray(rows), h), full, part)


def _scatter(full: np.ndarray, idx: np.ndarray, part: np.ndarray) -> np.ndarray:
    out = np.array(full)
    real = idx >= 0
    out[..., idx[real]] = np.asarray(part)[..., real]
    return out


def _joined(a, b):
    return jax.tree_util.tree_map(lambda x, y: np.concatenate([x, y], axis=-1), a, b)


class Waiting:
    """One owner's lanes in a `StragglerPool`: their host states (batch-last), filled in as each lane finishes;
    ``event`` is set when the last one has."""

    def __init__(self, lanes):
        self.state, self.left, self.event = lanes, int(lanes.t.shape[-1]), threading.Event()

    def put(self, ks: np.ndarray, lanes) -> None:
        self.state = put_lanes(self.state, ks, lanes)
        self.left -= ks.size
        if self.left == 0:
            self.event.set()


class StragglerPool:
    """One pool of lanes that several owners hand in over time: its loop (`run`, on a thread of the caller's) steps
    them together, one segment at a time (``advance(lanes, rows) -> lanes``, on the host, batch-last), takes in new
    lanes between segments and hands every lane that ``active(lanes)`` says is done back to its owner (`Waiting`).
    One fixed cost per attempted step for all owners instead of one each. ``advance`` steps every lane at the same
    attempt counts as before it came (whole segments) in batches of a `Ladder` whose sizes give each lane the same
    bits whatever the others are: a lane's result does not depend on when it came or with which lanes it ran."""

    def __init__(self, advance: Callable, active: Callable):
        self.advance, self.active = advance, active
        self.cond = threading.Condition()
        self.incoming: list = []
        self.closed = False
        self.error: Optional[BaseException] = None
        self.future = None
        self.owners: list = []

    def add(self, lanes, rows) -> Waiting:
        """Hand in ``lanes`` (host, batch-last; ``rows`` goes with them to ``advance``); returns their `Waiting`."""
        owner = Waiting(lanes)
        with self.cond:
            if self.error is not None:
                raise RuntimeError("the pool of stragglers failed") from self.error
            self.incoming.append((lanes, np.asarray(rows), owner))
            self.owners.append(owner)
            self.cond.notify_all()
        return owner

    def close(self) -> None:
        """No more lanes will come: `run` returns once its lanes are done."""
        with self.cond:
            self.closed = True
            self.cond.notify_all()

    def wait(self, owner: Waiting):
        """``owner``'s lanes once all are done (raises the pool's error if it failed)."""
        owner.event.wait()
        if self.error is not None and owner.left:
            raise RuntimeError("the pool of stragglers failed") from self.error
        return owner.state

    def run(self) -> None:
        """The pool's loop, until `close` and its last lane; an error is kept for the owners (`wait`)."""
        try:
            self._run()
        except BaseException as e:
            with self.cond:
                self.error = e
                for o in self.owners:
                    o.event.set()
            raise

    def _run(self) -> None:
        lanes, rows, who = None, np.zeros(0, np.int64), []      # who: (owner, k) of each lane
        while True:
            with self.cond:
                while not self.incoming and not self.closed and not who:
                    self.cond.wait()
                new, self.incoming = self.incoming, []
                closed = self.closed
            for st, r, owner in new:
                lanes = st if lanes is None or not who else _joined(lanes, st)
                rows = r if not who else np.concatenate([rows, r])
                who += [(owner, k) for k in range(r.size)]
            if not who:
                if closed:
                    return
                continue
            lanes = self.advance(lanes, rows)
            act = self.active(lanes)
            by_owner: dict = {}
            for i in np.flatnonzero(~act):
                owner, k = who[i]
                by_owner.setdefault(id(owner), (owner, [], []))[1].append(k)
                by_owner[id(owner)][2].append(i)
            for owner, ks, idx in by_owner.values():
                owner.put(np.asarray(ks), take_lanes_of(lanes, np.asarray(idx)))
            keep = np.flatnonzero(act)
            lanes, rows, who = take_lanes_of(lanes, keep), rows[keep], [who[i] for i in keep]
