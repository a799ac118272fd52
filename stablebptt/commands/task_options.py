"""Task options on the command line, shared by ``train`` and ``sweep``.

Every registered task's ``Config`` fields become options; the options given
choose the task (``--model`` the MJCF task, ``--env`` the environment task)
unless ``--task`` names it.
"""
from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from stablebptt import tasks
from stablebptt.cli import add_options, build, fail, option_name


def add_task_options(parser: argparse.ArgumentParser, owners: dict[str, set[str]]) -> dict[str, set[str]]:
    """``--task`` and one option per field of every task's Config, beside the command's own options.

    ``owners`` maps each option the command already has to the configs that have it (the command's
    own config by its name); the task options are added to it: option -> the task names that have it.
    """
    parser.add_argument("--task", choices=sorted(tasks.entries()) + sorted(tasks.LEGACY_NAMES), default=None,
                        help=f"which task (default: {tasks.DEFAULT_TASK}, or the task whose options are given)")
    for task_name in sorted(tasks.entries()):
        for name in add_options(parser, tasks.load(task_name).Config, f"task {task_name}", set(owners)):
            owners.setdefault(name, set()).add(task_name)
    return owners


def train_defaults_by_task(config_class: type) -> dict[str, str]:
    """Per field of ``config_class`` (the training options) whose default some task changes
    (``tasks.train_defaults``): the tasks and their values, for ``--help`` ("--task env: norm")."""
    fallback = {field.name: field.default for field in dataclasses.fields(config_class)}
    differing: dict[str, list[str]] = {}
    for task_name in sorted(tasks.entries()):
        for name, value in tasks.train_defaults(task_name).items():
            if name in fallback and value != fallback[name]:
                differing.setdefault(name, []).append(f"--task {task_name}: {value}")
    return {name: ", ".join(words) for name, words in differing.items()}


def task_options_given(args: argparse.Namespace, owners: dict[str, set[str]], command: str) -> dict:
    """The task options on the command line (those no config of the command itself has)."""
    return {name: value for name, value in vars(args).items() if name in owners and command not in owners[name]}


def choose_task(args: argparse.Namespace, owners: dict[str, set[str]], command: str) -> str:
    """--task, else the only task whose options are all given, else the default; its registry name.

    An option of another task than --task, options of no task in common, and options that leave
    several tasks but the default are refused in one line naming the options given."""
    given = task_options_given(args, owners, command)
    candidates = set.intersection(*(owners[name] for name in given)) if given else set()
    if args.task is None and given and not candidates:
        first, second = _clash(sorted(given), owners)
        fail(f"{option_name(first)} is an option of {_tasks(owners[first])}, and {option_name(second)} of "
             f"{_tasks(owners[second])}: give the options of one task")
    if args.task is None and len(candidates) > 1 and tasks.DEFAULT_TASK not in candidates:
        fail(f"{', '.join(option_name(name) for name in sorted(given))} fit {_tasks(candidates)}: "
             "give --task to choose")
    task_name = args.task or (candidates.pop() if len(candidates) == 1 else tasks.DEFAULT_TASK)
    foreign = sorted(name for name in given if task_name not in owners[name] and tasks.canonical(task_name) not in owners[name])
    if foreign:
        fail(f"{option_name(foreign[0])} is an option of {_tasks(owners[foreign[0]])}, not of --task {task_name}")
    return tasks.canonical(task_name)


def _clash(names: list[str], owners: dict[str, set[str]]) -> tuple[str, str]:
    """Two of ``names`` (options of no task in common together) that no task shares, else the first
    option and the next that leaves no task in common with those before it."""
    for first in names:
        for second in names:
            if first < second and not owners[first] & owners[second]:
                return first, second
    common = owners[names[0]]
    for name in names[1:]:
        common = common & owners[name]
        if not common:
            break
    return names[0], name


def _tasks(names: set[str]) -> str:
    return f"--task {'/'.join(sorted(names))}"


def task_config(task_name: str, values: dict):
    """The task's Config from option values; a model path made absolute, so that the run resumes and
    renders from any working directory. Validation errors propagate (InputError)."""
    values = dict(values)
    if values.get("model"):
        values["model"] = str(Path(values["model"]).resolve())
    return build(tasks.load(task_name).Config, values)
