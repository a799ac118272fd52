"""MJX's solves with a dense mass matrix differentiated as linear solves (stablebptt.physics.mass_solve): MJX's
values to the bit, MJX's own derivative both ways, MuJoCo's C step's central differences, and no derivative of
a Cholesky factor left in the reverse pass."""
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from stablebptt.physics import mass_solve
from stablebptt.physics.constraint_derivatives import differentiable_mjx
from stablebptt.physics.mjx_internals import mjx
from stablebptt.physics.mjx_patches import applied

from conftest import float64, jitted_anew

pytestmark = pytest.mark.fast

# A free body with a chain of hinges and a slide, damped (the Euler integrator factors M + h D again and
# solves with it), no contacts: every solve of the step is one of M's.
CHAIN = """
<mujoco><option timestep="0.01"/><default><joint damping="0.3"/><geom contype="0" conaffinity="0"/></default>
<worldbody>
  <body pos="0 0 1"><freejoint/><geom type="box" size="0.2 0.1 0.05" mass="2"/>
    <body pos="0.2 0 0"><joint axis="0 0 1"/><geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.04"/>
      <body pos="0.3 0 0"><joint axis="0 1 1"/><joint type="slide" axis="1 0 0"/>
        <geom type="sphere" size="0.06" mass="0.5"/></body></body></body>
</worldbody></mujoco>"""


@pytest.fixture(scope="module")
def chain():
    model = mujoco.MjModel.from_xml_string(CHAIN)
    data = mujoco.MjData(model)
    rng = np.random.default_rng(3)
    data.qpos[:] += 0.3 * rng.standard_normal(model.nq)
    data.qvel[:] = rng.standard_normal(model.nv)
    with float64():
        mjx_model, start = mjx.put_model(model, impl="jax"), mjx.put_data(model, data, impl="jax")

    def stepped(qpos, qvel):
        after = mjx.step(mjx_model, start.replace(qpos=qpos, qvel=qvel))
        return after.qpos, after.qvel, after.qacc
    return model, data, start, stepped


@pytest.mark.slow  # 25 s of float64 compiles: the full tier (the fast one checks the step's derivative against C's)
def test_values_are_mjxs_to_the_bit_and_the_derivative_both_ways_mjxs_own(chain):
    _, _, start, stepped = chain
    rng = np.random.default_rng(0)
    with float64():
        state = (start.qpos, start.qvel)
        directions = tuple(jnp.asarray(rng.standard_normal(array.shape)) for array in state)

        def tangents(*state):
            return jax.jvp(stepped, state, directions)[1]

        def cotangents(*state):
            return jax.vjp(stepped, *state)[1](jax.tree.map(jnp.ones_like, stepped(*state)))

        def second(*state):  # the second derivative along the directions
            return jax.jvp(tangents, state, directions)[1]

        functions = (stepped, tangents, cotangents, second)
        own = [jitted_anew(function)(*state) for function in functions]
        with applied("mass solve", mass_solve.REMEDIES):
            mine = [jitted_anew(function)(*state) for function in functions]
    for mine_array, own_array in zip(mine[0], own[0]):
        np.testing.assert_array_equal(mine_array, own_array)
    assert max(float(np.abs(array).max()) for array in own[1] + own[3]) > 1
    for mine_array, own_array in zip(mine[1] + mine[2] + mine[3], own[1] + own[2] + own[3]):
        np.testing.assert_allclose(mine_array, own_array, rtol=1e-11, atol=1e-11)


def test_the_steps_derivative_is_mujocos_c_steps_central_differences(chain):
    model, data, start, stepped = chain
    with float64(), differentiable_mjx():
        along_qpos, along_qvel = jitted_anew(jax.jacfwd(lambda qpos, qvel: stepped(qpos, qvel)[1], argnums=(0, 1)))(
            start.qpos, start.qvel)
    eps = 1e-6

    def c_step(qpos, qvel):
        moved = mujoco.MjData(model)
        moved.qpos[:], moved.qvel[:] = qpos, qvel
        mujoco.mj_step(model, moved)
        return moved.qvel.copy()
    # The free joint's position, the hinges' angles and the slide (M moves with the last three), every velocity.
    for argument, indices, jacobian in ((0, [0, 1, 2, 7, 8, 9], along_qpos), (1, range(model.nv), along_qvel)):
        for index in indices:
            step = np.zeros(len(data.qpos) if argument == 0 else model.nv)
            step[index] = eps
            moved = [(data.qpos + sign * step, data.qvel) if argument == 0 else (data.qpos, data.qvel + sign * step)
                     for sign in (1, -1)]
            central = (c_step(*moved[0]) - c_step(*moved[1])) / (2 * eps)
            np.testing.assert_allclose(np.asarray(jacobian)[:, index], central, rtol=1e-6, atol=1e-7,
                                       err_msg=f"{('qpos', 'qvel')[argument]}[{index}]")


def test_the_reverse_pass_differentiates_no_cholesky_factor(chain):
    _, _, start, stepped = chain

    def solves():  # M moves with the position alone: the columns of each triangular solve's right-hand side
        def pullback(qpos):
            value, back = jax.vjp(lambda qpos: stepped(qpos, start.qvel), qpos)
            return back(jax.tree.map(jnp.ones_like, value))
        return _solved_columns(jax.make_jaxpr(pullback)(start.qpos).jaxpr)

    with float64():
        plain = solves()
        with applied("mass solve", mass_solve.REMEDIES):
            remedied = solves()
    # Two factors a step (the position stage's and the damped Euler's): as written, each factor's tangent takes
    # triangular solves with whole matrices; remedied, only the solves with vectors remain (8 against 16).
    nv = start.qvel.shape[0]
    assert nv in plain and remedied and set(remedied) == {1}, (plain, remedied)


def _solved_columns(jaxpr) -> list[int]:
    """Each triangular solve's count of right-hand sides (1: a vector), in ``jaxpr`` and every program it calls."""
    found = []
    for equation in jaxpr.eqns:
        if equation.primitive.name == "triangular_solve":
            rows, columns = equation.invars[1].aval.shape[-2:]
            found.append(columns if equation.params["left_side"] else rows)
        for inner in jax.extend.core.jaxprs_in_params(equation.params):
            found += _solved_columns(inner)
    return found
