"""The one-kernel fixed-step path (`jaxsleigh.integrate.gpu_plain`) and the accelerator defaults.

The kernel runs on a GPU only where one is present; here it runs through Pallas' interpreter, which
traces the same kernel body (the same component field, the same RK4 order of operations), so its
arithmetic is checked against XLA's `run_plain` on any machine. The speed is measured by
`experiments/performance/gpu_kernel.py` on a GPU, never here.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxsleigh import cores
from jaxsleigh.integrate import gpu_plain
from jaxsleigh.integrate.engine import _args_key, check_ics, drive_plain, initial_w, make_horizon
from jaxsleigh.integrate.stepper import run_plain
from jaxsleigh.model.closed_loop import ClosedLoop, vector_field_w_components, vector_field_w_control
from jaxsleigh.model.damping import CustomDamping, ViscousDamping
from jaxsleigh.model.params import paper_gains, paper_plant
from jaxsleigh.model.shaped_law import shaped_from_gains
from jaxsleigh.status import Status

ARGS = ClosedLoop(paper_plant(), paper_gains())


def _starts(n, seed):
    rng = np.random.default_rng(seed)
    ics = np.column_stack([rng.uniform(-3, 3, (n, 2)), rng.uniform(0.3, np.pi, n) * rng.choice([-1.0, 1.0], n),
                           rng.normal(0.0, 1.0, (n, 2))])
    a, st = check_ics(ics)
    return np.asarray(initial_w(a, st, jnp.float32)), st


def _rel(a, b):
    return np.max(np.abs(a - b), axis=-1) / np.maximum(np.max(np.abs(b), axis=-1), 1.0)


@pytest.mark.parametrize("damping", [None, ViscousDamping(0.5, 2.0),
                                     CustomDamping(lambda q, p: jnp.diag(jnp.array([1.0, 0.5])) * (1 + q[0] ** 2))])
def test_component_field_is_the_array_field(damping):
    """The component form returns the array form's numbers, bit for bit, also for a damping model
    that reads q (the one case where q is formed)."""
    plant = paper_plant() if damping is None else paper_plant()._replace(damping=damping)
    args = ClosedLoop(plant, paper_gains())
    y = jnp.asarray(_starts(64, 0)[0].T)
    ref, u_ref = vector_field_w_control(0.0, y, args)
    got, u = vector_field_w_components(tuple(y), args)
    np.testing.assert_array_equal(np.stack(got), np.asarray(ref))
    np.testing.assert_array_equal(np.stack(u), np.stack(u_ref))


@pytest.mark.parametrize("n", [40, gpu_plain.KERNEL_BLOCK, 2 * gpu_plain.KERNEL_BLOCK + 44])
def test_kernel_agrees_with_xla(n):
    """The kernel's final states (through the interpreter) against XLA's `run_plain`, 300 steps
    from starts with momentum: to float32 rounding, with padded last blocks dropped."""
    y0, _ = _starts(n, n)
    y = jnp.asarray(y0.T)
    ref = np.asarray(run_plain(y, ARGS, jnp.float32(0.01), n_steps=300, block=None))
    got = np.asarray(gpu_plain.run_plain_kernel(y, 0.01, n_steps=300, key=_args_key(ARGS), interpret=True))
    assert got.shape == ref.shape == (5, n)
    assert np.all(np.isfinite(got))
    assert np.max(_rel(got.T, ref.T)) < 2e-5
    assert np.median(_rel(got.T, ref.T)) < 1e-6


def test_drive_plain_kernel_switch():
    """``kernel=True`` agrees with XLA (off a GPU through the interpreter); ``"auto"`` is XLA's path bit for
    bit on CPU and the kernel's on a GPU; a law or damping the kernel does not cover is refused by name."""
    y0, st = _starts(150, 7)
    hz = make_horizon(2.0, 0.01)
    y_xla, s_xla = drive_plain(y0, st, ARGS, hz, kernel=False)
    y_auto, _ = drive_plain(y0, st, ARGS, hz)
    y_k, s_k = drive_plain(y0, st, ARGS, hz, kernel=True, segment=120)    # two segments: 120 + 80 steps
    on_gpu = jax.default_backend() in ("gpu", "cuda", "rocm")
    np.testing.assert_array_equal(y_auto, drive_plain(y0, st, ARGS, hz, kernel=True)[0] if on_gpu else y_xla)
    np.testing.assert_array_equal(s_k, s_xla)
    assert np.all(s_k == Status.OK)
    assert np.max(_rel(y_k, y_xla)) < 2e-5
    shaped = ClosedLoop(paper_plant(), shaped_from_gains(paper_gains()))
    assert not gpu_plain.supported(shaped)
    with pytest.raises(ValueError, match="paper's law"):
        drive_plain(y0, st, shaped, hz, kernel=True)


