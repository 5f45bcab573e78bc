"""A tuning run that owns its output: the life of a run of any tuner, from its first check to its last file.

Every tuner writes a file that the other commands read back: `tune_run` (gradient descent on the paper's gains,
`jaxsleigh.tuning.tune`) and `search_run` (CMA-ES on the accurate engine's figures, `jaxsleigh.tuning.search`) a gains
file, `law_run` (any other law, or the paper's behind an actuator, `jaxsleigh.tuning.tune_law`) a tuned law's file,
`front_run` (`jaxsleigh.tuning.pareto_front`) a front. The four share one lifecycle, `TuningRun`, the
`jaxsleigh.files.run.Run` of every run that writes with a tuner's checkpoint and history:

1. **Before any work** the output, the history (if asked for) and the checkpoint ``OUT.ckpt.npz`` next to the output
   can be written, and the output is claimed: while another live run writes the same file, this one is refused
   with `jaxsleigh.errors.RunLockedError` naming that run (host, pid, start), so two runs never both write it. A
   checkpoint left by an interrupted run is refused without ``resume=True`` (nothing is
   written over it), ``resume=True`` without one, and a resume whose options differ from those the checkpoint
   records names the first that differs, with both values.
2. **During the work** the tuner writes its checkpoint, atomically, after every step (a front computed point by
   point: the output itself after every point, marked ``"interrupted": true``).
3. **Ctrl-C** writes the best result so far to the output (marked ``"interrupted": true``) with the history, keeps
   the checkpoint, and returns a `RunOutcome` with ``interrupted=True``; the same call with ``resume=True`` continues
   to the file an uninterrupted run writes (the same numbers, bit for bit).
4. **At the end** the output records how the result was found, the history is written, the checkpoint removed, and
   the held-out check (`HeldOut`: the initial and the found gains measured by the accurate engine on starts that the
   tuner never saw) is written into the output. The claim is released however the run ends.

Example::

    from jaxsleigh.tuning import TuneConfig
    from jaxsleigh.tuning.runs import TuningRun, tune_run

    outcome = tune_run(TuningRun("gains.json", history="history.npz"), "paper", config=TuneConfig(steps=60))
    if outcome.interrupted:           # Ctrl-C: gains.json holds the best so far; this continues the run
        outcome = tune_run(TuningRun("gains.json", history="history.npz", resume=True), "paper",
                           config=TuneConfig(steps=60))
"""
from __future__ import annotations

import contextlib
import json
import math
import time
from pathlib import Path
from typing import Any, NamedTuple, Optional

import numpy as np

from ..files.checkpoint import differences
from ..files.run import PYTHON_WORDS, Run, Words
from ..model.params import as_plant, gains_to_dict, load_gains, save_gains
from ..studies.config import plant_to_dict
from ..validate import check_memory, whole, writable_path
from .checkpoint import TuningInterrupted, checkpoint_options
from .history import history_wall, save_arrays
from .cma_search import NoFeasibleCandidate, SearchConfig
from .objective import LossConfig, training_max_step
from .optimizer import TuneConfig, check_sizes
from .starts import UniformStarts, draw_starts
from .law import law_attempts
from .law_file import save_law
from .validation import validation_dict
from .pareto import finished_points, front_settings, load_front

__all__ = ["TuningRun", "RunOutcome", "HeldOut", "tune_run", "search_run", "law_run", "front_run"]


class HeldOut(NamedTuple):
    """The check after a run: ``n`` starts drawn by `UniformStarts` from ``seed`` (starts the tuner never saw), each
    integrated over 100 s by the accurate engine with ``stepsize`` (a `jaxsleigh.StepSizeController`; ``None``: its
    defaults). ``n = 0``: no check (a front still records the settings)."""

    n: int = 256
    seed: int = 1000
    stepsize: Any = None

    def check(self, name: str = "held_out.n") -> HeldOut:
        """Self, or a `ValueError` naming ``name`` (the keyword, or ``--validate``) when the check's ``n`` starts
        would not fit in memory: refused before the run, not after it (`jaxsleigh.validate.check_memory`)."""
        n = whole(name, self.n, minimum=0, example=256)
        check_memory(n, name, fix=f"check on fewer starts ({name} 256 is the default; 0 skips the check)")
        return self

    def starts(self) -> np.ndarray:
        return UniformStarts()(np.random.default_rng(self.seed), self.n)

    def tolerances(self) -> dict:
        """``{"rtol": .., "atol": ..}`` as given (``None``: the engine's default for the dtype)."""
        s = self.stepsize
        return {"rtol": None if s is None else s.rtol, "atol": None if s is None else s.atol}


