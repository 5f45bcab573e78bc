r"""Aicardi, Casalino, Bicchi and Balestrino's Lyapunov law in polar coordinates, lifted to force level.

M. Aicardi, G. Casalino, A. Bicchi, A. Balestrino, "Closed loop steering of unicycle-like vehicles via
Lyapunov techniques", *IEEE Robotics & Automation Magazine* 2(1):27-35, 1995.

The law is kinematic (it prescribes the forward speed and the turning rate); `AicardiLaw` turns it into
the force ``u`` with the velocity loop of `jaxsleigh.controllers.lift.velocity_loop`.
"""
from __future__ import annotations

from typing import Any, NamedTuple

import jax.numpy as jnp

from ..model.charts import PhysicalChart
from ..model.params import PlantParams
from .lift import velocity_loop

__all__ = ["AicardiLaw", "polar_coordinates"]


def _wrap(a):
    """An angle in \\((-\\pi, \\pi]\\) (smooth away from \\(\\pm\\pi\\): its derivative is 1)."""
    return jnp.arctan2(jnp.sin(a), jnp.cos(a))


def _sin_over(a):
    r"""\(\sin a / a\), 1 at 0: its Taylor polynomial below \(|a| < 10^{-3}\) (error \(< 10^{-18}\))
    keeps the value and the derivatives finite at 0 (cheaper to differentiate twice than ``jnp.sinc``)."""
    small = jnp.abs(a) < 1e-3
    a_safe = jnp.where(small, 1.0, a)
    return jnp.where(small, 1.0 - a * a / 6.0 + a ** 4 / 120.0, jnp.sin(a_safe) / a_safe)


def polar_coordinates(q):
    r"""``(e, alpha, theta)`` of the paper for the goal at the origin with heading 0.

    \(e = \sqrt{x^2 + y^2}\) the distance to the goal, \(\vartheta = \operatorname{atan2}(-y, -x)\) the
    angle of the line from the vehicle to the goal, \(\alpha = \vartheta - \theta\) (wrapped into
    \((-\pi, \pi]\)) the angle between the heading and that line. At the goal (\(e = 0\)) the line is
    undefined: the function returns \(e = 0\), \(\vartheta = 0\), \(\alpha = -\theta\) (wrapped), finite
    with finite derivatives (the safe branch of a double ``jnp.where``). "At the goal" means
    \(s = \max(|x|, |y|) \le \text{max}^{-1/4}\) of the dtype (about \(2 \times 10^{-10}\) in float32,
    \(3 \times 10^{-78}\) in float64). The velocity loop differentiates \(\vartheta\) once and a tuner's reverse
    pass once more, and their factors up to \(1/s^4\) then stay finite (with \(\sqrt{\text{tiny}}\), \(10^{-19}\)
    in float32, the gradient over a 100 s horizon was NaN). At the goal the law stops translating and turns the
    heading to 0 modulo \(2\pi\), so the threshold is part of the dynamics: it is kept as small as the derivatives
    allow, because a larger one (\(\text{max}^{-1/6} \approx 4 \times 10^{-7}\) in float32) changed \(T_{0.05}\) of
    tuned gains with a slow heading mode by up to 15 s against float64 (``tests/test_literature_aicardi_astolfi.py``
    checks float32 against float64).
    """
    x, y, th = q[0], q[1], q[2]
    # scale-invariant: (x, y) / max(|x|, |y|), so that e^2 does not underflow as e -> 0 (e decays like exp(-gamma t))
    s = jnp.maximum(jnp.abs(x), jnp.abs(y))
    at_goal = s <= float(jnp.finfo(jnp.result_type(s, jnp.float32)).max) ** -0.25
    s_safe = jnp.where(at_goal, 1.0, s)
    xs = jnp.where(at_goal, -1.0, x / s_safe)          # a safe point on the goal's approach line
    ys = jnp.where(at_goal, 0.0, y / s_safe)
    e = jnp.where(at_goal, 0.0, s_safe * jnp.sqrt(xs * xs + ys * ys))
    vartheta = jnp.arctan2(-ys, -xs)
    return e, _wrap(vartheta - th), vartheta