def test_default_chunk_size(monkeypatch):
    """CPU keeps the caller's CPU default; an accelerator takes ACCELERATOR_CHUNK per device."""
    monkeypatch.setattr(jax, "default_backend", lambda: "cpu")        # whichever backend runs the tests
    assert cores.default_chunk_size(16384) == 16384
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert cores.default_chunk_size(16384, devices=["d0", "d1"]) == 2 * cores.ACCELERATOR_CHUNK
    assert cores.default_chunk_size(65536, devices=["d0"]) == cores.ACCELERATOR_CHUNK


def test_a_kernel_the_gpu_refuses_falls_back_with_a_warning(monkeypatch):
    """Where the GPU's compiler refuses the kernel, ``kernel="auto"`` says so once and runs XLA's loop;
    ``kernel=True`` raises instead (the user asked for the kernel)."""
    y0, st = _starts(64, 3)
    hz = make_horizon(1.0, 0.01)
    ref, _ = drive_plain(y0, st, ARGS, hz, kernel=False, block=None, segment=40, specialise=False)  # as off CPU

    def refuse(*a, **k):
        raise RuntimeError("Triton: unsupported operation")

    monkeypatch.setattr(gpu_plain, "run_plain_kernel", refuse)
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")       # an accelerator: whole-batch blocks
    with pytest.warns(UserWarning, match="one-kernel fixed-step path failed.*Triton"):
        y, s = drive_plain(y0, st, ARGS, hz, segment=40)
    np.testing.assert_array_equal(y, ref)
    assert np.all(s == Status.OK)
    with pytest.raises(RuntimeError, match="Triton"):
        drive_plain(y0, st, ARGS, hz, kernel=True)


def test_kernel_in_float64():
    """The one switch: float64 states give a float64 kernel, agreeing with XLA's float64 far below float32's rounding."""
    y0, _ = _starts(64, 5)
    with jax.enable_x64(True):
        y = jnp.asarray(y0.T, jnp.float64)
        ref = np.asarray(run_plain(y, ARGS, jnp.float64(0.01), n_steps=200, block=None))
        got = gpu_plain.run_plain_kernel(y, 0.01, n_steps=200, key=_args_key(ARGS), interpret=True)
        assert got.dtype == jnp.float64
        assert np.max(_rel(np.asarray(got).T, ref.T)) < 1e-12


def test_kernel_near_the_singular_set_flags_what_does_not_run():
    """Starts near theta = 0 with momentum, on the one-kernel path (through the interpreter): a start either ends
    OK with a finite state on the same side of theta = 0, or is flagged (NONFINITE / CROSSED_SINGULAR); no
    non-finite or crossed state passes as OK. Its statuses are XLA's."""
    rng = np.random.default_rng(4)
    n = 96
    th = rng.choice([-1.0, 1.0], n) * 10.0 ** rng.uniform(-3, -1, n)
    ics = np.column_stack([rng.uniform(-3, 3, (n, 2)), th, rng.normal(0.0, 3.0, (n, 2))])
    a, st = check_ics(ics)
    y0 = np.asarray(initial_w(a, st, jnp.float32))
    hz = make_horizon(5.0, 0.05)                      # a coarse fixed step: some of these cannot run
    y_k, s_k = drive_plain(y0, st, ARGS, hz, kernel=True)
    _, s_x = drive_plain(y0, st, ARGS, hz, kernel=False)
    ok = s_k == Status.OK
    assert np.all(np.isfinite(y_k[ok]))
    assert np.all(np.sign(y_k[ok, 0]) == np.sign(y0[ok, 0]))
    assert not np.all(ok), "the coarse step should leave some starts flagged"
    assert set(np.unique(s_k[~ok])) <= {Status.NONFINITE, Status.CROSSED_SINGULAR}
    np.testing.assert_array_equal(s_k, s_x)
