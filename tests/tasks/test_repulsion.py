"""Guidance by repulsion: forces point the right way, close encounters stay finite, friction decays speed."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stablebptt.flows.gradients import flow_gradients, reference_rollout
from stablebptt.tasks import repulsion
from stablebptt.tasks.repulsion import Physics, State, accelerations

pytestmark = pytest.mark.fast  # make test-fast: closed forms, invariants, tiny horizons


def test_an_evader_is_pushed_away_from_a_driver():
    physics = Physics(drivers=1, evaders=1)
    driver, evader = jnp.array([0.0, 0.0]), jnp.array([0.6, 0.8])
    state = State(jnp.stack([driver, evader]), jnp.zeros((2, 2)))
    push = accelerations(physics, state, jnp.zeros((1, 2)))[1]
    away = (evader - driver) / jnp.linalg.norm(evader - driver)
    assert float(push @ away) > 0
    np.testing.assert_allclose(push, physics.c_evade / (physics.epsilon + 1.0) ** 2 * (evader - driver), rtol=1e-6)


def test_coincident_agents_give_finite_forces_and_gradients():
    physics = Physics()
    state = State(jnp.zeros((6, 2)), jnp.zeros((6, 2)))  # everyone at the origin
    # Jitted: run eagerly, every operation would be compiled apart.
    forces = jax.jit(lambda s: accelerations(physics, s, jnp.ones((2, 2))))(state)
    assert np.all(np.isfinite(forces))
    jacobian = jax.jit(jax.jacobian(lambda p: accelerations(physics, State(p, state.velocity), jnp.ones((2, 2)))))(state.position)
    assert np.all(np.isfinite(jacobian))


def test_friction_alone_decays_speed_geometrically():
    physics = Physics(c_evade=0.0, c_flock=0.0, c_spread=0.0)
    dt = physics.duration / 60
    step = repulsion.make_step(physics, dt)
    velocity = jax.random.normal(jax.random.PRNGKey(0), (6, 2))
    state = State(jax.random.normal(jax.random.PRNGKey(1), (6, 2)) * 3, velocity)
    for _ in range(10):
        state = step(state, jnp.zeros(4))
    friction = np.array([physics.driver_friction] * 2 + [physics.evader_friction] * 4)[:, None]
    np.testing.assert_allclose(state.velocity, velocity * (1 - dt * friction) ** 10, rtol=1e-5)
    assert np.all(np.linalg.norm(state.velocity, axis=1) < np.linalg.norm(velocity, axis=1))


def test_a_driver_through_an_evader_keeps_states_and_gradients_finite():
    task = repulsion.make(repulsion.Config(rc=0.01))
    # Every agent starts at the origin; driver 0 then races through the evaders.
    position = jnp.zeros((6, 2))
    velocity = jnp.zeros((6, 2)).at[0].set(jnp.array([8.0, 0.0]))
    start = State(position, velocity)
    params = task.init_params(jax.random.PRNGKey(0), False)
    trajectory = jax.jit(lambda p, s: reference_rollout(task.dynamics, p, s))(params, start)
    assert np.all(np.isfinite(trajectory.states.position))
    batch = jax.tree.map(lambda a: a[None], start)
    _, grads = jax.jit(lambda p, s: flow_gradients(task.dynamics, ("R", "M", "S"), p, s))(params, batch)
    assert all(np.all(np.isfinite(leaf)) for leaf in jax.tree.leaves(grads))


def test_initial_states_follow_the_paper():
    physics = Physics()
    states = repulsion.sample_initial_states(physics, jax.random.PRNGKey(0), 512)
    driver_radius = np.linalg.norm(states.position[:, :2], axis=-1)
    assert driver_radius.min() >= 3.0 and driver_radius.max() <= 4.0
    centre = states.position[:, 2:].mean(axis=1)  # the evaders' mean lies within 0.5 of their centre
    assert np.linalg.norm(centre, axis=-1).min() >= 1.0 - 0.5 * np.sqrt(2)
    spread = states.position[:, 2:] - states.position[:, 2:].mean(axis=1, keepdims=True)
    assert np.abs(spread).max() <= 1.0
    assert np.all(states.velocity == 0)
