"""Brax's environment protocol: loading an environment by name, the checks that it keeps the protocol,
and its reset traced once for every program that resets it.

The protocol (Brax's, which MuJoCo Playground follows): ``env.reset(key) -> State`` and
``env.step(State, action) -> State``, where ``State`` is a pytree with ``obs``, ``reward`` and ``done``
(and anything else: an ``mjx.Data``, a PRNG key, a step counter), plus ``env.observation_size`` and
``env.action_size``.
"""
from __future__ import annotations

import copy
import functools
import importlib
import inspect
import numbers
import os
import sys
import types
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from stablebptt.errors import InputError, first_line, whole_number
from stablebptt.physics.c_sensors import sensors_as_c_computes

PyTree = Any


class EnvError(InputError):
    """An environment that cannot train: not in the protocol, or a reward with no usable gradient."""


def observation(state: PyTree) -> jax.Array:
    """The policy's input: ``State.obs``, or its ``"state"`` entry where the observation is a dict."""
    obs = state.obs
    if isinstance(obs, dict):
        return obs["state"]
    return obs


def sized_observation(size: int, label: str) -> Callable[[PyTree], jax.Array]:
    """``observation``, checked as it is traced against the ``size`` that ``observation_size`` gave: ``EnvError``
    naming both, where a policy of ``size`` inputs would meet a shape error."""
    def observed(state: PyTree) -> jax.Array:
        seen = observation(state)
        if seen.shape[-1:] != (size,):
            raise EnvError(f"{label}: its states' observations have shape {tuple(seen.shape)}, but observation_size "
                           f"is {size}")
        return seen
    return observed


def require_env_instance(env: Any) -> None:
    """``EnvError`` where ``env`` is a class or a module, not an environment: env_task would set its jitted
    reset on a class (for every instance), and cannot copy a module."""
    if isinstance(env, type):  # its methods are the class's: the task's would be set on it, for every instance
        raise EnvError(f"env_task takes an environment, got the class {env.__name__}: give an instance of it "
                       f"({env.__name__}(...))")
    if isinstance(env, types.ModuleType):
        raise EnvError(f"env_task takes an environment, got the module {env.__name__}: give the environment it "
                       "makes, or load it by name with sb.load_env('package.module:attribute')")


def check_protocol(env: Any) -> int:
    """The length of ``env``'s observation vector; ``EnvError`` naming what ``env`` lacks of Brax's
    environment protocol.

    ``observation_size`` is read once: MuJoCo Playground computes it by tracing ``reset``.
    """
    # Looked up on the class first, so that a property is not evaluated just to see that it exists.
    missing = [name for name in ("reset", "step", "observation_size", "action_size")
               if not (hasattr(type(env), name) or hasattr(env, name))]
    if missing:
        raise EnvError(f"{type(env).__name__} is not an environment in Brax's protocol: it has no "
                       f"{', '.join(missing)} (reset(key) -> State, step(State, action) -> State, "
                       "observation_size, action_size)")
    try:
        size, _ = env.observation_size, env.action_size
    except AttributeError as error:  # a wrapper whose class forwards them to an env that lacks one
        raise EnvError(f"{type(env).__name__} is not an environment in Brax's protocol: reading its "
                       f"observation_size or action_size failed ({error})") from None
    if isinstance(size, dict):
        if "state" not in size:
            raise EnvError(f"{type(env).__name__}'s observation is a dict without a 'state' entry "
                           f"({', '.join(size)}): give an environment with a vector observation")
        size = size["state"]
    if not (whole_number(size) or isinstance(size, tuple) and len(size) == 1):  # True is no count
        raise EnvError(f"{type(env).__name__}'s observation has shape {size}: only vector observations are supported")
    size = int(size[0] if isinstance(size, tuple) else size)
    actions = env.action_size
    # Nothing to act on, or nothing to see: every update would be zero, a run that only seems to train.
    if not (whole_number(actions) and actions >= 1):
        raise EnvError(f"{type(env).__name__}'s action_size is {actions!r}: a policy needs at least one action to train")
    if size < 1:
        raise EnvError(f"{type(env).__name__}'s observation_size is {size}: a policy needs at least one observation")
    return size