class RunOutcome(NamedTuple):
    """What a tuning run did.

    Attributes:
      result: the tuner's result (`TuneResult`, `SearchResult`, `LawTuneResult` or `Front`); after Ctrl-C the best so
        far (``None``: nothing valid yet, and nothing was written).
      written: the files written, the output first.
      interrupted: Ctrl-C stopped the run; its checkpoint is kept and ``resume=True`` continues it.
      wall_s: seconds the tuner ran (the held-out check not counted; recorded in the sidecar ``FILE.run.json``,
        not in the files written).
      held_out: ``{label: Validation}`` of the held-out check (e.g. ``initial`` and ``tuned``; ``{}`` without one).
      energy: the result's training energy where the run had an energy budget (else ``None``);
      energy_budget_met: whether it is within that budget (``None`` without one).
    """

    result: Any
    written: tuple
    interrupted: bool
    wall_s: float
    held_out: dict
    energy: Optional[float] = None
    energy_budget_met: Optional[bool] = None


class TuningRun(Run):
    """A tuning run's claim on its output ``out`` and the files beside it (module docstring): a
    `jaxsleigh.files.run.Run` (its lock, its resume decision) with a tuner's checkpoint and history.

    Args:
      out: the file the run writes (a gains file, a tuned law's file or a front).
      history: also write the history there (``.npz`` is appended to a name without it); ``None``: none.
      resume: continue the interrupted run whose checkpoint (`checkpoint`; a front: ``out`` itself) is there.
      options: what determines the run, ``{name: value}`` in the order a refused resume names them: recorded in the
        checkpoint, and a resume with another value of any of them is refused naming the first.
      command: the command recorded in the files written (``None``: not known).
      words: how the refusals name ``resume``, ``out`` and the options (`jaxsleigh.files.runner.Words`: Python's
        keywords by default; the command line gives its flags).
    """

    def __init__(self, out, *, history=None, resume: bool = False, options: Optional[dict] = None,
                 command: Optional[list] = None, words: Words = PYTHON_WORDS):
        h = None if history is None else Path(history)
        self._history_given = h
        self.history = h if h is None or h.suffix == ".npz" else h.with_name(h.name + ".npz")
        # as they read back from the checkpoint's JSON (tuples as lists)
        self.options = None if options is None else json.loads(json.dumps({str(k): v for k, v in options.items()},
                                                                          default=str))
        self.command = command
        # one process's run, no other shares its output; known options make it the run's settings, so that the same
        # run started twice is told it is in progress
        super().__init__(out, settings=None if self.options is None else [str(Path(out)), self.options],
                         resume=resume, words=words)

    @property
    def checkpoint(self) -> Path:
        """``OUT.ckpt.npz``: where the tuner keeps its whole state while it runs."""
        return self.out.with_name(self.out.name + ".ckpt.npz")

    @contextlib.contextmanager
    def owned(self, what: str, *, checkpointed: bool = True, also=()):
        """Hold the output for the body of a ``with``: every output (and ``also``) writable, the output claimed, the
        checkpoint matching ``resume`` (``what`` names the run in the refusals, e.g. ``"search"``); released however
        the body ends."""
        named = "output file" if self.words.out == PYTHON_WORDS.out else f"{self.words.out} file"
        writable_path(self.out, named)          # not a folder, device or named pipe, nor any file beside it
        if self._history_given is not None:
            writable_path(self._history_given, "history file", suffix=".npz")
        for p in (*(self.checkpoint,) * checkpointed, *also):
            if p is not None:
                writable_path(p)
        with self:
            if checkpointed:
                self._check_checkpoint(what)
            yield self

    def finished(self) -> None:
        """The run is complete: its checkpoint goes."""
        self.checkpoint.unlink(missing_ok=True)

    def _check_checkpoint(self, what: str) -> None:
        ckpt = self.checkpoint
        self.refuse_progress(f"{str(ckpt)!r} holds the state of an earlier, interrupted {what} for {str(self.out)!r}"
                             if ckpt.exists() else None, afresh="delete it",
                             missing=f"no checkpoint {str(ckpt)!r} to continue from")
        if self.resume and self.options is not None:
            self._check_options(checkpoint_options(ckpt))

    def _check_options(self, old: Optional[dict]) -> None:
        """Refuse a resume with another value of an option than the checkpoint's, naming the first that differs (a
        checkpoint that records none is left to the tuner's own check of its settings)."""
        if old is None:
            return
        old = {k.lstrip("-").replace("-", "_"): v for k, v in old.items()}     # earlier versions recorded flags
        diffs = differences({k: old.get(k) for k in self.options}, self.options, show=self.words.shown, sort=False,
                            flat=True)
        if diffs:
            raise ValueError(f"{diffs[0]}: rerun with the same options and {self.words.resume} to continue it, or "
                             f"choose another {self.words.out} to start afresh")


