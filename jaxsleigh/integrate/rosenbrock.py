r"""A linearly implicit step for stiff flights: the modified Rosenbrock pair of order 2(3) of Shampine and Reichelt.

**Why.** A start very close to \(\theta = 0\) flies off with a huge \(H_d\) and its closed loop is stiff for the
whole flight (`jaxsleigh.integrate.stragglers`): the explicit RK4 step is held at \(10^{-7}\)-\(10^{-5}\) s by
stability, not accuracy, and uses its whole budget of attempts before \(t = 1\) s. An implicit method crosses the
same 100 s in a few thousand steps (measured: `experiments/performance/flier_stiffness.py`,
`experiments/performance/flier_rosenbrock.py`). The ensemble engine therefore switches a trajectory to this step
once it is still flying after `jaxsleigh.integrate.engine.STIFF_AFTER` attempts.

**The step** (MATLAB's ``ode23s``; L. F. Shampine and M. W. Reichelt, *The MATLAB ODE suite*, SIAM J. Sci. Comput.
18(1), 1997). With \(F_0 = f(t, y)\), \(J = \partial f / \partial y\), \(T = \partial f / \partial t\) at
\((t, y)\), \(d = 1 / (2 + \sqrt 2)\), \(e_{32} = 6 + \sqrt 2\) and \(W = I - h d J\):

\[ k_1 = W^{-1}(F_0 + h d T), \qquad F_1 = f(t + \tfrac h2, y + \tfrac h2 k_1), \qquad
   k_2 = W^{-1}(F_1 - k_1) + k_1, \qquad y_1 = y + h k_2, \]
\[ F_2 = f(t + h, y_1), \qquad k_3 = W^{-1}\big(F_2 - e_{32}(k_2 - F_1) - 2 (k_1 - F_0) + h d T\big), \qquad
   e = \tfrac h6 (k_1 - 2 k_2 + k_3). \]

\(y_1\) is second order and L-stable (\(W\) holds the stiff part whatever \(h\)); \(e\) estimates its local error,
which is \(O(h^3)\), so the next step follows \(\mathrm{err}^{-1/3}\) (`jaxsleigh.integrate.stepsize`). \(F_2\) is
the next step's \(F_0\) (first same as last) and, with \(F_0\), gives \(T_\epsilon\)'s cubic Hermite dense output
as for RK4. The observers' integrals (the control effort) use Simpson's rule on \(g(y)\), \(g(y + \tfrac h2 k_1)\)
and \(g(y_1)\); the midpoint is the stage \(y + \tfrac h2 k_1 = y(t + \tfrac h2) + O(h^2)\), so the rule is as
accurate as the state, and its difference from the trapezoid rule is its error estimate.

\(J\) and \(T\) come from one `jax.linearize` of the field, its six products batched into one (``vmap`` over
the unit directions: one product in the program, not six; no finite differences), \(W\) is factorised by Gaussian
elimination with partial pivoting written out for the 5x5 case on batch-last arrays: every operation is elementwise
over the lanes, so a lane's bits do not depend on the lanes beside it.

**Derivatives.** The three solves with \(W\) are `jax.lax.custom_linear_solve`: differentiated, \(x = W^{-1} b\)
gives \(\dot x = W^{-1}(\dot b - \dot W x)\) and, in reverse mode, \(\bar b = W^{-\top} \bar x\),
\(\bar W = -\bar b\, x^\top\), with \(W^{-\top}\) from the same factors (\(P W = L U\) gives
\(W^\top = U^\top L^\top P\): `lu_solve_transposed`). So the elimination is never differentiated, only \(W\)'s
product with a vector is. With the batched Jacobian, the step's reverse-mode program is a third smaller (StableHLO
lines of one attempt, `experiments/performance/step_program.py`: 3,681 where 5,598); the values are the same bits,
the derivatives agree with those of the differentiated elimination to rounding (``tests/test_rosenbrock.py``).
"""
from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from .jacobian import jacobian_columns

__all__ = ["rosenbrock_stages", "lu_factor", "lu_solve", "lu_solve_transposed"]

D = 1.0 / (2.0 + math.sqrt(2.0))
E32 = 6.0 + math.sqrt(2.0)


