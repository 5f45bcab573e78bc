r"""Per-trajectory ("per-lane") plant parameters and gains.

The closed-loop vector field is written on components, so every leaf of ``ClosedLoop(plant, gains)``
may carry a *trailing* batch axis that broadcasts against the batch-last state ``(5, N)`` of the
stepper: ``m``, ``J``, ``l``, ``k`` and the damping model's numbers of shape ``(N,)``, ``L`` of shape
``(3, N)``, ``D_hat`` of shape ``(2, 2, N)``. Because the values are traced leaves (not static
arguments), changing them never recompiles; only the batch size is part of the compiled shape.

This module holds the host-side helpers that make such "lanes" usable by every entry point:

* `lane_count` (how many lanes, ``None`` for one plant) and `check_lanes` (eager,
  vectorised validation, with messages naming the first bad lane);
* `broadcast_lanes` (every leaf to ``base_shape + (n,)``, the canonical form the engine
  runs) and `take_lanes` (gather lanes: chunking, padding, batch compaction);
* `stack_plants` / `stack_gains` (lanes from lists of ordinary ``PlantParams`` /
  ``Gains``) and `lane_table` (the per-row record of the parameters a run used).

The damping *family* (Coulomb, viscous, none, custom) is a Python class, a static choice: lanes
of one run share the family and differ in its numbers.
"""
from __future__ import annotations


import hashlib
from typing import Any, Optional, Sequence

import jax
import numpy as np

from .damping import CoulombDamping, CustomDamping, NoDamping, ViscousDamping, as_damping, damping_from_name
from .controller import PerTrajectory, as_controller, law_leaf_names
from .params import Gains, PlantParams, as_gains, as_plant

__all__ = ["lane_count", "check_lanes", "broadcast_lanes", "take_lanes", "has_lanes", "stack_plants",
           "stack_gains", "lane_table", "lanes_digest", "DAMPING_FIELDS"]

#: Numeric fields of each damping family, with the names used in records and sweeps.
DAMPING_FIELDS = {CoulombDamping: {"eps": "coulomb_eps", "scale": "coulomb_scale"},
                  ViscousDamping: {"c1": "c1", "c2": "c2"}, NoDamping: {}, CustomDamping: {}}


def _lane_axes(law):
    """The law's own per-trajectory fields ``((field, base_ndim), ...)`` (``lane_axes``, `jaxsleigh.Gains`), or
    ``None`` for a law whose lanes come wrapped in `PerTrajectory` (or that is no law: a preset name, file, dict)."""
    return getattr(type(law), "lane_axes", None)


def _named_leaves(plant: PlantParams, law):
    """``(path, leaf, base_ndim)`` for every numeric leaf of a plant and of a law that carries its own lanes
    (`_lane_axes`; none for another)."""
    out = [(f"plant.{f}", getattr(plant, f), 0) for f in ("m", "J", "l")]
    d = plant.damping
    if hasattr(d, "_fields"):
        out += [(f"plant.damping.{f}", getattr(d, f), 0) for f in d._fields]
    out += [(f"gains.{f}", getattr(law, f), base) for f, base in (_lane_axes(law) or ())]
    return out


def _lane_size(path: str, leaf, base: int) -> Optional[int]:
    nd = np.ndim(leaf)
    if nd == base:
        return None
    if nd == base + 1:
        return int(np.shape(leaf)[-1])
    if path == "gains.D_hat" and nd == 1:
        return None                                   # a length-2 diagonal, one trajectory
    want = {0: "a number or an (N,) array", 1: "(3,) or (3, N)", 2: "(2, 2) or (2, 2, N)"}[base]
    raise ValueError(f"{path} must have shape {want} (a per-trajectory leaf carries the batch as its "
                     f"last axis), got {np.shape(leaf)}")


def has_lanes(plant: Any, gains: Any) -> bool:
    """True when a leaf of ``plant`` or ``gains`` carries a per-trajectory axis."""
    return lane_count(plant, gains) is not None


