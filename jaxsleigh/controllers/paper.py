r"""The paper's law (Ferguson, Donaire and Middleton 2018, eq. 13) as a plain controller ``u = law(q, v)``.

`jaxsleigh.Gains` passed as ``gains=`` or ``controller=`` is integrated in the w chart, where the law is
port-Hamiltonian and \(H_d\) is monitored. `PaperLaw` is the same law evaluated the way a digital
controller would, from the measured \(q\) and \(v\) in the physical chart: what actuator pieces
(saturation, sampling) wrap, since they break the w chart's structure.

\[ u = -Q_w^\top(w) L w - \hat D v - \mathrm{diag}(0,\ k / w_1^2)\, v, \qquad w = f_w(f_z(q)) \]
"""
from __future__ import annotations

from typing import NamedTuple

from ..model.coordinates import q_to_w
from ..model.paper_law import control_w
from ..model.controller import is_paper_law
from ..model.params import Gains, paper_gains

__all__ = ["PaperLaw", "measured_law"]


class PaperLaw(NamedTuple):
    """The paper's law in the physical chart (no singular-set handling: \\(u\\) is infinite on \\(\\theta = 0\\))."""

    gains: Gains = paper_gains()

    # class attributes, not fields (no annotation: a NamedTuple would make them leaves)
    name = "paper"
    citation = ("Ferguson, Donaire, Middleton, Discontinuous energy shaping control of the Chaplygin "
                               "sleigh, IFAC-PapersOnLine 51(3):211-216, 2018")
    needs = ()

    def __call__(self, q, v):
        return control_w(q_to_w(q), v, self.gains)


def measured_law(law):
    """The law as an actuator piece (saturation, sampling) evaluates it, from the measured \\(q\\) and \\(v\\):
    the paper's `jaxsleigh.Gains` as `PaperLaw` (the same floating-point operations as ``gains(q, v)``; the wrapper
    keeps the records' and the tuner's names ``law.gains.k``), any other law as it is."""
    return PaperLaw(law) if is_paper_law(law) else law
