"""The options of ``jaxsleigh tune`` (`jaxsleigh.cli.tune` registers the subcommand): its option groups and its help."""
from __future__ import annotations

import argparse

from .common import add_model_options, add_progress_option, add_sampler_options, add_tolerance_options, number, whole

__all__ = ["EPILOG", "add_tune_options"]

EPILOG = """\
The objective is the soft time spent outside |q| <= 0.05 (a smooth surrogate of the convergence
time T_0.05), averaged over --batch starts with |x|, |y| <= 3 and |theta0| in (0.3, pi), integrated
by adaptive RK4 in the w chart with gradients through the integrator. Every candidate is checked:
a training lane or a guard start (|theta0| = 0.05, 0.1) that fails or runs out of its step budget,
a non-finite loss or gradient, or a training start that needs more than --probe-budget steps to
simulate 100 s (faster convergence makes the loop stiffer after it) rejects it and the optimiser
backtracks; the best valid gains that also pass a final 100 s check of every training and guard
start with the accurate engine are written. --validate N then measures T_0.05 with the accurate
ensemble engine on N held-out starts (seed --seed + 1000) for the initial and the tuned gains.

--energy-budget E adds a budget on the batch's geometric-mean control energy int |u|^2 dt
(augmented Lagrangian). With a budget, train over the validation horizon and let lanes run on after
converging (--t-final 100 --stop-fraction 0.001), so the energy spent while settling counts; there
the paper's gains spend about 19 on 32 starts. Tuned gains that do not meet the budget are written
all the same, with "energy_budget_met": false, and the command says so and exits 3.
--pareto N computes N such tunings for budgets from a quarter of the paper's gains' training energy
to twice the 'tuned' preset's (or --budgets LO:HI), re-evaluates each on --validate held-out starts
(seed --seed + 1000) with the accurate engine over 100 s and writes front.json: per point the gains
(gains-file format) and median T_0.05 +- s.e., converged fraction, median energy, median peak |u|,
mean adaptive steps; with the paper's and 'tuned' gains as references and, with --baseline, a
random search spending the same number of objective evaluations.

--search replaces the gradient descent by a derivative-free search (CMA-ES)
on the figures the accurate engine reports over 100 s: the shortest median T_0.05 on --batch training
starts subject to median control energy <= --energy-margin x the --gains' on the same starts (or
--energy-budget E, an absolute median energy; --energy-percentiles 50,75,90: at each of those
percentiles), no fewer converged and no start failing or crossing theta = 0. Each generation's
--population candidates run as one ensemble (gains per trajectory). Use --atol 1e-8 when effort
matters: float32's default 1e-6 does not resolve energy spent after settling. The 'balanced' preset
is its result (experiments/studies/balanced_search.py: two such searches in a row, at --atol 1e-8 with
--energy-percentiles 50,75,90).

--controller NAME (a law of jaxsleigh controllers), --saturation U and --sample-period TS tune that
law's gains by Adam (--steps, --lr, --batch, --energy-budget as above; Ctrl-C keeps the best law so far
and --resume continues) and write the tuned law: its every parameter and the actuator it was tuned
behind, to give with --controller FILE.json; the paper's law behind an actuator is written as a gains
file (--gains FILE.json; give --saturation / --sample-period again).

Every mode owns its --out while it runs: another run on the same --out is refused (exit code 5, naming
the run that holds it). Ctrl-C keeps the progress (the best so far in --out, the state in
FILE.json.ckpt.npz; a front's finished points in --out) and the same command with --resume continues
to the result an uninterrupted run writes.

examples:
  jaxsleigh tune --out gains.json
  jaxsleigh tune --search --out mine.json --steps 60 --energy-percentiles 50,75,90 --atol 1e-8 --history search.npz
  jaxsleigh tune --out eco.json --energy-budget 19 --t-final 100 --stop-fraction 0.001 --n-attempts 6000
  jaxsleigh tune --pareto 5 --out front.json --plot front.png --baseline --t-final 100 --stop-fraction 0.001
  jaxsleigh tune --out gains.json --tune k,D_hat --steps 60 --history history.npz
  jaxsleigh tune --out robust.json --robust --steps 200
  jaxsleigh simulate --ic=-3,-2,pi/8 --gains gains.json --out run.npz
"""


