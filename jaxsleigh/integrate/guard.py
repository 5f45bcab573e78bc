r"""The settled oscillation's guard: resolve the \((w_2, p_1)\) oscillation where it is weakly damped or growing.

After settling, the closed loop in the w chart has a complex pair of Jacobian eigenvalues
\(\sigma \pm i\omega\), \(\omega \approx \sqrt{V_{22}/m}/|w_1|\), whose mode lives in \((w_2, p_1)\) and, through
the coupling \(\partial \dot w_2 / \partial p_2\), \(\partial \dot p_2 / \partial w_2\), in \(p_2\). For the paper's
gains it is well damped (\(\sigma \approx -1.2 \ldots -1.7\) s\(^{-1}\) along the README's starts); for gains with
little singular damping \(k\) or a shaped potential, \(\sigma\) rises through zero as \(\theta \to 0\) (the 0.2
``balanced`` gains: \(-0.85\) at 30 s, \(+1.24\) at 50 s; ``shaped``: \(-0.50\) at 30 s, \(+0.19\) at 60 s;
``docs/evidence/accuracy.md``). The mode then grows from the transient's remainder, of amplitude
\(10^{-9}\) or less, to \(10^{-2}\) and spends most of the control energy of the run.

No error estimate sees a mode below the tolerance, and a step of \(h \omega \gg 1\) (which the exponential step
of `jaxsleigh.integrate.etd` allows) gets its growth rate wrong: float32 at the default tolerances reported 5%
of the 0.2 gains' float64 energy on some starts. So near the target (\(|q| \le\) `NEAR` \(\epsilon\)), where the
pair is weakly damped, \(\sigma > -\delta\) (`DAMPING`), and not faster than `FASTEST`, the step is capped at
\(h \le c / \omega\) (`PHASE`) and the absolute tolerance divided by 100 (`ATOL_FACTOR`; not below `ATOL_FLOOR`):
the oscillation is resolved whatever its amplitude, the errors of the slow part stay below its seed, and its growth
rate comes out right. Elsewhere (the paper's gains,
the transient, a start flung far from the target) nothing changes. float32 gets the 0.2 gains' energies to a few
percent; closer it cannot: the onset hangs on the size of the seed, and float32's rounding is of that size
(``docs/evidence/settled-phase.md``; the accuracy audit, `jaxsleigh.studies.audit`, reports it).

**How \(\sigma\) is computed.** The 3x3 block \(B\) of the Jacobian on \((w_2, p_1, p_2)\) carries the pair exactly
(to the digits printed above, against the full 5x5 eigenvalues); its three columns are three forward-mode
products of the field. Its characteristic polynomial \(s^3 - \operatorname{tr} B\, s^2 + m_2 s - \det B\)
(\(m_2\) the sum of the principal 2x2 minors) has one real root \(r\), the stiff damping of \(p_2\), near
\(B_{33}\); Newton's method from \(B_{33}\) finds it, and the pair's real part is
\(\sigma = (\operatorname{tr} B - r) / 2\). The choice is not differentiated (``stop_gradient``).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from .jacobian import jacobian_columns

__all__ = ["pair_damping", "oscillation_guard", "grown_settled_mode", "DAMPING", "PHASE", "ATOL_FACTOR", "NEAR",
           "FASTEST", "ATOL_FLOOR", "GREW"]

#: \(\delta\) [1/s]: the pair counts as weakly damped where \(\sigma > -\delta\)
DAMPING = 0.75
#: \(c\) [rad]: the largest phase of the oscillation per step where it is weakly damped
PHASE = 0.5
#: [rad/s] the guard leaves a pair faster than this alone: \(\omega \propto 1/|w_1|\) grows without bound as
#: \(\theta \to 0\), and with it the cost of a cap \(c/\omega\). There the exponential step integrates the pair's
#: linear part exactly; where the guard corrects the energy (``balanced``, ``shaped``, the 0.2 ``balanced`` gains) the
#: pair is weak at lower frequencies (``experiments/studies/pair_damping.py``: 90% of weak states below 30 and 139
#: rad/s)
FASTEST = 500.0
#: the guard acts within this many radii of the ball |q| <= eps (the settled phase; not on a start flung far
#: from theta = 0, whose state and tolerances are of another scale)
NEAR = 4.0
#: the absolute tolerance's factor where the pair is weakly damped: the mode's seed, far below the tolerance, is
#: what grows; errors of the slow part must stay below it
ATOL_FACTOR = 1e-2
#: the guard tightens the absolute tolerance to no less than this: atol = 1e-8 resolves the settled phase in float32
#: and in float64 (``docs/evidence/settled-phase.md``), and float64's default is already there (tightened further,
#: the ``tuned`` gains' float64 runs spent their whole step budget on 36 of 2048 README starts)
ATOL_FLOOR = 1e-8
#: a row's settled oscillation has grown where its |theta| at the horizon is more than this factor above the
#: smallest |theta| of its run (a row whose oscillation stays damped ends at its smallest |theta|: theta shrinks
#: monotonically). On the README's starts the 0.2 ``balanced`` gains' rows whose float32 energy is more than 5% off
#: float64's all end at 1.25-1.55 times it, while ``shaped`` and ``balanced``, whose weakly damped oscillation the
#: guard resolves (energies within 1.7% of float64), end below 1.19 (``docs/evidence/accuracy.md``)
GREW = 1.2
#: (w2, p1, p2): the rows and columns of the block, in the w chart's state
_BLOCK = (1, 3, 4)


def pair_damping(field, t, y, args):
    r"""\((\sigma, \omega^2)\): the real part of the complex pair of the Jacobian block on \((w_2, p_1, p_2)\) of
    ``field`` at ``y`` (``(5,)`` or batch-last ``(5, N)``) and the square of its imaginary part (\(\le 0\): the
    block has three real eigenvalues there, no oscillation)."""
    _, cols = jacobian_columns(lambda tt, v: field(tt, v, args), t, y, _BLOCK)   # three products batched into one
    B = [[cols[c][_BLOCK[r]] for c in range(3)] for r in range(3)]
    tr = B[0][0] + B[1][1] + B[2][2]
    m2 = (B[0][0] * B[1][1] - B[0][1] * B[1][0] + B[0][0] * B[2][2] - B[0][2] * B[2][0]
          + B[1][1] * B[2][2] - B[1][2] * B[2][1])
    det = (B[0][0] * (B[1][1] * B[2][2] - B[1][2] * B[2][1]) - B[0][1] * (B[1][0] * B[2][2] - B[1][2] * B[2][0])
           + B[0][2] * (B[1][0] * B[2][1] - B[1][1] * B[2][0]))
    r = B[2][2]
    for _ in range(8):
        p = ((r - tr) * r + m2) * r - det
        dp = (3.0 * r - 2.0 * tr) * r + m2
        r = r - jnp.where(dp != 0, p / jnp.where(dp != 0, dp, 1.0), 0.0)
    sigma = 0.5 * (tr - r)
    # the other two roots are those of s^2 - 2 sigma s + det / r
    prod = det / jnp.where(r != 0, r, 1.0)
    return sigma, prod - sigma * sigma


def oscillation_guard(chart, t, y, args, atol, eps):
    r"""``(cap, atol)`` at ``y``: within `NEAR` radii ``eps`` of the target, where the block has a complex pair \(\sigma \pm i\omega\) that is weakly damped
    (\(\sigma > -\delta\)) the largest step \(c / \omega\) and the absolute tolerance ``atol`` times `ATOL_FACTOR`,
    elsewhere ``inf`` and ``atol``; ``None`` in a chart without the pair."""
    if chart.oscillation(y, args) is None:
        return None
    sigma, omega2 = pair_damping(chart.field, t, y, args)
    near = chart.q_norm2(y) <= (NEAR * eps) ** 2
    weak = jax.lax.stop_gradient(near & (omega2 > 0) & (omega2 < FASTEST ** 2) & (sigma > -DAMPING))
    cap = PHASE * jax.lax.rsqrt(jnp.where(omega2 > 0, omega2, 1.0))
    return (jax.lax.stop_gradient(jnp.where(weak, cap, jnp.inf).astype(y.dtype)),
            jnp.where(weak, jnp.minimum(atol, jnp.maximum(atol * ATOL_FACTOR, ATOL_FLOOR)), atol).astype(y.dtype))


def grown_settled_mode(chart, t, y, args, min_abs_theta, eps):
    r"""Per row of a batch-last ``y`` ``(5, N)`` (the chart's final states at ``t``): ``True`` where the settled
    oscillation has grown and is still weakly damped or growing at the horizon, so that what the row reports
    (its control energy above all) hangs on the size of the oscillation's seed, which is below every tolerance.

    A row is flagged where, at the horizon, it is within `NEAR` radii ``eps`` of the target, its pair
    \(\sigma \pm i\omega\) is weakly damped or growing (\(\sigma > -\delta\), `DAMPING`: the guard's own test) and
    \(|\theta(T)| > \) `GREW` \(\cdot \min_t |\theta|\): the oscillation has moved \(\theta\) back out from its
    closest approach (``min_abs_theta``, an on-line summary of the run). ``None`` in a chart without the pair
    (no law but the w chart's has it)."""
    if chart.oscillation(y, args) is None:
        return None
    sigma, omega2 = pair_damping(chart.field, t, y, args)
    near = chart.q_norm2(y) <= (NEAR * eps) ** 2
    grew = chart.abs_theta(y) > GREW * min_abs_theta
    return near & grew & (omega2 > 0) & (sigma > -DAMPING)
