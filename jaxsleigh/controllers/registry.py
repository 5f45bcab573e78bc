"""The controllers the library ships, by name: what ``--controller NAME`` and ``jaxsleigh controllers`` use.

``paper`` is the paper's law with its gains (`jaxsleigh.Gains`, integrated in the w chart); the others are
the literature's stabilisers of unicycle-like vehicles, each in its own module with its citation, lifted to
force level by a velocity loop that knows the plant's model (`jaxsleigh.controllers.lift`); ``shaped`` is the
shaped-energy law (`jaxsleigh.ShapedGains`, w chart) with its tuned preset.
"""
from __future__ import annotations

import importlib

__all__ = ["CONTROLLERS", "controller_names", "controller_class", "make_controller", "describe_controllers",
           "check_not_controller"]

#: name -> (module, class): the laws in the order ``jaxsleigh controllers`` lists them.
CONTROLLERS = {
    "paper": ("jaxsleigh.controllers.paper", "PaperLaw"),
    "aicardi": ("jaxsleigh.controllers.aicardi", "AicardiLaw"),
    "astolfi": ("jaxsleigh.controllers.astolfi", "AstolfiLaw"),
    "samson": ("jaxsleigh.controllers.samson", "Samson"),
    "shaped": ("jaxsleigh.model.shaped_law", "ShapedGains"),
}


def controller_names() -> list[str]:
    """The names, in listing order."""
    return list(CONTROLLERS)


def controller_class(name: str):
    """The class of the law called ``name``; ``ValueError`` naming the choices for an unknown name."""
    if name not in CONTROLLERS:
        raise ValueError(f"unknown controller {name!r}; choose one of {', '.join(CONTROLLERS)} "
                         f"(jaxsleigh controllers lists them)")
    module, cls = CONTROLLERS[name]
    return getattr(importlib.import_module(module), cls)


def make_controller(name: str, gains=None):
    """The law called ``name`` with its default parameters. For ``"paper"`` this is the paper's law as the
    engine integrates it best: its `jaxsleigh.Gains` (``gains``, default the paper's), in the w chart; for a law
    with a ``preset`` (``"shaped"``) its shipped preset."""
    cls = controller_class(name)
    if name == "paper":
        from ..model.params import as_gains

        return as_gains(gains)
    return cls.preset() if hasattr(cls, "preset") else cls()


def check_not_controller(spec: str, flag: str = "--gains") -> None:
    """Refuse, with the way on, a controller's name (``--gains shaped``) given to ``flag``, which takes gains of the
    paper's law: the refusal says to use ``--controller NAME``."""
    if spec != "paper" and spec in CONTROLLERS:
        raise ValueError(f"{flag} {spec}: {spec!r} is a controller of its own, not gains of the paper's law; use "
                         f"--controller {spec} (and no {flag})")


def describe_controllers() -> list[str]:
    """One line per law: name, what of the plant it must know (its model's parameters, or nothing: it reads only
    the measured q and v), citation."""
    lines = []
    for name in CONTROLLERS:
        cls = controller_class(name)
        needs = (f"needs a model of the plant ({', '.join(cls.needs)})" if cls.needs
                 else "knows nothing of the plant: reads only q and v")
        tv = "; time-varying" if getattr(cls, "time_varying", False) is True else ""
        lines.append(f"{name:8s} {needs}{tv}. {cls.citation}")
    return lines
