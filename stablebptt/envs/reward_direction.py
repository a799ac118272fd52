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
