"""One configuration object for every solve: `solve_config` resolves and checks the options
that `simulate`, `run_ensemble` and `run_basin`
share (plant, gains, horizon, method, precision, tolerances, step budget, convergence ball), once,
eagerly, with messages that say what to change.

The result, `SolveConfig`, is what the engine runs and what the result files record
(`SolveConfig.settings`).
"""
from __future__ import annotations

from typing import Any, NamedTuple, Optional

import jax
import numpy as np

from ..model.controller import as_controller, controller_record
from ..integrate.stepsize import DEFAULT_ATOL, DEFAULT_RTOL, MAX_STEP_FACTOR, StepSizeController
from ..integrate.engine import METHODS, Horizon, default_max_steps, make_horizon
from ..model.params import Gains, PlantParams, as_gains, as_plant, gains_to_dict, lane_record
from ..validate import INT32_MAX, real, whole
from ..model.closed_loop import ClosedLoop
from ..model.lanes import broadcast_lanes, check_lanes, lane_count, lanes_digest

__all__ = ["SolveConfig", "solve_config", "DEFAULT_RTOL", "DEFAULT_ATOL", "MAX_STEP_FACTOR", "plant_to_dict",
           "reject_traced"]



class SolveConfig(NamedTuple):
    """Everything that decides a solve, resolved and checked (see `solve_config`)."""

    plant: PlantParams
    gains: Gains
    horizon: Horizon
    #: the step policy, resolved: every number set (tolerances for the dtype, ``max_step`` and the budget
    #: ``max_steps`` from the horizon) with the caller's ``safety`` and factor limits; what the engine's drivers take
    stepsize: StepSizeController
    eps: float
    x64: bool
    #: number of per-trajectory parameter lanes (``None``: one plant and one set of gains)
    lanes: Optional[int] = None
    #: a feedback law other than the paper's (`jaxsleigh.model.controller`); ``None``: the paper's law with ``gains``
    controller: Any = None

    @property
    def law(self):
        """The controller the engine runs: ``controller``, or the paper's law with ``gains``."""
        return self.gains if self.controller is None else self.controller

    @property
    def adaptive(self) -> bool:
        """Whether the steps are adaptive (``stepsize.method == "adaptive"``) rather than fixed RK4."""
        return self.stepsize.method == "adaptive"

    def lane_loop(self, n: int) -> Optional[ClosedLoop]:
        """The closed loop with its per-trajectory parameters broadcast to one lane per start (``n``); ``None`` for
        one plant and one law; a ``ValueError`` when the lanes are neither 1 nor ``n``."""
        if self.lanes is None:
            return None
        if self.lanes not in (1, n):
            raise ValueError(f"the per-trajectory parameters have {self.lanes} lanes but there are {n} initial "
                             f"conditions; give one value per initial condition (or one for all)")
        return ClosedLoop(*broadcast_lanes(self.plant, self.law, n))

    @property
    def dtype(self) -> str:
        """``"float64"`` or ``"float32"``."""
        return "float64" if self.x64 else "float32"

    def settings(self) -> dict:
        """JSON-ready record of the configuration (written into every result file)."""
        ss = self.stepsize
        out = {
            "plant": plant_to_dict(self.plant),
            "gains": gains_to_dict(self.gains) if self.controller is None else None,
            "t_final": self.horizon.t_final, "dt": self.horizon.dt, "eps": self.eps, "method": ss.method,
            "rtol": ss.rtol, "atol": ss.atol, "max_step": ss.max_step, "max_steps": ss.max_steps,
            "dtype": self.dtype, "check_passivity": ss.check_passivity,
        }
        default = StepSizeController().resolved(self.dtype, self.horizon.dt)
        for k in ("safety", "factor_min", "factor_max"):  # recorded where not the default: earlier records unchanged
            if float(getattr(ss, k)) != float(getattr(default, k)):
                out[k] = float(getattr(ss, k))
        if self.controller is not None:
            out["controller"] = controller_record(self.controller)
        if self.lanes is not None:
            out["lanes"] = self.lanes
            out["lanes_sha256"] = lanes_digest(self.plant, self.gains)
        return out


