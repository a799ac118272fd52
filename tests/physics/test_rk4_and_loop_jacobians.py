"""The generated step's Jacobians through RK4's four constrained accelerations (against central differences)
and through a connect loop (against MJX's stages); apart from test_rigid_body_jacobians.py, so that the
two workers share their compiles."""
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from test_rigid_body import (
    HOPPING,
    IN_CONTACT_CONTROL,
    IN_CONTACT_QPOS,
    IN_CONTACT_QVEL,
    LOOPED,
    assert_central_differences,
    coupled_scene,
    lean_of,
)

from stablebptt.physics import lean_step


@pytest.mark.parametrize("jacobian", [jax.jacfwd, jax.jacrev])
def test_rk4_with_constraints_has_the_jacobian_of_central_differences(x64, jacobian):
    """Four constrained accelerations per step, each through the solver's implicit derivative: in contact
    and at a limit, forward and reverse mode against central differences of the step itself."""
    model = mujoco.MjModel.from_xml_string(HOPPING.format(integrator="RK4"))
    lean, effects = lean_of(model)
    inputs = tuple(jnp.array(x) for x in (IN_CONTACT_QPOS, IN_CONTACT_QVEL, IN_CONTACT_CONTROL))
    got = assert_central_differences(lean_step.make_step(lean, effects), inputs, jacobian, rtol=1e-5, atol=1e-6)
    assert np.abs(np.asarray(got[0])).max() > 0.1


def test_a_connect_loop_steps_as_mjx_stages_with_their_jacobians(x64):
    """A connect's rows read the generated body frames. MJX's connect rows are not MuJoCo 4's (their
    reference accelerations differ), so the comparison is with MJX's stages: the step and,
    reverse mode through the generated terms against forward mode through the stages, its Jacobians."""
    model, lean, effects, data = coupled_scene(LOOPED)
    state = lean_step.State(jnp.array(data.qpos), jnp.array(data.qvel), jnp.zeros(0))
    control = jnp.array([0.3, -0.2, 0.1, 0.4, -0.3])
    generated, stages = lean_step.make_step(lean, effects), lean_step.make_step(lean, effects, "stages")
    for a, b in zip(jax.jit(generated)(state, control), jax.jit(stages)(state, control)):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-10)
    expected = jax.jit(jax.jacfwd(stages, argnums=(0, 1)))(state, control)
    got = jax.jit(jax.jacrev(generated, argnums=(0, 1)))(state, control)
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(expected)):
        np.testing.assert_allclose(a, b, rtol=1e-7, atol=1e-9)
    assert np.abs(np.asarray(expected.qvel[1])[:, :2]).max() > 1e-3  # d qvel' / d (the tendons' controls)
