"""The epoch loop: training to a number of epochs with checkpoints, stops and divergence checks.

``fit`` is the loop itself (any state, any epoch function); ``train_epochs`` runs a
``Trainer`` into a run folder (``stablebptt.runs.run_folder``) as the command line does;
``train`` runs one in memory, the public API's ``stablebptt.train``.
"""
from __future__ import annotations

import contextlib
import functools
import time
import warnings
from typing import Any, Callable, NamedTuple

import jax
import numpy as np

from stablebptt.engine.checks import check_options
from stablebptt.engine.compiling import CompiledBeside, untimed_options
from stablebptt.engine.config import BUDGET_MARGIN, PACE_EPOCHS, TrainConfig, eval_cadence, seed_array
from stablebptt.engine.divergence import (
    failing, failure, keep_retired, nonfinite_message, retired_in, retirement_notice, without_retired, zeroed_notice)
from stablebptt.engine.metrics import COLUMNS, METRICS, empty_rows, env_steps_trained, epoch_rows
from stablebptt.engine.starting import compiled_refill, compiled_then_made, lowered_for, prepare
from stablebptt.engine.training import Trainer
from stablebptt.errors import InputError, keywords_named


def fit(
    run_epoch: Callable[[Any], tuple[Any, dict]],
    state: Any,
    start_epoch: int,
    epochs: int,
    rows: np.ndarray,
    row_ids: np.ndarray,
    save: Callable[[int, Any, np.ndarray], None],
    checkpoint_every: int,
    should_stop: Callable[[], bool] = lambda: False,
    on_epoch: Callable[[int, dict], None] = lambda epoch, metrics: None,
    diverged: Callable[[dict], str] = lambda metrics: "",
    checkpoint_seconds: float = 0.0,
    noticed: Callable[[dict], str] = lambda metrics: "",
    evaluate: Callable[[Any, dict, int, float, bool], tuple[dict, float]] = lambda state, metrics, epoch, seconds,
    final: (metrics, 0.0),
    out_of_time: Callable[[float], bool] = lambda ahead: False,
    steps_per_epoch: int = 0,
    seeds_apart: bool = False,
    updates_per_epoch: int = 0,
) -> tuple[str, int, Any, np.ndarray, str]:
    """The epoch loop: epochs ``start_epoch+1 .. epochs``, checkpointing, stopping and divergence.

    Args:
      run_epoch: ``run_epoch(state) -> (new state, metrics on the host)``, one per row id.
      state, start_epoch, rows: where training stands (``rows`` as ``epoch_rows`` makes them).
      epochs: the epoch to train to.
      row_ids: the seed (or cell) number of each row an epoch adds.
      save: ``save(epoch, state, rows)`` writes a checkpoint.
      checkpoint_every: save every this many epochs, and at the end.
      checkpoint_seconds: and no sooner than this many seconds after the
        last save (the end and a stop always save). A checkpoint rewrites
        every metric row so far: a grid of short epochs saving every few
        epochs spends much of its time writing.
      should_stop: polled before and after every epoch; true saves and stops (an answer that is not one truth
        value: ``InputError``).
      on_epoch: gets each epoch's metrics, with its wall time under ``"seconds"``.
      diverged: what failed when an epoch's metrics must not be kept (its state is dropped, the
        last good one saved), else ""; the run's message adds the epoch and the seeds.
      seeds_apart: the rows are seeds of one state's leading axis, and a seed that fails alone is
        retired (``stablebptt.engine.divergence``): it keeps its last good state, its rows hold NaN,
        ``on_epoch`` names it in its notice, and the others train on; the run stops as diverged only
        once every seed has failed.
      noticed: a message on an epoch that is kept but must not pass in silence (a non-finite flow
        gradient left at zero), else ""; ``on_epoch`` gets it under ``"notice"``.
      evaluate: ``evaluate(state, metrics, epoch, seconds, final) -> (metrics, seconds evaluating)``
        after every epoch, ``final`` on the last one a run trains (``Evaluations``).
      out_of_time: ``out_of_time(ahead)`` after every epoch and its evaluation, ``ahead`` one more epoch as long
        as the slowest of this start's last ``PACE_EPOCHS`` after its first (or cut short:
        ``updates_per_epoch``) and the longest evaluation's seconds, with ``BUDGET_MARGIN`` of them to spare,
        and twice the longest an epoch's save and ``on_epoch`` took; true evaluates, saves and stops (a
        wall-clock budget).
      steps_per_epoch: env steps a seed trains per epoch, counted in the rows (0: none to count).
      updates_per_epoch: where given, ``run_epoch(state, updates)`` runs an epoch of its first ``updates``
        (``Trainer.epoch_batches``), and the budget's last epoch is cut to the updates that fit in it with
        the last evaluation (each as long as in that slowest epoch), where a
        whole one does not: the budget trains to its end rather than stopping up to an epoch before it.
        ``run_epoch``'s metrics may hold ``fixed_seconds``, what the epoch spent whatever its updates (taken
        out of them here).
        Only the evaluations apart from the epoch (``evaluate``) are left room for: a caller whose epochs
        evaluate inside passes 0.

    Returns:
      (status, last saved epoch, state, rows, message); status "complete",
      "interrupted", "budget" or "diverged"; the message of a budget's last epoch cut short says so.
    """
    should_stop = _one_answer(should_stop)
    saved_epoch = start_epoch if start_epoch > 0 else -1  # a start past epoch 0 comes from a checkpoint
    last_save = time.monotonic()
    blocks = [rows]  # joined only when saved or returned: appending by concatenation is quadratic

    def all_rows():
        if len(blocks) > 1:
            blocks[:] = [np.concatenate(blocks)]
        return blocks[0]

    def checkpoint(epoch, state):
        nonlocal saved_epoch, last_save
        if saved_epoch != epoch:
            save(epoch, state, all_rows())
            saved_epoch, last_save = epoch, time.monotonic()

    retired = retired_in(all_rows(), row_ids) if seeds_apart else np.zeros(len(row_ids), dtype=bool)
    # The longest evaluation so far (a resumed run's too): the room a stop must leave for its last one.
    epoch, evaluation = start_epoch, float(np.max(np.nan_to_num(rows[:, COLUMNS.index("eval_seconds")]), initial=0.0))
    steps = steps_so_far(rows, start_epoch, steps_per_epoch)
    units = updates_per_epoch or 1  # the parts an epoch may be cut to (1: it runs whole or not at all)
    cut = None  # the updates of the epoch next, where the budget cuts it short
    # Each epoch's seconds an update, this start's: the cut plans with the slowest of the last few after the
    # first, which pays the programs' first calls (PACE_EPOCHS).
    rates = []
    aside = 0.0  # the longest an epoch's save and report took: planned twice, the epoch's just run and the next's

    def room(ran: int, fixed: float, per_update: float) -> int | None:
        """The next epoch's updates within the budget: None (all of them), as many as fit, or 0 (none)."""
        if ran < units:  # an epoch cut short is the budget's last
            return 0
        fits = lambda updates: not out_of_time(  # noqa: E731
            (fixed + updates * per_update + evaluation) * (1 + BUDGET_MARGIN) + 2 * aside)
        if fits(units):
            return None
        low, high = 0, units - 1  # the most updates that fit, by bisection
        while low < high:
            middle = (low + high + 1) // 2
            low, high = (middle, high) if fits(middle) else (low, middle - 1)
        return low

    for epoch in range(start_epoch + 1, epochs + 1):
        if should_stop():
            if epoch - 1 > start_epoch:
                checkpoint(epoch - 1, state)
            return "interrupted", epoch - 1, state, all_rows(), ""
        started = time.perf_counter()
        new_state, metrics = run_epoch(state) if cut is None else run_epoch(state, cut)
        seconds, ran = time.perf_counter() - started, cut or units
        # What an epoch spends whatever its updates (``run_epoch``'s ``fixed_seconds``: the pool's refill),
        # and each update.
        fixed = min(float(metrics.pop("fixed_seconds", 0.0)), seconds)
        rates.append((seconds - fixed) / ran)
        planned = functools.partial(room, ran, fixed, max(rates[1:][-PACE_EPOCHS:], default=rates[0]))
        stopping, cut = should_stop(), planned()
        metrics, eval_seconds = evaluate(new_state, metrics, epoch, seconds, epoch == epochs or stopping or cut == 0)
        evaluation = max(evaluation, eval_seconds)  # one due on the cadence may have used the next epoch's room
        cut = planned() if eval_seconds > 0 and cut != 0 else cut
        spent = cut == 0
        steps += steps_per_epoch * ran / units
        if retired.any():  # seeds stopped before fail again as they replay their epoch: only the others count
            metrics = without_retired(metrics, retired)
        evaluated = time.perf_counter()
        problem, retiring = diverged(metrics), ""
        if problem:
            newly = failing(metrics) if seeds_apart else np.ones(len(row_ids), dtype=bool)
            if (retired | newly).all():
                checkpoint(epoch - 1, state)
                return "diverged", epoch - 1, state, all_rows(), failure(problem, epoch, row_ids[newly])
            retired = retired | newly
            retiring = retirement_notice(problem, row_ids[newly], epoch, int((~retired).sum()))
            metrics = without_retired(metrics, retired)
        if retired.any():  # the retired seeds keep their state; the others' epoch is kept
            new_state = keep_retired(new_state, state, retired)
        state = new_state
        blocks.append(epoch_rows(epoch, row_ids, metrics, seconds, eval_seconds, steps if steps_per_epoch else np.nan))
        due = epoch % checkpoint_every == 0 and time.monotonic() - last_save >= checkpoint_seconds
        if due or epoch == epochs or stopping or spent:
            checkpoint(epoch, state)
        notice = "; ".join(line for line in (retiring, noticed(metrics)) if line)
        on_epoch(epoch, {**metrics, "seconds": seconds, "eval_seconds": eval_seconds, "notice": notice,
                         "env_steps": steps})
        aside = max(aside, time.perf_counter() - evaluated)
        if stopping or spent:
            short = f"cut to its first {ran} of {units} updates" if ran < units else ""
            return "interrupted" if stopping else "budget", epoch, state, all_rows(), "" if stopping else short
    return "complete", epoch, state, all_rows(), ""


