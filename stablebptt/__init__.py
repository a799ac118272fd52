"""stablebptt: stable backpropagation through time through differentiable physics.

The public API: describe a system as a ``Task`` (a ``Dynamics`` of policy, step, loss and horizon; a
network initialiser; an initial-state sampler; optionally its ``Episodes``, to train on carried ones) and
``train`` it with a ``TrainConfig``; how the engine
differentiates it is a ``Plan`` it chooses. The gradient flows R, M, S and their combination C live in
``stablebptt.flows``; run folders in ``stablebptt.runs``; MuJoCo scene analysis in
``stablebptt.physics.scene``; the built-in tasks in ``stablebptt.tasks``. ``env_task`` turns an
environment in Brax's protocol (MuJoCo Playground's, a lab's own) into a ``Task``
(``stablebptt.envs.adapter``).

Each name is imported where it is first used: ``import stablebptt`` loads neither JAX nor MuJoCo, so
a command can take its signals in hand before they load, and MuJoCo loads after a renderer has
chosen its OpenGL backend.
"""
import importlib

# Public name -> the module that defines it.
_HOMES = {
    "TrainConfig": "stablebptt.engine.config",
    "Episodes": "stablebptt.engine.episodes",
    "Trained": "stablebptt.engine.fitting", "TrainingDiverged": "stablebptt.engine.fitting",
    "NonFiniteFlowWarning": "stablebptt.engine.fitting",
    "train": "stablebptt.engine.fitting",
    "Task": "stablebptt.engine.task",
    "make_trainer": "stablebptt.engine.training",
    "InputError": "stablebptt.errors", "TaskError": "stablebptt.errors", "EnvError": "stablebptt.envs.protocol",
    "Dynamics": "stablebptt.flows.dynamics", "Plan": "stablebptt.flows.dynamics",
    "flow_gradients": "stablebptt.flows.gradients",
    "FLOWS": "stablebptt.flows.modes", "MODES": "stablebptt.flows.modes",
    "select_flow": "stablebptt.flows.modes", "sign_agreement": "stablebptt.flows.modes",
    "mlp_apply": "stablebptt.networks", "mlp_init": "stablebptt.networks",
    "one_cpu_thread": "stablebptt.runtime",
    "rarer_garbage_collections": "stablebptt.runtime",
    "env_task": "stablebptt.envs.adapter", "load_env": "stablebptt.envs.protocol", "recipe": "stablebptt.tasks.env",
    "ContactSmoothing": "stablebptt.physics.backward_contacts",
}
__all__ = sorted(_HOMES)


def __getattr__(name: str):
    if name in _HOMES:
        return getattr(importlib.import_module(_HOMES[name]), name)
    raise AttributeError(f"module 'stablebptt' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_HOMES))
