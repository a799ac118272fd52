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
    # The target's two bounds, one interval, share the larger of their medians.
    x = np.asarray(jax.vmap(step)(states, actions).x, float)
    shared = max(np.median(np.abs(x - (TARGET - WIDTH))), np.median(np.abs(x - (TARGET + WIDTH))))
    assert np.isclose(smoothing.temperatures, shared, rtol=1e-5).sum() == 2, smoothing.temperatures


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



LOW, HIGH = 0.6, 2.0  # HopperStand's box of heights; its sampled hoppers all lie below it


@jax.jit
def stand_step(state: Slider, action: jax.Array) -> Slider:
    x = state.x + DT * action[0]
    standing = jnp.where(jnp.logical_and(LOW <= x, x <= HIGH), 1.0, 0.0)
    return Slider(x, state.v, standing, {"in_target": standing})


def test_a_box_the_sampled_states_all_lie_below_rises_into_it_and_keeps_its_far_bound_as_written():
    states, actions = samples()
    below = states._replace(x=states.x * 0.4 - 0.6)  # in [-0.8, 0.4]: under LOW, far under HIGH
    smooth_step, smoothing = smooth_reward(stand_step, below, actions)
    x = np.asarray(below.x + DT * actions[:, 0], float)
    # Only the bound the states cross is smoothed, at its own median distance.
    assert len(smoothing.terms) == 1 and np.isclose(smoothing.temperatures[0], np.median(np.abs(x - LOW)), rtol=1e-5)
    heights = jnp.array([-0.5, 0.2, LOW, 1.0, 1.5, 1.99, 2.5])
    rewards = np.asarray(jax.vmap(smooth_step)(Slider(heights, jnp.zeros(7), jnp.zeros(7), {"in_target": jnp.zeros(7)}),
                                               jnp.zeros((7, 1))).reward)
    assert np.all(np.diff(rewards[:-1]) > 0), rewards  # higher is better all the way up the box (the slope to follow)
    np.testing.assert_allclose(rewards[2], 0.5, rtol=1e-5)  # at the bound crossed, half
    assert rewards[-1] == 0.0  # above the box, as written


NARROW, WIDE = 0.01, 1.0  # Gaussian margins: far smaller than the sampled distances, and of their size


@jax.jit
def gaussian_step(state: Slider, action: jax.Array) -> Slider:
    """A reward of two Gaussians of the distance to TARGET: the narrow one underflows at most sampled states."""
    x = state.x + DT * action[0]
    near = jnp.exp(-0.5 * ((x - TARGET) / NARROW) ** 2)
    broad = jnp.exp(-0.5 * ((x - TARGET) / WIDE) ** 2)
    return Slider(x, state.v, near * (0.5 + 0.5 * broad), {"in_target": near})


def test_an_underflowing_gaussian_is_widened_to_the_sampled_distances_and_a_fitting_one_is_left_alone():
    states, actions = samples()
    smooth_step, smoothing = smooth_reward(gaussian_step, states, actions)
    assert (smoothing.terms, len(smoothing.exponents)) == ((), 1), smoothing.describe()
    assert "test_surrogate.py" in smoothing.exponents[0] and "1 vanishing exponential" in smoothing.describe()
    # The exponent is scaled so that the median sampled one becomes -1: the margin widened to the median distance.
    x = states.x + DT * actions[:, 0]
    exponents = -0.5 * ((np.asarray(x, float) - TARGET) / NARROW) ** 2
    np.testing.assert_allclose(smoothing.exponent_scales[0], 1 / abs(np.median(exponents)), rtol=1e-4)
    state, action = jax.tree.map(lambda a: a[0], states), jnp.array([0.2])
    reached = gaussian_step(state, action)
    assert float(reached.reward) == 0.0 and float(jax.grad(lambda s: gaussian_step(s, action).reward)(state).x) == 0.0
    smooth = jax.jit(smooth_step)(state, action)
    factor, distance = smoothing.exponent_scales[0], float(reached.x) - TARGET
    expected = np.exp(-0.5 * factor * (distance / NARROW) ** 2) * (0.5 + 0.5 * np.exp(-0.5 * (distance / WIDE) ** 2))
    np.testing.assert_allclose(float(smooth.reward), expected, rtol=1e-4)  # the broad Gaussian as it was
    assert float(smooth.x) == float(reached.x)
    slope = jax.grad(lambda s: smooth_step(s, action).reward)(state)
    assert float(slope.x) * -distance > 0  # towards the target


