"""MJX's position and velocity stages differentiated without their tree scans (stablebptt.physics.
kinematics_derivative: body frames by the joints' twists; stablebptt.physics.tree_sums: sums over the tree as
constant products): MJX's values to the bit, MJX's own derivative, and MuJoCo's C stages' central differences."""
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from stablebptt.physics.constraint_derivatives import differentiable_mjx
from stablebptt.physics import tree_sums, values_kept
from stablebptt.physics.mjx_internals import forward, mjx, smooth

from conftest import float64, jitted_anew

pytestmark = pytest.mark.fast

# Every joint type and every rule of MuJoCo's trees: a free joint at the top, a hinge, a ball and a slide on one
# body (no rotation may follow a ball), an inertial frame apart from the body's, geoms and sites, a mocap body
# and a second tree.
TREES = """
<mujoco><default><geom contype="0" conaffinity="0"/></default>
<worldbody>
  <body name="torso" pos="0 0 1" quat="0.9 0.1 0.3 0.2"><freejoint/>
    <geom type="box" size="0.2 0.1 0.05" mass="2"/><site name="nose" pos="0.2 0 0.03"/>
    <body name="arm" pos="0.2 0.1 0" euler="10 20 30"><joint type="hinge" axis="0 0 1" pos="0.01 0 0"/>
      <joint type="ball" pos="0 0.02 0"/><joint type="slide" axis="1 1 0"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.04"/>
      <body name="hand" pos="0.3 0 0">
        <inertial pos="0.02 0.01 0" quat="0.8 0.6 0 0" mass="0.3" diaginertia="0.01 0.02 0.03"/>
        <joint type="hinge" axis="0 1 1"/><joint type="slide" axis="0 0 1"/>
        <geom type="sphere" size="0.06" pos="0.01 0 0"/><site name="finger" pos="0.05 0 0"/></body>
    </body>
  </body>
  <body name="target" mocap="true" pos="1 1 1" quat="0.7 0.7 0 0"><geom type="sphere" size="0.05"/></body>
  <body name="cart" pos="-1 0 0.5"><joint type="slide" axis="1 0 0"/><geom type="box" size="0.1 0.1 0.1"/>
    <body name="pole"><joint type="hinge" axis="0 1 0"/><geom type="capsule" fromto="0 0 0 0 0 0.5" size="0.02"/>
    </body></body>
</worldbody></mujoco>"""

_FIELDS = ("qpos", "xanchor", "xaxis", "xpos", "xquat", "xmat", "xipos", "ximat", "geom_xpos", "geom_xmat",
           "site_xpos", "site_xmat", "subtree_com", "cdof")


@pytest.fixture(scope="module")
def trees():
    """The model, a state off its reference pose with a turned mocap body, and the position stage's outputs
    as a function of (qpos, mocap_pos, mocap_quat) and, apart, of the bodies' positions in their parents."""
    model = mujoco.MjModel.from_xml_string(TREES)
    rng = np.random.default_rng(5)
    data = mujoco.MjData(model)
    data.qpos[:] += 0.3 * rng.standard_normal(model.nq)
    data.mocap_quat[:] += 0.2 * rng.standard_normal(data.mocap_quat.shape)
    with float64():
        mjx_model, start = mjx.put_model(model, impl="jax"), mjx.put_data(model, data, impl="jax")

    def placed(qpos, mocap_pos, mocap_quat, body_pos=mjx_model.body_pos):
        data = forward.fwd_position(mjx_model.replace(body_pos=body_pos),
                                    start.replace(qpos=qpos, mocap_pos=mocap_pos, mocap_quat=mocap_quat))
        return {**{name: getattr(data, name) for name in _FIELDS}, "cinert": data._impl.cinert, "M": data._impl.M}

    return model, data, start, mjx_model.body_pos, placed


def _largest_gap(mine, own) -> float:
    return max(float(np.abs(np.asarray(mine[name]) - np.asarray(own[name])).max(initial=0.0)) for name in own)


