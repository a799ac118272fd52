"""The windows' derivative cut at hard contacts (``env_task(contact_gradient_cut=...)``,
``--contact-gradient-cut``): the step's values stay the env's; at a state whose constraint forces pass
the given body weights the derivative through that state is zero, while the action's own is the
uncut step's; below the load, or clear of contact, the derivative is the uncut step's. Bad values and
envs that cannot take the cut are refused in one line."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stablebptt.engine.config import TrainConfig
from stablebptt.engine.training import make_trainer
from stablebptt.envs.adapter import env_task
from stablebptt.envs.protocol import EnvError
from stablebptt.errors import InputError

from conftest import jitted_anew, refused_in_one_line
from envs_for_tests import Ball, Cart, MjxDataBall

WEIGHT = 9.81  # envs_for_tests.BALL: one body of 1 kg under MuJoCo's default gravity
CUTS = (0.0, 0.5, 2.0)  # none; below the resting ball's load of one body weight; above it


def _ball_at(env, height, settle_steps):
    """The ball's state with its slide at ``height`` (-0.1: the sphere touching the plane), then settled
    for ``settle_steps`` steps with no push."""
    reset, step = jitted_anew(env.reset), jitted_anew(env.step)
    state = reset(jax.random.PRNGKey(0))
    state = step(state._replace(data=state.data.replace(qpos=jnp.array([height]))), jnp.zeros(1))
    for _ in range(settle_steps):
        state = step(state, jnp.zeros(1))
    return state


def test_values_stay_and_the_derivative_stops_only_through_a_state_under_the_load():
    env = MjxDataBall()
    tasks = {cut: env_task(env, horizon=4, diagnose=False, contact_gradient_cut=cut) for cut in CUTS}
    assert "the derivative cut at contact loads above 0.5 body weights" in tasks[0.5].summary
    assert tasks[2.0].resolved["contact_gradient_cut"] == 2.0 and "contact_gradient_cut" not in tasks[0.0].resolved
    resting, clear = _ball_at(env, -0.1, 20), _ball_at(env, 0.05, 0)
    load = float(jnp.linalg.norm(resting.data.qfrc_constraint)) / WEIGHT
    assert 0.5 < load < 2.0, load  # resting on the plane: about its own weight
    assert float(jnp.linalg.norm(clear.data.qfrc_constraint)) == 0.0  # 15 cm clear: nothing touches

    @jax.jit
    def values_and_slopes(state):
        action = jnp.array([0.3])

        def height_after(task, position, push):
            return task.dynamics.step(state._replace(data=state.data.replace(qpos=position)), push).data.qpos[0]
        return ({cut: task.dynamics.step(state, action) for cut, task in tasks.items()},
                {cut: jax.grad(height_after, argnums=(1, 2))(task, state.data.qpos, action) for cut, task in tasks.items()})

    # The states the step cuts at are the episodes' too, where a critic may value them.
    assert tasks[0.0].episodes.gradient_cut is None
    assert [bool(tasks[cut].episodes.gradient_cut(state)) for cut in CUTS[1:] for state in (resting, clear)] == [
        True, False, False, False]
    for state, cut_below in ((resting, True), (clear, False)):
        values, slopes = values_and_slopes(state)
        for cut in CUTS[1:]:
            for a, b in zip(jax.tree.leaves(values[0.0]), jax.tree.leaves(values[cut])):
                np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        through_state = {cut: float(slopes[cut][0][0]) for cut in CUTS}
        through_action = {cut: float(slopes[cut][1][0]) for cut in CUTS}
        assert abs(through_state[0.0]) > 0.5  # a slide's next height follows its height
        assert through_state[0.5] == (0.0 if cut_below else through_state[0.0])
        assert through_state[2.0] == through_state[0.0]
        assert through_action[0.0] != 0.0
        for cut in CUTS[1:]:  # the action's own derivative is never cut: the reward of the loaded state reaches it
            np.testing.assert_allclose(through_action[cut], through_action[0.0], rtol=1e-6)


def test_bad_values_and_envs_without_what_the_cut_reads_are_refused_in_one_line(tmp_path, capsys):
    with pytest.raises(EnvError, match=r"env_task's contact_gradient_cut must be a number of body weights >= 0 \(0: no cut\), got -1"):
        env_task(MjxDataBall(), horizon=4, diagnose=False, contact_gradient_cut=-1.0)
    with pytest.raises(InputError, match="TrainConfig.value_at_gradient_cut: .* cuts no window's derivative to value"):
        make_trainer(env_task(MjxDataBall(), horizon=4, diagnose=False),
                     TrainConfig(critic=True, value_at_gradient_cut=True, epochs=1, batch=2, train_size=2, test_size=2))
    with pytest.raises(EnvError, match="Cart: derivative cuts at contact loads need an env that keeps its MJX model in _mjx_model"):
        env_task(Cart(), horizon=4, diagnose=False, contact_gradient_cut=1.0)
    ball = env_task(Ball(), horizon=4, diagnose=False, contact_gradient_cut=1.0)  # its state's data is a dict
    with pytest.raises(EnvError, match=r"Ball: a derivative cut at contact loads reads the constraint forces of MJX's data in the state \(state.data.qfrc_constraint\)"):
        ball.dynamics.step(Ball().reset(jax.random.PRNGKey(0)), jnp.zeros(1))
    for value, expected in (("-1", "--contact-gradient-cut must be a number of body weights >= 0 (0: no cut), got -1"),
                            ("nan", "--contact-gradient-cut must be a number of body weights >= 0 (0: no cut), got nan")):
        refused_in_one_line(capsys, tmp_path / "refused", expected, "--env", "envs_for_tests:make_mjx_data_ball",
                            "--contact-gradient-cut", value, "--epochs", "1")


def test_the_settled_task_keeps_the_cut_step_so_a_start_traces_its_epoch_once():
    # engine/starting.py rebuilds the trainer and traces the epoch again where the settled task's step is
    # another function (a smoothed reward's); the cut alone must not make it one.
    pending = env_task(MjxDataBall(), horizon=4, defer_diagnosis=True, contact_gradient_cut=2.0)
    settled = pending.settled_fully()
    assert "reward_smoothing" not in settled.resolved
    assert settled.dynamics.step is pending.dynamics.step
