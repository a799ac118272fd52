"""The epoch loop: training to a number of epochs with checkpoints, stops and divergence checks.

``fit`` is the loop itself (any state, any epoch function); ``train_epochs`` runs a
``Trainer`` into a run folder (``stablebptt.runs.run_folder``) as the command line does;
``train`` runs one in memory, the public API's ``stablebptt.train``.
"""
from __future__ import annotations

import time
import warnings
from typing import Any, Callable, NamedTuple

import jax
import numpy as np

from stablebptt.engine.checks import check_options, tracing_shapes
from stablebptt.engine.config import TrainConfig, seed_array
from stablebptt.engine.metrics import COLUMNS, METRICS, empty_rows, epoch_rows
from stablebptt.engine.program_store import cache_dir, lower_epoch
from stablebptt.engine.training import FLOW_BITS, Trainer, make_trainer, nonfinite_names
from stablebptt.timing import compile_ahead


def nonfinite_message(flows: tuple[str, ...], metrics: dict) -> str:
    """"non-finite <what>" when an epoch's metrics (host arrays over seeds) failed a check, else ""."""
    if np.all(metrics["finite"]):
        return ""
    what = nonfinite_names(flows, int(np.bitwise_or.reduce(np.atleast_1d(metrics["nonfinite"]))))
    return f"non-finite {', '.join(what)}"


def zeroed_notice(flows: tuple[str, ...], metrics: dict, seeds: np.ndarray) -> str:
    """What an epoch that went on through non-finite flow gradients (``nonfinite_flows`` "zero") left
    at zero, in words; "" where nothing was."""
    counts = np.atleast_1d(metrics.get("nonfinite_flow_updates", 0))
    if not counts.any() or not np.all(metrics["finite"]):
        return ""
    bits = int(np.bitwise_or.reduce(np.atleast_1d(metrics["nonfinite"]))) >> FLOW_BITS << FLOW_BITS
    where = ", ".join(f"seed {int(seed)}: {int(count)}" for seed, count in zip(seeds, counts) if count)
    return (f"{', '.join(nonfinite_names(flows, bits))} non-finite in some updates ({where}); mode C's sign "
            "agreement left those components at zero and training went on")


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
      should_stop: polled before and after every epoch; true saves and stops.
      on_epoch: gets each epoch's metrics, with its wall time under ``"seconds"``.
      diverged: a message when an epoch's metrics must not be kept (its state is
        dropped, the last good one saved), else "".
      noticed: a message on an epoch that is kept but must not pass in silence (a non-finite flow
        gradient left at zero), else ""; ``on_epoch`` gets it under ``"notice"``.

    Returns:
      (status, last saved epoch, state, rows, message); status "complete",
      "interrupted" or "diverged".
    """
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

    epoch = start_epoch
    for epoch in range(start_epoch + 1, epochs + 1):
        if should_stop():
            if epoch - 1 > start_epoch:
                checkpoint(epoch - 1, state)
            return "interrupted", epoch - 1, state, all_rows(), ""
        started = time.perf_counter()
        new_state, metrics = run_epoch(state)
        seconds = time.perf_counter() - started
        problem = diverged(metrics)
        if problem:
            checkpoint(epoch - 1, state)
            return "diverged", epoch - 1, state, all_rows(), problem
        state = new_state
        blocks.append(epoch_rows(epoch, row_ids, metrics, seconds))
        stopping = should_stop()
        due = epoch % checkpoint_every == 0 and time.monotonic() - last_save >= checkpoint_seconds
        if due or epoch == epochs or stopping:
            checkpoint(epoch, state)
        on_epoch(epoch, {**metrics, "seconds": seconds, "notice": noticed(metrics)})
        if stopping:
            return "interrupted", epoch, state, all_rows(), ""
    return "complete", epoch, state, all_rows(), ""


class LoweredEpoch(NamedTuple):
    """A trainer's epoch traced and lowered (``lowered_epoch``) for states shaped as ``shapes``."""

    lowered: Any  # its compile() gives the epoch's program
    shapes: Any  # the states' shapes (jax.ShapeDtypeStruct) it was lowered for


def state_shapes(trainer: Trainer, seeds: Any) -> Any:
    """The shapes of ``trainer.init(seeds)``, traced with no values: a task's check still running need
    not have answered (it decides the parameters' start, not their shapes)."""
    # init's function, through a function of its own, not its jit: JAX would keep a jit's trace for
    # the next call, and this one's parameters start before the check has decided how.
    init = getattr(trainer.init, "__wrapped__", trainer.init)
    with tracing_shapes():
        return jax.eval_shape(lambda seeds: init(seeds), seeds)


def settled_trainer(task: Any, trainer: Trainer, config: TrainConfig) -> tuple[Any, Trainer]:
    """``task`` once its check left running has answered (``Task.settled``, which may refuse it), with
    ``trainer`` built for it, or a new one where the check smoothed its reward (another step). A
    smoothed reward's task is still checking its surrogate beside the caller: ``settled_fully()``
    waits for that check (and may refuse it) once the new trainer's program is traced."""
    settled = task.settled()
    return settled, trainer if settled.dynamics.step is task.dynamics.step else make_trainer(settled, config)