def steps_so_far(rows: np.ndarray, epoch: int, steps_per_epoch: int) -> float:
    """The env steps a seed trained by the end of ``epoch``: its last row's count (an epoch cut short
    counts its own), or ``epoch`` whole epochs where the rows hold none."""
    counted = rows[:, COLUMNS.index("env_steps")] if len(rows) else np.zeros(0)
    counted = counted[np.isfinite(counted)]
    return float(env_steps_trained(counted[-1] if len(counted) else np.nan, epoch, steps_per_epoch))


class Evaluations:
    """A trainer's evaluations made apart from its epochs (``Trainer.evaluation``), on its cadence
    (``TrainConfig.eval_every``): ``fit``'s ``evaluate``. A trainer that evaluates inside every epoch
    passes its metrics through."""

    def __init__(self, trainer: Trainer, config: TrainConfig):
        self.program = trainer.evaluation
        self.cadence, self.every = eval_cadence(config, trainer.episodes is not None)
        self.updates = trainer.updates_per_epoch
        self.arguments = (trainer.train_states, trainer.test_states)
        self.training = 0.0  # seconds trained since the last evaluation
        self.last = None  # seconds the last evaluation took

    def compile(self, state: Any, beside: CompiledBeside | None = None) -> float:
        """Compile the evaluation for ``state``'s parameters ahead; the seconds it took (0 where there is none).
        ``beside``: the evaluation compiling already (``LoweredEpoch``), waited for where it was lowered
        for parameters of ``state``'s shapes."""
        if self.program is None:
            return 0.0
        if lowered_for(beside, state.params):
            self.program = beside
            return beside.wait()
        started = time.perf_counter()  # compiled as a new run's, beside its epoch: a resume finds it cached
        self.program = self.program.lower(state.params, *self.arguments).compile(untimed_options() or None)
        return time.perf_counter() - started

    def due(self, epoch: int) -> bool:
        if self.cadence == "updates":  # counted from the run's start: a resumed run evaluates where it would have
            return epoch * self.updates // self.every > (epoch - 1) * self.updates // self.every
        if self.cadence == "seconds":
            return self.training >= self.every
        # "share": the evaluations' time within that share of the training and evaluating time
        return self.last is None or self.last <= self.every * (self.training + self.last)

    def __call__(self, state: Any, metrics: dict, epoch: int, seconds: float, final: bool) -> tuple[dict, float]:
        if self.program is None:
            return metrics, 0.0
        self.training += seconds
        if not (final or self.due(epoch)):
            return metrics, 0.0
        started = time.perf_counter()
        evaluated = jax.device_get(self.program(state.params, *self.arguments))
        self.last, self.training = time.perf_counter() - started, 0.0
        return {**metrics, "train_loss": evaluated["train_loss"], "test_loss": evaluated["test_loss"],
                "finite": np.logical_and(metrics["finite"], evaluated["finite"]),
                "nonfinite": np.bitwise_or(metrics["nonfinite"], evaluated["nonfinite"])}, self.last


