"""Parameters of the plant and gains of the controller: small frozen pytrees.

Numeric fields are leaves, so ``jax.grad`` / ``jax.vmap`` work over them. Build them with
`plant_params` and `gains` (or the presets) to get eager validation with messages
that say what to change; the raw ``NamedTuple`` constructors do no checking (they must also
accept tracers inside transformed code).
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, NamedTuple

import jax
import numpy as np

from . import paper_law
from .coordinates import q_to_w
from .damping import CoulombDamping, ViscousDamping, as_damping
from ..validate import real
from ..files.npz import atomic_write_text

__all__ = [
    "PlantParams",
    "Gains",
    "plant_params",
    "gains",
    "paper_plant",
    "paper_gains",
    "load_gains",
    "preset_names",
    "save_gains",
    "gains_to_dict",
    "gains_from_dict",
    "as_gains",
    "as_plant",
    "lane_record",
    "is_concrete",
]


class PlantParams(NamedTuple):
    r"""Chaplygin sleigh plant (paper eq. 1-2).

    \[ M = \mathrm{diag}(m,\ J + m l^2), \qquad J(p) = \frac{m l}{J + m l^2}\begin{bmatrix}0 & p_2\\ -p_2 & 0\end{bmatrix} \]

    Attributes:
      m: mass (> 0).
      J: rotational inertia about the centre of mass (>= 0; ``J + m l^2`` must be > 0).
      l: distance from the contact point to the centre of mass (>= 0; 0 is the knife edge).
      damping: a model from `jaxsleigh.model.damping` (the paper's Coulomb approximation by default).
    """

    m: Any = 2.0
    J: Any = 1.0
    l: Any = 1.0
    damping: Any = CoulombDamping()


class Gains(NamedTuple):
    r"""Gains of the discontinuous energy-shaping law (paper eq. 13).

    \[ u = -Q_w^\top L w - \hat D \nabla_p H - \mathrm{diag}(0, k / w_1^2)\, \nabla_p H \]

    Attributes:
      L: (3,) diagonal of \(L\) (each > 0).
      k: singular damping gain (> 0).
      D_hat: (2, 2) positive definite damping injection \(\hat D\).
    """

    L: Any
    k: Any
    D_hat: Any

    # The law interface (`jaxsleigh.model.controller`): class attributes, not fields (no annotation: a
    # NamedTuple would make them leaves). The law is integrated in the w chart (`jaxsleigh.model.w_laws`),
    # where it is port-Hamiltonian and its singular set theta = 0 is never crossed.
    w_chart = True
    # Per-trajectory leaves (`jaxsleigh.model.lanes`): each field with its number of axes for one trajectory; a
    # per-trajectory field carries one more, last (L (3, N), k (N,), D_hat (2, 2, N)). The law is written on
    # components, so such leaves broadcast against the batch-last state as they are (no `PerTrajectory`, no vmap).
    lane_axes = (("L", 1), ("k", 0), ("D_hat", 2))

    def __call__(self, q, v):
        r"""\(u\) from the measured \(q\) and \(v = \nabla_p H\), in the physical chart (infinite on
        \(\theta = 0\)): what a law called as ``u = law(q, v)`` returns."""
        return paper_law.control_w(q_to_w(q), v, self)

    def potential(self, w):
        r"""\(V(w) = \tfrac12 w^\top L w\) (`jaxsleigh.model.w_laws.potential`)."""
        return paper_law.potential(w, self)

    def control_w_components(self, w, v):
        r"""\(u\) on components, from \(w\) and \(v = \nabla_p H\) (eq. 13)."""
        return paper_law.control_w_components(w, v, self)

    def injection_components(self, w, v):
        r"""\((\hat D + \mathrm{diag}(0, k / w_1^2)) v\) on components."""
        return paper_law.damping_injection_components(w, v, self)

    def stiff_coeff(self, w):
        r"""\(\hat D_{22} + k / w_1^2\): the coefficient of \(-v_2\) in the turning moment."""
        return self.D_hat[1, 1] + self.k / (w[0] * w[0])

    def w2_stiffness(self, w):
        r"""\(\partial^2 V / \partial w_2^2 = L_2\), whatever \(w\)."""
        return self.L[1]

    def lane_columns(self) -> dict:
        """The per-row columns of a run's lane table (`jaxsleigh.model.lanes.lane_table`), from lanes broadcast to
        one per row: ``k, l1, l2, l3, d11, d12, d22``."""
        return dict(k=self.k, l1=self.L[0], l2=self.L[1], l3=self.L[2], d11=self.D_hat[0, 0], d12=self.D_hat[0, 1],
                    d22=self.D_hat[1, 1])

    def damping_floor(self):
        r"""\(d\) with \(\hat D + \mathrm{diag}(0, k / w_1^2) \succeq d\, I\): the smallest eigenvalue of the
        symmetric part of \(\hat D\), per lane (``(P,)`` with per-trajectory gains, else a scalar array), for the
        certificate of `jaxsleigh.integrate.stragglers` (it needs \(H_d \ge 0\), so \(L, k \ge 0\)); ``None``
        where it does not apply: values not concrete, \(L\) or \(k\) negative somewhere, \(d \le 0\) everywhere."""
        try:
            D = np.asarray(self.D_hat, np.float64)
            L = np.asarray(self.L, np.float64)
            k = np.asarray(self.k, np.float64)
        except Exception:           # noqa: BLE001 - traced gains: no certificate
            return None
        if np.any(L < 0) or np.any(k < 0) or D.shape[:2] != (2, 2):
            return None
        a, c, b = D[0, 0], D[1, 1], 0.5 * (D[0, 1] + D[1, 0])
        d = 0.5 * (a + c) - np.sqrt(0.25 * (a - c) ** 2 + b * b)
        d = np.where(np.isfinite(d), d, 0.0)
        if not np.any(d > 0):
            return None
        return d


def is_concrete(x) -> bool:
    """No leaf of ``x`` is a tracer (its numbers are known now, not inside ``jit``/``grad``/``vmap``)."""
    return not any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(x))


def _finite_scalar(name, value, *, hint):
    try:
        return real(name, value)
    except ValueError as e:
        raise ValueError(f"{e}. {hint}") from None


def _real_array(name, value, *, hint) -> np.ndarray:
    """A float64 array from real numbers only (no bools, complex numbers or strings)."""
    arr = np.asarray(value)
    if arr.dtype == bool or np.iscomplexobj(arr) or not (np.issubdtype(arr.dtype, np.number)
                                                          or arr.dtype == object):
        raise ValueError(f"{name} must hold real numbers, got {value!r}. {hint}")
    if arr.dtype == object:
        flat = list(arr.ravel())
        if any(isinstance(v, (bool, np.bool_, str, complex)) for v in flat):
            raise ValueError(f"{name} must hold real numbers, got {value!r}. {hint}")
    try:
        return arr.astype(float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must hold real numbers, got {value!r}. {hint}") from None


def plant_params(m=2.0, J=1.0, l=1.0, damping="coulomb") -> PlantParams:
    """Validated `PlantParams` (defaults: the paper's m = 2, J = 1, l = 1, Coulomb damping).

    ``damping`` is a model from `jaxsleigh.model.damping`, one of ``'coulomb' | 'viscous' | 'none'``,
    or a callable ``D(q, p) -> (2, 2)`` (wrapped in `CustomDamping`).
    """
    hint = "Plant parameters are (m, J, l): m > 0, J >= 0, l >= 0, e.g. --params 2,1,1."
    m = _finite_scalar("m", m, hint=hint)
    J = _finite_scalar("J", J, hint=hint)
    l = _finite_scalar("l", l, hint=hint)
    if m <= 0:
        raise ValueError(f"mass m must be > 0, got {m}. {hint}")
    if J < 0:
        raise ValueError(f"inertia J must be >= 0, got {J}. {hint}")
    if l < 0:
        raise ValueError(f"offset l must be >= 0 (l = 0 is the knife edge), got {l}. {hint}")
    if J + m * l * l <= 0:
        raise ValueError(f"J + m l^2 must be > 0, got {J + m * l * l}. {hint}")
    damping = as_damping(damping)
    if isinstance(damping, CoulombDamping):
        eps_ = _finite_scalar("CoulombDamping.eps", damping.eps, hint="e.g. CoulombDamping(eps=0.1, scale=1.0)")
        scale = _finite_scalar("CoulombDamping.scale", damping.scale, hint="e.g. CoulombDamping(eps=0.1, scale=1.0)")
        if not (eps_ > 0 and scale >= 0):
            raise ValueError(f"CoulombDamping needs eps > 0 and scale >= 0, got {damping}")
    if isinstance(damping, ViscousDamping):
        c1 = _finite_scalar("ViscousDamping.c1", damping.c1, hint="e.g. ViscousDamping(c1=1.0, c2=1.0)")
        c2 = _finite_scalar("ViscousDamping.c2", damping.c2, hint="e.g. ViscousDamping(c1=1.0, c2=1.0)")
        if not (c1 >= 0 and c2 >= 0):
            raise ValueError(f"ViscousDamping needs c1, c2 >= 0, got {damping}")
    return PlantParams(m, J, l, damping)


def gains(L=(2.0, 0.5, 0.8), k=0.1, D_hat=(4.0, 8.0)) -> Gains:
    """Validated `Gains` (defaults: the paper's ``L = diag(2, 0.5, 0.8)``, ``k = 0.1``,
    ``D_hat = diag(4, 8)``). ``D_hat`` may be a length-2 diagonal or a 2x2 matrix."""
    hint = ('Gains are {"L": [l1, l2, l3], "k": k, "D_hat": [d1, d2] or [[a, b], [c, d]]} '
            "with every l_i > 0, k > 0 and D_hat symmetric positive definite.")
    L_arr = _real_array("L", L, hint=hint)
    if L_arr.shape != (3,):
        raise ValueError(f"L must have 3 entries (the diagonal of L), got shape {L_arr.shape}. {hint}")
    if not np.all(np.isfinite(L_arr)) or np.any(L_arr <= 0):
        raise ValueError(f"every entry of L must be finite and > 0, got {L_arr.tolist()}. {hint}")
    k = _finite_scalar("k", k, hint=hint)
    if k <= 0:
        raise ValueError(f"k must be > 0 (k = 0 loses the invariance of theta != 0), got {k}. {hint}")
    D = _real_array("D_hat", D_hat, hint=hint)
    if D.shape == (2,):
        D = np.diag(D)
    if D.shape != (2, 2):
        raise ValueError(f"D_hat must be a length-2 diagonal or a 2x2 matrix, got shape {D.shape}. {hint}")
    if not np.all(np.isfinite(D)):
        raise ValueError(f"D_hat must be finite, got {D.tolist()}. {hint}")
    if not np.allclose(D, D.T, rtol=1e-12, atol=1e-12):
        raise ValueError(f"D_hat must be symmetric, got {D.tolist()}. {hint}")
    if np.linalg.eigvalsh(D).min() <= 0:
        raise ValueError(f"D_hat must be positive definite, got eigenvalues "
                         f"{np.linalg.eigvalsh(D).tolist()}. {hint}")
    # numpy float64 leaves: jit casts them to the working dtype, float64 runs keep full precision
    return Gains(L_arr, np.float64(k), D)


def paper_plant() -> PlantParams:
    """The plant of the paper's simulation: m = 2, J = 1, l = 1, Coulomb damping."""
    return plant_params()


def paper_gains() -> Gains:
    """The gains of the paper's simulation: L = diag(2, 0.5, 0.8), k = 0.1, D_hat = diag(4, 8)."""
    return gains()


def gains_to_dict(g: Gains) -> dict:
    """JSON-ready ``{"L": [...], "k": k, "D_hat": [[..], [..]]}``; a leaf that varies per trajectory
    (a trailing lane axis, see `jaxsleigh.model.lanes`) is recorded as ``{"per_trajectory": P, "min",
    "max"}``."""
    L, D = np.asarray(g.L, dtype=float), np.asarray(g.D_hat, dtype=float)
    return {"L": [float(x) for x in L] if L.ndim == 1 else lane_record(L),
            "k": float(g.k) if np.ndim(g.k) == 0 else lane_record(g.k),
            "D_hat": D.tolist() if D.ndim <= 2 else lane_record(D)}


def gains_from_dict(d: dict, *, source: str = "gains") -> Gains:
    """Validated gains from the JSON format ``{"L": [..], "k": k, "D_hat": [..]}``; every key is
    required (a file that omits one is refused rather than silently completed with the paper's)."""
    if not isinstance(d, dict):
        raise ValueError(f"{source} must hold a JSON object, got {type(d).__name__}")
    unknown = set(d) - {"L", "k", "D_hat", "note", "meta"}
    if unknown:
        raise ValueError(f"unknown keys in {source}: {sorted(unknown)}; expected L, k, D_hat")
    missing = [k for k in ("L", "k", "D_hat") if k not in d]
    if missing:
        paper = gains_to_dict(paper_gains())
        raise ValueError(f"{source} lacks {', '.join(missing)}; give every one of L, k, D_hat (the paper's: "
                         + ", ".join(f'"{k}": {json.dumps(paper[k])}' for k in missing) + ")")
    try:
        return gains(d["L"], d["k"], d["D_hat"])
    except ValueError as e:
        raise ValueError(f"{source}: {e}") from None


def preset_names() -> list[str]:
    """Names of the shipped gain presets (``'paper'`` and one per ``presets/*.json``)."""
    return ["paper"] + sorted(p.stem for p in (Path(__file__).parent.parent / "presets").glob("*.json"))


def load_gains(spec) -> Gains:
    """Gains from a preset name (`preset_names`: ``'paper'``, ``'tuned'``, ...) or a JSON file."""
    if isinstance(spec, Gains):
        return spec
    spec = str(spec)
    if spec == "paper":
        return paper_gains()
    presets = preset_names()
    path = Path(__file__).parent.parent / "presets" / f"{spec}.json"
    if spec not in presets:
        path = Path(spec)
        if not path.is_file():
            if (Path(__file__).parent.parent / "presets" / "controllers" / f"{spec}.json").is_file():
                # a law's preset ("shaped"), not gains (the command line says --controller: controllers.registry)
                raise ValueError(f"{spec!r} is a controller of its own, not gains of the paper's law; pass "
                                 f"controller=make_controller({spec!r}) (jaxsleigh.controllers.registry) instead of "
                                 f"gains")
            what = "is a folder" if path.is_dir() else "not found"
            raise ValueError(f"gains file {spec!r} {what}; give a JSON gains file or a preset "
                             f"({', '.join(repr(n) for n in presets)})")
    try:
        d = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"gains file {str(path)!r} is not valid JSON ({e}); write "
                         '{"L": [l1, l2, l3], "k": k, "D_hat": [d1, d2]}') from None
    except OSError as e:
        raise ValueError(f"cannot read gains file {str(path)!r} ({e.strerror or e})") from None
    return gains_from_dict(d, source=f"gains file {str(path)!r}")


def save_gains(g: Gains, path, **meta) -> None:
    """Write gains in the JSON format (``meta`` is stored under ``"meta"``)."""
    d = gains_to_dict(g)
    if meta:
        d["meta"] = meta
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(d, indent=2, default=str) + "\n")