def plant_to_dict(plant: PlantParams) -> dict:
    """The one record of a plant in every file jaxsleigh writes (a result's settings, a checkpoint's, a tuner's gains,
    law or front file, an optimum's settings): ``{"m", "J", "l", "damping": its class name, "damping_params": {its
    fields}}``, JSON-ready; a leaf that varies per trajectory is recorded as ``{"per_trajectory": P, "min": ..,
    "max": ..}`` (the values themselves go with the rows, see ``lane_table``). Files of earlier versions recorded the
    damping by its short name (``"coulomb"``) in the tuners' files, with a list of parameters in the optimum's; the
    readers take both (`jaxsleigh.files.npz.damping_name`)."""
    num = (lambda v: float(v) if np.ndim(v) == 0 else lane_record(v))  # noqa: E731
    d = plant.damping
    return {"m": num(plant.m), "J": num(plant.J), "l": num(plant.l),
            "damping": type(d).__name__, "damping_params": {k: num(v) for k, v in d._asdict().items()}
            if hasattr(d, "_asdict") else repr(d)}


#: Where to differentiate or jit instead of the NumPy-returning fronts (named in `reject_traced`'s message).
DIFFERENTIABLE_PATHS = ("jaxsleigh.solve (one start as a pure JAX function of the controller, the plant and the "
                        "start: jit, vmap, grad and jacfwd work through it), or jaxsleigh.tuning.soft_convergence "
                        "(the tuner's smooth surrogate of the convergence time)")


def reject_traced(front: str, **inputs) -> None:
    """Refuse JAX tracers among a front's inputs: ``TypeError`` naming the input and the differentiable path.

    `jaxsleigh.simulate`, `run_ensemble`, `run_basin` and `sweep` drive the integrator from
    Python and return NumPy arrays: under ``jax.jit``, ``jax.grad`` or ``jax.vmap`` they would fail
    deep inside with ``TracerArrayConversionError`` or a misleading "must be a real number". Every
    front calls this first, on everything it was given (``front``: its name in the message).
    """
    for name, value in inputs.items():
        try:
            leaves = jax.tree_util.tree_flatten_with_path(value)[0]
        except Exception:                      # noqa: BLE001 - not a pytree: nothing traced inside
            continue
        for path, leaf in leaves:
            if isinstance(leaf, jax.core.Tracer):
                where = name + jax.tree_util.keystr(path)      # e.g. "gains.k", "ics[0]"
                raise TypeError(
                    f"{front}() got a JAX tracer in {where} ({type(leaf).__name__}): it was called inside jax.jit, "
                    f"jax.grad or jax.vmap, but it integrates from Python and returns NumPy arrays, so it is neither "
                    f"jittable nor differentiable. Call it outside the transformation with concrete numbers; to "
                    f"differentiate, use {DIFFERENTIABLE_PATHS}")


def _flag(name: str, flags: Optional[dict]) -> str:
    return (flags or {}).get(name, name)


def _check_switches(method, x64, check_passivity, f) -> bool:
    """Check ``method`` and the two switches; returns ``x64`` as a bool (``f``: an option's name in messages)."""
    if method not in METHODS:
        raise ValueError(f"{f('method')} must be one of {', '.join(METHODS)}, got {method!r}")
    if not isinstance(x64, (bool, np.bool_)) and x64 not in (0, 1):
        raise ValueError(f"{f('x64')} must be True or False, got {x64!r}")
    for name, v in (("check_passivity", check_passivity),):
        if not isinstance(v, (bool, np.bool_)) and v not in (0, 1):
            raise ValueError(f"{f(name)} must be True or False, got {v!r}")
    return bool(x64)


def _resolve_law(plant, gains, controller, f, flags):
    """The plant and the law, checked: either ``gains`` (the paper's law) or ``controller`` (a `Gains` there is
    the paper's law too), with or without per-trajectory lanes. Returns ``(plant, gains, controller, lanes)``."""
    if controller is not None:
        if gains is not None:
            raise ValueError(f"give either {f('gains')} (the paper's law) or {f('controller')} (any law u = law(q, v)), "
                             "not both")
        if isinstance(controller, Gains):
            gains, controller = controller, None
        else:
            controller = as_controller(controller, f("controller"))
    lanes = lane_count(plant, gains if controller is None else controller)
    if lanes is None:
        plant = as_plant(plant)
        if controller is None:
            gains = as_gains(gains)
    elif controller is None:                   # per-trajectory leaves: every lane checked at once
        plant, gains = check_lanes(plant, gains, flags=flags)
    else:
        plant, controller = check_lanes(plant, controller, flags=flags)
    return plant, gains, controller, lanes


