"""Files: the ``.npz`` written by ``jaxsleigh simulate`` and ``jaxsleigh paper`` (a stable contract)."""
from __future__ import annotations

import ast
import json
import math
import operator
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

__all__ = ["write_npz", "npz_path", "damping_name", "parse_number", "load_ics"]


def npz_path(path) -> Path:
    p = Path(path)
    return p if p.suffix == ".npz" else p.with_name(p.name + ".npz")


def write_npz(path, sol, *, ics, command: Optional[Sequence[str]] = None) -> Path:
    """Write a :class:`~jaxsleigh.simulate.Solution` and the settings that produced it.

    Keys: ``t (T,)``, ``q (N, T, 3)``, ``p (N, T, 2)``, ``u (N, T, 2)``, ``Hd (N, T)``,
    ``status (N,)``, ``n_steps (N,)``, ``n_rejected (N,)``, ``ics (N, 5)``; ``settings_json`` (the
    solution's settings plus ``ics``, ``command`` and the status legend, as JSON) and the scalars
    ``dt, t_final, save_every, method, dtype, gains_L, gains_k, gains_D_hat, params (m, J, l),
    damping``. Returns the path written (``.npz`` appended when missing).
    """
    from .status import describe

    path = npz_path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    ics = np.asarray(ics, dtype=np.float64)
    if ics.ndim == 1:
        ics = ics[None]
    if ics.shape[1] == 3:
        ics = np.concatenate([ics, np.zeros((ics.shape[0], 2))], axis=1)
    s = dict(sol.settings)
    settings = {**s, "ics": ics.tolist(), "command": list(command) if command is not None else None,
                "status_codes": describe()}
    plant, g = s["plant"], s["gains"]
    np.savez_compressed(
        path,
        t=np.asarray(sol.t), q=np.asarray(sol.q), p=np.asarray(sol.p), u=np.asarray(sol.u),
        Hd=np.asarray(sol.Hd), status=np.asarray(sol.status, dtype=np.int32),
        n_steps=np.asarray(sol.n_steps), n_rejected=np.asarray(sol.n_rejected), ics=ics,
        settings_json=np.array(json.dumps(settings)),
        dt=np.float64(s["dt"]), t_final=np.float64(s["t_final"]), save_every=np.int64(s["save_every"]),
        method=np.array(s["method"]), dtype=np.array(s["dtype"]),
        gains_L=np.asarray(g["L"], dtype=np.float64), gains_k=np.float64(g["k"]),
        gains_D_hat=np.asarray(g["D_hat"], dtype=np.float64),
        params=np.array([plant["m"], plant["J"], plant["l"]], dtype=np.float64),
        damping=np.array(damping_name(plant["damping"])),
    )
    return path


def damping_name(class_name: str) -> str:
    return {"CoulombDamping": "coulomb", "ViscousDamping": "viscous", "NoDamping": "none"}.get(
        class_name, class_name)


_BINOPS = {ast.Add: operator.add, ast.Sub: operator.sub, ast.Mult: operator.mul, ast.Div: operator.truediv}
_NAMES = {"pi": math.pi, "nan": math.nan, "inf": math.inf}


def parse_number(text: str) -> float:
    """A float from ``'0.39'``, ``'-pi/8'``, ``'3*pi/4'``, ``'1e-3'`` (numbers, pi, + - * /)."""

    def ev(node):
        if isinstance(node, ast.Expression):
            return ev(node.body)
        if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)) \
                and not isinstance(node.value, bool):
            return float(node.value)
        if isinstance(node, ast.Name) and node.id.lower() in _NAMES:
            return _NAMES[node.id.lower()]
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
            v = ev(node.operand)
            return -v if isinstance(node.op, ast.USub) else v
        if isinstance(node, ast.BinOp) and type(node.op) in _BINOPS:
            return _BINOPS[type(node.op)](ev(node.left), ev(node.right))
        raise ValueError

    text = text.strip()
    try:
        return float(text)
    except ValueError:
        pass
    try:
        return ev(ast.parse(text, mode="eval"))
    except (SyntaxError, ValueError, ZeroDivisionError, RecursionError, OverflowError):
        raise ValueError(f"{text!r} is not a number") from None


def load_ics(path, *, hint: str = "") -> np.ndarray:
    """Initial conditions from a ``.npy`` (or ``.txt``/``.csv``) file: float64 (N, 3) or (N, 5).

    Raises ``ValueError`` with a message naming the fix; ``hint`` names the command's alternative.
    """
    p = Path(path)
    if not p.exists():
        raise ValueError(f"initial-conditions file {path!r} not found; give an existing .npy file of "
                         f"shape (N, 3) or (N, 5)" + (f", or {hint}" if hint else ""))
    try:
        if p.suffix.lower() in (".txt", ".csv"):
            arr = np.loadtxt(p, delimiter="," if p.suffix.lower() == ".csv" else None, ndmin=2)
        else:
            arr = np.load(p, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise ValueError(f"could not read initial conditions from {path!r} ({e}); save them with "
                         f"numpy.save as a float array of shape (N, 3) or (N, 5)") from None
    if not isinstance(arr, np.ndarray) or not np.issubdtype(arr.dtype, np.number):
        raise ValueError(f"{path!r} must hold a numeric array of shape (N, 3) or (N, 5)")
    if arr.ndim != 2 or arr.shape[1] not in (3, 5) or arr.shape[0] == 0:
        raise ValueError(f"{path!r} holds an array of shape {arr.shape}; initial conditions must have "
                         f"shape (N, 3) [x, y, theta] or (N, 5) [x, y, theta, p1, p2] with N >= 1")
    return arr.astype(np.float64)
