r"""Samson's smooth time-varying point stabiliser of the unicycle (chained form), lifted to force level.

**Citation.** C. Samson, "Control of chained systems: application to path following and time-varying
point-stabilization of mobile robots", IEEE Trans. Automatic Control 40(1):64-77, 1995 (the law for
the unicycle first appeared in C. Samson, "Velocity and torque feedback control of a nonholonomic
cart", Advanced Robot Control, LNCIS 162, 1991).

**Chained form.** With \(x_1 = \theta\), \(x_2 = x\cos\theta + y\sin\theta\),
\(x_3 = x\sin\theta - y\cos\theta\) (the paper's `jaxsleigh.model.coordinates.f_z`), the unicycle
\(\dot x = v\cos\theta\), \(\dot y = v\sin\theta\), \(\dot\theta = \omega\) reads

\[ \dot x_1 = u_1, \qquad \dot x_2 = u_2, \qquad \dot x_3 = x_2 u_1, \qquad
   u_1 = \omega, \quad u_2 = v - \omega x_3 . \]

(Samson orders the chain the other way, \(\dot x_2 = u_1 x_3\), \(\dot x_3 = u_2\): swap the indices 2 and 3
to read his formulas.)

**The law** (Samson's time-varying point stabiliser for \(n = 3\), written in the chain order above):

\[ u_1 = -k_1 x_1 + h(x_2, x_3, t), \qquad h = \alpha\,(x_2^2 + x_3^2)\sin(\nu t), \qquad
   u_2 = -k_2 x_2 - k_3 u_1 x_3, \]

\(k_1, k_2, k_3, \alpha, \nu > 0\), mapped back to the unicycle by \(\omega = u_1\), \(v = u_2 + \omega x_3\).
It is smooth (polynomial in \(x\), trigonometric in \(\theta\) and \(t\)), periodic in \(t\), and has **no
singular set**: \(\theta = 0\) is an ordinary point (unlike the paper's law, eq. 13).

*Why it works* (the argument of the paper, checked here and in the tests). For any signal \(u_1\),

\[ W = x_2^2 + k_3 x_3^2, \qquad \dot W = 2 x_2(-k_2 x_2 - k_3 u_1 x_3) + 2 k_3 x_3 x_2 u_1 = -2 k_2 x_2^2 \le 0, \]

so \(W\) never increases, \(h\) is bounded, and \(\dot x_1 = -k_1 x_1 + h\) keeps \(x_1\) bounded. On the
limit set \(x_2 \equiv 0\), hence \(u_1 x_3 \equiv 0\) with \(x_3\) constant; \(u_1 = -k_1 x_1 + \alpha x_3^2
\sin\nu t\) can vanish identically only if \(x_3 = 0\) (\(\partial h/\partial t \ne 0\) whenever
\((x_2, x_3) \ne 0\): the excitation condition on \(h\)), and then \(x_1 \to 0\). Claim: the origin is
**globally asymptotically stable**, uniformly (the closed loop is periodic in \(t\)), and *not*
exponentially: near the origin \(u_1 = O(|x|^2)\), the averaged decay of \(x_3\) is
\(\dot x_3 \approx -(k_3/k_2) \overline{u_1^2}\, x_3 = O(x_3^5)\), i.e. \(|x_3| \sim t^{-1/4}\). This slow tail is
the known price of smooth time-varying stabilisers (no smooth law, time-varying or not, is exponentially
stabilising for this system; `M'Closkey and Murray 1997` trade smoothness for \(\rho\)-exponential rates).

*What was verified and what reconstructed.* The published text was not at hand when this module was written,
so the equations above (and their numbers, which are therefore not quoted) are reconstructed from the
structure of Samson's design (his \(u_2 = -k_2 u_1 x_2 - k_3 x_3\) in his chain order, his
\(h(\bar x, t)\) with \(h(0, t) = 0\) and the excitation condition; \(h = \|\bar x\|^2 \sin t\) is his
usual example). What the tests check does not depend on the citation: \(\dot W = -2 k_2 x_2^2\) exactly along
the kinematic closed loop, and convergence from starts including \(\theta_0 = 0\)
(``tests/test_literature_time_varying.py``).

**Force level.** The sleigh is driven by forces; `jaxsleigh.controllers.lift.velocity_loop` makes the velocity
track \(v_\mathrm{ref}(q, t) = (u_2 + u_1 x_3,\ u_1)\) at rate ``K`` with the plant's model (computed torque,
\(\dot v_\mathrm{ref}\) including \(\partial v_\mathrm{ref}/\partial t\) by ``jax.jvp``), or with a plain velocity
loop when ``model=None``. The output is a polynomial of \(q, v\) times bounded trigonometric factors and the
model's (finite) damping: finite everywhere.
"""
from __future__ import annotations

from typing import Any, NamedTuple

import jax.numpy as jnp

from ..model.params import PlantParams
from .lift import velocity_loop

__all__ = ["Samson", "samson_chained", "samson_velocity"]


def samson_chained(z, t, k1, k2, k3, alpha, nu):
    r"""Samson's law in chained coordinates: \((u_1, u_2)\) at \(z = (x_1, x_2, x_3)\), time ``t``."""
    u1 = -k1 * z[0] + alpha * (z[1] * z[1] + z[2] * z[2]) * jnp.sin(nu * t)
    u2 = -k2 * z[1] - k3 * u1 * z[2]
    return u1, u2


def samson_velocity(q, t, k1, k2, k3, alpha, nu):
    r"""The kinematic law on the unicycle: \(v_\mathrm{ref} = (v, \omega) = (u_2 + u_1 x_3,\ u_1)\), shape (2,)."""
    c, s = jnp.cos(q[2]), jnp.sin(q[2])
    z = (q[2], q[0] * c + q[1] * s, q[0] * s - q[1] * c)
    u1, u2 = samson_chained(z, t, k1, k2, k3, alpha, nu)
    return jnp.stack([u2 + u1 * z[2], u1])


class Samson(NamedTuple):
    r"""Samson's smooth time-varying stabiliser (chained form, see the module), lifted by a velocity loop.

    Attributes:
      k1: rate of \(x_1 = \theta\) (> 0) [1/s].
      k2: damping of \(x_2\) (> 0) [1/s].
      k3: coupling gain of \(x_3\) (> 0) [1/m].
      alpha: amplitude of the time-varying term \(h = \alpha (x_2^2 + x_3^2) \sin\nu t\) (> 0) [1/(m^2 s)].
      nu: its angular frequency (> 0) [rad/s].
      K: rate of the velocity loop [1/s] (with ``model=None``: a gain, N s/m and N m s/rad).
      model: the plant the loop assumes, a `jaxsleigh.PlantParams` (default the nominal plant), or ``None``.
    """

    k1: float = 1.0
    k2: float = 2.0
    k3: float = 2.0
    alpha: float = 2.0
    nu: float = 1.0
    K: float = 5.0
    model: Any = PlantParams()

    name = "samson"
    positive = ("k1", "k2", "k3", "alpha", "nu", "K")   # every gain of the design is > 0
    citation = ("C. Samson, Control of chained systems: application to path following and time-varying "
                "point-stabilization of mobile robots, IEEE TAC 40(1):64-77, 1995")
    needs = ("m", "J", "l", "damping")
    time_varying = True

    def v_ref(self, q, t):
        """The kinematic law's velocity (forward speed, turning rate) at ``q``, time ``t``."""
        return samson_velocity(q, t, self.k1, self.k2, self.k3, self.alpha, self.nu)

    def __call__(self, q, v, t):
        return velocity_loop(self.v_ref, q, v, t, self.K, self.model)
