"""Coordinate maps q -> z -> w (paper eq. 4-11) checked against automatic differentiation.

Every matrix the library writes out by hand (Q_z, Q_w, the eq. 27 matrix) is compared with
``jax.jacfwd`` of the maps it is defined from, in float64, at random points away from the
singular set theta = w1 = 0.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxsleigh.model import coordinates as C

N = 64
pytestmark = pytest.mark.usefixtures("x64")


def _vm(f):
    return jax.jit(jax.vmap(f))


def test_float64_is_active():
    assert jnp.asarray(1.0).dtype == jnp.float64


def test_Q_is_orthonormal_columns(sample_q):
    q = jnp.asarray(sample_q(N))
    Qs = _vm(C.Q)(q)
    assert Qs.shape == (N, 3, 2)
    np.testing.assert_allclose(jnp.einsum("nij,nik->njk", Qs, Qs), np.broadcast_to(np.eye(2), (N, 2, 2)),
                               atol=1e-14)


def test_Qz_is_pushforward_of_Q(sample_q):
    """eq. 6: Q_z(f_z(q)) = (df_z/dq)(q) Q(q)."""
    q = jnp.asarray(sample_q(N))
    expected = _vm(lambda q: jax.jacfwd(C.f_z)(q) @ C.Q(q))(q)
    got = _vm(lambda q: C.Q_z(C.f_z(q)))(q)
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12)


def test_Qw_is_pushforward_of_Qz(sample_w):
    """eq. 11 (definition): Q_w(w) = (df_w/dz)(z) Q_z(z) at z = f_w^{-1}(w)."""
    w = jnp.asarray(sample_w(N))

    def by_ad(w):
        z = C.f_w_inv(w)
        return jax.jacfwd(C.f_w)(z) @ C.Q_z(z)

    np.testing.assert_allclose(_vm(C.Q_w)(w), _vm(by_ad)(w), rtol=1e-11, atol=1e-11)


def test_Qw_explicit_value():
    """The derived formula at one hand-computed point, w = (0.5, 1, -2)."""
    w = jnp.array([0.5, 1.0, -2.0])
    # 1/w1 = 2; -(3 w2 + w3)/w1 - w1 w3 / 2 = -(1)/0.5 + 0.5 = -1.5; 2 w2 / w1 = 4
    expected = np.array([[0.0, 1.0], [2.0, -1.5], [0.0, 4.0]])
    np.testing.assert_allclose(C.Q_w(w), expected, rtol=1e-14, atol=1e-14)


def test_pushforward_q_to_w(sample_q):
    """d(q_to_w)/dq Q(q) = Q_w(q_to_w(q)): the w-chart kinematics are the plant's kinematics."""
    q = jnp.asarray(sample_q(N))
    lhs = _vm(lambda q: jax.jacfwd(C.q_to_w)(q) @ C.Q(q))(q)
    rhs = _vm(lambda q: C.Q_w(C.q_to_w(q)))(q)
    np.testing.assert_allclose(lhs, rhs, rtol=1e-10, atol=1e-10)


def test_fz_round_trip(sample_q, rng):
    q = jnp.asarray(sample_q(N))
    np.testing.assert_allclose(_vm(lambda q: C.f_z_inv(C.f_z(q)))(q), q, rtol=1e-13, atol=1e-13)
    z = jnp.asarray(rng.uniform(-3, 3, size=(N, 3)))
    np.testing.assert_allclose(_vm(lambda z: C.f_z(C.f_z_inv(z)))(z), z, rtol=1e-13, atol=1e-13)


def test_fz_is_rotation_of_position(sample_q):
    """f_z keeps theta and rotates (x, y): |(z2, z3)| = |(x, y)|."""
    q = np.asarray(sample_q(N))
    z = np.asarray(_vm(C.f_z)(jnp.asarray(q)))
    np.testing.assert_array_equal(z[:, 0], q[:, 2])
    np.testing.assert_allclose(np.hypot(z[:, 1], z[:, 2]), np.hypot(q[:, 0], q[:, 1]), rtol=1e-13)


def test_fw_round_trip(sample_w):
    w = jnp.asarray(sample_w(N))
    np.testing.assert_allclose(_vm(lambda w: C.f_w(C.f_w_inv(w)))(w), w, rtol=1e-12, atol=1e-12)
    z = _vm(C.f_w_inv)(w)   # points with z1 away from 0
    np.testing.assert_allclose(_vm(lambda z: C.f_w_inv(C.f_w(z)))(z), z, rtol=1e-12, atol=1e-12)