def _percentiles(text: str) -> tuple:
    """argparse ``type=`` of ``--energy-percentiles``: distinct numbers in (0, 100), comma-separated."""
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        vals = ()
    if not vals or len(set(vals)) != len(vals) or not all(0 < v < 100 for v in vals):
        raise argparse.ArgumentTypeError(f"--energy-percentiles must be distinct percentiles in (0, 100), comma-"
                                         f"separated, got {text!r} (e.g. --energy-percentiles 50,75,90)")
    return vals


def _add_optimiser_options(p) -> None:
    """--steps, --batch, --seed, --lr, --tune, --robust, --mode."""
    g = p.add_argument_group("optimiser")
    g.add_argument("--steps", type=whole("--steps", "150"), default=None, metavar="N",
                   help="optimiser iterations (default 150; with --search: generations, default 100)")
    g.add_argument("--batch", type=whole("--batch", "256"), default=None, metavar="B",
                   help="training starts (default 256; with --search 128)")
    g.add_argument("--seed", type=whole("--seed", "0", minimum=0, maximum=2**62), default=0, metavar="S",
                   help="seed of the training starts (default 0)")
    g.add_argument("--lr", type=number("--lr", "0.05"), default=0.05, metavar="LR",
                   help="peak learning rate of Adam on the log-gains (default 0.05)")
    g.add_argument("--tune", default="L,k,D_hat", metavar="L,k,D_hat",
                   help="the gains to tune, a comma-separated subset of L, k, D_hat; the others stay at "
                        "their --gains values (default: all)")
    g.add_argument("--robust", action="store_true",
                   help="average the objective over sampled plants (m in 1-4, J in 0.5-2, l in 0.5-1.5, "
                        "Coulomb / viscous / no damping) instead of the --params/--damping plant")
    g.add_argument("--mode", choices=["forward", "reverse"], default="forward",
                   help="gradients: forward mode (default; fastest for the 7 gain parameters) or reverse "
                        "mode with checkpointed segments")


def _add_objective_options(p) -> None:
    """The gradient tuner's surrogate: horizon, steps, budgets."""
    h = p.add_argument_group("objective")
    h.add_argument("--t-final", type=number("--t-final", "30"), default=30.0, metavar="T",
                   help="training horizon in seconds (default 30)")
    h.add_argument("--dt", type=number("--dt", "0.01"), default=0.01, metavar="DT",
                   help="first step of the adaptive RK4; steps never exceed 10 DT (default 0.01)")
    h.add_argument("--n-attempts", type=whole("--n-attempts", "4000"), default=4000, metavar="N",
                   help="budget of attempted steps per lane; a lane that needs more rejects the candidate "
                        "(default 4000)")
    h.add_argument("--probe-budget", type=whole("--probe-budget", "100000"), default=100000, metavar="N",
                   help="most attempted steps any training start may need to simulate 100 s with the tuned "
                        "gains (the engine's default budget is 200180; default 100000)")
    h.add_argument("--stop-fraction", type=number("--stop-fraction", "0.001"), default=0.5, metavar="F",
                   help="a training lane stops once |q| <= F x 0.05 (default 0.5; 0.001 lets lanes run on so the "
                        "energy spent while settling counts)")
    h.add_argument("--energy-budget", type=number("--energy-budget", "29"), default=None, metavar="E",
                   help="budget on the training batch's geometric-mean control energy int |u|^2 dt "
                        "(default: none, the fastest gains the step budget allows)")