@pytest.mark.slow  # 30 s of compiling MJX's own derivative beside ours: the full tier
def test_values_are_mjxs_to_the_bit_and_the_derivative_in_every_direction_mjxs_own(trees):
    _, _, start, body_pos, placed = trees
    rng = np.random.default_rng(0)
    state = (start.qpos, start.mocap_pos, start.mocap_quat)
    with float64():
        directions = tuple(jnp.asarray(rng.standard_normal(array.shape)) for array in state)
        along_model = jnp.asarray(rng.standard_normal(np.shape(start.xpos)))  # moves the bodies in their parents

        def tangents(*state):
            return jax.jvp(placed, state, directions)[1]

        def in_the_model(*state):  # a derivative in the model's numbers: MJX's own, kept
            return jax.jvp(lambda moved: placed(*state, moved), (body_pos,), (along_model,))[1]

        def cotangents(*state):
            return jax.vjp(placed, *state)[1](jax.tree.map(jnp.ones_like, placed(*state)))

        own = [jitted_anew(function)(*state) for function in (placed, tangents, in_the_model, cotangents)]
        with differentiable_mjx():
            mine = [jitted_anew(function)(*state) for function in (placed, tangents, in_the_model, cotangents)]
    for name in own[0]:
        np.testing.assert_array_equal(mine[0][name], own[0][name], err_msg=name)
    assert _largest_gap(mine[1], own[1]) < 1e-12 and max(np.abs(own[1][name]).max() for name in own[1]) > 1
    assert _largest_gap(mine[2], own[2]) < 1e-12
    for mine_array, own_array in zip(mine[3], own[3]):
        np.testing.assert_allclose(mine_array, own_array, rtol=1e-12, atol=1e-11)


def _c_position_stage(model, qpos):
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_fwdPosition(model, data)
    mass_matrix = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, mass_matrix)
    return {"xpos": data.xpos.copy(), "xmat": data.xmat.reshape(-1, 3, 3).copy(), "xanchor": data.xanchor.copy(),
            "xaxis": data.xaxis.copy(), "xipos": data.xipos.copy(),
            "geom_xmat": data.geom_xmat.reshape(-1, 3, 3).copy(),
            "site_xpos": data.site_xpos.copy(), "subtree_com": data.subtree_com.copy(), "cdof": data.cdof.copy(),
            "cinert": data.cinert.copy(), "M": mass_matrix}


def test_the_derivative_in_every_coordinate_is_mujocos_c_position_stages(trees):
    model, data, start, _, placed = trees
    eps = 1e-6
    with float64(), differentiable_mjx():
        reverse = jitted_anew(jax.jacrev(lambda qpos: placed(qpos, start.mocap_pos, start.mocap_quat)))(start.qpos)
    # Quaternions move off their sphere in single coordinates; both MuJoCo and MJX normalise them first.
    qpos = data.qpos.copy()
    for index in range(model.nq):
        step = eps * np.eye(model.nq)[index]
        ahead, behind = _c_position_stage(model, qpos + step), _c_position_stage(model, qpos - step)
        for name in ahead:
            central = (ahead[name] - behind[name]) / (2 * eps)
            np.testing.assert_allclose(reverse[name][..., index], central, rtol=1e-6, atol=1e-7,
                                       err_msg=f"{name} along qpos[{index}]")


@pytest.fixture(scope="module")
def moving(trees):
    """The velocity stage's outputs (and the bias forces with accelerations, as inverse dynamics takes them)
    as a function of (qpos, qvel, qacc) and of the model (with gravity, or without), at a state with every dof
    moving; the two models."""
    model, data, start, _, _ = trees
    rng = np.random.default_rng(7)
    weightless = mujoco.MjModel.from_xml_string(TREES)
    weightless.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_GRAVITY
    with float64():
        start = start.replace(qvel=jnp.asarray(rng.standard_normal(model.nv)),
                              qacc=jnp.asarray(rng.standard_normal(model.nv)))
        models = {"gravity": mjx.put_model(model, impl="jax"), "no gravity": mjx.put_model(weightless, impl="jax")}

    def velocity_stage(qpos, qvel, qacc, mjx_model=models["gravity"]):
        data = forward.fwd_velocity(mjx_model, forward.fwd_position(mjx_model, start.replace(qpos=qpos, qvel=qvel,
                                                                                               qacc=qacc)))
        return {"cvel": data.cvel, "cdof_dot": data.cdof_dot, "qfrc_bias": data.qfrc_bias,
                "inverse": smooth.rne(mjx_model, data, flg_acc=True).qfrc_bias}

    return (start.qpos, start.qvel, start.qacc), velocity_stage, models