def check_step(env: Any, step: Callable, observations: int, label: str) -> bool:
    """``EnvError`` where ``env``'s reset or step breaks Brax's protocol in a way that tracing alone
    shows: an observation of another size than ``observation_size`` says, a step returning a state of
    another tree, shapes or dtypes than the one it is given, a reward or done that is not a number.
    Traced with shapes only; True where all holds."""
    try:
        state = jax.eval_shape(env.reset, jax.random.PRNGKey(0))
    except Exception as error:  # noqa: BLE001 - the user's reset failed: one line naming it
        raise EnvError(f"{label}: reset(key) fails: {first_line(error)}") from None
    for name in ("obs", "reward", "done"):
        if not hasattr(state, name):
            raise EnvError(f"{label}: reset(key) returns {type(state).__name__} without .{name}: Brax's protocol's "
                           "State has obs, reward and done")
    seen = jax.tree.map(lambda leaf: leaf.shape, observation(state))
    if seen != (observations,):
        raise EnvError(f"{label}: reset(key) gives an observation of shape {seen}, but observation_size is "
                       f"{observations}")
    action = jax.ShapeDtypeStruct((int(env.action_size),), jnp.float32)
    try:
        reached = jax.eval_shape(step, state, action)
    except EnvError:  # this library's refusal of the step as it traces it: one line already
        raise
    except Exception as error:  # noqa: BLE001 - the user's step failed: one line naming it
        raise EnvError(f"{label}: step(state, action) fails on the state reset gives and an action of "
                       f"{int(env.action_size)} numbers: {first_line(error)}") from None
    difference = _first_difference(state, reached)
    if difference:
        raise EnvError(f"{label}: step(state, action) {difference}")
    for name in ("reward", "done"):
        if getattr(reached, name).shape != ():
            raise EnvError(f"{label}: step(state, action) gives a {name} of shape {getattr(reached, name).shape}, "
                           "not one number")
    return True


def check_same_states(env: Any, step: Callable, label: str) -> bool:
    """``EnvError`` where ``step`` (another env's, whose reward is trained on) does not take ``env``'s states
    to states of the same tree, shapes and dtypes; traced with shapes only."""
    state = jax.eval_shape(env.reset, jax.random.PRNGKey(0))
    action = jax.ShapeDtypeStruct((int(env.action_size),), jnp.float32)
    try:
        reached = jax.eval_shape(step, state, action)
    except Exception as error:  # noqa: BLE001 - the other env's step failed on these states: one line naming it
        raise EnvError(f"{label}: the step whose reward is trained on fails on {label}'s states: {first_line(error)}") from None
    difference = _first_difference(state, reached)
    if difference:
        raise EnvError(f"{label}: the step whose reward is trained on does not return states like {label}'s: it "
                       f"{difference}; train on the reward of an env of the same model and states")
    return True


def function_name(function: Callable) -> str:
    """How messages name a function of the user's: ``module:name``, as ``--surrogate-reward`` takes it; a
    partly applied one ``functools.partial(module:name)``, a callable object ``module:Class()`` (never its
    repr, whose address would change from run to run)."""
    module, name = getattr(function, "__module__", None), getattr(function, "__qualname__", None)
    if name:
        return f"{module}:{name}" if module else name
    if isinstance(function, functools.partial):
        return f"functools.partial({function_name(function.func)})"
    kind = type(function)
    return f"{kind.__module__}:{kind.__qualname__}()"


def trained_reward_words(surrogate_reward: Callable | None, reward_env: Any, dense_variant: str) -> tuple[str, bool]:
    """What a task's windows train on besides its env's own reward, in words ('' for the env's own): the
    user's surrogate, or another env's step's reward (a ``...Sparse`` env's dense variant, named so); and
    whether those words tell that reward apart, so that a diagnosis kept under them is of it alone: the env's
    own, or another env's named by ``dense_variant``. A function's name does not tell its body or arguments,
    nor a class the envs built of it (Playground's cart-poles are all one class)."""
    if surrogate_reward is not None:
        return f"the reward {function_name(surrogate_reward)}", False
    if reward_env is None:
        return "", True
    if dense_variant:
        return f"the reward of {dense_variant}, its dense variant", True
    return f"the reward of {type(reward_env).__name__}", False


