r"""The step-size policy of the adaptive RK4: how the error of a step is measured and the next step chosen.

`StepSizeController` holds the policy's numbers (as diffrax's ``PIDController`` does); they travel
into the compiled step as traced values (`jaxsleigh.integrate.stepper.Controls`), so changing them never
recompiles.

**Error of a step.** RK4 with \(k_5 = f(t + h, y_{n+1})\) (the next step's \(k_1\), no extra
evaluation) has the embedded third-order companion
\(\hat y_{n+1} = y_n + h(k_1 + 2k_2 + 2k_3 + k_5)/6\), so \(e = y_{n+1} - \hat y_{n+1} = h (k_4 - k_5) / 6\).
Its size is measured component-wise against

\[ \mathrm{scale}_i = \mathrm{atol} + \mathrm{rtol} \max(|y_{n,i}|, |y_{n+1,i}|) + 16\,\epsilon_{\mathrm{mach}} |h| \max(|k_{4,i}|, |k_{5,i}|), \]

the last term a rounding floor: \(k_4 - k_5\) cannot be resolved better than a few ulps of
\(|k|\), so asking for more would reject forever in float32 where \(|w|\) is huge (starts near
\(\theta = 0\)). The step is accepted when \(\mathrm{err} = \max_i |e_i| / \mathrm{scale}_i \le 1\).

**Next step.** After an accepted step, the PI controller of Gustafsson
\(h_{\text{next}} = h \cdot \mathrm{clip}(\mathrm{safety}\ \mathrm{err}^{-\alpha}\ \mathrm{err}_{\text{prev}}^{\beta},\ \mathrm{factor\_min},\ \mathrm{factor\_max})\)
with \(\alpha = 0.15\), \(\beta = 0.05\) and \(\mathrm{err}_{\text{prev}}\) the ratio of the last accepted
step (it damps the step sequence that the stiff settled phase makes oscillate between accepted and
rejected); after a rejected step, \(h \cdot \mathrm{clip}(\mathrm{safety}\ \mathrm{err}^{-1/4}, \ldots)\). Never above
``max_step``; the error estimate is \(O(h^4)\), hence the exponents. The choice is not differentiated
(``stop_gradient``): gradients flow through the accepted steps, not through the controller's decisions.

In the w chart the step itself is the exponential RK4 of `jaxsleigh.integrate.etd` on \(p_2\) (classical
RK4 on the rest), whose own error estimate replaces the one above on \(p_2\) (``e``).
"""
from __future__ import annotations

import math
from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp

from ..model.params import is_concrete
from ..validate import INT32_MAX, whole

__all__ = ["StepSizeController", "STATIC_FIELDS", "check_policy", "error_ratio", "next_step", "DEFAULT_RTOL", "DEFAULT_ATOL",
           "MAX_STEP_FACTOR"]

#: Tolerances of the adaptive method, per dtype (chosen from measured accuracy, see the docs).
DEFAULT_RTOL = {"float32": 1e-6, "float64": 1e-8}
DEFAULT_ATOL = {"float32": 1e-6, "float64": 1e-8}
#: Largest adaptive step, in base steps (1 s at dt = 0.01). Since T_eps is located on the step's
#: dense output (jaxsleigh.integrate.observers.ConvergenceTime), the cap no longer sets T_eps's resolution and
#: the error control decides the step: on the benchmark workload (experiments/studies/adaptive_steps.py)
#: 1,076 steps per 100 s on average against 1,363 with the 0.1 release's cap of 10 dt, T_eps within
#: 2.1e-4 s of a float64 reference.
MAX_STEP_FACTOR = 100


