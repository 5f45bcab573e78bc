r"""Coordinate maps of the paper, \(q \to z \to w\), and the matrices derived from them.

* \(z = f_z(q)\) (paper eq. 4) and \(Q_z = \frac{\partial f_z}{\partial q} Q\) (eq. 6),
  with left annihilator \(Q_z^\perp\) (eq. 7).
* \(w = f_w(z)\) (eq. 8), its inverse (eq. 9) and
  \(Q_w = \frac{\partial f_w}{\partial z} Q_z \big|_{z = f_w^{-1}(w)}\) (eq. 11).

**Correction of the paper.** The printed \(Q_w\) (eq. 11) does not follow from its own
definition. Differentiating the printed maps gives (checked symbolically and, in
``tests/test_coordinates.py``, against ``jax.jacfwd``)

\[ Q_w(w) = \begin{bmatrix} 0 & 1 \\ 1/w_1 & -\frac{3 w_2 + w_3}{w_1} - \tfrac12 w_1 w_3 \\ 0 & \frac{2 w_2}{w_1} \end{bmatrix} \]

whereas the paper prints ``1``, ``-2 w_2/w_1 - w_3 - w_1^2 w_3 / 2`` and ``2 w_2 / w_1^2`` for
the three entries that differ. All the other printed formulas (f_z, f_w, f_w^{-1}, Q_z,
Q_z^perp, Remark 1 (eq. 14), the matrix of eq. 27) agree with each other and with this Q_w. With the
printed matrix in the control law the closed-loop Hamiltonian *increases* at some states
(``tests/test_closed_loop.py::test_printed_Qw_breaks_passivity``); with the derived one it never
does. `Q_w_printed` keeps the paper's version for that demonstration only.

All maps act on single points (shape (3,)); ``vmap`` them for batches. They are undefined on the
singular set \(\theta = w_1 = z_1 = 0\).
"""
from __future__ import annotations

import jax.numpy as jnp

from .smallmat import as_array

__all__ = [
    "Q_entries",
    "Q_w_entries",
    "Q",
    "f_z",
    "f_z_inv",
    "Q_z",
    "Q_z_perp",
    "f_w",
    "f_w_inv",
    "Q_w",
    "Q_w_printed",
    "q_to_w",
    "w_to_q",
]


def Q_entries(q):
    """Rows of \\(Q(q)\\) (eq. 2), structural zeros and ones as literals (see `.smallmat`)."""
    c, s = jnp.cos(q[2]), jnp.sin(q[2])
    return ((c, 0), (s, 0), (0, 1))


def Q(q):
    """Input/kinematic matrix of the plant, \\(\\dot q = Q(q) \\nabla_p H\\) (paper eq. 2)."""
    return as_array(Q_entries(q), q[2])


def f_z(q):
    """\\(z = (\\theta,\\ x\\cos\\theta + y\\sin\\theta,\\ x\\sin\\theta - y\\cos\\theta)\\) (eq. 4)."""
    x, y, th = q[0], q[1], q[2]
    c, s = jnp.cos(th), jnp.sin(th)
    return jnp.stack([th, x * c + y * s, x * s - y * c])


def f_z_inv(z):
    """Inverse of `f_z`: \\((x, y, \\theta) = (z_2 c + z_3 s,\\ z_2 s - z_3 c,\\ z_1)\\)."""
    c, s = jnp.cos(z[0]), jnp.sin(z[0])
    return jnp.stack([z[1] * c + z[2] * s, z[1] * s - z[2] * c, z[0]])


def Q_z(z):
    """\\(Q_z = \\frac{\\partial f_z}{\\partial q} Q\\) in z coordinates (eq. 6)."""
    return as_array(((0, 1), (1, -z[2]), (0, z[1])), z[0])


def Q_z_perp(z):
    """Full-rank left annihilator of `Q_z`, \\([-z_2, 0, 1]\\) (eq. 7), shape (1, 3)."""
    return as_array(((-z[1], 0, 1),), z[0])


def f_w(z):
    """\\(w = (z_1,\\ z_2/z_1 - 2 z_3/z_1^2,\\ 2 z_3/z_1^2)\\) (eq. 8); singular at \\(z_1 = 0\\)."""
    inv = 1.0 / z[0]
    w3 = 2.0 * z[2] * inv * inv
    return jnp.stack([z[0], z[1] * inv - w3, w3])


def f_w_inv(w):
    """\\(z = (w_1,\\ w_1 (w_2 + w_3),\\ \\tfrac12 w_1^2 w_3)\\) (eq. 9); smooth everywhere."""
    return jnp.stack([w[0], w[0] * (w[1] + w[2]), 0.5 * w[0] * w[0] * w[2]])


def Q_w_entries(w):
    """Rows of the **derived** \\(Q_w(w)\\) (corrects eq. 11; see the module docstring)."""
    w1, w2, w3 = w[0], w[1], w[2]
    inv = 1.0 / w1
    return ((0, 1),
            (inv, -(3.0 * w2 + w3) * inv - 0.5 * w1 * w3),
            (0, 2.0 * w2 * inv))


def Q_w(w):
    """\\(Q_w = \\frac{\\partial f_w}{\\partial z} Q_z|_{z = f_w^{-1}(w)}\\), **derived** (corrects eq. 11).

    See the module docstring for the printed version and why it is wrong.
    """
    return as_array(Q_w_entries(w), w[0])


def Q_w_printed(w):
    """The paper's printed eq. 11 (**wrong**; kept only to show, in tests, that it breaks passivity)."""
    w1, w2, w3 = w[0], w[1], w[2]
    return as_array(((0, 1), (1, -2.0 * w2 / w1 - w3 - 0.5 * w1 * w1 * w3), (0, 2.0 * w2 / (w1 * w1))), w1)


def q_to_w(q):
    """\\(w = f_w(f_z(q))\\)."""
    return f_w(f_z(q))


def w_to_q(w):
    """\\(q = f_z^{-1}(f_w^{-1}(w))\\)."""
    return f_z_inv(f_w_inv(w))
