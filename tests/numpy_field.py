"""The closed loop's vector field for SciPy's reference solvers: compiled once in float64 and called with NumPy
arrays (about 4x less overhead per call than a ``jax.jit`` function fed ``jnp.asarray``; Radau's stiff references
make 10^5 calls)."""
import jax
import jax.numpy as jnp
import numpy as np

from jaxsleigh.model.closed_loop import vector_field


def numpy_field(args, field=vector_field):
    """``(f(t, y), jac(t, y))`` of ``field(t, y, args)`` (the physical chart's by default) for
    ``scipy.integrate.solve_ivp``, float64: call them inside ``jax.enable_x64(True)`` (the programs were compiled for
    float64 inputs)."""
    with jax.enable_x64(True):
        y, t = jnp.zeros(5, jnp.float64), jnp.zeros((), jnp.float64)
        fc = jax.jit(lambda t, y: field(t, y, args)).lower(t, y).compile()
        jc = jax.jit(jax.jacfwd(lambda t, y: field(t, y, args), argnums=1)).lower(t, y).compile()

    def f(t, y):
        return np.asarray(fc(np.float64(t), np.asarray(y, np.float64)))

    def jac(t, y):
        return np.asarray(jc(np.float64(t), np.asarray(y, np.float64)))

    return f, jac