def lane_record(leaf) -> Any:
    """JSON-ready record of a leaf that varies per trajectory: ``{"per_trajectory": P, "min", "max"}``
    (the values themselves go with the rows, see `jaxsleigh.model.lanes.lane_table`)."""
    a = np.asarray(leaf, np.float64)
    return {"per_trajectory": int(a.shape[-1]), "min": float(a.min()), "max": float(a.max())}


def as_gains(g, name: str = "gains"):
    """Validated `Gains` from ``None`` (the paper's), a preset name
    (``"paper"``, ``"tuned"``, ...), a gains-file path, a dict in the file format, or a ``Gains``
    (re-checked: every ``L_i > 0``, ``k > 0``, ``D_hat`` symmetric positive definite)."""
    if g is None:
        return paper_gains()
    if isinstance(g, (str, Path)):
        return load_gains(g)
    if isinstance(g, dict):
        return gains_from_dict(g)
    if isinstance(g, Gains):
        for leaf_name, leaf in zip(Gains._fields, g):
            arr = np.asarray(leaf)
            if arr.dtype == bool or not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr):
                raise ValueError(f"{name}.{leaf_name} must be real numbers, got {leaf!r}")
        return gains(g.L, g.k, g.D_hat)
    raise ValueError(f"{name} must be a Gains (jaxsleigh.gains(...)), a preset name ('paper', 'tuned'), "
                     f"a gains JSON file or a dict, got {type(g).__name__}")


def as_plant(p, name: str = "plant"):
    """Validated `PlantParams` from ``None`` (the paper's) or a
    ``PlantParams`` (re-checked: ``m > 0``, ``J >= 0``, ``l >= 0``, a known damping model)."""
    if p is None:
        return paper_plant()
    if isinstance(p, PlantParams):
        for leaf_name in ("m", "J", "l"):
            leaf = getattr(p, leaf_name)
            real(f"{name}.{leaf_name}", leaf)
        return plant_params(p.m, p.J, p.l, damping=p.damping)
    raise ValueError(f"{name} must be a PlantParams (jaxsleigh.plant_params(m, J, l, damping)), "
                     f"got {type(p).__name__}")
