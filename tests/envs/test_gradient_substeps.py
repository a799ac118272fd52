"""A control step differentiated in fewer physics steps than it simulates (``env_task(gradient_substeps=...)``,
``--gradient-substeps``): the task's step keeps the env's values, and its derivative is the closed form of
semi-implicit Euler in that many steps; a flat reward's surrogate is made alike in both steps; an env that
cannot take it, and bad counts, are refused in one line."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stablebptt.envs.adapter import env_task
from stablebptt.envs.protocol import EnvError

from conftest import refused_in_one_line
from envs_for_tests import Ball, SubsteppedBall

GEAR, MASS, CONTROL_STEP = 5.0, 1.0, 0.02  # envs_for_tests.BALL's motor and ball, SubsteppedBall.dt


def test_the_tasks_step_keeps_the_envs_values_and_takes_the_derivative_of_fewer_longer_steps():
    env = SubsteppedBall()  # 10 physics steps of 2 ms per control step
    tasks = {count: env_task(env, horizon=4, diagnose=False, gradient_substeps=count or None) for count in (0, 10, 5, 1)}
    assert "derivative through 5 physics steps per control step" in tasks[5].summary
    assert "physics steps per control step" not in tasks[10].summary  # the env's own count: nothing changes
    state = env.reset(jax.random.PRNGKey(0))
    state = state._replace(data={**state.data, "qpos": jnp.array([0.05])})  # 15 cm clear: no contact

    @jax.jit
    def values_and_slopes(state):
        def position_after(task):
            return lambda action: task.dynamics.step(state, action).data["qpos"][0]
        action = jnp.array([0.3])
        return ({count: task.dynamics.step(state, action) for count, task in tasks.items()},
                {count: jax.grad(position_after(task))(action)[0] for count, task in tasks.items()})

    values, slopes = values_and_slopes(state)
    for count in (10, 5, 1):
        for a, b in zip(jax.tree.leaves(values[0]), jax.tree.leaves(values[count])):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # Semi-implicit Euler in n steps of h = T / n: d position / d action = (gear / mass) h^2 n (n + 1) / 2.
    for count in (0, 5, 1):  # 0: the env's own count
        n = count or 10
        expected = GEAR / MASS * (CONTROL_STEP / n) ** 2 * n * (n + 1) / 2
        np.testing.assert_allclose(float(slopes[count]), expected, rtol=1e-5)


def test_an_env_without_substeps_and_bad_counts_are_refused_in_one_line(tmp_path, capsys):
    with pytest.raises(EnvError, match="Ball: fewer physics steps in the derivative need an env that keeps its physics step"):
        env_task(Ball(), horizon=4, diagnose=False, gradient_substeps=1)
    with pytest.raises(EnvError, match=r"SubsteppedBall simulates 10 physics steps per control step: "
                                       r"gradient_substeps \(--gradient-substeps\), the derivative's count, must "
                                       r"divide it, got 3"):
        env_task(SubsteppedBall(), horizon=4, diagnose=False, gradient_substeps=3)
    with pytest.raises(EnvError, match="env_task's gradient_substeps must be a whole number of physics steps >= 1"):
        env_task(SubsteppedBall(), horizon=4, diagnose=False, gradient_substeps=0)
    for value, expected in (("-1", "--gradient-substeps must be a whole number of physics steps >= 1"),
                            ("3", "make_substepped_ball simulates 10 physics steps per control step")):
        refused_in_one_line(capsys, tmp_path / "refused", expected, "--env", "envs_for_tests:make_substepped_ball",
                            "--gradient-substeps", value, "--epochs", "1")


class FragileBall(SubsteppedBall):
    """The ball whose step's derivative is NaN where its physics step is longer than ``breaks_at`` (as a
    stiff env's can be), and zero where it is exactly that long."""

    def __init__(self, breaks_at: float = 0.015):
        super().__init__()
        self.breaks_at = breaks_at

    def step(self, state, action):
        stepped = super().step(state, action)
        return stepped._replace(reward=stepped.reward * jnp.sqrt(self.breaks_at - self._sim_dt))


