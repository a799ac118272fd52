"""What of MJX's outputs nothing an env returns reads is left out (stablebptt.envs.unread_outputs): sensors
left out of its model, the cameras' poses held in its step; found from the traced reset and step, every
read followed to what it reads; where a read cannot be followed, every sensor and camera stays; the env
left out of them returns the same to the bit."""
from __future__ import annotations

import contextlib
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from stablebptt.envs.adapter import env_task
from stablebptt.envs.protocol import with_reset_traced_once
from stablebptt.envs.unread_outputs import _inner, _scan_parts, outputs_read, unread_outputs_off
from stablebptt.physics.constraint_derivatives import differentiable_mjx

ARM = """
<mujoco>
  <worldbody>
    <body name="arm" pos="0 0 1">
      <!-- a limit: MJX computes acceleration sensors only where its solver has rows -->
      <joint name="hinge" type="hinge" axis="0 1 0" damping="0.1" range="-2 2"/>
      <geom type="capsule" fromto="0 0 0 0.5 0 0" size="0.05"/>
      <site name="tip" pos="0.5 0 0"/>
      <camera name="along" pos="0.25 -1 0" xyaxes="1 0 0 0 0 1"/>
    </body>
  </worldbody>
  <actuator><motor joint="hinge" gear="1"/></actuator>
  <sensor>
    <accelerometer name="acceleration" site="tip"/>
    <jointpos name="angle" joint="hinge"/>
    <force name="force" site="tip"/>
    <subtreelinvel name="velocity" body="arm"/>
  </sensor>
</mujoco>
"""
ANGLE, VELOCITY, ACCELERATION = slice(3, 4), slice(7, 10), slice(0, 3)  # sensordata's addresses, in the file's order


class State(NamedTuple):
    data: Any
    obs: jax.Array
    reward: jax.Array
    done: jax.Array


class Arm:
    """MuJoCo Playground's shape of env (its MJX model in ``_mjx_model``, two physics steps a control step),
    observing ``observe(data)`` after a step and ``observe_at_reset(data)`` after a reset."""

    action_size, observation_size = 1, 4

    def __init__(self, observe: Callable, observe_at_reset: Callable | None = None, xml: str = ARM):
        self.mj_model = mujoco.MjModel.from_xml_string(xml)
        self._mjx_model = mjx.put_model(self.mj_model, impl="jax")
        self.observe, self.observe_at_reset = observe, observe_at_reset or observe

    def reset(self, key):
        data = mjx.make_data(self._mjx_model).replace(qpos=jax.random.uniform(key, (1,)))
        data = mjx.forward(self._mjx_model, data)
        observed = self.observe_at_reset(data)  # before a second forward pass, as a settling reset would
        return State(mjx.forward(self._mjx_model, data), observed, jnp.zeros(()), jnp.zeros(()))

    def step(self, state, action):
        def physics_step(data, _):
            return mjx.step(self._mjx_model, data.replace(ctrl=action)), None
        data = jax.lax.scan(physics_step, state.data, None, length=2)[0]
        return State(data, self.observe(data), -jnp.sum(data.sensordata[ANGLE] ** 2), state.done)


def sensors_read(env, step_context=contextlib.nullcontext):
    return outputs_read(env, env._mjx_model, step_context)["sensors"]


def test_only_the_sensors_a_step_or_a_reset_reads_are_read():
    arm = Arm(lambda data: data.sensordata[VELOCITY], lambda data: jnp.concatenate([data.sensordata[VELOCITY], data.qvel]))
    assert sensors_read(arm) == [False, True, False, True]
    at_reset_only = Arm(lambda data: data.qvel, lambda data: data.sensordata[ACCELERATION])
    assert sensors_read(at_reset_only) == [True, True, False, False]


@pytest.mark.parametrize("observe", [lambda data: data.sensordata * 2.0,  # every element, not by a slice
                                     lambda data: data.sensordata[jnp.array([0, 3])],  # a gather
                                     lambda data: data._impl.cfrc_ext[1],  # a field only the sensors' stages write
                                     lambda data: data._impl.cacc.sum(0)])
