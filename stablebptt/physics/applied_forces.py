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

from typing import Callable

import jax
import jax.numpy as jnp

from stablebptt.physics.mjx_internals import mjx, passive, support
from stablebptt.physics.tree_maps import root, structure
from stablebptt.physics.tree_sums import dof_forces
from stablebptt.physics.values_kept import times, values_kept


def _at_roots(model: mjx.Model, array: jax.Array) -> jax.Array:
    """Each body's row of ``array`` (nbody, ...) replaced by its tree's root's."""
    return times(root(structure(model)), array)


def _subtree_summed(model: mjx.Model, data: mjx.Data, force: jax.Array, torque: jax.Array,
                    point: jax.Array) -> jax.Array:
    """The generalised force of ``force`` and ``torque`` (nbody, 3) applied at ``point`` (nbody, 3) on
    each body: the same map as MJX's ``support.apply_ft`` summed over the bodies."""
    offset = point - _at_roots(model, data.subtree_com)
    wrench = jnp.concatenate([torque + jnp.cross(offset, force), force], axis=-1)  # cdof's order: angular, linear
    return dof_forces(model, data, wrench)


def _values_kept(original: Callable, forces: Callable) -> Callable:
    """``original(model, data)``, MJX's function, whose derivative is that of ``_subtree_summed`` of
    ``forces(model, data)`` (a force, a torque and a point per body): the same function of both."""
    def summed(model: mjx.Model, data: mjx.Data) -> jax.Array:
        return _subtree_summed(model, data, *forces(model, data))

    return values_kept(original, lambda model, data, value, moving, vary: vary(summed), reads=summed)


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
