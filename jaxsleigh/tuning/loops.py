r"""The two loops every tuner runs: `descend` around an optax optimiser, and `ask_tell` around an evolution strategy.

Each tuner brings its own pieces, in the style of optax (one small loop around small transformations): how a
candidate is evaluated, what the tuner records of it (validity and backtracking, robust plant groups, the
integration-cost probe, the history row, the best point, the multipliers of an augmented Lagrangian), how the
optimiser steps, when the run stops, what a checkpoint holds, and what it reports (progress bars, callbacks). The
loops only fix the order, which is what makes an interrupted run that resumes from its checkpoint end where an
uninterrupted run does:

* `descend`: evaluate candidate ``it`` at the current parameters, observe it, step, decide whether to stop, save
  the state the next iteration starts from, report;
* `ask_tell`: ask for a generation, evaluate it, tell the strategy the scores, observe, save, report.
"""
from __future__ import annotations

from typing import Any, Callable, Optional

import optax

__all__ = ["descend", "ask_tell", "step_if"]


def descend(evaluate: Callable, observe: Callable, step: Callable, params, state, *, steps: int, start: int = 0,
            stopped: bool = False, stop: Optional[Callable] = None, save: Optional[Callable] = None,
            report: Optional[Callable] = None) -> tuple[Any, Any, bool]:
    """Iterations ``start`` to ``steps`` of a gradient tuner, from ``params`` and the optimiser's ``state``.

    Per iteration ``it``, in this order:

    * ``out = evaluate(it, params)``: the candidate's evaluation (typically ``((value, aux), grad)``);
    * ``verdict = observe(it, params, state, out)``: the tuner's bookkeeping of the candidate (is it valid, its
      history row, the best point, a multiplier update); the verdict is what the step needs;
    * ``params, state = step(params, state, out, verdict)``: the optimiser's update (which may decline to move, or
      backtrack, on the verdict);
    * ``stopped = stop(params, state, verdict)``: whether the run ends after this iteration (default: never);
    * ``save(it + 1, params, state, stopped)``: the checkpoint of the state iteration ``it + 1`` starts from;
    * ``report(it, verdict)``: progress bars and callbacks.

    A run ``stopped`` already (resumed from the checkpoint of a run that stopped) does no iteration. Returns
    ``(params, state, stopped)``.
    """
    for it in range(int(start), int(steps)):
        if stopped:
            break
        out = evaluate(it, params)
        verdict = observe(it, params, state, out)
        params, state = step(params, state, out, verdict)
        stopped = bool(stop(params, state, verdict)) if stop is not None else False
        if save is not None:
            save(it + 1, params, state, stopped)
        if report is not None:
            report(it, verdict)
    return params, state, stopped


def step_if(opt: optax.GradientTransformation) -> Callable:
    """The step piece of a descent that stops at its first bad candidate: ``opt``'s update with the candidate's
    gradient (``out[1]``) where the verdict is true, none where it is false (no step is taken with a gradient that
    is not to be trusted; the stopping rule then ends the run)."""

    def step(params, state, out, verdict):
        if not verdict:
            return params, state
        updates, state = opt.update(out[1], state, params)
        return optax.apply_updates(params, updates), state

    return step


def ask_tell(state, ask: Callable, evaluate: Callable, tell: Callable, *, done: Callable,
             observe: Optional[Callable] = None, save: Optional[Callable] = None,
             report: Optional[Callable] = None):
    """Generations of an ask/tell strategy from its ``state`` until ``done(state)``.

    Per generation, in this order:

    * ``xs, ys = ask(state)``: the candidates (and the steps the strategy drew them by);
    * ``scores, info = evaluate(state, xs)``: one score per candidate (lower is better) and whatever else the tuner
      measured; fewer scores than candidates means the evaluation budget ran out inside the generation, which is then
      not told and ends the run;
    * ``state = tell(state, ys, scores)``;
    * ``observe(state, xs, scores, info)``: the tuner's bookkeeping (best candidates, history);
    * ``save(state)``: the checkpoint; ``report(state)``: progress.

    Returns the last state.
    """
    while not done(state):
        xs, ys = ask(state)
        scores, info = evaluate(state, xs)
        if len(scores) < len(xs):
            break
        state = tell(state, ys, scores)
        if observe is not None:
            observe(state, xs, scores, info)
        if save is not None:
            save(state)
        if report is not None:
            report(state)
    return state