class Trained(NamedTuple):
    """What ``train`` returns: the parameters and every epoch's metrics, per seed."""

    params: Any  # the trained parameters; every leaf has a leading seed axis
    metrics: dict[str, np.ndarray]  # METRICS name -> [epochs, seeds]
    seconds_to_first_update: float  # compiling included

    @property
    def test_loss(self) -> np.ndarray:
        """Mean test loss over the seeds scored, per epoch (a seed stopped apart has none)."""
        losses = self.metrics["test_loss"]
        scored = np.isfinite(losses).sum(axis=1)
        return np.where(scored > 0, np.nansum(losses, axis=1) / np.maximum(scored, 1), np.nan)


class TrainingDiverged(ArithmeticError):
    """A loss, update or gradient of training went non-finite; the message says which, and when."""


class NonFiniteFlowWarning(RuntimeWarning):
    """Training went on through a non-finite value: a flow's gradient left at zero (``nonfinite_flows``
    "zero"), or a seed that failed alone and stopped while the others trained on."""


@keywords_named
def train(task: Any, config: TrainConfig = TrainConfig(),
          on_epoch: Callable[[int, dict], None] = lambda epoch, metrics: None,
          progress_fn: Callable[[int, dict], None] | None = None,
          should_stop: Callable[[], bool] = lambda: False) -> Trained:
    """Train ``task``'s controller in memory, with no run folder, and return the result.

    Args:
      task: a ``Task``: dynamics (policy, step, loss, horizon), network initialiser
        and initial-state sampler.
      config: a ``TrainConfig`` (gradient flow ``mode``, ``epochs``, sizes, seeds, a wall-clock
        ``budget`` counted from this call, ``eval_every``, ...).
        With ``x64`` the call trains in float64 while JAX runs in float32 elsewhere
        (``jax.enable_x64`` for the call alone; the parameters come back as float64
        NumPy arrays). Arrays the task made before are float32 and used as such:
        for float64 physics constants too, build the task under ``jax.enable_x64(True)``.
        A ``matmul_precision`` other than "default" holds for the call alone in the same way.
      on_epoch: called after every epoch with its metrics (arrays over seeds; ``seconds`` and
        ``eval_seconds`` its training and evaluation time).
      progress_fn: Brax's convention, ``progress_fn(env_steps, metrics)`` after every epoch: each
        seed's env steps so far (episodes: windows times states times steps; fixed starts: the
        training states' rollouts) and that epoch's metrics.
      should_stop: polled as every epoch's updates end (before ``on_epoch`` hears of it) and before
        the next: true ends training there, with that epoch evaluated, as the budget does.

    Returns:
      A ``Trained``: parameters with a leading seed axis and metrics ``[epochs, seeds]`` (an epoch
      trained without an evaluation has NaN train and test losses). A seed whose epoch went
      non-finite while others' did not stops there with its last good parameters, its metrics NaN
      from that epoch on, named in a ``NonFiniteFlowWarning``; the others train on.

    Raises:
      TrainingDiverged: a loss, update or gradient of a computed flow was not finite, for every seed.
      InputError: a config that is not a ``TrainConfig``, options that make each other
        meaningless (``checks.check_options``), a task that cannot train (``sb.TaskError``), or a
        ``should_stop`` whose answer is not one truth value.

    Example::

      result = stablebptt.train(task, stablebptt.TrainConfig(mode="C", epochs=50))
      print(result.test_loss[-1])
    """
    started = time.perf_counter()
    for name, function in (("on_epoch", on_epoch), ("progress_fn", progress_fn), ("should_stop", should_stop)):
        if not (callable(function) or function is None and name == "progress_fn"):  # called only once compiled
            raise InputError(f"train's {name} must be a function{' or None' if name == 'progress_fn' else ''}, "
                             f"got {function!r}")
    if isinstance(config, TrainConfig):  # anything else make_trainer names
        check_options(config)
        widened = config.x64 and not jax.config.jax_enable_x64
        # The user's own settings are back when the call ends.
        precision = (contextlib.nullcontext() if config.matmul_precision == "default" else
                     jax.default_matmul_precision(config.matmul_precision))
        with jax.enable_x64(widened or jax.config.jax_enable_x64), precision:
            trained = _train(task, config, on_epoch, progress_fn, should_stop, started)
            return trained._replace(params=jax.device_get(trained.params)) if widened else trained
    return _train(task, config, on_epoch, progress_fn, should_stop, started)


