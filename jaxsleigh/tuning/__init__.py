r"""Differentiable tuning of the controller's gains: objective, parametrisation, gradients, optimiser.

**Objective.** The hard convergence time \(T_\epsilon\) (first time after which
\(|q| \le \epsilon\) holds) is piecewise constant in the gains. Its smooth surrogate is the time
a trajectory spends outside the ball, weighted by a soft indicator that is exactly zero inside it:

\[ S = \int_0^{T} \phi\big(\log(|q(t)| / \epsilon) / \tau\big)\,dt, \qquad \phi(u) = 1 - e^{-u^2}\ (u > 0), \quad \phi(u) = 0\ (u \le 0), \]

averaged over a batch of starts (``tau`` is the temperature: the band
\(\epsilon < |q| \lesssim \epsilon e^{2\tau}\) where the indicator rises). A lane stops once
\(|q| \le\) ``stop_fraction`` \(\cdot\,\epsilon\): after that the closed loop only gets stiffer
(the injected damping \(k / w_1^2\) grows without bound as \(\theta \to 0\)), and since
\(\phi = 0\) there the stopped integral has the same value and exact gradient as the full one as
long as the trajectory stays in the ball (validation with the accurate engine checks that it does).

**Effort.** The same scan integrates the control energy \(E = \int |u|^2 dt\) by the engine's quadrature (the
`jaxsleigh.integrate.observers.ControlEffort` observer: each accepted step's RK4 weights over its stages, so a lane's
\(E\) is the one `jaxsleigh.run_ensemble` reports for the same steps; differentiable), and the loss may carry a
budget on the batch's geometric-mean energy, enforced by an augmented Lagrangian (`objective` argues the choice):
minimise the soft time subject to "effort <= budget". `pareto` sweeps the
budget (the time-effort front). The ``balanced`` preset answers a question the surrogate does not
weigh directly (the fastest *median* \(T_{0.05}\) at no more *median* energy than the paper's gains'):
`search` optimises those medians themselves, derivative-free, on the accurate engine.

**Numerical safety.** Lanes are integrated in the w chart by the engine's adaptive RK4
(`jaxsleigh.integrate.stepper.attempt`: steps that cross \(\theta = 0\), go non-finite or increase
\(H_d\) are rejected and retried smaller) with a fixed budget of attempts per lane, as one
differentiable ``lax.scan``. A lane that does not reach its horizon within the budget (too stiff)
or fails is charged the rest of the horizon and makes the candidate *invalid*. A differentiable
term keeps unconverged trajectories away from the singular set, where the loop is stiff:

\[ B = \int_0^{T} \phi(\cdot)\, \max\big(0, \log(\theta_b / |\theta|)\big)^2\,dt . \]

**Integration cost.** Faster convergence has a price after convergence: as \(\theta \to 0\) the
closed loop's eigenvalues grow like \(k / \theta^2\) and \(\sqrt{L} / \theta\), and with stronger
gains \(\theta\) gets small sooner, so the steps needed for a fixed horizon grow quickly (left
alone, the optimiser drives the gains up until 100 s need ~10^5 adaptive steps and the engine's
default budget runs out). Each candidate is therefore also *probed*: the training starts that need
the most steps (an active set, re-found every ``probe_refresh`` accepted candidates by running the
whole training batch) are integrated over the validation horizon (100 s) by the accurate engine
with a budget of ``probe_budget`` attempted steps each (half the engine's default); a start that
needs more makes the candidate invalid. Without an effort budget the tuner in effect minimises the soft
convergence time subject to "every training start needs at most ``probe_budget`` steps for 100 s"
(the ``tuned`` preset is shaped by that limit); with one, the probe stays as a safety guard and the
history records whether it was active (``probe_active``; ``settings["probe_at_result"]`` for the
returned gains).

The optimiser loop (`tune`) rejects every invalid candidate (non-OK lane, non-finite loss or
gradient, on the training batch and on a *guard* set of starts with \(|\theta_0|\) down to
0.05, failed probe), backtracks to the last valid point with a halved step, and returns the best
valid gains that also pass a final check with the accurate engine over the validation horizon.

**Parametrisation** (always admissible, see `GainParams`):
\(L = e^{\ell}\), \(k = e^{\kappa}\), \(\hat D = C C^\top + \delta I\) with
\(C = \begin{bmatrix} e^{c_0} & 0 \\ c_1 & e^{c_2} \end{bmatrix}\).

**Gradients** go through the integrator (the adaptive step sizes are ``stop_gradient``'ed in the
stepper, so this is the exact derivative of the discrete map with its step sequence frozen):
reverse mode with ``jax.checkpoint`` over segments of the scan (memory grows with the number of
segments plus one segment's residuals, not with the number of steps) or forward mode
(``jax.jacfwd``, one tangent per free parameter, memory independent of the number of steps).
``experiments/performance/bench_gradients.py`` measures both: for the 7 gain parameters, 10^4 steps and 256
starts (float32, 2 CPU cores), forward mode took 2.0 s and 0.4 MB of XLA temporaries against
3.2 s and 20 MB for checkpointed reverse mode (5.3 s and 1.8 GB without checkpointing), so
forward mode is the default. Reverse mode's cost does not grow with the number of parameters;
it wins from roughly a dozen of them.

**Modules** (one concept each): `params` (parametrisation),
`starts` (samplers of starts and plants), `objective`
(the objective and its scan), `gradients`, `optimizer`
(the loop, backtracking as an optax wrapper), `probes` (safety guards),
`checkpoint`, `history`, `law_file` (a tuned law on disk),
`validation`, `pareto` (the time-effort front), `cmaes` (CMA-ES, ask / tell) and
`cma_search` (derivative-free search of the gains on the accurate engine's median figures under an energy budget:
where the ``balanced`` preset comes from), `budget` (laws tuned to one energy budget, for comparisons at equal
effort).
Everything public is re-exported here.
"""
from __future__ import annotations

