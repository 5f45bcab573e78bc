r"""Parametrisation of the gains in unconstrained coordinates (every parameter vector is admissible).

\(L = e^{\ell}\), \(k = e^{\kappa}\), \(\hat D = C C^\top + \delta I\) with
\(C = \begin{bmatrix} e^{c_0} & 0 \\ c_1 & e^{c_2} \end{bmatrix}\); a subset of the gains may be
tuned while the others stay frozen (`split_params` / `merge_params`).
"""
from __future__ import annotations

from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from ..model.params import Gains, gains as make_gains, load_gains

__all__ = ["GainParams", "TUNABLE", "D_FLOOR", "params_from_gains", "gains_from_params", "parse_tune",
           "split_params", "merge_params", "gains_numpy"]

#: Gains that can be tuned, each mapped to its unconstrained field of :class:`GainParams`.
TUNABLE = {"L": "log_L", "k": "log_k", "D_hat": "d_chol"}
#: Floor :math:`\delta` of :math:`\hat D = C C^\top + \delta I` (its smallest eigenvalue is >= this).
D_FLOOR = 1e-3


class GainParams(NamedTuple):
    r"""Unconstrained coordinates of `Gains`; every value is admissible.

    \[ L = \mathrm{diag}(e^{\ell_1}, e^{\ell_2}, e^{\ell_3}),\quad k = e^{\kappa},\quad \hat D = C C^\top + \delta I,\ C = \begin{bmatrix} e^{c_0} & 0\\ c_1 & e^{c_2}\end{bmatrix} \]

    Attributes:
      log_L: (3,) \(\ell\).
      log_k: () \(\kappa\).
      d_chol: (3,) \((c_0, c_1, c_2)\); the floor \(\delta\) is not a parameter.
    """

    log_L: Any
    log_k: Any
    d_chol: Any


def gains_from_params(theta: GainParams, *, d_floor: float = D_FLOOR) -> Gains:
    """Map unconstrained parameters to gains: ``L > 0``, ``k > 0``, ``D_hat`` symmetric with
    eigenvalues ``>= d_floor`` for every finite ``theta`` (traceable)."""
    L = jnp.exp(theta.log_L)
    k = jnp.exp(theta.log_k)
    c = theta.d_chol
    a, b, d = jnp.exp(c[0]), c[1], jnp.exp(c[2])
    D = jnp.stack([jnp.stack([a * a + d_floor, a * b]), jnp.stack([a * b, b * b + d * d + d_floor])])
    return Gains(L, k, D)


def params_from_gains(g, *, d_floor: float = D_FLOOR) -> GainParams:
    """Inverse of `gains_from_params` (eager, float64 NumPy); ``g`` may be gains or a preset
    name / JSON path. Raises if ``D_hat - d_floor I`` is not positive definite."""
    g = load_gains(g)
    D = np.asarray(g.D_hat, dtype=np.float64) - d_floor * np.eye(2)
    try:
        C = np.linalg.cholesky(D)
    except np.linalg.LinAlgError:
        raise ValueError(f"D_hat = {np.asarray(g.D_hat).tolist()} has an eigenvalue below the floor "
                         f"{d_floor}; use a larger D_hat or a smaller d_floor") from None
    return GainParams(np.log(np.asarray(g.L, dtype=np.float64)), np.float64(np.log(float(g.k))),
                      np.array([np.log(C[0, 0]), C[1, 0], np.log(C[1, 1])]))


def parse_tune(spec) -> tuple[str, ...]:
    """``'L,k'`` / ``('L', 'D_hat')`` / ``None`` (all) -> a tuple of names from `TUNABLE`."""
    if spec is None:
        return tuple(TUNABLE)
    names = [s.strip() for s in (spec.split(",") if isinstance(spec, str) else spec)]
    names = [s for s in names if s]
    bad = [s for s in names if s not in TUNABLE]
    if bad or not names:
        raise ValueError(f"gains to tune must be a non-empty subset of {', '.join(TUNABLE)} "
                         f"(e.g. 'L,k'), got {spec!r}")
    return tuple(s for s in TUNABLE if s in names)


def split_params(theta: GainParams, tune) -> tuple[dict, GainParams]:
    """``(trainable, frozen)``: a dict of the tuned fields and the whole parameter tuple."""
    names = parse_tune(tune)
    return {TUNABLE[n]: theta._asdict()[TUNABLE[n]] for n in names}, theta


def merge_params(trainable: dict, frozen: GainParams) -> GainParams:
    """The parameters with the tuned fields taken from ``trainable`` and the rest from ``frozen``."""
    return frozen._replace(**trainable)


def gains_numpy(trainable, frozen, d_floor, initial: Gains, names) -> Gains:
    """Validated float64 gains; frozen gains are the initial ones, bit for bit."""
    g = gains_from_params(merge_params(trainable, frozen), d_floor=d_floor)
    D = np.asarray(g.D_hat, dtype=np.float64)
    return make_gains(np.asarray(g.L, dtype=np.float64) if "L" in names else initial.L,
                      float(g.k) if "k" in names else initial.k,
                      0.5 * (D + D.T) if "D_hat" in names else initial.D_hat)
