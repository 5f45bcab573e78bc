"""The shaped-energy law (jaxsleigh.model.shaped_law): the conditions of the paper's proof for its family, the
monitored energy, the absence of rest points off w1 = 0, and the loop against scipy's Radau in the physical chart."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.optimize import least_squares

import jaxsleigh as js
from jaxsleigh.model import coordinates as C
from jaxsleigh.model.closed_loop import ClosedLoop, dissipation_w, vector_field_law_control, vector_field_w
from jaxsleigh.model.controller import FunctionLaw
from jaxsleigh.model.params import paper_gains, paper_plant
from jaxsleigh.model.shaped_law import ShapedGains, shaped_from_gains, shaped_gains
from jaxsleigh.model.w_laws import control_w_components, potential
from jaxsleigh.status import Status

SHAPED = shaped_gains(L=[0.3, 0.2, 0.4], B=[2.0, 1.5, 3.0], C=[0.4, 0.8, 0.3], k=0.05, D_near=[3.0, 9.0],
                      D_far=[1.0, 2.5], s=0.7)
ICS = np.array([[-3.0, -2.0, np.pi / 8], [1.0, 1.0, 0.5], [2.0, -1.0, -1.2], [-0.5, 2.5, 2.8], [3.0, 0.2, 0.15]])


def _random_params(rng, n):
    for _ in range(n):
        yield shaped_gains(L=rng.uniform(1e-3, 3, 3), B=rng.uniform(0, 5, 3), C=rng.uniform(0.05, 3, 3),
                           k=rng.uniform(1e-3, 1), D_near=rng.uniform(0.1, 10, 2), D_far=rng.uniform(0.1, 10, 2),
                           s=rng.uniform(0.1, 3))


def test_potential_is_strictly_convex_coercive_with_minimum_zero_at_zero():
    """phi_i(0) = 0, phi_i'' > 0 and phi_i >= l_i w^2 / 2 (coercive) for random members of the family, on a wide
    range of w (the proof's conditions, checked on the functions the engine uses)."""
    rng = np.random.default_rng(1)
    w = np.concatenate([-np.logspace(-4, 6, 200), [0.0], np.logspace(-4, 6, 200)])
    with jax.enable_x64(True):
        for g in _random_params(rng, 20):
            g = jax.tree_util.tree_map(jnp.asarray, g)
            for i in range(3):
                phi = lambda x, i=i: g.potential(tuple(x if j == i else jnp.zeros_like(x) for j in range(3)))  # noqa: E731
                vals = np.asarray(jax.vmap(phi)(jnp.asarray(w)))
                d2 = np.asarray(jax.vmap(jax.grad(jax.grad(phi)))(jnp.asarray(w)))
                d1 = np.asarray(jax.vmap(jax.grad(phi))(jnp.asarray(w)))
                assert vals[200] == 0.0 and d1[200] == 0.0
                assert np.all(d2 > 0)
                assert np.all(vals >= 0.5 * float(g.L[i]) * w * w * (1 - 1e-12))
                # the closed-form gradient the law applies is the derivative of the potential
                grad = np.asarray(g.potential_grad(tuple(jnp.asarray(w) if j == i else jnp.zeros_like(jnp.asarray(w))
                                                         for j in range(3)))[i])
                np.testing.assert_allclose(grad, d1, rtol=1e-10, atol=1e-12)


def test_damping_injection_is_bounded_below_by_delta():
    rng = np.random.default_rng(2)
    with jax.enable_x64(True):
        for g in _random_params(rng, 20):
            w = jnp.asarray(rng.normal(size=(3, 500)) * rng.choice([1e-3, 1, 1e3], size=(1, 500)))
            d1, d2 = (np.asarray(d) for d in g.damping_diag(w))
            delta = min(np.min(g.D_near), np.min(g.D_far))
            assert np.all(d1 >= delta * (1 - 1e-12)) and np.all(d2 >= delta * (1 - 1e-12))
            assert np.all(d1 <= max(g.D_near[0], g.D_far[0]) * (1 + 1e-12))


def test_paper_law_is_the_special_case_b_zero():
    """shaped_from_gains(paper gains) is the paper's law: same trajectories, same T_eps, same energy."""
    a = js.run_ensemble(ICS, gains=paper_gains(), t_final=60, x64=True)
    b = js.run_ensemble(ICS, controller=shaped_from_gains(paper_gains()), t_final=60, x64=True)
    np.testing.assert_allclose(b.q_final, a.q_final, atol=1e-9)
    np.testing.assert_allclose(b.u_energy, a.u_energy, rtol=1e-9)
    np.testing.assert_array_equal(np.isfinite(a.T_eps), np.isfinite(b.T_eps))


def test_hd_never_rises_and_matches_the_dissipation_formula():
    """Along trajectories H_d (kinetic + V) never increases (float64), and at random states its derivative along the
    field is -v^T D_d v <= 0 (eq. 18 with V in place of w^T L w / 2)."""
    sol = js.simulate(ICS, controller=SHAPED, t_final=80, x64=True, saveat=js.SaveAt(every=1))
    assert np.all(sol.status == Status.OK)
    Hd = np.asarray(sol.Hd)
    assert np.all(np.isfinite(Hd))
    assert np.max(np.diff(Hd, axis=1) / np.maximum(Hd[:, :1], 1.0)) <= 1e-9
    rng = np.random.default_rng(3)
    with jax.enable_x64(True):
        args = ClosedLoop(jax.tree_util.tree_map(jnp.asarray, paper_plant()), jax.tree_util.tree_map(jnp.asarray,
                                                                                                      SHAPED))
        y = jnp.asarray(np.concatenate([rng.normal(size=(3, 400)) * 2, rng.normal(size=(2, 400))]))

        def hd(yy):
            from jaxsleigh.model.plant import hamiltonian
            return hamiltonian(yy[3:], args.plant) + potential(yy[:3], args.controller)

        dH = jax.vmap(lambda yy: jnp.dot(jax.grad(hd)(yy), vector_field_w(0.0, yy, args)), in_axes=1)(y)
        diss = dissipation_w(y, args)
        np.testing.assert_allclose(np.asarray(dH), np.asarray(diss), rtol=1e-8, atol=1e-10)
        assert np.all(np.asarray(diss) <= 0)


def _rest_residual(grad_V, R=5.0):
    """min over |w2|, |w3| <= R of |Q_w(w)^T grad V(w)| at fixed w1 (the p = 0 rest condition), from several guesses.
    (Bounded: along w2 -> 0, w3 -> infinity the residual tends to 0 without a root; H_d <= H_d(0) keeps w bounded.)"""
    def best(w1):
        def F(x):
            w = (w1, x[0], x[1])
            return np.asarray(C.Q_w(jnp.asarray(w)).T @ jnp.asarray(grad_V(w)), np.float64)
        return min(np.linalg.norm(least_squares(F, x0, bounds=([-R, -R], [R, R]), xtol=1e-14, ftol=1e-14, gtol=1e-14).fun)
                   for x0 in ([0.3, -0.2], [-1.0, 2.0], [2.0, 1.0], [-0.1, -3.0]))
    return best


def test_no_rest_points_off_the_singular_set_and_a_full_L_has_them():
    """Lemma 3 for the separable family: at p = 0 the field vanishes only where Q_w^T grad V = 0, which forces
    phi_2'(w_2) = 0 and then phi_1'(w_1) = 0, so w_1 = 0. Numerically: for w_1 != 0 no (w_2, w_3) makes the residual
    small (it stays near |phi_1'(w_1)|). A full, non-diagonal L (not in the family) has such rest points: the same
    search finds them, so the check can fail."""
    with jax.enable_x64(True):
        g = jax.tree_util.tree_map(jnp.asarray, SHAPED)
        best = _rest_residual(lambda w: jnp.stack(g.potential_grad(tuple(jnp.asarray(x) for x in w))))
        for w1 in (-1.5, -0.4, 0.2, 0.9, 2.0):
            phi1 = abs(float(g.potential_grad((jnp.asarray(w1), 0.0, 0.0))[0]))
            assert best(w1) > 0.03 * phi1 > 0
        Lfull = jnp.array([[1.0, 0.6, 0.3], [0.6, 1.0, 0.2], [0.3, 0.2, 1.0]])
        full = _rest_residual(lambda w: Lfull @ jnp.asarray(w))
        assert full(0.9) < 1e-8


def test_shaped_loop_converges_and_never_crosses_theta_zero():
    """Proposition 2 (q -> 0, theta never crosses 0) for a member far from tuned: slow, but every start ends within
    0.06 of the target by 400 s, from |q0| up to 3.6."""
    r = js.run_ensemble(ICS, controller=SHAPED, t_final=400, x64=True)
    assert np.all(r.status == Status.OK)
    assert np.all(np.linalg.norm(r.q_final, axis=1) < 0.06)
    assert np.all(np.sign(r.q_final[:, 2]) == np.sign(ICS[:, 2])) and np.all(r.min_abs_theta > 0)


def test_w_chart_against_scipy_radau_in_the_physical_chart():
    """The engine's w-chart integration of the shaped law against scipy's Radau integrating the same law, as a plain
    law u = law(q, v), in the physical state (x, y, theta, p1, p2)."""
    plant = paper_plant()
    with jax.enable_x64(True):
        args = ClosedLoop(jax.tree_util.tree_map(jnp.asarray, plant), FunctionLaw(SHAPED))
        f = jax.jit(lambda y: jnp.stack(vector_field_law_control(0.0, y, args)[0]))
        jac = jax.jit(jax.jacfwd(lambda y: jnp.stack(vector_field_law_control(0.0, y, args)[0])))
        r = js.run_ensemble(ICS[:3], controller=SHAPED, t_final=20, x64=True,
                            stepsize=js.StepSizeController(rtol=1e-10, atol=1e-10))
        for i, ic in enumerate(ICS[:3]):
            sol = solve_ivp(lambda t, y: np.asarray(f(jnp.asarray(y))), (0, 20), np.r_[ic, 0, 0], method="Radau",
                            rtol=1e-10, atol=1e-10, jac=lambda t, y: np.asarray(jac(jnp.asarray(y))))
            np.testing.assert_allclose(r.q_final[i], sol.y[:3, -1], atol=1e-6)


def test_physical_call_is_the_w_chart_law():
    rng = np.random.default_rng(4)
    with jax.enable_x64(True):
        g = jax.tree_util.tree_map(jnp.asarray, SHAPED)
        for _ in range(10):
            q, v = jnp.asarray(rng.normal(size=3)), jnp.asarray(rng.normal(size=2))
            np.testing.assert_allclose(np.asarray(g(q, v)),
                                       np.asarray(jnp.stack(control_w_components(C.q_to_w(q), v, g))), rtol=1e-12)


@pytest.mark.parametrize("field,value,msg", [("L", [1.0, -1.0, 1.0], "L must be > 0"),
                                             ("B", [1.0, -0.1, 1.0], "B must be >= 0"),
                                             ("k", 0.0, "Lemma 2 needs k > 0"),
                                             ("D_far", [1.0, np.nan], "must be finite"),
                                             ("C", [1.0, 1.0], "shape (3,)")])
def test_shaped_gains_say_which_condition_fails(field, value, msg):
    kw = SHAPED._asdict()
    kw[field] = value
    with pytest.raises(ValueError, match=msg.replace("(", r"\(").replace(")", r"\)")):
        shaped_gains(**kw)


def test_is_a_namedtuple_of_positive_leaves_for_the_tuner():
    assert isinstance(SHAPED, ShapedGains)
    assert set(ShapedGains.positive) == set(ShapedGains._fields)


def test_shaped_preset_runs_from_the_command_line_and_python(tmp_path, capsys):
    from jaxsleigh.cli import main

    law = js.load_shaped("shaped")
    assert isinstance(law, ShapedGains)
    assert all(np.array_equal(a, b) for a, b in zip(law, ShapedGains.preset()))
    out = tmp_path / "s.npz"
    code = main(["simulate", "--controller", "shaped", "--ic", "1,1,0.5", "--t-final", "5", "--out", str(out)])
    assert code == 0
    d = np.load(out)
    assert np.all(np.isfinite(d["q"])) and np.all(np.diff(d["Hd"], axis=-1) <= 1e-5 * d["Hd"][..., :1])


def test_load_shaped_says_what_is_wrong(tmp_path):
    with pytest.raises(ValueError, match="not found"):
        js.load_shaped("no-such-preset")
    bad = tmp_path / "bad.json"
    bad.write_text('{"L": [1, 1, 1]}')
    with pytest.raises(ValueError, match="fields L, B, C, k, D_near, D_far, s"):
        js.load_shaped(str(bad))


@pytest.mark.parametrize("x64", [False, True])
def test_near_theta_zero_the_shaped_preset_says_what_it_did(x64):
    """Starts down to theta0 = 1e-6 under the shaped preset, float32 and float64: a start either ends OK with a finite
    state and summaries, or with another status and NaN outputs; no silent non-finite value."""
    th = np.r_[np.geomspace(1e-6, 0.05, 24) * np.resize([1, -1], 24), 0.5, -1.0, 2.0, -2.5]
    ics = np.column_stack([np.resize([2.0, -1.0, 0.5], 28), np.resize([1.0, 2.0, -2.5], 28), th])
    r = js.run_ensemble(ics, controller=js.load_shaped(), t_final=5.0, x64=x64,
                        stepsize=js.StepSizeController(max_steps=4000), run=js.RunOptions(progress=False))
    ok = r.status == Status.OK
    assert ok[24:].all()                                     # the ordinary starts run through
    fields = np.column_stack([r.q_final, r.p_final, r.u_energy, r.min_abs_theta])
    assert np.all(np.isfinite(fields[ok])) and np.all(r.min_abs_theta[ok] > 0)
    assert np.all(np.isnan(r.q_final[~ok])) and np.all(np.isin(r.status[~ok], [s.value for s in Status]))
