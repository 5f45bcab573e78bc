r"""The settled phase: an exponential RK4 step for the stiff injected damping and the stiff oscillation.

Near the target (and near the singular set) two linear terms of the w-chart loop grow without bound as
\(\theta = w_1 \to 0\). The paper's damping injection \(k / w_1^2\) puts \(\lambda p_2\) into the \(p_2\) equation,

\[ \dot p_2 = \lambda(w_1)\, p_2 + N_5(y), \qquad \lambda = -\frac{\hat D_{22} + k / w_1^2}{J + m l^2}, \]

and the shaped potential V couples \(w_2\) and \(p_1\) through \(\dot w_2 = p_1 / (m w_1) + \ldots\) and
\(u_1 = -V_{22} w_2 / w_1 + \ldots\) (\(V_{22} = \partial^2 V / \partial w_2^2\), the paper's \(L_2\)):

\[ \begin{pmatrix} \dot w_2 \\ \dot p_1 \end{pmatrix} = \begin{pmatrix} 0 & a \\ -b & 0 \end{pmatrix}
   \begin{pmatrix} w_2 \\ p_1 \end{pmatrix} + \begin{pmatrix} N_2(y) \\ N_4(y) \end{pmatrix}, \qquad
   a = \frac{1}{m w_1},\quad b = \frac{V_{22}}{w_1}, \]

an oscillation of frequency \(\omega = \sqrt{ab} = \sqrt{V_{22} / m} / |w_1|\). Classical RK4 is stable only for
\(|\lambda h| \lesssim 2.8\) and \(\omega h \lesssim 2.8\), so after settling the adaptive step was capped by
stability, not accuracy (5-25x the steps with fast gains; ``docs/evidence/settled-phase.md``).

**The step.** The exponential time-differencing RK4 of Cox & Matthews (2002) for \(\dot y = L y + N(y)\), with
\(L\) frozen at the start of the step (the chart's ``stiff_rate`` and ``oscillation``,
`jaxsleigh.model.charts.WChart`): \(L\) is \(\lambda\) on \(p_2\), the 2x2 block above on \((w_2, p_1)\) and 0 on
\(w_1, w_3\). It integrates \(\dot y = L y + N\) exactly for constant \(N\); on \(w_1\) and \(w_3\) it *is*
classical RK4 (computed with the same operations). With \(\varphi_0 = \exp\) and
\(\varphi_1(z) = (e^z - 1)/z\), \(\varphi_2 = (\varphi_1 - 1)/z\), \(\varphi_3 = (\varphi_2 - 1/2)/z\)
(each \(\to 1/k!\) as \(z \to 0\)), \(E_2 = \varphi_0(hL/2)\), \(E = \varphi_0(hL)\) and \(N(y) = f(y) - L y\):

\[ \begin{aligned}
A &= E_2 y + \tfrac h2 \varphi_1(hL/2) N(y), &
B &= E_2 y + \tfrac h2 \varphi_1(hL/2) N(A), &
C &= E_2 A + \tfrac h2 \varphi_1(hL/2) \big(2 N(B) - N(y)\big), \\
y_{n+1} &= E y + h\big(f_1 N(y) + 2 f_2 (N(A) + N(B)) + f_3 N(C)\big), &
f_1 &= \varphi_1 - 3\varphi_2 + 4\varphi_3,\ f_2 = \varphi_2 - 2\varphi_3,\ f_3 = -\varphi_2 + 4\varphi_3,
\end{aligned} \]

the functions taken of \(hL\). At \(L = 0\) every weight is RK4's (\(f_i = 1/6\), \(\varphi_1 = 1\)). The error
estimate is the library's embedded one with the last stage's weight: \(e = h f_3 (N(C) - N(y_{n+1}))\), which is
\(h (k_4 - k_5)/6\) as \(L \to 0\), and exactly that on \(w_1, w_3\); the FSAL evaluation \(f(y_{n+1})\) is shared
as before.

On \(p_2\) the functions are of the scalar \(z = \lambda h\) (`phis`: the Taylor series for \(|z| < 1\), 14 terms,
truncation below 1e-11, and the closed forms otherwise, so they are accurate in float32 near 0, where the
closed forms cancel). On \((w_2, p_1)\) the step's matrix \(M = hL\) has \(M^2 = -\theta^2 I\),
\(\theta = h\omega\), so every power series of it is \(\alpha I + \beta M\): \(\varphi_k(M) = \alpha_k I +
\alpha_{k+1} M\) with \(\alpha_0 = \cos\theta\), \(\alpha_1 = \sin\theta / \theta\) and
\(\alpha_{k+2} = (1/k! - \alpha_k) / \theta^2\) (`rotation_alphas`). The block is used where \(\omega \ge\)
`OSCILLATION_PHASE_IN` (20 rad/s: after settling), and the pair is stepped by RK4 elsewhere; a law that does not
give \(V_{22}\) gets the step on \(p_2\) alone.
"""
from __future__ import annotations

import math

import jax
import jax.numpy as jnp

__all__ = ["phis", "rotation_alphas", "etd_stages", "OSCILLATION_PHASE_IN"]


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


