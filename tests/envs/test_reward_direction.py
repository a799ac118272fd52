"""The observed reward direction (``envs.reward_direction``): the unit direction in the actions that raises
the reward one control step on, as finite differences of the env's own step find it; zero, never NaN,
where the reward has no usable slope; held as an observation (no derivative through it); carried by the
states a task's steps reach, which the window's gradient does not tell from computing it anew."""
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stablebptt.envs.adapter import env_task
from stablebptt.envs.reward_direction import Directed, reward_direction

from envs_for_tests import Ball, MjxDataBall


def _ball_at(env, height):
    state = env.reset(jax.random.PRNGKey(0))
    return state._replace(data={**state.data, "qpos": jnp.array([height])})


def test_the_direction_is_the_finite_differences_sign():
    env = Ball()  # rewarded for hovering at -0.05: above it, pushing up (the motor's positive action) costs reward
    step = env_task(env, horizon=2, diagnose=False).dynamics.step
    for height, expected in ((-0.02, -1.0), (-0.08, 1.0)):
        state = _ball_at(env, height)
        direction = reward_direction(step, state, env.action_size)
        eps = 1e-3
        differences = float(step(state, jnp.array([eps])).reward - step(state, jnp.array([-eps])).reward)
        assert float(direction[0]) == expected == np.sign(differences), (height, direction, differences)


@pytest.mark.parametrize("forward_up_to", [0, 3])  # reverse, forward
def test_the_direction_is_the_closed_forms_in_forward_and_reverse_mode(monkeypatch, forward_up_to):
    """A reward -sum(w (x + a - t)^2) one step on: its slope in the actions at a = 0 is -2 w (x - t), the
    direction that over its length, whether the slope is taken in forward or in reverse mode; held as an
    observation, its derivative in the state is zero, where the closed form's turns with x."""
    from stablebptt.envs import reward_direction as module
    monkeypatch.setattr(module, "FORWARD_MODE_ACTIONS", forward_up_to)
    weights, target, position = jnp.array([1.0, 3.0, 0.5]), jnp.array([0.2, -0.4, 1.0]), jnp.array([0.5, 0.1, -1.0])
    step = lambda x, a: types.SimpleNamespace(reward=-jnp.sum(weights * (x + a - target) ** 2))  # noqa: E731
    slope = -2.0 * weights * (position - target)
    np.testing.assert_allclose(np.asarray(module.reward_direction(step, position, 3)),
                               np.asarray(slope / jnp.linalg.norm(slope)), rtol=1e-6)
    closed_form = lambda x: -2.0 * weights * (x - target) / jnp.linalg.norm(-2.0 * weights * (x - target))  # noqa: E731
    assert float(jnp.abs(jax.jacfwd(closed_form)(position)).max()) > 0.1  # it turns with x
    for derivative in (jax.jacfwd, jax.jacrev):
        np.testing.assert_array_equal(np.asarray(derivative(lambda x: module.reward_direction(step, x, 3))(position)),
                                      np.zeros((3, 3)))

def test_a_flat_or_non_finite_slope_gives_zero_not_nan():
    env = Ball()
    state = _ball_at(env, -0.02)
    stepped = env_task(env, horizon=2, diagnose=False).dynamics.step
    flat = lambda state, action: stepped(state, action)._replace(reward=jnp.zeros(()))  # noqa: E731
    root = lambda state, action: stepped(state, action)._replace(reward=jnp.sqrt(jnp.sum(action ** 2)))  # noqa: E731
    for step in (flat, root):  # the square root's slope at zero is NaN
        np.testing.assert_array_equal(np.asarray(reward_direction(step, state, env.action_size)), [0.0])


def test_an_env_tasks_states_carry_their_direction_and_its_policy_sees_it_after_the_observation():
    env = Ball()
    task = env_task(env, horizon=2, diagnose=False, reward_direction_observed=True)
    plain = env_task(env, horizon=2, diagnose=False).dynamics.step  # the reward trained on, no direction carried
    assert "the policy sees the direction of its trained reward in its actions" in task.summary
    assert task.resolved["reward_direction_observed"] is True
    params = task.init_params(jax.random.PRNGKey(0), False)
    assert params[0][0].shape[0] == env.observation_size + env.action_size
    from stablebptt.envs.adapter import observation_policy
    starts = task.sample_initial_states(jax.random.PRNGKey(1), 3)
    for k in range(3):  # each start carries the direction at its own state
        start = jax.tree.map(lambda a, k=k: a[k], starts)
        np.testing.assert_array_equal(np.asarray(start.direction),
                                      np.asarray(reward_direction(plain, start.state, env.action_size)))
    state = Directed(_ball_at(env, -0.02), jnp.array([-1.0]))  # above the hover height: the direction is -1
    seen = jnp.concatenate([state.obs, state.direction])
    np.testing.assert_allclose(np.asarray(task.dynamics.policy(params, state)),
                               np.asarray(observation_policy(params, seen)), rtol=1e-6)
    # A step reaches the state the env's own step reaches, carrying the direction there; its fields read through.
    action = jnp.array([0.3])
    reached = task.dynamics.step(state, action)
    own = plain(state.state, action)
    assert float(reached.reward) == float(own.reward) and float(reached.data["qpos"][0]) == float(own.data["qpos"][0])
    np.testing.assert_array_equal(np.asarray(reached.direction), np.asarray(reward_direction(plain, own, env.action_size)))


