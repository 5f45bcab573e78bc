"""jaxsleigh: differentiable simulation of the Chaplygin sleigh under the discontinuous
energy-shaping controller of Ferguson, Donaire and Middleton.

Importing it changes no JAX setting and does not start JAX. The first run asks JAX for one CPU device
per core, if JAX has not started by then (`jaxsleigh.cores`); `enable_compilation_cache` turns on the
persistent compilation cache the command line uses, so that a later process compiles nothing again.
"""
from . import cores  # noqa: F401
from .cache import enable_compilation_cache  # noqa: F401
from .studies.basin import BasinResult, BasinStarts, grid_starts, load_basin, run_basin, sample_starts, save_basin
from .model.closed_loop import (ClosedLoop, closed_loop_hamiltonian, closed_loop_hamiltonian_w, dissipation_w,
                          state_from_w, state_to_w, vector_field, vector_field_w)
from .model.paper_law import control, control_w, measured_velocity, potential
from .model.damping import CoulombDamping, CustomDamping, NoDamping, ViscousDamping
from .studies.ensemble import EnsembleResult, run_ensemble
from .model.params import (Gains, PlantParams, gains, load_gains, paper_gains, paper_plant, plant_params,
                     save_gains)
from .model.shaped_law import ShapedGains, load_shaped, shaped_from_gains, shaped_gains
from .studies.simulate import Solution, simulate
from .integrate.solve import SolveOutput, solve
from .integrate.stepsize import StepSizeController
from .studies.options import RunOptions, SaveAt
from .studies.audit import Audit
from .status import Status
from .studies.optimum import OptimumOptions, OptimumResult, load_optimum, optimum, save_optimum
from .studies.sweep import SweepResult, load_sweep, save_sweep, sweep
from .model import charts, controller  # noqa: F401
from . import errors  # noqa: F401
from .integrate import observers  # noqa: F401

__version__ = "0.4.0"