class StepSizeController(NamedTuple):
    """The adaptive method's policy (defaults: the library's measured choices).

    Attributes:
      rtol, atol: tolerances (``None``: per dtype, `DEFAULT_RTOL` / `DEFAULT_ATOL`).
      safety: factor on the optimal step (0.9).
      factor_min, factor_max: limits of the change of step per attempt (0.1, 5).
      max_step: largest step (``None``: `MAX_STEP_FACTOR` base steps).
      max_steps: budget of attempted steps per trajectory (``None``: 20x the base steps in float32, 30x in float64, + room).
      method: ``"adaptive"`` (this policy) or ``"rk4"`` (fixed steps of the base step ``dt``; the policy's
        numbers are then unused).
      check_passivity: reject (adaptive) or flag (``"rk4"``) steps that increase the paper's H_d.

    As a pytree, ``max_steps``, ``method`` and ``check_passivity`` are static (`STATIC_FIELDS`) and the other
    numbers are leaves, so a policy may sit in a config that ``jit``, ``grad`` or ``vmap`` traces.
    """

    rtol: Optional[float] = None
    atol: Optional[float] = None
    safety: float = 0.9
    factor_min: float = 0.1
    factor_max: float = 5.0
    max_step: Optional[float] = None
    max_steps: Optional[int] = None
    method: str = "adaptive"
    check_passivity: bool = True

    def resolved(self, dtype, dt) -> "StepSizeController":
        """This policy with its defaults filled in for ``dtype`` and the base step ``dt``: ``rtol`` and ``atol`` per
        dtype (`DEFAULT_RTOL`, `DEFAULT_ATOL`), ``max_step`` `MAX_STEP_FACTOR` base steps (``max_steps``, which
        depends on the horizon, is left as given). The one place these defaults are applied."""
        name = jnp.dtype(dtype).name
        return self._replace(rtol=DEFAULT_RTOL.get(name, 1e-6) if self.rtol is None else self.rtol,
                             atol=DEFAULT_ATOL.get(name, 1e-6) if self.atol is None else self.atol,
                             max_step=MAX_STEP_FACTOR * dt if self.max_step is None else self.max_step)


#: The fields of `StepSizeController` that stay static under ``jit``, ``grad`` and ``vmap`` (the pytree's auxiliary
#: data): the method and the passivity switch choose the compiled program, and the budget ``max_steps`` is the length
#: of a scan. Its other numbers (tolerances, ``safety``, the factor limits, ``max_step``) are leaves: a policy inside a
#: traced config (the tuner's `jaxsleigh.tuning.LossConfig`) has them traced, and changing them does not recompile.
STATIC_FIELDS = ("max_steps", "method", "check_passivity")
_LEAF_FIELDS = tuple(f for f in StepSizeController._fields if f not in STATIC_FIELDS)


def _flatten(ss: StepSizeController):
    return tuple(getattr(ss, f) for f in _LEAF_FIELDS), tuple(getattr(ss, f) for f in STATIC_FIELDS)


def _unflatten(static, leaves) -> StepSizeController:
    return StepSizeController(**dict(zip(_LEAF_FIELDS, leaves)), **dict(zip(STATIC_FIELDS, static)))


jax.tree_util.register_pytree_node(StepSizeController, _flatten, _unflatten)


#: the policy's numbers and what each must be: ``(field, lowest, lowest allowed, highest, highest allowed, words)``
_RANGES = (("rtol", 0.0, False, None, False, "> 0"), ("atol", 0.0, False, None, False, "> 0"),
           ("max_step", 0.0, False, None, False, "> 0"), ("safety", 0.0, False, 1.0, True, "in (0, 1]"),
           ("factor_min", 0.0, False, 1.0, False, "in (0, 1)"), ("factor_max", 1.0, False, None, False, "> 1"))


