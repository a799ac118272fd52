"""An env's rollouts scored by their return: the windows' loss (``rollout_loss``) and whole episodes'
(``episode_dynamics``), each counting rewards until the first ``done``."""
from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

from stablebptt.flows.dynamics import Dynamics, PyTree


class EpisodeState(NamedTuple):
    """An environment state with the return so far and whether the episode still runs."""

    env: PyTree
    total: jax.Array
    running: jax.Array


def episode_dynamics(step: Callable, policy: Callable, episode_length: int) -> Dynamics:
    """A rollout whose loss is the negative episode return, rewards counted until the first ``done``.

    Its state wraps the environment's (``EpisodeState``) so that the return is
    summed as the rollout goes and no step's state needs keeping.
    """
    def episode_step(state: EpisodeState, action):
        reached = step(state.env, action)
        # where, not a product: a reward after the end (a NaN state, say) must not leak in.
        total = state.total + jnp.where(state.running, reached.reward, 0.0)
        return EpisodeState(reached, total, state.running & (reached.done == 0))

    return Dynamics(step=episode_step, policy=lambda params, state: policy(params, state.env),
                    loss=lambda states, actions: -states.total[-1], horizon=episode_length)


def rollout_loss(discount: float) -> Callable:
    """The negative discounted return of one rollout, rewards counted until the first ``done``."""
    def loss(states, actions):
        done = jax.lax.stop_gradient(states.done)
        # Step t's reward counts if no earlier step ended the episode.
        running = jnp.concatenate([jnp.ones((1,), done.dtype), jnp.cumprod(1 - done)[:-1]]) > 0
        weights = discount ** jnp.arange(done.shape[0], dtype=states.reward.dtype)
        return -jnp.sum(jnp.where(running, weights * states.reward, 0.0))

    return loss
