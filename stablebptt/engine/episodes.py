"""Training on carried episodes: states kept from one update to the next, one window of each per update.

The paper's protocol trains every update from fixed initial states, one window from each, so a policy
never meets a state past the window's end. A task with ``Episodes`` may train on whole episodes
instead, as the field's first-order trainers do: a population of states is carried from update to
update (``Carried``, part of the training state and of every checkpoint); each update rolls every
state one window of the horizon further, the gradient stopped at the window's start; a state whose
episode is over (done, or at the episode's length) starts again between windows from a fresh state
of the carried pool, which an epoch's first update draws (one reset per env: about the episodes an
epoch ends); and the episodes' clocks start spread over an episode, so that the windows cover
every phase of it from the first update on. An episode started again begins with the next window,
so the clocks stay spread to within a window; the steps a window rolls past an episode's end (half
a window per episode, on average) are simulated and count for nothing.

Within a window the flows roll a ``Window``: the task's state, its episode clock, whether its
episode still runs, and the reward of the step that reached it. Once an episode ends its state stays
as it was before the end and its rewards count no more, so no state past an episode's end (a NaN
one, say) reaches the policy or the loss. An episode that reaches its length is cut there, not ended
by its task; with ``window_dynamics(value_at_time_limit=True)`` the state it reached is kept and
valued (``Window.cut``), as if the episode went on.
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, replace
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from stablebptt.engine.shapes import shapes_only
from stablebptt.errors import InputError, keywords_named
from stablebptt.flows.dynamics import Dynamics, PyTree

# The stream of a seed's PRNG keys that its episodes' resets draw from; the parameters draw from the seed itself.
RESET_STREAM = 1
# The stream of the carried key that a window's exploration noise draws from (its resets split the key itself).
NOISE_STREAM = 3


@keywords_named
@dataclass(frozen=True)
class Episodes:
    """What a task knows of its episodes, to train on carried ones (``Task.episodes``).

    Attributes:
      reset: ``reset(key) -> state``, one state at an episode's start (the task's state, as ``Dynamics.step`` takes).
      reward: ``reward(state) -> scalar``, the reward of the step that reached ``state``.
      done: ``done(state) -> bool`` (or a number, read as its truth), whether the episode ends at ``state``
        before its length.
      length: steps of an episode.
      discount: per-step discount of a window's return, in (0, 1].
      observe: ``observe(state) -> vector``, what a learned value sees (``TrainConfig.critic``); None: no critic.
      step: ``step(state, action) -> state``, the step of the episodes whose return is reported, where the
        windows train on another reward (an environment's own step beside a surrogate's); None: the
        task's ``Dynamics.step``.
      gradient_cut: ``gradient_cut(state) -> bool``, whether the task's step stops a window's derivative at
        ``state`` (its ``Dynamics.step`` holds such a state constant as it starts from it), which a critic
        may value there (``window_dynamics(value_at_gradient_cut=True)``); None: the step cuts nowhere.
      pool_per_env: fresh states the carried pool holds per env, about the episodes each env starts in an
        epoch (more than 1 where training cuts episodes sooner than an epoch's steps: each start its own).
    """

    reset: Callable[[jax.Array], PyTree]
    reward: Callable[[PyTree], jax.Array]
    done: Callable[[PyTree], jax.Array]
    length: int
    discount: float = 1.0
    observe: Callable[[PyTree], jax.Array] | None = None
    step: Callable[[PyTree, PyTree], PyTree] | None = None
    gradient_cut: Callable[[PyTree], jax.Array] | None = None
    pool_per_env: int = 1

    def __post_init__(self):
        for name in ("reset", "reward", "done"):
            if not callable(getattr(self, name)):
                raise InputError(f"Episodes.{name} must be a function, got {type(getattr(self, name)).__name__}")
        for name in ("step", "gradient_cut"):
            if getattr(self, name) is not None and not callable(getattr(self, name)):
                raise InputError(f"Episodes.{name} must be a function or None, got {type(getattr(self, name)).__name__}")
        for name in ("length", "pool_per_env"):
            value = getattr(self, name)
            if not isinstance(value, numbers.Integral) or isinstance(value, bool) or value < 1:
                raise InputError(f"Episodes.{name} must be a positive whole number, got {value!r}")
        discount = self.discount
        if not (isinstance(discount, numbers.Real) and not isinstance(discount, bool) and math.isfinite(discount)
                and 0 < discount <= 1):
            raise InputError(f"Episodes.discount must be a number in (0, 1], got {discount!r}")


class Carried(NamedTuple):
    """The population a trainer of episodes carries from update to update (one seed's)."""

    states: PyTree  # [envs, ...] where each episode stands
    clocks: jax.Array  # int32 [envs]: steps into each episode
    key: jax.Array  # the PRNG key the next resets draw from
    pool: PyTree = None  # [envs, ...] fresh states an ended episode starts again from (``continue_from``)
    pool_used: jax.Array | None = None  # int32: the pool's states taken since it was drawn (``refill_pool``)


class Window(NamedTuple):
    """A state within a window, as the flows roll it."""

    state: PyTree
    clock: jax.Array  # int32: steps into its episode
    running: jax.Array  # bool: its episode has not ended
    reward: jax.Array  # the reward of the step that reached it (0 once the episode has ended)
    noise_key: jax.Array | None = None  # with exploration noise: the key its actions' noise draws from
    # bool: the step that reached it cut its episode at the episode's length (a time limit, not the task's end),
    # and the state is valued there (``window_dynamics(value_at_time_limit=True)``); else None, the program unchanged
    cut: jax.Array | None = None


class Exploring(NamedTuple):
    """What a window differentiates where its noise's scale is learned (``window_dynamics(learned_noise=True)``):
    the policy's parameters and the log standard deviation of each action's noise, a tree shaped as the action."""

    policy: PyTree
    log_std: PyTree


def window_dynamics(dynamics: Dynamics, episodes: Episodes, window: int,
                    value: Callable[[PyTree], jax.Array] | None = None, action_noise: float = 0.0,
                    learned_noise: bool = False, value_at_time_limit: bool = False,
                    value_at_gradient_cut: bool = False) -> Dynamics:
    """``dynamics`` over ``Window`` states: a window of ``window`` steps whose loss is its negative
    (discounted) return, rewards after its episode's end left out; with ``value`` (of a task's state),
    plus the discounted value of the window's last state where its episode still runs there.

    With ``action_noise``, every action gets Gaussian noise of that standard deviation, drawn from the
    state's ``noise_key`` and its clock (``start_window``), so a flow that evaluates the policy again at a
    visited state sees the same noise. The noise does not depend on the parameters: the gradient is the
    policy's own, taken along the noisy trajectory. With ``learned_noise`` the parameters are ``Exploring``:
    each action's noise is its standard deviation ``exp(log_std)`` times the same draw, so the window's
    gradient reaches the deviations too (reparameterised, as SHAC's stochastic actor learns them).

    With ``value_at_time_limit``, an episode the window cuts at its length (a time limit: the task did not
    end it) keeps the state it reached, marked ``cut``, and with ``value`` the loss adds that state's
    discounted value where the window's last state would have added its own: the time limit is not
    taken for the end of what the policy can still earn, which its observations do not show.

    With ``value_at_gradient_cut`` and ``value``, where the task's step stops the derivative at a state
    (``Episodes.gradient_cut``), the actions before that state are also pulled by its discounted value's
    derivative, as a window ended there would be (AHAC's windows end where contact forces spike); the
    loss's value is unchanged, the later rewards reaching those actions through the cut no more."""
    def step(current: Window, control) -> Window:
        reached = dynamics.step(current.state, control)
        clock = current.clock + 1
        goes_on = current.running & jnp.logical_not(episodes.done(reached))
        still = goes_on & (clock < episodes.length)
        cut = goes_on & (clock >= episodes.length) if value_at_time_limit else None
        # where, not a product: the value of a step past the end (a NaN, say) must not leak in.
        reward = jnp.where(current.running, episodes.reward(reached), 0.0)
        kept = still if cut is None else still | cut
        state = jax.tree.map(lambda new, old: jnp.where(kept, new, old), reached, current.state)
        return Window(state, jnp.where(current.running, clock, current.clock), still, reward, current.noise_key, cut)

    def loss(states: Window, controls) -> jax.Array:
        weights = episodes.discount ** jnp.arange(window, dtype=states.reward.dtype)
        total = jnp.sum(weights * states.reward)
        if value is not None:  # a loss on the last state: its gradient reaches that state, in every flow
            last = jax.tree.map(lambda a: a[-1], states)
            last_value = value(last.state)
            total = total + episodes.discount ** window * jnp.where(last.running, last_value, 0.0)
            if value_at_time_limit:  # a cut episode's state stays where the limit cut it: the last state, valued
                at_cut = jnp.sum(jnp.where(states.cut, episodes.discount * weights, 0.0))  # at the cut's discount
                total = total + jnp.where(jnp.any(states.cut), at_cut * last_value, 0.0)
            if value_at_gradient_cut:  # the last state is valued above; before it, a value of zero with a slope
                inner = jax.tree.map(lambda a: a[:-1], states)
                values = jax.vmap(value)(inner.state)
                held = jax.vmap(episodes.gradient_cut)(inner.state) & inner.running
                slope_only = values - jax.lax.stop_gradient(values)
                total = total + jnp.sum(jnp.where(held, episodes.discount * weights[:-1] * slope_only, 0.0))
        return -total

    def policy(params, current: Window):
        if not learned_noise:
            control = dynamics.policy(params, current.state)
            if action_noise == 0:
                return control
            deviations = jax.tree.map(lambda _: action_noise, control)
        else:
            control = dynamics.policy(params.policy, current.state)
            deviations = jax.tree.map(jnp.exp, params.log_std)
        keys = jax.random.split(jax.random.fold_in(current.noise_key, current.clock), len(jax.tree.leaves(control)))
        noise = jax.tree.unflatten(jax.tree.structure(control), [
            jax.random.normal(key, jnp.shape(leaf), jnp.result_type(leaf)) for key, leaf in
            zip(keys, jax.tree.leaves(control))])
        return jax.tree.map(lambda c, d, n: c + d * n, control, deviations, noise)

    return Dynamics(step=step, policy=policy, loss=loss, horizon=window)


# The learned noise's deviations stay within these (an action's range is [-1, 1] where a policy squashes it):
# the entropy's pull has no other counterweight where the return is flat in the noise.
DEVIATION_BOUNDS = (1e-3, 1.0)


def initial_log_std(control: PyTree, action_noise: float) -> PyTree:
    """The learned noise's first log deviations: ``action_noise`` for every action (a tree shaped as ``control``)."""
    return jax.tree.map(lambda leaf: jnp.full(jnp.shape(leaf), math.log(action_noise), jnp.result_type(leaf)), control)


def bounded_log_std(log_std: PyTree) -> PyTree:
    low, high = (math.log(bound) for bound in DEVIATION_BOUNDS)
    return jax.tree.map(lambda leaf: jnp.clip(leaf, low, high), log_std)


def entropy_gradient(log_std: PyTree, discount: float, window: int, coefficient: float) -> PyTree:
    """The gradient, in the log deviations, of a window loss's entropy term: less ``coefficient`` times the
    noise's entropy at each step, discounted as the rewards are. A Gaussian's entropy is its log deviation
    plus a constant per action, the same at every state, so the gradient is a constant."""
    weight = coefficient * sum(discount ** step for step in range(window))
    return jax.tree.map(lambda leaf: jnp.full_like(leaf, -weight), log_std)


def start_window(carried: Carried, reward_dtype, noise: bool = False, value_at_time_limit: bool = False) -> Window:
    """The carried states as the first states of a window: every episode running; with ``noise``, each
    with a key of its own for the window's exploration noise; with ``value_at_time_limit``, none yet cut
    (as ``window_dynamics`` is given)."""
    envs = carried.clocks.shape[0]
    keys = jax.random.split(jax.random.fold_in(carried.key, NOISE_STREAM), envs) if noise else None
    return Window(carried.states, carried.clocks, jnp.ones(envs, bool), jnp.zeros(envs, reward_dtype), keys,
                  jnp.zeros(envs, bool) if value_at_time_limit else None)


def continue_from(final: Window, carried: Carried) -> Carried:
    """The population after a window: each ended episode starts again from the next fresh state of the
    carried ``pool`` (in the envs' order; past its end, from its start again), the others go on where the
    window left them. No reset runs here: a reset may cost far more than a window (Playground's cheetah
    settles its model for 200 physics steps, which a GPU runs one after another), so ``refill_pool``
    draws the fresh states once an epoch, about one per env (``Episodes.pool_per_env`` per env where
    training cuts episodes sooner, ``TrainConfig.training_episode_length``)."""
    ended = jnp.logical_not(final.running)
    pool_size = jax.tree.leaves(carried.pool)[0].shape[0]
    taken = (carried.pool_used + jnp.cumsum(ended) - 1) % pool_size  # the ended envs' pool states, in turn
    fresh = jax.tree.map(lambda pool: pool[taken], carried.pool)
    states = jax.tree.map(lambda new, old: jnp.where(_along(ended, old), new, old), fresh, final.state)
    return carried._replace(states=states, clocks=jnp.where(ended, 0, final.clock).astype(jnp.int32),
                            key=jax.random.split(carried.key)[0],  # the next window's noise draws anew
                            pool_used=carried.pool_used + jnp.sum(ended, dtype=jnp.int32))


def refill_pool(carried: Carried, episodes: Episodes) -> Carried:
    """``carried`` with a fresh pool: ``episodes.pool_per_env`` resets per env, each from a key of its own split
    from the carried key."""
    key, resets = jax.random.split(carried.key)
    envs = carried.clocks.shape[0]
    return carried._replace(key=key, pool=_reset(episodes, resets, envs * episodes.pool_per_env),
                            pool_used=jnp.zeros((), jnp.int32))


def checkpointed(state: Any) -> Any:
    """What a checkpoint keeps of a trainer's ``state`` (``TrainState``): all but its carried population's pool,
    which every epoch draws afresh as it begins (``refill_pool``) before an update reads it. Cut at N steps
    (``cut_sooner``) the pool holds ceil(length / N) states per env: HopperStand's cut at 64 kept 16 of every
    17 states it carried in a checkpoint of 136.2 MiB (benchmarks/update_program.py --programs state)."""
    return state if state.carried is None else state._replace(carried=state.carried._replace(pool=None))


def restored(kept: Any, template: Any) -> Any:
    """A ``checkpointed`` state whole again, shaped as ``template``: its pool zeros until the epoch's refill."""
    pool = None if template.carried is None else jax.tree.map(lambda leaf: np.zeros(leaf.shape, leaf.dtype),
                                                              template.carried.pool)
    return kept if pool is None else kept._replace(carried=kept.carried._replace(pool=pool))


def first_population(seed_key: jax.Array, episodes: Episodes, envs: int, window: int) -> Carried:
    """A seed's first population: ``envs`` fresh episodes whose clocks are spread uniformly over an
    episode where a window is shorter than one (so that the windows cover every phase of it), else at 0.
    Its pool holds those states (and ``pool_per_env - 1`` more per env) until an epoch's first update draws
    fresh ones (``refill_pool``)."""
    key = jax.random.fold_in(seed_key, RESET_STREAM)
    key, resets, clocks = jax.random.split(key, 3)
    pool = _reset(episodes, resets, envs * episodes.pool_per_env)
    states = jax.tree.map(lambda leaf: leaf[:envs], pool)
    if window < episodes.length:
        start = jax.random.randint(clocks, (envs,), 0, episodes.length, dtype=jnp.int32)
    else:
        start = jnp.zeros(envs, jnp.int32)
    return Carried(states, start, key, pool, jnp.zeros((), jnp.int32))


def _reset(episodes: Episodes, key: jax.Array, envs: int) -> Any:
    """``envs`` fresh states, each from a key of its own split from ``key``, every leaf strongly typed: a
    reset may give weakly typed leaves (an MJX state's time, a Python float), which a checkpoint's
    arrays read back do not carry, and a resume then compiled every program again for its state.
    Traced for shapes alone (``tracing_shapes``), stand-ins of one reset's shapes: the batched reset is
    a large trace (docs/performance.md, "The population's shapes from one reset"), and its shapes are
    one reset's with a leading axis of ``envs``."""
    keys = jax.random.split(key, envs)
    if shapes_only():
        one = jax.eval_shape(episodes.reset, jax.ShapeDtypeStruct(keys.shape[1:], keys.dtype))
        return jax.tree.map(lambda leaf: jnp.zeros((envs, *leaf.shape), leaf.dtype), one)
    states = jax.vmap(episodes.reset)(keys)
    return jax.tree.map(lambda leaf: jax.lax.convert_element_type(leaf, leaf.dtype), states)


def cut_sooner(episodes: Episodes, length: int, option: str, name: str) -> Episodes:
    """The episodes training carries where ``option`` cuts the task ``name``'s ``episodes`` at ``length``
    steps (``TrainConfig.training_episode_length``): each starts again from a pool state of its own."""
    if length >= episodes.length:
        raise InputError(f"{option} {length}: {name}'s episodes are {episodes.length} steps; cut them sooner, or "
                         "drop it")
    return replace(episodes, length=length, pool_per_env=-(-episodes.length // length))


def updates_per_epoch(episodes: Episodes, window: int) -> int:
    """An epoch of episode training: enough windows that every state advances one episode's length."""
    return max(1, -(-episodes.length // window))


def _along(flags: jax.Array, leaf: jax.Array) -> jax.Array:
    """Per-example ``flags`` [envs] broadcast against a leaf [envs, ...]."""
    return flags.reshape(flags.shape + (1,) * (jnp.ndim(leaf) - 1))


def cut_short(batches: jax.Array, updates: int) -> jax.Array:
    """An epoch's batches (training on episodes: its updates' numbers) with all but the first ``updates``
    made negative, which ``skipping`` leaves out: the epoch's own program then runs an epoch cut short,
    with nothing compiled again (a budget's last epoch: ``fitting.fit``)."""
    if not 1 <= updates <= len(batches):
        raise InputError(f"an epoch of {len(batches)} updates is cut to 1 of them or more, got {updates}")
    every = np.arange(len(batches))
    return jax.device_put(np.where(every < updates, every, -1).astype(batches.dtype), batches.sharding)


def skipping(update: Callable, skipped: Any) -> Callable:
    """``update(state, number) -> (state, output)`` as an epoch's step that leaves the state as it was
    where ``number`` < 0, its output then ``skipped``, whose dtypes the update's output is cast to."""
    def taken(state, number):
        state, output = update(state, number)
        return state, jax.tree.map(lambda value, like: jnp.asarray(value).astype(like.dtype), output, skipped)

    return lambda state, number: jax.lax.cond(number >= 0, taken, lambda state, _: (state, skipped), state, number)
