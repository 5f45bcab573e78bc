"""A tuned law on disk: the file ``jaxsleigh tune --controller NAME`` writes, and `load_controller_record`, which
reads it back as the law (for ``--controller FILE.json``).

The file holds the law, not its actuator: ``{"controller": NAME, "params": {leaf: value, ...}, "actuator":
{"saturation": U, "sample_period": TS, "delay": K, "noise": SIGMA}, "meta": {...}}``, where ``params`` are every
numeric leaf of the bare law (named as `jaxsleigh.model.controller.law_leaf_names` names them: its gains and the
plant model it carries) and ``actuator`` records the saturation and digital controller it was tuned behind (the
flags to give again). The paper's law is written as a gains file (``{"L", "k", "D_hat", "meta"}``), which
``--gains FILE`` reads as it is.
"""
from __future__ import annotations

import json
from pathlib import Path

import jax
import numpy as np
from ..controllers.actuators import NormSaturation, Sampled, Saturation
from ..controllers.paper import PaperLaw
from ..controllers.registry import make_controller
from ..files.npz import atomic_write_text
from ..model.controller import as_controller, is_paper_law, law_leaf_names
from ..model.params import gains_to_dict, load_gains

__all__ = ["bare_law", "actuator_record", "law_file_record", "save_law", "load_controller_record"]


def bare_law(law):
    """``law`` without its actuators (saturation, digital controller): the law itself; the paper's as its `Gains`."""
    while isinstance(law, (Saturation, NormSaturation, Sampled)):
        law = law.law
    return law.gains if isinstance(law, PaperLaw) else law


def actuator_record(law) -> dict:
    """The actuators ``law`` runs behind, as the flags that give them: ``saturation``, ``sample_period``, ``delay``,
    ``noise`` (``None`` / 0 where there is none)."""
    out = {"saturation": None, "sample_period": None, "delay": 0, "noise": 0.0}
    while isinstance(law, (Saturation, NormSaturation, Sampled)):
        if isinstance(law, Sampled):
            out.update(sample_period=float(law.sampler.period), delay=int(law.sampler.delay),
                       noise=float(law.sampler.noise))
        else:
            u = law.u_max
            out["saturation"] = float(u) if np.ndim(u) == 0 else [float(x) for x in u]
        law = law.law
    return out


def law_file_record(law, controller: str, **meta) -> dict:
    """The JSON document of a tuned ``law`` of the registered kind ``controller`` (module docstring)."""
    inner = bare_law(law)
    if is_paper_law(inner):
        return {**gains_to_dict(inner), "meta": {"controller": "paper", "actuator": actuator_record(law), **meta}}
    params = {n: np.asarray(v, np.float64).tolist() for n, v in law_leaf_names(inner).items()}
    return {"controller": controller, "params": params, "actuator": actuator_record(law), "meta": meta}


def save_law(law, controller: str, path, **meta) -> None:
    """Write `law_file_record` to ``path`` atomically."""
    atomic_write_text(path, json.dumps(law_file_record(law, controller, **meta), indent=1, default=str) + "\n")


def load_controller_record(path):
    """The law a file of `save_law` holds (a gains file: the paper's `Gains`), checked: a registered controller, every
    parameter of its law given as a finite number of the right shape, no other. Its ``actuator`` is not applied
    (give ``--saturation`` / ``--sample-period`` for that). ``ValueError`` saying what is wrong otherwise."""
    doc = _read(path)
    if "controller" not in doc:
        if {"L", "k", "D_hat"} & set(doc):
            return load_gains(str(path))
        raise ValueError(f"controller file {str(path)!r} names no controller; write it with jaxsleigh tune "
                         f"--controller NAME --out FILE.json (or give a gains file with L, k, D_hat)")
    if doc["controller"] == "paper":
        raise ValueError(f"controller file {str(path)!r}: the paper's law is stored as a gains file (L, k, D_hat); "
                         f"give it with --gains")
    return _law_from_params(doc["controller"], doc.get("params"), f"controller file {str(path)!r}")


def _read(path) -> dict:
    """The JSON object in ``path`` (``ValueError`` naming the file if it cannot be read or is not one)."""
    p = Path(path)
    try:
        doc = json.loads(p.read_text())
    except OSError as e:
        raise ValueError(f"cannot read controller file {str(p)!r} ({e.strerror or e})") from None
    except (ValueError, UnicodeDecodeError) as e:
        raise ValueError(f"controller file {str(p)!r} is not valid JSON ({e}); write it with jaxsleigh tune "
                         f"--controller NAME --out FILE.json") from None
    if not isinstance(doc, dict):
        raise ValueError(f"controller file {str(p)!r} must hold a JSON object, got {type(doc).__name__}")
    return doc


def _law_from_params(name, params, source: str):
    """The registered law ``name`` with its numeric leaves set from ``params`` (``{leaf name: value}``)."""
    if not isinstance(name, str):
        raise ValueError(f"{source}: \"controller\" must be a name (jaxsleigh controllers lists them), got {name!r}")
    law = make_controller(name)
    names = list(law_leaf_names(law))
    if not isinstance(params, dict):
        raise ValueError(f"{source}: \"params\" must be an object {{name: value}} of the law's parameters "
                         f"({', '.join(names)})")
    missing, unknown = [n for n in names if n not in params], sorted(set(params) - set(names))
    if missing or unknown:
        raise ValueError(f"{source}: the {name} law's parameters are {', '.join(names)}"
                         + (f"; missing {', '.join(missing)}" if missing else "")
                         + (f"; unknown {', '.join(unknown)}" if unknown else ""))
    leaves, tree = jax.tree_util.tree_flatten(law)
    law = jax.tree_util.tree_unflatten(tree, [_leaf(params[n], old, n, source) for n, old in zip(names, leaves)])
    return as_controller(law, name=f"law in {source}")


def _leaf(value, old, name: str, source: str):
    """``value`` in the kind of the default leaf ``old``: a Python float for a float, else an array of its shape."""
    try:
        a = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        a = None
    if a is None or a.shape != np.shape(old) or not np.all(np.isfinite(a)):
        raise ValueError(f"{source}: parameter {name} must be finite numbers of shape {list(np.shape(old))}, "
                         f"got {value!r}")
    if isinstance(old, float):
        return float(a)
    return a.astype(np.asarray(old).dtype)