def test_fw_inv_formula_eq9(sample_w):
    w = np.asarray(sample_w(N))
    z = np.asarray(_vm(C.f_w_inv)(jnp.asarray(w)))
    w1, w2, w3 = w.T
    np.testing.assert_allclose(z, np.column_stack([w1, w1 * w2 + w1 * w3, 0.5 * w1 ** 2 * w3]), rtol=1e-14)


def test_q_to_w_round_trip(sample_q, sample_w):
    q = jnp.asarray(sample_q(N))
    np.testing.assert_allclose(_vm(lambda q: C.w_to_q(C.q_to_w(q)))(q), q, rtol=1e-12, atol=1e-12)
    w = jnp.asarray(sample_w(N))
    np.testing.assert_allclose(_vm(lambda w: C.q_to_w(C.w_to_q(w)))(w), w, rtol=1e-11, atol=1e-11)


def test_singular_set_maps_to_origin(rng):
    """eq. 9: every w with w1 = 0 corresponds to z = 0, hence q = 0."""
    w = jnp.asarray(np.column_stack([np.zeros(N), rng.uniform(-5, 5, size=(N, 2))]))
    np.testing.assert_array_equal(_vm(C.f_w_inv)(w), 0.0)
    np.testing.assert_allclose(_vm(C.w_to_q)(w), 0.0, atol=0.0)


def test_Qz_perp_annihilates_Qz(rng):
    """eq. 7: Q_z^perp Q_z = 0 and Q_z^perp is a full-rank (non-zero) row."""
    z = jnp.asarray(rng.uniform(-3, 3, size=(N, 3)))
    perp = _vm(C.Q_z_perp)(z)
    assert perp.shape == (N, 1, 3)
    np.testing.assert_allclose(jnp.einsum("nij,njk->nik", perp, _vm(C.Q_z)(z)), 0.0, atol=1e-14)
    assert np.all(np.linalg.norm(np.asarray(perp), axis=(1, 2)) >= 1.0)
    # Q_z itself has full column rank, so the annihilator is unique up to scale
    assert np.all(np.linalg.matrix_rank(np.asarray(_vm(C.Q_z)(z))) == 2)


def _eq27_matrix(w):
    """The matrix printed in eq. 27 (the proof of Lemma 3), written out here."""
    w1, w2, w3 = w[0], w[1], w[2]
    return jnp.array([[1.0, w2 + w3, w1 * w3],
                      [0.0, w1, 0.0],
                      [0.0, w1, 0.5 * w1 * w1]])


def test_eq27_matrix_is_transposed_jacobian_of_fw_inv(sample_w):
    w = jnp.asarray(sample_w(N))
    np.testing.assert_allclose(_vm(_eq27_matrix)(w), _vm(lambda w: jax.jacfwd(C.f_w_inv)(w).T)(w),
                               rtol=1e-14, atol=1e-14)


def test_jacobians_of_fw_and_fw_inv_are_inverse(sample_w):
    w = jnp.asarray(sample_w(N))
    prod = _vm(lambda w: jax.jacfwd(C.f_w)(C.f_w_inv(w)) @ jax.jacfwd(C.f_w_inv)(w))(w)
    np.testing.assert_allclose(prod, np.broadcast_to(np.eye(3), (N, 3, 3)), atol=1e-11)


def test_printed_Qw_differs_from_its_definition(sample_w):
    """Documents the correction: the paper's printed eq. 11 is NOT (df_w/dz) Q_z at f_w^{-1}(w)."""
    w = jnp.asarray(sample_w(N))

    def by_ad(w):
        z = C.f_w_inv(w)
        return jax.jacfwd(C.f_w)(z) @ C.Q_z(z)

    printed = np.asarray(_vm(C.Q_w_printed)(w))
    exact = np.asarray(_vm(by_ad)(w))
    diff = np.abs(printed - exact)
    # the first row and the third row's first entry agree ...
    np.testing.assert_allclose(printed[:, 0, :], exact[:, 0, :], atol=1e-12)
    np.testing.assert_allclose(printed[:, 2, 0], exact[:, 2, 0], atol=1e-12)
    # ... but the printed matrix is wrong at every sampled point, by a wide margin
    assert np.all(diff.max(axis=(1, 2)) > 1e-2)
    # entry (2, 1): printed 1, derived 1/w1
    w1 = np.asarray(w[:, 0])
    np.testing.assert_allclose(printed[:, 1, 0], 1.0)
    np.testing.assert_allclose(exact[:, 1, 0], 1.0 / w1, rtol=1e-12)