def lane_count(plant: Any, gains: Any) -> Optional[int]:
    """The number of lanes ``P`` of ``plant`` and ``gains`` (``None``: one plant and one set of gains).

    Only `PlantParams` / `Gains` can carry lanes (a preset name, file or dict cannot).
    Leaves of size 1 broadcast; two leaves with different sizes > 1 are an error.
    """
    p = plant if isinstance(plant, PlantParams) else PlantParams()
    law_sizes = {}
    if isinstance(gains, PerTrajectory):          # a user's law with a lane axis on every leaf
        law_sizes = {f"controller.{k}": int(np.shape(v)[-1]) for k, v in law_leaf_names(gains).items()}
    if isinstance(p.damping, str):
        p = p._replace(damping=damping_from_name(p.damping))
    sizes = dict(law_sizes)
    for path, leaf, base in _named_leaves(p, gains):
        s = _lane_size(path, leaf, base)
        if s is not None:
            sizes[path] = s
    if isinstance(gains, PerTrajectory) and not sizes:
        return 1                                   # a PerTrajectory law without leaves: one lane for all
    big = {k: v for k, v in sizes.items() if v != 1}
    if len(set(big.values())) > 1:
        detail = ", ".join(f"{k} {v}" for k, v in big.items())
        raise ValueError(f"per-trajectory parameters must all have the same number of lanes (last axis), got "
                         f"{detail}")
    if not sizes:
        return None
    return next(iter(big.values())) if big else 1


def _bad(path: str, cond: np.ndarray, values: np.ndarray, need: str, flags: Optional[dict]) -> None:
    if np.all(cond):
        return
    i = int(np.flatnonzero(~cond)[0])
    name = (flags or {}).get(path, path)
    v = values.reshape(-1, values.shape[-1])[:, i] if values.ndim > 1 else values[i]
    v = v.tolist() if np.ndim(v) else float(v)
    raise ValueError(f"{name} must be {need}, got {v} in lane {i} ({int((~cond).sum())} of {cond.size} lanes "
                     f"bad)")


def _real(path: str, leaf, flags) -> np.ndarray:
    arr = np.asarray(leaf)
    if arr.dtype == bool or np.iscomplexobj(arr) or not np.issubdtype(arr.dtype, np.number):
        raise ValueError(f"{(flags or {}).get(path, path)} must hold real numbers, got dtype {arr.dtype}")
    arr = arr.astype(np.float64)
    fin = np.isfinite(arr)
    cond = fin.reshape(-1, fin.shape[-1]).all(axis=0) if arr.ndim else np.atleast_1d(fin)
    _bad(path, cond, arr if arr.ndim else arr[None], "finite", flags)
    return arr


def check_lanes(plant: Any, gains: Any, *, flags: Optional[dict] = None) -> tuple[PlantParams, Gains]:
    """Validate per-lane ``plant`` / ``gains`` eagerly, every lane at once; returns them with float64
    NumPy leaves (``D_hat`` as ``(2, 2)`` or ``(2, 2, P)``).

    ``plant`` / ``gains`` may also be ``None`` (the paper's), and ``gains`` a preset name, file or
    dict (then it has no lanes). The conditions are those of `plant_params`
    and `gains`, per lane: ``m > 0``, ``J >= 0``, ``l >= 0``, every
    ``L_i > 0``, ``k > 0``, ``D_hat`` symmetric positive definite, Coulomb ``eps > 0``,
    ``scale >= 0``, viscous ``c1, c2 >= 0``. ``flags`` maps leaf paths (``"plant.m"``,
    ``"gains.D_hat"``, ...) to names used in messages (e.g. ``"--param m=..."``).
    """
    n = lane_count(plant, gains)
    plant, gains, law = _resolved(plant, gains)
    d = as_damping(plant.damping)
    m, J, l = (_real(f"plant.{f}", getattr(plant, f), flags) for f in ("m", "J", "l"))
    for path, v, cond, need in (("plant.m", m, m > 0, "> 0"), ("plant.J", J, J >= 0, ">= 0"),
                                ("plant.l", l, l >= 0, ">= 0 (l = 0 is the knife edge)")):
        _bad(path, np.atleast_1d(cond), np.atleast_1d(v), need, flags)
    d = _checked_damping(d, flags)
    L = _checked_L(gains.L, flags)
    k = _real("gains.k", gains.k, flags)
    _bad("gains.k", np.atleast_1d(k > 0), np.atleast_1d(k), "> 0", flags)
    gains = Gains(L, k, _checked_D_hat(gains.D_hat, flags))
    plant = PlantParams(m, J, l, d)
    if n is not None:
        mass = np.atleast_1d(J + m * l * l)
        _bad("plant.J", mass > 0, np.atleast_1d(J) + 0 * mass, "such that J + m l^2 > 0", flags)
    return plant, (gains if law is None else law)