@pytest.mark.slow  # 25 s of float64 compiles: the full tier (the fast one checks the stage's derivative against C's)
def test_the_velocity_stage_keeps_mjxs_values_and_its_derivative_is_mjxs_own(moving):
    state, velocity_stage, models = moving
    rng = np.random.default_rng(3)
    with float64():
        directions = tuple(jnp.asarray(rng.standard_normal(np.shape(array))) for array in state)

        def moved(mjx_model):
            return lambda *state: jax.jvp(lambda *state: velocity_stage(*state, mjx_model), state, directions)

        def cotangents(*state):
            return jax.vjp(velocity_stage, *state)[1](jax.tree.map(jnp.ones_like, velocity_stage(*state)))

        def both():  # tangents with and without gravity, cotangents, values
            return [*(jitted_anew(moved(mjx_model))(*state) for mjx_model in models.values()),
                    jitted_anew(cotangents)(*state), jitted_anew(velocity_stage)(*state)]

        own = both()
        with differentiable_mjx():
            assert (smooth.com_vel, smooth.rne) == (tree_sums.com_vel, tree_sums.rne)
            mine = both()
    for name in own[3]:
        np.testing.assert_array_equal(mine[3][name], own[3][name], err_msg=name)
    for (own_values, own_tangents), (values, tangents) in zip(own[:2], mine[:2]):
        assert _largest_gap(values, own_values) < 1e-12 and _largest_gap(tangents, own_tangents) < 1e-12
        assert min(np.abs(own_tangents[name]).max() for name in own_tangents) > 1
    assert _largest_gap(own[0][0], own[1][0]) > 1  # gravity is felt
    for mine_array, own_array in zip(mine[2], own[2]):
        np.testing.assert_allclose(mine_array, own_array, rtol=1e-12, atol=1e-11)


def _c_velocity_stage(model, qpos, qvel, qacc):
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:], data.qacc[:] = qpos, qvel, qacc
    mujoco.mj_fwdPosition(model, data)
    mujoco.mj_fwdVelocity(model, data)
    inverse = np.zeros(model.nv)
    mujoco.mj_rne(model, data, 1, inverse)
    return {"cvel": data.cvel.copy(), "cdof_dot": data.cdof_dot.copy(), "qfrc_bias": data.qfrc_bias.copy(),
            "inverse": inverse}


def test_the_velocity_stages_derivative_in_every_coordinate_and_velocity_is_mujocos_c(trees, moving):
    model = trees[0]
    state, velocity_stage, _ = moving
    with float64(), differentiable_mjx():
        reverse = jitted_anew(jax.jacrev(lambda qpos, qvel: velocity_stage(qpos, qvel, state[2]), (0, 1)))(*state[:2])
    qpos, qvel, qacc = (np.asarray(array) for array in state)
    eps = 1e-6
    for argument, size in enumerate((model.nq, model.nv)):
        for index in range(size):
            step = eps * np.eye(size)[index]
            moved = [(qpos + sign * step, qvel) if argument == 0 else (qpos, qvel + sign * step) for sign in (1, -1)]
            ahead, behind = (_c_velocity_stage(model, *pair, qacc) for pair in moved)
            for name in ahead:
                central = (ahead[name] - behind[name]) / (2 * eps)
                np.testing.assert_allclose(reverse[name][argument][..., index], central, rtol=1e-6, atol=1e-7,
                                           err_msg=f"{name} along {('qpos', 'qvel')[argument]}[{index}]")


def test_the_reverse_pass_is_a_smaller_program_than_mjxs(trees):
    _, _, start, _, placed = trees

    def lines():
        def pullback(qpos):
            value, back = jax.vjp(lambda qpos: placed(qpos, start.mocap_pos, start.mocap_quat), qpos)
            return back(jax.tree.map(jnp.ones_like, value))
        return jitted_anew(pullback).lower(start.qpos).as_text().count("\n")

    with float64():
        plain = lines()
        with differentiable_mjx():
            remedied = lines()
    assert remedied < 0.7 * plain, (remedied, plain)  # 6,540 lines against 11,210 as written


def test_both_forms_of_the_constant_product_are_the_product():
    rng = np.random.default_rng(2)
    matrix = (rng.random((5, 7)) < 0.5).astype(np.float64)
    with float64():
        for shape in ((7,), (7, 6), (7, 3, 3)):
            array = rng.standard_normal(shape)
            expected = np.tensordot(matrix, array, axes=1)
            for form in (values_kept._matmul, values_kept._summed):
                np.testing.assert_allclose(form(jnp.asarray(matrix), jnp.asarray(array)), expected, rtol=1e-12,
                                           atol=1e-12, err_msg=f"{form.__name__} of {shape}")


def test_each_platform_compiles_its_own_form_of_the_product():
    """By the platform the program is lowered for, not JAX's default backend: an accelerator's host also
    compiles programs for its CPU (the reward check's), which keep the matmul."""
    matrix = (np.arange(35).reshape(5, 7) % 2).astype(np.float32)
    traced = jax.jit(lambda array: values_kept.times(matrix, array)).trace(jnp.ones((7, 6)))
    texts = {platform: traced.lower(lowering_platforms=(platform,)).as_text() for platform in ("cpu", "cuda")}
    assert "dot_general" in texts["cpu"] and "stablehlo.reduce" not in texts["cpu"]
    assert "stablehlo.reduce" in texts["cuda"] and "dot_general" not in texts["cuda"]


