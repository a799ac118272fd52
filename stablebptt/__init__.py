"""stablebptt: stable backpropagation through time through differentiable physics.

The public API: describe a system as a ``Task`` (a ``Dynamics`` of policy, step,
loss and horizon; a network initialiser; an initial-state sampler) and ``train``
it with a ``TrainConfig``; how the engine differentiates it is a ``Plan`` it chooses. The gradient flows R, M, S and their combination C
live in ``stablebptt.flows``; run folders in ``stablebptt.runs``; MuJoCo scene
analysis in ``stablebptt.scene``; the built-in tasks in ``stablebptt.tasks``.
``env_task`` turns an environment in Brax's protocol (MuJoCo Playground's, a
lab's own) into a ``Task`` (``stablebptt.environments``).
"""
import os

# One XLA:CPU intra-op thread, set before JAX creates its CPU client (it reads
# PJRT_NPROC then). jaxlib's LAPACK kernels (MJX's Newton solver: cholesky and
# triangular solves, batched over every step's Jacobian) split a large batch into
# chunks queued on the intra-op pool and block the pool thread that runs them until
# the chunks are done; when as many such calls run at once as the pool has threads,
# every thread waits and the program hangs. With one
# thread the kernels run the batch in place. A user's own PJRT_NPROC is kept.
os.environ.setdefault("PJRT_NPROC", "1")

from stablebptt.errors import InputError
from stablebptt.flows import FLOWS, MODES, Dynamics, Plan, flow_gradients, select_flow, sign_agreement
from stablebptt.networks import mlp_apply, mlp_init
from stablebptt.fitting import Trained, TrainingDiverged, train
from stablebptt.training import Task, TrainConfig, make_trainer

__all__ = ["FLOWS", "MODES", "Dynamics", "InputError", "Plan", "Task", "TrainConfig", "Trained", "TrainingDiverged",
           "env_task", "flow_gradients", "make_trainer", "mlp_apply", "mlp_init", "select_flow", "sign_agreement",
           "train"]


def __getattr__(name: str):
    # Imported on first use: the environment adapter imports MJX, and MuJoCo must not load before a
    # renderer has chosen its OpenGL backend.
    if name == "env_task":
        from stablebptt.environments import env_task
        return env_task
    raise AttributeError(f"module 'stablebptt' has no attribute {name!r}")
