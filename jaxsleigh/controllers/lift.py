r"""Kinematic laws lifted to force level: a velocity loop with the plant's model (computed torque).

Most stabilisers of unicycle-like vehicles in the literature are *kinematic*: they prescribe the
velocity \(v_\mathrm{ref}(q, t) = (\text{forward speed}, \text{turning rate})\). The sleigh is driven by
forces, and its velocity obeys (paper eq. 1-2, with \(p = M v\), \(M = \mathrm{diag}(m, I)\),
\(I = J + m l^2\))

\[ m \dot v_1 = m l\, v_2^2 - d_1 + u_1, \qquad I \dot v_2 = -m l\, v_1 v_2 - d_2 + u_2, \]

\(d = D(q, p) v\) the damping force. The velocity loop with the model \(\hat m, \hat J, \hat l, \hat D\)
(cancel what the model predicts, then make the velocity error \(e = v - v_\mathrm{ref}\) decay at
rate \(K\)):

\[ u = \hat M (\dot v_\mathrm{ref} - K e) - \hat J(\hat p) v + \hat D(q, \hat p) v, \qquad \hat p = \hat M v,
   \qquad \dot v_\mathrm{ref} = \frac{\partial v_\mathrm{ref}}{\partial q} Q(q) v + \frac{\partial v_\mathrm{ref}}{\partial t} \]

With the exact model, \(\dot e = -K e\): the velocity converges exponentially to the kinematic law's,
and the kinematic law's claim carries over (the cascade of an exponentially stable velocity loop and a
kinematic loop that is asymptotically stable, with \(\dot v_\mathrm{ref}\) computed exactly by ``jax.jvp``
from measured \(q\) and \(v\)). The price is the **model**: \(m, J, l\) and the damping law. With a
wrong model the cancellation leaves a disturbance. ``model=None`` drops the feed-forward and the
cancellation and keeps a plain velocity loop \(u = -K \operatorname{diag}(1, 1) e\) [N per m/s, N m per rad/s],
which needs no model and tracks only approximately.
"""
from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp

from ..model.coordinates import Q_entries
from ..model.plant import gyroscopic_entries
from ..model.smallmat import matvec

__all__ = ["velocity_loop"]


def velocity_loop(v_ref: Callable, q, v, t, K, model: Any):
    r"""Force ``u`` (2,) that makes the measured velocity ``v`` track ``v_ref(q, t)`` (2,) at rate ``K``.

    ``K``: a scalar or (2,) [1/s]. ``model``: a `jaxsleigh.PlantParams` estimate (the law knows ``m, J, l`` and
    the damping model) or ``None`` (no model: ``u = -K (v - v_ref)``, ``K`` then in N s/m).
    """
    q, v = jnp.asarray(q), jnp.asarray(v)
    qdot = jnp.stack(matvec(Q_entries(q), (v[0], v[1])))
    ref, dref = jax.jvp(lambda qq, tt: jnp.asarray(v_ref(qq, tt)), (q, jnp.asarray(t, q.dtype)),
                        (qdot, jnp.ones((), q.dtype)))
    e = v - ref
    if model is None:
        return -K * e
    m, J, l = model.m, model.J, model.l
    M = jnp.stack([jnp.asarray(m, q.dtype), jnp.asarray(J + m * l * l, q.dtype)])
    p_hat = M * v
    gyro = matvec(gyroscopic_entries(p_hat, model), (v[0], v[1]))
    damp = model.damping.force(q, (p_hat[0], p_hat[1]), (v[0], v[1]))
    return M * (dref - K * e) - jnp.stack(gyro) + jnp.stack(damp)
