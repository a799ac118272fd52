"""The task registry: each task module offers ``Config``, ``make(config) -> Task`` and ``DEFAULT_EPOCHS``."""
from __future__ import annotations

import importlib
from types import ModuleType

TASK_MODULES = {
    "cartpole": "stablebptt.tasks.cartpole",
    "repulsion": "stablebptt.tasks.repulsion",
    "quantum": "stablebptt.tasks.quantum",
}
DEFAULT_TASK = "cartpole"


def load(name: str) -> ModuleType:
    """The task module; imported lazily so that a task's heavy imports are paid only when used."""
    return importlib.import_module(TASK_MODULES[name])