def test_a_window_through_carried_directions_has_the_gradient_of_one_whose_policy_computes_them_anew():
    env = Ball()
    task = env_task(env, horizon=3, diagnose=False, reward_direction_observed=True)
    plain = env_task(env, horizon=3, diagnose=False).dynamics.step
    from stablebptt.envs.adapter import observation_policy
    params = task.init_params(jax.random.PRNGKey(0), False)
    height = -0.02

    def carried(params):  # the task's own dynamics: each state carries the direction its step computed
        state, total = Directed(_ball_at(env, height), reward_direction(plain, _ball_at(env, height), 1)), 0.0
        for _ in range(3):
            state = task.dynamics.step(state, task.dynamics.policy(params, state))
            total = total + state.reward
        return total

    def anew(params):  # the plain rollout: the policy computes the direction at every state it sees
        state, total = _ball_at(env, height), 0.0
        for _ in range(3):
            seen = jnp.concatenate([state.obs, reward_direction(plain, state, 1)])
            state = plain(state, observation_policy(params, seen))
            total = total + state.reward
        return total

    expected, gradient = jax.grad(anew)(params), jax.grad(carried)(params)
    assert any(float(jnp.max(jnp.abs(leaf))) > 0 for leaf in jax.tree.leaves(expected))
    for ours, theirs in zip(jax.tree.leaves(gradient), jax.tree.leaves(expected)):
        np.testing.assert_allclose(np.asarray(ours), np.asarray(theirs), rtol=1e-5, atol=1e-9)


def test_the_direction_is_traced_once_per_shape_however_many_programs_reach_a_state(monkeypatch):
    # Every program of a run reaches states (the window and its derivative, the resets, the evaluation): the
    # direction's derivative of the step is traced once for a state's shape, then reused.
    from stablebptt.envs import reward_direction as module
    traced = []
    own = module.reward_direction
    monkeypatch.setattr(module, "reward_direction", lambda *args: traced.append(1) or own(*args))
    env = Ball()
    task = env_task(env, horizon=2, diagnose=False, reward_direction_observed=True)
    state = jax.tree.map(lambda a: a[0], task.sample_initial_states(jax.random.PRNGKey(0), 2))
    before = len(traced)

    def rollout(params):
        reached, total = state, 0.0
        for _ in range(2):
            reached = task.dynamics.step(reached, task.dynamics.policy(params, reached))
            total = total + reached.reward
        return total

    params = task.init_params(jax.random.PRNGKey(1), False)
    for program, arguments in ((lambda s: task.dynamics.step(s, jnp.array([0.2])).direction, (state,)),
                               (lambda s: jax.vmap(task.dynamics.step, (None, 0))(s, jnp.ones((3, 1))).direction, (state,)),
                               (jax.grad(rollout), (params,))):
        jax.make_jaxpr(program)(*arguments)
    assert len(traced) - before <= 1, len(traced) - before


def test_the_settled_task_keeps_the_directed_step_so_a_start_keeps_the_epoch_it_compiled_beside_the_check():
    # engine/starting.py traces and compiles the epoch again where the settled task's step is another function
    # (a smoothed reward's); carrying the direction alone must not make it one.
    pending = env_task(MjxDataBall(), horizon=4, defer_diagnosis=True, reward_direction_observed=True)
    settled = pending.settled_fully()
    assert "reward_smoothing" not in settled.resolved and settled.resolved["reward_direction_observed"] is True
    assert settled.dynamics.step is pending.dynamics.step
    assert settled.episodes.step is pending.episodes.step and settled.episodes.reset is pending.episodes.reset


def test_bad_values_are_refused_in_one_line(tmp_path, capsys):
    import pytest
    from stablebptt.envs.protocol import EnvError
    with pytest.raises(EnvError, match="reward_direction_observed must be True or False"):
        env_task(Ball(), horizon=2, diagnose=False, reward_direction_observed="yes")
