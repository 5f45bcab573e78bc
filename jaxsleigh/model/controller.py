r"""The controller as a piece: any feedback law ``u = law(q, v)`` on the sleigh.

A *controller* is a pytree ``law`` (a ``NamedTuple`` of numbers and arrays, a registered dataclass, or a
plain function) whose call

\[ u = \mathrm{law}(q, v), \qquad q = (x, y, \theta), \quad v = \nabla_p H = (\text{forward speed},\ \text{turning rate}) \]

returns the generalised force ``u`` (shape (2,): forward force in N, turning moment in N m). It sees
what a controller on the real sleigh measures (configuration and velocity; \(v = Q(q)^\top \dot q\),
paper Remark 1), never the momentum or the plant's parameters. Its numeric leaves are traced: new
values never recompile, and ``jax.grad`` differentiates through them.

The paper's law (eq. 13) is the controller `jaxsleigh.Gains`: ``gains=`` keeps meaning it, ``gains(q, v)`` is
its ``u``, and it declares the w chart (``w_chart = True``: its singular set \(\theta = 0\) belongs to it, not to
the plant), so the engine integrates it there (`jaxsleigh.model.charts.WChart`, `jaxsleigh.model.w_laws`). A law
whose leaves carry a per-trajectory axis of their own declares ``lane_axes`` (`jaxsleigh.model.lanes`), and one that
bounds its injected damping below, ``damping_floor()`` (`jaxsleigh.integrate.stragglers`). Any other law is integrated in the
physical chart (`jaxsleigh.model.charts.PhysicalChart`). A law may declare its own chart with a class
attribute ``chart``, and the parameters that must stay positive with a class attribute ``positive`` (names of
its fields; the tuner then optimises their logarithm).

A *time-varying* law (the classic answer to Brockett's condition) says so with a class attribute
``time_varying = True`` and is called as ``law(q, v, t)``, ``t`` the time since the start of the run.

Example: a PD law on the distance and heading to the origin (not a stabiliser of the sleigh, which
no smooth static law is, by Brockett's condition; it shows the contract):

```python
class PD(NamedTuple):
    kp: float = 1.0
    kd: float = 2.0

    def __call__(self, q, v):
        return jnp.stack([-self.kp * (q[0] * jnp.cos(q[2]) + q[1] * jnp.sin(q[2])) - self.kd * v[0],
                          -self.kp * q[2] - self.kd * v[1]])

sol = js.simulate(ics, controller=PD(kp=2.0))
```
"""
from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..cores import configure
from .params import Gains, lane_record

__all__ = ["FunctionLaw", "PerTrajectory", "as_controller", "apply_law", "is_paper_law", "is_time_varying",
           "controller_record"]


@jax.tree_util.register_pytree_node_class
class FunctionLaw:
    """A plain function ``fn(q, v) -> u`` as a controller without parameters (the function is static)."""

    def __init__(self, fn):
        self.fn = fn

    def __call__(self, q, v, *t):
        return self.fn(q, v, *t)

    def tree_flatten(self):
        return (), self.fn

    @classmethod
    def tree_unflatten(cls, fn, children):
        return cls(fn)

    def __repr__(self):
        return f"FunctionLaw({getattr(self.fn, '__qualname__', repr(self.fn))})"


@jax.tree_util.register_pytree_node_class
class PerTrajectory:
    """A law whose every numeric leaf carries a trailing per-trajectory axis (size N, or 1 for all).

    ``PerTrajectory(PD(kp=np.array([1.0, 2.0, 4.0]), kd=np.full(3, 2.0)))`` runs three trajectories with
    three gains, as one compiled batch (the law, written for one trajectory, is vmapped over the lanes);
    sweeps build these. A law's call on one trajectory's slice is the wrapped law's call.
    """

    def __init__(self, law):
        self.law = law

    def __call__(self, q, v, *t):
        return self.law(q, v, *t)

    def tree_flatten(self):
        return (self.law,), None

    @classmethod
    def tree_unflatten(cls, aux, children):
        return cls(children[0])

    def __repr__(self):
        return f"PerTrajectory({self.law!r})"