def lowered_epoch(trainer: Trainer, config: TrainConfig, program_key: dict | None = None) -> LoweredEpoch:
    """``trainer``'s epoch traced and lowered for the states ``trainer.init`` gives, from their shapes
    alone: a task's check still running (``Task.settle``: an environment's reward diagnosis, which
    decides the parameters' start) need not have answered, and XLA compiles that check beside this
    trace. A ``PerUpdateEpoch`` (a large step; a constraint solver on a CPU of several cores) is
    traced as it compiles instead: its metrics' program takes its shapes from the update's compiled
    one. ``program_key`` as ``train_epochs`` takes it."""
    shapes = state_shapes(trainer, seed_array(config))
    arguments = (shapes, trainer.batches, trainer.train_states, trainer.test_states)
    return LoweredEpoch(lower_epoch(trainer.epoch, arguments, program_key, cache_dir(), trainer.compiler_options), shapes)


class Trained(NamedTuple):
    """What ``train`` returns: the parameters and every epoch's metrics, per seed."""

    params: Any  # the trained parameters; every leaf has a leading seed axis
    metrics: dict[str, np.ndarray]  # METRICS name -> [epochs, seeds]
    seconds_to_first_update: float  # compiling included

    @property
    def test_loss(self) -> np.ndarray:
        """Mean test loss over seeds, per epoch."""
        return self.metrics["test_loss"].mean(axis=1)


class TrainingDiverged(ArithmeticError):
    """A loss, update or gradient of training went non-finite; the message says which, and when."""


class NonFiniteFlowWarning(RuntimeWarning):
    """Training went on through a flow's non-finite gradient, left at zero (``nonfinite_flows`` "zero")."""


def train(task: Any, config: TrainConfig = TrainConfig(),
          on_epoch: Callable[[int, dict], None] = lambda epoch, metrics: None) -> Trained:
    """Train ``task``'s controller in memory, with no run folder, and return the result.

    Args:
      task: a ``Task``: dynamics (policy, step, loss, horizon), network initialiser
        and initial-state sampler.
      config: a ``TrainConfig`` (gradient flow ``mode``, ``epochs``, sizes, seeds, ...).
        With ``x64`` the call trains in float64 while JAX runs in float32 elsewhere
        (``jax.enable_x64`` for the call alone; the parameters come back as float64
        NumPy arrays). Arrays the task made before are float32 and used as such:
        for float64 physics constants too, build the task under ``jax.enable_x64(True)``.
      on_epoch: called after every epoch with its metrics (arrays over seeds).

    Returns:
      A ``Trained``: parameters with a leading seed axis and metrics ``[epochs, seeds]``.

    Raises:
      TrainingDiverged: a loss, update or gradient of a computed flow was not finite.
      InputError: a config that is not a ``TrainConfig``, options that make each other
        meaningless (``checks.check_options``), or a task that cannot train (``checks.TaskError``).

    Example::

      result = stablebptt.train(task, stablebptt.TrainConfig(mode="C", epochs=50))
      print(result.test_loss[-1])
    """
    if isinstance(config, TrainConfig):  # anything else make_trainer names
        check_options(config)
        if config.x64 and not jax.config.jax_enable_x64:
            with jax.enable_x64(True):  # the user's own setting is back when the call ends
                trained = _train(task, config, on_epoch)
                return trained._replace(params=jax.device_get(trained.params))
    return _train(task, config, on_epoch)


def _train(task: Any, config: TrainConfig, on_epoch: Callable[[int, dict], None]) -> Trained:
    started = time.perf_counter()
    # A check left running (an environment's reward diagnosis) may refuse the task here, or smooth its reward.
    task, trainer = settled_trainer(task, make_trainer(task, config), config)
    seeds = np.asarray(seed_array(config))
    state = trainer.init(seed_array(config))
    arguments = (trainer.batches, trainer.train_states, trainer.test_states)
    epoch_fn, _ = compile_ahead(trainer.epoch, state, *arguments)
    task = task.settled_fully()  # a smoothed reward's surrogate, checked beside that compile, may refuse it here
    first_update = 0.0  # seconds from the call to the end of the first epoch

    def run_epoch(state):
        nonlocal first_update
        new_state, metrics = epoch_fn(state, *arguments)
        metrics = jax.device_get(metrics)
        first_update = first_update or time.perf_counter() - started
        return new_state, metrics

    def noticed(metrics):
        notice = zeroed_notice(trainer.flows, metrics, seeds)
        if notice:
            warnings.warn(f"{task.name}: {notice}", NonFiniteFlowWarning, stacklevel=2)
        return notice

    status, epoch, state, rows, problem = fit(run_epoch, state, 0, config.epochs, empty_rows(), seeds,
                                              lambda *saved: None, config.epochs, on_epoch=on_epoch,
                                              diverged=lambda metrics: nonfinite_message(trainer.flows, metrics),
                                              noticed=noticed)
    if status == "diverged":
        raise TrainingDiverged(f"{task.name}: {problem} at epoch {epoch + 1} (TrainConfig.mode {config.mode!r})")
    per_epoch = {name: rows[:, COLUMNS.index(name)].reshape(epoch, len(seeds)) for name in METRICS}
    return Trained(state.params, per_epoch, first_update)