def _one_answer(should_stop: Callable[[], bool]) -> Callable[[], bool]:
    """``should_stop`` whose answer is one truth value, or ``InputError`` naming what it gave."""
    def asked() -> bool:
        answer = should_stop()
        try:
            return bool(answer)
        except (TypeError, ValueError):  # an array of several values has no single truth
            raise InputError(f"should_stop must return one bool, got {answer!r}") from None
    return asked


def _train(task: Any, config: TrainConfig, on_epoch: Callable[[int, dict], None],
           progress_fn: Callable[[int, dict], None] | None, should_stop: Callable[[], bool], started: float) -> Trained:
    prepared = prepare(task, config)  # a check left running may refuse the task here, or smooth its reward
    task, trainer = prepared.task, prepared.trainer
    seeds = np.asarray(seed_array(config))
    epoch_fn, _, state, _ = compiled_then_made(trainer, lambda: trainer.init(seed_array(config)), prepared.lowered)
    refill, _ = compiled_refill(trainer, state, prepared.lowered and prepared.lowered.refill)
    evaluations = Evaluations(trainer, config)
    evaluations.compile(state, prepared.lowered and prepared.lowered.evaluation)
    first_update = 0.0  # seconds from the call to the end of the first epoch

    def ended():
        nonlocal first_update
        first_update = first_update or time.perf_counter() - started

    def reported(epoch, metrics):
        if metrics["notice"]:  # a flow's non-finite gradient left at zero, or seeds that stopped apart
            warnings.warn(f"{task.name}: {metrics['notice']}", NonFiniteFlowWarning, stacklevel=2)
        on_epoch(epoch, metrics)
        if progress_fn is not None:
            progress_fn(int(metrics["env_steps"]), metrics)

    status, epoch, state, rows, problem = fit(epoch_runner(trainer, epoch_fn, refill, ended), state, 0, config.epochs,
                                              empty_rows(), seeds,
                                              lambda *saved: None, config.epochs, should_stop, reported,
                                              diverged=lambda metrics: nonfinite_message(trainer.flows, metrics),
                                              noticed=lambda metrics: zeroed_notice(trainer.flows, metrics, seeds),
                                              evaluate=evaluations, out_of_time=out_of_time(config, started),
                                              steps_per_epoch=env_steps_per_epoch(trainer, config), seeds_apart=True,
                                              updates_per_epoch=cuttable_updates(trainer))
    if status == "diverged":
        raise TrainingDiverged(f"{task.name}: {problem} (TrainConfig.mode {config.mode!r})")
    per_epoch = {name: rows[:, COLUMNS.index(name)].reshape(epoch, len(seeds)) for name in METRICS}
    return Trained(state.params, per_epoch, first_update)


