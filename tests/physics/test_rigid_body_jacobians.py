"""The generated step's Jacobians in contact, at limits and in loops (stablebptt/physics/rigid_body.py): reverse
mode through the generated terms and the implicit solver against forward mode through MJX's own stages,
(RK4's and a connect loop's: test_rk4_and_loop_jacobians.py). Apart from test_rigid_body.py, whose scenes
they use, so that the modules' compiles share the cores."""
import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from test_rigid_body import (
    FLOATING_ARM,
    HOPPING,
    IN_CONTACT_CONTROL,
    IN_CONTACT_QPOS,
    IN_CONTACT_QVEL,
    lean_of,
)

from stablebptt.physics import lean_step


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


@functools.cache
def floating_arm_in_contact():
    """The floating arm on the floor, its shoulder turning: its lean model, the state, the control, and
    the Jacobians of forward mode through MJX's stages (computed once for both forms)."""
    model = mujoco.MjModel.from_xml_string(FLOATING_ARM)
    assert (model.nv, model.nu) == (10, 1)
    lean, effects = lean_of(model)
    data = mujoco.MjData(model)
    data.qvel[6:9] = [2.0, -1.0, 0.5]
    for _ in range(200):
        if data.ncon:
            break
        mujoco.mj_step(model, data)
    assert data.ncon > 0
    state = lean_step.State(jnp.array(data.qpos), jnp.array(data.qvel), jnp.zeros(0))
    control = jnp.array(IN_CONTACT_CONTROL[:model.nu])
    expected = jax.jit(jax.jacfwd(lean_step.make_step(lean, effects, "stages"), argnums=(0, 1)))(state, control)
    return lean, effects, state, control, expected


def test_free_and_ball_joints_in_contact_have_mjx_stages_jacobians(x64, form):
    """Through the quaternions' normalisation and the three-dof groups, in either form: the floating torso
    and its arm on the floor, at the size a GPU writes the terms out (the 15-dof floating scene's terms in
    arrays are MuJoCo's: test_rigid_body.py)."""
    lean, effects, state, control, expected = floating_arm_in_contact()
    got = jax.jit(jax.jacrev(lean_step.make_step(lean, effects), argnums=(0, 1)))(state, control)
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(expected)):
        np.testing.assert_allclose(a, b, rtol=1e-7, atol=1e-9)
    assert np.abs(np.asarray(expected.qvel[0].qpos)[6:9, 3:7]).max() > 1e-3  # the shoulder by the torso's turn
