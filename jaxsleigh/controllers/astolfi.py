r"""Astolfi's discontinuous exponential stabiliser (chained form and \(\sigma\)-process), lifted to force level.

A. Astolfi, "Discontinuous control of nonholonomic systems", *Systems & Control Letters* 27(1):37-45, 1996;
for the wheeled robot also A. Astolfi, "Exponential stabilization of a wheeled mobile robot via
discontinuous control", *J. Dyn. Sys., Meas., Control* 121(1):121-126, 1999.

The law is kinematic; `AstolfiLaw` turns it into the force ``u`` with the velocity loop of
`jaxsleigh.controllers.lift.velocity_loop`.
"""
from __future__ import annotations

from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from ..model.params import PlantParams
from .lift import velocity_loop

__all__ = ["AstolfiLaw", "chained_form"]


def chained_form(q):
    r"""\(x = (\theta,\ x\cos\theta + y\sin\theta,\ x\sin\theta - y\cos\theta)\) (the chained form; the
    same map as `jaxsleigh.model.coordinates.f_z`)."""
    c, s = jnp.cos(q[2]), jnp.sin(q[2])
    return q[2], q[0] * c + q[1] * s, q[0] * s - q[1] * c


class AstolfiLaw(NamedTuple):
    r"""Astolfi's \(\sigma\)-process law: exponential convergence from every start with \(\theta \ne 0\).

    Citation: those of `jaxsleigh.controllers.astolfi` (the module).

    **Chained form.** With \(x_1 = \theta\), \(x_2 = x\cos\theta + y\sin\theta\),
    \(x_3 = x\sin\theta - y\cos\theta\) (`chained_form`; \(|q|^2 = x_1^2 + x_2^2 + x_3^2\)) the unicycle
    \(\dot x = v\cos\theta\), \(\dot y = v\sin\theta\), \(\dot\theta = \omega\) becomes

    \[ \dot x_1 = u_1, \qquad \dot x_2 = u_2, \qquad \dot x_3 = x_2 u_1, \qquad
       u_1 = \omega, \quad u_2 = v - \omega x_3 . \]

    **\(\sigma\)-process.** \(z_3 = x_3 / x_1\) (singular on \(\theta = 0\), the set the paper's w chart
    also excludes) gives \(\dot z_3 = u_1 (x_2 - z_3)/x_1\). With

    \[ u_1 = -k\,x_1, \qquad u_2 = -p_2\,x_2 - p_3\,z_3 \]

    the closed loop is *linear*:

    \[ \dot x_1 = -k x_1, \qquad
       \frac{d}{dt}\begin{bmatrix} x_2 \\ z_3 \end{bmatrix} =
       \underbrace{\begin{bmatrix} -p_2 & -p_3 \\ -k & k \end{bmatrix}}_{A}
       \begin{bmatrix} x_2 \\ z_3 \end{bmatrix}. \]

    \(A\) is Hurwitz iff \(\operatorname{tr} A = k - p_2 < 0\) and \(\det A = -k(p_2 + p_3) > 0\), i.e.

    \[ k > 0, \qquad p_2 > k, \qquad p_3 < -p_2 . \]

    Then \(x_1 = \theta_0 e^{-kt}\) never reaches 0 (the chart is never left), \((x_2, z_3)\) decay at the
    rate \(\rho_A = -\max\operatorname{Re}\lambda(A)\), \(x_3 = x_1 z_3\) at \(k + \rho_A\), and
    \(|q| \le C e^{-\min(k, \rho_A)\,t}\) from every \(\theta_0 \ne 0\). Back in the unicycle's velocities:
    \(\omega = u_1\), \(v = u_2 + \omega x_3\).

    **What was checked.** The chained form, \(\dot z_3\), the linear closed loop and the gain conditions
    were derived here and are checked by the tests (the measured decay rate of \(|q|\) matches
    \(\min(k, \rho_A)\)). The \(\sigma\)-process \(\xi_3 = x_3/x_1\), the choice \(u_1 = -k\xi_1\) and the
    resulting linear system \(\dot\xi = A\xi + b_2 u_2\) with the row \((0, -k, k)\) agree with Astolfi's
    own account of the method (Sec. 5.5 of the Ge-Lewis book *Autonomous Mobile Robots*, 2006, eq.
    5.24-5.27 there). The two papers were not available to this module's author, so their equation
    numbers are not given and the gain conditions above are the Hurwitz conditions, not a quotation.

    **Guard.** On \(\theta = 0\) the law is undefined (\(z_3 \to \pm\infty\)); there (in practice: for
    \(|\theta| \le \sqrt{\text{tiny}}\) of the dtype, about \(10^{-19}\) in float32, which the closed loop
    reaches only when \(x_3 = x_1 z_3\) is far smaller still) it uses \(z_3 = 0\)
    (a finite ``u``: \(\omega = 0\), \(v = -p_2 x_2\)), through a double ``jnp.where`` so that the
    derivatives the velocity loop takes are finite too. Near \(\theta = 0\) the law is large
    (\(|v| \sim |p_3 x_3/\theta|\)): that is the price of its exponential rate.

    **Defaults.** \(k = 1\), \(p_2 = 4\), \(p_3 = -6\): \(A\) has the eigenvalues \(-1, -2\), so
    \(|q|\) decays like \(e^{-t}\). Force level: ``u = velocity_loop(law, q, v, 0, K, model)``
    (`jaxsleigh.controllers.lift`), \(K = 5\) by default (above the kinematic rates; with \(K > k\) the
    heading of the lifted loop from rest never crosses 0).

    Attributes:
      k: heading rate \(k > 0\) [1/s].
      p2, p3: gains of \(u_2\) (\(p_2 > k\), \(p_3 < -p_2\)).
      K: velocity-loop rate [1/s] (with ``model=None``: the gain of ``u = -K (v - v_ref)``).
      model: the plant as the law knows it (`jaxsleigh.PlantParams`, default the nominal plant), or
        ``None`` for the model-free velocity loop.
    """

    k: float = 1.0
    p2: float = 4.0
    p3: float = -6.0
    K: float = 5.0
    model: Any = PlantParams()

    name = "astolfi"
    positive = ("k", "p2", "K")                  # k > 0 and p2 > k are part of the Hurwitz conditions
    citation = ("Astolfi, 'Discontinuous control of nonholonomic systems', Syst. Control Lett. 27(1):37-45, "
                "1996")
    needs = ("m", "J", "l", "damping")

    def closed_loop_matrix(self):
        """\\(A = [[-p_2, -p_3], [-k, k]]\\), the linear closed loop of \\((x_2, z_3)\\) (NumPy)."""
        return np.array([[-float(self.p2), -float(self.p3)], [-float(self.k), float(self.k)]])

    def rate(self):
        """The predicted exponential rate of \\(|q|\\): \\(\\min(k, -\\max \\mathrm{Re}\\,\\lambda(A))\\)."""
        return min(float(self.k), -float(np.max(np.linalg.eigvals(self.closed_loop_matrix()).real)))

    def kinematic(self, q):
        """``(v, omega)`` of the kinematic law at ``q`` (shape (2,))."""
        x1, x2, x3 = chained_form(q)
        # |theta| below sqrt(tiny) of the dtype counts as theta = 0: the velocity loop differentiates
        # x3 / x1, whose derivative holds 1 / x1^2 (underflow, then inf * 0 = NaN, below that)
        on_singular = jnp.abs(x1) <= jnp.sqrt(jnp.finfo(jnp.result_type(x1, jnp.float32)).tiny)
        z3 = jnp.where(on_singular, 0.0, x3 / jnp.where(on_singular, 1.0, x1))
        u1 = -self.k * x1
        u2 = -self.p2 * x2 - self.p3 * z3
        return jnp.stack([u2 + u1 * x3, u1])

    def __call__(self, q, v):
        return velocity_loop(lambda qq, t: self.kinematic(qq), q, v, 0.0, self.K, self.model)