def _resolved(plant: Any, gains: Any) -> tuple[Any, Any, Any]:
    """``(plant, gains, law)`` for `check_lanes`: a plant or gains without lanes (or ``None``, a preset name,
    file or dict) checked and made whole by `as_plant` / `as_gains`; a user's law checked by
    `as_controller` and returned as ``law`` (then ``gains`` are the paper's, unused)."""
    if plant is None or (isinstance(plant, PlantParams) and lane_count(plant, None) is None):
        plant = as_plant(plant)
    law = None
    if gains is not None and not isinstance(gains, (Gains, str, dict)) and callable(gains):
        law, gains = as_controller(gains), None    # a user's law: checked as a controller, plant per lane
    if lane_count(None, gains) is None:          # no lanes (or a preset name, file, dict): checked whole
        gains = as_gains(gains)
    if not isinstance(plant, PlantParams):
        raise ValueError(f"plant must be a PlantParams, got {type(plant).__name__}")
    return plant, gains, law


def _checked_damping(d, flags):
    """A damping model with its numbers checked per lane (Coulomb ``eps > 0``, ``scale >= 0``; viscous
    ``c1, c2 >= 0``) as float64 NumPy leaves; models without numbers as they are."""
    if isinstance(d, CoulombDamping):
        eps_, scale = _real("plant.damping.eps", d.eps, flags), _real("plant.damping.scale", d.scale, flags)
        _bad("plant.damping.eps", np.atleast_1d(eps_ > 0), np.atleast_1d(eps_), "> 0", flags)
        _bad("plant.damping.scale", np.atleast_1d(scale >= 0), np.atleast_1d(scale), ">= 0", flags)
        d = CoulombDamping(eps_, scale)
    elif isinstance(d, ViscousDamping):
        c1, c2 = _real("plant.damping.c1", d.c1, flags), _real("plant.damping.c2", d.c2, flags)
        _bad("plant.damping.c1", np.atleast_1d(c1 >= 0), np.atleast_1d(c1), ">= 0", flags)
        _bad("plant.damping.c2", np.atleast_1d(c2 >= 0), np.atleast_1d(c2), ">= 0", flags)
        d = ViscousDamping(c1, c2)
    return d


def _checked_L(leaf, flags) -> np.ndarray:
    """``gains.L`` as float64, checked: shape ``(3,)`` or ``(3, N)``, every entry of every lane ``> 0``."""
    L = _real("gains.L", leaf, flags)
    if L.shape[0] != 3:
        raise ValueError(f"gains.L must have shape (3,) or (3, N), got {L.shape}")
    _bad("gains.L", np.all((L > 0).reshape(3, -1), axis=0), L.reshape(3, -1), "> 0 in every entry", flags)
    return L


def _checked_D_hat(leaf, flags) -> np.ndarray:
    """``gains.D_hat`` as float64 ``(2, 2)`` or ``(2, 2, N)`` (a length-2 diagonal made a matrix), checked
    symmetric positive definite in every lane."""
    D = _real("gains.D_hat", leaf, flags)
    if D.ndim == 1:
        D = np.diag(D)
    if D.shape[:2] != (2, 2):
        raise ValueError(f"gains.D_hat must have shape (2, 2) or (2, 2, N), got {D.shape}")
    D3 = D.reshape(2, 2, -1)
    _bad("gains.D_hat", np.isclose(D3[0, 1], D3[1, 0], rtol=1e-12, atol=1e-12), D3, "symmetric", flags)
    det = D3[0, 0] * D3[1, 1] - D3[0, 1] * D3[1, 0]
    _bad("gains.D_hat", (D3[0, 0] > 0) & (det > 0), D3, "positive definite (d11 > 0, d11 d22 - d12^2 > 0)",
         flags)
    return D


def broadcast_lanes(plant: PlantParams, gains: Gains, n: int) -> tuple[PlantParams, Gains]:
    """Every numeric leaf as a float64 array of shape ``base_shape + (n,)`` (the canonical per-lane
    form the engine runs and gathers). Leaves without lanes, or with one, are repeated."""
    def bc(path, leaf, base):
        a = np.asarray(leaf, np.float64)
        if path == "gains.D_hat" and a.ndim == 1:
            a = np.diag(a)
        if a.ndim == base:
            a = a[..., None]
        if a.shape[-1] not in (1, n):
            raise ValueError(f"{path} has {a.shape[-1]} lanes but the batch has {n} trajectories; give one "
                             f"value per trajectory (or one for all)")
        return np.ascontiguousarray(np.broadcast_to(a, a.shape[:-1] + (n,)))

    d = plant.damping
    if hasattr(d, "_fields"):
        d = type(d)(*(bc(f"plant.damping.{f}", getattr(d, f), 0) for f in d._fields))
    p = PlantParams(*(bc(f"plant.{f}", getattr(plant, f), 0) for f in ("m", "J", "l")), d)
    axes = _lane_axes(gains)
    if axes is None:                              # a law with lanes wrapped: every leaf gets the lane axis
        laned = isinstance(gains, PerTrajectory)
        inner = gains.law if laned else gains
        g = PerTrajectory(jax.tree_util.tree_map(
            lambda a: bc("controller", a, np.ndim(a) - 1 if laned else np.ndim(a)), inner))
        return p, g
    return p, type(gains)(**{f: bc(f"gains.{f}", getattr(gains, f), base) for f, base in axes})