def test_a_read_that_cannot_be_followed_keeps_every_sensor(observe):
    arm = Arm(observe)
    assert sensors_read(arm) is None
    left_out = unread_outputs_off(arm)
    assert left_out.sensors == 0 and left_out.env._mjx_model is arm._mjx_model


# The same arithmetic is asked in float64, where it is the same to the bit: in float32 the smaller program's last
# bits follow how XLA fuses it (a camera computed or not moved the velocity sensor's by an ulp).
def test_the_env_without_its_unread_sensors_returns_the_same_to_the_bit():
    with jax.enable_x64(True):
        arm = Arm(lambda data: jnp.concatenate([data.sensordata[VELOCITY], data.qpos]))
        left_out = unread_outputs_off(arm)
        lean = left_out.env
        assert left_out.sensors == 2 and lean is not arm
        assert list(np.asarray(arm._mjx_model.sensor_needstage)) != list(np.asarray(lean._mjx_model.sensor_needstage))
        assert list(np.asarray(lean._mjx_model.sensor_needstage)[[0, 2]]) == [0, 0]  # the acceleration's and the force's

        def episode(env):
            state = env.reset(jax.random.PRNGKey(3))
            states = jax.lax.scan(lambda state, action: (env.step(state, action),) * 2, state, jnp.full((6, 1), 0.4))[1]
            return state.obs, states.obs, states.reward, states.data.qacc, states.data.sensordata
        full, without = jax.jit(lambda: episode(with_reset_traced_once(arm)))(), jax.jit(lambda: episode(lean))()
    assert full[1].dtype == jnp.float64
    for kept, left in zip(full[:4], without[:4]):
        np.testing.assert_array_equal(np.asarray(kept), np.asarray(left))
    assert np.all(np.asarray(without[4])[:, ACCELERATION] == 0.0)  # never computed
    assert np.all(np.linalg.norm(np.asarray(full[4])[:, ACCELERATION], axis=1) > 1.0)  # gravity: the full model's measure it


def test_a_scans_constants_and_carried_values_are_counted_from_its_shapes():
    def looped(constant, carried, scanned):
        return jax.lax.scan(lambda carry, x: (carry * constant + x, carry.sum()), carried, scanned)
    jaxpr = jax.make_jaxpr(looped)(jnp.ones(3), jnp.ones(3), jnp.ones((4, 3))).jaxpr
    scan = next(equation for equation in jaxpr.eqns if equation.primitive.name == "scan")
    assert _scan_parts(scan, _inner(scan)[0]) == (1, 1)  # the constant, the carried vector; the scanned rows


def test_the_step_is_searched_as_the_task_traces_it_inside_its_context():
    entered = []

    @contextlib.contextmanager
    def repaired():  # stands for the task's reward repair, which changes what its step computes
        entered.append(True)
        try:
            yield
        finally:
            entered.pop()
    arm = Arm(lambda data: data.sensordata[ACCELERATION] if entered else data.qvel, lambda data: data.qvel)
    assert sensors_read(arm) == [False, True, False, False]  # the reward's angle alone
    assert sensors_read(arm, repaired) == [True, True, False, False]


