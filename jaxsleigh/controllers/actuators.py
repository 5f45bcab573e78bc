r"""Actuators between a feedback law and the plant: saturation of the force, and the digital part.

A real sleigh cannot apply any force: its motors saturate, and a digital controller measures, computes
and updates its output only at sampling instants. The pieces here wrap a law (any controller in the sense
of `jaxsleigh.model.controller`) and are themselves laws, so they compose
(``Saturation(NormSaturation(PaperLaw(), 10.0), (8.0, 4.0))``), run through `jaxsleigh.solve`, `jaxsleigh.simulate`,
`jaxsleigh.run_ensemble` and `jaxsleigh.integrate.sampled.solve_sampled`, and are differentiable (their
numbers are traced leaves; ``jax.grad`` goes through them, also with respect to ``u_max``).

* `Saturation`: per-component clipping, \(u_i = \operatorname{clip}(\hat u_i, -\bar u_i, \bar u_i)\).
* `NormSaturation`: the Euclidean norm bounded, direction kept,
  \(u = \hat u \min(1, \bar u / \|\hat u\|)\).
* `Sampler`: zero-order hold at period \(T_s\), a delay of whole samples, Gaussian measurement noise. It is
  not a law (the sampled loop is not an ODE): ``sampled(law, period)`` puts it behind a law, and `jaxsleigh.solve`
  (one start, traced) or `jaxsleigh.integrate.sampled.solve_sampled` (a batch) integrates that.

The classes do not check their numbers when constructed (JAX rebuilds them from arbitrary leaves inside
``jit``, ``vmap`` and ``grad``); build them with the checking factories `saturate` and `sampler`, which
raise ``ValueError`` for a ``u_max <= 0``, a non-finite value, a bad period, delay or noise.
"""
from __future__ import annotations

import math
import numbers
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..model.controller import FunctionLaw, PerTrajectory, is_time_varying
from .paper import measured_law

__all__ = ["Saturation", "NormSaturation", "Sampler", "Sampled", "saturate", "sampler", "sampled", "is_sampled",
           "check_u_max", "check_sampler"]


def _inner_u(law, q, v, t):
    """The wrapped law's ``u`` (2,), called with ``t`` only when it is time-varying."""
    return jnp.asarray(law(q, v, t) if is_time_varying(law) else law(q, v))


class Saturation(NamedTuple):
    r"""Per-component saturation of a law's output (an actuator with a force and a torque limit).

    \[ u_i = \operatorname{clip}(\hat u_i(q, v),\ -\bar u_i,\ \bar u_i), \qquad i = 1, 2 \]

    ``law``: the wrapped controller \(\hat u\); ``u_max``: \(\bar u\), a scalar (the same bound on the force
    [N] and on the moment [N m]) or a pair ``(u1_max, u2_max)``; it must be > 0 and finite (checked by
    `saturate`, not here). Where \(|\hat u_i| < \bar u_i\) the output equals the law's and so does its
    derivative; where a component is clipped, its derivative with respect to the state is 0 and with
    respect to \(\bar u_i\) is \(\pm 1\). A non-finite ``±inf`` of the law is clipped to \(\pm\bar u_i\); NaN
    stays NaN. Time-varying exactly when the wrapped law is (``law(q, v, t)`` is forwarded).
    """

    law: Any
    u_max: Any

    name = "saturation"

    @property
    def time_varying(self) -> bool:
        return is_time_varying(self.law)

    def __call__(self, q, v, *t):
        u = _inner_u(self.law, q, v, t[0] if t else 0.0)
        bound = jnp.broadcast_to(jnp.asarray(self.u_max, u.dtype), u.shape)
        return jnp.clip(u, -bound, bound)