def as_run(run) -> TuningRun:
    """A `TuningRun`, or one for the output path ``run``."""
    return run if isinstance(run, TuningRun) else TuningRun(run)


# ---------------------------------------------------------------------------------------------
# the four tuners
# ---------------------------------------------------------------------------------------------

def tune_run(run, gains0="paper", *, config: TuneConfig = TuneConfig(), loss: LossConfig = LossConfig(), tune=None,
             plant=None, robust=None, x64: bool = False, progress: Any = None,
             held_out: Optional[HeldOut] = None) -> RunOutcome:
    """`jaxsleigh.tuning.tune` (the arguments are its own) as a run that owns ``run.out`` (a `TuningRun` or a
    path): a gains file that records how the gains were found (with ``loss.energy_budget``: the training energy and
    whether it meets the budget), the `TuneHistory`, then the ``held_out`` check of the initial and the tuned gains
    (``initial``, ``tuned``) written into it. After Ctrl-C the best valid gains so far, not re-checked by the accurate
    engine. Raises what `tune` raises (``RuntimeError``: no candidate passed the final check)."""
    from .. import tuning as tu

    run, names = as_run(run), tu.parse_tune(tune)

    def budget(res) -> dict:
        energy = float(res.history.energy[res.best_iteration])
        met = _budget_met(loss.energy_budget, energy)
        return {} if met is None else dict(energy_budget=float(loss.energy_budget), training_energy=energy,
                                           energy_budget_met=met)

    def write(res, interrupted: bool = False, **fields) -> tuple:
        if interrupted:          # the best valid gains so far
            save_gains(res.gains, run.out, how="jaxsleigh tune, INTERRUPTED: the best valid candidate so far, not "
                       "re-checked with the accurate engine", command=run.command, interrupted=True,
                       best_loss=res.best_loss, best_iteration=res.best_iteration,
                       iterations_run=res.settings["iterations_run"])
        else:
            save_gains(res.gains, run.out, how=f"jaxsleigh tune: {res.settings['method']}", command=run.command,
                       tuned=list(names), initial_gains=gains_to_dict(res.initial), initial_loss=res.initial_loss,
                       best_loss=res.best_loss, best_iteration=res.best_iteration,
                       iterations_run=res.settings["iterations_run"], seed=config.seed, batch=config.batch,
                       dtype=res.settings["dtype"], plant="sampled (robust)" if robust is not None else
                       plant_to_dict(as_plant(plant)), objective=res.settings["loss"], **fields)
        return (run.out, *_history(run, lambda p: tu.save_history(res.history, p)))

    return _tuner_run(run, "tuning run", lambda: tu.tune(
        gains0, config=config, loss=loss, tune=names, plant=None if robust is not None else plant, robust=robust,
        x64=x64, progress=progress, checkpoint=run.checkpoint, resume=run.resume, options=run.options), write,
        lambda r: _held_out_rows(r.initial, r.gains, plant, x64, held_out, "tuned"), held_out, budget)