def check_policy(stepsize, name: str = "stepsize") -> StepSizeController:
    """``stepsize`` (``None``: the default policy) checked; the one check of a step policy, run by every front
    (`jaxsleigh.solve`, the sampled-data loop, the studies' option objects): a `StepSizeController`, ``method``
    ``"adaptive"`` or ``"rk4"``, ``rtol``, ``atol``, ``max_step`` (where given) > 0, ``safety`` in (0, 1],
    ``factor_min`` in (0, 1), ``factor_max`` > 1, each finite, and ``max_steps`` (where given) a whole number
    >= 1, static. A traced number passes: it is checked where it is concrete. Otherwise a ``ValueError`` naming
    the field as ``{name}.{field}``."""
    ss = StepSizeController() if stepsize is None else stepsize
    if not isinstance(ss, StepSizeController):
        raise ValueError(f"{name} must be a jaxsleigh.StepSizeController, got {type(ss).__name__}")
    if ss.method not in ("adaptive", "rk4"):
        raise ValueError(f"{name}.method must be 'adaptive' or 'rk4', got {ss.method!r}")
    for field, lo, lo_in, hi, hi_in, need in _RANGES:
        value = getattr(ss, field)
        if value is None or not is_concrete(value):
            continue
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise ValueError(f"{name}.{field} must be a number {need}, got {value!r}") from None
        if not (math.isfinite(v) and (v >= lo if lo_in else v > lo) and (hi is None or (v <= hi if hi_in else v < hi))):
            raise ValueError(f"{name}.{field} must be {need} and finite, got {value!r}")
    if ss.max_steps is not None:
        ss = ss._replace(max_steps=whole(f"{name}.max_steps", ss.max_steps, maximum=INT32_MAX - 1, example=20000))
    return ss


def error_ratio(h, y, y_new, k4, k5, ctl, e=None):
    """\\(\\max_i |e_i| / \\mathrm{scale}_i\\) per trajectory (axis 0 is the state), with the error estimate
    \\(e = h (k_4 - k_5) / 6\\) unless the step gives its own ``e`` (the exponential step's,
    `jaxsleigh.integrate.etd`)."""
    dtype = y.dtype
    noise = 16.0 * jnp.finfo(dtype).eps * jnp.abs(h) * jnp.maximum(jnp.abs(k4), jnp.abs(k5))
    scale = ctl.atol + ctl.rtol * jnp.maximum(jnp.abs(y), jnp.abs(y_new)) + noise
    if e is None:
        e = (h / 6.0) * (k4 - k5)
    return jnp.max(jnp.abs(e) / scale, axis=0)


#: exponents of the PI controller (Gustafsson's form, err ~ h^4). On 512 benchmark starts (100 s, float32,
#: python experiments/performance/engine_defaults.py): Hairer & Wanner's 0.7 / 4, 0.4 / 4 took 1,008 mean steps, T_eps
#: within 6.8e-4 s of float64; these 927 steps, 9.1e-4 s; the I controller (0.25, 0) 804 steps but 1.7e-3 s
PI_ALPHA, PI_BETA = 0.15, 0.05


def next_step(h, err, ctl, err_prev=None, order: int = 4):
    """The next step after one of size ``h`` with error ratio ``err`` (not differentiated). With
    ``err_prev`` (the ratio of the last accepted step) an accepted step is followed by the PI choice
    \\(h\\,\\mathrm{safety}\\,\\mathrm{err}^{-\\alpha}\\,\\mathrm{err}_{\\text{prev}}^{\\beta}\\) (`PI_ALPHA`, `PI_BETA`); a rejected one, and every
    step without ``err_prev``, by \\(h\\,\\mathrm{safety}\\,\\mathrm{err}^{-1/4}\\). ``order=2`` (the Rosenbrock
    step of `jaxsleigh.integrate.rosenbrock`, whose error is \\(O(h^3)\\)): always
    \\(h\\,\\mathrm{safety}\\,\\mathrm{err}^{-1/3}\\)."""
    if order == 2:
        return h * jax.lax.stop_gradient(jnp.clip(ctl.safety * err ** (-1.0 / 3.0), ctl.factor_min, ctl.factor_max))
    fac = ctl.safety * jax.lax.rsqrt(jnp.sqrt(err))
    if err_prev is not None:
        pi = ctl.safety * err ** (-PI_ALPHA) * err_prev ** PI_BETA
        fac = jnp.where(err <= 1.0, pi, fac)
    return h * jax.lax.stop_gradient(jnp.clip(fac, ctl.factor_min, ctl.factor_max))
