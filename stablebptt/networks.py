"""Small controller networks as plain pytrees: a list of (weights, bias) pairs."""
from __future__ import annotations

from typing import Callable, Sequence

import jax
import jax.numpy as jnp

from stablebptt.errors import InputError, whole_number


def glorot_uniform(key: jax.Array, fan_in: int, fan_out: int, shape: tuple[int, ...] | None = None) -> jax.Array:
    """Glorot/Xavier uniform initialisation, the Keras default the original uses."""
    limit = jnp.sqrt(6.0 / (fan_in + fan_out))
    return jax.random.uniform(key, shape or (fan_in, fan_out), jnp.result_type(float), -limit, limit)


def mlp_init(key: jax.Array, sizes: Sequence[int], zero_output: bool = True) -> list[tuple[jax.Array, jax.Array]]:
    """Dense layers ``sizes[0] -> ... -> sizes[-1]``: Glorot weights, zero biases.

    Args:
      key: PRNG key.
      sizes: layer widths including input and output, e.g. ``(6, 100, 100, 1)``.
      zero_output: start the output layer's weights at zero, so the initial
        policy outputs exactly zero, as the paper's public run scripts do.
    """
    if getattr(sizes, "ndim", None) == 1:  # a NumPy or JAX vector of widths
        sizes = sizes.tolist()
    if (isinstance(sizes, (str, bytes)) or not isinstance(sizes, Sequence) or len(sizes) < 2
            or not all(whole_number(size) and size > 0 for size in sizes)):
        raise InputError(f"mlp_init's sizes are the layers' widths, the input's first and the output's last: two or "
                         f"more positive whole numbers, e.g. (6, 100, 100, 1); got {sizes!r}")
    try:
        keys = jax.random.split(key, len(sizes) - 1)
    except (TypeError, ValueError):  # JAX's "invalid PRNG key data", or a batch of keys
        shown = repr(key) if getattr(key, "shape", None) is None else f"an array of shape {tuple(key.shape)}"
        raise InputError(f"mlp_init's key is one PRNG key, e.g. jax.random.PRNGKey(0); got {shown}") from None
    layers = []
    for index, (k, fan_in, fan_out) in enumerate(zip(keys, sizes[:-1], sizes[1:])):
        is_output = index == len(sizes) - 2
        weights = jnp.zeros((fan_in, fan_out)) if (is_output and zero_output) else glorot_uniform(k, fan_in, fan_out)
        layers.append((weights, jnp.zeros((fan_out,))))
    return layers


def mlp_apply(layers: list[tuple[jax.Array, jax.Array]], inputs: jax.Array,
              activation: Callable[[jax.Array], jax.Array] = jnp.tanh) -> jax.Array:
    """Hidden layers of ``activation`` (tanh), linear output."""
    hidden = inputs
    for weights, bias in layers[:-1]:
        hidden = activation(hidden @ weights + bias)
    weights, bias = layers[-1]
    return hidden @ weights + bias


def floored_tanh(floor: float):
    """``tanh`` whose derivative is at least ``floor`` (its values unchanged): a policy's action pushed to its
    bound, where tanh's own slope is nearly 0 (0.07 at 2, 0.002 at 4), still passes that share of its
    gradient back to the network. ``floor`` 0: tanh itself."""
    if floor == 0:
        return jnp.tanh

    @jax.custom_jvp
    def squash(x):
        return jnp.tanh(x)

    @squash.defjvp
    def squash_jvp(primals, tangents):
        (x,), (dx,) = primals, tangents
        y = jnp.tanh(x)
        return y, jnp.maximum(1 - y ** 2, jnp.asarray(floor, y.dtype)) * dx

    return squash