def search_run(run, gains0="paper", *, config: SearchConfig = SearchConfig(), reference=None,
               energy_budget: Optional[float] = None, tune=None, plant=None, x64: bool = False, stepsize=None,
               progress: Any = None, held_out: Optional[HeldOut] = None, frontier=None) -> RunOutcome:
    """`jaxsleigh.tuning.search` (the arguments are its own; ``reference`` defaults to ``gains0``) as a run that owns
    ``run.out``: a gains file with the training figures of the gains found and of the reference, the history (one
    row per generation), then the ``held_out`` check (``initial``, ``searched``) written into it. A finished or
    interrupted search continues with ``resume=True`` and more ``config.generations``. After Ctrl-C the best
    feasible gains so far (not checked on the guard starts). Raises `NoFeasibleCandidate` when no candidate was
    feasible, after writing the history (the checkpoint is kept: more generations continue the run)."""
    from .. import tuning as tu

    run, names = as_run(run), tu.parse_tune(tune)
    what = ("median gap to the optimum T_0.05 / T*(E)" if config.objective == "gap" else "median T_0.05")

    def work():
        try:
            return tu.search(gains0, config=config, reference=gains0 if reference is None else reference,
                             energy_budget=energy_budget, tune=names, plant=plant, x64=x64, stepsize=stepsize,
                             progress=progress, checkpoint=run.checkpoint, resume=run.resume, options=run.options,
                             frontier=frontier)
        except NoFeasibleCandidate as e:          # finished: its history is kept, and its checkpoint
            history = e.history
            _history(run, lambda p: save_arrays(p, history))
            raise

    def write(res, **fields) -> tuple:
        save_gains(res.gains, run.out, how=f"jaxsleigh tune --search: CMA-ES on the accurate engine's {what} under "
                   "a control-energy budget at the percentiles " + ", ".join(f"{q:g}" for q in
                                                                             config.energy_percentiles),
                   command=run.command, tuned=list(names), **HeldOut(stepsize=stepsize).tolerances(),
                   initial_gains=gains_to_dict(res.initial), training_figures=res.figures,
                   reference_figures=res.reference, best_generation=res.best_generation,
                   generations_run=res.settings["generations_run"], seed=config.seed, batch=config.batch,
                   population=config.population, plant=plant_to_dict(as_plant(plant)), x64=bool(x64), **fields)
        return (run.out, *_history(run, lambda p: save_arrays(p, res.history)))

    return _tuner_run(run, "search", work, write,
                      lambda r: _held_out_rows(r.initial, r.gains, plant, x64, held_out, "searched"), held_out)


def law_run(run, law, name: str, *, starts=UniformStarts(), batch: int = 256, seed: int = 0, tune=None, plant=None,
            loss: LossConfig = LossConfig(), steps: int = 150, lr: float = 0.05, x64: bool = False,
            n_attempts: Optional[int] = None, held_out: Optional[HeldOut] = None) -> RunOutcome:
    """`jaxsleigh.tuning.tune_law` of ``law`` (registered as ``name``; ``tune``: the leaves to tune, default all of
    `jaxsleigh.tuning.gain_names`) on ``batch`` starts drawn from ``starts`` with ``seed``, as a run that owns
    ``run.out``: the tuned law's file (`jaxsleigh.tuning.law_file`: every parameter, the actuator, how it was found,
    the history; with ``loss.energy_budget`` whether the training energy meets it) and the history, then the
    ``held_out`` check of the starting and the tuned law (`jaxsleigh.tuning.validate`: the accurate engine, audited)
    written into it. After Ctrl-C the best valid law so far. Raises what `tune_law` raises (`InvalidStartingLaw`: the
    law is not a valid start)."""
    from .. import tuning as tu

    run = as_run(run)
    names = tu.gain_names(law) if tune is None else list(tune)
    budget = _budget(loss.energy_budget)

    def write(res, **fields) -> tuple:
        save_law(res.law, name, run.out, how="jaxsleigh tune --controller: Adam on the soft convergence time"
                 + ("" if budget is None else f" under a training energy budget {budget:g}"), command=run.command,
                 tuned=list(names), training_loss=res.loss, training_energy=res.energy, energy_budget=budget,
                 seed=seed, batch=batch, x64=bool(x64), plant=plant_to_dict(as_plant(plant)),
                 history={k: np.asarray(v).tolist() for k, v in res.history.items()}, **fields)
        return (run.out, *_history(run, lambda p: save_arrays(p, res.history)))

    check_sizes(steps, batch, loss.t_final, training_max_step(loss), law_attempts(loss, n_attempts))
    met = (lambda r: _budget_met(loss.energy_budget, r.energy))
    o = _tuner_run(run, "tuning run", lambda: tu.tune_law(
        law, draw_starts(starts, batch, seed), tune=names, plant=plant, loss=loss, steps=steps, lr=lr, x64=x64,
        n_attempts=n_attempts, checkpoint=run.checkpoint, resume=run.resume, options=run.options), write,
        lambda r: _held_out_rows(law, r.law, plant, x64, held_out, "tuned"), held_out,
        lambda r: {} if met(r) is None else {"energy_budget_met": met(r)})
    return o if o.energy_budget_met is None else o._replace(energy=o.result.energy)