def _add_search_options(p) -> None:
    """--search and what only it uses."""
    d = p.add_argument_group("derivative-free search (the balanced preset's method)")
    d.add_argument("--search", action="store_true",
                   help="instead of gradient descent on the surrogate, search (CMA-ES) for the gains with the "
                        "shortest median T_0.05 on the training starts whose median control energy is at most "
                        "--energy-margin x the --gains' (or --energy-budget), with no fewer converged and no start "
                        "failing or crossing theta = 0, all measured by the accurate engine over 100 s")
    d.add_argument("--population", type=whole("--population", "16", minimum=2), default=16, metavar="P",
                   help="candidates per generation, run together in one ensemble (default 16)")
    d.add_argument("--energy-margin", type=number("--energy-margin", "0.95"), default=0.95, metavar="F",
                   help="energy budget as a fraction of the starting gains' median energy on the training "
                        "starts (default 0.95: room for the median's sampling noise on other starts)")
    d.add_argument("--energy-percentiles", type=_percentiles, default=(50.0,), metavar="P,P,...",
                   help="hold the energy within --energy-margin x the --gains' at each of these percentiles over the "
                        "training starts, not only the median (e.g. 50,75,90: the energy is bimodal, and a median "
                        "budget lets the upper half grow several-fold)")
    d.add_argument("--frontier", default=None, metavar="FILE.npz",
                   help="minimise the median gap to the optimum instead of the median time: T_0.05 / T*(E), the "
                        "law's time over the earliest rest in the ball that its own energy could buy, against the "
                        "energy-optimal frontier in FILE (written by 'jaxsleigh optimum'), on FILE's starts, under the "
                        "same energy budget")


def _add_pareto_options(p) -> None:
    """--pareto and what only the front uses."""
    f = p.add_argument_group("Pareto front")
    f.add_argument("--pareto", type=whole("--pareto", "6"), default=None, metavar="N",
                   help="compute N points (at most 100) of the time-effort front instead of one set of gains")
    f.add_argument("--front-method", choices=["warm", "vmap"], default="warm",
                   help="warm: budgets in turn, each from the last point's gains (default); vmap: every budget "
                        "at once, the optimiser vmapped over budgets")
    f.add_argument("--budgets", default=None, metavar="LO:HI",
                   help="energy budgets (geometric spacing; default: paper's training energy / 4 to tuned's x 2)")
    f.add_argument("--warm-steps", type=whole("--warm-steps", "40"), default=None, metavar="N",
                   help="iterations of each warm-started point after the first (default --steps / 2)")
    f.add_argument("--baseline", action="store_true",
                   help="also run a random search with the same number of objective evaluations")
    f.add_argument("--plot", default=None, metavar="FILE.png", help="draw the front")


def add_tune_options(p) -> None:
    """Every option of ``jaxsleigh tune`` on its parser ``p``."""
    p.add_argument("--out", required=True, metavar="FILE.json",
                   help="output gains file (with --pareto: the front's JSON file); no other run may write it "
                        "at the same time")
    p.add_argument("--resume", action="store_true",
                   help="continue an interrupted run from its checkpoint FILE.json.ckpt.npz (same options; with "
                        "--pareto and --front-method warm: from the finished points kept in FILE.json)")
    for add in (_add_optimiser_options, _add_objective_options, _add_search_options, _add_pareto_options):
        add(p)
    add_model_options(p)
    add_sampler_options(p, seed=False)          # --seed (above) also seeds the measurement noise
    p.add_argument("--history", default=None, metavar="FILE.npz",
                   help="also write the history (loss, gains, gradient norm per iteration)")
    p.add_argument("--validate", type=whole("--validate", "256", minimum=0), default=256, metavar="N",
                   help="held-out starts for the final check with the accurate engine (0: skip; default 256)")
    # --rtol, --atol: the accurate engine's, in the held-out check (every mode) and in every run of --search
    add_tolerance_options(p.add_argument_group("the accurate engine's tolerances (held-out check; --search)"))
    add_progress_option(p)
