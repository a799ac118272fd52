"""The direction in an environment's actions that raises its reward one control step on, as the
differentiable step computes it: an observation a policy can be given. The reacher's policy, which
its raw observation leaves parked, reaches PPO's return once it sees this direction
(docs/performance.md, "The direction to push, observed")."""
from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp


def reward_direction(step: Callable[[Any, jax.Array], Any], state: Any, action_size: int) -> jax.Array:
    """The unit vector along d reward(step(state, a)) / d a at still actions (a = 0), held as an
    observation: no derivative runs through it. Zero where that slope is zero (a flat reward, or one
    whose slope underflows there) or not finite, never NaN."""
    slope = jax.grad(lambda action: step(state, action).reward)(jnp.zeros(action_size))
    length = jnp.linalg.norm(slope)
    usable = jnp.isfinite(length) & (length > 0)
    direction = jnp.where(usable, slope / jnp.where(usable, length, 1.0), 0.0)
    return jax.lax.stop_gradient(direction)


def seen_by_policy(observation: Callable[[Any], jax.Array], step: Callable[[Any, jax.Array], Any], action_size: int,
                   direction_observed: bool) -> Callable[[Any], jax.Array]:
    """What a policy sees of a state: ``observation(state)`` and, where ``direction_observed``, after it
    ``reward_direction`` of ``step`` (whose reward the policy trains on) at that state."""
    if not direction_observed:
        return observation
    def seen(state: Any) -> jax.Array:
        own = observation(state)
        return jnp.concatenate([own, reward_direction(step, state, action_size).astype(own.dtype)])
    return seen