def env_steps_per_epoch(trainer: Trainer, config: TrainConfig) -> int:
    """The env steps each seed simulates in an epoch's training (its evaluations not counted)."""
    return trainer.updates_per_epoch * config.batch * trainer.horizon


def cuttable_updates(trainer: Trainer) -> int:
    """The updates of an epoch that ``fit`` may cut short (``Trainer.epoch_batches``): training on episodes,
    its evaluations apart from the epoch (0: none; one inside would be cut with it, unaccounted)."""
    return trainer.updates_per_epoch if trainer.episodes is not None and trainer.evaluation is not None else 0


def epoch_runner(trainer: Trainer, epoch_fn: Callable, refill: Callable, ended: Callable[[], None] = lambda: None):
    """``fit``'s ``run_epoch``: ``epoch_fn`` from the state ``refill`` refills, of its first ``updates`` (None: all),
    with the metrics on the host and the refill's seconds as ``fixed_seconds`` (a cut epoch runs it whole);
    ``ended()`` is called as each epoch ends."""
    def run_epoch(state, updates=None):
        started = time.perf_counter()
        state = jax.block_until_ready(refill(state))
        refilled = time.perf_counter() - started
        new_state, metrics = epoch_fn(state, trainer.epoch_batches(updates), trainer.train_states, trainer.test_states)
        metrics = jax.device_get(metrics)
        ended()
        return new_state, {**metrics, "fixed_seconds": refilled}
    return run_epoch


def out_of_time(config: TrainConfig, started: float) -> Callable[[float], bool]:
    """Whether ``ahead`` seconds more end past ``config.budget`` since ``started`` (never without a budget)."""
    return lambda ahead: bool(config.budget) and time.perf_counter() - started + ahead > config.budget