class AicardiLaw(NamedTuple):
    r"""Aicardi et al.'s globally convergent polar-coordinate law, lifted with a velocity loop.

    Citation: that of `jaxsleigh.controllers.aicardi` (the module).

    **Coordinates.** Goal at the origin with heading 0. With \(e\) the distance to the goal,
    \(\vartheta\) the angle (in the goal frame) of the line from the vehicle to the goal and
    \(\alpha = \vartheta - \theta\) the angle between the heading and that line (both in
    \((-\pi, \pi]\), see `polar_coordinates`), the unicycle \(\dot x = v\cos\theta\),
    \(\dot y = v\sin\theta\), \(\dot\theta = \omega\) reads, for \(e > 0\),

    \[ \dot e = -v\cos\alpha, \qquad \dot\alpha = -\omega + v\,\frac{\sin\alpha}{e}, \qquad
       \dot\vartheta = v\,\frac{\sin\alpha}{e}. \]

    **Law.** With \(\gamma, k, h > 0\),

    \[ v = \gamma \cos\alpha\; e, \qquad
       \omega = k\,\alpha + \gamma\,\frac{\cos\alpha \sin\alpha}{\alpha}\,(\alpha + h\,\vartheta), \]

    and the Lyapunov function \(V = \tfrac12(\lambda e^2 + \alpha^2 + h\vartheta^2)\) (any \(\lambda > 0\))
    decreases along the closed loop:

    \[ \dot V = -\lambda\gamma\cos^2\!\alpha\; e^2 - k\,\alpha^2 \le 0 . \]

    By LaSalle (the paper's argument) \(e, \alpha, \vartheta \to 0\) from every start with \(e > 0\), and
    \(e\) never reaches 0 in finite time (\(\dot e \ge -\gamma e\)), so the polar chart is never left. The
    law is smooth in \((e, \alpha, \vartheta)\) but discontinuous in \((x, y, \theta)\) at the goal:
    this is how it escapes Brockett's condition. \(\sin\alpha/\alpha\) is 1 at \(\alpha = 0\) (a Taylor
    polynomial near 0); at \(e = 0\) `polar_coordinates` returns a safe finite value, so ``u`` is finite
    everywhere. The heading converges to 0 modulo \(2\pi\) (the law sees angles only through
    \(\alpha, \vartheta \in (-\pi, \pi]\)); \(\alpha = \pm\pi\) is repelling (\(\dot\alpha = \mp k\pi\) there).
    So the law declares the physical chart that measures the heading modulo \(2\pi\)
    (`jaxsleigh.model.charts.PhysicalChart`, ``heading_modulo=True``): \(T_\epsilon\) and \(\min|\theta|\) count
    \(\theta = \pm 2\pi\) at the goal as the goal's heading.

    **What was checked.** The form of \(v\), \(\omega\) and \(V\), and the sign conventions above
    (\(\vartheta\) the angle of the vector from the vehicle to the goal, \(\alpha = \vartheta - \theta\)),
    agree with public implementations of this law (e.g. the Robotarium's ``pose_uni_clf_controller``);
    the polar kinematics and \(\dot V\) were re-derived here (and \(\dot V \le 0\) is checked numerically
    by the tests). The paper itself was not available to this module's author, so its equation numbers
    are not given; \(\lambda\) enters only \(V\), not the law.

    **Defaults.** \(\gamma = 1\), \(k = 2\), \(h = 1\): the linearisation at the goal,
    \(\dot\alpha = -k\alpha - \gamma h\vartheta\), \(\dot\vartheta = \gamma\alpha\), has the double
    eigenvalue \(-1\) (critical damping, \(k^2 = 4\gamma^2 h\)); \(e\) then decays like \(e^{-\gamma t}\).

    **Force level.** ``u = velocity_loop(law, q, v, 0, K, model)`` (`jaxsleigh.controllers.lift`): with the
    exact model the velocity error decays like \(e^{-K t}\); take \(K\) above the kinematic rates
    (\(K = 5\) by default).

    Attributes:
      gamma: forward-speed gain \(\gamma > 0\) [1/s].
      k: turning gain \(k > 0\) [1/s].
      h: weight \(h > 0\) of the goal-line angle \(\vartheta\).
      K: velocity-loop rate [1/s] (with ``model=None``: the gain of ``u = -K (v - v_ref)``).
      model: the plant as the law knows it (`jaxsleigh.PlantParams`, default the nominal plant), or
        ``None`` for the model-free velocity loop.
    """

    gamma: float = 1.0
    k: float = 2.0
    h: float = 1.0
    K: float = 5.0
    model: Any = PlantParams()

    name = "aicardi"
    chart = PhysicalChart(heading_modulo=True)   # the heading converges to 0 modulo 2 pi
    positive = ("gamma", "k", "h", "K")          # the Lyapunov argument needs them > 0 (tuning keeps them so)
    #: the loosest tolerance at which a float64 reference resolves this law (`jaxsleigh.studies.audit.for_law`): the
    #: law is discontinuous at its goal, and once the distance to it is below the absolute tolerance the angle it turns
    #: towards is not resolved, so at 1e-10 float64 chatters about the goal (217 of 256 held-out starts, 9 at 1e-12,
    #: none at 1e-13 or 1e-14; ``docs/evidence/accuracy.md``)
    reference_tol = 1e-12
    citation = ("Aicardi, Casalino, Bicchi, Balestrino, 'Closed loop steering of unicycle-like vehicles via "
                "Lyapunov techniques', IEEE Robot. Autom. Mag. 2(1):27-35, 1995")
    needs = ("m", "J", "l", "damping")

    def kinematic(self, q):
        """``(v, omega)`` of the kinematic law at ``q`` (shape (2,))."""
        e, alpha, vartheta = polar_coordinates(q)
        ca = jnp.cos(alpha)
        sinc = _sin_over(alpha)
        v = self.gamma * ca * e
        omega = self.k * alpha + self.gamma * ca * sinc * (alpha + self.h * vartheta)
        return jnp.stack([v, omega])

    def lyapunov(self, q, lam=1.0):
        r"""\(V = \tfrac12(\lambda e^2 + \alpha^2 + h\vartheta^2)\) at ``q``."""
        e, alpha, vartheta = polar_coordinates(q)
        return 0.5 * (lam * e * e + alpha * alpha + self.h * vartheta * vartheta)

    def __call__(self, q, v):
        return velocity_loop(lambda qq, t: self.kinematic(qq), q, v, 0.0, self.K, self.model)
