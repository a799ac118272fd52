"""Physics steps whose loop carries MuJoCo's integration state alone (stablebptt.physics.state_carried): mjx.step
reads no field of the data outside that state, and the steps' values and derivative are the whole data's loop's."""
import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from stablebptt.physics import state_carried
from stablebptt.physics.mjx_internals import mjx

from conftest import float64

# A free body falling onto the floor beside a hinge arm with a motor and a filtered actuator (an activation), a
# fingertip sensor, a mocap target and an accelerometer: contacts and their solver, actuators, activations and
# sensors, so every stage of a step runs.
SCENE = """
<mujoco><worldbody><geom type="plane" size="2 2 0.1"/>
  <body name="ball" pos="0 0 0.1"><freejoint/><geom type="sphere" size="0.1"/><site name="imu"/></body>
  <body name="arm" pos="0.5 0 0.3"><joint name="shoulder" type="hinge" axis="0 1 0" damping="0.1"/>
    <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03"/><site name="tip" pos="0.3 0 0"/></body>
  <body name="target" mocap="true" pos="1 0 0.5"><geom type="sphere" size="0.05" contype="0" conaffinity="0"/></body>
</worldbody>
<actuator><motor joint="shoulder" gear="2"/><general joint="shoulder" dyntype="filter" dynprm="0.05"/></actuator>
<sensor><accelerometer site="imu"/><framepos objtype="site" objname="tip"/><jointpos joint="shoulder"/></sensor>
<equality><joint joint1="shoulder" active="false"/></equality><size nuserdata="2"/>
</mujoco>"""


@pytest.fixture(scope="module")
def scene():
    """The model on MJX and a state in float64 a step past its start, the ball on the floor and the arm moving."""
    with float64():
        model = mujoco.MjModel.from_xml_string(SCENE)
        data = mujoco.MjData(model)
        data.qvel[:3] = (0.3, -0.2, -0.5)
        data.qvel[6] = 1.5
        data.ctrl[:] = 0.4
        mujoco.mj_step(model, data)
        yield mjx.put_model(model, impl="jax"), mjx.put_data(model, data, impl="jax")


def _poisoned(data, fields):
    """``data`` with the floating-point arrays of ``fields`` made NaN (integers and booleans kept)."""
    def nan(leaf):
        return jnp.full_like(leaf, jnp.nan) if jnp.issubdtype(leaf.dtype, jnp.floating) else leaf
    return data.replace(**{name: jax.tree.map(nan, getattr(data, name)) for name in fields})


def test_the_state_carried_is_mujocos_integration_state():
    # MuJoCo's own count of its integration state's numbers: a field left out of READ_BY_STEP (the solver's warm
    # start, whose absence changes no value the other tests see) makes the counts differ where the scene gives it a
    # size, as it does all but the actuators' history and the plugins' state (no delay, no plugin).
    model = mujoco.MjModel.from_xml_string(SCENE)
    data = mujoco.MjData(model)
    sizes = {name: np.size(getattr(data, name)) for name in state_carried.READ_BY_STEP}
    assert sum(sizes.values()) == mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_INTEGRATION)
    assert {name for name, size in sizes.items() if not size} == {"history", "plugin_state"}, sizes


def test_a_step_reads_no_field_outside_the_state(scene):
    # Every field outside READ_BY_STEP made NaN: the step's outputs are those of the data as it was, but for the
    # fields it passes on untouched, which it returns as given.
    model, data = scene
    with float64():
        step = jax.jit(lambda data: mjx.step(model, data))
        poisoned = _poisoned(data, [field.name for field in dataclasses.fields(data)
                                    if field.name not in state_carried.READ_BY_STEP])
        clean, from_poisoned = step(data), step(poisoned)
        passed_on = set()
        for (path, value), given, reached in zip(jax.tree_util.tree_flatten_with_path(clean)[0],
                                                 jax.tree.leaves(poisoned), jax.tree.leaves(from_poisoned)):
            if not np.array_equal(np.asarray(value), np.asarray(reached)):
                # A field the step does not compute comes back as it was given: here NaN, as poisoned.
                assert np.array_equal(np.asarray(reached), np.asarray(given), equal_nan=True), \
                    jax.tree_util.keystr(path)
                passed_on.add(jax.tree_util.keystr(path))
        # What every step computes is among the fields it computed, not passed on.
        assert not passed_on & {".qacc", ".xpos", ".cvel", ".qfrc_bias", ".sensordata", ".act_dot", "._impl.efc_force"}
        # And the state is read: each of its fields with numbers, made NaN alone, changes the step (not the
        # solver's warm start, which the solver takes only where it beats the smooth acceleration, as NaN never does).
        for name in state_carried.READ_BY_STEP:
            leaves = jax.tree.leaves(getattr(data, name))
            if name == "qacc_warmstart" or not any(leaf.size and jnp.issubdtype(leaf.dtype, jnp.floating)
                                                   for leaf in leaves):
                continue
            reached = step(_poisoned(data, [name]))
            assert not all(np.array_equal(np.asarray(a), np.asarray(b))
                           for a, b in zip(jax.tree.leaves(clean), jax.tree.leaves(reached))), name


def test_the_state_carried_steps_are_the_whole_datas_loop(scene):
    model, data = scene
    with float64():
        def whole(data, count):  # the whole data from step to step (unrolled: in float64 MJX's contacts'
            for _ in range(count):  # geom indices come back int64, put_data's int32, which a scan refuses)
                data = mjx.step(model, data)
            return data

        # The data the steps reach, and the derivative of its sensors and velocities in the starting velocities
        # (forward mode: MJX's own solver loop has no reverse mode outside differentiable_mjx), in one program.
        def reached(steps):
            def outputs(qvel):
                end = steps(data.replace(qvel=qvel))
                return jnp.concatenate([end.sensordata, end.qvel]), end
            derivative, end = jax.jit(jax.jacfwd(outputs, has_aux=True))(data.qvel)
            return end, derivative

        # 3 steps: a scan of two, the second reading the state the first carried, then the last step.
        carried, found = reached(lambda data: state_carried.steps(model, data, 3))
        looped, expected = reached(lambda data: whole(data, 3))
        for (path, value), reached_value in zip(jax.tree_util.tree_flatten_with_path(looped)[0],
                                                jax.tree.leaves(carried)):
            np.testing.assert_allclose(reached_value, value, rtol=1e-10, atol=1e-12, err_msg=jax.tree_util.keystr(path))
        assert float(carried.time - data.time) == pytest.approx(3 * float(model.opt.timestep))
        assert np.any(np.asarray(carried._impl.efc_force) > 0)  # the ball pressed on the floor: the solver's forces
        assert state_carried.steps(model, data, 0) is data
        one = jax.jit(lambda data: state_carried.steps(model, data, 1))(data)
        assert jax.tree.all(jax.tree.map(lambda a, b: bool(jnp.array_equal(a, b, equal_nan=True)),
                                         one, jax.jit(lambda data: mjx.step(model, data))(data)))
    assert np.all(np.isfinite(expected)) and np.abs(expected).max() > 1e-3
    np.testing.assert_allclose(found, expected, rtol=1e-9, atol=1e-10)