from .checkpoint import TuningInterrupted
from .gradients import GRADIENT_MODES, make_value_and_grad
from .history import load_history, save_history
from .objective import (TRAINING_STEPSIZE, LaneSummary, LossConfig, TrainingSet, make_training_set, objective,
                        soft_convergence, traced_loss)
from .optimizer import BacktrackState, TuneConfig, TuneHistory, TuneResult, backtracking, make_optimizer, tune
from .pareto import (FRONT_METHODS, Front, FrontPoint, budgets_between, default_budgets, evaluate_front, front_dict,
                     load_front, pareto_front, point_gains, random_search, save_front, training_energy)
from .law import LawTuneResult, gain_names, tune_law
from .budget import EqualEnergy, tune_to_budget
from .law_file import load_controller_record, save_law
from .cma_search import PopulationFigures, SearchConfig, SearchResult, evaluate_population, search
from .params import (D_FLOOR, TUNABLE, GainParams, gains_from_params, merge_params, params_from_gains, parse_tune,
                     split_params)
from .starts import (PlantDistribution, UniformStarts, draw_starts, guard_starts, sample_plants, sample_starts,
                     validation_plants)
from .validation import Validation, markdown_table, validate, validation_dict

__all__ = [
    "GainParams", "TUNABLE", "D_FLOOR", "params_from_gains", "gains_from_params", "parse_tune", "split_params",
    "merge_params",
    "UniformStarts", "draw_starts", "sample_starts", "guard_starts", "PlantDistribution", "sample_plants",
    "validation_plants",
    "LossConfig", "TRAINING_STEPSIZE", "traced_loss", "LaneSummary", "TrainingSet", "make_training_set",
    "soft_convergence", "objective",
    "make_value_and_grad", "GRADIENT_MODES",
    "TuneConfig", "TuneHistory", "TuneResult", "TuningInterrupted", "BacktrackState", "backtracking",
    "make_optimizer", "tune", "save_history", "load_history",
    "Validation", "validate", "markdown_table", "validation_dict",
    "FRONT_METHODS", "Front", "FrontPoint", "training_energy", "default_budgets", "budgets_between", "pareto_front",
    "random_search", "evaluate_front", "front_dict", "save_front", "load_front", "point_gains",
    "SearchConfig", "SearchResult", "PopulationFigures", "evaluate_population", "search",
    "LawTuneResult", "tune_law", "gain_names", "save_law", "load_controller_record",
    "EqualEnergy", "tune_to_budget",
]