def is_paper_law(controller) -> bool:
    """True for the paper's law (`jaxsleigh.Gains`), integrated in the w chart."""
    return isinstance(controller, Gains)


def is_time_varying(law) -> bool:
    """True for a law that says ``time_varying = True``: it is called as ``law(q, v, t)``."""
    inner = law.law if isinstance(law, PerTrajectory) else law
    return bool(getattr(inner, "time_varying", False))


def apply_law(law, q, v, t=0.0):
    """``law(q, v)`` (``law(q, v, t)`` for a time-varying law) as a tuple ``(u1, u2)``, for one trajectory
    (``q`` (3,), ``v`` (2,)) or a batch-last batch (``q`` (3, N), ``v`` (2, N), ``t`` a scalar or (N,): the
    law, written for one trajectory, is vmapped over the batch)."""
    q, v = jnp.asarray(q), jnp.asarray(v)
    tv = is_time_varying(law)

    def call(c, qi, vi, ti):
        return jnp.asarray(c(qi, vi, ti) if tv else c(qi, vi))

    if q.ndim == 1:
        u = call(law, q, v, jnp.asarray(t, q.dtype))
    else:
        tb = jnp.broadcast_to(jnp.asarray(t, q.dtype), q.shape[1:])
        if isinstance(law, PerTrajectory):      # one law per lane: vmap the law's leaves with the batch
            u = jax.vmap(call, in_axes=(-1, 1, 1, 0), out_axes=1)(law.law, q, v, tb)
        else:
            u = jax.vmap(lambda qi, vi, ti: call(law, qi, vi, ti), in_axes=(1, 1, 0), out_axes=1)(q, v, tb)
    if not _real_dtype(u.dtype):            # a static property of the law: refused where it is traced, not data
        raise ValueError(_not_real("controller", u.dtype, ""))
    return u[0].astype(q.dtype), u[1].astype(q.dtype)


def _real_dtype(dtype) -> bool:
    """Whether a law's output dtype is real (floating, integer): not complex, bool or object."""
    d = np.dtype(dtype)
    return d != np.bool_ and (np.issubdtype(d, np.floating) or np.issubdtype(d, np.integer))


def _not_real(name: str, dtype, where: str) -> str:
    return (f"the {name} must return a real u (forward force, turning moment), got dtype {np.dtype(dtype).name}"
            f"{where}; a complex u's imaginary part would be dropped: return the real part (jnp.real(u)) if that "
            f"is what is meant")


def _is_number_leaf(x) -> bool:
    if isinstance(x, (bool, np.bool_, str)):
        return False
    try:
        a = np.asarray(x)
    except Exception:                  # noqa: BLE001  (anything that is not an array)
        return isinstance(x, jax.Array)
    return a.dtype != object and (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer))


@jax.jit
def _at_test_point(law, q, v):
    """``u = law(q, v)`` (or ``law(q, v, 0)``) under ``jax.jit``, compiled once per kind of law and reused: the check
    of `as_controller` runs on every call of a front, the accuracy audit's float64 references included, and a jit of
    a fresh function compiled it again each time (0.1-0.2 s a call for the laws of Astolfi and Aicardi, more than the
    audit's reference rows themselves)."""
    return jnp.asarray(law(q, v, 0.0) if is_time_varying(law) else law(q, v))


