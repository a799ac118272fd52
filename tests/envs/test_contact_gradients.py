"""An environment's contacts smoothed in the derivative alone (``env_task(contact_smoothing=...)``,
``--contact-gradient-margin``, ``--contact-gradient-softness``): the task's step keeps the env's values
and takes the smoothed model's derivative; an env that cannot take it, and bad values, are refused in
one line."""
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

import stablebptt as sb
from stablebptt.envs.adapter import env_task
from stablebptt.envs.protocol import EnvError

from conftest import jitted_anew, train_in_process
from envs_for_tests import Ball, Cart, MjxDataBall

SMOOTHING = sb.ContactSmoothing(margin=0.05, softness=2.0)


def test_the_tasks_step_keeps_the_envs_values_and_sees_a_contact_before_it_is_made():
    env = Ball()
    exact = env_task(env, horizon=4, diagnose=False)
    smoothed = env_task(env, horizon=4, diagnose=False, contact_smoothing=SMOOTHING)
    assert "contacts smoothed in the derivative alone (acting from 0.05 m, time constants x2)" in smoothed.summary
    assert "contacts smoothed" not in exact.summary
    state = env.reset(jax.random.PRNGKey(0))
    # The ball 3 cm clear of the plane, falling: a contact the smoothed model makes within its margin.
    state = state._replace(data={**state.data, "qpos": jnp.array([-0.07]), "qvel": jnp.array([-0.2])})
    action = jnp.array([0.1])

    @jax.jit
    def compare(state):
        def velocity_after(task):
            return lambda qpos: task.dynamics.step(state._replace(data={**state.data, "qpos": qpos}), action).data["qvel"][0]
        values = [task.dynamics.step(state, action) for task in (exact, smoothed)]
        slopes = [jax.grad(velocity_after(task))(state.data["qpos"])[0] for task in (exact, smoothed)]
        return values, slopes

    (exact_value, smoothed_value), (exact_slope, smoothed_slope) = compare(state)
    for a, b in zip(jax.tree.leaves(exact_value), jax.tree.leaves(smoothed_value)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert float(exact_slope) == 0.0 and float(smoothed_slope) < -1.0  # d vz' / d z: only the smoothed sees it


def test_an_env_without_its_mjx_model_and_bad_values_are_refused_in_one_line(tmp_path, capsys):
    with pytest.raises(EnvError, match="Cart: contacts smoothed in the derivative need an env that keeps its MJX model"):
        env_task(Cart(), horizon=4, diagnose=False, contact_smoothing=SMOOTHING)
    untouchable = Ball()  # the same ball with its collisions off: no pair of geoms can touch
    untouchable._mjx_model = untouchable._mjx_model.replace(geom_contype=np.zeros(2, np.int32),
                                                            geom_conaffinity=np.zeros(2, np.int32))
    with pytest.raises(EnvError, match="Ball: its model has no pair of geoms that can touch"):
        env_task(untouchable, horizon=4, diagnose=False, contact_smoothing=SMOOTHING)
    for flag in (mujoco.mjtDisableBit.mjDSBL_CONTACT, mujoco.mjtDisableBit.mjDSBL_CONSTRAINT):
        switched_off = Ball()  # its pairs as they were, contacts off in its flags (as the cart-pole's file says)
        switched_off._mjx_model = switched_off._mjx_model.replace(opt=switched_off._mjx_model.opt.replace(
            disableflags=switched_off._mjx_model.opt.disableflags | flag))
        with pytest.raises(EnvError, match=r"Ball: its model switches contacts off \(opt.disableflags\)"):
            env_task(switched_off, horizon=4, diagnose=False, contact_smoothing=SMOOTHING)
    with pytest.raises(EnvError, match="env_task's contact_smoothing must be a stablebptt.ContactSmoothing"):
        env_task(Cart(), horizon=4, diagnose=False, contact_smoothing=(0.05, 2.0))
    for option, value, expected in (("--contact-gradient-margin", "-0.1", "--contact-gradient-margin must be a number of metres >= 0"),
                                    ("--contact-gradient-softness", "0.5", "--contact-gradient-softness must be a number >= 1")):
        code, err = train_in_process(capsys, "--env", "envs_for_tests:make_cart", option, value, "--epochs", "1",
                                     "--out", str(tmp_path / "refused"))
        assert code == 2 and len(err) == 1 and expected in err[0], err
        assert not (tmp_path / "refused").exists()


@pytest.mark.parametrize("recomputed", [False, True])
def test_the_contacts_geometry_held_keeps_values_and_distances_derivative_and_holds_the_points(recomputed):
    env = MjxDataBall()  # its state carries MJX's data, the step's contacts among it
    # Recomputed, the physics step is rematerialized: the held geometry must reach inside it.
    exact = env_task(env, horizon=4, diagnose=False, physics_steps_recomputed=recomputed)
    held = env_task(env, horizon=4, diagnose=False, contact_geometry_held=True, physics_steps_recomputed=recomputed)
    assert "the contacts' points and frames held in the derivative" in held.summary
    assert "points and frames held" not in exact.summary
    state = jitted_anew(env.reset)(jax.random.PRNGKey(0))
    state = state._replace(data=state.data.replace(qpos=jnp.array([-0.103])))  # the ball 3 mm in the plane
    action = jnp.array([0.1])

    @jax.jit
    def tangents(state):
        def stepped(task):
            step = lambda qpos: task.dynamics.step(state._replace(data=state.data.replace(qpos=qpos)), action)  # noqa: E731
            return jax.jvp(step, (state.data.qpos,), (jnp.ones(1),))
        return stepped(exact), stepped(held)

    (exact_value, exact_tangent), (held_value, held_tangent) = tangents(state)
    for a, b in zip(jax.tree.leaves(exact_value), jax.tree.leaves(held_value)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    exact_contact, held_contact = exact_tangent.data._impl.contact, held_tangent.data._impl.contact
    # The slide lifts the ball: its gap to the plane grows as fast, in both; the contact point, midway, at
    # half that speed in MJX's derivative and not at all where the geometry is held.
    np.testing.assert_allclose(np.asarray(held_contact.dist), np.asarray(exact_contact.dist), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(exact_contact.dist), 1.0, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(exact_contact.pos)[..., 2], 0.5, rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(held_contact.pos), 0.0)
    # The ball moves as a whole along the slide: the Jacobian at any point is the same, so the velocity's
    # derivative is MJX's own.
    np.testing.assert_allclose(np.asarray(held_tangent.data.qvel), np.asarray(exact_tangent.data.qvel), rtol=1e-5)


def test_the_contacts_geometry_held_is_refused_where_it_would_change_nothing(tmp_path, capsys):
    with pytest.raises(EnvError, match="Cart: contacts' points and frames held in the derivative need an env"):
        env_task(Cart(), horizon=4, diagnose=False, contact_geometry_held=True)
    with pytest.raises(EnvError, match="env_task's contact_geometry_held must be True or False"):
        env_task(Ball(), horizon=4, diagnose=False, contact_geometry_held="held")
    for value, expected in (("held", "make_cart: contacts' points and frames held in the derivative need an env"),
                            ("loose", "--contact-gradient-geometry")):
        code, err = train_in_process(capsys, "--env", "envs_for_tests:make_cart", "--contact-gradient-geometry", value,
                                     "--epochs", "1", "--out", str(tmp_path / "refused"))
        assert code == 2 and len(err) == 1 and expected in err[0], err
        assert not (tmp_path / "refused").exists()
