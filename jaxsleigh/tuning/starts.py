"""Where the tuner's starts and plants come from: samplers of initial conditions, the guard starts near
the singular set, and plant distributions for robust tuning.

Box sampling is the library's one `sample_starts` (re-exported here);
`UniformStarts` draws the sign-symmetric band ``|theta0|`` in ``(theta_min, theta_max)`` that
the tuner trains on, and `draw_starts` turns any of these (or a fixed array) into validated rows.
"""
from __future__ import annotations

import math
from typing import NamedTuple, Sequence

import jax
import numpy as np

from ..studies.basin import BasinStarts, sample_starts
from ..model.damping import CoulombDamping, NoDamping, ViscousDamping
from ..integrate.engine import check_ics
from ..model.params import PlantParams, paper_plant, plant_params

__all__ = ["UniformStarts", "WideStarts", "draw_starts", "sample_starts", "guard_starts", "PlantDistribution", "sample_plants",
           "validation_plants", "plant_groups", "first_lane"]


class UniformStarts(NamedTuple):
    """Starts with ``x, y`` uniform in ``(-xy, xy)``, ``|theta0|`` uniform in ``(theta_min, theta_max)``
    with a random sign and zero momentum (the issue's "typical starts")."""

    xy: float = 3.0
    theta_min: float = 0.3
    theta_max: float = math.pi

    def __call__(self, rng: np.random.Generator, n: int) -> np.ndarray:
        xy = rng.uniform(-self.xy, self.xy, size=(n, 2))
        th = rng.choice([-1.0, 1.0], size=n) * rng.uniform(self.theta_min, self.theta_max, size=n)
        return np.column_stack([xy, th])


class WideStarts(NamedTuple):
    """Wider starts than `UniformStarts`: ``x, y`` uniform in ``(-xy, xy)``, ``|theta0|`` uniform in
    ``(theta_min, pi)`` except a fraction ``near`` drawn in ``(theta_min, theta_near)`` (close to the singular set),
    random sign, momentum ``p1, p2 ~ N(0, 1)`` for half the starts and zero for the rest."""

    xy: float = 4.0
    theta_min: float = 0.05
    theta_near: float = 0.3
    near: float = 0.125

    def __call__(self, rng: np.random.Generator, n: int) -> np.ndarray:
        xy = rng.uniform(-self.xy, self.xy, size=(n, 2))
        near = rng.random(n) < self.near
        mag = np.where(near, rng.uniform(self.theta_min, self.theta_near, size=n),
                       rng.uniform(self.theta_min, math.pi, size=n))
        th = rng.choice([-1.0, 1.0], size=n) * mag
        p = rng.normal(0.0, 1.0, size=(n, 2)) * (rng.random(n) < 0.5)[:, None]
        return np.column_stack([xy, th, p])


