"""The plant (paper eq. 1-2) and the control law (eq. 13, Remark 1 / eq. 14)."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsleigh as js
from jaxsleigh.model import coordinates as C
from jaxsleigh.model import plant as P
from jaxsleigh.model.closed_loop import vector_field
from jaxsleigh.model.paper_law import control, control_w, measured_velocity, potential

pytestmark = pytest.mark.usefixtures("x64")

N = 64
PLANTS = [(2.0, 1.0, 1.0), (0.5, 0.0, 2.0), (3.0, 0.7, 0.0), (7.5, 2.0, 0.3)]


@pytest.mark.parametrize("m,J,l", PLANTS)
def test_mass_matrix(m, J, l):
    par = js.plant_params(m, J, l)
    np.testing.assert_allclose(P.mass_matrix(par), np.diag([m, J + m * l * l]), rtol=1e-14)
    np.testing.assert_allclose(P.inverse_mass(par), [1 / m, 1 / (J + m * l * l)], rtol=1e-14)
    np.testing.assert_allclose(P.mass_matrix(par) @ jnp.diag(P.inverse_mass(par)), np.eye(2), rtol=1e-14)


@pytest.mark.parametrize("m,J,l", PLANTS)
def test_gyroscopic_is_skew_with_paper_entries(m, J, l, rng):
    par = js.plant_params(m, J, l)
    for p in rng.normal(size=(8, 2)) * 3:
        Jp = np.asarray(P.gyroscopic(jnp.asarray(p), par))
        np.testing.assert_allclose(Jp + Jp.T, 0.0, atol=1e-15)
        np.testing.assert_allclose(Jp[0, 1], m * l / (J + m * l * l) * p[1], rtol=1e-14)
        # J(p) does no work: v^T J(p) v = 0
        v = np.asarray(P.velocity(jnp.asarray(p), par))
        assert abs(v @ Jp @ v) <= 1e-13 * (1 + v @ v)


@pytest.mark.parametrize("m,J,l", PLANTS)
def test_hamiltonian_and_its_gradient(m, J, l, rng):
    par = js.plant_params(m, J, l)
    Minv = np.diag([1 / m, 1 / (J + m * l * l)])
    for p in rng.normal(size=(8, 2)) * 3:
        pj = jnp.asarray(p)
        np.testing.assert_allclose(P.hamiltonian(pj, par), 0.5 * p @ Minv @ p, rtol=1e-14)
        # the plant's velocity is nabla_p H
        np.testing.assert_allclose(jax.grad(P.hamiltonian)(pj, par), P.velocity(pj, par), rtol=1e-14)


def test_damping_models_match_their_formulas(rng):
    q = jnp.zeros(3)
    for p in rng.normal(size=(8, 2)) * 2:
        pj = jnp.asarray(p)
        D = np.asarray(js.CoulombDamping(eps=0.1, scale=1.0).matrix(q, pj))
        np.testing.assert_allclose(D, np.diag(1 / np.sqrt(0.1 + p * p)), rtol=1e-13)
        D = np.asarray(js.ViscousDamping(0.3, 1.7).matrix(q, pj))
        np.testing.assert_allclose(D, np.diag([0.3, 1.7]), rtol=1e-15)
        np.testing.assert_array_equal(np.asarray(js.NoDamping().matrix(q, pj)), 0.0)


def test_open_loop_field_is_eq1(sample_states, rng):
    """qdot = Q(q) M^{-1} p, pdot = (J(p) - D) M^{-1} p + u, written out independently."""
    par = js.paper_plant()
    for y in sample_states(16):
        q, p = y[:3], y[3:]
        u = rng.normal(size=2)
        v = p / np.array([2.0, 1.0 + 2.0])
        a = 2.0 * 1.0 / 3.0 * p[1]
        D = np.diag(1 / np.sqrt(0.1 + p * p))
        qd_exp = np.array([np.cos(q[2]) * v[0], np.sin(q[2]) * v[0], v[1]])
        pd_exp = (np.array([[0, a], [-a, 0]]) - D) @ v + u
        qd, pd = P.open_loop(jnp.asarray(q), jnp.asarray(p), jnp.asarray(u), par)
        np.testing.assert_allclose(qd, qd_exp, rtol=1e-13, atol=1e-14)
        np.testing.assert_allclose(pd, pd_exp, rtol=1e-13, atol=1e-14)


def test_measured_velocity_recovers_v(sample_q, rng):
    """Remark 1: nabla_p H is recovered from (q, qdot) alone."""
    qs = jnp.asarray(sample_q(N))
    vs = jnp.asarray(rng.normal(size=(N, 2)) * 2)
    got = jax.vmap(lambda q, v: measured_velocity(q, C.Q(q) @ v))(qs, vs)
    np.testing.assert_allclose(got, vs, rtol=1e-13, atol=1e-14)


def test_measured_velocity_equals_remark1_z_form(sample_q, rng):
    """eq. 14: nabla_p H = [[z3, 1], [1, 0]] (zdot1, zdot2) with zdot = (df_z/dq) qdot."""
    qs = jnp.asarray(sample_q(N))
    vs = jnp.asarray(rng.normal(size=(N, 2)) * 2)

    def remark1(q, v):
        qdot = C.Q(q) @ v
        z = C.f_z(q)
        zdot = jax.jacfwd(C.f_z)(q) @ qdot
        return jnp.array([[z[2], 1.0], [1.0, 0.0]]) @ zdot[:2], measured_velocity(q, qdot)

    paper, lib = jax.vmap(remark1)(qs, vs)
    np.testing.assert_allclose(lib, paper, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(paper, vs, rtol=1e-12, atol=1e-12)


def test_control_w_is_eq13(sample_w, rng, sample_gains):
    g = sample_gains()
    L, k, Dh = np.asarray(g.L), float(g.k), np.asarray(g.D_hat)
    for w, v in zip(sample_w(16), rng.normal(size=(16, 2))):
        w1, w2, w3 = w
        Qw = np.array([[0, 1], [1 / w1, -(3 * w2 + w3) / w1 - 0.5 * w1 * w3], [0, 2 * w2 / w1]])
        expected = -Qw.T @ (L * w) - Dh @ v - np.diag([0.0, k / w1 ** 2]) @ v
        np.testing.assert_allclose(control_w(jnp.asarray(w), jnp.asarray(v), g), expected, rtol=1e-12, atol=1e-12)


def test_control_in_q_matches_control_w(sample_q, rng):
    g = js.paper_gains()
    for q, v in zip(sample_q(16), rng.normal(size=(16, 2))):
        qj = jnp.asarray(q)
        qdot = C.Q(qj) @ jnp.asarray(v)
        np.testing.assert_allclose(control(qj, qdot, g), control_w(C.q_to_w(qj), jnp.asarray(v), g),
                                   rtol=1e-12, atol=1e-12)


def _closed_loop_input(y, plant, g):
    """u that the closed loop actually applies: closed-loop pdot minus the open-loop pdot (u = 0)."""
    args = js.ClosedLoop(plant, g)
    return vector_field(0.0, y, args)[3:] - P.open_loop_field(0.0, y, plant)[3:]


def test_control_independent_of_mass_matrix(sample_q, rng):
    """Remark 1: with the same measured (q, qdot) two different plants receive the same u."""
    g = js.paper_gains()
    plant_a = js.plant_params(2.0, 1.0, 1.0, "coulomb")
    plant_b = js.plant_params(5.5, 0.25, 0.2, "viscous")
    Ma = np.diag(np.asarray(P.mass_matrix(plant_a)))
    Mb = np.diag(np.asarray(P.mass_matrix(plant_b)))
    assert not np.allclose(Ma, Mb)
    for q, v in zip(sample_q(16), rng.normal(size=(16, 2)) * 1.5):
        pa, pb = Ma * v, Mb * v              # different momenta ...
        assert np.max(np.abs(pa - pb)) > 1e-3 * np.max(np.abs(v))
        ya = jnp.asarray(np.concatenate([q, pa]))
        yb = jnp.asarray(np.concatenate([q, pb]))
        qdot_a = vector_field(0.0, ya, js.ClosedLoop(plant_a, g))[:3]
        qdot_b = vector_field(0.0, yb, js.ClosedLoop(plant_b, g))[:3]
        np.testing.assert_allclose(qdot_a, qdot_b, rtol=1e-13, atol=1e-14)   # ... same measurement
        ua, ub = control(ya[:3], qdot_a, g), control(yb[:3], qdot_b, g)
        np.testing.assert_allclose(ua, ub, rtol=1e-12, atol=1e-12)
        # and that is what each closed loop feeds its plant
        np.testing.assert_allclose(_closed_loop_input(ya, plant_a, g), ua, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(_closed_loop_input(yb, plant_b, g), ub, rtol=1e-10, atol=1e-10)


def test_control_depends_on_measured_velocity(sample_q, rng):
    """Guard for the test above: u does respond to qdot (D_hat and D_i terms)."""
    g = js.paper_gains()
    q = jnp.asarray(sample_q(1)[0])
    u0 = control(q, C.Q(q) @ jnp.zeros(2), g)
    u1 = control(q, C.Q(q) @ jnp.array([1.0, -0.5]), g)
    assert np.max(np.abs(np.asarray(u1 - u0))) > 0.5


def test_potential_force_is_gradient_of_shaped_potential(sample_q, sample_gains):
    """-Q_w^T L w = -Q(q)^T grad_q V(q) with V(q) = 1/2 w(q)^T L w(q): an independent check of the
    corrected Q_w (through the chain rule, not through the formula of eq. 11)."""
    g = sample_gains()
    V = lambda q: potential(C.q_to_w(q), g)

    def both(q):
        w = C.q_to_w(q)
        lhs = -C.Q_w(w).T @ (jnp.asarray(g.L) * w)
        rhs = -C.Q(q).T @ jax.grad(V)(q)
        printed = -C.Q_w_printed(w).T @ (jnp.asarray(g.L) * w)
        return lhs, rhs, printed

    lhs, rhs, printed = jax.vmap(both)(jnp.asarray(sample_q(N)))
    scale = 1.0 + np.abs(np.asarray(rhs))
    np.testing.assert_allclose(np.asarray(lhs) / scale, np.asarray(rhs) / scale, atol=1e-11)
    # the printed Q_w does not give a gradient force
    assert np.max(np.abs(np.asarray(printed - rhs)) / scale) > 1e-2


def test_potential_is_half_wLw(sample_w, sample_gains):
    g = sample_gains()
    for w in sample_w(8):
        np.testing.assert_allclose(potential(jnp.asarray(w), g), 0.5 * np.sum(np.asarray(g.L) * w * w), rtol=1e-14)