def check_surrogate_reward(env: Any, step: Callable, reward: Callable, label: str) -> bool:
    """``EnvError`` in one line naming ``reward`` (a surrogate of the user's, ``reward(state reached)``)
    where its signature or tracing it on the state ``step`` reaches shows it cannot be trained on: it
    takes other arguments, fails (the user's own message), or returns other than one float per state.
    Traced with shapes only; True where all holds. Its gradient is the reward diagnosis's to look at."""
    named = f"{label}: the surrogate reward {function_name(reward)}"
    try:
        signature = inspect.signature(reward)
    except (TypeError, ValueError):  # no signature to read (a builtin): calling it tells
        signature = None
    if signature is not None:
        try:
            signature.bind(None)
        except TypeError:
            raise EnvError(f"{named} takes ({', '.join(signature.parameters)}): it is called with one argument, the state a step reaches "
                           "(reward(state) -> one number)") from None
    state = jax.eval_shape(env.reset, jax.random.PRNGKey(0))
    reached = jax.eval_shape(step, state, jax.ShapeDtypeStruct((int(env.action_size),), jnp.float32))
    returned = []  # what the reward returned, where it is not an array

    def call(reached):
        value = reward(reached)
        if isinstance(value, (jax.Array, np.ndarray, np.generic, numbers.Number)):
            return jnp.asarray(value)
        returned.append(value)
        return None

    try:
        value = jax.eval_shape(call, reached)
    except Exception as error:  # noqa: BLE001 - the user's reward failed: one line naming it, with its message
        raise EnvError(f"{named} fails on the state a step reaches: {first_line(error)}") from None
    if returned:
        shown = repr(returned[0])
        raise EnvError(f"{named} returns {type(returned[0]).__name__} ({shown if len(shown) <= 60 else shown[:57] + '...'}), "
                       "not a number: it must return one float per state, the reward of the state a step reaches")
    if value.shape != ():
        raise EnvError(f"{named} returns an array of shape {value.shape} for one state: it must return one number "
                       "per state (the reward of the state a step reaches; a sum or a norm of a vector?)")
    if not jnp.issubdtype(value.dtype, jnp.floating):
        raise EnvError(f"{named} returns {value.dtype}, not a float: a reward of whole numbers or truths has no "
                       "gradient to follow (compute it in floats, e.g. a distance's negative square)")
    return True


def _first_difference(state: Any, reached: Any) -> str | None:
    """How a step's returned state ``reached`` first differs from the ``state`` it was given (its tree,
    then a leaf's shape or dtype), in words that follow "step(state, action)"; None where none does."""
    given, got = jax.tree.structure(state), jax.tree.structure(reached)
    if given != got:
        return f"must return a state of the tree it is given: reset gives {_tree_text(given)}, step returns {_tree_text(got)}"
    for (path, before), after in zip(jax.tree_util.tree_leaves_with_path(state), jax.tree.leaves(reached)):
        if (before.shape, before.dtype) != (after.shape, after.dtype):
            return (f"changes state{jax.tree_util.keystr(path)} from {before.dtype}{list(before.shape)} to "
                    f"{after.dtype}{list(after.shape)}: a state keeps its shapes and dtypes from step to step")
    return None


def _tree_text(structure: Any) -> str:
    text = str(structure)
    return text if len(text) <= 200 else text[:197] + "..."