def draw_starts(starts, n: int, seed: int) -> np.ndarray:
    """``n`` validated starts ``(n, 3|5)`` from ``starts``: a sampler ``(rng, n) -> array`` (e.g.
    `UniformStarts`, drawn with ``numpy.random.default_rng(seed)``), a
    `BasinStarts` (e.g. from `sample_starts`, the library's box sampler,
    shared with `jaxsleigh.studies.basin`) or a fixed array; of the last two the first ``n`` rows are used."""
    if callable(starts):
        arr = np.asarray(starts(np.random.default_rng(seed), int(n)), dtype=np.float64)
    else:
        arr = np.asarray(starts.ics if isinstance(starts, BasinStarts) else starts, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[0] < n:
            raise ValueError(f"a fixed set of starts needs at least {n} rows of (x, y, theta[, p1, p2]), "
                             f"got shape {arr.shape}")
        arr = arr[:n]
    check_ics(arr)
    return arr


def guard_starts(theta0: Sequence[float] = (0.05, 0.1), xy: float = 3.0) -> np.ndarray:
    """Hard starts near the singular set: ``(+-xy, +-xy)`` corners, each with ``+-theta0`` of each
    size (signs alternate). They carry huge ``H_d(0)`` and are stiff; the tuner requires them to
    stay integrable (status OK, finite loss and gradient)."""
    rows = []
    for j, th in enumerate(theta0):
        for i, (sx, sy) in enumerate(((1, 1), (-1, 1), (1, -1), (-1, -1))):
            rows.append((sx * xy, sy * xy, (-1) ** (i + j) * th))
    return np.asarray(rows, dtype=np.float64)


class PlantDistribution(NamedTuple):
    """Plants for robust tuning: ``m, J, l`` log-uniform in the ranges; lanes are spread evenly over
    the damping models in ``dampings``, each with a scale log-uniform in ``damping_scale``
    (Coulomb's ``scale``; viscous ``c1, c2``; ``'none'`` has no parameter)."""

    m: tuple = (1.0, 4.0)
    J: tuple = (0.5, 2.0)
    l: tuple = (0.5, 1.5)
    dampings: tuple = ("coulomb", "viscous", "none")
    damping_scale: tuple = (0.5, 2.0)


def _log_uniform(rng, lo_hi, n):
    lo, hi = lo_hi
    return np.exp(rng.uniform(np.log(lo), np.log(hi), size=n))


def sample_plants(dist: PlantDistribution, n: int, seed: int) -> list[tuple[np.ndarray, PlantParams]]:
    """``[(lane_indices, plant), ...]``: one group per damping model, whose ``PlantParams`` leaves are
    arrays over the group's lanes (the stepper broadcasts them along the batch axis)."""
    rng = np.random.default_rng(seed)
    kinds = tuple(dist.dampings)
    if not kinds:
        raise ValueError("PlantDistribution.dampings must name at least one damping model")
    out = []
    for j, kind in enumerate(kinds):
        idx = np.arange(j, n, len(kinds))
        if idx.size == 0:
            continue
        m, J, l = (_log_uniform(rng, r, idx.size) for r in (dist.m, dist.J, dist.l))
        s = _log_uniform(rng, dist.damping_scale, idx.size)
        if kind == "coulomb":
            damping = CoulombDamping(0.1, s)
        elif kind == "viscous":
            damping = ViscousDamping(s, _log_uniform(rng, dist.damping_scale, idx.size))
        elif kind == "none":
            damping = NoDamping()
        else:
            raise ValueError(f"unknown damping {kind!r}; use coulomb, viscous or none")
        out.append((idx, PlantParams(m, J, l, damping)))
    return out


def validation_plants() -> dict[str, PlantParams]:
    """Named plants for the per-plant validation table (paper's plant first)."""
    return {
        "paper (m 2, J 1, l 1, Coulomb)": plant_params(2.0, 1.0, 1.0, "coulomb"),
        "heavy (m 4, J 2, l 1, Coulomb)": plant_params(4.0, 2.0, 1.0, "coulomb"),
        "light (m 1, J 0.5, l 0.5, Coulomb)": plant_params(1.0, 0.5, 0.5, "coulomb"),
        "long (m 2, J 1, l 1.5, Coulomb x2)": plant_params(2.0, 1.0, 1.5, CoulombDamping(0.1, 2.0)),
        "paper inertia, viscous": plant_params(2.0, 1.0, 1.0, "viscous"),
        "paper inertia, no damping": plant_params(2.0, 1.0, 1.0, "none"),
    }



def first_lane(plant: PlantParams) -> PlantParams:
    """The plant of a group's first lane (leaves that are arrays over lanes -> their first entry)."""
    return jax.tree_util.tree_map(lambda x: x[0] if np.ndim(x) >= 1 else x, plant)


def plant_groups(n: int, plant, robust, seed) -> list:
    """``[(lane indices, group plant, plant of its first lane), ...]`` (one group for one plant)."""
    if robust is None:
        plant = paper_plant() if plant is None else plant
        return [(np.arange(n), plant, plant)]
    return [(idx, p, first_lane(p)) for idx, p in sample_plants(robust, n, seed)]