class NormSaturation(NamedTuple):
    r"""Saturation of the Euclidean norm of a law's output, keeping its direction.

    \[ u = \hat u(q, v)\, \min\!\Big(1,\ \frac{\bar u}{\|\hat u(q, v)\|}\Big), \qquad \|u\| \le \bar u \]

    ``law``: the wrapped controller \(\hat u\); ``u_max``: \(\bar u > 0\), a scalar (checked by `saturate`).
    Safe at \(\hat u = 0\) (value and gradient: the scale is 1 there, no \(0/0\)). Inside the ball the output
    and its derivatives equal the law's. Mixed units (N and N m) are taken as they come, as in
    ``u_norm_peak``. Time-varying exactly when the wrapped law is.
    """

    law: Any
    u_max: Any

    name = "norm_saturation"

    @property
    def time_varying(self) -> bool:
        return is_time_varying(self.law)

    def __call__(self, q, v, *t):
        u = _inner_u(self.law, q, v, t[0] if t else 0.0)
        bound = jnp.asarray(self.u_max, u.dtype)
        n2 = jnp.sum(u * u)
        over = n2 > bound * bound
        n_safe = jnp.sqrt(jnp.where(over, n2, jnp.ones_like(n2)))   # never sqrt(0): a finite gradient at u = 0
        return u * jnp.where(over, bound / n_safe, jnp.ones_like(n2))


class Sampler(NamedTuple):
    r"""The digital part of a controller: sampling, zero-order hold, delay, measurement noise.

    At the instants \(t_k = k T_s\) the controller measures \(\tilde q_k = q(t_k) + \sigma \xi^q_k\),
    \(\tilde v_k = v(t_k) + \sigma \xi^v_k\) (\(\xi \sim \mathcal N(0, I)\), drawn from ``jax.random`` keyed by
    ``(seed, k)``: the same seed gives the same bytes), computes \(\hat u_k = \mathrm{law}(\tilde q_k, \tilde v_k, t_k)\),
    and the plant receives

    \[ u(t) = \hat u_{k - d} \quad (t \in [t_k, t_{k+1})), \qquad \hat u_{j} = 0 \text{ for } j < 0, \]

    ``d = delay`` whole samples (computation and communication latency).

    Fields: ``period`` \(T_s\) [s] > 0; ``delay`` \(d\), an integer >= 0; ``noise`` \(\sigma \ge 0\) (the same
    standard deviation on every component of \(q\) and \(v\), in their units); ``seed`` an integer.
    Build it with `sampler` (checks them); `jaxsleigh.integrate.sampled.solve_sampled` checks them too.
    """

    period: float
    delay: int = 0
    noise: float = 0.0
    seed: int = 0

    name = "sampler"


def check_u_max(u_max, *, norm: bool = False):
    """``u_max`` as a float64 array after checking it: finite and > 0, a scalar (or, per component, a pair;
    for `NormSaturation` only a scalar). Raises ``ValueError`` naming ``u_max``."""
    try:
        a = np.asarray(u_max, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"u_max must be a positive finite number{'' if norm else ' or a pair of them'}, "
                         f"got {u_max!r}") from None
    if norm and a.ndim != 0:
        raise ValueError(f"u_max of a norm saturation must be one positive number (a bound on ||u||), got shape "
                         f"{a.shape}")
    if a.ndim > 1 or (a.ndim == 1 and a.shape != (2,)):
        raise ValueError(f"u_max must be a scalar or a pair (u1_max [N], u2_max [N m]), got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"u_max must be finite, got {u_max!r}")
    if not np.all(a > 0):
        raise ValueError(f"u_max must be > 0 (an actuator's bound), got {u_max!r}")
    return a


def _as_law(law):
    """A plain function (not a pytree of numbers) as a `FunctionLaw`, so that the wrapper stays a pytree."""
    if not callable(law):
        raise ValueError(f"the law to saturate must be a feedback law u = law(q, v), got {type(law).__name__}")
    if isinstance(law, tuple) or hasattr(law, "tree_flatten"):
        return law
    leaves = jax.tree_util.tree_leaves(law)
    if leaves == [law]:               # a function or an opaque object: its own (static) leaf
        return FunctionLaw(law)
    return law


def saturate(law, u_max, norm: bool = False):
    """Checked `Saturation` (``norm=False``: per component) or `NormSaturation` (``norm=True``) of ``law``.

    ``u_max`` must be finite and > 0 (``ValueError`` naming it otherwise). A plain function is wrapped in
    `jaxsleigh.model.controller.FunctionLaw`; the paper's `jaxsleigh.Gains` in `PaperLaw` (the law evaluated from
    the measured q and v, as an actuator sees it).
    """
    a = check_u_max(u_max, norm=norm)
    law = _as_law(measured_law(law))
    value = float(a) if a.ndim == 0 else tuple(float(x) for x in a)
    return NormSaturation(law, value) if norm else Saturation(law, value)


def check_sampler(s: Sampler) -> Sampler:
    """The sampler with its numbers as Python numbers after checking them (``ValueError`` naming the field):
    ``period`` > 0 and finite, ``delay`` an integer >= 0, ``noise`` >= 0 and finite, ``seed`` an integer."""
    if not isinstance(s, Sampler):
        raise ValueError(f"sampler must be a jaxsleigh.controllers.actuators.Sampler, got {type(s).__name__}")
    try:
        period = float(s.period)
    except (TypeError, ValueError):
        raise ValueError(f"sampler period must be a number of seconds, got {s.period!r}") from None
    if not (math.isfinite(period) and period > 0):
        raise ValueError(f"sampler period must be > 0 and finite [s], got {s.period!r}")
    d = s.delay
    if isinstance(d, (bool, np.bool_)) or not (isinstance(d, numbers.Integral) or
                                               (isinstance(d, (float, np.floating)) and float(d).is_integer())):
        raise ValueError(f"sampler delay must be a whole number of samples (an integer >= 0), got {d!r}")
    if int(d) < 0:
        raise ValueError(f"sampler delay must be >= 0 samples, got {d!r}")
    try:
        noise = float(s.noise)
    except (TypeError, ValueError):
        raise ValueError(f"sampler noise must be a standard deviation (a number >= 0), got {s.noise!r}") from None
    if not (math.isfinite(noise) and noise >= 0):
        raise ValueError(f"sampler noise must be >= 0 and finite (a standard deviation), got {s.noise!r}")
    seed = s.seed
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, numbers.Integral):
        raise ValueError(f"sampler seed must be an integer, got {seed!r}")
    return Sampler(period, int(d), noise, int(seed))


