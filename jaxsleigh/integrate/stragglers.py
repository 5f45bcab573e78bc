r"""Stragglers near \(\theta = 0\): a certificate, from \(H_d\), that a trajectory cannot settle before the horizon.

**What the stragglers are.** A start close to the singular set carries a huge \(H_d(0) \sim \theta_0^{-4}\). Measured
on the default 10^5-start basin (`experiments/performance/basin_stragglers.py`), its trajectory has two phases:

1. a *flight*: the sleigh turns away from \(\theta = 0\) within milliseconds and travels \(10^4\)-\(10^5\) m at up
   to \(10^7\) m/s while the injected damping burns \(H_d\) down; the adaptive step is \(10^{-7}\)-\(10^{-5}\) s,
   not set by the float32 rounding floor nor by rejections (~10% of attempts), but by stability: the flight is
   stiff. An explicit step needs ~2e5 attempts for the first second or less (SciPy's RK45 as many, in either chart),
   where the implicit Radau and LSODA (float64, rtol = atol = 1e-8) cross the whole 100 s in ~2e3 steps
   (`experiments/performance/flier_stiffness.py`). The ensembles' engine therefore switches a lane that is still
   flying after `jaxsleigh.integrate.engine.STIFF_AFTER` attempts to the linearly implicit step of
   `jaxsleigh.integrate.rosenbrock`, which carries a flight to the horizon in a few thousand more;
2. a *creep*: the sleigh has stopped (kinetic energy ~1e-9 J) far from the target with \(|w_3| \sim 10^3\), and the
   potential and the damping nearly balance; \(H_d\) stays at ~1e6 J, the sleigh creeps at ~1e-5 m/s, and the
   stiff, lightly damped oscillation of \((w_2, p_2)\) at \(\sim |Q_{w,22}| \sqrt{L_2 / (J + m l^2)}\) rad/s caps
   RK4's step by stability at ~1e-3 s: ~1e5 steps to reach a 100 s horizon, float64 alike, with nothing to learn.

Phase 2 is most of the steps of most stragglers, and it has a cheap answer.

**The certificate.** Along the exact closed loop \(\dot H_d = -v^\top D_d v\) (eq. 18) with
\(v = \nabla_p H\) and \(D_d = D + \hat D + \mathrm{diag}(0, k / w_1^2) \succeq d\, I\), where \(d\) is the smallest
eigenvalue of the symmetric part of \(\hat D\) (the plant's damping \(D\) is positive semi-definite, \(k \ge 0\)).
The configuration moves at \(|\dot q| = |Q(q) v| = |v|\) (\(Q\)'s columns are orthonormal), and
\(H_d \ge 0\) when \(L \ge 0\). So over \([t, T]\), by Cauchy-Schwarz,

\[ |q(T) - q(t)| \le \int_t^T |v|\,ds \le \sqrt{(T - t) \int_t^T |v|^2 ds}
   \le \sqrt{(T - t)\, \frac{H_d(t) - H_d(T)}{d}} \le \sqrt{\frac{(T - t)\, H_d(t)}{d}}. \]

A trajectory settles by the horizon \(T\) only if \(|q(T)| \le \epsilon\) (``T_eps`` finite). Hence if

\[ |q(t)| - \epsilon > c \sqrt{(T - t)\, H_d(t) / d}, \qquad c = `MARGIN` = 2, \]

it cannot settle before \(T\): the engine stops it there with status ``NOT_SETTLING`` (``T_eps = inf``, as for a
trajectory that reached the horizon unsettled; its final state is not computed). The margin \(c\) (4x on the
energy) covers the difference between the computed and the exact \(H_d\) (the adaptive step's tolerances and the
passivity monitor's 1e-6 slack). A stopped creeping straggler qualifies at once: \(H_d \sim 10^6\) J, \(d = 4\) and
\(|q| \sim 10^4\) m give \(T - t \ge 10^3\) s. A flying one does not (its \(H_d\) is still huge): it keeps stepping,
implicitly once past the switch, until it creeps and is certified, or reaches the horizon; only where the budget runs
out first does it end ``BUDGET_EXHAUSTED``.

The check runs on the host between the engine's segments (`jaxsleigh.integrate.engine.drive_final`), at every
lane's same attempt counts, so whether and where a lane stops never depends on the batch it runs in.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from ..status import Status

__all__ = ["MARGIN", "damping_floor", "cannot_settle", "certify"]

#: safety factor on the certificate's distance bound (4x on the energy)
MARGIN = 2.0


def damping_floor(args, lanes: Optional[int] = None) -> Optional[np.ndarray]:
    r"""\(d\): a floor \(D_d \succeq d\, I\) under the law's injected damping, per lane (shape ``(lanes,)`` with
    per-trajectory gains, else a scalar array), or ``None`` where the certificate does not apply: a law that gives no
    ``damping_floor()`` (the paper's `jaxsleigh.Gains` gives the smallest eigenvalue of the symmetric part of
    \(\hat D\)), or one whose floor is ``None`` (values not concrete, \(H_d\) not bounded below by 0, \(d \le 0\)
    everywhere)."""
    floor = getattr(args.controller, "damping_floor", None)
    return floor() if callable(floor) else None


def cannot_settle(t, y, Hd, status, *, t_final: float, eps: float, d) -> np.ndarray:
    r"""Lanes (batch-last host arrays: ``t`` (N,), the w-chart ``y`` (5, N), ``Hd`` (N,), ``status`` (N,)) that are
    still OK, short of ``t_final`` and certified not to settle before it:
    \(|q| - \epsilon > c \sqrt{(T - t) H_d / d}\) (module docstring), in float64."""
    t, Hd = np.asarray(t, np.float64), np.asarray(Hd, np.float64)
    w = np.asarray(y, np.float64)[:3]
    q = np.sqrt(w[0] ** 2 + (w[0] * (w[1] + w[2])) ** 2 + (0.5 * w[0] * w[0] * w[2]) ** 2)
    tau = np.maximum(float(t_final) - t, 0.0)
    d = np.broadcast_to(np.asarray(d, np.float64), t.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        reach = MARGIN * np.sqrt(tau * np.maximum(Hd, 0.0) / d)
        out = (np.asarray(status) == Status.OK) & (t < t_final) & (d > 0) & np.isfinite(Hd) & np.isfinite(q) \
            & (q - eps > reach)
    return out


def certify(status, t, y, Hd, *, args, t_final: float, eps: float) -> Optional[np.ndarray]:
    """``status`` with the lanes that `cannot_settle` set to ``NOT_SETTLING``, or ``None`` where no lane changes (or
    the certificate does not apply to ``args``, `damping_floor`)."""
    d = damping_floor(args)
    if d is None:
        return None
    d = np.asarray(d)
    n = np.shape(t)[-1]
    if d.ndim and d.shape[-1] not in (1, n):
        return None
    stop = cannot_settle(t, y, Hd, status, t_final=t_final, eps=eps, d=d.reshape(-1) if d.ndim else d)
    if not stop.any():
        return None
    out = np.array(status, np.int32)
    out[stop] = Status.NOT_SETTLING
    return out
