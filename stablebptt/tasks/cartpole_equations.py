"""Closed-form cart-pole dynamics: the physics reference for the MJX models and the speed floor.

Poles of mass m and half-length l hang in parallel from one cart (uniform rods,
inertia m (2l)^2 / 3 about the pivot). Angle 0 is upright.
"""
from __future__ import annotations

import jax.numpy as jnp

from stablebptt.physics.lean_step import State

CART_MASS, POLE_MASS, HALF_LENGTH, GRAVITY = 1.0, 0.1, 0.5, 9.8


def classic_accelerations(state: State, force: jnp.ndarray) -> jnp.ndarray:
    """The classic single-pole equations (Barto et al.; the Gym cart-pole), verbatim."""
    theta, theta_dot = state.qpos[1], state.qvel[1]
    total_mass = CART_MASS + POLE_MASS
    temp = (force + POLE_MASS * HALF_LENGTH * theta_dot**2 * jnp.sin(theta)) / total_mass
    theta_acc = (GRAVITY * jnp.sin(theta) - jnp.cos(theta) * temp) / (
        HALF_LENGTH * (4.0 / 3.0 - POLE_MASS * jnp.cos(theta) ** 2 / total_mass))
    x_acc = temp - POLE_MASS * HALF_LENGTH * theta_acc * jnp.cos(theta) / total_mass
    return jnp.stack([x_acc, theta_acc])


def exact_accelerations(state: State, force: jnp.ndarray) -> jnp.ndarray:
    """Exact rigid-body accelerations for any number of parallel poles.

    Eliminating each pole's equation, (4/3) l theta'' = g sin(theta) - cos(theta) x'',
    from the cart's leaves one scalar equation for x''. With one pole this is the
    classic system above.
    """
    theta, theta_dot = state.qpos[1:], state.qvel[1:]
    sin, cos = jnp.sin(theta), jnp.cos(theta)
    effective_mass = CART_MASS + jnp.sum(POLE_MASS * (1.0 - 0.75 * cos**2))
    x_acc = (force + jnp.sum(POLE_MASS * HALF_LENGTH * sin * theta_dot**2)
             - jnp.sum(0.75 * POLE_MASS * GRAVITY * sin * cos)) / effective_mass
    theta_acc = (GRAVITY * sin - cos * x_acc) / (4.0 / 3.0 * HALF_LENGTH)
    return jnp.concatenate([x_acc[None], theta_acc])


def make_step(dt: float = 0.01, accelerations=exact_accelerations):
    """Semi-implicit Euler (velocity first, then position), as MuJoCo's Euler integrator."""
    def step(state: State, ctrl: jnp.ndarray) -> State:
        qvel = state.qvel + dt * accelerations(state, ctrl[0])
        return State(state.qpos + dt * qvel, qvel, state.act)

    return step