LOST = 0.1  # a Gaussian margin whose term is lost beside an order-1 term at the sampled states, though not 0


@jax.jit
def faint_target_step(state: Slider, action: jax.Array) -> Slider:
    """FishSwim's reward in small: a Gaussian reach of TARGET beside an upright-like term of order 1."""
    x = state.x + DT * action[0]
    near = jnp.exp(-0.5 * ((x - TARGET) / LOST) ** 2)
    upright = 0.5 * (jnp.cos(state.v) + 1)
    return Slider(x, state.v, (7 * near + upright) / 8, {"in_target": near})


def test_an_exponential_lost_beside_the_rewards_other_term_is_widened_though_it_does_not_underflow():
    states, actions = samples()
    x = np.asarray(states.x + DT * actions[:, 0], np.float32)
    median = float(np.median(-0.5 * ((x - TARGET) / LOST) ** 2))
    float32 = np.finfo(np.float32)
    assert np.log(float32.tiny) < median < np.log(float32.eps)  # not 0 in float32, but below its resolution next to 1
    smooth_step, smoothing = smooth_reward(faint_target_step, states, actions)
    assert (smoothing.terms, len(smoothing.exponents)) == ((), 1) and "1 vanishing exponential" in smoothing.describe()
    np.testing.assert_allclose(smoothing.exponent_scales[0], 1 / abs(median), rtol=1e-3)
    # At a state 0.6 from the target the true reward's slope in x is its Gaussian's, some 1e-7 of the upright
    # term's scale (lost in the sum); the surrogate's points to the target and is of the reward's own order.
    state, action = Slider(jnp.float32(TARGET + 0.6), jnp.float32(0.3), jnp.float32(0), {"in_target": jnp.float32(0)}), jnp.array([0.0])
    true_slope = float(jax.grad(lambda s: faint_target_step(s, action).reward)(state).x)
    smooth_slope = float(jax.grad(lambda s: smooth_step(s, action).reward)(state).x)
    assert abs(true_slope) < 1e-6 and smooth_slope < -1e-2
    # The upright term and the state the step reaches are the step's own.
    reached, smoothed_state = faint_target_step(state, action), jax.jit(smooth_step)(state, action)
    assert float(smoothed_state.x) == float(reached.x) and float(smoothed_state.v) == float(reached.v)
    widened = 7 * np.exp(-0.5 * smoothing.exponent_scales[0] * (0.6 / LOST) ** 2) + 0.5 * (np.cos(0.3) + 1)
    np.testing.assert_allclose(float(smoothed_state.reward), widened / 8, rtol=1e-5)


@jax.jit
def rectified_step(state: Slider, action: jax.Array) -> Slider:
    v = jax.nn.relu(state.v + DT * action[0])  # jax.nn.relu: a custom derivative (jax.custom_jvp) in the step
    x = state.x + DT * v
    target = in_target(x)
    return Slider(x, v, target * jax.nn.relu(1.0 - v), {"in_target": target})


def test_a_step_calling_a_custom_derivative_is_smoothed_and_keeps_its_state_and_derivative():
    states, actions = samples()
    smooth_step, _ = smooth_reward(rectified_step, states, actions)
    ours, theirs = jax.jit(jax.vmap(smooth_step))(states, actions), jax.vmap(rectified_step)(states, actions)
    np.testing.assert_array_equal(ours.x, theirs.x)
    np.testing.assert_array_equal(ours.v, theirs.v)
    assert not np.allclose(ours.reward, theirs.reward)  # the target's bounds smoothed
    moving = Slider(jnp.array(0.0), jnp.array(0.5), jnp.array(0.0), {"in_target": jnp.array(0.0)})
    slope = jax.grad(lambda action: smooth_step(moving, action).x)(jnp.array([0.2]))
    np.testing.assert_allclose(slope, [DT * DT], rtol=1e-6)  # x = x0 + DT (v0 + DT a) where v is positive
