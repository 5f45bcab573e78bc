"""The deprecation of `jaxsleigh.solve`'s keyword options ``method=`` and ``max_attempts=``.

`jaxsleigh.solve` takes its step policy as ``stepsize=jaxsleigh.StepSizeController(method=..., max_steps=...)``;
the two keywords it took before still work, and each call that gives any emits one `DeprecationWarning`, at the
caller's line, that names every such keyword and the object and field it belongs to::

    solve(method=..., max_attempts=...) is deprecated: pass stepsize=jaxsleigh.StepSizeController(method=...,
    max_steps=...) (these keywords work until jaxsleigh 0.4)

(The studies' keywords of jaxsleigh 0.1 were removed in 0.4: `jaxsleigh.studies.options` refuses them by name.)
A filter on these warnings alone matches `DEPRECATED_SAYS`::

    warnings.filterwarnings("error", message=".*" + jaxsleigh.deprecation.DEPRECATED_SAYS, category=DeprecationWarning)
"""
from __future__ import annotations

import warnings
from typing import Iterable

__all__ = ["DEPRECATED_SAYS", "OBJECT_CLASS", "warn_deprecated"]

#: The words every deprecation of a keyword option says: what a filter on jaxsleigh's own deprecations matches.
DEPRECATED_SAYS = "is deprecated: pass"
#: The class of each option object (by the front's parameter that takes it), as the warning names it.
OBJECT_CLASS = {"stepsize": "StepSizeController", "saveat": "SaveAt", "run": "RunOptions"}


def warn_deprecated(front: str, moves: Iterable[tuple], *, stacklevel: int = 2) -> None:
    """One `DeprecationWarning` for every keyword option of one call of ``front`` (nothing when there is none).

    ``moves``: ``(keyword, object, field)`` for each keyword given, in the order given (``object``: a key of
    `OBJECT_CLASS`). ``stacklevel`` counts from the caller of this function: 2, its caller's caller (the
    user's call of a front that calls this directly).
    """
    moves = list(moves)
    if not moves:
        return
    fields: dict = {}
    for _, home, field in moves:
        fields.setdefault(home, []).append(field)
    objects = ", ".join(f"{home}=jaxsleigh.{OBJECT_CLASS[home]}({', '.join(f'{f}=...' for f in fields[home])})"
                        for home in OBJECT_CLASS if home in fields)
    keywords = ", ".join(f"{k}=..." for k, _, _ in moves)
    warnings.warn(f"{front}({keywords}) {DEPRECATED_SAYS} {objects} (these keywords work until jaxsleigh 0.4)",
                  DeprecationWarning, stacklevel=stacklevel + 1)
