"""What a user hands the library, checked once before anything compiles.

``check_task`` traces a ``Task`` with shapes only (``jax.eval_shape``: nothing
runs): the initial-state sampler's leading size, float parameters, a control
the step accepts, a step that returns the state's own structure, a scalar
loss, a ``Plan`` as the task's plan (a ``Plan`` checks its own fields when
it is made; its known columns are checked against the state here), and its
``Episodes``' functions on one state. Each failure is a ``TaskError`` that names the field and what was
found, instead of an error deep inside JAX.
``check_options`` refuses options given together where one makes the other
meaningless, before a run records both as if they applied.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from stablebptt.engine.episodes import Episodes
from stablebptt.engine.shapes import tracing_shapes
from stablebptt.engine.task import Task
from stablebptt.errors import InputError, TaskError, config_field, users_call
from stablebptt.flows.dynamics import Dynamics, Plan, check_dynamics, check_known_columns, one_state_shape, split
from stablebptt.flows.modes import flows_needed


def parameter_shapes(task: Any, zero_output: bool) -> Any:
    """The shapes of ``task.init_params(key, zero_output)``, traced with no values (``tracing_shapes``)."""
    with tracing_shapes():
        return jax.eval_shape(lambda key: task.init_params(key, zero_output), jax.random.PRNGKey(0))


def _describe(tree: Any) -> str:
    leaves = jax.tree.leaves(tree)
    # a user's function may return Python numbers or lists where arrays belong
    shown = ", ".join(f"{getattr(leaf, 'dtype', type(leaf).__name__)}{list(jnp.shape(leaf))}" for leaf in leaves[:4])
    return f"{jax.tree.structure(tree)} with leaves {shown}{', ...' if len(leaves) > 4 else ''}"


def require_task(task: Any) -> None:
    """Raise ``TaskError`` unless ``task`` is a ``Task`` whose fields are of their kinds (no tracing): before
    anything reads them."""
    if not isinstance(task, Task):
        raise TaskError(f"expected a stablebptt.Task, got {type(task).__name__}")
    for name, kind, words in (("dynamics", Dynamics, "a stablebptt.Dynamics"), ("plan", Plan, "a stablebptt.Plan"),
                              ("episodes", (Episodes, type(None)), "a stablebptt.Episodes or None")):
        if not isinstance(getattr(task, name), kind):
            raise TaskError(f"Task.{name} must be {words}, got {type(getattr(task, name)).__name__}")
    if not isinstance(task.name, str):  # it names the run's folder and every message about the task
        raise TaskError(f"Task.name must be a string, got {task.name!r}")
    for name in ("init_params", "sample_initial_states"):
        if not callable(getattr(task, name)):
            raise TaskError(f"Task.{name} must be a function, got {getattr(task, name)!r}")
    for name in ("evaluation", "settle", "refresh_statistics"):
        if not (getattr(task, name) is None or callable(getattr(task, name))):
            raise TaskError(f"Task.{name} must be a function or None, got {getattr(task, name)!r}")


def evaluated(task: Task, params: Any, initial_states: Any) -> jax.Array:
    """``task.evaluation(params, initial_states)``, checked as it is traced: one float loss per state, or
    ``TaskError`` (a loss of another shape would be averaged, or its states mixed, without a word)."""
    losses = task.evaluation(params, initial_states)
    count = jax.tree.leaves(initial_states)[0].shape[0]
    if not (hasattr(losses, "shape") and losses.shape == (count,) and jnp.issubdtype(losses.dtype, jnp.floating)):
        raise TaskError(f"Task.evaluation(params, initial_states) must return one float loss per initial state "
                        f"(float[{count}] for {count} states), got {_describe(losses)}")
    return losses


def check_task(task: Any, zero_output: bool = True, counts: tuple[int, ...] = (2,)) -> None:
    """Trace ``task`` with shapes only and raise ``TaskError`` naming the first field that does not fit;
    its sampler at each of ``counts`` (a trainer's: the counts it draws, so that an environment's batched
    reset, a large trace, is traced for no other)."""
    require_task(task)
    dynamics = task.dynamics
    check_dynamics(dynamics)
    key = jax.random.PRNGKey(0)
    params = users_call("Task.init_params(key, zero_output) fails", lambda: parameter_shapes(task, zero_output))
    not_float = [leaf for leaf in jax.tree.leaves(params) if not jnp.issubdtype(leaf.dtype, jnp.floating)]
    if not jax.tree.leaves(params) or not_float:
        raise TaskError(f"Task.init_params must return float parameters to train, got {_describe(params)}")
    for count in dict.fromkeys(counts):
        states = users_call(f"Task.sample_initial_states(key, {count}) fails",
                            lambda: jax.eval_shape(lambda k: task.sample_initial_states(k, count), key))
        sizes = {leaf.shape[0] if leaf.ndim else None for leaf in jax.tree.leaves(states)}
        if sizes != {count}:
            raise TaskError(f"Task.sample_initial_states(key, {count}) must return {count} states (every leaf's "
                            f"leading axis {count}), got {_describe(states)}")
    state = one_state_shape(states)
    control = users_call("Dynamics.policy(params, state) fails on one sampled state",
                         lambda: jax.eval_shape(dynamics.policy, params, state))
    reached = users_call(f"Dynamics.step(state, control) fails on one sampled state and the policy's control "
                         f"({_describe(control)})", lambda: jax.eval_shape(dynamics.step, state, control))
    pairs = list(zip(jax.tree.leaves(reached), jax.tree.leaves(state)))
    shaped_alike = jax.tree.structure(reached) == jax.tree.structure(state) and all(a.shape == b.shape for a, b in pairs)
    if not (shaped_alike and all(a.dtype == b.dtype for a, b in pairs)):
        raise TaskError(f"Dynamics.step must return a state like the one it is given ({_describe(state)}), "
                        f"got {_describe(reached)}" + ("; only the dtypes differ: the step keeps those of the states "
                                                       "Task.sample_initial_states gives (floats where it computes "
                                                       "in floats)" if shaped_alike else ""))
    over_time = lambda tree: jax.tree.map(  # noqa: E731
        lambda leaf: jax.ShapeDtypeStruct((dynamics.horizon,) + leaf.shape, leaf.dtype), tree)
    loss = users_call(f"Dynamics.loss(states, controls) fails on a rollout of {dynamics.horizon} steps",
                      lambda: jax.eval_shape(dynamics.loss, over_time(state), over_time(control)))
    if not (hasattr(loss, "shape") and loss.shape == () and jnp.issubdtype(loss.dtype, jnp.floating)):
        raise TaskError(f"Dynamics.loss must return one float for a trajectory, got {_describe(loss)}")
    if task.plan.known_columns is not None:  # the memory plan counts them before the Jacobians are traced
        check_known_columns(task.plan.known_columns, sum(leaf.size for leaf in split(state).floats))
    if task.episodes is not None:
        check_episodes(task.episodes, state)


def _one_float(out) -> bool:
    return out.shape == () and jnp.issubdtype(out.dtype, jnp.floating)


def _one_bool(out) -> bool:
    return out.shape == () and out.dtype == jnp.bool_


# What each function of a task's Episodes returns for one state, as a window's loop reads it: (words, test).
# done is negated (a number reads as its truth); gradient_cut is and-ed with a mask, which takes a bool alone.
EPISODE_OUTPUTS = {
    "reward": ("one float", _one_float),
    "done": ("one bool or number",
             lambda out: _one_bool(out) or (out.shape == () and jnp.issubdtype(out.dtype, jnp.number))),
    "gradient_cut": ("one bool", _one_bool),
    "observe": ("a float vector", lambda out: out.ndim == 1 and jnp.issubdtype(out.dtype, jnp.floating))}


def check_episodes(episodes: Episodes, state: Any) -> None:
    """``TaskError`` naming the first function of ``episodes`` that fails on one sampled ``state`` (shapes
    only), or returns another shape than a window's loop reads (a vector reward was summed into every
    env's return, or broadcast over the batch, without a word). Its reset is not traced here: an env's
    reset is a large trace, which a start would pay for twice; a task's sampler, traced above, draws from it
    in the library's tasks."""
    for name, (words, holds) in EPISODE_OUTPUTS.items():
        function = getattr(episodes, name)
        if function is None:
            continue
        out = users_call(f"Episodes.{name}(state) fails on one sampled state", lambda: jax.eval_shape(function, state))
        if not (hasattr(out, "shape") and holds(out)):
            raise TaskError(f"Episodes.{name}(state) must return {words} for one state, got {_describe(out)}")


