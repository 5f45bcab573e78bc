r"""The laws integrated in the w chart, behind one interface: the paper's `jaxsleigh.Gains` (eq. 13) and any
law that declares ``w_chart = True`` (`jaxsleigh.model.shaped_law.ShapedGains`).

A w-chart law is energy shaping plus damping injection,

\[ u = -Q_w^\top(w)\,\nabla V(w) - \big(\hat D(w, v) + D_i(w, v)\big) v, \qquad H_d = \tfrac12 p^\top M^{-1} p + V(w), \]

so along the closed loop \(\dot H_d = -v^\top (D + \hat D + D_i) v \le 0\) whatever \(V\) is (the engine monitors
it). Such a law provides ``potential(w)``, ``control_w_components(w, v)``, ``injection_components(w, v)`` and
``stiff_coeff(w)`` (the coefficient of \(-v_2\) in the turning moment) and ``w2_stiffness(w)``
(\(\partial^2 V / \partial w_2^2\)), for the exponential step of `jaxsleigh.integrate.etd`; the paper's law has
them as methods of `jaxsleigh.Gains` (over the functions of `jaxsleigh.model.paper_law`), so these functions
only call the law's own.
"""
from __future__ import annotations

__all__ = ["is_w_law", "potential", "control_w_components", "injection_components", "stiff_coeff", "w2_stiffness"]


def is_w_law(controller) -> bool:
    """True for a law integrated in the w chart: one that says ``w_chart = True`` (`jaxsleigh.Gains`, ...)."""
    return bool(getattr(type(controller), "w_chart", False))


def potential(w, law):
    """\\(V(w)\\), the shaped potential of \\(H_d\\)."""
    return law.potential(w)


def control_w_components(w, v, law):
    """\\(u\\) on components, from \\(w\\) and \\(v = \\nabla_p H\\)."""
    return law.control_w_components(w, v)


def injection_components(w, v, law):
    """\\((\\hat D + D_i) v\\) on components."""
    return law.injection_components(w, v)


def stiff_coeff(w, law):
    """\\(\\hat D_{22} + k / w_1^2\\) (may depend on \\(w\\)), or ``None`` for a law without that form."""
    fn = getattr(law, "stiff_coeff", None)
    return None if fn is None else fn(w)


def w2_stiffness(w, law):
    """\\(\\partial^2 V / \\partial w_2^2\\) (the paper's: \\(L_2\\)), or ``None`` for a law that does not say.
    With \\(\\dot w_2 = p_1 / (m w_1) + \\ldots\\) and \\(u_1 = -\\partial_{w_2} V / w_1 - \\ldots\\) it sets the
    frequency \\(\\sqrt{V_{22} / m} / |w_1|\\) of the (w2, p1) oscillation, stiff near \\(\\theta = 0\\)."""
    fn = getattr(law, "w2_stiffness", None)
    return None if fn is None else fn(w)
