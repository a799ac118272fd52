"""Forces applied at bodies' points, mapped to joint space, with a derivative that sums over subtrees.

MJX maps a force and a torque on each body (``xfrc_applied``, every step's; fluid forces; gravity
compensation) to joint space body by body: for each body, a tree scan finds the joints above it and a
(nv, 3) Jacobian is built, all of them summed. Reverse mode then carries a cotangent of every joint's
motion axis (``cdof``) per body and adds them up, in every physics step, whether or not any force is
applied (``xfrc_applied`` is zero in most scenes, and its derivative is still taken).

The same map is one sum over subtrees: a body's force f at point p and its torque t make the wrench
(t + (p - c) x f, f) about its tree's centre of mass c, in which ``cdof`` is expressed; joint j's
generalised force is ``cdof_j`` dotted with the wrenches summed over the subtree of j's body.
``_subtree_summed`` computes that; ``REMEDIES`` give MJX's functions its derivative while their values
stay MJX's own, bit for bit (``jax.custom_jvp``: the forward pass computes MJX's map alone). What it
saves: docs/performance.md, "Applied forces differentiated through subtree sums".
"""
from __future__ import annotations

import functools
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero

from stablebptt.physics.mjx_internals import mjx, passive, support
from stablebptt.physics.scene_terms import subtree_mask


@functools.lru_cache(maxsize=64)
def _tree_maps(parents: tuple[int, ...], roots: tuple[int, ...],
               dof_bodies: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Two 0/1 matrices: ``root[a, b] = 1`` where ``b`` is the root of ``a``'s tree, and ``summed[j, b] = 1``
    where body ``b`` lies in the subtree of dof ``j``'s body."""
    root = np.eye(len(parents), dtype=np.float32)[list(roots)]
    return root, subtree_mask(np.asarray(parents))[list(dof_bodies)].astype(np.float32)


def _maps(model: mjx.Model) -> tuple[np.ndarray, np.ndarray]:
    return _tree_maps(*(tuple(int(i) for i in np.asarray(indices)) for indices in
                        (model.body_parentid, model.body_rootid, model.dof_bodyid)))


def _times(matrix: np.ndarray, array: jax.Array) -> jax.Array:
    """A constant 0/1 matrix times ``array``: a product, not a gather, whose transpose is a scatter-add, a
    loop on a CPU. HIGHEST: a GPU's default float32 matmul may round its inputs to TF32's 10 bits."""
    return jnp.matmul(jnp.asarray(matrix, array.dtype), array, precision=jax.lax.Precision.HIGHEST)


def _at_roots(model: mjx.Model, array: jax.Array) -> jax.Array:
    """Each body's row of ``array`` (nbody, ...) replaced by its tree's root's."""
    return _times(_maps(model)[0], array)


def _subtree_summed(model: mjx.Model, data: mjx.Data, force: jax.Array, torque: jax.Array,
                    point: jax.Array) -> jax.Array:
    """The generalised force of ``force`` and ``torque`` (nbody, 3) applied at ``point`` (nbody, 3) on
    each body: the same map as MJX's ``support.apply_ft`` summed over the bodies."""
    offset = point - _at_roots(model, data.subtree_com)
    wrench = jnp.concatenate([torque + jnp.cross(offset, force), force], axis=-1)  # cdof's order: angular, linear
    return jnp.sum(data.cdof * _times(_maps(model)[1], wrench), axis=-1)


def _read(function: Callable, arrays: list) -> list[int]:
    """The indices of the ``arrays`` that ``function(arrays)``'s traced program reads."""
    program = jax.make_jaxpr(function)(arrays).jaxpr
    used = {id(var) for equation in program.eqns for var in equation.invars} | {id(var) for var in program.outvars}
    return [index for index, var in enumerate(program.invars) if id(var) in used]


def _values_kept(original: Callable, forces: Callable) -> Callable:
    """``original(model, data)``, MJX's function, whose derivative is that of ``_subtree_summed`` of
    ``forces(model, data)`` (a force, a torque and a point per body): the same function of both."""
    def remedied(model: mjx.Model, data: mjx.Data) -> jax.Array:
        # The JAX arrays both functions read are the custom derivative's arguments: inside a jitted step the
        # model's are traced, and a custom derivative may not close over what is traced. Only those read: an
        # argument is kept alive, so a step recomputed in the backward pass would store every field of the
        # data per physics step. The rest are zeros no one reads; NumPy arrays (MJX's indices) stay as they are.
        leaves, structure = jax.tree.flatten((model, data))
        arrays = [index for index, leaf in enumerate(leaves) if isinstance(leaf, jax.Array)]

        def rebuilt(given: dict):
            return jax.tree.unflatten(structure, [given[index] if index in given else
                                                  jnp.zeros(leaf.shape, leaf.dtype) if index in arrays else leaf
                                                  for index, leaf in enumerate(leaves)])

        def both(every: list):
            model, data = rebuilt(dict(zip(arrays, every)))
            return original(model, data), _subtree_summed(model, data, *forces(model, data))

        read = [arrays[index] for index in _read(both, [leaves[index] for index in arrays])]

        @jax.custom_jvp
        def mapped(given: list):
            return original(*rebuilt(dict(zip(read, given))))

        def derivative(primals, tangents):
            (given,), (moving,) = primals, tangents
            # Only the arrays that move: zeros for the model's would be traced, then dropped.
            which = [index for index, tangent in enumerate(moving) if not isinstance(tangent, SymbolicZero)]

            def summed(moved):
                current = dict(zip(read, given))
                current.update(zip([read[index] for index in which], moved))
                model, data = rebuilt(current)
                return _subtree_summed(model, data, *forces(model, data))

            value = mapped(given)
            if not which:
                return value, jnp.zeros_like(value)
            return value, jax.jvp(summed, ([given[index] for index in which],), ([moving[index] for index in which],))[1]

        mapped.defjvp(derivative, symbolic_zeros=True)
        return mapped([leaves[index] for index in read])

    return remedied


def _applied(model: mjx.Model, data: mjx.Data) -> tuple:
    return data.xfrc_applied[:, :3], data.xfrc_applied[:, 3:], data.xipos


def _fluid(model: mjx.Model, data: mjx.Data) -> tuple:
    force, torque = jax.vmap(passive._inertia_box_fluid_model, in_axes=(None, 0, 0, 0, 0, 0, 0))(
        model, model.body_inertia, model.body_mass, _at_roots(model, data.subtree_com), data.xipos,
        data.ximat, data.cvel)
    return force, torque, data.xipos


def _gravity_compensation(model: mjx.Model, data: mjx.Data) -> tuple:
    force = -model.opt.gravity * (model.body_mass * model.body_gravcomp)[:, None]
    return force, jnp.zeros_like(force), data.xipos


# (owner, attribute, replacement) for constraint_derivatives' remedies: built once MJX is imported.
REMEDIES = (
    (support, "xfrc_accumulate", _values_kept(support.xfrc_accumulate, _applied)),
    (passive, "_fluid", _values_kept(passive._fluid, _fluid)),
    (passive, "_gravcomp", _values_kept(passive._gravcomp, _gravity_compensation)),
)
