r"""The settled phase: an exponential RK4 step for the stiff injected damping.

Near the target (and near the singular set) the paper's damping injection \(k / w_1^2\) puts a
linear term \(\lambda p_2\) into the \(p_2\) equation,

\[ \dot p_2 = \lambda(w_1)\, p_2 + N_5(y), \qquad \lambda = -\frac{\hat D_{22} + k / w_1^2}{J + m l^2}, \]

and \(|\lambda|\) grows without bound as \(\theta = w_1 \to 0\). Classical RK4 is stable only for
\(|\lambda h| \lesssim 2.8\), so after settling the adaptive step is capped by stability, not accuracy
(5-25x the steps with fast gains; ``docs/evidence/settled-phase.md``).

**The step.** The exponential time-differencing RK4 of Cox & Matthews (2002) with \(\lambda\) frozen at
the start of the step (the chart's ``stiff_rate``, `jaxsleigh.model.charts.WChart`) integrates \(\dot p_2 = \lambda p_2 + N_5\) exactly for constant \(N_5\); on the other
four components it *is* classical RK4 (computed with the same operations, so they round as before).
With \(z = \lambda h\), \(E = e^{z}\), \(E_2 = e^{z/2}\) and the functions
\(\varphi_1(z) = (e^z - 1)/z\), \(\varphi_2 = (\varphi_1 - 1)/z\), \(\varphi_3 = (\varphi_2 - 1/2)/z\)
(each \(\to 1/k!\) as \(z \to 0\)), and \(N(y) = f(y) - \lambda y_5 e_5\):

\[ \begin{aligned}
a &= E_2 y_5 + \tfrac h2 \varphi_1(z/2) N(y), &
b &= E_2 y_5 + \tfrac h2 \varphi_1(z/2) N(A), &
c &= E_2 a + \tfrac h2 \varphi_1(z/2) \big(2 N(B) - N(y)\big), \\
y_{5,n+1} &= E y_5 + h\big(f_1 N(y) + 2 f_2 (N(A) + N(B)) + f_3 N(C)\big), &
f_1 &= \varphi_1 - 3\varphi_2 + 4\varphi_3,\ f_2 = \varphi_2 - 2\varphi_3,\ f_3 = -\varphi_2 + 4\varphi_3,
\end{aligned} \]

where \(A, B, C\) are the classical stages with their fifth component replaced by \(a, b, c\). At
\(z = 0\) every weight is RK4's (\(f_i = 1/6\), \(\varphi_1 = 1\)). The error estimate is the library's
embedded one with the last stage's weight: \(e = h f_3 (N(C) - N(y_{n+1}))\) on \(p_2\), which is
\(h (k_4 - k_5)/6\) as \(z \to 0\), and exactly that on the other components; the FSAL evaluation
\(f(y_{n+1})\) is shared as before.

The \(\varphi\) functions are evaluated by their Taylor series for \(|z| < 1\) (14 terms, truncation
below 1e-11) and by the closed forms otherwise, so they are accurate in float32 near 0, where the
closed forms cancel.
"""
from __future__ import annotations

import math

import jax.numpy as jnp

__all__ = ["phis", "etd_stages"]


#: Taylor coefficients 1 / (j + k)! of phi_k, j = 0..13 (truncation below 1e-11 for |z| < 1)
_COEF = {k: [1.0 / math.factorial(j + k) for j in range(14)] for k in (1, 2, 3)}


def _series(z, k):
    """phi_k(z) by Horner's scheme on its Taylor series (multiplications and additions only)."""
    acc = jnp.full_like(z, _COEF[k][-1])
    for c in reversed(_COEF[k][:-1]):
        acc = acc * z + c
    return acc


def phis(z, upto: int = 3):
    """\\(\\varphi_1, \\ldots, \\varphi_{\\text{upto}}\\) of ``z <= 0`` (any shape): the series for
    ``|z| < 1``, the closed forms otherwise (one division, by ``z``, shared)."""
    small = jnp.abs(z) < 1.0
    zs = jnp.where(small, z, jnp.zeros_like(z))
    zl = jnp.where(small, -jnp.ones_like(z), z)
    r = 1.0 / zl
    out, p = [], jnp.expm1(zl) * r
    for k in range(1, upto + 1):
        if k > 1:
            p = (p - 1.0 / math.factorial(k - 1)) * r
        out.append(jnp.where(small, _series(zs, k), p))
    return tuple(out)


def etd_stages(field_and_control, t, y, h, args, k1, lam):
    """One exponential RK4 step from ``k1 = f(t, y)`` with the frozen rate ``lam`` on ``p2``.

    Returns ``(dy, k4, error, stages)``: the increment (``y + dy`` is the step's result), the last-stage
    slope ``k4 = f(C)``, a function ``error(y_new, k5)`` giving the step's error estimate from the FSAL
    slope ``k5 = f(y + dy)`` (the module docstring's), and the stage states and controls
    ``((A, uA), (B, uB), (C, uC))`` (for the observers' quadrature)."""
    dtype = y.dtype
    z = lam * h
    (p1h,) = phis(0.5 * z, upto=1)
    p1, p2, p3 = phis(z)
    e2, e1 = jnp.exp(0.5 * z), jnp.exp(z)
    f1, f2, f3 = p1 - 3.0 * p2 + 4.0 * p3, p2 - 2.0 * p3, -p2 + 4.0 * p3
    half = 0.5 * h

    def n5(yy, kk):                       # the non-stiff rest of p2's slope
        return kk[4] - lam * yy[4]

    def with5(yy, v5):
        return jnp.concatenate([yy[:4], v5[None].astype(dtype)], axis=0)

    nu = n5(y, k1)
    A = with5(y + half * k1, e2 * y[4] + half * p1h * nu)
    k2, u2 = field_and_control(t + half, A, args)
    na = n5(A, k2)
    B = with5(y + half * k2, e2 * y[4] + half * p1h * na)
    k3, u3 = field_and_control(t + half, B, args)
    nb = n5(B, k3)
    C = with5(y + h * k3, e2 * A[4] + half * p1h * (2.0 * nb - nu))
    k4, u4 = field_and_control(t + h, C, args)
    nc = n5(C, k4)
    dy = (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    y5_new = e1 * y[4] + h * (f1 * nu + 2.0 * f2 * (na + nb) + f3 * nc)
    dy = with5(dy, y5_new - y[4])

    def error(y_new, k5):                 # classical h (k4 - k5) / 6, its p2 row the exponential one
        return with5((h / 6.0) * (k4 - k5), h * f3 * (nc - n5(y_new, k5)))

    return dy, k4, error, ((A, u2), (B, u3), (C, u4))
