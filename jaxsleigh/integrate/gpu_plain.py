r"""The plain fixed-step path as one GPU kernel: every lane takes all its RK4 steps in registers.

XLA compiles `jaxsleigh.integrate.stepper.run_plain` on a GPU as a loop of kernels, one loop
iteration per step: every step reads and writes the whole batch's state in the GPU's memory and
pays its kernel launches. On one H200 that ran at 8.7e9 trajectory-steps/s for 10^6 starts, this
kernel at 6.1e10 (`experiments/performance/gpu_kernel.py`, float32, 10^4 steps). Here the batch is cut into
blocks of ``block`` lanes, one program per block (`jax.experimental.pallas`, Triton on NVIDIA
GPUs); a program loads its lanes' five components once, takes ``n_steps`` steps with
``lax.fori_loop`` and writes the final state once, the structure of a hand-written CUDA kernel.

The step is the classical RK4 of `jaxsleigh.integrate.rk4.rk4_stages`, on the five components
(`jaxsleigh.model.closed_loop.vector_field_w_components`): the same arithmetic in the same order,
so final states agree with `run_plain` to rounding (they are not bitwise equal: the compilers
contract multiplies and adds differently).

Scope: the paper's law (`jaxsleigh.model.params.Gains`) in the w chart, a built-in damping model,
concrete parameters (their values are compiled into the kernel, as in
`jaxsleigh.integrate.engine._plain_specialised`); `supported` says whether a run qualifies, and
`jaxsleigh.integrate.engine.drive_plain` falls back to `run_plain` where it does not.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ..model.closed_loop import ClosedLoop, vector_field_w_components
from ..model.damping import BUILTIN_DAMPINGS
from ..model.params import Gains

__all__ = ["supported", "run_plain_kernel", "KERNEL_BLOCK"]

#: lanes per program (a power of two, as Triton requires). One H200, 10^4 steps: 256 ran at 2.7e10
#: trajectory-steps/s for 10^5 starts (128: 1.6e10), both at 6.1e10 for 10^6 (experiments/performance/gpu_kernel.py)
KERNEL_BLOCK = 256


def supported(args: ClosedLoop) -> bool:
    """Whether `run_plain_kernel` can run ``args``: the paper's law, a built-in damping model."""
    return isinstance(args.controller, Gains) and isinstance(args.plant.damping, BUILTIN_DAMPINGS)


def _rk4_components(f, y, h):
    """One classical RK4 step on a tuple of components, in `rk4_stages`'s order of operations."""
    k1 = f(y)
    k2 = f(tuple(yi + (0.5 * h) * ki for yi, ki in zip(y, k1)))
    k3 = f(tuple(yi + (0.5 * h) * ki for yi, ki in zip(y, k2)))
    k4 = f(tuple(yi + h * ki for yi, ki in zip(y, k3)))
    return tuple(yi + (h / 6.0) * (a + 2.0 * b + 2.0 * c + d) for yi, a, b, c, d in zip(y, k1, k2, k3, k4))


@functools.lru_cache(maxsize=16)
def _kernel(key, dt: float, n_steps: int, n: int, dtype: str, block: int, interpret: bool):
    """The jitted Pallas call for one (plant, gains, dt, steps, padded batch size)."""
    from jax.experimental import pallas as pl

    tree, leaves = key
    args = jax.tree_util.tree_unflatten(tree, [np.asarray(v, dtype).reshape(s) for s, v in leaves])
    h = np.asarray(dt, dtype)[()]

    def f(y):
        return vector_field_w_components(y, args)[0]

    def kernel(*refs):
        ins, outs = refs[:5], refs[5:]

        def body(_, y):
            return tuple(v.astype(dtype) for v in _rk4_components(f, y, h))

        y = jax.lax.fori_loop(0, n_steps, body, tuple(r[...] for r in ins))
        for r, v in zip(outs, y):
            r[...] = v

    spec = pl.BlockSpec((block,), lambda i: (i,))
    call = pl.pallas_call(kernel, out_shape=[jax.ShapeDtypeStruct((n,), jnp.dtype(dtype))] * 5,
                          grid=(n // block,), in_specs=[spec] * 5, out_specs=[spec] * 5, interpret=interpret)
    return jax.jit(lambda *rows: call(*rows))


def run_plain_kernel(y, dt: float, *, n_steps: int, key, block=None, interpret: bool = False):
    """`run_plain` on a batch-last w-chart state ``y`` (5, N) as one kernel (see the module
    docstring); ``key`` is `jaxsleigh.integrate.engine._args_key` of a `supported` ``args``. ``interpret``
    runs the kernel through Pallas' interpreter (any backend; for tests). ``block``: lanes per
    program (default `KERNEL_BLOCK`, read at each call)."""
    block = KERNEL_BLOCK if block is None else block
    n = y.shape[1]
    npad = -(-n // block) * block
    dtype = np.dtype(y.dtype).name
    rows = [jnp.pad(y[i], (0, npad - n), constant_values=1.0 if i == 0 else 0.0) for i in range(5)]
    out = _kernel(key, float(dt), int(n_steps), npad, dtype, int(block), bool(interpret))(*rows)
    return jnp.stack([r[:n] for r in out])