def take_lanes(tree, idx):
    """Gather lanes ``idx`` along the last axis of every leaf (of canonical per-lane pytrees)."""
    return jax.tree_util.tree_map(lambda a: a[..., idx], tree)


def stack_plants(plants: Sequence[PlantParams]) -> PlantParams:
    """One per-lane `PlantParams` from a list of plants that share a damping family."""
    plants = list(plants)
    if not plants:
        raise ValueError("stack_plants needs at least one plant")
    kinds = {type(p.damping) for p in plants}
    if len(kinds) != 1:
        raise ValueError(f"the plants of one run must share a damping family, got {sorted(k.__name__ for k in kinds)}; "
                         "run one sweep per family")
    d0 = plants[0].damping
    d = type(d0)(*(np.array([float(getattr(p.damping, f)) for p in plants]) for f in d0._fields)) \
        if hasattr(d0, "_fields") else d0
    return PlantParams(*(np.array([float(getattr(p, f)) for p in plants]) for f in ("m", "J", "l")), d)


def stack_gains(gains: Sequence[Gains]) -> Gains:
    """One per-lane `Gains` (``L`` (3, P), ``k`` (P,), ``D_hat`` (2, 2, P)) from a list."""
    gains = list(gains)
    if not gains:
        raise ValueError("stack_gains needs at least one set of gains")
    D = [np.asarray(g.D_hat, np.float64) for g in gains]
    D = [np.diag(x) if x.ndim == 1 else x for x in D]
    return Gains(np.stack([np.asarray(g.L, np.float64) for g in gains], axis=-1),
                 np.array([float(g.k) for g in gains]), np.stack(D, axis=-1))


def lane_table(plant: PlantParams, gains: Gains, n: int) -> dict:
    """The parameters each of ``n`` rows used: ``{name: (n,) float64}`` with names ``m, J, l``, the
    damping's numbers (``coulomb_eps, coulomb_scale`` or ``c1, c2``), ``k, l1, l2, l3, d11, d12, d22``."""
    p, g = broadcast_lanes(plant, gains, n)
    out = {"m": p.m, "J": p.J, "l": p.l}
    for f, name in DAMPING_FIELDS.get(type(p.damping), {}).items():
        out[name] = getattr(p.damping, f)
    columns = getattr(g, "lane_columns", None)
    if columns is None:                           # a law without its own columns: its scalar leaves, by name
        out.update({k: v for k, v in law_leaf_names(g).items() if np.ndim(v) == 1})
    else:
        out.update(columns())
    return {k: np.asarray(v, np.float64) for k, v in out.items()}


def lanes_digest(plant: PlantParams, gains: Gains) -> str:
    """SHA-256 of every numeric leaf (as float64 bytes, with its shape): part of the fingerprint of a
    checkpointed run, so a resume with other per-lane values is refused."""
    h = hashlib.sha256()
    if _lane_axes(gains) is None:
        for path, leaf in law_leaf_names(gains).items():
            a = np.ascontiguousarray(np.asarray(leaf, np.float64))
            h.update(f"controller.{path}{a.shape}".encode())
            h.update(a.tobytes())
        h.update(repr(jax.tree_util.tree_structure(gains)).encode())
        # then unit gains in the paper's leaves' place: the bytes every digest so far was made of (a checkpoint
        # written before stays resumable)
        gains = Gains(np.ones(3), 1.0, np.eye(2))
    for path, leaf, _ in _named_leaves(plant, gains):
        a = np.ascontiguousarray(np.asarray(leaf, np.float64))
        h.update(f"{path}{a.shape}".encode())
        h.update(a.tobytes())
    h.update(type(plant.damping).__name__.encode())
    return h.hexdigest()
