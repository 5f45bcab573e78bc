"""The public vector field works with another solver (diffrax) and under jax.grad.

The examples are the code blocks of ``docs/how-to/interop.md``, executed as written (so the page cannot
drift from what works); the assertions below re-check their results independently of the page's own.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

PAGE = Path(__file__).resolve().parents[1] / "docs" / "how-to" / "interop.md"


@pytest.fixture(scope="module")
def page_namespace():
    pytest.importorskip("diffrax")
    blocks = re.findall(r"```python\n(.*?)```", PAGE.read_text(), re.S)
    assert len(blocks) == 2, "interop.md should hold the diffrax example and the gradient example"
    ns: dict = {}
    for i, code in enumerate(blocks):
        exec(compile(code, f"{PAGE.name} (block {i + 1})", "exec"), ns)
    return ns


def test_diffrax_integrates_the_public_vector_field_like_simulate(page_namespace):
    ns = page_namespace
    js = ns["js"]
    assert isinstance(ns["args"], js.ClosedLoop)
    ys = np.asarray(ns["out"].ys)
    ref = ns["ref"]
    assert ys.dtype == np.float64 and ref.q.dtype == np.float64
    assert ys.shape == (11, 5) and ref.q.shape == (1, 11, 3)
    assert np.all(ref.status == js.Status.OK)
    # different solvers in different charts (diffrax: physical, simulate: w chart) agree tightly
    np.testing.assert_allclose(ys[:, :3], ref.q[0], rtol=0, atol=1e-8)
    np.testing.assert_allclose(ys[:, 3:], ref.p[0], rtol=0, atol=1e-8)
    # and the run is not trivial: the sleigh moved by metres and is near the origin only later
    assert np.abs(ys[:, :2] - ys[0, :2]).max() > 1.0


def test_gradient_of_a_user_loss_matches_central_differences(page_namespace):
    ns = page_namespace
    dk, fd_k = float(ns["dk"]), float(ns["fd_k"])
    dL, fd_L2 = np.asarray(ns["dL"]), float(ns["fd_L2"])
    assert dL.shape == (3,) and np.all(np.isfinite(dL)) and np.isfinite(dk)
    assert abs(dk) > 1e-3 and abs(fd_L2) > 1e-3          # the check is not between two zeros
    assert dk == pytest.approx(fd_k, rel=1e-6)
    assert dL[1] == pytest.approx(fd_L2, rel=1e-6)


def test_gradient_other_components_and_forward_mode(page_namespace):
    """L1 and L3 agree with central differences too, and forward mode (as the page says:
    ``adjoint=diffrax.ForwardMode()``, then ``jax.jacfwd``) gives the same gradient as ``jax.grad``."""
    ns = page_namespace
    jax, jnp, js, diffrax, loss = ns["jax"], ns["jnp"], ns["js"], ns["diffrax"], ns["loss"]
    k0, L0, dL, y0, g0, plant = ns["k0"], ns["L0"], np.asarray(ns["dL"]), ns["y0"], ns["g0"], ns["plant"]
    with jax.enable_x64(True):
        h = 1e-6
        for i in (0, 2):
            e = jnp.zeros(3).at[i].set(1.0)
            fd = float((loss(k0, L0 + h * e) - loss(k0, L0 - h * e)) / (2 * h))
            assert dL[i] == pytest.approx(fd, rel=1e-6, abs=1e-9)

        def loss_fwd(L):
            sol = diffrax.diffeqsolve(
                diffrax.ODETerm(js.vector_field), diffrax.Tsit5(), t0=0.0, t1=5.0, dt0=0.005, y0=y0,
                args=js.ClosedLoop(plant, g0._replace(L=L)), stepsize_controller=diffrax.ConstantStepSize(),
                max_steps=2000, adjoint=diffrax.ForwardMode())
            return jnp.sum(sol.ys[-1, :3] ** 2)

        fwd = np.asarray(jax.jit(jax.jacfwd(loss_fwd))(L0))
    np.testing.assert_allclose(fwd, dL, rtol=1e-9)


def test_simulate_is_documented_as_not_differentiable(page_namespace):
    """The page says which path is differentiable; keep that true: simulate hands back NumPy arrays."""
    assert "**not** differentiable" in PAGE.read_text()
    ref = page_namespace["ref"]
    assert type(ref.q) is np.ndarray and type(ref.Hd) is np.ndarray