def as_controller(law: Any, name: str = "controller"):
    """Check a user's law eagerly; returns it (a plain function wrapped in `FunctionLaw`).

    The law must be callable as ``law(q, v)``, its leaves real numbers or arrays, and at a test point
    (``q = (1, 0.5, 0.3)``, ``v = (0.1, -0.2)``, float64) it must return two finite real numbers (a complex ``u``
    is refused: its imaginary part would be dropped without a word). Raises ``ValueError`` saying what is wrong.
    """
    if isinstance(law, Gains):
        return law
    if isinstance(law, PerTrajectory):
        leaves = jax.tree_util.tree_leaves(law.law)
        if any(np.ndim(x) < 1 for x in leaves):
            raise ValueError(f"every leaf of a PerTrajectory {name} needs a trailing per-trajectory axis, got shapes "
                             f"{[np.shape(x) for x in leaves]}")
        bad = [x for x in leaves if not np.all(np.isfinite(np.asarray(x, np.float64)))]
        if bad:
            raise ValueError(f"the per-trajectory parameters of the {name} must be finite, got {bad[0]!r}")
        as_controller(jax.tree_util.tree_map(lambda x: np.asarray(x)[..., 0], law.law), name)
        return law
    if not callable(law):
        raise ValueError(f"{name} must be a feedback law u = law(q, v) (a callable pytree, e.g. a NamedTuple "
                         f"with __call__, or a function), or jaxsleigh.gains(...) for the paper's law; got "
                         f"{type(law).__name__}")
    leaves = jax.tree_util.tree_leaves(law)
    if leaves and not hasattr(law, "tree_flatten") and not all(_is_number_leaf(x) for x in leaves):
        if not isinstance(law, tuple):           # a plain function (or object) is its own, static, leaf
            law = FunctionLaw(law)
        else:
            bad = next(x for x in leaves if not _is_number_leaf(x))
            raise ValueError(f"every parameter of the {name} must be a real number or array (they are traced), "
                             f"got {bad!r}")
    configure()              # the law's first evaluation starts JAX: one CPU device per core first (jaxsleigh.cores)
    q = jnp.array([1.0, 0.5, 0.3])
    v = jnp.array([0.1, -0.2])
    try:
        with jax.enable_x64(True):
            u = np.asarray(_at_test_point(law, q.astype(jnp.float64), v.astype(jnp.float64)))
    except Exception as e:              # noqa: BLE001  (a user's code: report what it raised)
        raise ValueError(f"the {name} {law!r} failed when called as law(q, v{', t' if is_time_varying(law) else ''}) with q = (1, 0.5, 0.3), "
                         f"v = (0.1, -0.2) under jax.jit: {type(e).__name__}: {e}") from None
    if u.shape != (2,):
        raise ValueError(f"the {name} must return u of shape (2,) (forward force, turning moment), got shape "
                         f"{u.shape}")
    if not _real_dtype(u.dtype):
        raise ValueError(_not_real(name, u.dtype, f" = {u.tolist()} at q = (1, 0.5, 0.3), v = (0.1, -0.2)"))
    if not np.all(np.isfinite(u)):
        raise ValueError(f"the {name} returned a non-finite u = {u.tolist()} at q = (1, 0.5, 0.3), "
                         f"v = (0.1, -0.2)")
    return law


def controller_record(law) -> dict:
    """JSON-ready record of a law that is not the paper's: its type and its numeric leaves."""
    inner = law.law if isinstance(law, PerTrajectory) else law
    leaves, _ = jax.tree_util.tree_flatten_with_path(inner)
    rec = lane_record if isinstance(law, PerTrajectory) else (lambda x: np.asarray(x, np.float64).tolist())
    params = {jax.tree_util.keystr(path) or "value": rec(x) for path, x in leaves}
    kind = repr(inner) if isinstance(inner, FunctionLaw) else type(inner).__qualname__
    return {"type": kind, "params": params}


def positive_names(law) -> set:
    """Names (spelled as `law_leaf_names` spells them) of the leaves a law declares positive with a class attribute
    ``positive``, also through wrappers that hold their law in a field ``law`` (``law.k``). The tuner keeps them
    positive (it optimises their logarithm)."""
    inner = law.law if isinstance(law, PerTrajectory) else law
    out = set(getattr(type(inner), "positive", ()))
    sub = getattr(inner, "law", None)
    if sub is not None and sub is not inner and callable(sub):
        out |= {"law." + n for n in positive_names(sub)}
    return out


def law_leaf_names(law) -> dict:
    """``{name: leaf}`` of a law's numeric leaves, named by their path without the leading dot (``kp``,
    ``gains[0]``): the names sweeps and lane tables use."""
    inner = law.law if isinstance(law, PerTrajectory) else law
    leaves, _ = jax.tree_util.tree_flatten_with_path(inner)
    return {jax.tree_util.keystr(p).lstrip(".") or "value": x for p, x in leaves}
