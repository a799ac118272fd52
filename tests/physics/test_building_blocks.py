"""The integrators' convergence orders and the controller network's invariants, against closed forms."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stablebptt.networks import floored_tanh, mlp_apply, mlp_init
from stablebptt.physics.integrators import INTEGRATORS

from conftest import float64

pytestmark = pytest.mark.fast  # make test-fast: closed forms, invariants, tiny horizons


def _oscillator_error(name: str, steps: int) -> float:
    """Error at t = 1 of a driven harmonic oscillator x'' = -x + u (u held), exact: x = u + (x0 - u) cos t + v0 sin t."""
    derivative = lambda state, u: (state[1], -state[0] + u)
    step = INTEGRATORS[name](derivative, 1.0 / steps)
    state = (jnp.array(1.0), jnp.array(0.5))
    state = jax.lax.fori_loop(0, steps, lambda _, s: step(s, jnp.array(0.3)), state)
    exact = 0.3 + 0.7 * np.cos(1.0) + 0.5 * np.sin(1.0)
    return abs(float(state[0]) - exact)


@pytest.mark.parametrize("name, order", [("euler", 1), ("rk4", 4)])
def test_integrators_converge_at_their_order(name, order):
    with float64():
        errors = [_oscillator_error(name, steps) for steps in (20, 40, 80)]
    rates = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))  # halving dt divides the error by 2^order
    np.testing.assert_allclose(rates, order, atol=0.15)


def test_integrators_step_pytrees_of_any_structure():
    derivative = lambda state, u: {"a": state["b"], "b": u * jnp.ones(2)}
    for name, integrator in INTEGRATORS.items():
        out = integrator(derivative, 0.1)({"a": jnp.zeros(2), "b": jnp.ones(2)}, 2.0)
        assert jax.tree.structure(out) == jax.tree.structure({"a": 0, "b": 0}), name
        np.testing.assert_allclose(out["b"], 1.2)  # a constant rate: every scheme is exact


def test_a_zero_output_layer_gives_zero_control_and_a_nonzero_gradient():
    layers = mlp_init(jax.random.PRNGKey(0), (5, 16, 16, 3), zero_output=True)
    inputs = jax.random.normal(jax.random.PRNGKey(1), (5,))
    np.testing.assert_array_equal(mlp_apply(layers, inputs), np.zeros(3))
    # The output layer still learns: its gradient is the last hidden activation.
    gradient = jax.grad(lambda p: mlp_apply(p, inputs).sum())(layers)
    assert float(jnp.abs(gradient[-1][0]).max()) > 0
    glorot = mlp_init(jax.random.PRNGKey(0), (5, 16, 16, 3), zero_output=False)
    assert float(jnp.abs(mlp_apply(glorot, inputs)).max()) > 0
    # Glorot uniform: every weight within sqrt(6 / (fan_in + fan_out)).
    for (weights, bias), (fan_in, fan_out) in zip(glorot, [(5, 16), (16, 16), (16, 3)]):
        assert weights.shape == (fan_in, fan_out) and float(jnp.abs(weights).max()) <= np.sqrt(6 / (fan_in + fan_out))
        np.testing.assert_array_equal(bias, 0.0)


def test_a_floored_tanh_keeps_tanh_s_values_and_its_slope_where_above_the_floor():
    """Its derivative is max(1 - tanh(x)^2, floor): tanh's own near 0, the floor where the action saturates,
    in forward and reverse mode and under vmap."""
    x = jnp.linspace(-6.0, 6.0, 121)
    squash = floored_tanh(0.1)
    np.testing.assert_array_equal(np.asarray(jax.vmap(squash)(x)), np.asarray(jnp.tanh(x)))
    expected = np.maximum(1 - np.tanh(np.asarray(x, np.float64)) ** 2, 0.1)
    np.testing.assert_allclose(np.asarray(jax.vmap(jax.grad(squash))(x)), expected, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(np.asarray(jax.jvp(squash, (x,), (jnp.ones_like(x),))[1]), expected, rtol=1e-6, atol=1e-7)
    assert floored_tanh(0.0) is jnp.tanh  # no floor: tanh itself, its derivative untouched
