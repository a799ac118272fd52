"""The hooks of each task's side of the studies, reached through its registry entry: no study names a task.

A task's entry names its studies module (``stablebptt.tasks.Entry.studies``), which
may define any of these; a study refuses, in one line, a task whose module lacks
the one it needs, and takes any registered task where it needs none:

- ``trajectory_setup(config: AccuracyConfig) -> TrajectorySetup``: the trajectory study
  (``stablebptt.apps.trajectory_study``); none: the task is not in that study.
- ``gradient_setup(config: AccuracyConfig) -> GradientSetup``: the gradient study
  (``stablebptt.apps.gradient_study``); none: the task is not in that study.
- ``training_config(module) -> Config``: the task's configuration in the training study
  (``stablebptt.apps.training_study``); none: ``module.Config()``.
- ``bench_cases(module, config: BenchConfig) -> [BenchCase]``: what the benchmark times
  (``stablebptt.apps.bench``); none: one case, the task's defaults, without a steps table.

The built-in tasks' modules are ``cartpole`` (the MJCF task's cart-poles),
``repulsion`` and ``quantum`` in ``stablebptt.apps.studies``.
"""
from __future__ import annotations

import importlib
from typing import Callable

from stablebptt.errors import InputError


def hook(task: str, name: str) -> Callable | None:
    """The function ``name`` of ``task``'s studies module, or None where it has none."""
    from stablebptt import tasks
    entry = tasks.entry(task)
    if not entry.studies:
        return None
    return getattr(importlib.import_module(entry.studies), name, None)


def required_hook(task: str, name: str, study: str) -> Callable:
    """``hook(task, name)``, or an ``InputError`` saying that ``study`` cannot take the task."""
    found = hook(task, name)
    if found is None:
        raise InputError(f"the {study} study has no set-up for the task {task!r}: its registry entry's studies "
                         f"module defines no {name}() (stablebptt.apps.studies)")
    return found