def test_the_derivative_through_a_gpus_form_of_the_product_is_mjxs_own(trees, monkeypatch):
    _, _, start, _, placed = trees
    state = (start.qpos, start.mocap_pos, start.mocap_quat)
    direction = np.random.default_rng(1).standard_normal(np.shape(start.qpos))

    def tangents(*state):
        return jax.jvp(lambda qpos: placed(qpos, *state[1:]), (state[0],), (jnp.asarray(direction),))[1]

    monkeypatch.setattr(values_kept, "PRODUCTS", {"default": values_kept._summed})  # as on a GPU
    with float64():
        own = jitted_anew(tangents)(*state)
        with differentiable_mjx():
            mine = jitted_anew(tangents)(*state)
    assert _largest_gap(mine, own) < 1e-12 and max(np.abs(own[name]).max() for name in own) > 1


def test_the_subtree_velocities_keep_mjxs_values_and_its_derivative_in_every_input(trees):
    model, _, start, _, _ = trees
    rng = np.random.default_rng(7)
    with float64():
        mjx_model = mjx.put_model(model, impl="jax")
        placed = jitted_anew(lambda data: forward.fwd_velocity(mjx_model, forward.fwd_position(mjx_model, data)))(
            start.replace(qvel=jnp.asarray(rng.standard_normal(model.nv))))
        # Every input moved on its own, the centres of mass apart from the bodies: the derivative as a function
        # of what MJX's scans read, not only along states where those agree.
        inputs = (placed.cvel, placed.xipos, placed.ximat, placed.subtree_com)
        directions = tuple(jnp.asarray(rng.standard_normal(np.shape(array))) for array in inputs)

        def velocities(cvel, xipos, ximat, subtree_com):
            moved = smooth.subtree_vel(mjx_model, placed.replace(cvel=cvel, xipos=xipos, ximat=ximat,
                                                                 subtree_com=subtree_com))
            return moved._impl.subtree_linvel, moved._impl.subtree_angmom

        def tangents(*inputs):
            return jax.jvp(velocities, inputs, directions)[1]

        def cotangents(*inputs):
            return jax.vjp(velocities, *inputs)[1](jax.tree.map(jnp.ones_like, velocities(*inputs)))

        own = [jitted_anew(function)(*inputs) for function in (velocities, tangents, cotangents)]
        with differentiable_mjx():
            assert smooth.subtree_vel is tree_sums.subtree_vel
            mine = [jitted_anew(function)(*inputs) for function in (velocities, tangents, cotangents)]
    for mine_array, own_array in zip(mine[0], own[0]):
        np.testing.assert_array_equal(mine_array, own_array)
    assert min(float(np.abs(array).max()) for array in own[1]) > 0.1
    for mine_array, own_array in zip(mine[1] + mine[2], own[1] + own[2]):
        np.testing.assert_allclose(mine_array, own_array, rtol=1e-12, atol=1e-11)


def test_the_subtree_velocities_derivative_in_the_velocities_is_mujocos_c(trees):
    model, data, start, _, _ = trees
    with float64(), differentiable_mjx():
        mjx_model = mjx.put_model(model, impl="jax")

        def velocities(qvel):
            moved = smooth.subtree_vel(mjx_model, forward.fwd_velocity(mjx_model, forward.fwd_position(
                mjx_model, start.replace(qvel=qvel))))
            return jnp.concatenate([moved._impl.subtree_linvel, moved._impl.subtree_angmom], -1)
        jacobian = np.asarray(jitted_anew(jax.jacfwd(velocities))(start.qvel))
    eps = 1e-6

    def c_velocities(qvel):
        moved = mujoco.MjData(model)
        moved.qpos[:], moved.qvel[:], moved.mocap_pos[:], moved.mocap_quat[:] = (data.qpos, qvel, data.mocap_pos,
                                                                                 data.mocap_quat)
        mujoco.mj_forward(model, moved)
        mujoco.mj_subtreeVel(model, moved)
        return np.concatenate([moved.subtree_linvel, moved.subtree_angmom], -1)
    for index in range(model.nv):
        step = np.zeros(model.nv)
        step[index] = eps
        central = (c_velocities(data.qvel + step) - c_velocities(data.qvel - step)) / (2 * eps)
        np.testing.assert_allclose(jacobian[..., index], central, rtol=1e-6, atol=1e-7, err_msg=f"qvel[{index}]")
