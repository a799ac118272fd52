"""MJX's functions with their values kept to the bit and a derivative of this package's (``values_kept``),
and the constant 0/1 products through which those derivatives sum over a kinematic tree (``times``)."""
from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.ad_checkpoint import checkpoint_name
from jax.custom_derivatives import SymbolicZero

from stablebptt.physics.mjx_internals import mjx

# The values of MJX's functions that carry this package's derivative, by name: their tangents read the values
# and the functions' inputs, never MJX's intermediates, so a physics step recomputed in the backward pass
# keeps these (a few rows per body) rather than running the functions again (constraint_derivatives). A
# tangent that itself runs a function of the inputs (``vary``: the fluid's forces, or the body frames where
# a model number moves) runs that one again.
KEPT_VALUES = "stablebptt_values_kept"

# tangent(model, data, value, moving, vary) -> the value's tangent; ``moving`` names the arrays that move by
# their paths in (model, data), "[0].body_pos" or "[1].qpos"; ``vary(function)`` is the tangent of
# ``function(model, data)`` as they move.
Tangent = Callable[[mjx.Model, mjx.Data, Any, frozenset, Callable[[Callable], Any]], Any]


def _matmul(constant: jax.Array, array: jax.Array) -> jax.Array:
    return jnp.tensordot(constant, array, axes=1, precision=jax.lax.Precision.HIGHEST)


def _summed(constant: jax.Array, array: jax.Array) -> jax.Array:
    return jnp.sum(constant.reshape(constant.shape + (1,) * (array.ndim - 1)) * array[None], axis=1)


# The product's form by the platform the program is compiled for (docs/performance.md, "The position stage
# differentiated without the tree's scans"): on a CPU a matmul; on a GPU, where a float32 matmul rounds to TF32
# or at HIGHEST takes several passes, a broadcast product and a sum (exact float32 products, one fused
# reduction). By the program's platform, not JAX's default backend: beside an accelerator the reward check's
# programs compile for the host's CPU, where the broadcast form took three times the matmul's time.
PRODUCTS = {"cpu": _matmul, "default": _summed}


def times(matrix: np.ndarray, array: jax.Array) -> jax.Array:
    """A constant 0/1 matrix times ``array``: a product, not a gather, whose transpose is a scatter-add, a
    loop on a CPU. Only the form of the platform the program is lowered for is compiled."""
    return jax.lax.platform_dependent(jnp.asarray(matrix, array.dtype), array, **PRODUCTS)


def _traced(function: Callable, arrays: list) -> tuple[list[int], list[set[int]]]:
    """The indices of the ``arrays`` that ``function(arrays)``'s traced program reads, and those each of its
    output arrays depends on (an equation's outputs on all its inputs, as JAX batches it)."""
    program = jax.make_jaxpr(function)(arrays).jaxpr
    depends = {id(var): {index} for index, var in enumerate(program.invars)}
    for equation in program.eqns:
        inputs = set().union(*(depends.get(id(var), set()) for var in equation.invars))
        depends.update((id(var), inputs) for var in equation.outvars)
    used = {id(var) for equation in program.eqns for var in equation.invars} | {id(var) for var in program.outvars}
    return ([index for index, var in enumerate(program.invars) if id(var) in used],
            [depends.get(id(var), set()) for var in program.outvars])


def values_kept(original: Callable, tangent: Tangent, reads: Callable) -> Callable:
    """``original(model, data)``, MJX's function, with the derivative ``tangent`` gives (``Tangent``), which
    reads no more of the model and data than ``original`` and ``reads(model, data)`` do."""
    def remedied(model: mjx.Model, data: mjx.Data):
        # The JAX arrays these functions read are the custom derivative's arguments: inside a jitted step the
        # model's are traced, and a custom derivative may not close over what is traced. Only those read: an
        # argument is kept alive, so a step recomputed in the backward pass would store every field of the
        # data per physics step. The rest are zeros no one reads; NumPy arrays (MJX's indices) stay as they are.
        pathed, structure = jax.tree_util.tree_flatten_with_path((model, data))
        leaves = [leaf for _, leaf in pathed]
        arrays = [index for index, leaf in enumerate(leaves) if isinstance(leaf, jax.Array)]

        def rebuilt(given: dict):
            return jax.tree.unflatten(structure, [given[index] if index in given else
                                                  jnp.zeros(leaf.shape, leaf.dtype) if index in arrays else leaf
                                                  for index, leaf in enumerate(leaves)])

        def both(every: list):
            model, data = rebuilt(dict(zip(arrays, every)))
            return original(model, data), reads(model, data)

        positions, depends = _traced(both, [leaves[index] for index in arrays])  # the value's outputs first
        read = [arrays[index] for index in positions]

        @jax.custom_jvp
        def mapped(given: list):
            return original(*rebuilt(dict(zip(read, given))))

        def derivative(primals, tangents):
            (given,), (moving,) = primals, tangents
            # Only the arrays that move: zeros for the model's would be traced, then dropped.
            which = [index for index, tangent in enumerate(moving) if not isinstance(tangent, SymbolicZero)]
            current = dict(zip(read, given))
            value = jax.tree.map(lambda leaf: checkpoint_name(leaf, KEPT_VALUES), original(*rebuilt(current)))
            if not which:
                return value, jax.tree.map(jnp.zeros_like, value)

            def vary(function: Callable):
                def moved(arrays: list):
                    return function(*rebuilt({**current, **dict(zip([read[index] for index in which], arrays))}))
                return jax.jvp(moved, ([given[index] for index in which],), ([moving[index] for index in which],))[1]

            paths = frozenset(jax.tree_util.keystr(pathed[read[index]][0]) for index in which)
            values, output_structure = jax.tree.flatten(value)
            found = jax.tree.leaves(tangent(*rebuilt(current), value, paths, vary))
            # An output MJX's program computes without any moving array keeps a zero tangent, as MJX's own
            # derivative does: a tangent found from arrays JAX batches, beside a value it does not, breaks a
            # step batched (vmap of a jitted step) and then differentiated.
            moved = {positions[index] for index in which}
            return value, jax.tree.unflatten(output_structure, [
                tangent_leaf if depends[number] & moved else jnp.zeros_like(value_leaf)
                for number, (value_leaf, tangent_leaf) in enumerate(zip(values, found))])

        mapped.defjvp(derivative, symbolic_zeros=True)
        return mapped([leaves[index] for index in read])

    return remedied