def sampler(period, delay=0, noise=0.0, seed=0) -> Sampler:
    """Checked `Sampler` (see `check_sampler`)."""
    return check_sampler(Sampler(period, delay, noise, seed))


class Sampled(NamedTuple):
    r"""A law run by a digital controller: the `Sampler` (zero-order hold at period \(T_s\), a delay of whole
    samples, measurement noise) between the law and the plant.

    \[ u(t) = \mathrm{law}(\tilde q_{k-d}, \tilde v_{k-d}, t_{k-d}) \quad (t \in [t_k, t_{k+1})) \]

    It is a piece like the others: ``js.solve(sampled(law, 0.05), y0)``, ``js.simulate(ics, controller=...)``,
    ``js.run_ensemble``, ``js.run_basin`` and ``js.compare`` integrate it with the sampled-data loop
    (`jaxsleigh.integrate.sampled.solve_sampled`: the law evaluated once per sample, the plant by the adaptive
    RK4 to the run's tolerances in between, each sample instant a step boundary). Called as a law it is the
    continuous idealisation (the wrapped law itself).
    Build it with `sampled` (checks the numbers, and runs the paper's `jaxsleigh.Gains` as `PaperLaw`).
    """

    law: Any
    sampler: Sampler

    name = "sampled"

    @property
    def time_varying(self) -> bool:
        return is_time_varying(self.law)

    def __call__(self, q, v, *t):
        return _inner_u(self.law, q, v, t[0] if t else 0.0)


def sampled(law, period, delay=0, noise=0.0, seed=0) -> Sampled:
    """Checked `Sampled`: ``law`` (any controller, the paper's gains included, possibly saturated) behind a
    `Sampler` of period ``period`` [s], ``delay`` whole samples, noise ``noise`` and ``seed``."""
    law = _as_law(measured_law(law))
    return Sampled(law, sampler(period, delay, noise, seed))


def is_sampled(law) -> bool:
    """True for a `Sampled` law, bare or inside `jaxsleigh.model.controller.PerTrajectory` (the studies then run the
    sampled-data loop, or say what they cannot do with one; nothing integrates it as if it were continuous)."""
    return isinstance(law.law if isinstance(law, PerTrajectory) else law, Sampled)
