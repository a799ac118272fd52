"""stablebptt: stable backpropagation through time through differentiable physics.

The public API: describe a system as a ``Task`` (a ``Dynamics`` of policy, step,
loss and horizon; a network initialiser; an initial-state sampler) and ``train``
it with a ``TrainConfig``; how the engine differentiates it is a ``Plan`` it chooses. The gradient flows R, M, S and their combination C
live in ``stablebptt.flows.gradients``; run folders in ``stablebptt.runs.run_folder``; MuJoCo scene
analysis in ``stablebptt.physics.scene``; the built-in tasks in ``stablebptt.tasks``.
``env_task`` turns an environment in Brax's protocol (MuJoCo Playground's, a
lab's own) into a ``Task`` (``stablebptt.envs.adapter``).
"""
from stablebptt.engine.config import TrainConfig
from stablebptt.engine.fitting import Trained, TrainingDiverged, train
from stablebptt.engine.task import Task
from stablebptt.engine.training import make_trainer
from stablebptt.errors import InputError
from stablebptt.flows.dynamics import Dynamics, Plan
from stablebptt.flows.gradients import flow_gradients
from stablebptt.flows.modes import FLOWS, MODES, select_flow, sign_agreement
from stablebptt.networks import mlp_apply, mlp_init
from stablebptt.runtime import one_cpu_thread

__all__ = ["FLOWS", "MODES", "Dynamics", "InputError", "Plan", "Task", "TrainConfig", "Trained", "TrainingDiverged",
           "env_task", "flow_gradients", "make_trainer", "mlp_apply", "mlp_init", "one_cpu_thread", "select_flow", "sign_agreement",
           "train"]


def __getattr__(name: str):
    # Imported on first use: the environment adapter imports MJX, and MuJoCo must not load before a
    # renderer has chosen its OpenGL backend.
    if name == "env_task":
        from stablebptt.envs.adapter import env_task
        return env_task
    raise AttributeError(f"module 'stablebptt' has no attribute {name!r}")
