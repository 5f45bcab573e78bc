"""`SaveAt`: what a run keeps, for the traced `jaxsleigh.solve` and the NumPy fronts alike."""
from __future__ import annotations

from typing import NamedTuple, Optional

__all__ = ["SaveAt"]


class SaveAt(NamedTuple):
    """What a run keeps: the fronts (`jaxsleigh.simulate`, `jaxsleigh.run_ensemble`, ...) and `jaxsleigh.solve`.

    Attributes:
      every: keep the trajectories every ``every`` base steps (``None``: final states and summaries only).
      summaries: ``False`` runs the plain fixed-step path (final states only, no per-step checks or
        summaries; needs ``StepSizeController(method="rk4", check_passivity=False)``).
    """

    every: Optional[int] = None
    summaries: bool = True