def rotation_alphas(theta2, upto: int):
    r"""\(\alpha_0, \ldots, \alpha_{\text{upto}}\) of \(\theta^2 \ge 0\) (any shape), the coefficients with which
    \(\varphi_k(M) = \alpha_k I + \alpha_{k+1} M\) for a 2x2 matrix with \(M^2 = -\theta^2 I\) (\(\varphi_0 = \exp\)):

    \[ \alpha_k = \sum_{j \ge 0} \frac{(-\theta^2)^j}{(2j + k)!}, \qquad \alpha_0 = \cos\theta,\quad
       \alpha_1 = \frac{\sin\theta}{\theta},\quad \alpha_{k+2} = \frac{1/k! - \alpha_k}{\theta^2}. \]

    For \(\theta^2 < 4\) the two highest come from their series (12 terms, truncation below 1e-16) and the lower
    ones from the recurrence read downwards, \(\alpha_k = 1/k! - \theta^2 \alpha_{k+2}\) (no cancellation); from
    \(\theta = 2\) on, the closed forms (the cancellation in \(1/k! - \alpha_k\) costs at most a factor ~3.4 there).
    The closed branch sees a safe \(\theta \ge 2\) where the series is used, so gradients stay finite."""
    small = theta2 < 4.0
    s = jnp.where(small, -theta2, jnp.zeros_like(theta2))
    series = {}
    for k in (upto - 1, upto):
        acc = jnp.full_like(s, 1.0 / math.factorial(2 * 11 + k))
        for j in range(10, -1, -1):
            acc = acc * s + 1.0 / math.factorial(2 * j + k)
        series[k] = acc
    for k in range(upto - 2, -1, -1):
        series[k] = 1.0 / math.factorial(k) + s * series[k + 2]
    t2 = jnp.where(small, 4.0 * jnp.ones_like(theta2), theta2)
    th = jnp.sqrt(t2)
    closed = [jnp.cos(th), jnp.sin(th) / th]
    for k in range(2, upto + 1):
        closed.append((1.0 / math.factorial(k - 2) - closed[k - 2]) / t2)
    return tuple(jnp.where(small, series[k], closed[k]) for k in range(upto + 1))


#: the frequency \(\omega_c\) (rad/s) from which on the (w2, p1) oscillation is integrated exponentially
#: (\(\omega = \sqrt{V_{22}/m}/|w_1| \ge \omega_c\); below it the pair is stepped as before). In the transient the
#: frozen block's error constant is larger than RK4's and its error estimate does not show it: with the block
#: everywhere the paper's T_eps moved by up to 1.3e-3 s; phased in smoothly, \(\rho = \omega^2/(\omega^2 +
#: \omega_c^2)\), a half-on block excited the oscillation of one benchmark start (docs/evidence/settled-phase.md)
OSCILLATION_PHASE_IN = 20.0


def _rate_coefficients(z):
    """Cox & Matthews' coefficients for the rate on p2 over a step, ``z = lam h``: ``(phi1(z / 2), e^(z / 2),
    e^z, f1, f2, f3)`` with ``f1 = phi1 - 3 phi2 + 4 phi3``, ``f2 = phi2 - 2 phi3``, ``f3 = -phi2 + 4 phi3`` at ``z``."""
    (p1h,) = phis(0.5 * z, upto=1)
    p1, p2, p3 = phis(z)
    e2, e1 = jnp.exp(0.5 * z), jnp.exp(z)
    return p1h, e2, e1, p1 - 3.0 * p2 + 4.0 * p3, p2 - 2.0 * p3, -p2 + 4.0 * p3


