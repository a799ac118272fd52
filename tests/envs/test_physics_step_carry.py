"""MuJoCo Playground's loop of physics steps carrying the state alone (``env_task(physics_steps_carrying_state=True)``,
``--physics-step-carry state``): the same values and derivative as the env's own loop (the closed form of
semi-implicit Euler); bad values refused in one line, and so is the choice on an env whose step calls no such
loop, where it would change nothing."""
import contextlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stablebptt.envs.adapter import env_task
from stablebptt.envs.derivative_model import steps_traced
from stablebptt.envs.protocol import EnvError

from conftest import refused_in_one_line
from envs_for_tests import PlaygroundLoopBall, SubsteppedBall

CARRIED = "the physics steps' loop carrying the state alone"


def test_the_state_carried_loop_keeps_the_values_and_the_derivative():
    env = PlaygroundLoopBall()  # 10 physics steps of 2 ms per control step, through Playground's loop
    state = env.reset(jax.random.PRNGKey(0))
    state = state._replace(data={**state.data, "qpos": jnp.array([0.05])})  # 15 cm clear: no contact
    tasks = {carried: env_task(env, horizon=2, diagnose=False, physics_steps_carrying_state=carried)
             for carried in (False, True)}
    assert CARRIED in tasks[True].summary and CARRIED not in tasks[False].summary
    # The env's own loop runs its 10 physics steps; the state's runs 9 and takes the last after it.
    loops = {carried: str(jax.make_jaxpr(task.dynamics.step)(state, jnp.array([0.3])))
             for carried, task in tasks.items()}
    assert "length=10" in loops[False] and "length=10" not in loops[True] and "length=9" in loops[True]

    def position_after(task):
        return lambda action: task.dynamics.step(task.dynamics.step(state, action), action).data["qpos"][0]
    action = jnp.array([0.3])
    (own_value, own_slope), (carried_value, carried_slope) = (
        jax.jit(jax.value_and_grad(position_after(tasks[carried])))(action) for carried in (False, True))
    np.testing.assert_allclose(carried_value, own_value, rtol=1e-6)
    # Semi-implicit Euler, n steps of h under a constant force: d position / d action = (gear / mass) h^2 n (n + 1) / 2,
    # here n the two control steps' physics steps.
    gear, mass = float(env._mjx_model.actuator_gear[0, 0]), float(env._mjx_model.body_mass[1])
    n, h = 2 * env.n_substeps, env._sim_dt
    np.testing.assert_allclose(float(carried_slope[0]), gear / mass * h ** 2 * n * (n + 1) / 2, rtol=1e-5)
    np.testing.assert_allclose(carried_slope, own_slope, rtol=1e-6)


def test_bad_values_and_an_env_without_playgrounds_loop_are_refused_in_one_line(tmp_path, capsys):
    env = SubsteppedBall()  # its own loop of mjx.step, not Playground's
    state, action = env.reset(jax.random.PRNGKey(0)), jnp.array([0.3])
    with pytest.raises(EnvError, match="^SubsteppedBall: its step calls no MuJoCo Playground loop of physics steps"):
        env_task(env, horizon=2, diagnose=False, physics_steps_carrying_state=True)
    env_step = steps_traced(False, False, False, contextlib.nullcontext, "ball", physics_steps_carrying_state=True)(env)
    for _ in range(2):  # a refusal caught where it was first traced (a start's trace beside its compile) is said again
        with pytest.raises(EnvError, match="calls no MuJoCo Playground loop of physics steps"):
            jax.make_jaxpr(lambda *given: env_step(*given))(state, action)
    refused_in_one_line(capsys, tmp_path / "kept", "--physics-step-carry", "--env",
                        "envs_for_tests:make_substepped_ball", "--physics-step-carry", "kept", "--epochs", "1")
    refused_in_one_line(capsys, tmp_path / "state", "calls no MuJoCo Playground loop", "--env",
                        "envs_for_tests:make_substepped_ball", "--physics-step-carry", "state", "--epochs", "1")
