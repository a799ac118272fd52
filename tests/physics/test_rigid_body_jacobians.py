"""The generated step's Jacobians in contact, at limits and in loops (stablebptt/physics/rigid_body.py): reverse
mode through the generated terms and the implicit solver against forward mode through MJX's own stages,
(RK4's and a connect loop's: test_rk4_and_loop_jacobians.py). Apart from test_rigid_body.py, whose scenes
they use, so that the modules' compiles share the cores."""
import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from test_rigid_body import (
    FLOATING_ARM,
    HOPPING,
    IN_CONTACT_CONTROL,
    IN_CONTACT_QPOS,
    IN_CONTACT_QVEL,
    lean_of,
)

from stablebptt.physics import lean_step, rigid_body
from stablebptt.physics.array_terms import ArrayTerms
from stablebptt.physics.written_out import WrittenOut


def test_the_generated_step_with_constraints_has_mjx_stages_jacobians(x64):
    """In contact and at a limit, reverse mode through the generated terms and the implicit solver gives
    the Jacobians of forward mode through MJX's stages and the same solver."""
    model = mujoco.MjModel.from_xml_string(HOPPING.format(integrator="Euler"))
    lean, effects = lean_of(model)
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:] = IN_CONTACT_QPOS, IN_CONTACT_QVEL
    mujoco.mj_forward(model, data)
    assert data.ncon > 0 and int(mujoco.mjtConstraint.mjCNSTR_LIMIT_JOINT) in data.efc_type[:data.nefc]
    state = lean_step.State(jnp.array(data.qpos), jnp.array(data.qvel), jnp.zeros(0))
    control = jnp.array(IN_CONTACT_CONTROL)
    generated = lean_step.make_step(lean, effects)
    stages = lean_step.make_step(lean, effects, "stages")
    expected = jax.jit(jax.jacfwd(stages, argnums=(0, 1)))(state, control)
    got = jax.jit(jax.jacrev(generated, argnums=(0, 1)))(state, control)
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(expected)):
        np.testing.assert_allclose(a, b, rtol=1e-7, atol=1e-9)
    assert np.abs(np.asarray(expected.qvel[0].qpos)).max() > 1e-3


def replaced(mjcf: str, part: str, by: str = "") -> str:
    """``mjcf`` with ``part`` (which must be in it: a scene derived from an edited one fails here) replaced."""
    assert part in mjcf, part
    return mjcf.replace(part, by)


# The written-out form's compile grows with the terms a scene couples (about 100 s for the torso and its
# arm together, 15 s and 28 s apart, on one core), so that form is checked on each joint group alone;
# the coupled scene in the array form, which compiles its loops once.
ARM = FLOATING_ARM[FLOATING_ARM.index('      <body name="arm"'):FLOATING_ARM.index("    </body>\n  </worldbody>")]
ELBOW_MOTOR = FLOATING_ARM[FLOATING_ARM.index("  <actuator>"):FLOATING_ARM.index("</mujoco>")]
FREE_BODY = replaced(replaced(FLOATING_ARM, ARM), ELBOW_MOTOR)  # the torso alone, falling
# The arm alone, hung where the torso was from the world, a little lower: on its ball joint it swings down
# into the floor.
TORSO = '      <joint name="root" type="free" damping="0.01"/>\n      <geom type="capsule" fromto="-0.1 0 0 0.1 0 0" size="0.05" mass="2"/>\n'
BALL_ARM = replaced(replaced(FLOATING_ARM, TORSO), 'pos="0.1 0.2 0.35"', 'pos="0.1 0.2 0.3"')
# scene -> (its MJCF, the form its terms take, the columns of its orientation's quaternion in qpos)
FREE_AND_BALL = {"free body, written out": (FREE_BODY, "written out", slice(3, 7)),
                 "ball arm, written out": (BALL_ARM, "written out", slice(0, 4)),
                 "torso and arm, in arrays": (FLOATING_ARM, "in arrays", slice(3, 7))}


@functools.cache
def in_contact(xml):
    """The scene on the floor, falling or swinging into it: its lean model, the state, the control, and the
    Jacobians of forward mode through MJX's stages."""
    model = mujoco.MjModel.from_xml_string(xml)
    lean, effects = lean_of(model)
    data = mujoco.MjData(model)
    data.qvel[-min(model.nv, 3):] = [2.0, -1.0, 0.5][:min(model.nv, 3)]
    for _ in range(400):
        if data.ncon:
            break
        mujoco.mj_step(model, data)
    assert data.ncon > 0
    state = lean_step.State(jnp.array(data.qpos), jnp.array(data.qvel), jnp.zeros(0))
    control = jnp.array(IN_CONTACT_CONTROL[:model.nu])
    expected = jax.jit(jax.jacfwd(lean_step.make_step(lean, effects, "stages"), argnums=(0, 1)))(state, control)
    return lean, effects, state, control, expected


@pytest.mark.parametrize("name", FREE_AND_BALL)
def test_free_and_ball_joints_in_contact_have_mjx_stages_jacobians(x64, monkeypatch, name):
    """Through the quaternions' normalisation and the three-dof groups, in the form each scene's terms take:
    a free body and a ball-jointed arm on the floor written out, as a GPU writes them, and the floating
    torso with its arm in arrays (the 15-dof floating scene's terms in arrays are MuJoCo's: test_rigid_body.py)."""
    xml, form, quaternion = FREE_AND_BALL[name]
    most = 1000 if form == "written out" else 0
    monkeypatch.setattr(rigid_body, "WRITTEN_OUT_DOFS", {"cpu": most, "gpu": most})
    lean, effects, state, control, expected = in_contact(xml)
    assert isinstance(rigid_body.make_scene(mujoco.MjModel.from_xml_string(xml)), WrittenOut if most else ArrayTerms)
    got = jax.jit(jax.jacrev(lean_step.make_step(lean, effects), argnums=(0, 1)))(state, control)
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(expected)):
        np.testing.assert_allclose(a, b, rtol=1e-7, atol=1e-9)
    assert np.abs(np.asarray(expected.qvel[0].qpos)[:, quaternion]).max() > 1e-3  # the velocities by the turn