def _resolve_horizon(t_final, dt, save_every, f, flags) -> Horizon:
    """The checked `Horizon` of ``t_final``, ``dt`` and ``save_every``."""
    t_final = real(f("t_final"), t_final, positive=True, example=100, maximum=1e30)
    dt = real(f("dt"), dt, positive=True, example=0.01)
    if save_every is not None:
        save_every = whole(f("save_every"), save_every, example=10)
    return make_horizon(t_final, dt, save_every, flags=flags)


def _resolve_steps(stepsize: StepSizeController, horizon: Horizon, dtype: str, f) -> StepSizeController:
    """``stepsize`` resolved: its numbers checked, their defaults filled in (tolerances for ``dtype``, ``max_step``
    and ``max_steps`` from the horizon), ``check_passivity`` a bool; fixed-step RK4 needs a budget of at least the
    horizon's base steps. ``safety`` and the factor limits stay as given (checked by
    `jaxsleigh.integrate.stepsize.check_policy`)."""
    adaptive = stepsize.method == "adaptive"
    checked = {k: real(f(k), v, positive=True, example=ex) for k, v, ex in
               (("rtol", stepsize.rtol, 1e-6), ("atol", stepsize.atol, 1e-6), ("max_step", stepsize.max_step, 0.1))
               if v is not None}
    full = stepsize._replace(**checked).resolved(dtype, horizon.dt)     # the defaults, in one place
    max_steps = full.max_steps
    if max_steps is None:
        max_steps = default_max_steps(horizon, adaptive, dtype)
    else:
        max_steps = whole(f("max_steps"), max_steps, minimum=1, maximum=INT32_MAX - 1, example=2000000)
        if not adaptive and max_steps < horizon.n_steps:
            raise ValueError(f"{f('max_steps')} {max_steps} is below the {horizon.n_steps} base steps of the "
                             f"horizon (t_final / dt) that fixed-step RK4 takes; raise it to at least "
                             f"{horizon.n_steps}")
    return full._replace(max_steps=max_steps, check_passivity=bool(stepsize.check_passivity))


def solve_config(*, plant: Any = None, gains: Any = None, controller: Any = None, t_final: Any = 100.0,
                 dt: Any = 0.01, save_every: Any = None, eps: Any = 0.05, x64: Any = False,
                 stepsize: Optional[StepSizeController] = None, flags: Optional[dict] = None) -> SolveConfig:
    """Resolve defaults and check every option; raises ``ValueError`` naming the option to change.

    Args mean the same as in `jaxsleigh.simulate`. ``stepsize`` is a `jaxsleigh.StepSizeController` (its
    ``method``, ``rtol``, ``atol``, ``max_step``, ``max_steps`` and ``check_passivity`` are checked here;
    default: ``StepSizeController()``), resolved here once into `SolveConfig.stepsize` (every number set, ``safety``
    and the factor limits as given): the policy the engine runs and the settings record. ``gains`` may be a `Gains`, a preset
    name (``"paper"``, ``"tuned"``, ...), a gains-file path or a dict; ``plant`` a
    `PlantParams` (both re-validated). ``controller`` is any feedback law ``u = law(q, v)``
    (`jaxsleigh.model.controller`; a `Gains` there means the paper's law, as ``gains``). ``flags`` maps keyword names to the command-line
    flags to name in messages (e.g. ``{"max_steps": "--max-steps"}``).
    """
    f = lambda n: _flag(n, flags)  # noqa: E731
    stepsize = StepSizeController() if stepsize is None else stepsize
    reject_traced("solve_config", plant=plant, gains=gains, t_final=t_final, dt=dt, save_every=save_every,
                  rtol=stepsize.rtol, atol=stepsize.atol, max_step=stepsize.max_step, max_steps=stepsize.max_steps,
                  eps=eps)
    x64 = _check_switches(stepsize.method, x64, stepsize.check_passivity, f)
    dtype = "float64" if x64 else "float32"
    plant, gains, controller, lanes = _resolve_law(plant, gains, controller, f, flags)
    horizon = _resolve_horizon(t_final, dt, save_every, f, flags)
    eps = real(f("eps"), eps, positive=True, example=0.05)
    stepsize = _resolve_steps(stepsize, horizon, dtype, f)
    if controller is not None:
        gains = None
    return SolveConfig(plant, gains, horizon, stepsize, eps, x64, lanes, controller)
