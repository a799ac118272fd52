"""The direction in an environment's actions that raises its reward one control step on, as the
differentiable step computes it: an observation a policy can be given. The reacher's policy, which
its raw observation leaves parked, reaches PPO's return once it sees this direction
(docs/performance.md, "The direction to push, observed").

The direction is computed once per state, where a step or a reset reaches it, and carried with the
state (``Directed``): every program that reads the policy at a state (the window, each flow's passes
over it, the critic, the evaluation) reads it there rather than computing it again."""
from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable

import jax
import jax.numpy as jnp


# The slope in forward mode, one tangent per action, for envs of this many actions or fewer; reverse mode
# (one pass back through the step) above, where forward mode is not measured. On the 2-core CPU forward
# mode's programs compiled and ran faster on the finger's 2 actions (the update 0.78x and 0.83x reverse
# mode's time, the evaluation 0.61x and 0.64x) and on the cheetah's 6 (0.88x and 0.90x, 0.74x and 0.85x):
# docs/performance.md, "The direction in forward mode".
FORWARD_MODE_ACTIONS = 6


def reward_direction(step: Callable[[Any, jax.Array], Any], state: Any, action_size: int) -> jax.Array:
    """The unit vector along d reward(step(state, a)) / d a at still actions (a = 0), held as an
    observation: no derivative runs through it. Zero where that slope is zero (a flat reward, or one
    whose slope underflows there) or not finite, never NaN."""
    # Held at the state, not only at the result: a derivative of a rollout then finds no tangent here
    # and traces nothing of this step's derivative.
    state = jax.lax.stop_gradient(state)
    slope_of = jax.jacfwd if action_size <= FORWARD_MODE_ACTIONS else jax.grad
    slope = slope_of(lambda action: step(state, action).reward)(jnp.zeros(action_size))
    length = jnp.linalg.norm(slope)
    usable = jnp.isfinite(length) & (length > 0)
    direction = jnp.where(usable, slope / jnp.where(usable, length, 1.0), 0.0)
    return jax.lax.stop_gradient(direction)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Directed:
    """An environment's state and ``reward_direction`` there. Its fields read through: ``directed.reward``
    is the state's reward, so whatever reads an environment's state reads this one alike."""
    state: Any
    direction: jax.Array

    def __getattr__(self, name: str) -> Any:
        if name in ("state", "direction") or name.startswith("__"):  # not yet set (a copy being made)
            raise AttributeError(name)
        return getattr(self.state, name)


@dataclasses.dataclass(frozen=True)
class Direction:
    """How a task's states carry the direction of the reward ``trained`` trains on (``reward_direction``),
    where the policy observes it; where it does not, every function here is the one it is given."""
    trained: Callable[[Any, jax.Array], Any]
    action_size: int
    observed: bool

    @functools.cached_property
    def _at(self) -> Callable[[Any], jax.Array]:
        # One jit per task: each program that reaches a state (the window, the resets, the evaluation, the
        # checks) traces the step's derivative once per shape, not once per call.
        return jax.jit(lambda state: reward_direction(self.trained, state, self.action_size))

    def of(self, state: Any) -> Any:
        """``state`` carrying its direction."""
        # Held before the call, so a derivative of a rollout carries no tangent into the jitted direction.
        return Directed(state, self._at(jax.lax.stop_gradient(state))) if self.observed else state

    @functools.cached_property
    def _made(self) -> dict:
        # One function per function given, kept by this direction (a task's, with it): a task its check
        # settles into keeps its pending task's step, so a run's start keeps the epoch it traced and compiled
        # beside the check (engine/starting.py).
        return {}

    def stepping(self, step: Callable[[Any, jax.Array], Any]) -> Callable[[Any, jax.Array], Any]:
        """``step`` on states that carry their direction, reaching one that carries its own."""
        if not self.observed:
            return step
        return self._made.setdefault(("step", step), lambda state, action: self.of(step(state.state, action)))

    def resetting(self, reset: Callable[[jax.Array], Any]) -> Callable[[jax.Array], Any]:
        """``reset(key)`` reaching a state that carries its direction."""
        if not self.observed:
            return reset
        return self._made.setdefault(("reset", reset), lambda key: self.of(reset(key)))

    def sampling(self, sample: Callable[[jax.Array, int], Any]) -> Callable[[jax.Array, int], Any]:
        """``sample(key, count)``, a batch of states, each carrying its direction (one program per count)."""
        if not self.observed:
            return sample
        directed = jax.jit(jax.vmap(self.of))
        return lambda key, count: directed(sample(key, count))

    def seen(self, observation: Callable[[Any], jax.Array]) -> Callable[[Any], jax.Array]:
        """What a policy sees of a state: ``observation`` of it and, where observed, after it its direction."""
        if not self.observed:
            return observation

        def seen(state: Directed) -> jax.Array:
            own = observation(state.state)
            return jnp.concatenate([own, state.direction.astype(own.dtype)])
        return seen
