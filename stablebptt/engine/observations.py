"""Running statistics of what a policy observes, and its observations standardised by them.

A policy that sees raw observations learns slowly where their scales differ by orders of magnitude
(a joint's angle in radians beside its velocity in radians per second). The field's trainers
standardise every observation by the mean and deviation of all observations met so far; here the
statistics are part of the policy's parameters (so a checkpoint, a resumed run and a rendering all
see the policy the run trained), take no gradient, and are refreshed after every update from the
states its window visited (``Task.refresh_statistics``).
"""
from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

# Standardised observations are clipped to this many deviations: a state far outside everything met
# so far (early in training) must not saturate every hidden unit.
CLIP_DEVIATIONS = 5.0
# The smallest deviation an observation is divided by: a constant one (a fixed target) stays finite.
SMALLEST_DEVIATION = 1e-6


class ObservationStatistics(NamedTuple):
    """The running mean and spread of observations; floats throughout, so gradients pass the pytree."""

    count: jax.Array  # scalar: observations counted so far
    mean: jax.Array  # [size]
    squares: jax.Array  # [size]: the sum of squared deviations from the mean


def no_observations(size: int) -> ObservationStatistics:
    """Statistics of nothing yet: they standardise nothing (mean 0, deviation 1) until the first refresh."""
    dtype = jnp.result_type(float)
    return ObservationStatistics(jnp.zeros((), dtype), jnp.zeros(size, dtype), jnp.zeros(size, dtype))


def with_observations(statistics: ObservationStatistics, observations: jax.Array,
                      counted: jax.Array) -> ObservationStatistics:
    """``statistics`` combined with the ``observations`` [N, size] where ``counted`` [N] holds (the
    pairwise update of Chan, Golub and LeVeque: exact for any split of the data into batches)."""
    weights = counted.astype(statistics.mean.dtype)
    new_count = jnp.sum(weights)
    new_mean = jnp.sum(weights[:, None] * observations, axis=0) / jnp.maximum(new_count, 1.0)
    new_squares = jnp.sum(weights[:, None] * (observations - new_mean) ** 2, axis=0)
    total = statistics.count + new_count
    share = new_count / jnp.maximum(total, 1.0)
    delta = new_mean - statistics.mean
    return ObservationStatistics(total, statistics.mean + share * delta,
                                 statistics.squares + new_squares + delta ** 2 * statistics.count * share)


def deviation(statistics: ObservationStatistics) -> jax.Array:
    """The observations' standard deviation (1 before any was counted)."""
    variance = statistics.squares / jnp.maximum(statistics.count, 1.0)
    return jnp.where(statistics.count > 0, jnp.sqrt(variance), 1.0)


def standardized(statistics: ObservationStatistics, observation: jax.Array) -> jax.Array:
    """``observation`` in deviations from the mean of those met so far, clipped; the statistics are
    constants to every derivative (they follow the data, not the loss)."""
    statistics = jax.lax.stop_gradient(statistics)
    scaled = (observation - statistics.mean) / jnp.maximum(deviation(statistics), SMALLEST_DEVIATION)
    return jnp.clip(scaled, -CLIP_DEVIATIONS, CLIP_DEVIATIONS)


class StandardizedNetwork(NamedTuple):
    """A policy's parameters where it sees standardised observations: its network's, and the statistics."""

    network: Any
    statistics: ObservationStatistics


def refresh_from(observe: Callable[[Any], jax.Array]) -> Callable[[StandardizedNetwork, Any, jax.Array], StandardizedNetwork]:
    """``Task.refresh_statistics`` of a policy whose parameters are a ``StandardizedNetwork`` and which
    sees ``observe(state)``."""
    def refresh(params: StandardizedNetwork, states: Any, counted: jax.Array) -> StandardizedNetwork:
        seen = jax.vmap(jax.vmap(observe))(states)  # [T, B, size]: states may hold leaves of size 0, not reshaped
        return params._replace(statistics=with_observations(params.statistics, seen.reshape((-1, seen.shape[-1])),
                                                            counted.reshape(-1)))

    return refresh