def _tuner_run(run: TuningRun, what: str, work, write, check, held_out: Optional[HeldOut], budget=None) -> RunOutcome:
    """The life of a tuner's run (module docstring) under the claim of ``run.out`` (``what`` names it in a refusal):
    ``work()`` runs the tuner; ``write(result, **fields)`` writes the output and the history and returns the paths:
    after Ctrl-C the best so far (if any) with ``interrupted=True``, else with the fields of ``budget(result)`` (with an energy budget: ``energy_budget_met``, and ``training_energy`` for the outcome), then
    again with the ``held_out`` check's ``validation`` (``check(result)``: its rows, `_held_out_rows`)."""
    if held_out is not None:
        held_out.check()
    with run.owned(what):
        t0 = time.perf_counter()
        try:
            res = work()
        except TuningInterrupted as stop:
            wall, part = time.perf_counter() - t0, stop.partial
            return RunOutcome(part, () if part is None else write(part, interrupted=True), True, wall, {})
        wall = time.perf_counter() - t0
        fields = budget(res) if budget else {}
        written = write(res, **fields)          # before the held-out check, so that it cannot lose it
        written = (*written, _sidecar(run, wall, history=history_wall(getattr(res, "history", None))))
        run.finished()
        rows = check(res)
        if rows:          # as every tuner's file records it: with the seed and the tolerances of the check
            write(res, **fields, validation={k: validation_dict(v, seed=held_out.seed, **held_out.tolerances())
                                             for k, v in rows.items()})
    return RunOutcome(res, written, False, wall, rows, fields.get("training_energy"), fields.get("energy_budget_met"))


