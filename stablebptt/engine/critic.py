"""A learned value at a window's end (``TrainConfig.critic``), as short-horizon actor-critic trains.

The actor's loss of a window becomes its discounted rewards plus the discounted value of the state
it ends in, where that state's episode still runs (``window_dynamics(value=...)``). That term is a
loss on the window's last state, so its gradient reaches that state and enters every flow as the
loss's own gradient does, cut by none of them. The value is the target critic's, which follows the
critic slowly. After each window the critic, a network of the observation with its own Adam, is
fitted to TD(lambda) targets computed from the window's rewards and the target critic's values.
Where asked (``TrainConfig.normalize_critic_observations``) the critic sees its observations
standardised by statistics of its own, refreshed from every window's states before it is fitted.
With several networks (``TrainConfig.critics``, ``Members``) each is fitted to the same targets and
the least of their values is the critic's, in the targets and in the window's loss (TD3's clipped
double learning): the actor, which follows the value's gradient, finds no state one network alone
overvalues.
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import optax

from stablebptt.engine.observations import ObservationStatistics, no_observations, standardized, with_observations
from stablebptt.flows.dynamics import PyTree
from stablebptt.networks import mlp_apply, mlp_init

# Short-horizon actor-critic's settings: Adam steps on a window's targets, and the share of the target
# critic kept at each window (the rest is the critic's).
ITERATIONS = 16
TARGET_KEEP = 0.2
# The stream of a seed's PRNG keys the critic's initial weights draw from (the resets draw from 1).
CRITIC_STREAM = 2


class Members(NamedTuple):
    """Several networks' weights stacked along a leading axis, valued as one by their least value."""

    stacked: PyTree


class Critic(NamedTuple):
    """One seed's critic: its weights, its optimizer's state, the target critic that follows it, and the
    statistics that standardise what it sees (None: it sees raw observations)."""

    params: PyTree
    opt_state: PyTree
    target: PyTree
    statistics: ObservationStatistics | None = None


def value(params: PyTree, observation: jax.Array) -> jax.Array:
    """The value of one observation: the network's, or the least of ``Members``'."""
    return jnp.min(members_values(params, observation))


def members_values(params: PyTree, observation: jax.Array) -> jax.Array:
    """Each network's value of one observation, [members] (one network, not ``Members``: [1])."""
    if isinstance(params, Members):
        return jax.vmap(lambda member: mlp_apply(member, observation)[0])(params.stacked)
    return mlp_apply(params, observation)[:1]


def seen(critic: Critic, observation: jax.Array) -> jax.Array:
    """What ``critic``'s networks take of an observation: it standardised where the critic keeps statistics."""
    return observation if critic.statistics is None else standardized(critic.statistics, observation)


def init_critic(seed_key: jax.Array, observations: int, optimizer: optax.GradientTransformation, hidden: tuple[int, ...],
                standardize: bool = False, members: int = 1) -> Critic:
    """A seed's critic: tanh hidden layers of the widths ``hidden`` (``TrainConfig.critic_width``, ``critic_depth``);
    ``members`` > 1: that many such networks (``Members``), each from keys of its own (the first one's are
    the single network's)."""
    key = jax.random.fold_in(seed_key, CRITIC_STREAM)
    sizes = (observations, *hidden, 1)
    if members == 1:
        params = mlp_init(key, sizes, zero_output=False)
    else:
        keys = jnp.stack([key, *(jax.random.fold_in(key, member) for member in range(1, members))])
        params = Members(jax.vmap(lambda member_key: mlp_init(member_key, sizes, zero_output=False))(keys))
    return Critic(params, optimizer.init(params), params, no_observations(observations) if standardize else None)


