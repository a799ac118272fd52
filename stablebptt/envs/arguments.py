"""``env_task``'s arguments checked before anything is built: the first of the wrong type or range
refused in one line, named as ``env_task`` takes it."""
from __future__ import annotations

import math
from typing import Any, Sequence

from stablebptt.envs.protocol import EnvError
from stablebptt.errors import real_number, whole_number
from stablebptt.physics.backward_contacts import ContactSmoothing


def _real(value: Any) -> bool:
    """A finite real number, not a bool."""
    return real_number(value) and math.isfinite(value)


def check_env_task_arguments(**given: Any) -> None:
    """``EnvError`` naming the first argument of ``env_task`` of the wrong type or range."""
    def refuse(name: str, wanted: str) -> None:
        raise EnvError(f"env_task's {name} must be {wanted}, got {given[name]!r}")

    if not whole_number(given["horizon"]) or given["horizon"] < 1:
        refuse("horizon", "a positive whole number of steps")
    discount = given["discount"]
    if not (_real(discount) and 0 < discount <= 1):
        refuse("discount", "a number in (0, 1]")
    if given["episode_length"] is not None and (not whole_number(given["episode_length"]) or given["episode_length"] < 1):
        refuse("episode_length", "a positive whole number of steps, or None for the environment's own")
    hidden = given["hidden"]
    if isinstance(hidden, (str, bytes)) or not isinstance(hidden, Sequence) or \
            not all(whole_number(width) and width >= 1 for width in hidden):
        refuse("hidden", "a sequence of positive whole numbers, the hidden layers' widths")
    for name in ("name", "reward_repairs", "dense_variant"):
        if not isinstance(given[name], str):
            refuse(name, "a string")
    for name in ("diagnose", "defer_diagnosis", "normalize_observations", "contact_geometry_held",
                 "reward_direction_observed", "physics_steps_carrying_state"):
        if not isinstance(given[name], bool):
            refuse(name, "True or False")
    if not whole_number(given["diagnosis_seed"]):
        refuse("diagnosis_seed", "a whole number")
    if given["reward_context"] is not None and not callable(given["reward_context"]):
        refuse("reward_context", "a context manager's factory, or None")
    if given["diagnosis_key"] is not None and not isinstance(given["diagnosis_key"], dict):
        refuse("diagnosis_key", "a dict, or None")
    choices = given["smoothing_choices"]
    if choices is not None and not (isinstance(choices, dict) and set(choices) == {"temperatures", "exponents"}):
        refuse("smoothing_choices", 'a run\'s recorded "reward_smoothing_choices" (a dict of "temperatures" and '
               '"exponents"), or None')
    if given["smoothing"] not in ("auto", "always", "off"):
        refuse("smoothing", '"auto", "always" or "off"')
    scale = given["smoothing_scale"]
    if not (_real(scale) and scale > 0):
        refuse("smoothing_scale", "a positive number")
    if given["surrogate_reward"] is not None and not callable(given["surrogate_reward"]):
        refuse("surrogate_reward", "a function of the state a step reaches, or None")
    if given["smoothing"] == "always" and (given["surrogate_reward"] is not None or not given["diagnose"]):
        raise EnvError("env_task: smoothing always makes a surrogate of the env's reward from the reward check's "
                       "samples: not with a surrogate_reward of your own (trained as given) nor with diagnose off")
    if given["contact_smoothing"] is not None and not isinstance(given["contact_smoothing"], ContactSmoothing):
        refuse("contact_smoothing", "a stablebptt.ContactSmoothing, or None")
    if not (given["physics_steps_recomputed"] is None or isinstance(given["physics_steps_recomputed"], bool)):
        refuse("physics_steps_recomputed", "True, False or None (recomputed where a control step spans several physics steps)")
    substeps = given["gradient_substeps"]
    if substeps is not None and not (whole_number(substeps) and substeps >= 1):
        refuse("gradient_substeps", "a whole number of physics steps >= 1, or None")
    floor = given["squash_gradient_floor"]
    if not (_real(floor) and 0 <= floor < 1):
        refuse("squash_gradient_floor", "a number in [0, 1)")
    cut = given["contact_gradient_cut"]
    if not (_real(cut) and cut >= 0):
        refuse("contact_gradient_cut", "a number of body weights >= 0 (0: no cut)")
    if given["reward_env"] is not None:
        if given["surrogate_reward"] is not None:
            raise EnvError("env_task: give a surrogate_reward or a reward_env to train on, not both")
        if not callable(getattr(given["reward_env"], "step", None)):
            refuse("reward_env", "an environment whose step takes the env's states, or None")
