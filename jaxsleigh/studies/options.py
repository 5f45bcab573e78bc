"""The options of a study as small objects, in the manner of diffrax's ``saveat`` and ``stepsize_controller``.

* `jaxsleigh.StepSizeController` (`jaxsleigh.integrate.stepsize`): how steps are taken (method, tolerances,
  the policy's safety and factor limits, largest step, step budget, the passivity monitor);
* `SaveAt` (`jaxsleigh.integrate.saveat`): what to keep (trajectories every ``every`` base steps, or final states and summaries only, or the
  plain fast path without summaries);
* `RunOptions`: how to run (chunks, segments, devices, checkpoint, resume, progress, the share of a
  multi-process run).

The fronts take their options as these objects. The keywords of jaxsleigh 0.1 (``rtol=``, ``chunk_size=``,
``save_every=``, ...) are deprecated: they work until 0.4, each call that gives any with one `DeprecationWarning`
naming the object and field of each (`jaxsleigh.deprecation`). `front_options` folds them into the three
objects (`StudyOptions`), which the studies then pass down whole: a front takes at most a dozen parameters, the
engine behind it as many.
"""
from __future__ import annotations

from typing import Any, NamedTuple, Optional

from ..deprecation import OBJECT_CLASS, warn_deprecated
from ..integrate.saveat import SaveAt
from ..integrate.stepsize import StepSizeController, check_policy

__all__ = ["SaveAt", "RunOptions", "StudyOptions", "front_options"]


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
      audit: the accuracy audit (`jaxsleigh.Audit`; ``None``: the default one, rows from 500 starts on; ``False``:
        none): it adds ``run_info["audit"]`` and changes no number of the result.
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
    """The three option objects of a study, every 0.1 keyword folded in (what `front_options` returns)."""

    stepsize: StepSizeController
    saveat: SaveAt
    run: RunOptions


#: Where each keyword of jaxsleigh 0.1 lives: ``(object, field)``; the one table both ways (`front_options`).
_KEYWORD_HOME = {**{k: ("stepsize", k) for k in ("rtol", "atol", "max_step", "max_steps", "method",
                                                  "check_passivity")},
                 "save_every": ("saveat", "every"), "summaries": ("saveat", "summaries"),
                 **{k: ("run", k) for k in RunOptions._fields if k != "audit"}}
#: the fronts that audit (``RunOptions.audit`` is not a keyword of jaxsleigh 0.1: it goes through as it is)
_AUDITED = frozenset({"run_ensemble", "run_basin", "sweep"})
#: fields put even at their default: an object's ``method="adaptive"`` clashes with ``method="rk4"`` given by itself
_ALWAYS_PUT = frozenset({"method", "check_passivity", "summaries"})


def front_options(front: str, allowed: frozenset, stepsize=None, saveat=None, run=None, options=None, *,
                  saveat_default: SaveAt = SaveAt(), stacklevel: int = 3) -> StudyOptions:
    """The option objects of a study, with the 0.1 keywords in ``options`` folded in.

    An unknown keyword is a ``TypeError`` naming the valid ones; the known ones are deprecated, and one
    `DeprecationWarning` (`jaxsleigh.deprecation.warn_deprecated`) names them all, pointing at the frame ``stacklevel`` levels up
    (3: the caller of the front that calls this). A keyword given both as an object's field and by itself
    (with another value) is a ``ValueError``; an object's field the front has no use for (a chunk size for
    `jaxsleigh.simulate`) is a ``ValueError`` naming it. ``saveat_default``: what an unset ``SaveAt`` field
    means for this front (`jaxsleigh.simulate` keeps every 10th step).
    """
    _refuse_unknown(front, allowed, dict(options or {}))
    audit = None if run is None else getattr(run, "audit", None)
    if audit is not None and front not in _AUDITED:
        raise ValueError(f"{front}() has no use for run.audit = {audit!r} (drop it; run_ensemble, run_basin and "
                         f"sweep audit)")
    warn_deprecated(front, ((k,) + _KEYWORD_HOME[k] for k in options or {}), stacklevel=stacklevel)
    out = _merged_keywords(front, allowed, stepsize, saveat, run, options)
    ss = stepsize if stepsize is not None else StepSizeController()
    fields = {"stepsize": {"safety": float(ss.safety), "factor_min": float(ss.factor_min),
                           "factor_max": float(ss.factor_max)}, "saveat": {}, "run": {}}
    for key, value in out.items():
        home, field = _KEYWORD_HOME[key]
        fields[home][field] = value
    return StudyOptions(StepSizeController(**fields["stepsize"]), saveat_default._replace(**fields["saveat"]),
                        RunOptions(**fields["run"], audit=audit))


def _refuse_unknown(front: str, allowed: frozenset, options: dict) -> None:
    """A ``TypeError`` naming the keywords of ``options`` that ``front`` does not know, and the objects it takes."""
    unknown = sorted(set(options) - allowed)
    if unknown:
        homes = [h for h in OBJECT_CLASS if any(_KEYWORD_HOME.get(k, ("",))[0] == h for k in allowed)]
        raise TypeError(f"{front}() got unexpected keyword argument{'s' if len(unknown) > 1 else ''} "
                        f"{', '.join(repr(k) for k in unknown)}; its options are "
                        f"{', '.join(f'{h}=jaxsleigh.{OBJECT_CLASS[h]}(...)' for h in homes)}")


def _fields_put(home: str, cls, obj):
    """``(keyword, value, default)`` for each field of the option object ``obj`` (given as ``home``, checked to be
    a ``cls``) that goes into the keywords: those that differ from their defaults, and `_ALWAYS_PUT`."""
    if not isinstance(obj, cls):
        raise ValueError(f"{home} must be a jaxsleigh.{cls.__name__}, got {type(obj).__name__}")
    if cls is StepSizeController:
        check_policy(obj)
    for key, field in ((k, f) for k, (h, f) in _KEYWORD_HOME.items() if h == home):
        value, default = getattr(obj, field), cls._field_defaults[field]
        if value != default or key in _ALWAYS_PUT:
            yield key, value, default


def _merged_keywords(front: str, allowed: frozenset, stepsize, saveat, run, options) -> dict:
    """The 0.1 keywords given, with the objects' fields that differ from their defaults put in (checked)."""
    options = dict(options or {})
    _refuse_unknown(front, allowed, options)
    out = dict(options)

    def put(key, value, source, default=None):
        if key not in allowed:
            if value != default:
                raise ValueError(f"{front}() has no use for {source}.{key} = {value!r} (drop it)")
            return
        if key in out and out[key] != value:
            raise ValueError(f"{front}(): {key} given twice, {source}.{key} = {value!r} and {key}={out[key]!r}; "
                             f"give it once")
        out[key] = value

    given = {"stepsize": stepsize, "saveat": saveat, "run": run}
    for home, cls in (("stepsize", StepSizeController), ("saveat", SaveAt), ("run", RunOptions)):
        if given[home] is not None:
            for key, value, default in _fields_put(home, cls, given[home]):
                put(key, value, home, default)
    return out