def etd_stages(field_and_control, t, y, h, args, k1, lam, osc=None):
    """One exponential RK4 step from ``k1 = f(t, y)`` with the frozen rate ``lam`` on ``p2`` and, when ``osc``
    is given, the frozen oscillation ``osc = (a, b)`` on ``(w2, p1)`` (module docstring).

    Returns ``(dy, k4, error, stages)``: the increment (``y + dy`` is the step's result), the last-stage
    slope ``k4 = f(C)``, a function ``error(y_new, k5)`` giving the step's error estimate from the FSAL
    slope ``k5 = f(y + dy)`` (the module docstring's), and the stage states and controls
    ``((A, uA), (B, uB), (C, uC))`` (for the observers' quadrature)."""
    dtype = y.dtype
    p1h, e2, e1, f1, f2, f3 = _rate_coefficients(lam * h)
    half = 0.5 * h
    rot = None if osc is None else _Rotation(h, *osc)

    def n5(yy, kk):                       # the non-stiff rest of p2's slope
        return kk[4] - lam * yy[4]

    def rows(classical, v5, pair=None):
        """A state from the classical rows, p2's exponential value and (w2, p1)'s. Materialised: without the
        barrier XLA:CPU fused each stage into every later use, and a step cost up to 100x as much."""
        r = [classical[i] for i in range(4)] + [v5]
        if pair is not None:
            r[1], r[3] = pair
        return jax.lax.optimization_barrier(jnp.stack(r).astype(dtype))

    nu = n5(y, k1)
    A = rows(y + half * k1, e2 * y[4] + half * p1h * nu, rot and rot.stage(y, rot.rest(y, k1)))
    k2, u2 = field_and_control(t + half, A, args)
    na = n5(A, k2)
    B = rows(y + half * k2, e2 * y[4] + half * p1h * na, rot and rot.stage(y, rot.rest(A, k2)))
    k3, u3 = field_and_control(t + half, B, args)
    nb = n5(B, k3)
    C = rows(y + h * k3, e2 * A[4] + half * p1h * (2.0 * nb - nu),
             rot and rot.stage(A, _lin(2.0, rot.rest(B, k3), -1.0, rot.rest(y, k1))))
    k4, u4 = field_and_control(t + h, C, args)
    nc = n5(C, k4)
    dy = (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    y5_new = e1 * y[4] + h * (f1 * nu + 2.0 * f2 * (na + nb) + f3 * nc)
    pair = rot and rot.update(y, rot.rest(y, k1), rot.rest(A, k2), rot.rest(B, k3), rot.rest(C, k4))
    dy = rows(dy, y5_new - y[4], pair and (pair[0] - y[1], pair[1] - y[3]))

    def error(y_new, k5):                 # classical h (k4 - k5) / 6, its exponential rows the exponential ones
        pair = rot and rot.error(rot.rest(C, k4), rot.rest(y_new, k5))
        return rows((h / 6.0) * (k4 - k5), h * f3 * (nc - n5(y_new, k5)), pair)

    return dy, k4, error, ((A, u2), (B, u3), (C, u4))


def _lin(ca, a, cb, b):
    """``ca a + cb b`` on pairs."""
    return (ca * a[0] + cb * b[0], ca * a[1] + cb * b[1])


class _Rotation:
    r"""The oscillation \(\dot w_2 = a p_1 + N_2,\ \dot p_1 = -b w_2 + N_4\) frozen over a step of ``h`` where its
    frequency \(\omega = \sqrt{ab}\) is at least `OSCILLATION_PHASE_IN` (elsewhere \(a = b = 0\): RK4 on the pair):
    the step's matrix \(M = h \begin{pmatrix} 0 & a \\ -b & 0 \end{pmatrix}\), \(M^2 = -\theta^2 I\), and its
    functions \(\varphi_k(M) = \alpha_k I + \alpha_{k+1} M\) (`rotation_alphas`), applied to the pair (w2, p1) in
    the Cox-Matthews formulas (module docstring)."""

    def __init__(self, h, a, b):
        on = a * b >= OSCILLATION_PHASE_IN ** 2
        self.h, self.a, self.b = h, jnp.where(on, a, 0.0), jnp.where(on, b, 0.0)
        th2 = (h * self.a) * (h * self.b)
        al, self.half = jax.lax.optimization_barrier((rotation_alphas(th2, 4), rotation_alphas(0.25 * th2, 2)))
        self.E = (al[0], al[1])
        self.g1 = (al[1] - 3.0 * al[2] + 4.0 * al[3], al[2] - 3.0 * al[3] + 4.0 * al[4])
        self.g2 = (al[2] - 2.0 * al[3], al[3] - 2.0 * al[4])
        self.g3 = (-al[2] + 4.0 * al[3], -al[3] + 4.0 * al[4])

    def rest(self, yy, kk):
        """The pair's rest of the slope, \\(N = f - L y = (k_{w_2} - a p_1,\\ k_{p_1} + b w_2)\\)."""
        return (kk[1] - self.a * yy[3], kk[3] + self.b * yy[1])

    def _apply(self, c, pair, scale=1.0):
        """\\((c_0 I + c_1 M_s) (u, v)\\) with \\(M_s\\) = ``scale`` M."""
        u, v = pair
        return (c[0] * u + c[1] * (scale * self.h * self.a) * v, c[0] * v - c[1] * (scale * self.h * self.b) * u)

    def stage(self, y_from, n):
        """A stage's pair, \\(E_{1/2} y + \\tfrac h2 \\varphi_1(M/2)\\, n\\) with ``y_from``'s pair."""
        e = self._apply((self.half[0], self.half[1]), (y_from[1], y_from[3]), 0.5)
        p = self._apply((self.half[1], self.half[2]), n, 0.5)
        return _lin(1.0, e, 0.5 * self.h, p)

    def update(self, y, n1, n2, n3, n4):
        """The pair after the step: \\(E y + h (g_1 N_1 + 2 g_2 (N_2 + N_3) + g_3 N_4)\\)."""
        e = self._apply(self.E, (y[1], y[3]))
        a = self._apply(self.g1, n1)
        b = self._apply(self.g2, _lin(1.0, n2, 1.0, n3))
        c = self._apply(self.g3, n4)
        return tuple(e[i] + self.h * (a[i] + 2.0 * b[i] + c[i]) for i in range(2))

    def error(self, n4, n5):
        """\\(h\\, g_3 (N(C) - N(y_{n+1}))\\) on the pair."""
        d = self._apply(self.g3, _lin(1.0, n4, -1.0, n5))
        return (self.h * d[0], self.h * d[1])