def test_a_task_of_the_env_names_the_sensors_left_out_and_leaves_the_callers_env_as_it_was():
    arm = Arm(lambda data: jnp.concatenate([data.sensordata[VELOCITY], data.qpos]))
    needed = np.asarray(arm._mjx_model.sensor_needstage).copy()
    task = env_task(arm, horizon=2, diagnose=False)
    assert "; 2 sensors nothing returned reads not simulated" in task.summary
    assert "; camera poses nothing returned reads not computed" in task.summary
    # Windows trained on another env's reward or a surrogate read states the search did not trace: all stays.
    dense = Arm(lambda data: jnp.concatenate([data.sensordata[VELOCITY], data.qpos]))
    own = env_task(arm, horizon=2, diagnose=False,
                   surrogate_reward=lambda state: -state.data.sensordata[ACCELERATION].sum())
    for task in (env_task(arm, horizon=2, diagnose=False, reward_env=dense), own):
        assert "camera poses" not in task.summary and "sensors nothing returned reads" not in task.summary
    state = jax.tree.map(lambda leaf: leaf[0], own.sample_initial_states(jax.random.PRNGKey(0), 1))
    simulated = arm.step(state, jnp.ones(1)).data.sensordata[ACCELERATION]  # the caller's env: every sensor
    assert float(own.dynamics.step(state, jnp.ones(1)).reward) == pytest.approx(-float(simulated.sum()), rel=1e-5)
    np.testing.assert_array_equal(np.asarray(arm._mjx_model.sensor_needstage), needed)
    every_sensor_read = Arm(lambda data: data.sensordata * 1.0)
    every_sensor_read.observation_size = 10
    assert "sensors nothing returned reads" not in env_task(every_sensor_read, horizon=2, diagnose=False).summary


class ArmWatchingEachPhysicsStep(Arm):
    """Observes a camera's position after each physics step, inside the loop over them."""

    def step(self, state, action):
        def physics_step(data, _):
            data = mjx.step(self._mjx_model, data.replace(ctrl=action))
            return data, data.cam_xpos[0]
        data, seen = jax.lax.scan(physics_step, state.data, None, length=2)
        return State(data, seen[-1], -jnp.sum(data.qpos ** 2), state.done)


CAMERA_SENSOR = ARM.replace("</sensor>", '<framepos name="camera" objtype="camera" objname="along"/></sensor>')


@pytest.mark.parametrize("make", [lambda: Arm(lambda data: data.cam_xpos[0]),
                                  lambda: Arm(lambda data: data.cam_xmat.sum(axis=(1, 2))),
                                  lambda: ArmWatchingEachPhysicsStep(lambda data: data.qpos),  # where MJX wrote it
                                  lambda: Arm(lambda data: data.qpos, xml=CAMERA_SENSOR)],  # by a sensor
                         ids=["position", "orientation", "inside the loop", "a sensor"])
def test_a_step_that_reads_a_cameras_pose_keeps_the_cameras(make):
    arm = make()
    assert outputs_read(arm, arm._mjx_model)["camera poses"] is None
    assert not unread_outputs_off(arm).camera_poses_held


def test_a_step_with_the_cameras_held_returns_the_same_to_the_bit_and_keeps_the_resets_poses():
    with jax.enable_x64(True):  # as above: the same to the bit in float64
        arm = Arm(lambda data: jnp.concatenate([data.sensordata[VELOCITY], data.qpos]))
        assert outputs_read(arm, arm._mjx_model)["camera poses"] is False and unread_outputs_off(arm).camera_poses_held

        def episode(held):
            def step(state, action):
                with differentiable_mjx(implicit_solver=True, camera_poses_held=held):
                    return arm.step(state, action)
            state = arm.reset(jax.random.PRNGKey(5))
            states = jax.lax.scan(lambda state, action: (step(state, action),) * 2, state, jnp.full((6, 1), 0.4))[1]
            return (states.obs, states.reward, states.data.qpos, states.data.qacc), (state.data.cam_xpos,
                                                                                     states.data.cam_xpos)
        (computed, (at_reset, moving)), (held, (_, kept)) = jax.jit(lambda: episode(False))(), jax.jit(lambda: episode(True))()
    for value, value_held in zip(computed, held):
        np.testing.assert_array_equal(np.asarray(value), np.asarray(value_held))
    np.testing.assert_array_equal(np.asarray(kept), np.broadcast_to(np.asarray(at_reset), np.shape(kept)))
    assert np.ptp(np.asarray(moving)[:, 0, 2]) > 1e-3  # computed, the camera on the arm moves with it
