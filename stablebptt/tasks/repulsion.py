"""Guidance by repulsion: two drivers herd four evaders towards the origin.

Hand-written JAX integrator (explicit Euler: positions advance with the old
velocities), with the constants, data and loss of the paper's public code.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import jax
import jax.numpy as jnp

from stablebptt.engine.task import CellOption, Task
from stablebptt.errors import InputError, check_field_types, config_field, keywords_named
from stablebptt.flows.dynamics import Dynamics
from stablebptt.networks import mlp_apply, mlp_init
from stablebptt.physics.integrators import INTEGRATORS

DEFAULT_EPOCHS = 100  # the public script says 10; the paper's smoothed figures imply more.


@keywords_named
@dataclass(frozen=True)
class Config:
    """Options of the repulsion task."""

    rc: float = field(default=0.1, metadata={"help": "regularisation coefficient of the control cost (paper: 1, 0.1, 0.01, 0.001)"})
    integrator: str = field(default="euler", metadata={"help": "euler (the paper's explicit Euler) or rk4", "choices": ("euler", "rk4")})
    steps: int = field(default=60, metadata={"help": "time steps over T = 4 (the paper: 60)"})

    def __post_init__(self):
        check_field_types(self)
        if not self.rc >= 0:
            raise InputError(f"{config_field(self, 'rc')} must be zero or positive, got {self.rc}")
        if self.steps <= 0:
            raise InputError(f"{config_field(self, 'steps')} must be a positive integer, got {self.steps}")


@dataclass(frozen=True)
class Physics:
    """Constants of the paper's repulsion system (names follow the original)."""

    drivers: int = 2
    evaders: int = 4
    duration: float = 4.0
    epsilon: float = 0.1  # every distance is epsilon + |r|: close encounters stay finite
    c_evade: float = 15.0
    c_flock: float = 0.2
    d_flock: float = 0.5
    c_spread: float = 0.2
    evader_friction: float = 4.0
    driver_friction: float = 1.0


class State(NamedTuple):
    """Drivers first, then evaders; shapes [agents, 2]."""

    position: jax.Array
    velocity: jax.Array


def _safe_norm(r: jax.Array) -> jax.Array:
    """|r| over the last axis with a zero (not NaN) gradient at r = 0."""
    squared = jnp.sum(r * r, axis=-1)
    nonzero = squared > 0
    return jnp.where(nonzero, jnp.sqrt(jnp.where(nonzero, squared, 1.0)), 0.0)


def _pairs(a: jax.Array, b: jax.Array, epsilon: float):
    """diff[i, j] = a_i - b_j and the softened distance epsilon + |diff|."""
    diff = a[:, None, :] - b[None, :, :]
    return diff, epsilon + _safe_norm(diff)


def rot90(v: jax.Array) -> jax.Array:
    return jnp.stack([-v[..., 1], v[..., 0]], axis=-1)


def accelerations(physics: Physics, state: State, coefficients: jax.Array) -> jax.Array:
    """Forces (unit masses) on every agent; ``coefficients`` is [drivers, 2] = (c0, c1)."""
    drivers, evaders = state.position[: physics.drivers], state.position[physics.drivers :]
    # Driver i repels evader k: 15 * -(d^-2) * (x_i - x_k), summed over drivers.
    diff, d = _pairs(drivers, evaders, physics.epsilon)
    on_evaders = jnp.sum(-physics.c_evade * d[..., None] ** -2 * diff, axis=0)
    # Evader i acts on evader j: 0.2 * ((0.5/d - 1)/d) * (x_i - x_j); i == j gives zero.
    diff, d = _pairs(evaders, evaders, physics.epsilon)
    on_evaders += jnp.sum(physics.c_flock * ((physics.d_flock / d - 1.0) / d)[..., None] * diff, axis=0)
    # Driver i pushes driver j apart: 0.2 * d^-2 * (x_j - x_i).
    diff, d = _pairs(drivers, drivers, physics.epsilon)
    on_drivers = jnp.sum(physics.c_spread * d[..., None] ** -2 * -diff, axis=0)
    # The control: c0 * r + c1 * rot90(r), r relative to the SUM of evader positions (as the original).
    relative = drivers - jnp.sum(evaders, axis=0)
    on_drivers += coefficients[:, :1] * relative + coefficients[:, 1:] * rot90(relative)
    friction = jnp.concatenate([
        jnp.full((physics.drivers, 1), physics.driver_friction),
        jnp.full((physics.evaders, 1), physics.evader_friction),
    ])
    return jnp.concatenate([on_drivers, on_evaders]) - friction * state.velocity


def make_step(physics: Physics, dt: float, integrator: str = "euler"):
    """``step(state, control)`` with the control held over the step."""
    def derivative(state, control):
        return State(state.velocity, accelerations(physics, state, control.reshape(physics.drivers, 2)))

    return INTEGRATORS[integrator](derivative, dt)


def observe(state: State) -> jax.Array:
    return jnp.concatenate([state.position.ravel(), state.velocity.ravel()])


def sample_initial_states(physics: Physics, key: jax.Array, count: int) -> State:
    """Drivers on the annulus r in [3, 4]; evaders within +-0.5 of a centre on r in [1, 2]; at rest."""
    k_driver_r, k_driver_a, k_centre_r, k_centre_a, k_offset = jax.random.split(key, 5)

    def on_annulus(k_radius, k_angle, shape, low, high):
        radius = jax.random.uniform(k_radius, shape, minval=low, maxval=high)
        angle = jax.random.uniform(k_angle, shape, minval=0.0, maxval=2 * jnp.pi)
        return jnp.stack([radius * jnp.cos(angle), radius * jnp.sin(angle)], axis=-1)

    drivers = on_annulus(k_driver_r, k_driver_a, (count, physics.drivers), 3.0, 4.0)
    centres = on_annulus(k_centre_r, k_centre_a, (count, 1), 1.0, 2.0)
    evaders = centres + jax.random.uniform(k_offset, (count, physics.evaders, 2), minval=-0.5, maxval=0.5)
    position = jnp.concatenate([drivers, evaders], axis=1)
    return State(position, jnp.zeros_like(position))


def make(config: Config, physics: Physics = Physics()) -> Task:
    step = make_step(physics, physics.duration / config.steps, config.integrator)
    agents = physics.drivers + physics.evaders
    sizes = (4 * agents, 100, 100, 2 * physics.drivers)

    def policy(params, state):
        return mlp_apply(params, observe(state))

    def dynamics_with(rc):
        """rc enters only the loss, so a sweep passes it per cell as a traced value."""
        def loss(states, controls):
            # Mean over steps 1..T, evaders and coordinates of the squared distance to the origin.
            evaders = states.position[:, physics.drivers :]
            return jnp.mean(evaders**2) + rc * jnp.mean(controls**2)

        return Dynamics(step=step, policy=policy, loss=loss, horizon=config.steps)

    return Task(
        name="repulsion",
        dynamics=dynamics_with(config.rc),
        init_params=lambda key, zero_output: mlp_init(key, sizes, zero_output),
        sample_initial_states=lambda key, count: sample_initial_states(physics, key, count),
        cell_option=CellOption("rc", dynamics_with),
    )


def program_inputs(config: Config) -> dict:
    """What the task's compiled programs read besides the library and ``config``: nothing."""
    return {}