def td_lambda_targets(rewards: jax.Array, values: jax.Array, running: jax.Array, discount: float,
                      td_lambda: float, cut: jax.Array | None = None) -> jax.Array:
    """TD(lambda) targets of the states a window starts each step from, [T, batch].

    ``rewards[t]``: the reward of step t (to x_{t+1}); ``values[t]``: the value of x_{t+1};
    ``running[t]``: whether x_{t+1}'s episode still runs (where it does not, nothing after it counts);
    ``cut[t]``: whether a time limit cut it at x_{t+1}, whose value then stands for all that follows.
    The last step's target bootstraps from the value of the window's last state.
    """
    def back(after, step):
        reward, value_next, still, *cut_here = step  # no cut given: the program is the one without the option
        at_end = jnp.where(cut_here[0], value_next, 0.0) if cut_here else 0.0
        target = reward + discount * jnp.where(still, (1 - td_lambda) * value_next + td_lambda * after, at_end)
        return target, target

    _, targets = jax.lax.scan(back, values[-1], (rewards, values, running) + (() if cut is None else (cut,)), reverse=True)
    return targets


def fit_critic(critic: Critic, observations: jax.Array, targets: jax.Array, weights: jax.Array,
               optimizer: optax.GradientTransformation, iterations: int = ITERATIONS) -> tuple[Critic, jax.Array]:
    """``iterations`` Adam steps of the critic on the weighted squared error to ``targets`` (all examples
    at once; of ``Members``, each network's error, summed), then the target critic moved towards it.
    Returns the critic and its last loss."""
    def loss(params):  # each network to the targets, not their least value
        errors = jax.vmap(lambda o: members_values(params, o), out_axes=1)(observations) - targets
        return jnp.sum(weights * errors ** 2) / jnp.maximum(jnp.sum(weights), 1.0)

    def step(current: Critic, _):
        error, grads = jax.value_and_grad(loss)(current.params)
        updates, opt_state = optimizer.update(grads, current.opt_state, current.params)
        return current._replace(params=optax.apply_updates(current.params, updates), opt_state=opt_state), error

    fitted, errors = jax.lax.scan(step, critic, None, length=iterations)
    target = jax.tree.map(lambda kept, new: TARGET_KEEP * kept + (1 - TARGET_KEEP) * new, fitted.target, fitted.params)
    return fitted._replace(target=target), errors[-1]


def fit_to_window(critic: Critic, visited: PyTree, final: PyTree, observe: Callable[[PyTree], jax.Array],
                  discount: float, td_lambda: float, optimizer: optax.GradientTransformation) -> Critic:
    """The critic after fitting it to the TD(lambda) targets of a window just rolled: ``visited``, the
    window's states x_0..x_{T-1} [T, batch] and ``final``, x_T [batch] (``stablebptt.engine.episodes.Window``:
    a task's state, its reward and whether its episode runs)."""
    reached = jax.tree.map(lambda past, last: jnp.concatenate([past[1:], last[None]]), visited, final)
    observe_all = jax.vmap(jax.vmap(observe))
    observed = observe_all(visited.state)  # [T, batch, observations]; a state past its episode's end weighs 0
    flat, weights = observed.reshape((-1, observed.shape[-1])), visited.running.reshape(-1)
    if critic.statistics is not None:  # the window's states counted first, as the policy's statistics count them
        critic = critic._replace(statistics=with_observations(critic.statistics, flat, weights))
    in_view = jax.vmap(lambda o: seen(critic, o))
    values = jax.vmap(jax.vmap(lambda o: value(critic.target, seen(critic, o))))(observe_all(reached.state))
    targets = td_lambda_targets(reached.reward, values, reached.running, discount, td_lambda, reached.cut)
    return fit_critic(critic, in_view(flat), targets.reshape(-1), weights.astype(targets.dtype), optimizer)[0]


def bootstrap(critic: Critic, observe: Callable[[PyTree], jax.Array]) -> Callable[[PyTree], jax.Array]:
    """The value a window's loss adds at its last state: the target critic's, of the state's observation."""
    return lambda state: value(critic.target, seen(critic, observe(state)))
