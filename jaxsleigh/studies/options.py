"""The options of a study as small objects, in the manner of diffrax's ``saveat`` and ``stepsize_controller``.

* `jaxsleigh.StepSizeController` (`jaxsleigh.integrate.stepsize`): how steps are taken (method, tolerances,
  the policy's safety and factor limits, largest step, step budget, the passivity monitor);
* `SaveAt` (`jaxsleigh.integrate.saveat`): what to keep (trajectories every ``every`` base steps, or final states and summaries only, or the
  plain fast path without summaries);
* `RunOptions`: how to run (chunks, segments, devices, checkpoint, resume, progress, the share of a
  multi-process run).

The fronts take their options as these objects only and pass them down whole: a front takes at most a dozen
parameters, the engine behind it as many. `study_options` checks the objects a front is given (their types, the
step policy, and that no field the front has no use for differs from its default). The loose keywords of
jaxsleigh 0.1 (``rtol=``, ``chunk_size=``, ``save_every=``, ...) were removed in 0.4: `takes_objects` refuses each
with a ``TypeError`` that names the object and field that hold it now (`REMOVED_KEYWORDS`).
"""
from __future__ import annotations

from typing import Any, NamedTuple, Optional

from ..integrate.saveat import SaveAt
from ..integrate.stepsize import StepSizeController, check_policy
from ..validate import refuses_removed_keywords

__all__ = ["SaveAt", "RunOptions", "StudyOptions", "study_options", "takes_objects", "REMOVED_KEYWORDS"]


class RunOptions(NamedTuple):
    """How a study runs (none of these changes the numbers).

    Attributes:
      chunk_size: trajectories integrated, and checkpointed, at once (``None``: the study's default).
      segment: attempted steps per compiled segment between the host's checks.
      devices: the devices each chunk is split over (default: every core on CPU, every local device
        elsewhere; `jaxsleigh.cores`); cores: use at most this many of them (``None``: all; ``1``: one core).
        Neither changes a result: the parts of a chunk are integrated exactly as the whole chunk.
      checkpoint_dir: write every finished chunk there; resume: reuse them (same settings and starts).
      progress: ``True`` / ``False`` / ``None`` (auto: on a terminal).
      shard: ``(index, count)``: compute only this process's share of the chunks (multi-process runs).
      audit: the accuracy audit (`jaxsleigh.Audit`; ``None``: the default one, rows from 500 starts on, the
        unresolved ones first, within 10% of the run's time; ``False``: none): it adds ``run_info["audit"]`` and
        changes no number of the result (``result.unresolved`` is computed either way).
    """

    chunk_size: Optional[int] = None
    segment: int = 1000
    devices: Any = None
    cores: Optional[int] = None
    checkpoint_dir: Any = None
    resume: bool = False
    progress: Any = None
    shard: Optional[tuple] = None
    audit: Any = None


class StudyOptions(NamedTuple):
    """The three option objects of a study, checked and defaulted (what `study_options` returns)."""

    stepsize: StepSizeController
    saveat: SaveAt
    run: RunOptions


#: The class of the option object each front's parameter takes.
OBJECTS = {"stepsize": StepSizeController, "saveat": SaveAt, "run": RunOptions}
_ALL = {home: frozenset(cls._fields) for home, cls in OBJECTS.items()}
#: The fields of each option object that a front uses (an object the front does not take is absent); any other
#: field must keep its default (``run.audit``, say, is for the fronts that audit: ensembles, basins and sweeps).
USES = {
    "simulate": {"stepsize": _ALL["stepsize"] - {"check_passivity"}, "saveat": frozenset({"every"}),
                 "run": frozenset({"progress"})},
    "run_ensemble": dict(_ALL),
    "run_basin": {"stepsize": _ALL["stepsize"], "run": _ALL["run"] - {"segment"}},
    "sweep": {"stepsize": _ALL["stepsize"], "run": _ALL["run"] - {"segment"}},
    "optimum": {"run": frozenset({"chunk_size", "progress", "checkpoint_dir", "resume", "shard"})},
}
#: The keywords of jaxsleigh 0.1, removed in 0.4: ``keyword -> (parameter, field)`` of the object that holds it now.
#: Only the message that refuses one reads it.
REMOVED_KEYWORDS = {**{k: ("stepsize", k) for k in ("rtol", "atol", "max_step", "max_steps", "method",
                                                    "check_passivity")},
                    "save_every": ("saveat", "every"), "summaries": ("saveat", "summaries"),
                    **{k: ("run", k) for k in ("chunk_size", "segment", "devices", "cores", "checkpoint_dir",
                                               "resume", "progress", "shard")}}


def _differs(value, default) -> bool:
    """Whether an object's field was changed from its default (an array or a device list is a change)."""
    if value is default:
        return False
    try:
        return bool(value != default)
    except (TypeError, ValueError):
        return True


def study_options(front: str, stepsize=None, saveat=None, run=None, *,
                  saveat_default: SaveAt = SaveAt()) -> StudyOptions:
    """The option objects of ``front`` (a key of `USES`), checked, the missing ones at their defaults.

    Each must be its class (``ValueError`` naming the parameter and the class), the step policy passes
    `jaxsleigh.integrate.stepsize.check_policy`, and a field the front has no use for (a chunk size for
    `jaxsleigh.simulate`, an audit for `jaxsleigh.optimum`) is a ``ValueError`` naming it unless it keeps its
    default. ``saveat_default``: the ``SaveAt`` of a front given none, and its ``every`` where the one given
    leaves it unset (`jaxsleigh.simulate` keeps every 10th step).
    """
    uses = USES[front]
    given = {"stepsize": stepsize, "saveat": saveat, "run": run}
    out = {}
    for home, cls in OBJECTS.items():
        obj = given[home]
        if obj is None:
            out[home] = saveat_default if home == "saveat" else cls()
            continue
        if not isinstance(obj, cls):
            raise ValueError(f"{home} must be a jaxsleigh.{cls.__name__}, got {type(obj).__name__}")
        for field in cls._fields:
            value = getattr(obj, field)
            if field not in uses.get(home, ()) and _differs(value, cls._field_defaults[field]):
                raise ValueError(f"{front}() has no use for {home}.{field} = {value!r} (drop it)")
        out[home] = check_policy(obj) if home == "stepsize" else obj
    if out["saveat"].every is None:
        out["saveat"] = out["saveat"]._replace(every=saveat_default.every)
    return StudyOptions(out["stepsize"], out["saveat"], out["run"])


def takes_objects(front):
    """Decorate a front (a function whose name is a key of `USES`): a keyword of jaxsleigh 0.1 it is given
    (`REMOVED_KEYWORDS`) is a ``TypeError`` naming the object and field to pass instead
    (`jaxsleigh.validate.refuses_removed_keywords`)."""
    return refuses_removed_keywords(REMOVED_KEYWORDS, USES[front.__name__],
                                    "the keywords of jaxsleigh 0.1 were removed in 0.4")(front)
