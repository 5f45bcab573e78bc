"""Files: the ``.npz`` written by ``jaxsleigh simulate`` and ``jaxsleigh paper`` (a stable contract)."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

__all__ = ["write_npz", "npz_path", "damping_name"]


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
