"""Contacts smoothed in the derivative alone (``stablebptt.physics.backward_contacts``): a ball above
and in a plane, its values against the exact step's, its derivative against the exact one's where
they must agree and differ, and the smoothed model against MuJoCo's C step of the same parameters."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from stablebptt.errors import InputError
from stablebptt.physics.backward_contacts import (CLOSED_FORM_PAIRS, ContactSmoothing, differentiated_through,
                                                  smoothed_model, softer)
from stablebptt.physics.constraint_derivatives import differentiable_mjx
from stablebptt.physics.mjx_internals import mjx

BALL = """<mujoco><option timestep="0.01"/><worldbody><geom type="plane" size="1 1 .1"/>
<body pos="0 0 0.1"><freejoint/><geom type="sphere" size="0.1" mass="1"/></body></worldbody></mujoco>"""
SMOOTHING = ContactSmoothing(margin=0.05, softness=2.0)
# The ball's centre: 10 cm clear of the plane (beyond the margin), 3 cm clear (inside it), 1 mm in it.
HEIGHTS = jnp.array([0.2, 0.13, 0.099])


def _step(model):
    def step(qpos, qvel):
        with differentiable_mjx(implicit_solver=True):
            data = mjx.step(model, mjx.make_data(model).replace(qpos=qpos, qvel=qvel))
        return data.qpos, data.qvel
    return step


@pytest.fixture(scope="module")
def ball():
    model = mujoco.MjModel.from_xml_string(BALL)
    exact_model = mjx.put_model(model)
    exact, smoothed = _step(exact_model), _step(smoothed_model(exact_model, SMOOTHING))
    stepped = differentiated_through(exact, smoothed)
    up = jnp.zeros(7).at[2].set(1.0)

    @jax.jit
    @jax.vmap
    def measure(height):
        qpos, qvel = jnp.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]).at[2].set(height), jnp.zeros(6)
        values, tangents = jax.jvp(stepped, (qpos, qvel), (up, jnp.zeros(6)))
        exact_values, exact_tangents = jax.jvp(exact, (qpos, qvel), (up, jnp.zeros(6)))
        pulled = jax.grad(lambda q: stepped(q, qvel)[1][2])(qpos)[2]  # reverse mode: d vz' / d z
        return values, exact_values, tangents[1][2], exact_tangents[1][2], pulled, smoothed(qpos, qvel)[1]

    return model, measure(HEIGHTS)


def test_the_values_are_the_exact_steps_bit_for_bit(ball):
    _, (values, exact_values, *_) = ball
    for value, exact in zip(values, exact_values):
        np.testing.assert_array_equal(np.asarray(value), np.asarray(exact))


def test_the_derivative_sees_a_contact_within_the_margin_and_none_beyond_it(ball):
    _, (_, _, smoothed, exact, pulled, _) = ball
    # d vz' / d z: gravity alone does not depend on the height, a contact pushes the harder the lower.
    assert float(smoothed[0]) == 0.0 and float(exact[0]) == 0.0  # 10 cm clear: no contact in either model
    assert float(exact[1]) == 0.0 and float(smoothed[1]) < -1.0  # 3 cm clear: only the smoothed one sees it
    assert float(exact[2]) < -1.0  # in the plane: both see it
    np.testing.assert_allclose(np.asarray(pulled), np.asarray(smoothed), rtol=1e-5)  # reverse mode agrees


def test_a_softness_of_k_divides_the_contacts_stiffness_by_k_squared(ball):
    # MuJoCo's reference acceleration has stiffness 1 / (timeconst^2 dampratio^2 width^2): a time
    # constant k times longer, k^2 times less stiff, the impedance unchanged across the margin's shift.
    _, (_, _, smoothed, exact, _, _) = ball
    np.testing.assert_allclose(float(smoothed[2]) / float(exact[2]), 1.0 / SMOOTHING.softness ** 2, rtol=1e-4)


def test_the_smoothed_model_is_mujocos_own_with_that_margin_and_time_constant(ball):
    model, (*_, smoothed_velocities) = ball
    model.geom_margin[:] += SMOOTHING.margin / 2  # a pair's margin is the sum of its two geoms'
    model.geom_solref[:, 0] *= SMOOTHING.softness
    data = mujoco.MjData(model)
    for height, velocities in zip(np.asarray(HEIGHTS), np.asarray(smoothed_velocities)):
        mujoco.mj_resetData(model, data)
        data.qpos[2] = height
        mujoco.mj_step(model, data)
        np.testing.assert_allclose(velocities, data.qvel, atol=1e-5)


@pytest.mark.parametrize("margin, softness", [(-0.01, 1.0), (float("nan"), 1.0), (0.0, 0.5), (0.0, "2")])
def test_a_smoothing_that_is_not_one_is_refused_in_its_terms(margin, softness):
    with pytest.raises(InputError, match=r"ContactSmoothing\.(margin|softness) must be a number"):
        ContactSmoothing(margin, softness)


def test_the_direct_forms_stiffness_goes_over_k_squared_its_damping_over_k_and_refsafes_floor_holds():
    # Standard form (time constant, damping ratio); direct form (-stiffness, -damping).
    solrefs = np.array([[0.02, 1.0], [-1000.0, -10.0], [0.005, 1.0]])
    # The third's time constant is below twice a time step of 0.005: MuJoCo simulates 0.01 (refsafe).
    np.testing.assert_allclose(softer(solrefs, 2.0, shortest=0.01), [[0.04, 1.0], [-250.0, -5.0], [0.02, 1.0]])


# A tilted capsule in the plane with another across it, a box and a ball in the plane, and a box tilted on
# the first box: capsule-plane, capsule-capsule, box-plane (a contact per corner) and sphere-plane pairs,
# each within 2 cm of its contact, which the closed form differentiates, and a box-box pair (clipped face
# against face), which keeps MJX's own derivative.
PAIRS = """<mujoco><option timestep="0.01"/><worldbody><geom type="plane" size="2 2 .1"/>
<body pos="0 0 0.06" euler="0 10 0"><freejoint/><geom type="capsule" size="0.05 0.3" euler="0 90 0"/></body>
<body pos="0.05 0 0.153" euler="0 0 70"><freejoint/><geom type="capsule" size="0.04 0.25" euler="0 90 0"/></body>
<body pos="0.8 0 0.098" euler="0 0 20"><freejoint/><geom type="box" size="0.1 0.1 0.1"/></body>
<body pos="0.88 0.05 0.295" euler="3 2 25"><freejoint/><geom type="box" size="0.1 0.1 0.1"/></body>
<body pos="-0.8 0 0.09"><freejoint/><geom type="sphere" size="0.1"/></body></worldbody></mujoco>"""


@pytest.fixture(scope="module")
def pairs():
    from stablebptt.physics.mjx_internals import collision_driver, smooth
    model = mjx.put_model(mujoco.MjModel.from_xml_string(PAIRS))

    def contacts(qpos, held):
        with differentiable_mjx(contact_geometry_held=held):
            data = smooth.kinematics(model, mjx.make_data(model).replace(qpos=qpos))
            contact = collision_driver.collision(model, data)._impl.contact
        return contact.dist, contact.pos, contact.frame, contact.geom

    qpos = jnp.asarray(mujoco.MjData(mujoco.MjModel.from_xml_string(PAIRS)).qpos)
    directions = jax.random.normal(jax.random.PRNGKey(0), (4, qpos.shape[0]))
    exact = jax.jit(jax.vmap(lambda d: jax.jvp(lambda q: contacts(q, False)[:3], (qpos,), (d,))))(directions)
    held = jax.jit(jax.vmap(lambda d: jax.jvp(lambda q: contacts(q, True)[:3], (qpos,), (d,))))(directions)
    types = np.asarray(model.geom_type)[np.asarray(jax.jit(lambda q: contacts(q, False)[3])(qpos))]
    return exact, held, types


def test_geometry_held_keeps_the_contacts_values_bit_for_bit(pairs):
    (exact_values, _), (held_values, _), _ = pairs
    assert np.any(np.asarray(exact_values[0]) < 0.01)  # contacts within a cm: the pairs collide
    for exact, held in zip(exact_values, held_values):
        np.testing.assert_array_equal(np.asarray(held), np.asarray(exact))


def test_geometry_held_differentiates_each_distance_by_its_closed_form_and_holds_points_and_frames(pairs):
    (exact_values, exact_tangents), (_, held_tangents), types = pairs
    closed = np.array([tuple(pair) in CLOSED_FORM_PAIRS for pair in types])
    near = np.asarray(exact_values[0][0]) < 0.02  # the pairs MJX found close; the others' witness points jump
    assert (near & closed).sum() >= 7 and (near & ~closed).sum() >= 1
    exact_distance, held_distance = np.asarray(exact_tangents[0]), np.asarray(held_tangents[0])
    assert np.abs(exact_distance[:, near]).max() > 0.1  # the directions move every distance
    # n . (v2 - v1) at the contact point: first-order exact, as MJX's own collision functions differentiate it
    largest = np.abs(exact_distance[:, near & closed]).max()
    np.testing.assert_allclose(held_distance[:, near & closed], exact_distance[:, near & closed], atol=2e-5 * largest)
    for exact, held in zip(exact_tangents[1:], held_tangents[1:]):  # points and frames
        assert np.abs(np.asarray(exact)[:, closed]).max() > 0  # MJX's move with the bodies; held, they do not
        np.testing.assert_array_equal(np.asarray(held)[:, closed], 0.0)
    # Box against box: its points slide along the clipped edges, which the closed form misses; MJX's own
    # derivative, the same program, stays.
    for exact, held in zip(exact_tangents, held_tangents):
        np.testing.assert_allclose(np.asarray(held)[:, ~closed], np.asarray(exact)[:, ~closed], rtol=1e-6, atol=1e-7)
