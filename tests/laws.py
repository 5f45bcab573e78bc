"""Feedback laws the tests share (user-written controllers, `jaxsleigh.model.controller`)."""
from typing import NamedTuple

import jax.numpy as jnp


class PD(NamedTuple):
    """Proportional-derivative law on the distance along the heading and on the heading (concepts page)."""

    kp: float = 1.0
    kd: float = 2.0

    def __call__(self, q, v):
        along = q[0] * jnp.cos(q[2]) + q[1] * jnp.sin(q[2])
        return jnp.stack([-self.kp * along - self.kd * v[0], -self.kp * q[2] - self.kd * v[1]])
