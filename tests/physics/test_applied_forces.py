"""Forces applied to bodies (xfrc_applied, fluid forces, gravity compensation) differentiated through subtree
sums (stablebptt.physics.applied_forces): MJX's values to the bit, the derivative MuJoCo's C step's."""
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from stablebptt.physics.constraint_derivatives import differentiable_mjx
from stablebptt.physics.mjx_internals import mjx, support

from conftest import float64, jitted_anew

pytestmark = pytest.mark.fast

# A branched tree: a slide and a hinge at its root, a ball joint and a hinge below, two limbs off the trunk,
# and a second tree of its own; no contacts. Fluid forces (the inertia-box model), gravity compensation on one limb.
BRANCHED = """
<mujoco><option timestep="0.005" density="800" viscosity="0.2" wind="0.3 0 -0.1"/>
<default><geom contype="0" conaffinity="0"/></default>
<worldbody>
  <body name="trunk" pos="0 0 1"><joint type="slide" axis="1 0 0"/><joint type="hinge" axis="0 1 0"/>
    <geom type="box" size="0.2 0.1 0.05" mass="2"/>
    <body name="left" pos="0.2 0.1 0"><joint type="ball"/><geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.04"/>
      <body name="hand" pos="0.3 0 0"><joint type="hinge" axis="0 0 1"/><geom type="sphere" size="0.06"/></body>
    </body>
    <body name="right" pos="-0.2 0.1 0" gravcomp="0.7"><joint type="hinge" axis="1 0 0"/>
      <geom type="capsule" fromto="0 0 0 -0.3 0 0.1" size="0.05"/></body>
  </body>
  <body name="float" pos="1 0 1"><joint type="slide" axis="0 0 1"/><joint type="hinge" axis="1 0 0"/>
    <geom type="ellipsoid" size="0.1 0.2 0.05"/></body>
</worldbody></mujoco>"""


@pytest.fixture(scope="module")
def branched():
    """The model, a state with every joint moving and a force and torque on every body, and the state's
    generalised acceleration as a function of (qpos, qvel) through MJX (float64)."""
    model = mujoco.MjModel.from_xml_string(BRANCHED)
    rng = np.random.default_rng(3)
    data = mujoco.MjData(model)
    mujoco.mj_resetData(model, data)
    data.qpos[:] += 0.2 * rng.standard_normal(model.nq)
    mujoco.mj_normalizeQuat(model, data.qpos)
    data.qvel[:] = rng.standard_normal(model.nv)
    data.xfrc_applied[1:] = rng.standard_normal((model.nbody - 1, 6))
    with float64():
        mjx_model = mjx.put_model(model, impl="jax")
        start = mjx.put_data(model, data, impl="jax")

    def acceleration(qpos, qvel):
        return mjx.forward(mjx_model, start.replace(qpos=qpos, qvel=qvel)).qacc

    return model, data, mjx_model, start, acceleration


def test_every_applied_force_is_simulated_and_the_values_are_mjxs_to_the_bit(branched):
    model, data, _, start, acceleration = branched
    assert model.opt.density > 0 and model.body_gravcomp.any() and np.abs(data.xfrc_applied).sum() > 1
    with float64():
        plain = jitted_anew(acceleration)(start.qpos, start.qvel)
        with differentiable_mjx():
            remedied = jitted_anew(acceleration)(start.qpos, start.qvel)
    np.testing.assert_array_equal(remedied, plain)
    mujoco.mj_forward(model, data)
    np.testing.assert_allclose(plain, data.qacc, rtol=1e-9, atol=1e-9)


def _c_acceleration(model, qpos, qvel):
    data = mujoco.MjData(model)
    data.xfrc_applied[:] = _branched_forces(model)
    data.qpos[:], data.qvel[:] = qpos, qvel
    mujoco.mj_forward(model, data)
    return data.qacc.copy()


def _branched_forces(model):
    rng = np.random.default_rng(3)
    rng.standard_normal(model.nq), rng.standard_normal(model.nv)  # the fixture's draws, in its order
    forces = np.zeros((model.nbody, 6))
    forces[1:] = rng.standard_normal((model.nbody - 1, 6))
    return forces


