"""Measuring the studies: precision contexts, compiled calls timed round-robin, flat states and norms.

Shared by the accuracy studies (``stablebptt.apps.accuracy``) and the task set-ups they measure.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable, NamedTuple

if TYPE_CHECKING:
    import numpy as np


PRECISIONS = (32, 64)


def precision(bits: int):
    """Context in which arrays, models and traces are float32 (32) or float64 (64)."""
    import jax
    return jax.enable_x64(bits == 64)


def cast(tree: Any, bits: int) -> Any:
    """A NumPy/JAX pytree as JAX arrays of the given float width; call inside ``precision(bits)``."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    dtype = jnp.float64 if bits == 64 else jnp.float32
    return jax.tree.map(lambda a: jnp.asarray(np.asarray(a), dtype), tree)


def to_numpy(tree: Any) -> Any:
    import jax
    import numpy as np
    return jax.tree.map(lambda a: np.asarray(a, np.float64), tree)


def flat_states(tree: Any) -> "np.ndarray":
    """A batch of states (any pytree, leading axis = batch) as float64 rows [batch, numbers]."""
    import jax
    import numpy as np
    leaves = [np.asarray(leaf, np.float64) for leaf in jax.tree.leaves(tree)]
    return np.concatenate([leaf.reshape(len(leaf), -1) for leaf in leaves], axis=1)


class Call(NamedTuple):
    """A compiled executable, its arguments and the precision it runs in."""

    function: Callable
    arguments: tuple
    bits: int


_traced_in = {"bits": None}


def compile_call(function: Callable, arguments: tuple, bits: int) -> tuple[Call, float]:
    """Compile ``function`` (jitted) for ``arguments`` ahead of time; returns the call and the compile seconds.

    JAX's trace caches do not tell float32 from float64 everywhere: an inner
    jitted helper traced in one precision (``jnp.tril`` inside MJX's RK4) is
    reused in the other and fails to lower. The caches are therefore cleared
    whenever the precision changes; compiled executables do not depend on them.
    """
    import jax
    if _traced_in["bits"] not in (None, bits):
        jax.clear_caches()
    _traced_in["bits"] = bits
    from stablebptt import timing
    with precision(bits):
        compiled, seconds = timing.compile_ahead(function, *arguments)
        return Call(compiled, arguments, bits), seconds


def run_once(call: Call) -> tuple[Any, float]:
    """Run a compiled call; returns the result and the seconds it took."""
    from stablebptt import timing
    with precision(call.bits):
        return timing.timed(lambda: call.function(*call.arguments))


def time_round_robin(calls: dict, rounds: int) -> dict:
    """Median seconds per call of already compiled ``calls``, one call of each per round."""
    from stablebptt import timing
    return timing.round_robin({key: (lambda call=call: run_once(call)[0]) for key, call in calls.items()}, rounds, warmup=0)


def policy_params(task, seed: int) -> Any:
    """Float32 Glorot parameters, output layer included (a zero output layer would make R equal M)."""
    import jax
    with precision(32):
        return to_numpy(task.init_params(jax.random.PRNGKey(seed), False))


def rollout_program(step: Callable, steps: int) -> Callable:
    """Jitted ``(initial states [B], controls [B]) -> final states [B]`` holding each control for ``steps`` steps."""
    import jax
    batch_step = jax.vmap(step)

    def rollout(initial_states, controls):
        return jax.lax.scan(lambda state, _: (batch_step(state, controls), None), initial_states, None, length=steps)[0]

    return jax.jit(rollout)


def tree_norm(tree) -> float:
    import jax
    import numpy as np
    return float(np.sqrt(sum(np.sum(np.asarray(leaf, np.float64) ** 2) for leaf in jax.tree.leaves(tree))))