def lu_factor(a):
    """``a`` (an ``n x n`` nested list of arrays, every entry one number per lane) factorised with partial pivoting:
    ``(swaps, lower, upper)`` for `lu_solve`. The pivot of column ``j`` is brought up by pairwise swaps (each lane
    swaps where the candidate is larger in magnitude), so a lane's arithmetic is its own."""
    a = [list(row) for row in a]
    n = len(a)
    swaps, lower = [], {}
    for j in range(n):
        for r in range(j + 1, n):
            swap = jnp.abs(a[r][j]) > jnp.abs(a[j][j])
            a[j], a[r] = ([jnp.where(swap, x, y) for x, y in zip(a[r], a[j])],
                          [jnp.where(swap, y, x) for x, y in zip(a[r], a[j])])
            for c in range(j):          # the multipliers of the columns done travel with their rows
                lower[j, c], lower[r, c] = (jnp.where(swap, lower[r, c], lower[j, c]),
                                            jnp.where(swap, lower[j, c], lower[r, c]))
            swaps.append((j, r, swap))
        inv = 1.0 / a[j][j]
        for r in range(j + 1, n):
            m = a[r][j] * inv
            lower[r, j] = m
            a[r] = [a[r][c] - m * a[j][c] if c > j else a[r][c] for c in range(n)]
    return swaps, lower, a


def lu_solve(factors, b):
    """The solution ``x`` of ``a x = b`` from ``lu_factor(a)``; ``b`` and ``x`` are lists of ``n`` arrays."""
    swaps, lower, upper = factors
    b = list(b)
    for j, r, swap in swaps:
        b[j], b[r] = jnp.where(swap, b[r], b[j]), jnp.where(swap, b[j], b[r])
    n = len(b)
    for j in range(n):
        for r in range(j + 1, n):
            b[r] = b[r] - lower[r, j] * b[j]
    x = [None] * n
    for r in reversed(range(n)):
        acc = b[r]
        for c in range(r + 1, n):
            acc = acc - upper[r][c] * x[c]
        x[r] = acc / upper[r][r]
    return x


def lu_solve_transposed(factors, b):
    """The solution ``x`` of ``a^T x = b`` from ``lu_factor(a)`` (``P a = L U``, so ``a^T = U^T L^T P``): ``U^T`` by
    forward substitution, ``L^T`` (unit diagonal) by back substitution, then the swaps undone in reverse order."""
    swaps, lower, upper = factors
    n = len(b)
    z = list(b)
    for r in range(n):
        acc = z[r]
        for c in range(r):
            acc = acc - upper[c][r] * z[c]
        z[r] = acc / upper[r][r]
    for r in reversed(range(n)):
        for c in range(r + 1, n):
            z[r] = z[r] - lower[c, r] * z[c]
    for j, r, swap in reversed(swaps):
        z[j], z[r] = jnp.where(swap, z[r], z[j]), jnp.where(swap, z[j], z[r])
    return z


def rosenbrock_stages(field_and_control, t, y, h, args, f0):
    r"""One Rosenbrock step (module docstring) from ``y`` at ``t`` of size ``h``, with ``f0 = f(t, y)`` known.

    ``field_and_control(t, y, args) -> (f, u)``; ``y`` is ``(n,)`` or batch-last ``(n, N)``, ``t`` and ``h`` scalars
    or ``(N,)``. Returns ``(dy, f2, u2, e, mid)``: the increment \(h k_2\), \(F_2 = f(t + h, y_1)\) and the control
    there, the error estimate \(e\), and ``(y_mid, u_mid, f1)`` at the stage \(y + \tfrac h2 k_1\)."""
    n = y.shape[0]
    t = jnp.asarray(t, y.dtype)
    dft, cols = jacobian_columns(lambda tt, yy: field_and_control(tt, yy, args)[0], t, y, with_time=True)
    hd = h * D
    w = [[(1.0 if r == c else 0.0) - hd * cols[c][r] for c in range(n)] for r in range(n)]
    lu = lu_factor([[jax.lax.stop_gradient(x) for x in row] for row in w])   # never differentiated: see the module

    def product(x):
        return jnp.stack([sum(w[r][c] * x[c] for c in range(n)) for r in range(n)])

    def solve(v):
        return jax.lax.custom_linear_solve(
            product, v, lambda _, b: jnp.stack(lu_solve(lu, [b[i] for i in range(n)])),
            transpose_solve=lambda _, b: jnp.stack(lu_solve_transposed(lu, [b[i] for i in range(n)])))

    k1 = solve(f0 + hd * dft)
    y_mid = y + (0.5 * h) * k1
    f1, u_mid = field_and_control(t + 0.5 * h, y_mid, args)
    k2 = solve(f1 - k1) + k1
    dy = h * k2
    f2, u2 = field_and_control(t + h, y + dy, args)
    k3 = solve(f2 - E32 * (k2 - f1) - 2.0 * (k1 - f0) + hd * dft)
    e = (h / 6.0) * (k1 - 2.0 * k2 + k3)
    return dy, f2, u2, e, (y_mid, u_mid, f1)