def test_the_derivative_through_subtree_sums_is_mujocos_c_steps_and_mjxs_own(branched):
    model, data, _, start, acceleration = branched
    np.testing.assert_array_equal(_branched_forces(model), data.xfrc_applied)
    # Tangents in qvel, and in qpos along the hinges and slides (a ball's quaternion moves off its sphere).
    ball = model.jnt_qposadr[model.jnt_type == mujoco.mjtJoint.mjJNT_BALL][0]
    scalar = [index for index in range(model.nq) if not ball <= index < ball + 4]
    eps = 1e-6
    with float64():
        def along_qpos(qpos_part, qvel):
            return acceleration(start.qpos.at[np.array(scalar)].set(qpos_part), qvel)

        arguments = (start.qpos[np.array(scalar)], start.qvel)
        plain = jax.jit(jax.jacrev(along_qpos, argnums=(0, 1)))(*arguments)
        with differentiable_mjx():
            reverse = jax.jit(jax.jacrev(along_qpos, argnums=(0, 1)))(*arguments)
            forward = jax.jit(jax.jacfwd(along_qpos, argnums=(0, 1)))(*arguments)
    qpos, qvel = data.qpos.copy(), data.qvel.copy()
    central_qvel = np.stack([(_c_acceleration(model, qpos, qvel + eps * e)
                              - _c_acceleration(model, qpos, qvel - eps * e)) / (2 * eps)
                             for e in np.eye(model.nv)], axis=1)
    central_qpos = np.stack([(_c_acceleration(model, qpos + eps * np.eye(model.nq)[index], qvel)
                              - _c_acceleration(model, qpos - eps * np.eye(model.nq)[index], qvel)) / (2 * eps)
                             for index in scalar], axis=1)
    assert np.abs(central_qpos).max() > 1 and np.abs(central_qvel).max() > 1
    for mine, own in zip(reverse, plain):
        np.testing.assert_allclose(mine, own, rtol=1e-10, atol=1e-10)
    for mine, mine_forward in zip(reverse, forward):
        np.testing.assert_allclose(mine, mine_forward, rtol=1e-10, atol=1e-10)
    # MJX's own derivative (above) differs from the C step's central differences by up to 2e-5 here,
    # with or without this remedy: the bound is MJX's, at 1e-5 of the largest entry.
    scale = max(np.abs(central_qpos).max(), np.abs(central_qvel).max())
    np.testing.assert_allclose(reverse[0], central_qpos, rtol=1e-4, atol=1e-5 * scale)
    np.testing.assert_allclose(reverse[1], central_qvel, rtol=1e-4, atol=1e-5 * scale)


def test_the_derivative_of_applied_forces_is_a_smaller_program_than_mjxs(branched):
    _, _, mjx_model, start, _ = branched

    def lines():  # reverse mode of the map alone, through what it reads of the data
        def mapped(xipos, cdof, subtree_com):
            return support.xfrc_accumulate(mjx_model, start.replace(xipos=xipos, cdof=cdof, subtree_com=subtree_com))
        pullback = jax.vjp(mapped, start.xipos, start.cdof, start.subtree_com)[1]
        return jax.jit(pullback).lower(jnp.ones(mjx_model.nv)).as_text().count("\n")

    with float64():
        plain = lines()
        with differentiable_mjx():
            remedied = lines()
    assert remedied < plain / 2  # 59 lines against 192 as written


def test_the_derivative_in_the_applied_forces_is_the_inverse_mass_matrix_times_the_jacobians_transpose(branched):
    model, data, mjx_model, start, _ = branched

    def of_forces(applied):
        return mjx.forward(mjx_model, start.replace(xfrc_applied=applied)).qacc

    with float64():
        plain = jax.jit(jax.jacrev(of_forces))(start.xfrc_applied)
        with differentiable_mjx():
            remedied = jax.jit(jax.jacrev(of_forces))(start.xfrc_applied)
    np.testing.assert_allclose(remedied, plain, rtol=1e-10, atol=1e-10)
    # No constraint acts (no contacts, limits or equalities): qacc = M^-1 (... + J(xipos)^T applied).
    mujoco.mj_forward(model, data)
    assert data.nefc == 0
    closed = np.zeros((model.nv, model.nbody, 6))
    for body in range(1, model.nbody):
        jacp, jacr = np.zeros((3, model.nv)), np.zeros((3, model.nv))
        mujoco.mj_jac(model, data, jacp, jacr, data.xipos[body], body)
        for column, axis in enumerate(np.concatenate([jacp, jacr])):
            solved = np.zeros((1, model.nv))
            mujoco.mj_solveM(model, data, solved, axis[None])
            closed[:, body, column] = solved[0]
    assert np.abs(closed).max() > 1
    np.testing.assert_allclose(remedied, closed, rtol=1e-8, atol=1e-8)
