r"""Laws tuned to one energy budget, so that `jaxsleigh.studies.compare` sets them side by side at equal effort.

The budget is by default the paper's training energy \(E_{paper} = \exp(\overline{\log E_i})\),
\(E_i = \int_0^{30} \|u\|^2 dt\) on the tuner's training starts (`jaxsleigh.tuning.training_energy`); each
literature law is tuned to it by `jaxsleigh.tuning.tune_law`; the paper's gains stay as published and a law that
ships a tuned preset (``shaped``) keeps it. A tuned law whose training energy stays outside `BUDGET_BAND` of the
budget is recorded (``budget_reached`` false) and named.
"""
from __future__ import annotations

import math
import time
from typing import Callable, NamedTuple, Optional, Sequence

from ..controllers.registry import controller_class, make_controller
from ..model.controller import controller_record
from ..studies.compare import json_ready
from .law import tune_law
from .objective import LossConfig
from .optimizer import TuneConfig
from .pareto import training_energy
from .starts import UniformStarts, draw_starts

__all__ = ["EqualEnergy", "tune_to_budget", "BUDGET_BAND", "budget_note"]


class EqualEnergy(NamedTuple):
    r"""The laws of `tune_to_budget`, ready for `compare`, and what was done to each.

    Attributes:
      laws: name -> law, in the order asked for.
      budget: the energy budget [N^2 s, (N m)^2 s]: geometric mean of \(\int_0^{30} \|u\|^2 dt\) over the
        training starts.
      laws_info: name -> ``{"as": "published" | "preset" | "tuned" | "untuned", "law": record, ...}``; a tuned
        law adds its ``training_energy``, ``training_loss``, ``steps`` and ``wall_s``, an untuned one ``why``.
      settings: the training starts' count and seed, the tuner's steps and learning rate, the horizon.
    """

    laws: dict
    budget: float
    laws_info: dict
    settings: dict

    def record(self) -> dict:
        """JSON-ready: budget, settings and each law's record, but its tuning's wall time (``laws_info``'s
        ``wall_s``), which varies between runs."""
        laws = {k: {f: v for f, v in info.items() if f != "wall_s"} for k, info in self.laws_info.items()}
        return json_ready({"budget": self.budget, "settings": self.settings, "laws": laws})


#: The band of training energy / budget in which a tuned law counts as at the budget (``budget_reached``).
BUDGET_BAND = (0.95, 1.05)


def budget_note(ratio: float) -> str:
    """What a tuned law's training energy / budget ``ratio`` means for an equal-energy comparison: ``''`` within
    `BUDGET_BAND`; above it the budget is exceeded, below it not reached (the law is compared at less energy than
    the others, not at equal energy)."""
    if not math.isfinite(ratio):
        return "; its training energy is not finite: the budget was not reached"
    if ratio > BUDGET_BAND[1]:
        return " (above the budget: more tuner steps bring it closer)"
    if ratio < BUDGET_BAND[0]:
        return (f"; the budget was NOT reached: it is compared at {ratio:.2f}x the energy of the others, not at "
                f"equal energy (more tuner steps, or a law that cannot use more energy there)")
    return ""


def tune_to_budget(names: Sequence[str], *, train: int = 32, steps: int = 60, lr: float = 0.1, seed: int = 0,
                   t_train: float = 30.0, budget: Optional[float] = None,
                   log: Optional[Callable[[str], None]] = None) -> EqualEnergy:
    r"""The laws called ``names`` (`jaxsleigh.controllers.registry`) at one energy budget.

    The budget is ``budget`` or the paper's training energy,
    \(E_{paper} = \exp\big(\tfrac1N \sum_i \log \int_0^{T} \|u_i\|^2 dt\big)\) over the tuner's ``train``
    training starts (``UniformStarts()``, ``seed``; \(T\) = ``t_train``), `jaxsleigh.tuning.training_energy`.
    Each literature law is tuned on those starts by `jaxsleigh.tuning.tune_law` (Adam, ``steps`` iterations at
    learning rate ``lr``, augmented Lagrangian on "energy \(\le\) budget"); the paper's gains stay as published
    and a law with a tuned preset (``shaped``) keeps it. A law whose default is not a valid candidate on the
    training starts is compared untuned (``laws_info[name]["as"] == "untuned"``, with the reason). A tuned law
    records its ``energy_ratio`` (training energy / budget) and ``budget_reached`` (the ratio within
    `BUDGET_BAND`): a law below the band was not brought to the budget and is compared at less energy. ``log``
    gets one line per law, which says so.
    """
    say = log or (lambda msg: None)
    loss = LossConfig(t_final=float(t_train))
    starts = draw_starts(UniformStarts(), train, seed)
    if budget is None:
        budget = training_energy("paper", config=TuneConfig(batch=train, seed=seed),
                                        loss=loss)["energy"]
    budget = float(budget)
    laws, info = {}, {}
    for name in names:
        law = make_controller(name)
        # the paper's gains stay as published and a law that ships a tuned preset keeps it; the others are tuned
        kept = "published" if name == "paper" else "preset" if hasattr(controller_class(name), "preset") else None
        if kept is not None:
            laws[name], info[name] = law, {"as": kept, "law": controller_record(law)}
            continue
        t0 = time.perf_counter()
        try:
            res = tune_law(law, starts, loss=loss._replace(energy_budget=budget), steps=steps, lr=lr)
        except ValueError as e:                 # the default law is not a valid candidate there
            laws[name], info[name] = law, {"as": "untuned", "why": str(e), "law": controller_record(law)}
            say(f"{name}: compared untuned ({e})")
            continue
        laws[name] = res.law
        ratio = res.energy / budget
        info[name] = {"as": "tuned", "law": controller_record(res.law), "training_energy": res.energy,
                      "training_loss": res.loss, "steps": len(res.history["loss"]),
                      "wall_s": time.perf_counter() - t0, "energy_ratio": ratio,
                      "budget_reached": bool(BUDGET_BAND[0] <= ratio <= BUDGET_BAND[1])}
        say(f"{name}: tuned in {time.perf_counter() - t0:.0f} s; training energy {res.energy:.4g}, "
            f"{ratio:.2f}x the budget {budget:.4g}" + budget_note(ratio))
    settings = {"train": int(train), "seed": int(seed), "steps": int(steps), "lr": float(lr),
                "t_train": float(t_train), "starts": "UniformStarts()"}
    return EqualEnergy(laws, budget, info, settings)
