r"""The shaped-energy law: the paper's law with a separable, shaped potential and a state-dependent
damping injection, built so that the paper's proof holds for every parameter value
(docs/evidence/shaped-energy.md writes the proof out).

\[ u = -Q_w^\top(w)\,\nabla V(w) - \hat D(w)\, v - \mathrm{diag}\big(0,\ k / w_1^2\big)\, v,
   \qquad H_d = \tfrac12 p^\top M^{-1} p + V(w) \]

**Potential.** \(V(w) = \phi_1(w_1) + \phi_2(w_2) + \phi_3(w_3)\) with

\[ \phi_i(w) = \tfrac12 l_i w^2 + b_i c_i^2\Big(\sqrt{1 + (w/c_i)^2} - 1\Big), \qquad
   \phi_i'(w) = l_i w + \frac{b_i w}{\sqrt{1 + (w/c_i)^2}}, \]

\(l_i > 0,\ b_i \ge 0,\ c_i > 0\). Then \(\phi_i(0) = 0\), \(\phi_i'' = l_i + b_i (1 + (w/c_i)^2)^{-3/2} > 0\)
(strictly convex, minimum 0 at 0, \(\phi_i' = 0\) only at 0) and \(\phi_i \ge l_i w^2 / 2\) (coercive): the
conditions under which Lemmas 2 and 3 and Proposition 2 of the paper hold. The pseudo-Huber term is
stiff (slope \(l_i + b_i\)) near the target and grows only linearly (slope \(b_i c_i\)) far from it,
where the quadratic potential makes \(H_d(0) \sim \theta_0^{-4}\).

**Damping.** \(\hat D(w) = \mathrm{diag}(\hat d_1(w), \hat d_2(w))\),
\(\hat d_j(w) = n_j^{\sigma(w)} f_j^{1 - \sigma(w)}\), \(\sigma(w) = s^2 / (s^2 + |w|^2) \in (0, 1]\): the
geometric blend of a damping \(n_j\) near the target and \(f_j\) far from it, so
\(\hat D(w) \ge \delta I\) with \(\delta = \min_j \min(n_j, f_j) > 0\). The paper's law is
``b = 0``, ``n = f = diag(D_hat)``, see `shaped_from_gains`.

Like the paper's `jaxsleigh.Gains`, a `ShapedGains` is integrated in the w chart (where \(H_d\) is
monitored); called as ``law(q, v)`` it is the same law in the physical chart (for actuators). It reads
only \(q\) and \(v = Q(q)^\top \dot q\) (Remark 1).
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from .coordinates import Q_w_entries, q_to_w
from .smallmat import rmatvec

__all__ = ["ShapedGains", "shaped_gains", "shaped_from_gains", "load_shaped"]


def _huber_slope(w, c):
    """\\(w / \\sqrt{1 + (w/c)^2}\\)."""
    r = w / c
    return w * (1.0 / jnp.sqrt(1.0 + r * r))


def _huber_value(w, c):
    """\\(c^2 (\\sqrt{1 + (w/c)^2} - 1) = w^2 / (1 + \\sqrt{1 + (w/c)^2})\\) (no cancellation near 0)."""
    r = w / c
    return w * w / (1.0 + jnp.sqrt(1.0 + r * r))


class ShapedGains(NamedTuple):
    r"""Parameters of the shaped-energy law (module docstring). Every field is positive (``B`` may be 0).

    Attributes:
      L: (3,) quadratic part \(l_i > 0\) of \(\phi_i\).
      B: (3,) weight \(b_i \ge 0\) of the pseudo-Huber part of \(\phi_i\).
      C: (3,) width \(c_i > 0\) of the pseudo-Huber part.
      k: singular damping gain \(k > 0\) (as the paper's).
      D_near: (2,) damping injection \(n_j > 0\) at the target.
      D_far: (2,) damping injection \(f_j > 0\) far from it.
      s: width \(s > 0\) of the blend \(\sigma(w) = s^2 / (s^2 + |w|^2)\).
    """

    L: Any
    B: Any
    C: Any
    k: Any
    D_near: Any
    D_far: Any
    s: Any

    # class attributes, not fields (no annotation)
    name = "shaped"
    citation = ("the paper's law with a separable shaped potential and state-dependent damping "
                "(docs/evidence/shaped-energy.md); preset jaxsleigh/presets/controllers/shaped.json")
    needs = ()
    w_chart = True
    positive = ("L", "B", "C", "k", "D_near", "D_far", "s")

    @classmethod
    def preset(cls, name: str = "shaped") -> "ShapedGains":
        """The shipped preset ``name`` (`load_shaped`): what ``--controller shaped`` runs."""
        return load_shaped(name)

    def potential(self, w):
        """\\(V(w) = \\sum_i \\phi_i(w_i)\\)."""
        return sum(0.5 * self.L[i] * w[i] * w[i] + self.B[i] * _huber_value(w[i], self.C[i]) for i in range(3))

    def potential_grad(self, w):
        """\\((\\phi_1'(w_1), \\phi_2'(w_2), \\phi_3'(w_3))\\) as a tuple."""
        return tuple(self.L[i] * w[i] + self.B[i] * _huber_slope(w[i], self.C[i]) for i in range(3))

    def damping_diag(self, w):
        """\\((\\hat d_1(w), \\hat d_2(w))\\) as a tuple."""
        s2 = self.s * self.s
        sigma = s2 / (s2 + w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
        return tuple(jnp.exp(sigma * jnp.log(self.D_near[j]) + (1.0 - sigma) * jnp.log(self.D_far[j]))
                     for j in range(2))

    def w2_stiffness(self, w):
        """\\(\\phi_2''(w_2) = l_2 + b_2 (1 + (w_2/c_2)^2)^{-3/2}\\) (`jaxsleigh.model.w_laws.w2_stiffness`)."""
        r = w[1] / self.C[1]
        g = 1.0 / jnp.sqrt(1.0 + r * r)
        return self.L[1] + self.B[1] * (g * g * g)

    def stiff_coeff(self, w):
        """\\(\\hat d_2(w) + k / w_1^2\\): the coefficient of \\(-v_2\\) in the turning moment."""
        return self.damping_diag(w)[1] + self.k / (w[0] * w[0])

    def injection_components(self, w, v):
        """\\((\\hat D(w) + D_i(w)) v\\) as a tuple."""
        d1, d2 = self.damping_diag(w)
        return (d1 * v[0], (d2 + self.k / (w[0] * w[0])) * v[1])

    def control_w_components(self, w, v):
        """\\(u = -Q_w^\\top \\nabla V - (\\hat D + D_i) v\\) on components (one trajectory or batch-last)."""
        force = rmatvec(Q_w_entries(w), self.potential_grad(w))
        inj = self.injection_components(w, v)
        return (-force[0] - inj[0], -force[1] - inj[1])

    def __call__(self, q, v):
        """The law in the physical chart, from the measured \\(q\\) and \\(v\\) (for actuators)."""
        w = q_to_w(q)
        return jnp.stack(self.control_w_components(w, v)).astype(w.dtype)


def shaped_gains(L, B, C, k, D_near, D_far, s) -> ShapedGains:
    """A validated `ShapedGains` (float64 NumPy leaves); ``ValueError`` saying which condition of the proof
    fails: ``L, C, k, D_near, D_far, s > 0``, ``B >= 0``, finite, of shapes (3,), (3,), (3,), (), (2,), (2,), ()."""
    out = {}
    for name, value, shape, strict in (("L", L, (3,), True), ("B", B, (3,), False), ("C", C, (3,), True),
                                       ("k", k, (), True), ("D_near", D_near, (2,), True),
                                       ("D_far", D_far, (2,), True), ("s", s, (), True)):
        try:
            a = np.asarray(value, np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"shaped gains: {name} must be real numbers, got {value!r}") from None
        if a.shape != shape:
            raise ValueError(f"shaped gains: {name} must have shape {shape}, got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"shaped gains: {name} must be finite, got {a.tolist()}")
        if np.any(a <= 0 if strict else a < 0):
            why = {"L": "each phi_i must be strictly convex and coercive",
                   "B": "the pseudo-Huber part must be convex", "C": "widths are lengths",
                   "k": "Lemma 2 needs k > 0", "s": "the blend's width is a length"}.get(name, "D_hat(w) >= delta I > 0")
            raise ValueError(f"shaped gains: {name} must be {'> 0' if strict else '>= 0'} ({why}), got {a.tolist()}")
        out[name] = a
    return ShapedGains(**out)


def shaped_from_gains(gains, *, B=(0.0, 0.0, 0.0), C=(1.0, 1.0, 1.0), s=1.0) -> ShapedGains:
    """The paper's law ``gains`` (a `jaxsleigh.Gains` with diagonal ``D_hat``) as a `ShapedGains`: with the default
    ``B = 0`` the same law exactly; a start for tuning the shaped family."""
    D = np.asarray(gains.D_hat, np.float64)
    if D.shape != (2, 2) or D[0, 1] != 0 or D[1, 0] != 0:
        raise ValueError(f"shaped_from_gains needs a diagonal D_hat, got {D.tolist()}")
    d = np.diag(D)
    return shaped_gains(gains.L, B, C, gains.k, d, d, s)


_PRESETS = Path(__file__).resolve().parent.parent / "presets" / "controllers"


def load_shaped(spec="shaped") -> ShapedGains:
    """A `ShapedGains` from a preset name (``"shaped"``: ``jaxsleigh/presets/controllers/shaped.json``, written by
    ``experiments/studies/shaped_study.py``) or a JSON file with the fields of `ShapedGains` (a ``"meta"`` entry is kept
    out)."""
    path = _PRESETS / f"{spec}.json"
    if not path.is_file():
        path = Path(spec)
    if not path.is_file():
        names = sorted(p.stem for p in _PRESETS.glob("*.json"))
        raise ValueError(f"shaped gains {str(spec)!r} not found; give a JSON file or a preset ({', '.join(names)})")
    try:
        d = json.loads(path.read_text())
        return shaped_gains(**{k: d[k] for k in ShapedGains._fields})
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError) as e:
        raise ValueError(f"shaped gains file {str(path)!r} is not a JSON object with the fields "
                         f"{', '.join(ShapedGains._fields)} ({type(e).__name__}: {e})") from None