def test_a_nan_derivative_of_the_longer_steps_is_refused_naming_them_and_a_flat_one_is_not_smoothed():
    fragile = FragileBall()
    assert env_task(fragile, horizon=4, gradient_substeps=2).settled().settle is None  # 10 ms: finite, not flat
    with pytest.raises(EnvError, match="FragileBall: the reward's gradient is NaN at 100% of sampled states with random "
                                       "actions, its derivative taken through 1 physics steps per control step where "
                                       "the env simulates 10"):
        env_task(fragile, horizon=4, gradient_substeps=1).settled()
    # Flat through the longer steps alone, by a factor of zero, not a comparison: nothing to smooth; refused.
    with pytest.raises(EnvError, match="FragileBall: the reward's gradient is zero at every sampled state and action, "
                                       "and no comparison of the reward could be smoothed"):
        env_task(FragileBall(breaks_at=0.01), horizon=4, gradient_substeps=2).settled()


class BoxBall(SubsteppedBall):
    """The ball paid 1 while within 1 cm of hovering 5 cm clear, else 0 (a tolerance with margin 0):
    a reward whose gradient is zero almost everywhere, which the task smooths."""

    def step(self, state, action):
        stepped = super().step(state, action)
        return stepped._replace(reward=jnp.where(jnp.abs(stepped.data["qpos"][0] + 0.05) <= 0.01, 1.0, 0.0))


def test_a_flat_reward_is_smoothed_alike_in_the_steps_values_and_in_the_fewer_steps_its_derivative_takes():
    """The surrogate's sigmoid at the same temperature in both: the reward's value is the env's own step's
    surrogate, and its slope in the action is that sigmoid's slope times the closed form of the fewer steps."""
    own, fewer = (env_task(BoxBall(), horizon=4, gradient_substeps=count).settled().settled_fully() for count in (None, 2))
    assert own.resolved["reward_smoothing"] == fewer.resolved["reward_smoothing"]
    assert "comparison" in fewer.resolved["reward_smoothing"]
    assert "derivative through 2 physics steps per control step" in fewer.summary
    state = BoxBall().reset(jax.random.PRNGKey(0))
    state = state._replace(data={**state.data, "qpos": jnp.array([-0.02])})  # 8 cm clear, outside the box

    action = jnp.array([0.3])

    @jax.jit
    def reward_and_slope(state):
        return [jax.value_and_grad(lambda a: task.dynamics.step(state, a).reward)(action) for task in (own, fewer)]

    (own_reward, own_slope), (fewer_reward, fewer_slope) = reward_and_slope(state)
    np.testing.assert_array_equal(np.asarray(own_reward), np.asarray(fewer_reward))
    assert 0 < float(own_reward) < 1 and float(own_slope[0]) != 0  # the sigmoid's, not the box's
    # The sigmoid of the box's comparison, sigma((0.01 - |p + 0.05|) / t), its t read from the value; each
    # step's slope is sigma' at the position its own model reaches times d position / d action, which for
    # semi-implicit Euler in n steps of h = T / n is (gear / mass) h^2 n (n + 1) / 2.
    inside = lambda position: 0.01 - abs(position + 0.05)  # noqa: E731
    reached = {n: float(SubsteppedBall(sim_dt=CONTROL_STEP / n).step(state, action).data["qpos"][0]) for n in (10, 2)}
    p = float(own_reward)
    temperature = inside(reached[10]) / np.log(p / (1 - p))
    sigmoid_slope = {n: (s := 1 / (1 + np.exp(-inside(reached[n]) / temperature))) * (1 - s) for n in (10, 2)}
    position_slope = {n: (CONTROL_STEP / n) ** 2 * n * (n + 1) / 2 for n in (10, 2)}
    np.testing.assert_allclose(float(fewer_slope[0]) / float(own_slope[0]),
                               sigmoid_slope[2] * position_slope[2] / (sigmoid_slope[10] * position_slope[10]), rtol=1e-4)


class RewardByStepBall(BoxBall):
    """BoxBall whose reward is the box only while its physics step is as short as its own (a step whose
    Python reads its time step): the derivative's longer steps compute no comparison to smooth alike."""

    def step(self, state, action):
        stepped = super().step(state, action)
        return stepped if self._sim_dt < 0.005 else stepped._replace(reward=jnp.zeros_like(stepped.reward))


def test_a_derivative_model_that_computes_the_reward_otherwise_is_refused_naming_the_comparison():
    with pytest.raises(EnvError, match="RewardByStepBall: the reward's gradient is zero at every sampled state and "
                                       "action, and the derivative's model .* computes the reward otherwise than the "
                                       "env's step \\(nothing at .*test_gradient_substeps.py"):
        env_task(RewardByStepBall(), horizon=4, gradient_substeps=2).settled()