def _given(config: Any, name: str) -> bool:
    """Whether field ``name`` of a dataclass config differs from its default (was set by the user)."""
    field = next(f for f in dataclasses.fields(config) if f.name == name)
    return getattr(config, name) != field.default


def train_conflicts(config: Any) -> list[str]:
    """The ``TrainConfig`` options set together where one makes the other meaningless, one message each."""
    field = lambda name: config_field(config, name)  # noqa: E731
    problems = []
    if config.clip == "none" and _given(config, "clip_threshold"):
        problems.append(f"{field('clip_threshold')} {config.clip_threshold:g} has no effect with {field('clip')} none: "
                        f"drop it, or clip by value or norm")
    if config.seeds == 1 and _given(config, "seed_batching"):
        problems.append(f"{field('seed_batching')} {config.seed_batching} says how seeds share a program, and "
                        f"{field('seeds')} is 1: drop it, or train several seeds")
    if not config.cosine and {"M", "R"} <= set(flows_needed(config.mode, with_cosine=False)):
        problems.append(f"{field('cosine')} is off, but mode {config.mode} computes g_M and g_R anyway and logs "
                        f"their cosine: leave {field('cosine')} on")
    for name, what in (("critic_lr", "the critic's learning rate"), ("td_lambda", "the critic's TD(lambda) targets"),
                       ("critic_width", "the critic's layers' width"), ("critic_depth", "the critic's layers"),
                       ("critics", "the critic's networks")):
        if not config.critic and _given(config, name):
            problems.append(f"{field(name)} {getattr(config, name):g} sets {what}, and {field('critic')} is off: "
                            f"drop it, or train with {field('critic')}")
    for name, what in (("normalize_critic_observations", "standardises what the critic sees"),
                       ("value_at_time_limit", "values the state a time limit cuts an episode at by the critic"),
                       ("value_at_gradient_cut", "values the states the task's step cuts the derivative at by the critic")):
        if not config.critic and getattr(config, name):
            problems.append(f"{field(name)} {what}, and {field('critic')} is off: drop it, or train with {field('critic')}")
    if config.nonfinite_flows == "zero" and config.mode != "C":
        problems.append(f"{field('nonfinite_flows')} zero leaves a flow's non-finite gradient at zero as mode C's "
                        f"sign agreement does, and mode {config.mode}'s update is that gradient itself: use mode C, or stop")
    return problems


def check_options(train_config: Any, task_config: Any = None) -> None:
    """Refuse options set together where one makes the other meaningless (a new run would record
    both as if they applied): ``train_conflicts`` and the task config's own ``conflicts()``.

    Raises:
      InputError: naming the options and what to do, the first conflict found.
    """
    problems = train_conflicts(train_config)
    if task_config is not None and hasattr(task_config, "conflicts"):
        problems += task_config.conflicts()
    if problems:
        raise InputError(problems[0])
