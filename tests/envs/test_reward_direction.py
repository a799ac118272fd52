"""The observed reward direction (``envs.reward_direction``): the unit direction in the actions that raises
the reward one control step on, as finite differences of the env's own step find it; zero, never NaN,
where the reward has no usable slope; held as an observation (no derivative through it)."""
import jax
import jax.numpy as jnp
import numpy as np

from stablebptt.envs.adapter import env_task
from stablebptt.envs.reward_direction import reward_direction

from envs_for_tests import Ball


def _ball_at(env, height):
    state = env.reset(jax.random.PRNGKey(0))
    return state._replace(data={**state.data, "qpos": jnp.array([height])})


def test_the_direction_is_the_finite_differences_sign_and_holds_no_derivative():
    env = Ball()  # rewarded for hovering at -0.05: above it, pushing up (the motor's positive action) costs reward
    step = env_task(env, horizon=2, diagnose=False).dynamics.step
    for height, expected in ((-0.02, -1.0), (-0.08, 1.0)):
        state = _ball_at(env, height)
        direction = reward_direction(step, state, env.action_size)
        eps = 1e-3
        differences = float(step(state, jnp.array([eps])).reward - step(state, jnp.array([-eps])).reward)
        assert float(direction[0]) == expected == np.sign(differences), (height, direction, differences)
    # Held as an observation: its derivative in the state it was computed from is zero.
    moved = jax.grad(lambda h: reward_direction(step, _ball_at(env, h), env.action_size)[0])(-0.02)
    assert float(moved) == 0.0


def test_a_flat_or_non_finite_slope_gives_zero_not_nan():
    env = Ball()
    state = _ball_at(env, -0.02)
    stepped = env_task(env, horizon=2, diagnose=False).dynamics.step
    flat = lambda state, action: stepped(state, action)._replace(reward=jnp.zeros(()))  # noqa: E731
    root = lambda state, action: stepped(state, action)._replace(reward=jnp.sqrt(jnp.sum(action ** 2)))  # noqa: E731
    for step in (flat, root):  # the square root's slope at zero is NaN
        np.testing.assert_array_equal(np.asarray(reward_direction(step, state, env.action_size)), [0.0])


def test_an_env_tasks_policy_observing_the_direction_sees_it_after_the_observation_and_trains_on_finite_gradients():
    env = Ball()
    task = env_task(env, horizon=2, diagnose=False, reward_direction_observed=True)
    assert "the policy sees the direction of its trained reward in its actions" in task.summary
    assert task.resolved["reward_direction_observed"] is True
    params = task.init_params(jax.random.PRNGKey(0), False)
    assert params[0][0].shape[0] == env.observation_size + env.action_size
    state = _ball_at(env, -0.02)  # above the hover height: the direction is -1
    from stablebptt.envs.adapter import observation_policy
    seen = jnp.concatenate([state.obs, reward_direction(task.dynamics.step, state, env.action_size)])
    np.testing.assert_allclose(np.asarray(task.dynamics.policy(params, state)),
                               np.asarray(observation_policy(params, seen)), rtol=1e-6)

    def window_loss(params):  # two steps of the task's own dynamics, the policy seeing the direction
        reached = task.dynamics.step(state, task.dynamics.policy(params, state))
        return -task.dynamics.step(reached, task.dynamics.policy(params, reached)).reward
    gradient = jax.grad(window_loss)(params)
    assert all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree.leaves(gradient))
    assert any(float(jnp.max(jnp.abs(leaf))) > 0 for leaf in jax.tree.leaves(gradient))


def test_bad_values_are_refused_in_one_line(tmp_path, capsys):
    import pytest
    from stablebptt.envs.protocol import EnvError
    with pytest.raises(EnvError, match="reward_direction_observed must be True or False"):
        env_task(Ball(), horizon=2, diagnose=False, reward_direction_observed="yes")