def front_run(run, budgets, *, method: str = "warm", gains0="paper", config: TuneConfig = TuneConfig(),
              loss: LossConfig = LossConfig(), warm_steps: Optional[int] = None, tune=None, plant=None,
              x64: bool = False, progress: Any = None, held_out: Optional[HeldOut] = None, baseline: bool = False,
              plot=None) -> RunOutcome:
    """`jaxsleigh.tuning.pareto_front` (the arguments are its own; ``budgets`` a whole number N: N budgets from a
    quarter of the paper's gains' training energy to twice the ``tuned`` preset's) as a run that owns ``run.out``:
    the front is written after every point (``"interrupted": true`` until the last; ``resume=True`` keeps the
    finished points of the file and computes the others); ``method="vmap"``, which finishes every point at once,
    keeps its whole state in ``run.checkpoint`` after every iteration instead, writes each budget's best candidate
    so far on Ctrl-C, and ``resume=True`` continues from the checkpoint. Then every point and the paper's
    and ``tuned`` gains (``references``) are measured on the ``held_out`` starts, with ``baseline`` a random search
    that spends as many objective evaluations, and the front is drawn to ``plot`` (which needs the check)."""
    from .. import tuning as tu

    run, names, held_out = as_run(run), tu.parse_tune(tune), (held_out or HeldOut(n=0)).check()
    if plot is not None and not held_out.n:
        raise ValueError("plot draws the front measured on the held-out starts: give held_out with n > 0")
    kw = dict(config=config, loss=loss, plant=plant, x64=x64)
    vmap = method == "vmap"
    with run.owned("front", checkpointed=vmap, also=(plot,)):
        # an interrupted front in the output is never written over without resume (the vmapped one resumes from its
        # checkpoint, not from the file)
        earlier = None if vmap and run.resume else _interrupted_front(run)
        if isinstance(budgets, (int, np.integer)):
            budgets = tu.default_budgets(int(budgets), **kw)
        done = None
        if earlier is not None:
            warm = max(1, config.steps // 2) if warm_steps is None else int(warm_steps)
            done = finished_points(earlier, front_settings("warm", np.sort(np.asarray(budgets, np.float64)), config,
                                                            loss, warm, x64, gains0, names, UniformStarts()))
        initial = {"initial_gains": gains_to_dict(load_gains(gains0))}

        def keep(part):            # after every point: Ctrl-C (or a crash) loses at most the current one
            tu.save_front(part, run.out, command=run.command, interrupted=True, **initial)

        t0 = time.perf_counter()
        try:
            resumable = dict(checkpoint=run.checkpoint, resume=run.resume, options=run.options) if vmap else {}
            front = tu.pareto_front(budgets, method=method, gains0=gains0, warm_steps=warm_steps, tune_names=names,
                                    progress=progress, on_point=keep, done=done, **resumable, **kw)
        except TuningInterrupted as stop:
            if stop.partial is not None:
                keep(stop.partial)
            return RunOutcome(stop.partial, () if stop.partial is None else (run.out,), True,
                              time.perf_counter() - t0, {})
        run.finished()
        front, refs, rows, base = _measured_front(front, budgets, held_out, baseline, progress, kw)
        meta = {"command": run.command, "held_out": {"n": held_out.n, "seed": held_out.seed, **held_out.tolerances(),
                                                     "starts": repr(UniformStarts())}, **initial}
        if base is not None:
            meta["baseline"] = tu.front_dict(base)
        tu.save_front(front, run.out, references=refs, **meta)
        written = [run.out, _sidecar(run, front.wall_s, **({} if base is None else {"baseline_wall_s": base.wall_s}))]
        if plot is not None:
            from ..plots import tuning as tp

            doc = tu.load_front(run.out)
            written.append(tp.save_figure(tp.plot_front(doc, baseline=doc.get("baseline")), plot))
    return RunOutcome(front, tuple(written), False, front.wall_s, rows)


def _sidecar(run: TuningRun, wall_s: float, **more) -> Path:
    """The run's sidecar next to ``run.out`` (`jaxsleigh.files.runner.write_sidecar`): its command, wall time and
    devices (and ``more``: the history's wall time per row), which vary between runs and so stay out of the files
    the tuner writes."""
    import jax

    from ..files.runner import run_record, write_sidecar

    resumed = {"resumed": True} if getattr(run, "resume", False) else {}
    return write_sidecar(run.out, run_record(run.command, wall_s, [str(d) for d in jax.devices()], **resumed,
                                             **more))


def _interrupted_front(run: TuningRun) -> Optional[dict]:
    """The interrupted front in ``run.out`` that ``resume=True`` continues (``None``: none); refuses one without
    ``resume=True`` and ``resume=True`` without one."""
    earlier = None
    if run.out.is_file():
        try:
            earlier = load_front(run.out)
        except ValueError:
            earlier = None
        earlier = earlier if isinstance(earlier, dict) and earlier.get("interrupted") else None
    run.refuse_progress(None if earlier is None else f"{str(run.out)!r} holds the finished points of an interrupted "
                        f"front", afresh="delete it",
                        missing=f"{str(run.out)!r} is not an interrupted front to continue")
    return earlier


def _measured_front(front, budgets, held_out: HeldOut, baseline: bool, progress, kw) -> tuple:
    """``(front, references, rows, baseline front)`` after the held-out check (nothing measured without one)."""
    from .. import tuning as tu

    if not held_out.n:
        return front, {}, {}, None
    ics = held_out.starts()
    ss = {"plant": kw["plant"], "x64": kw["x64"], "stepsize": held_out.stepsize}
    front = tu.evaluate_front(front, ics, **ss)
    refs = {"paper": tu.validate("paper", ics, **ss), "tuned": tu.validate("tuned", ics, **ss)}
    base = None
    if baseline:
        base = tu.random_search(budgets, front.evaluations, seed=kw["config"].seed, progress=progress, **kw)
        base = tu.evaluate_front(base, ics, **ss)
    rows = {**refs, **{f"budget {p.budget:.3g}": p.evaluation for p in front.points}}
    return front, refs, rows, base


# ---------------------------------------------------------------------------------------------
# what the runs write
# ---------------------------------------------------------------------------------------------

def _held_out_rows(initial, found, plant, x64: bool, held_out: Optional[HeldOut], label: str) -> dict:
    """``{"initial": .., label: ..}``: the initial and the found gains (or laws) on the held-out starts, each by
    `jaxsleigh.tuning.validate` (audited; re-measured in float64 where the audit fails)."""
    from .. import tuning as tu

    if held_out is None or not held_out.n:
        return {}
    ics = held_out.starts()
    return {"initial": tu.validate(initial, ics, plant=plant, x64=x64, stepsize=held_out.stepsize),
            label: tu.validate(found, ics, plant=plant, x64=x64, stepsize=held_out.stepsize)}


def _history(run: TuningRun, write) -> list:
    """``[path]`` after ``write(run.history)``, or ``[]`` when the run writes no history."""
    if run.history is None:
        return []
    return [Path(write(run.history) or run.history)]


def _budget(energy_budget) -> Optional[float]:
    """The energy budget as a number, ``None`` for none (``inf``)."""
    b = float(energy_budget)
    return b if math.isfinite(b) else None


def _budget_met(energy_budget, energy: float) -> Optional[bool]:
    """Whether ``energy`` is within the budget (``None`` without one)."""
    b = _budget(energy_budget)
    return None if b is None else bool(math.isfinite(energy) and energy <= b)

