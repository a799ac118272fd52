"""The smooth training surrogate of a step reward: the comparisons a reward makes numbers of become
sigmoids, with temperatures from sampled states, while the state a step returns stays its own to the bit."""
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stablebptt.envs.surrogate import smooth_reward

pytestmark = pytest.mark.fast

DT, WALL, TARGET, WIDTH, FAST = 0.1, 2.0, 1.0, 0.1, 0.3


class Slider(NamedTuple):
    x: jax.Array
    v: jax.Array
    reward: jax.Array
    metrics: dict  # the reward's terms as logged, as Playground's states keep them: no later step reads them


def in_target(x):
    """A tolerance with margin 0: 1 inside the bounds, 0 outside."""
    return jnp.where(jnp.logical_and(TARGET - WIDTH <= x, x <= TARGET + WIDTH), 1.0, 0.0)


@jax.jit
def step(state: Slider, action: jax.Array) -> Slider:
    v = state.v + DT * action[0]
    x = jnp.where(state.x + DT * v > WALL, WALL, state.x + DT * v)  # a wall: a comparison of the state, kept
    moving_fast = (v > FAST).astype(jnp.float32)  # a threshold made a number
    distance = jnp.where(x < 0, -x, x)  # a piecewise function: its gradient is already there
    target = in_target(x)
    return Slider(x, v, target + 0.5 * moving_fast - 0.01 * distance, {"in_target": target})


def samples(count=256, seed=0):
    keys = jax.random.split(jax.random.PRNGKey(seed), 3)
    states = Slider(jax.random.uniform(keys[0], (count,), minval=-0.5, maxval=2.5),
                    jax.random.uniform(keys[1], (count,), minval=-1.0, maxval=1.0), jnp.zeros(count),
                    {"in_target": jnp.zeros(count)})
    return states, jax.random.uniform(keys[2], (count, 1), minval=-1.0, maxval=1.0)


@pytest.fixture(scope="module")
def smoothed():
    states, actions = samples()
    return smooth_reward(step, states, actions)


def test_the_state_a_smoothed_step_returns_is_the_steps_own_to_the_bit(smoothed):
    smooth_step, _ = smoothed
    states, actions = samples(seed=1)
    ours, theirs = jax.jit(jax.vmap(smooth_step))(states, actions), jax.vmap(step)(states, actions)
    np.testing.assert_array_equal(ours.x, theirs.x)
    np.testing.assert_array_equal(ours.v, theirs.v)
    assert np.any(theirs.x == WALL)  # the wall's comparison ran, hard
    assert not np.allclose(ours.reward, theirs.reward)


def test_the_comparisons_made_numbers_are_smoothed_and_named_and_the_rest_is_not(smoothed):
    _, smoothing = smoothed
    # The target's two bounds and the threshold; not the wall (it reaches the state) nor the piecewise distance.
    assert len(smoothing.terms) == 3, smoothing.describe()
    assert all("test_surrogate.py" in term for term in smoothing.terms), smoothing.terms
    assert "smoothed 3 comparisons of the reward into sigmoids" in smoothing.describe()
    # Each temperature is the median absolute difference it compares at the sampled states.
    states, actions = samples()
    v = states.v + DT * actions[:, 0]
    assert np.isclose(smoothing.temperatures, np.median(np.abs(v - FAST)), rtol=1e-5).sum() == 1


def test_the_surrogate_has_a_gradient_where_the_reward_has_none_and_it_points_the_right_way(smoothed):
    smooth_step, _ = smoothed
    state, action = Slider(jnp.float32(0.5), jnp.float32(0.0), jnp.float32(0.0), {"in_target": jnp.float32(0.0)}), jnp.array([0.0])
    true_slope = jax.grad(lambda s, a: step(s, a).reward)(state, action)
    assert float(true_slope.x) == pytest.approx(-0.01)  # the distance term's alone: the target gives nothing
    slope = jax.jit(jax.grad(lambda s, a: smooth_step(s, a).reward))(state, action)
    assert float(slope.x) > 0.05 and float(slope.v) > 0.1  # towards the target (where the true slope points away), and faster
    # Far from every threshold (eight temperatures or more) the surrogate is the reward.
    far = Slider(jnp.array([-3.0, -5.0]), jnp.array([-8.0, 8.0]), jnp.zeros(2), {"in_target": jnp.zeros(2)})
    still = jnp.zeros((2, 1))
    np.testing.assert_allclose(jax.vmap(smooth_step)(far, still).reward, jax.vmap(step)(far, still).reward, atol=0.005)

