"""A run begun in its folder: everything ``stablebptt train`` does before its first epoch.

    from stablebptt import tasks
    from stablebptt.engine.config import TrainConfig
    from stablebptt.runs import epochs, session
    module = tasks.load("repulsion")
    begun = session.begin(module, "repulsion", module.Config(), TrainConfig(epochs=20))
    try:
        outcome = epochs.train_epochs(*begun.training_arguments(), phases=begun.phases,
                                      compile_saved_mark=begun.compile_saved_mark)
    finally:
        begun.run.close()

``begin`` builds the task and its trainer, claims a new run's folder once the task is settled (a
refusal leaves no folder), or opens a run to resume, and returns the state to train from (a new run's
as the function that makes it once the epoch has compiled: ``Session.state``). A task
may leave a check running while its trainer is built (an environment's reward diagnosis,
``Task.settle``): the epoch is traced meanwhile and compiled once training starts.
"""
from __future__ import annotations

import functools
import os
import time
from pathlib import Path
from types import ModuleType
from typing import Any, Callable, NamedTuple

import jax
import numpy as np

from stablebptt.engine.config import TrainConfig, require_train_config, seed_array
from stablebptt.engine.fitting import env_steps_per_epoch
from stablebptt.engine.lowering import LoweredEpoch
from stablebptt.engine.program_store import compile_seconds_saved, run_key
from stablebptt.engine.starting import prepare
from stablebptt.engine.task import Task
from stablebptt.engine.training import Trainer, TrainState
from stablebptt.errors import InputError
from stablebptt.runs.run_folder import Run, default_run_dir, new_record, refuse_used


class Session(NamedTuple):
    """A run ready to train: its folder (locked until ``run.close()``), task, trainer and starting point."""

    run: Run
    task: Task
    trainer: Trainer
    config: TrainConfig  # as the run records it (a resumed run's, with the epochs asked for)
    # The checkpoint's, else the function that makes the trainer's fresh one: ``train_epochs`` runs it once
    # the epoch has compiled.
    state: TrainState | Callable[[], TrainState]
    start_epoch: int
    rows: np.ndarray  # the metric rows recorded so far
    seeds: np.ndarray
    program_key: dict | None  # what decides the run's programs (``program_store.run_key``)
    lowered: LoweredEpoch | None  # a new run's epoch, traced while the task settled
    phases: dict[str, float]  # seconds of each start-up phase so far (``Prepared.phases``, and the task's build)
    compile_saved_mark: float  # ``program_store.compile_seconds_saved()`` as the start began

    def training_arguments(self) -> tuple:
        """``runs.epochs.train_epochs``'s positional arguments up to its callbacks."""
        return self.trainer, self.config, self.run.directory, self.state, self.start_epoch, self.rows, self.seeds


def task_of(task_module: ModuleType, task_config: Any, resolved: dict | None = None, deferred: bool = False) -> Any:
    """``task_module``'s task of ``task_config``, left checking beside the caller where ``deferred`` and its module
    can (``make_deferred``); a run's that resumes or is reopened (``resolved``: what its record says the task
    resolved to) made as recorded where its module reads that (``make_as_recorded``: a reward's surrogate made
    with the temperatures the run began with)."""
    deferred = deferred and hasattr(task_module, "make_deferred")
    as_recorded = getattr(task_module, "make_as_recorded", None)
    if resolved is not None and as_recorded is not None:
        return as_recorded(task_config, resolved, deferred=deferred)
    return task_module.make_deferred(task_config) if deferred else task_module.make(task_config)


def _check_arguments(task_module: Any, task_name: str, task_config: Any, train_config: Any, run_dir: Any,
                     runs_root: Any) -> None:
    """``InputError`` naming an argument of ``begin`` of another kind than it takes, before anything is built."""
    if not callable(getattr(task_module, "make", None)):
        raise InputError(f"begin's task_module is a task's module, stablebptt.tasks.load({task_name!r}); "
                         f"got {task_module!r}")
    config_type = getattr(task_module, "Config", None)
    if isinstance(config_type, type) and not isinstance(task_config, config_type):
        raise InputError(f"begin's task_config is a {task_module.__name__}.Config, got {type(task_config).__name__}")
    require_train_config(train_config, "begin's train_config is")
    if not (run_dir is None or isinstance(run_dir, (str, os.PathLike))):
        raise InputError(f"begin's run_dir is a folder's path or None, got {run_dir!r}")
    if not isinstance(runs_root, (str, os.PathLike)):
        raise InputError(f"begin's runs_root is a folder's path, got {runs_root!r}")


def begin(task_module: ModuleType, task_name: str, task_config: Any, train_config: TrainConfig,
          run_dir: Path | str | None = None, record: dict | None = None,
          runs_root: Path | str = Path("runs")) -> Session:
    """Begin a new run (``record`` None) or resume the one in ``run_dir`` (its ``config.json`` as ``record``).

    Args:
      task_module: the task's module (``stablebptt.tasks.load(task_name)``): its ``make`` (or
        ``make_deferred``; a resumed run's ``make_as_recorded`` where it has one) builds the task from
        ``task_config``.
      run_dir: a new run's folder (default: ``runs_root``/TASK-TIME); refused at once where it is in use,
        claimed once the task is settled.

    Raises:
      InputError: bad input, a task that cannot train (named), a folder in use; no folder is left behind.
      StorageError: the folder cannot be written.
    """
    _check_arguments(task_module, task_name, task_config, train_config, run_dir, runs_root)
    run_dir, runs_root = None if run_dir is None else Path(run_dir), Path(runs_root)
    run = None
    compile_saved_mark = compile_seconds_saved()
    try:
        if record is not None:
            run = Run.open(run_dir, record)
        elif run_dir is not None:
            refuse_used(run_dir)
        checking = time.perf_counter()
        # A task may leave a check running while the trainer is built (an environment's reward diagnosis).
        task = task_of(task_module, task_config, None if record is None else record.get("resolved_task", {}),
                       deferred=True)
        checking = time.perf_counter() - checking
        # The epoch is traced while XLA may still compile the task's check beside, a resumed run's too (its
        # checkpoint is read into the shapes it was lowered for). A refusal leaves no folder behind.
        prepared = prepare(task, train_config, run_key(task_module, task_name, task_config, train_config),
                           resuming=record is not None)
        task, trainer = prepared.task, prepared.trainer
        if run is None:
            run_dir = run_dir or default_run_dir(runs_root, task.name)  # named as it is claimed
            # The env steps each seed simulates in an epoch's training: learning curves may be drawn against them.
            run = Run.create(run_dir, new_record(task_name, task_config, task, train_config,
                                                 steps_per_epoch=env_steps_per_epoch(trainer, train_config)))
        initializing = time.perf_counter()
        seeds = seed_array(train_config)
        # A new run's state is made once its epoch has compiled (train_epochs, inside the command's block of
        # signals), so that init's programs compile beside the epoch's rather than hold it back; a checkpoint's
        # state is read here.
        start_epoch, state, rows = run.start(lambda: functools.partial(trainer.init, seeds),
                                             lambda: prepared.lowered.shapes, train_config)
        initialized = {}
        if not callable(state):
            jax.block_until_ready(state)
            initialized["init"] = time.perf_counter() - initializing
        phases = {"task's build and checks": checking, **prepared.phases, **initialized}
    except BaseException:
        if run is not None:
            run.close()
        raise
    return Session(run, task, trainer, train_config, state, start_epoch, rows, np.asarray(seed_array(train_config)),
                   prepared.program_key, prepared.lowered, phases, compile_saved_mark)