def load_env(spec: str) -> Any:
    """The environment ``spec`` names: ``package.module:attribute`` (an environment, or a class or
    factory called without arguments), else a name in MuJoCo Playground's registry.

    Whether it follows Brax's protocol is ``env_task``'s check, made once where the environment is
    used: reading ``observation_size`` may trace ``reset``, which a rendering has no need of."""
    if not isinstance(spec, str):
        raise EnvError(f"an environment is named by a string, a name in MuJoCo Playground's registry or "
                       f"package.module:attribute; got {spec!r}")
    if ":" not in spec:
        from stablebptt.envs import playground
        return playground.load(spec)
    found, attribute = import_attribute(spec, "environment")
    if not all(hasattr(found, name) for name in ("reset", "step")) or isinstance(found, type):
        if not callable(found):
            raise EnvError(f"environment {spec}: {attribute} is neither an environment nor a factory of one")
        try:
            found = found()
        except Exception as error:  # noqa: BLE001 - the user's factory failed: say so in one line
            raise EnvError(f"environment {spec}: {attribute}() failed ({type(error).__name__}: {error})") from None
    return found


def load_reward(spec: str) -> Callable[[PyTree], jax.Array]:
    """The function ``package.module:function`` names: a reward of the state a step reaches, trained on in
    place of an environment's own (``env_task(surrogate_reward=...)``)."""
    if ":" not in spec:
        raise EnvError(f"surrogate reward {spec}: give it as package.module:function, a reward of the state a step reaches")
    found, attribute = import_attribute(spec, "surrogate reward")
    if not callable(found) or isinstance(found, type):
        raise EnvError(f"surrogate reward {spec}: {attribute} is not a function of the state a step reaches")
    return found


def import_attribute(spec: str, what: str) -> tuple[Any, str]:
    """(the attribute ``package.module:attribute`` names, its name); ``EnvError`` in one line, naming ``what``
    ``spec`` was to be, where the module cannot be imported or lacks it."""
    module_name, _, attribute = spec.partition(":")
    if not module_name.strip() or not attribute.strip():
        raise EnvError(f"{what} {spec!r}: give package.module:attribute, a module and one of its names")
    # A user's module is found where Python finds modules, and in the folder the command runs in, as
    # `python -m` would (an installed command's path holds only its own folder); last, so that it
    # shadows no installed package.
    if os.getcwd() not in sys.path and "" not in sys.path:
        sys.path.append(os.getcwd())
    try:
        module = importlib.import_module(module_name)
    except ImportError as error:
        raise EnvError(f"{what} {spec}: cannot import {module_name} ({error})") from None
    except Exception as error:  # noqa: BLE001 - the user's module failed as it ran (a SyntaxError too): one line
        where = f" (line {error.lineno})" if isinstance(error, SyntaxError) and error.lineno else ""
        raise EnvError(f"{what} {spec}: importing {module_name} failed{where}: "
                       f"{type(error).__name__}: {error.msg if isinstance(error, SyntaxError) else error}") from None
    if not attribute or not hasattr(module, attribute):
        raise EnvError(f"{what} {spec}: {module_name} has no attribute {attribute!r}")
    return getattr(module, attribute), attribute


def with_reset_traced_once(env: Any) -> Any:
    """A shallow copy of ``env`` whose ``reset`` is jitted, so that JAX traces the env's reset once per key
    shape and every program and check that resets reuses that trace: the protocol's check, the reward
    diagnosis, the initial states, init's first population and each epoch's refill. CheetahRun's reset
    settles its states for 200 physics steps: traced by each of them, it made the start's trace phase
    27-32 s on the 2-core CPU, traced once 4-5 s (docs/performance.md, "Start-up against Brax PPO's
    compile"). The reset is traced as the steps are, with MJX's acceleration sensors computed where a model
    has no constraint rows (``sensors_as_c_computes``: MuJoCo's C values, where MJX leaves zeros).
    ``env`` itself is left as it is; one whose attributes cannot be set is used as it is."""
    copied = copy.copy(env)

    def reset(key):  # traced as the steps are: MJX's acceleration sensors computed where it leaves zeros
        with sensors_as_c_computes():
            return env.reset(key)

    try:
        copied.reset = jax.jit(reset)
    except (AttributeError, TypeError):  # a frozen dataclass's FrozenInstanceError is an AttributeError
        return env
    return copied
